"""The ``Project``: one object owns one incident folder (its settings, sub-folders, every load and save).

Layout (``docs/formats.md``)::

    projects/<incident>/
        project.toml            settings (validated, see core/settings.py)
        camera_profile.json     optional camera profile (calibrated intrinsics)
        photos/<set>/           input photos (JPEG/PNG); the set used is settings.camera.photos
        rolling_stock/          optional extra carriage types (one TOML each)
        correspondences.json    optional manual marked-point picks
        truth/                  ground truth (synthetic incidents only)
        out/                    every output of the stages; out/state.json records their runs

Nothing else builds paths into the folder. Every write is atomic (temp file, then rename).
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from .core.frames import SceneFrame
from .core.io import atomic_write, atomic_write_json, atomic_write_text
from .core.settings import SETTINGS_FILE, TEMPLATE, ProjectSettings, load_settings
from .errors import InputError, SettingsError, UnknownModelType

log = logging.getLogger(__name__)

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")


class Project:
    """An incident folder. ``Project(path)`` opens it; settings are read (and validated) on first use."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root).resolve()
        if not self.root.is_dir():
            raise InputError(f"{root}: no such incident folder; create one with `workbench init {root}`")

    # -- creation -------------------------------------------------------------------------------------
    @classmethod
    def create(cls, root: str | Path, *, name: str | None = None, lat: float = 0.0, lon: float = 0.0,
               crs: str = "EPSG:32618", date: _dt.date | None = None) -> "Project":
        """Create an incident folder with a documented ``project.toml``; refuses to overwrite one."""
        root = Path(root)
        settings = root / SETTINGS_FILE
        if settings.exists():
            raise SettingsError(f"{settings}: already exists; `workbench init` never overwrites an incident")
        root.mkdir(parents=True, exist_ok=True)
        text = TEMPLATE.format(name=(name or root.name).replace('"', "'"), date=(date or _dt.date.today()).isoformat(),
                               lat=repr(float(lat)), lon=repr(float(lon)), crs=crs)
        atomic_write_text(settings, text)
        for sub in ("photos/panorama", "out"):
            (root / sub).mkdir(parents=True, exist_ok=True)
        project = cls(root)
        project.settings  # validate what we wrote
        return project

    # -- paths ----------------------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.root.name

    @property
    def settings_path(self) -> Path:
        return self.root / SETTINGS_FILE

    @property
    def out_dir(self) -> Path:
        return self.root / "out"

    @property
    def state_path(self) -> Path:
        return self.out_dir / "state.json"

    @property
    def truth_dir(self) -> Path:
        return self.root / "truth"

    @property
    def rolling_stock_dir(self) -> Path:
        return self.root / "rolling_stock"

    def stage_dir(self, stage: str) -> Path:
        return self.out_dir / stage

    def path(self, relative: str | Path) -> Path:
        """A path given in the settings (relative to the incident folder, or absolute)."""
        p = Path(relative)
        return p if p.is_absolute() else (self.root / p)

    def relative(self, path: Path) -> str:
        """``path`` relative to the incident folder, POSIX style (for files written into JSON)."""
        try:
            return Path(path).resolve().relative_to(self.root).as_posix()
        except ValueError:
            return Path(path).resolve().as_posix()

    def require_file(self, relative: str | Path, key: str) -> Path:
        p = self.path(relative)
        if not p.is_file():
            raise InputError(f"{self.settings_path}: {key} = {str(relative)!r} -> {p} does not exist; fix the path "
                             f"or put the file there")
        return p

    # -- settings -------------------------------------------------------------------------------------
    @cached_property
    def settings(self) -> ProjectSettings:
        return load_settings(self.settings_path)

    def reload(self) -> None:
        self.__dict__.pop("settings", None)
        self.__dict__.pop("frame", None)

    @cached_property
    def frame(self) -> SceneFrame:
        loc = self.settings.location
        return SceneFrame(loc.crs, loc.lat, loc.lon, loc.height_m)

    def settings_section(self, *sections: str) -> dict:
        dump = self.settings.model_dump(mode="json")
        return {s: dump.get(s) for s in sections}

    # -- inputs ---------------------------------------------------------------------------------------
    def carriage_types(self) -> dict[str, Any]:
        """``{car number: CarriageType}`` for the consist, with the incident's own types in ``rolling_stock/``."""
        from .rolling_stock import get_type

        extra = [self.rolling_stock_dir] if self.rolling_stock_dir.is_dir() else []
        out = {}
        for i, car in enumerate(self.settings.consist):
            try:
                out[car.number] = get_type(car.type, extra_dirs=extra)
            except UnknownModelType as exc:
                raise UnknownModelType(f"{self.settings_path}: consist[{i}].type = {car.type!r}: {exc}") from None
        return out

    def photo_paths(self, folder: str | None = None) -> list[Path]:
        rel = folder or self.settings.camera.photos
        d = self.path(rel)
        if not d.is_dir():
            raise InputError(f"{self.settings_path}: camera.photos = {rel!r} -> {d} is not a folder; put the photos "
                             f"there or fix the key")
        photos = sorted(p for p in d.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES and not p.name.startswith("."))
        if not photos:
            raise InputError(f"{d}: no photos (JPEG, PNG or TIFF) in this folder")
        return photos

    # -- reading and writing --------------------------------------------------------------------------
    def read_json(self, path: Path) -> Any:
        from .core.io import read_json

        return read_json(path)

    def write_json(self, path: Path, data: Any) -> Path:
        return atomic_write_json(Path(path), data)

    def write_text(self, path: Path, text: str) -> Path:
        return atomic_write_text(Path(path), text)

    def write_image(self, path: Path, rgb: np.ndarray) -> Path:
        """Write an (h, w, 3) uint8 RGB or (h, w) image (PNG/JPEG by suffix), atomically."""
        from PIL import Image

        img = Image.fromarray(np.ascontiguousarray(rgb))
        return atomic_write(Path(path), lambda p: img.save(p))

    def write_with(self, path: Path, writer) -> Path:
        """Atomic write through ``writer(tmp_path)`` (for meshes, GeoTIFFs, ...)."""
        return atomic_write(Path(path), writer)

    # -- stage state ----------------------------------------------------------------------------------
    def read_state(self) -> dict:
        if not self.state_path.is_file():
            return {}
        try:
            return json.loads(self.state_path.read_text(encoding="utf-8"))
        except json.JSONDecodeError:
            log.warning("%s is corrupt; all stages will run again", self.state_path)
            return {}

    def write_state(self, state: dict) -> None:
        atomic_write_json(self.state_path, state)
