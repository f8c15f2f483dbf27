"""The ``known`` route: the incident's hand-written ``cameras.json`` validated and kept as it is, and checked
against the control points when the incident has them."""

from __future__ import annotations

import logging
import warnings
from typing import Any

import numpy as np

from ..project import Project
from ..files.cameras import read_cameras
from .inputs import control_points_of_photos, photos_by_name, unknown_photo_error
from .options import GeorefOptions, GeorefResidualsLarge

log = logging.getLogger(__name__)

__all__ = ["known_route"]


def known_route(project: Project, opts: GeorefOptions) -> tuple[dict, dict]:
    """(cameras.json document, stage statistics) of the known route."""
    path = project.own_cameras_path
    cameras = read_cameras(path)
    views = cameras.views
    photos = photos_by_name(project)
    for i, v in enumerate(views):  # an incident without photo files (hand-written, solved from picks) is allowed
        if photos and v.name not in photos:
            raise unknown_photo_error(project, v.name, f"{path}: views[{i}].name", "view")
    extra: dict[str, Any] = {"n_views": len(views), "source": project.relative(path)}
    cp_path = project.control_points_path
    if cp_path.is_file():  # check the known cameras against the control points
        cps = control_points_of_photos(project, cp_path)
        resid = []
        for v in views:
            intr, M = v.intrinsics, v.cam_from_world
            for cp in cps:
                uv = cp.pixels.get(v.name)
                if uv is None:
                    continue
                q = M[:3, :3] @ cp.enu + M[:3, 3]
                e = float(np.hypot(*(intr.project(q[None])[0] - uv))) if q[2] > 0 else None
                resid.append({"point": cp.name, "view": v.name, "error_px": e})
        px = np.array([r["error_px"] for r in resid if r["error_px"] is not None])
        extra["control_point_check"] = {"n_observations": len(resid),
                                        "rms_px": float(np.sqrt(np.mean(px ** 2))) if px.size else None,
                                        "max_px": float(px.max()) if px.size else None, "residuals": resid}
        if px.size and float(np.sqrt(np.mean(px ** 2))) > opts.warn_rms_px:
            msg = (f"{path}: the known cameras disagree with {cp_path.name} by {np.sqrt(np.mean(px ** 2)):.1f} px "
                   f"RMS; check the cameras or the control points")
            log.warning(msg)
            warnings.warn(msg, GeorefResidualsLarge, stacklevel=2)
    return cameras.doc, extra
