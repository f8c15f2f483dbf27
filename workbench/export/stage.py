"""The ``export`` stage: the reconstructed scene in formats GIS and 3D tools open (docs/exports.md).

Reads ``out/solve/solution.json``, ``out/terrain/terrain.ply`` and ``buildings.ply`` (when the terrain stage wrote
them), the orthophoto (when the project has one) and the rolling-stock models; writes under ``out/export/``:

* ``scene.glb``: glTF 2.0 binary (terrain, buildings, carriages with liveries), georeference in
  ``asset.extras.georeference``;
* ``carriages.geojson``: footprints and centres, WGS84 (RFC 7946), with each carriage's place on the railway line
  when the incident has one (``terrain.railways``);
* ``scene.kmz``: the carriage models placed for Google Earth;
* ``scene.city.json``: CityJSON 2.0 in the project CRS;
* ``tiles/tileset.json`` + ``tiles/scene.glb``: Cesium 3D Tiles 1.1 (``ExportOptions.tiles``).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..core.io import atomic_write_bytes, to_json
from ..core.settings import GIS_FORMATS, ExportFormat
from ..core.stage_api import Progress, StageResult
from ..errors import InputError
from ..files.railways import carriage_track_positions
from ..project import Project
from .cityjson import cityjson_document
from .geojson import carriages_geojson
from .gltf import glb_bytes
from .kmz import kmz_bytes
from .scene import ExportOptions, build_scene
from .tiles import tileset_document

log = logging.getLogger(__name__)

OUTPUTS = {"glb": "scene.glb", "geojson": "carriages.geojson", "kmz": "scene.kmz", "cityjson": "scene.city.json",
           "tileset": "tiles/tileset.json", "tiles_glb": "tiles/scene.glb"}


def export_formats(project: Project, relative: bool) -> tuple[list[str], dict[str, str]]:
    """(formats to write, {format: why not}) from ``export.formats`` (absent: every format the scene allows). A
    relative scene (no survey) has no place on the Earth: asking for a GIS format is an :class:`InputError`
    naming the setting and what is missing; by default those formats are left out with the reason."""
    asked = project.settings.export.formats
    names = [f.value for f in asked] if asked else [f.value for f in ExportFormat]
    if not relative:
        return names, {}
    why = ("the scene is relative (no control_points.json, no known cameras, no GPS): it has no place on the "
           "Earth; add control points (docs/gis.md) and run again")
    if asked:
        gis = [n for n in names if n in GIS_FORMATS]
        if gis:
            raise InputError(f"{project.settings_path}: export.formats asks for {', '.join(gis)}, but {why}; or "
                             f"keep export.formats = [\"glb\"] (the scene in its local frame)")
    return [n for n in names if n not in GIS_FORMATS], {n: why for n in GIS_FORMATS}


def export_scene(project: Project, options: ExportOptions | None = None,
                 progress: Progress = lambda f, m="": None) -> tuple[dict[str, Path], dict]:
    """Write the exports of ``project`` under ``out/export/`` (``export.formats``; a relative scene: the glTF
    only, in its local frame); returns ({name: path}, statistics)."""
    options = options or ExportOptions()
    out = project.stage_dir("export")
    t0 = time.perf_counter()
    progress(0.05, "reading the solution, terrain and models")
    relative = project.solution("export").relative
    formats, refused = export_formats(project, relative)  # refused before anything is written
    scene = build_scene(project, options)
    stats: dict[str, Any] = {"carriages": [c.number for c in scene.carriages], "left_out": scene.left_out,
                             "georeference": scene.georeference(), "formats": formats, "refused": refused,
                             "timings_s": {}}
    for fmt in refused:  # a georeferenced run's files must not outlive it: they would place a relative scene
        for key in ("tileset", "tiles_glb") if fmt == "tiles" else (fmt,):
            (out / OUTPUTS[key]).unlink(missing_ok=True)
    if scene.terrain is not None:
        tex = scene.terrain.texture_source
        stats["terrain"] = {**scene.terrain.info, "texture": project.relative(Path(tex)) if tex else None,
                            "colour": "orthophoto" if scene.terrain.texture is not None else "by height"}
    stats["timings_s"]["scene"] = round(time.perf_counter() - t0, 3)
    paths: dict[str, Path] = {}

    def timed(name: str, fn):
        t = time.perf_counter()
        r = fn()
        stats["timings_s"][name] = round(time.perf_counter() - t, 3)
        return r

    glb = None
    if "glb" in formats or "tiles" in formats:
        progress(0.3, "glTF")
        glb, gstats = timed("glb", lambda: glb_bytes(scene, options))
        stats["glb"] = gstats
    if "glb" in formats:
        paths["glb"] = atomic_write_bytes(out / OUTPUTS["glb"], glb)
    gj = None
    if "geojson" in formats:
        progress(0.5, "GeoJSON")
        track = carriage_track_positions(project.solution("export"), project.railways(heights=False))
        gj = timed("geojson", lambda: carriages_geojson(scene, track))
        paths["geojson"] = project.write_text(out / OUTPUTS["geojson"], to_json(gj))
    if "kmz" in formats:
        progress(0.6, "KMZ")
        kmz, kstats = timed("kmz", lambda: kmz_bytes(scene, options))
        paths["kmz"] = atomic_write_bytes(out / OUTPUTS["kmz"], kmz)
        stats["kmz"] = kstats
    if "cityjson" in formats:
        progress(0.75, "CityJSON")
        cj = timed("cityjson", lambda: cityjson_document(scene))
        paths["cityjson"] = project.write_text(out / OUTPUTS["cityjson"], _compact_json(cj))
        stats["cityjson"] = {"city_objects": len(cj["CityObjects"]), "vertices": len(cj["vertices"])}
    if options.tiles and "tiles" in formats:
        progress(0.9, "3D Tiles")
        paths["tiles_glb"] = atomic_write_bytes(out / OUTPUTS["tiles_glb"], glb)
        paths["tileset"] = project.write_text(out / OUTPUTS["tileset"],
                                              to_json(tileset_document(scene, "scene.glb")))
    # consistency: the exported centres against the solution's own WGS84 centres (same conversion: ~0)
    stats["centre_vs_solution_m"] = _centre_check(project, scene, gj) if gj is not None else None
    if refused:
        log.warning("export: %s not written: %s", ", ".join(refused), next(iter(refused.values())))
    stats["bytes"] = {k: p.stat().st_size for k, p in paths.items()}
    stats["time_s"] = round(time.perf_counter() - t0, 3)
    for k, p in paths.items():
        log.info("export: %s (%.1f MB)", project.relative(p), stats["bytes"][k] / 1e6)
    return paths, stats


def _compact_json(data: Any) -> str:
    """JSON without indentation (large vertex lists), NaN refused."""
    return json.dumps(data, separators=(",", ":"), allow_nan=False) + "\n"


def _centre_check(project: Project, scene: Any, gj: dict) -> float | None:
    """Largest distance (m) between a GeoJSON centre and the solution's ``body_centre_wgs84`` (None if absent)."""
    given = {c.number: c.floats("body_centre_wgs84") for c in project.solution("export").carriages}
    worst = None
    for ft in gj["features"]:
        if ft["geometry"]["type"] != "Point":
            continue
        g = given.get(ft["properties"]["number"])
        if g is None:
            continue
        a = scene.frame.enu_from_wgs84(np.asarray(ft["geometry"]["coordinates"], dtype=float)[None])[0]
        b = scene.frame.enu_from_wgs84(np.asarray(g, dtype=float)[None])[0]
        d = float(np.linalg.norm(a - b))
        worst = d if worst is None else max(worst, d)
    return worst


def run_export(project: Project, progress: Progress) -> StageResult:
    paths, stats = export_scene(project, ExportOptions(), progress)
    return StageResult(outputs=paths, stats=stats)
