"""The central routes: the ``panorama`` route (the stitch stage's panorama model placed by ``world_from_pano``)
and the ``single`` route (one photo, intrinsics from the camera profile or the EXIF focal), both solved by
:func:`~workbench.georef.central.solve_central` from the control points, with ``camera.position_enu`` or EXIF GPS
as a prior on the centre and EXIF ``GPSImgDirection`` as a prior on each photo's heading (:mod:`.priors`)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
import numpy as np
from PIL import Image

from ..core.camera import CameraIntrinsics
from ..core.layout import CAMERAS_FILE
from ..errors import InputError
from ..project import Project
from ..files.exif import read_focal_px
from .central import solve_central
from ..files.control_points import ControlPoint
from .documents import georeg_block, view_entry
from ..files.panorama import PanoramaFile, RigView, read_panorama
from .inputs import PANORAMA_KEY, photos_by_name, require_control_points, track_term
from .options import GeorefOptions
from .priors import Priors, central_priors, prior_outcome

__all__ = ["panorama_route", "single_route"]


def _priors(project: Project, photos: list[tuple[str, Path | None]], opts: GeorefOptions) -> Priors:
    """The centre and heading priors of the rig whose views are ``photos`` (:func:`central_priors`)."""
    return central_priors(project.frame, project.settings.camera.position_enu, photos, opts)


def _prior_stats(pri: Priors, res) -> tuple[dict, dict]:
    """(the ``georegistration`` block's prior entries, the stage statistics' ones)."""
    rec = prior_outcome(pri, res.stats)
    return {"prior_source": pri.source, "priors": rec}, {"prior_source": pri.source, "priors": rec}


def panorama_route(project: Project, opts: GeorefOptions, where: str) -> tuple[dict, dict]:
    """(cameras.json document, stage statistics) of the panorama route."""
    pano_path = project.require_output(project.panorama_model_path, "stitch", "panorama route",
                                       f" (or write a {CAMERAS_FILE} by hand)")
    pano = read_panorama(pano_path)
    views, pdoc = list(pano.sources), pano.doc
    cps = _panorama_pixels_to_sources(require_control_points(project), pano, where)
    photos = photos_by_name(project)
    pri = _priors(project, [(v.name, photos.get(v.name)) for v in views], opts)
    res = solve_central(views, cps, prior_centre=pri.centre, prior_sigma_m=pri.sigma_m, heading_priors=pri.headings,
                        opts=opts, where=where, track=track_term(project, views, opts, where))
    block_extra, stats_extra = _prior_stats(pri, res)
    src = str(pdoc.get("intrinsics_source", project.settings.camera.source.value))
    focal_known = src in ("calibrated", "sfm")
    images = pano.images
    out_views = [view_entry(v.name, images.get(v.name) or (project.relative(photos[v.name]) if v.name in photos
                                                           else v.name),
                            v.intrinsics, res.cam_from_world(v.cam_from_rig), focal_known) for v in views]
    pano_image = project.stage_dir("stitch") / "panorama.jpg"
    doc = {"route": "panorama", "intrinsics_source": src,
           "georegistration": georeg_block("control_points", res, block_extra),
           "views": out_views,
           "panorama": {"model": project.relative(pano_path), "image": project.relative(pano_image),
                        "world_from_pano": res.world_from_rig.tolist()}}
    return doc, {**dict(res.stats), **stats_extra, "centre_enu": res.centre_enu.tolist()}


def _panorama_pixels_to_sources(cps: list[ControlPoint], pano: PanoramaFile, where: str) -> list[ControlPoint]:
    """Picks made in the stitched panorama (pixel key ``"panorama"``) mapped exactly into the source photo."""
    if not any(PANORAMA_KEY in cp.pixels for cp in cps):
        return cps
    try:
        model = pano.model()
    except InputError as exc:
        raise InputError(f"{where}: has picks in the panorama image, but {exc}; or pick the points in the source "
                         f"photos instead") from None
    out = []
    for cp in cps:
        if PANORAMA_KEY not in cp.pixels:
            out.append(cp)
            continue
        pix = dict(cp.pixels)
        uv = pix.pop(PANORAMA_KEY)
        idx, uv_src = model.to_source(np.asarray(uv, float)[None])
        if idx[0] < 0:
            raise InputError(f"{where}: control point {cp.name!r}: panorama pixel {list(map(float, uv))} is outside "
                             f"every source photo (the panorama is {model.width}x{model.height}); fix the pick")
        pix.setdefault(model.sources[int(idx[0])].name, uv_src[0])
        out.append(replace(cp, pixels=pix))
    return out


def _single_intrinsics(project: Project, photo: Path) -> tuple[CameraIntrinsics, str]:
    """The photo's intrinsics and their source: the camera profile (scaled to the photo) or the EXIF focal."""
    with Image.open(photo) as im:
        w, h = im.size
    prof = project.camera_profile()
    if prof is not None:
        intr = prof.for_size(w, h)
        return intr, "calibrated"
    f = read_focal_px(photo)
    if f is None:
        raise InputError(f"{photo}: no EXIF focal length and no camera.profile; single-photo georegistration "
                         f"needs the focal: calibrate the camera (camera.profile) or use a photo with EXIF")
    return CameraIntrinsics(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2.0, cy=(h - 1) / 2.0), "exif"


def single_route(project: Project, opts: GeorefOptions, where: str) -> tuple[dict, dict]:
    """(cameras.json document, stage statistics) of the single-photo route."""
    photo = project.photo_paths()[0]
    intr, src = _single_intrinsics(project, photo)
    cps = require_control_points(project)
    pri = _priors(project, [(photo.name, photo)], opts)
    view = RigView(photo.name, intr, np.eye(3))
    res = solve_central([view], cps, prior_centre=pri.centre, prior_sigma_m=pri.sigma_m, heading_priors=pri.headings,
                        opts=opts, where=where, track=track_term(project, [view], opts, where))
    block_extra, stats_extra = _prior_stats(pri, res)
    solver = "p3p_ransac_refined" if pri.centre is None else "p3p_and_prior_starts_refined_with_priors"
    doc = {"route": "single", "intrinsics_source": src,
           "georegistration": georeg_block("control_points", res, {"solver": solver, **block_extra}),
           "views": [view_entry(photo.name, project.relative(photo), intr, res.cam_from_world(np.eye(3)),
                                src == "calibrated")],
           "panorama": None}
    return doc, {**dict(res.stats), **stats_extra, "centre_enu": res.centre_enu.tolist()}
