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
import fcntl
import json
import logging
import os
import tomllib
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .core.io import atomic_write, atomic_write_json, atomic_write_text, read_json, resolve_dem_sources
from .core.layout import CAMERAS_FILE, CONTROL_POINTS_FILE, CORRESPONDENCES_FILE, SETTINGS_FILE
from .errors import InputError, SettingsError, StageError, UnknownModelType

if TYPE_CHECKING:  # numpy and the frame are loaded on use: `workbench status` needs neither
    import numpy as np

    # (the settings' models, pydantic and pyproj, on the first read of the settings: a folder's paths, photos and
    # records need none of them, and `workbench stitch` starts describing its photos before they are loaded)
    from .core.settings import ProjectSettings

    from .core.frames import SceneFrame
    from .files.cameras import Cameras
    from .files.dem import TerrainModel
    from .files.profile import CameraProfile
    from .files.railways import RailwayLayer
    from .files.solution import Solution

log = logging.getLogger(__name__)

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")



class Project:
    """An incident folder. ``Project(path)`` opens it; settings are read (and validated) on first use."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root).resolve()
        if not self.root.is_dir():
            raise InputError(f"{root}: no such incident folder; create one with `workbench init {root}`")
        # the folder's fixed places (the layout above); a stage's output folder is stage_dir(stage)
        self.name = self.root.name
        self.settings_path = self.root / SETTINGS_FILE
        self.out_dir = self.root / "out"
        self.state_path = self.out_dir / "state.json"
        self.truth_dir = self.root / "truth"
        self.rolling_stock_dir = self.root / "rolling_stock"

    # -- creation -------------------------------------------------------------------------------------
    @classmethod
    def create(cls, root: str | Path, *, name: str | None = None, lat: float = 0.0, lon: float = 0.0,
               crs: str = "EPSG:32618", date: _dt.date | None = None) -> "Project":
        """Create an incident folder with a documented ``project.toml``; refuses to overwrite one."""
        from .core.settings import TEMPLATE, parse_settings

        root = Path(root)
        settings = root / SETTINGS_FILE
        if settings.exists():
            raise SettingsError(f"{settings}: already exists; `workbench init` never overwrites an incident")
        text = TEMPLATE.format(name=(name or root.name).replace('"', "'"), date=(date or _dt.date.today()).isoformat(),
                               lat=repr(float(lat)), lon=repr(float(lon)), crs=crs.replace('"', "'"))
        try:  # validated before anything is written: a bad --crs or --lat leaves nothing behind
            parse_settings(tomllib.loads(text), str(settings))
        except tomllib.TOMLDecodeError as exc:
            raise SettingsError(f"{settings}: the values given do not make a valid settings file ({exc})") from None
        root.mkdir(parents=True, exist_ok=True)
        atomic_write_text(settings, text)
        for sub in ("photos/panorama", "out"):
            (root / sub).mkdir(parents=True, exist_ok=True)
        project = cls(root)
        project.settings  # validate what we wrote
        return project

    # -- paths ----------------------------------------------------------------------------------------
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

    # -- the incident's files: where each one is (docs/formats.md) ------------------------------------
    @property
    def own_cameras_path(self) -> Path:
        """The incident's hand-written ``cameras.json`` (known cameras; it takes georef's output's place)."""
        return self.root / CAMERAS_FILE

    def cameras_path(self) -> Path | None:
        """The views every stage after georef reads: the incident's own ``cameras.json``, else georef's, else
        None."""
        if self.own_cameras_path.is_file():
            return self.own_cameras_path
        out = self.stage_dir("georef") / CAMERAS_FILE
        return out if out.is_file() else None

    def cameras(self) -> "Cameras | None":
        """The views every stage after georef reads (:meth:`cameras_path`), read and checked; None without."""
        from .files.cameras import read_cameras

        p = self.cameras_path()
        return read_cameras(p) if p is not None else None

    def camera_profile(self) -> "CameraProfile | None":
        """The camera profile that ``camera.profile`` names, read and checked; None when none is named."""
        from .files.profile import read_profile

        prof = self.settings.camera.profile
        return read_profile(self.require_file(prof, "camera.profile")) if prof else None

    def terrain_model(self, *, max_cells: int | None = None) -> "TerrainModel":
        """The incident's terrain model (``terrain.dem``: tiles mosaicked, cropped to ``terrain.aoi_radius_m``,
        holes filled), built as the terrain stage builds it; ``max_cells`` caps its nodes (for pictures)."""
        from .files.dem import TerrainModel

        t = self.settings.terrain
        if t.dem is None:
            raise InputError(f"{self.settings_path}: terrain.dem is not set")
        return TerrainModel.from_sources(self.dem_paths(), self.frame, aoi_radius_m=t.aoi_radius_m,
                                         vertical_accuracy_m=t.dem_vertical_accuracy_m,
                                         max_cells=max_cells if max_cells is not None else 400_000)

    def railways(self, *, heights: bool = True) -> "RailwayLayer | None":
        """The railway layer ``terrain.railways`` names, in the scene frame (docs/gis.md, "Railway lines"); None when
        it is unset, or (with a warning naming the file) when the file holds no railway line. ``heights``: drape the
        lines on the DEM when the incident has one (else the file's heights); the map, chainages and offsets do
        without."""
        from .files.railways import read_railways

        rel = self.settings.terrain.railways
        if not rel:
            return None
        path = self.require_file(rel, "terrain.railways")
        terrain = self.terrain_model(max_cells=160_000) if heights and self.settings.terrain.dem else None
        return read_railways(path, self.frame, terrain=terrain)

    @property
    def manual_picks_path(self) -> Path:
        """The user's marked-point picks and rejections (``correspondences.json`` in the incident folder)."""
        return self.root / CORRESPONDENCES_FILE

    def correspondences_path(self) -> Path | None:
        """The marked points the solve reads: the correspond stage's merge, else the user's own file, else None."""
        out = self.stage_dir("correspond") / CORRESPONDENCES_FILE
        if out.is_file():
            return out
        return self.manual_picks_path if self.manual_picks_path.is_file() else None

    @property
    def control_points_path(self) -> Path:
        return self.root / CONTROL_POINTS_FILE

    @property
    def panorama_model_path(self) -> Path:
        """The stitch stage's panorama model (its exact camera model), which georef places."""
        return self.stage_dir("stitch") / "panorama.json"

    @property
    def reconstruction_path(self) -> Path:
        """The sfm stage's reconstruction (every photo's camera), which georef places."""
        return self.stage_dir("sfm") / "reconstruction.json"

    @property
    def solution_path(self) -> Path:
        return self.stage_dir("solve") / "solution.json"

    def require_output(self, path: Path, stage: str, needed_by: str, otherwise: str = "") -> Path:
        """``path``, a file the ``stage`` stage writes; :class:`StageError` naming the stage to run when it is not
        there (``otherwise``: what the user may do instead, appended to the message)."""
        if not path.is_file():
            raise StageError(f"{path}: not found; the {needed_by} needs the {stage} stage's output: run "
                             f"`workbench run {self.root} --only {stage}` first{otherwise}")
        return path

    def require_solution(self, needed_by: str) -> Path:
        p = self.solution_path
        if not p.is_file():
            raise InputError(f"{p}: not found; the {needed_by} needs the 'solve' stage's output, and the 'solve' "
                             f"stage has not run for this incident. Run `workbench run {self.root}` first")
        return p

    def solution(self, needed_by: str = "scene") -> "Solution":
        """The solve stage's ``solution.json``, read and checked against this incident's frame and consist
        (:class:`InputError` naming the stage to run when it has not run, or the file when it is stale)."""
        from .files.solution import read_solution

        return read_solution(self.require_solution(needed_by), frame=self.frame,
                             numbers=[c.number for c in self.settings.consist])

    def dem_paths(self) -> list[Path]:
        """The DEM file(s) ``terrain.dem`` names (one file, a folder of tiles or a glob); [] when it is unset."""
        dem = self.settings.terrain.dem
        if not dem:
            return []
        try:
            return resolve_dem_sources(dem, self.root)
        except InputError as exc:
            raise InputError(f"{self.settings_path}: {exc}") from None

    def orthophoto_path(self) -> Path | None:
        """The orthophoto draped on the terrain, or None: ``terrain.ortho`` when set; else a synthetic incident's
        (``truth/ground_truth.json`` ``layers.ortho``); else a JPEG beside a single DEM file named like it with
        ``_ortho`` for ``_dem``. It covers the DEM's whole extent, row 0 at the north edge."""
        t = self.settings.terrain
        if t.ortho:
            return self.require_file(t.ortho, "terrain.ortho")
        truth = self.truth_dir / "ground_truth.json"
        if truth.is_file():
            try:
                rel = json.loads(truth.read_text(encoding="utf-8")).get("layers", {}).get("ortho")
            except (json.JSONDecodeError, UnicodeDecodeError, AttributeError):
                rel = None
            if rel and self.path(rel).is_file():
                return self.path(rel)
        if t.dem and self.path(t.dem).is_file():  # one DEM file (not a folder or pattern of tiles)
            d = self.path(t.dem)
            for cand in (d.with_name(d.stem.replace("_dem", "_ortho") + ".jpg"), d.with_suffix(".ortho.jpg")):
                if cand != d and cand.is_file():
                    return cand
        return None

    def georef_route(self) -> str:
        """How the cameras are placed: ``known`` (the incident's own ``cameras.json``), ``multiview`` (SfM),
        ``single`` (one photo) or ``panorama`` from control points, or ``relative`` (photos but no control
        points: a local frame anchored at the camera; docs/gis.md, "Relative incidents")."""
        if self.own_cameras_path.is_file():
            return "known"
        if self.settings.camera.source.value == "sfm":
            return "multiview"
        try:
            photos = self.photo_paths()
        except InputError:
            photos = []
        if photos and not self.control_points_path.is_file():
            return "relative"
        return "single" if len(photos) == 1 else "panorama"

    # -- settings -------------------------------------------------------------------------------------
    @cached_property
    def settings(self) -> ProjectSettings:
        from .core.settings import load_settings

        return load_settings(self.settings_path)

    def written_setting(self, section: str, key: str) -> Any:
        """``[section] key`` as written in ``project.toml``, not validated; None where the file, the table or the key
        is missing or the file is not TOML. Only for work started while the settings are being validated (the
        panorama's head start, :func:`workbench.stitch.stage.head_start`), which the stages take only if
        :attr:`settings` gives what it used."""
        try:
            table = tomllib.loads(self.settings_path.read_text(encoding="utf-8")).get(section)
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
            return None
        return table.get(key) if isinstance(table, dict) else None

    def reload(self) -> None:
        self.__dict__.pop("settings", None)
        self.__dict__.pop("frame", None)

    @cached_property
    def frame(self) -> SceneFrame:
        from .core.frames import SceneFrame

        loc = self.settings.location
        return SceneFrame(loc.crs, loc.lat, loc.lon, loc.height_m)

    def settings_section(self, *sections: str) -> dict:
        """The settings a stage reads, for its hash: whole sections (``"solver"``) or single keys
        (``"terrain.dem"``), so a stage is not re-run for a key it does not read."""
        dump = self.settings.model_dump(mode="json")
        out = {}
        for s in sections:
            section, _, key = s.partition(".")
            value = dump.get(section)
            out[s] = value.get(key) if key and isinstance(value, dict) else value
        return out

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

    @property
    def photos_optional(self) -> bool:
        """Whether the incident can do without photo files: its cameras are hand-written (``cameras.json``), so
        its marked points (``correspondences.json``) can be solved without the pixels."""
        return self.own_cameras_path.is_file()

    def photo_paths_if_any(self) -> list[Path]:
        """The photos; [] when there are none and the incident can do without them (:attr:`photos_optional`),
        else the :meth:`photo_paths` error."""
        try:
            return self.photo_paths()
        except InputError:
            if self.photos_optional:
                return []
            raise

    # -- reading and writing --------------------------------------------------------------------------
    def read_json(self, path: Path) -> Any:
        return read_json(path)

    def write_json(self, path: Path, data: Any) -> Path:
        return atomic_write_json(Path(path), data)

    def write_text(self, path: Path, text: str) -> Path:
        return atomic_write_text(Path(path), text)

    def write_image(self, path: Path, rgb: np.ndarray) -> Path:
        """Write an (h, w, 3) uint8 RGB or (h, w) image (PNG/JPEG by suffix), atomically."""
        import numpy as np
        from PIL import Image

        img = Image.fromarray(np.ascontiguousarray(rgb))
        return atomic_write(Path(path), lambda p: img.save(p))

    def write_with(self, path: Path, writer) -> Path:
        """Atomic write through ``writer(tmp_path)`` (for meshes, GeoTIFFs, ...)."""
        return atomic_write(Path(path), writer)

    # -- stage state ----------------------------------------------------------------------------------
    def read_state(self) -> dict:
        """The runner's record of every stage (``out/state.json``); {} when there is none or it is corrupt (then
        every stage counts as not run, and the next write keeps the corrupt file aside, see :meth:`write_state`)."""
        state = self._read_state_file()
        if state is None:
            log.warning("%s is corrupt (not a JSON object); every stage counts as not run, and the file is kept as "
                        "%s when a stage next runs", self.state_path, self.state_path.name + ".corrupt")
            return {}
        return state

    def recorded_status(self, stage: str) -> str | None:
        """The status that ``out/state.json`` records for ``stage`` (``"done"``, ``"failed"``), not checked against its
        inputs (:class:`workbench.runner.Runner` does that); None where there is none or the file is corrupt."""
        rec = (self._read_state_file() or {}).get(stage)
        return rec.get("status") if isinstance(rec, dict) else None

    def _read_state_file(self) -> dict | None:
        """The state file's object; {} when there is none; None when it is corrupt."""
        try:
            state = json.loads(self.state_path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return {}
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError):
            return None
        if not isinstance(state, dict) or not all(isinstance(v, dict) for v in state.values()):
            return None
        return state

    def write_state(self, state: dict) -> None:
        if self.state_path.is_file() and self._read_state_file() is None:  # keep a corrupt record for inspection
            os.replace(self.state_path, self.state_path.with_name(self.state_path.name + ".corrupt"))
        atomic_write_json(self.state_path, state)

    def lock(self) -> "IncidentLock":
        """An exclusive lock on the incident folder for a run (``with project.lock(): ...``); a second run on the
        same folder is refused with a message naming the process that holds it."""
        return IncidentLock(self.out_dir / ".lock")


class IncidentLock:
    """``flock`` on ``out/.lock``: released when the process ends, even by ``kill -9``, so it is never stale."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd: int | None = None

    def __enter__(self) -> "IncidentLock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = os.read(fd, 64).decode(errors="replace").strip() or "another process"
            finally:
                os.close(fd)
            raise StageError(f"{self.path.parent.parent}: another workbench command is running on this incident "
                             f"({holder}); wait for it to finish, then run this one again") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()}".encode())
        self._fd = fd
        return self

    def __exit__(self, *exc: object) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing releases the lock
            self._fd = None
