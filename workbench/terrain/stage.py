"""The ``terrain`` stage: DEM (one file, a folder or a glob of tiles) and buildings (GeoJSON or CityJSON) to
meshes in the scene frame: ``out/terrain/terrain.ply`` (simplified where flat, within a vertical tolerance) and
``out/terrain/buildings.ply``, with statistics (docs/gis.md).

Settings read (``[terrain]``): ``dem``, ``buildings``, ``aoi_radius_m``, ``dem_vertical_accuracy_m`` and, when the
settings model has it, ``simplify_max_error_m`` (default :data:`DEFAULT_SIMPLIFY_MAX_ERROR_M`; 0 = keep every
DEM node).
"""

from __future__ import annotations

import logging
import time
import warnings

import numpy as np

from ..core.stage_api import Progress, StageResult
from ..errors import InputError, WorkbenchWarning
from ..files.dem import TerrainModel, simplify_terrain_mesh
from ..project import Project
from .buildings import read_buildings

log = logging.getLogger(__name__)

__all__ = ["run_terrain", "DEFAULT_SIMPLIFY_MAX_ERROR_M", "DemHeightMismatch",
           "DemPartialCoverage"]

DEFAULT_SIMPLIFY_MAX_ERROR_M = 0.05


class DemHeightMismatch(WorkbenchWarning):
    """The DEM's height at the reference point differs much from ``location.height_m``."""


class DemPartialCoverage(WorkbenchWarning):
    """The DEM covers only part of the area of interest around the incident."""


def _check_coverage(project: Project, tm: TerrainModel, where: str) -> dict:
    r = float(project.settings.terrain.aoi_radius_m)
    b = np.asarray(tm.bounds_enu)
    cell = float(max(abs(tm.transform.a), abs(tm.transform.e)))
    short = {"west": b[0, 0] + r, "south": b[0, 1] + r, "east": r - b[1, 0], "north": r - b[1, 1]}
    missing = {k: round(v, 1) for k, v in short.items() if v > 2.0 * cell + 1.0}
    out = {"aoi_radius_m": r, "coverage_short_m": missing}
    if missing:
        msg = (f"DEM {where} covers only part of the area of interest (+-{r:.0f} m around the reference point): it "
               f"stops short by {', '.join(f'{v} m on the {k}' for k, v in missing.items())}; use a larger DEM (or "
               f"more tiles) or a smaller terrain.aoi_radius_m")
        log.warning(msg)
        warnings.warn(msg, DemPartialCoverage, stacklevel=2)
    return out


def _check_origin_height(project: Project, tm: TerrainModel, where: str) -> dict:
    """Compare the DEM at the origin with location.height_m: a ratio near 3.28 or 100 means feet or centimetres."""
    h_set = float(project.settings.location.height_m)
    z0 = float(tm.height_at(np.zeros((1, 2)))[0]) + h_set  # ENU up is relative to the origin height
    out = {"dem_height_at_origin_m": z0, "location_height_m": h_set}
    if h_set == 0.0 or abs(z0 - h_set) <= max(30.0, 0.2 * abs(h_set)):
        return out
    ratio = z0 / h_set
    for factor, unit in ((1 / 0.3048, "feet"), (100.0, "centimetres"), (0.3048, "metres while location.height_m "
                                                                         "is in feet")):
        if abs(ratio / factor - 1.0) < 0.05:
            raise InputError(f"DEM {where}: its height at the reference point is {z0:.2f} but location.height_m = "
                             f"{h_set:.2f} ({ratio:.2f} times): the DEM looks like it is in {unit}; convert it to "
                             f"metres "
                             f"(or declare its unit: gdal_edit.py -units ft|cm) and check location.height_m")
    msg = (f"DEM {where}: its height at the reference point is {z0:.2f} m but location.height_m = {h_set:.2f} m; "
           f"check the DEM's vertical datum and units and the reference height")
    log.warning(msg)
    warnings.warn(msg, DemHeightMismatch, stacklevel=2)
    out["warning"] = msg
    return out


def run_terrain(project: Project, progress: Progress) -> StageResult:
    t = project.settings.terrain
    paths = project.dem_paths()
    where = str(paths[0]) if len(paths) == 1 else f"tiles {[p.name for p in paths]}"
    stats: dict = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", WorkbenchWarning)
        progress(0.1, "DEM")
        t0 = time.perf_counter()
        tm = project.terrain_model()
        stats["dem_read_s"] = round(time.perf_counter() - t0, 3)
        stats.update(_check_origin_height(project, tm, where))
        stats.update(_check_coverage(project, tm, where))
        tol = getattr(t, "simplify_max_error_m", DEFAULT_SIMPLIFY_MAX_ERROR_M)
        progress(0.3, "mesh")
        if tol and tol > 0:
            t0 = time.perf_counter()
            mesh, simp = simplify_terrain_mesh(tm, float(tol))
            simp["time_s"] = round(time.perf_counter() - t0, 3)
        else:
            mesh = tm.mesh()
            simp = {"max_error_m": 0.0, "tolerance_m": 0.0, "n_vertices": int(len(mesh.vertices)),
                    "n_vertices_full": int(len(mesh.vertices))}
        out = project.stage_dir("terrain")
        terrain_ply = project.write_with(out / "terrain.ply", lambda p: mesh.export(p))
        outputs = {"terrain_mesh": terrain_ply}
        info = {k: v for k, v in tm.info.items() if k not in ("tiles",)}
        stats.update({
            "dem": [project.relative(p) for p in paths] if len(paths) > 1 else project.relative(paths[0]),
            "n_vertices": int(len(mesh.vertices)), "n_faces": int(len(mesh.faces)),
            "bounds_enu": np.asarray(tm.bounds_enu).tolist(),
            "height_at_origin_m": float(tm.height_at(np.zeros((1, 2)))[0]),
            "vertical_accuracy_m": t.dem_vertical_accuracy_m, "simplification": simp,
            "dem_info": {k: (list(v) if isinstance(v, tuple) else v) for k, v in info.items()},
        })
        if t.buildings:
            progress(0.6, "buildings")
            res = read_buildings(project.require_file(t.buildings, "terrain.buildings"), project.frame, tm)
            merged = res.merged()
            if merged is not None:
                outputs["buildings_mesh"] = project.write_with(out / "buildings.ply", lambda p: merged.export(p))
            stats["buildings"] = res.info
            stats["n_buildings"] = int(res.info.get("n_buildings", len(res.meshes)))
    stats["warnings"] = [str(w.message) for w in caught if issubclass(w.category, WorkbenchWarning)]
    return StageResult(outputs=outputs, stats=stats)
