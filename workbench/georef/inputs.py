"""What the georef stage reads besides the incident files (``workbench.files``): the incident's photos (by
file name), their EXIF GPS and the control points picked in them."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..core.layout import CAMERAS_FILE
from ..errors import InputError
from ..project import Project
from ..files.control_points import ControlPoint, TrackPick, load_control_points, load_track_picks
from .gps import read_gps
from .options import GeorefOptions
from .track_picks import TrackTerm, build_track_term

__all__ = ["PANORAMA_KEY", "photos_by_name", "gps_enu", "require_control_points", "control_points_of_photos",
           "unknown_photo_error", "track_term"]

PANORAMA_KEY = "panorama"  # pixel key of a pick made in the stitched panorama image


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


def _track_picks_of_photos(project: Project, path: Path) -> list[TrackPick]:
    picks = load_track_picks(path)
    photos = photos_by_name(project)
    for i, tp in enumerate(picks):
        if tp.photo == PANORAMA_KEY:
            raise InputError(f"{path}: track_picks[{i}]: picks in the stitched panorama are not read for the track; "
                             f"pick the rail in a source photo (its file name as 'photo')")
        if photos and tp.photo not in photos:
            raise unknown_photo_error(project, tp.photo, f"{path}: track_picks[{i}]", "photo")
    return picks


def track_term(project: Project, views, opts: GeorefOptions, where: str) -> TrackTerm | None:
    """The incident's track picks in ``views`` (``control_points.json`` ``track_picks``) on its railway layer, or None
    when it has none. The lines' heights (top of rail): the layer's own where every vertex has one (their 1-sigma
    ``opts.track_height_sigma_m``), else the DEM's under the line (1-sigma: the DEM's ``dem_vertical_accuracy_m``
    and ``opts.track_height_sigma_m`` for the rail above the ground the DEM sees); neither is an error."""
    path = project.control_points_path
    if not path.is_file():
        return None
    picks = _track_picks_of_photos(project, path)
    if not picks:
        return None
    if not project.settings.terrain.railways:
        raise InputError(f"{path}: has track_picks, but the incident has no railway layer; set terrain.railways in "
                         f"project.toml to the line the picks are on (GeoJSON or OpenStreetMap XML, docs/gis.md)")
    layer = project.railways(heights=False)
    if layer is None:
        raise InputError(f"{path}: has track_picks, but the railway layer {project.settings.terrain.railways} holds no "
                         f"railway line (railway=rail); give the layer the track the picks are on")
    h_sigma = float(opts.track_height_sigma_m)
    if layer.heights != "file":
        if not project.settings.terrain.dem:
            raise InputError(f"{path}: track picks need the track's heights: the railway layer "
                             f"{project.settings.terrain.railways} has none, and the incident has no DEM "
                             f"(terrain.dem); give [x, y, h] positions (top of rail) or a DEM")
        layer = project.railways(heights=True)
        h_sigma = math.hypot(float(project.settings.terrain.dem_vertical_accuracy_m), h_sigma)
    return build_track_term(picks, layer.lines, views, sigma_px=opts.track_sigma_px,
                            line_sigma_m=opts.track_line_sigma_m, height_sigma_m=h_sigma, where=where)
