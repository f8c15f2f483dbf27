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

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..core.io import atomic_write_bytes, to_json
from ..core.stage_api import Progress, StageResult
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


def export_scene(project: Project, options: ExportOptions | None = None,
                 progress: Progress = lambda f, m="": None) -> tuple[dict[str, Path], dict]:
    """Write every export of ``project`` under ``out/export/``; returns ({name: path}, statistics)."""
    options = options or ExportOptions()
    out = project.stage_dir("export")
    t0 = time.perf_counter()
    progress(0.05, "reading the solution, terrain and models")
    scene = build_scene(project, options)
    stats: dict[str, Any] = {"carriages": [c.number for c in scene.carriages], "left_out": scene.left_out,
                             "georeference": scene.georeference(), "timings_s": {}}
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

    progress(0.3, "glTF")
    glb, gstats = timed("glb", lambda: glb_bytes(scene, options))
    paths["glb"] = atomic_write_bytes(out / OUTPUTS["glb"], glb)
    stats["glb"] = gstats
    progress(0.5, "GeoJSON")
    track = carriage_track_positions(project.solution("export"), project.railways(heights=False))
    gj = timed("geojson", lambda: carriages_geojson(scene, track))
    paths["geojson"] = project.write_text(out / OUTPUTS["geojson"], to_json(gj))
    progress(0.6, "KMZ")
    kmz, kstats = timed("kmz", lambda: kmz_bytes(scene, options))
    paths["kmz"] = atomic_write_bytes(out / OUTPUTS["kmz"], kmz)
    stats["kmz"] = kstats
    progress(0.75, "CityJSON")
    cj = timed("cityjson", lambda: cityjson_document(scene))
    paths["cityjson"] = project.write_text(out / OUTPUTS["cityjson"], _compact_json(cj))
    stats["cityjson"] = {"city_objects": len(cj["CityObjects"]), "vertices": len(cj["vertices"])}
    if options.tiles:
        progress(0.9, "3D Tiles")
        paths["tiles_glb"] = atomic_write_bytes(out / OUTPUTS["tiles_glb"], glb)
        paths["tileset"] = project.write_text(out / OUTPUTS["tileset"],
                                              to_json(tileset_document(scene, "scene.glb")))
    # consistency: the exported centres against the solution's own WGS84 centres (same conversion: ~0)
    stats["centre_vs_solution_m"] = _centre_check(project, scene, gj)
    stats["bytes"] = {k: p.stat().st_size for k, p in paths.items()}
    stats["time_s"] = round(time.perf_counter() - t0, 3)
    for k, p in paths.items():
        log.info("export: %s (%.1f MB)", project.relative(p), stats["bytes"][k] / 1e6)
    return paths, stats


def _compact_json(data: Any) -> str:
    """JSON without indentation (large vertex lists), NaN refused."""
    import json

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
