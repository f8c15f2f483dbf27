"""Control-point picks as the solvers see them: the picks in a set of photos, their noise, and the residual
summary and warnings every solver reports (pixels and metres, per pick and per point)."""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..core.camera import CameraIntrinsics
from ..errors import InputError
from ..files.control_points import ControlPoint
from .options import GeorefOptions, GeorefResidualsLarge

log = logging.getLogger(__name__)

__all__ = ["Pick", "picks_in_views", "pick_sigma", "summarize_residuals", "warn_residuals"]


@dataclass
class Pick:
    """One pick of a control point in a photo."""

    point: int  # index into the control points
    view: int  # index into the views
    uv: np.ndarray  # (2,) pixels


def picks_in_views(cps: Sequence[ControlPoint], views: Sequence, where: str) -> list[Pick]:
    """Every pick of a control point in one of ``views``; pixels outside a photo are an error."""
    by_name = {v.name: i for i, v in enumerate(views)}
    obs: list[Pick] = []
    ignored: set[str] = set()
    for k, cp in enumerate(cps):
        for photo, uv in cp.pixels.items():
            i = by_name.get(photo)
            if i is None:
                ignored.add(photo)
                continue
            intr = views[i].intrinsics
            if not intr.in_image(np.asarray(uv, float)[None])[0]:
                raise InputError(f"{where}: control point {cp.name!r} has pixel {list(map(float, uv))} in photo "
                                 f"{photo!r}, outside the {intr.width}x{intr.height} image (u in [-0.5, "
                                 f"{intr.width - 0.5}], v in [-0.5, {intr.height - 0.5}]): if the photo was resized "
                                 f"or cropped after the points were picked in it, pick them again in the photo as it is "
                                 f"now; else fix the pick (u right, v down, origin at the top-left pixel's centre) or "
                                 f"remove it")
            obs.append(Pick(k, i, np.asarray(uv, float)))
    if ignored:
        log.info("%s: pixels in photo(s) %s are not used by this route (its photos: %s)", where, sorted(ignored),
                 sorted(by_name))
    return obs


def pick_sigma(intr: CameraIntrinsics, sigma_px: float, sigma_m: float, depth_m: float) -> float:
    """1-sigma (px) of a pick: the pick's noise and the point's position error seen at ``depth_m``."""
    f = 0.5 * (intr.fx + intr.fy)
    return math.sqrt(sigma_px ** 2 + (f * sigma_m / max(depth_m, 1e-3)) ** 2)


def summarize_residuals(residuals: list[dict], opts: GeorefOptions) -> dict:
    """RMS and maximum of the inliers' residuals (px, m), the outliers' number, and per point RMS."""
    px = np.array([r["error_px"] for r in residuals if r.get("error_px") is not None and r.get("inlier", True)])
    m = np.array([r["error_m"] for r in residuals if r.get("error_m") is not None and r.get("inlier", True)])
    per_point: dict[str, dict] = {}
    for r in residuals:
        d = per_point.setdefault(r["point"], {"px": [], "m": []})
        if r.get("error_px") is not None:
            d["px"].append(r["error_px"])
        if r.get("error_m") is not None:
            d["m"].append(r["error_m"])
    pts = {k: {"rms_px": float(np.sqrt(np.mean(np.square(v["px"])))) if v["px"] else None,
               "rms_m": float(np.sqrt(np.mean(np.square(v["m"])))) if v["m"] else None,
               "n_views": len(v["px"])} for k, v in per_point.items()}
    return {"rms_px": float(np.sqrt(np.mean(px ** 2))) if px.size else None,
            "max_px": float(px.max()) if px.size else None,
            "rms_m": float(np.sqrt(np.mean(m ** 2))) if m.size else None,
            "max_m": float(m.max()) if m.size else None,
            "n_outliers": int(sum(1 for r in residuals if not r.get("inlier", True))),
            "points": pts}


def warn_residuals(residuals: list[dict], stats: dict, opts: GeorefOptions, where: str) -> list[str]:
    """Messages for a large RMS and for every large or rejected pick, logged and warned as
    :class:`GeorefResidualsLarge` (attributed to the caller of the solver that calls this)."""
    out = []
    if stats.get("rms_px") is not None and stats["rms_px"] > opts.warn_rms_px:
        out.append(f"{where}: control-point RMS residual {stats['rms_px']:.2f} px exceeds {opts.warn_rms_px} px; "
                   f"check the picks and the coordinates of the points listed in out/georef/stats.json")
    for r in residuals:
        bad_px = r.get("error_px") is None or r["error_px"] > opts.warn_point_px
        bad_m = r.get("error_m") is not None and r["error_m"] > opts.warn_point_m
        if bad_px or bad_m or not r.get("inlier", True):
            e_px = "behind the camera" if r.get("error_px") is None else f"{r['error_px']:.1f} px"
            e_m = "" if r.get("error_m") is None else f", {r['error_m']:.2f} m"
            out.append(f"{where}: control point {r['point']!r} in {r['view']}: residual {e_px}{e_m}"
                       f"{' (rejected as an outlier)' if not r.get('inlier', True) else ''}; check its "
                       f"coordinates and its pick")
    for msg in out:
        log.warning(msg)
        warnings.warn(msg, GeorefResidualsLarge, stacklevel=3)
    return out
