"""``out/sfm/reconstruction.json``: the sfm stage's cameras in the SfM model frames (format in
``docs/intrinsics.md``), the one reader.

The main model's images are ``images``; separate smaller models (each in its own frame) are ``models``, largest
first; photos left out are ``unregistered``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.io import matrix_from_json, read_json
from ..errors import InputError, StageError
from .cameras import intrinsics_checked, intrinsics_factor_checked, rotation_checked

__all__ = ["SfmView", "Reconstruction", "read_reconstruction"]


@dataclass(frozen=True)
class SfmView:
    """A photo of an SfM model: its name, intrinsics and ``cam_from_model`` (4, 4), model units; ``pose_factor``
    (6, r): its rows of the model's pose covariance factor (the sfm stage's bundle adjustment, gauge: the centres'
    similarity taken out; ``C_v = F F^T``, the model's views sharing one ``z ~ N(0, I_r)``; docs/formats.md), or
    None when the file states none; ``intrinsics_factor`` (k, r): its camera's refined intrinsics (named by
    ``intrinsics_params``, fields of :class:`CameraIntrinsics`, ``f`` moving ``fx`` and ``fy`` together) in the
    same factor, or None."""

    name: str
    intrinsics: CameraIntrinsics
    cam_from_model: np.ndarray
    pose_factor: np.ndarray | None = field(default=None, compare=False)
    intrinsics_factor: np.ndarray | None = field(default=None, compare=False)
    intrinsics_params: tuple[str, ...] = field(default=(), compare=False)


def _intrinsics_factor(s: dict, r: int, w: str) -> tuple[np.ndarray | None, tuple[str, ...]]:
    """A view's ``intrinsics_factor`` ({"params": [...], "factor": k x r}) checked; (None, ()) when absent."""
    if s.get("intrinsics_factor") is None:
        return None, ()
    try:
        params, F = intrinsics_factor_checked(s["intrinsics_factor"], r, f"{w}.intrinsics_factor")
    except InputError as exc:
        raise StageError(f"{exc}; run the sfm stage again") from None
    return F, params


@dataclass(frozen=True)
class Reconstruction:
    """A read ``reconstruction.json``: every model as ``(label, views)`` — ``("main", ...)`` first, then
    ``("models[0]", ...)`` and so on in the file's order — and the whole document."""

    path: Path
    models: tuple[tuple[str, tuple[SfmView, ...]], ...]
    doc: dict = field(compare=False, repr=False)

    @property
    def main(self) -> tuple[SfmView, ...]:
        return self.models[0][1]

    def image_of(self, name: str) -> str | None:
        """The image path the file gives for photo ``name`` (any of its models), or None."""
        for images in [self.doc.get("images", [])] + [m.get("images", []) for m in self.doc.get("models", [])]:
            for s in images:
                if s.get("name") == name:
                    return s.get("image")
        return None


def _views(images: Any, where: str) -> tuple[SfmView, ...]:
    if not isinstance(images, list) or not images:
        raise StageError(f"{where}: no 'images' list; run the sfm stage again")
    views = []
    for i, s in enumerate(images):
        w = f"{where}[{i}]"
        if not isinstance(s, dict) or not isinstance(s.get("name"), str):
            raise StageError(f"{w}: needs 'name'")
        intr = intrinsics_checked(s.get("intrinsics"), f"{w}.intrinsics")
        M = matrix_from_json(s.get("cam_from_model"), (4, 4), f"{w}.cam_from_model")
        rotation_checked(M[:3, :3], f"{w}.cam_from_model")
        F = None
        if s.get("pose_factor") is not None:
            F = np.asarray(s["pose_factor"], dtype=float) if isinstance(s["pose_factor"], list) else None
            if F is None or F.ndim != 2 or F.shape[0] != 6 or F.shape[1] < 1 or not np.all(np.isfinite(F)):
                raise StageError(f"{w}.pose_factor: must be a 6 x r list of finite numbers (r >= 1), got "
                                 f"{None if F is None else F.shape}; run the sfm stage again")
        K, names = (None, ()) if F is None else _intrinsics_factor(s, F.shape[1], w)
        views.append(SfmView(s["name"], intr, M, F, K, names))
    ranks = {v.pose_factor.shape[1] for v in views if v.pose_factor is not None}
    if len(ranks) > 1 or (ranks and any(v.pose_factor is None for v in views)):
        raise StageError(f"{where}: every image of a model needs a pose_factor of the same rank (found ranks "
                         f"{sorted(ranks)}, {sum(v.pose_factor is None for v in views)} images without); run the "
                         f"sfm stage again")
    return tuple(views)


def parse_reconstruction(doc: Any, path: Path | str) -> Reconstruction:
    """Check a parsed ``reconstruction.json``; :class:`StageError` naming the file and the entry. A file written
    before separate models were kept has the main model only."""
    if not isinstance(doc, dict):
        raise StageError(f"{path}: not a reconstruction; run the sfm stage again")
    models = [("main", _views(doc.get("images"), f"{path}: images"))]
    extra = doc.get("models", [])
    if not isinstance(extra, list):
        raise StageError(f"{path}: 'models' must be a list; run the sfm stage again")
    for k, m in enumerate(extra):
        if not isinstance(m, dict):
            raise StageError(f"{path}: models[{k}] must be an object; run the sfm stage again")
        models.append((f"models[{k}]", _views(m.get("images"), f"{path}: models[{k}].images")))
    return Reconstruction(Path(path), tuple(models), doc)


def read_reconstruction(path: Path) -> Reconstruction:
    """Read and check the ``reconstruction.json`` at ``path``."""
    return parse_reconstruction(read_json(Path(path)), path)
