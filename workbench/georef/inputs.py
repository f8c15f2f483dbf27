"""What the georef stage reads: the stitch stage's panorama model, the SfM reconstruction, a hand-written
``cameras.json``, the incident's photos (by file name), their EXIF GPS and the control points picked in them."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.io import matrix_from_json
from ..core.layout import CAMERAS_FILE
from ..errors import InputError, StageError
from ..project import Project
from ..files.control_points import ControlPoint, load_control_points
from .gps import read_gps
from .options import RigView, SfmView

__all__ = ["PANORAMA_KEY", "read_intrinsics", "read_panorama_model", "read_reconstruction",
           "read_reconstruction_models", "validate_cameras_doc", "photos_by_name", "gps_enu",
           "require_control_points", "control_points_of_photos", "unknown_photo_error", "image_in_reconstruction"]

PANORAMA_KEY = "panorama"  # pixel key of a pick made in the stitched panorama image


def _rotation(R: np.ndarray, where: str) -> np.ndarray:
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
        raise InputError(f"{where}: not a rotation (orthonormal with determinant +1)")
    return R


def read_intrinsics(d: Any, where: str) -> CameraIntrinsics:
    """A camera_profile.json-style ``intrinsics`` object; :class:`InputError` naming ``where`` when it is not."""
    if not isinstance(d, dict):
        raise InputError(f"{where}: needs an 'intrinsics' object (camera_profile.json model)")
    try:
        return CameraIntrinsics.from_dict(d)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: {exc}") from None


def read_panorama_model(project: Project, path: Path) -> tuple[list[RigView], dict]:
    """The sources of a panorama model (``out/stitch/panorama.json``) as rig views, and the document."""
    doc = project.read_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("sources"), list) or not doc["sources"]:
        raise StageError(f"{path}: no 'sources' list; run the stitch stage again")
    views = []
    for i, s in enumerate(doc["sources"]):
        where = f"{path}: sources[{i}]"
        if not isinstance(s, dict) or not isinstance(s.get("name"), str):
            raise StageError(f"{where}: needs 'name'")
        intr = read_intrinsics(s.get("intrinsics"), f"{where}.intrinsics")
        R = _rotation(matrix_from_json(s.get("cam_from_pano"), (3, 3), f"{where}.cam_from_pano"),
                      f"{where}.cam_from_pano")
        views.append(RigView(s["name"], intr, R))
    return views, doc


def _sfm_views(images: Any, where: str) -> list[SfmView]:
    if not isinstance(images, list) or not images:
        raise StageError(f"{where}: no 'images' list; run the sfm stage again")
    views = []
    for i, s in enumerate(images):
        w = f"{where}[{i}]"
        if not isinstance(s, dict) or not isinstance(s.get("name"), str):
            raise StageError(f"{w}: needs 'name'")
        intr = read_intrinsics(s.get("intrinsics"), f"{w}.intrinsics")
        M = matrix_from_json(s.get("cam_from_model"), (4, 4), f"{w}.cam_from_model")
        _rotation(M[:3, :3], f"{w}.cam_from_model")
        views.append(SfmView(s["name"], intr, M))
    return views


def read_reconstruction(project: Project, path: Path) -> tuple[list[SfmView], dict]:
    """The images of an SfM reconstruction's main model (``out/sfm/reconstruction.json``) and the document."""
    doc = project.read_json(path)
    if not isinstance(doc, dict):
        raise StageError(f"{path}: not a reconstruction; run the sfm stage again")
    return _sfm_views(doc.get("images"), f"{path}: images"), doc


def read_reconstruction_models(project: Project, path: Path) -> tuple[list[tuple[str, list[SfmView]]], dict]:
    """Every model of an SfM reconstruction, each in its own frame: ``[("main", views), ("models[0]", views),
    ...]`` (the separate models in the file's order, largest first), and the document. A file written before
    separate models were kept has the main model only."""
    views, doc = read_reconstruction(project, path)
    models = doc.get("models", [])
    if not isinstance(models, list):
        raise StageError(f"{path}: 'models' must be a list; run the sfm stage again")
    out = [("main", views)]
    for k, m in enumerate(models):
        if not isinstance(m, dict):
            raise StageError(f"{path}: models[{k}] must be an object; run the sfm stage again")
        out.append((f"models[{k}]", _sfm_views(m.get("images"), f"{path}: models[{k}].images")))
    return out, doc


def image_in_reconstruction(rdoc: dict, name: str) -> str | None:
    """The image path a reconstruction document gives for photo ``name`` (any of its models), or None."""
    for images in [rdoc.get("images", [])] + [m.get("images", []) for m in rdoc.get("models", [])]:
        for s_ in images:
            if s_.get("name") == name:
                return s_.get("image")
    return None


def validate_cameras_doc(doc: Any, where: str) -> list[dict]:
    """Check a ``cameras.json`` document (docs/pipeline.md); returns its views. Errors name the entry."""
    if not isinstance(doc, dict) or not isinstance(doc.get("views"), list) or not doc["views"]:
        raise InputError(f"{where}: needs a non-empty 'views' list; see docs/pipeline.md (cameras.json)")
    if doc.get("route") not in ("panorama", "multiview", "single"):
        raise InputError(f"{where}: route = {doc.get('route')!r}; give 'panorama', 'multiview' or 'single'")
    names = set()
    for i, v in enumerate(doc["views"]):
        w = f"{where}: views[{i}]"
        if not isinstance(v, dict) or not isinstance(v.get("name"), str) or not v["name"]:
            raise InputError(f"{w}: needs a 'name' (the photo's file name)")
        w = f"{where}: views[{i}] ({v['name']!r})"
        if v["name"] in names:
            raise InputError(f"{w}: the name is used twice")
        names.add(v["name"])
        read_intrinsics(v.get("intrinsics"), f"{w}.intrinsics")
        M = matrix_from_json(v.get("cam_from_world"), (4, 4), f"{w}.cam_from_world")
        _rotation(M[:3, :3], f"{w}.cam_from_world")
        if not np.allclose(M[3], [0, 0, 0, 1]):
            raise InputError(f"{w}.cam_from_world: last row must be 0 0 0 1")
        if "center_enu" in v:
            c = matrix_from_json(v["center_enu"], (3,), f"{w}.center_enu") if np.ndim(v["center_enu"]) == 1 else None
            if c is None or np.linalg.norm(c + M[:3, :3].T @ M[:3, 3]) > 1e-3:
                raise InputError(f"{w}.center_enu = {v['center_enu']} disagrees with cam_from_world (its centre is "
                                 f"{(-M[:3, :3].T @ M[:3, 3]).round(4).tolist()}); fix one of them")
    pano = doc.get("panorama")
    if pano is not None:
        if not isinstance(pano, dict):
            raise InputError(f"{where}: 'panorama' must be an object or null")
        if "world_from_pano" in pano:
            _rotation(matrix_from_json(pano["world_from_pano"], (4, 4), f"{where}: panorama.world_from_pano")[:3, :3],
                      f"{where}: panorama.world_from_pano")
    return doc["views"]


def photos_by_name(project: Project) -> dict[str, Path]:
    """Every photo of the incident by file name: every photo set under ``photos/`` (following linked folders),
    the run's photos taking precedence."""
    out = {}
    photos_root = project.root / "photos"
    if photos_root.is_dir():  # every photo set, following linked folders (Path.rglob does not)
        for folder, _dirs, files in sorted(os.walk(photos_root, followlinks=True)):
            for f in sorted(files):
                out.setdefault(f, Path(folder) / f)
    try:
        for p in project.photo_paths():
            out[p.name] = p
    except InputError:
        pass
    return out


def gps_enu(project: Project, path: Path | None) -> np.ndarray | None:
    """A photo's EXIF GPS position in the scene frame (ENU metres; the scene's height when it has no
    altitude), or None."""
    if path is None or not path.is_file():
        return None
    g = read_gps(path)
    if g is None:
        return None
    lon, lat, alt = g
    enu = project.frame.enu_from_wgs84(np.array([lon, lat, alt if alt is not None else project.frame.height_m]))
    return enu


def require_control_points(project: Project) -> list[ControlPoint]:
    """The incident's control points (:func:`control_points_of_photos`); an error when the file is missing."""
    path = project.control_points_path
    if not path.is_file():
        raise InputError(f"{path}: not found; georegistration needs control points (landmarks with known "
                         f"coordinates picked in the photos, docs/gis.md) or a hand-written {CAMERAS_FILE}")
    return control_points_of_photos(project, path)


def unknown_photo_error(project: Project, name: str, where: str, what: str) -> InputError:
    """The error for a file name that is not a photo of the incident, listing the photos it has."""
    known = sorted(photos_by_name(project))
    listed = ", ".join(known[:8]) + (f" and {len(known) - 8} more" if len(known) > 8 else "")
    return InputError(f"{where}: {what} {name!r} is not a photo of this incident (under {project.root / 'photos'}: "
                      f"{listed}); give the photo's file name, or put the photo there")


def control_points_of_photos(project: Project, path: Path) -> list[ControlPoint]:
    """The control points of ``path``; a pixel keyed by a photo the incident does not have is an error naming the
    point (a renamed or missing photo would otherwise just leave the point out)."""
    cps = load_control_points(path, project.frame)
    photos = photos_by_name(project)
    if photos:
        for cp in cps:
            for name in cp.pixels:
                if name != PANORAMA_KEY and name not in photos:
                    raise unknown_photo_error(project, name, f"{path}: point {cp.name!r}", "pixels of photo")
    return cps
