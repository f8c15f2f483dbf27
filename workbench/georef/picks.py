"""Control-point picks as the solvers see them: the picks in a set of photos, their noise, and the residual
summary and warnings every solver reports (pixels and metres, per pick and per point)."""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.special import chdtrc

from ..core.camera import CameraIntrinsics
from ..errors import InputError
from ..files.control_points import ControlPoint
from .options import GeorefOptions, GeorefResidualsLarge

log = logging.getLogger(__name__)

__all__ = ["Pick", "picks_in_views", "pick_sigma", "inlier_limit_px", "misfit_doubt", "MISFIT_ALPHA",
           "shared_point_information", "influence_weights", "variance_factor", "summarize_residuals", "warn_residuals"]


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


def inlier_limit_px(sigma_px: float, opts: GeorefOptions) -> float:
    """A pick's inlier limit (px): ``opts.ransac_threshold_px``, or 4 times the pick's stated sigma
    (:func:`pick_sigma`) where that is larger: a landmark placed on a map to 0.5 m and seen 50 m away is 11 px
    uncertain, and a 12 px limit would throw out a good pick of it."""
    return max(float(opts.ransac_threshold_px), 4.0 * float(sigma_px))


MISFIT_ALPHA = 1e-3  # a fit's picks miss by more than their stated errors explain beyond this chi-square tail


def misfit_doubt(residuals: list[dict], rms_px: float | None, opts: GeorefOptions, n_params: int) -> str | None:
    """Why a fit's inlier residuals are doubted (None: they are not): their RMS (``rms_px``, 2-d pick errors) over
    ``opts.warn_rms_px`` *and* more than the picks' stated errors explain: the chi-square of their residuals over
    their stated sigma (each residual's ``sigma_px``: :func:`pick_sigma`, the point's survey error seen at its depth
    included) beyond its ``1 - MISFIT_ALPHA`` point on ``2 n - n_params`` degrees of freedom. Points surveyed to
    5 cm seen 30 m away by a 1700 px camera are about 3 px uncertain, so a right model of them has an RMS of 4-5 px,
    which the 3 px limit alone refused; SfM's focal 8 % off leaves 2-3 times the stated errors, which the
    chi-square refuses. Without stated sigmas the RMS limit alone decides."""
    if rms_px is None or rms_px <= opts.warn_rms_px:
        return None
    rows = [(float(r["error_px"]), float(r["sigma_px"])) for r in residuals
            if r.get("inlier", True) and r.get("error_px") is not None and r.get("sigma_px")]
    head = f"control-point RMS residual {rms_px:.2f} px exceeds {opts.warn_rms_px:g} px"
    dof = 2 * len(rows) - int(n_params)
    if dof < 1:
        return head
    chi2 = float(sum((e / sg) ** 2 for e, sg in rows))
    p = float(chdtrc(dof, chi2))
    if p >= MISFIT_ALPHA:
        return None
    return (f"{head} and more than the picks' stated errors explain (their points' survey error included: "
            f"chi-square {chi2:.0f} on {dof} degrees of freedom, p = {p:.1g})")


def shared_point_information(J_picks: np.ndarray, point_ids: np.ndarray, centre_cols: np.ndarray,
                             own_weight: np.ndarray, sigma_m: np.ndarray) -> np.ndarray:
    """The picks' part (P, P) of ``G`` in a fit's sandwich covariance ``H^-1 G H^-1``, in which a control point's
    position error is one error shared by all its picks (a landmark picked in three photos is off by the same
    metres in each), the pick's own noise independent.

    ``J_picks`` (2 n, P): the picks' whitened rows (pick k's at 2 k, 2 k + 1), each divided by the pick's whole
    sigma (:func:`pick_sigma`); ``own_weight`` (n,): the share of that variance that is the pick's own noise
    (``(sigma_px / sigma)^2``); ``point_ids`` (n,): the control point of each pick; ``sigma_m`` (n,): that
    point's position error (m, isotropic); ``centre_cols`` (n, 3): the parameter columns of the centre of the
    camera the pick is in (a pick's residual depends on the point less that centre, so its Jacobian with respect
    to the point is minus the centre's)."""
    G = (J_picks * np.repeat(own_weight, 2)[:, None]).T @ J_picks
    point_ids = np.asarray(point_ids)
    for p in np.unique(point_ids):
        k = np.nonzero(point_ids == p)[0]
        rows = np.stack([2 * k, 2 * k + 1], axis=1).ravel()
        cols = np.repeat(np.asarray(centre_cols)[k], 2, axis=0)  # (2 m, 3)
        s_m = np.repeat(np.asarray(sigma_m, float)[k], 2)[:, None]
        J_point = -np.take_along_axis(J_picks[rows], cols, axis=1) * s_m
        A = J_picks[rows].T @ J_point  # (P, 3): the gradient's response to the point's error
        G += A @ A.T
    return G


_INFLUENCE = {  # rho'(z) + 2 z rho''(z) of scipy's losses (z = (r / loss_scale)^2)
    "linear": lambda z: np.ones_like(z),
    "huber": lambda z: np.where(z <= 1.0, 1.0, 0.0),
    "soft_l1": lambda z: (1.0 + z) ** -1.5,
    "cauchy": lambda z: (1.0 - z) / (1.0 + z) ** 2,
    "arctan": lambda z: (1.0 - 3.0 * z ** 2) / (1.0 + z ** 2) ** 2,
}


def influence_weights(r: np.ndarray, opts: GeorefOptions) -> np.ndarray:
    """Per whitened residual ``r`` at a robust fit's solution, the slope of its influence (``d psi / d r``,
    ``rho'(z) + 2 z rho''(z)`` with ``z = (r / loss_scale)^2``, clipped at 1e-10 as scipy's ``least_squares``
    clips the factor it scales its Jacobian by): a fit's first-order response to a shift ``dr`` of its rows is
    ``-(J^T W J)^-1 J^T W dr`` with ``W`` these weights, so a pick far out on the loss moves it less."""
    z = (np.asarray(r, float) / opts.loss_scale) ** 2
    return np.maximum(_INFLUENCE.get(opts.loss, _INFLUENCE["linear"])(z), 1e-10)


def variance_factor(cost: float, chi2_red: float, dof: int, opts: GeorefOptions, narrow: bool = True) -> float:
    """The factor a fit's covariance is scaled by (the a posteriori variance of unit weight): the reduced chi-square
    of its whitened rows when above 1 (``2 cost / dof`` of the robust loss, or the plain ``chi2_red`` where that is
    larger with ``opts.variance_factor_min_dof`` degrees of freedom), so that picks which miss by more than their
    stated sigma (a lens the camera model cannot hold, a sloppy pick, a landmark off the map) widen the pose's
    interval by as much; with that many degrees of freedom also below 1 (well determined there: relative 1-sigma
    sqrt(2 / dof)), so that a pessimistic ``sigma_px`` does not inflate it, unless ``narrow`` is False (the central
    fits: a survey's or a map's stated error is partly common to all its points, which no residual shows). 1 with
    no degree of freedom."""
    vf = 1.0
    if dof > 0:
        vf = max(1.0, 2.0 * float(cost) / dof)
        if dof >= opts.variance_factor_min_dof and np.isfinite(chi2_red):
            vf = max(vf, chi2_red) if chi2_red >= 1.0 or not narrow else chi2_red
    return vf


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


def warn_residuals(residuals: list[dict], stats: dict, opts: GeorefOptions, where: str,
                   n_params: int = 6) -> list[str]:
    """Messages for a large RMS (:func:`misfit_doubt`, ``n_params`` the fit's parameters) and for every large or
    rejected pick (beyond ``opts.warn_point_px`` and 4 times its stated sigma), logged and warned as
    :class:`GeorefResidualsLarge` (attributed to the caller of the solver that calls this)."""
    out = []
    doubt = misfit_doubt(residuals, stats.get("rms_px"), opts, n_params)
    if doubt is not None:
        out.append(f"{where}: {doubt}; check the picks and the coordinates of the points listed in "
                   f"out/georef/stats.json")
    for r in residuals:  # beyond the fixed limit and 4 stated sigmas (a 1 in 3000 miss of a 2-d pick)
        point_lim = max(opts.warn_point_px, 4.0 * float(r.get("sigma_px") or 0.0))
        bad_px = r.get("error_px") is None or r["error_px"] > point_lim
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
