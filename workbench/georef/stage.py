"""The ``georef`` stage: every view in the scene frame, written to ``out/georef/cameras.json`` (docs/pipeline.md).

Routes (``route`` in cameras.json; docs/gis.md):

* **known** (:mod:`.route_known`): the incident has a hand-written ``cameras.json``; it is validated and copied
  as it is (and, when ``control_points.json`` exists, the control points are checked against it).
* **panorama** (:mod:`.route_central`): the stitch stage's panorama model placed by ``world_from_pano`` from the
  control points (:func:`~workbench.georef.central.solve_central`), with ``camera.position_enu`` or EXIF GPS as
  a prior.
* **multiview** (``camera.source = "sfm"``, :mod:`.route_multiview`): the SfM reconstruction's models mapped by
  similarities fitted to the control points and to the photos' GPS
  (:func:`~workbench.georef.similarity.solve_similarity`).
* **relative** (photos, no control points, :mod:`.route_relative`): the camera at the origin of a provisional
  local frame, which the solve stage levels from the carriages; nothing is georeferenced.
* **single** (one photo, :mod:`.route_central`): P3P + refinement from the control points, intrinsics from the
  camera profile (``calibrated``) or the EXIF focal (``exif``).

Control-point residuals (pixels and metres, per point and per photo) go to ``out/georef/stats.json`` and into
``cameras.json``'s ``georegistration``; large ones are warned about (:class:`GeorefResidualsLarge`), and so is a
malformed EXIF GPS tag, which is ignored (:class:`~workbench.georef.gps.GpsTagIgnored`). The central routes'
priors (GPS centre, compass heading) and their sigmas are in ``georegistration.priors`` and the statistics.
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from typing import Any

from ..core.layout import CAMERAS_FILE
from ..project import Project
from ..core.stage_api import Progress, StageResult
from .gps import GpsTagIgnored
from .options import GeorefOptions, GeorefResidualsLarge
from .route_central import panorama_route, single_route
from .route_known import known_route
from .route_multiview import multiview_route
from .route_relative import relative_route

__all__ = ["run_georef"]


def run_georef(project: Project, progress: Progress, opts: GeorefOptions = GeorefOptions()) -> StageResult:
    """Run the incident's georef route and write ``cameras.json``; the stage statistics include every residual
    warning raised."""
    route = project.georef_route()
    opts = replace(opts, sigma_px=float(project.settings.georef.pick_sigma_px),
                   track_sigma_px=float(project.settings.georef.track_sigma_px))
    out_dir = project.stage_dir("georef")
    where = str(project.control_points_path)
    stats: dict[str, Any] = {"route": route}
    progress(0.05, route)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", GeorefResidualsLarge)
        warnings.simplefilter("always", GpsTagIgnored)
        if route == "known":
            doc, extra = known_route(project, opts)
        elif route == "panorama":
            doc, extra = panorama_route(project, opts, where)
        elif route == "multiview":
            doc, extra = multiview_route(project, opts, where)
        elif route == "relative":
            doc, extra = relative_route(project)
        else:
            doc, extra = single_route(project, opts, where)
    for w in caught:  # a malformed GPS tag is also shown to the user (one line each, the CLI's handler)
        if issubclass(w.category, GpsTagIgnored):
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    stats.update(extra)
    stats["warnings"] = [str(w.message) for w in caught
                         if issubclass(w.category, (GeorefResidualsLarge, GpsTagIgnored))]
    progress(0.9, "writing cameras.json")
    path = project.write_json(out_dir / CAMERAS_FILE, doc)
    return StageResult(outputs={"cameras": path}, stats=stats)
