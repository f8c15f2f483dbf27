"""``out/stitch/panorama.json``: the stitch stage's panorama model (format in ``docs/stitching.md``), the one
reader and writer.

The file is :meth:`workbench.core.panorama.PanoramaModel.to_dict` plus the run's metadata. Georef reads its
sources as a central rig (:class:`RigView`); the solve and the report read the projection model.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.io import atomic_write_json, matrix_from_json, read_json
from ..core.panorama import PanoramaModel
from ..errors import InputError, StageError
from .cameras import intrinsics_checked, rotation_checked

__all__ = ["RigView", "PanoramaFile", "read_panorama", "write_panorama"]


@dataclass(frozen=True)
class RigView:
    """A photo of a central rig: its name, intrinsics and ``cam_from_rig`` rotation (3, 3)."""

    name: str
    intrinsics: CameraIntrinsics
    cam_from_rig: np.ndarray = field(default_factory=lambda: np.eye(3))


@dataclass(frozen=True)
class PanoramaFile:
    """A read ``panorama.json``: its sources as rig views (file order) and the whole document."""

    path: Path
    sources: tuple[RigView, ...]
    doc: dict = field(compare=False, repr=False)

    def model(self) -> PanoramaModel:
        """The projection model; :class:`InputError` naming the file when it is not one."""
        try:
            return PanoramaModel.from_dict(self.doc)
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            raise InputError(f"{self.path}: cannot be read as a panorama model ({exc}); run the stitch stage "
                             f"again") from None

    @property
    def images(self) -> dict[str, str]:
        """Photo name -> the photo's path as the stitch stage recorded it ('' when it did not)."""
        return {s["name"]: s.get("image", "") for s in self.doc["sources"]}


def parse_panorama(doc: Any, path: Path | str) -> PanoramaFile:
    """Check a parsed ``panorama.json``'s sources; :class:`StageError` naming the file and the entry."""
    if not isinstance(doc, dict) or not isinstance(doc.get("sources"), list) or not doc["sources"]:
        raise StageError(f"{path}: no 'sources' list; run the stitch stage again")
    views = []
    for i, s in enumerate(doc["sources"]):
        where = f"{path}: sources[{i}]"
        if not isinstance(s, dict) or not isinstance(s.get("name"), str):
            raise StageError(f"{where}: needs 'name'")
        intr = intrinsics_checked(s.get("intrinsics"), f"{where}.intrinsics")
        R = rotation_checked(matrix_from_json(s.get("cam_from_pano"), (3, 3), f"{where}.cam_from_pano"),
                             f"{where}.cam_from_pano")
        views.append(RigView(s["name"], intr, R))
    return PanoramaFile(Path(path), tuple(views), doc)


def read_panorama(path: Path) -> PanoramaFile:
    """Read and check the ``panorama.json`` at ``path``."""
    return parse_panorama(read_json(Path(path)), path)


def write_panorama(path: Path, doc: dict) -> Path:
    """Check ``doc`` (sources and model) and write it atomically."""
    parse_panorama(doc, path).model()
    return atomic_write_json(Path(path), doc)
