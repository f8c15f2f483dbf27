"""The relative route: an incident with no survey (no control points, no hand-written cameras, no GPS-placed
SfM model) gets its cameras in a provisional local frame anchored at the camera (docs/gis.md, "Relative
incidents").

The camera centre is the origin; the reference photo (the only one, or the panorama's middle source) looks along
+y with its x axis along +x, as if it were held level. The solve stage then levels the frame from the carriages
that stand on their wheels (:mod:`workbench.solve.level`) and says in ``solution.json`` that the scene is
relative: the scale comes from the cars' dimensions, the azimuth from the camera's viewing direction; there is no
latitude, longitude or project-CRS figure.
"""

from __future__ import annotations

import numpy as np

from ..files.intrinsics import resolve_intrinsics
from ..files.panorama import read_panorama
from ..project import Project
from .documents import view_entry
from .options import GeorefOptions
from .priors import central_priors

__all__ = ["relative_route", "LEVEL_CAM_FROM_WORLD", "RELATIVE_NOTE"]

# x_cam = +x (east-like), y_cam = -z (down), z_cam = +y (forward): a level camera looking along +y
LEVEL_CAM_FROM_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

RELATIVE_NOTE = ("relative scene: no control points, no known cameras and no GPS, so nothing ties the scene to "
                 "the Earth; it is placed in a local frame with the camera at the origin, levelled from the "
                 "carriages standing on their wheels, y along the camera's viewing direction, scaled by the cars' "
                 "dimensions")


def _pose(R: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = R
    return M


def _anchor(project: Project, reference: str, names: list[str]) -> dict | None:
    """Where the reference photo's EXIF (or ``camera.position_enu``) puts the camera and which way it looked: the
    centre (ENU m) and its 1-sigma, the compass azimuth (true north) of the reference photo and its 1-sigma, and
    what was read (:func:`~workbench.georef.priors.central_priors`); None without a centre. The solve stage
    places the levelled scene with it when both are there (docs/gis.md, "Relative incidents")."""
    by_name = {p.name: p for p in project.photo_paths()}
    opts = GeorefOptions()
    pr = central_priors(project.frame, project.settings.camera.position_enu,
                        [(n, by_name.get(n)) for n in names], opts)
    if pr.centre is None:
        return None
    ref = names.index(reference)
    heading = next((h for h in pr.headings if h.view == ref), None)
    sig = [float(x) if np.isfinite(x) else None for x in pr.sigma_m]
    return {"source": pr.source, "centre_enu": pr.centre.tolist(), "sigma_enu_m": sig,
            "azimuth_deg": None if heading is None else heading.azimuth_deg,
            "sigma_azimuth_deg": None if heading is None else heading.sigma_deg, "priors": pr.record}


def relative_route(project: Project) -> tuple[dict, dict]:
    """(cameras.json document, stage statistics) of an incident with no georeference."""
    pano_path = project.panorama_model_path
    photos = project.photo_paths()
    if len(photos) > 1 and pano_path.is_file():
        pano = read_panorama(pano_path)
        sources = list(pano.sources)
        ref = sources[len(sources) // 2]
        rig_from_world = np.asarray(ref.cam_from_rig, float).T @ LEVEL_CAM_FROM_WORLD
        src = str(pano.doc.get("intrinsics_source", project.settings.camera.source.value))
        known = src in ("calibrated", "sfm")
        by_name = {p.name: p for p in photos}
        images = pano.images
        views = [view_entry(v.name, images.get(v.name) or (project.relative(by_name[v.name]) if v.name in by_name
                                                           else v.name),
                            v.intrinsics, _pose(np.asarray(v.cam_from_rig, float) @ rig_from_world), known)
                 for v in sources]
        route, reference = "panorama", ref.name
        image = project.stage_dir("stitch") / "panorama.jpg"
        panorama = {"model": project.relative(pano_path), "image": project.relative(image),
                    "world_from_pano": _pose(rig_from_world.T).tolist()}
    else:
        choice = resolve_intrinsics(project, photos[:1])
        p = photos[0]
        views = [view_entry(p.name, project.relative(p), choice.per_photo[p.name], _pose(LEVEL_CAM_FROM_WORLD),
                            choice.focal_known[p.name])]
        route, reference, src, panorama = "single", p.name, choice.source, None
    doc = {"route": route, "frame": "relative", "intrinsics_source": src, "georegistration": None,
           "relative": {"reference_view": reference, "note": RELATIVE_NOTE,
                        "anchor": _anchor(project, reference, [v["name"] for v in views])},
           "views": views, "panorama": panorama}
    if len(photos) > 1 and panorama is None:
        doc["relative"]["photos_left_out"] = [q.name for q in photos[1:]]
    stats = {"frame": "relative", "reference_view": reference, "n_views": len(views), "note": RELATIVE_NOTE}
    return doc, stats
