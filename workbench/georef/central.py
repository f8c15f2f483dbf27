"""Placing a *central* rig from control points: one projection centre, several photos that only turned (a
panorama, its frame ``pano`` = ``rig``), or a single photo (``rig`` = the camera).

Unknowns: ``rig_from_world`` (rotation) and the centre (3). Start: P3P (OpenCV) on the control-point rays in the
rig frame, each triple seen through a virtual pinhole looking along their mean direction; with a centre prior
(``camera.position_enu`` or EXIF GPS) also the rotation that best aligns the rays with the directions to the
points (Kabsch), and with a heading prior (EXIF ``GPSImgDirection``) the rotations that put a photo's optical axis
on that heading and one pick on its ray (the candidates and their scoring: :mod:`.central_start`). Refinement:
reprojection error in every source photo (its own intrinsics and distortion), each residual divided by
``sqrt(sigma_px^2 + (f sigma_m / depth)^2)``, plus the priors (centre, per axis; heading: the azimuth of a photo's
optical axis); robust loss (docs/gis.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares

from ..core.camera import CameraIntrinsics, brown_distortion
from ..core.geometry import exp_so3, log_so3, orthonormal
from ..errors import InputError
from ..files.control_points import ControlPoint
from ..files.panorama import RigView
from .central_start import best_candidate, central_errors, heading_errors, prior_grid, start_candidates
from .fitting import point_line_distance
from .options import GeorefOptions, HeadingPrior
from .picks import (Pick, inlier_limit_px, pick_sigma, picks_in_views, shared_point_information, summarize_residuals,
                    variance_factor, warn_residuals)
from .track_picks import TrackTerm, track_fit_stats, track_inliers, track_rotation_candidates

__all__ = ["CentralResult", "solve_central", "refine_resection_focal"]


@dataclass
class CentralResult:
    """``rig_from_world`` rotation (3, 3), ``centre_enu`` (3,), residuals and statistics."""

    rig_from_world: np.ndarray
    centre_enu: np.ndarray
    residuals: list[dict]
    stats: dict
    warnings: list[str]

    @property
    def world_from_rig(self) -> np.ndarray:
        """(4, 4) ``world_from_rig``."""
        M = np.eye(4)
        M[:3, :3] = self.rig_from_world.T
        M[:3, 3] = self.centre_enu
        return M

    def cam_from_world(self, cam_from_rig: np.ndarray) -> np.ndarray:
        """(4, 4) ``cam_from_world`` of a photo of the rig with ``cam_from_rig`` (3, 3)."""
        R = np.asarray(cam_from_rig, float) @ self.rig_from_world
        M = np.eye(4)
        M[:3, :3] = R
        M[:3, 3] = -R @ self.centre_enu
        return M


def _multi_start(bear: np.ndarray, pts: np.ndarray, X: np.ndarray, views: Sequence[RigView], obs: list[Pick],
                 cps: Sequence[ControlPoint], prior_centre: np.ndarray, sig_prior: np.ndarray,
                 headings: Sequence[HeadingPrior], opts: GeorefOptions, rng: np.random.Generator,
                 first: tuple[np.ndarray, np.ndarray], track: TrackTerm | None = None
                 ) -> tuple[tuple[np.ndarray, np.ndarray] | None, int]:
    """With few points the cost has several minima (with 2 map points the camera fits them above or below its
    true height, tens of metres apart): the RANSAC start ``first`` and a start at each centre of
    :func:`~workbench.georef.central_start.prior_grid` (Kabsch on the picks, and the compass starts), each
    refined, the lowest cost kept.
    Returns ((rig_from_world, centre) or None, the number of starts)."""
    best, best_cost, n = None, np.inf, 0
    for c in [None, *prior_grid(prior_centre, sig_prior)]:
        if c is None:
            R0, c0 = first
        else:
            cands = start_candidates(bear, pts, X, 0, c, opts, rng, views, headings, n_pairs=0)
            if not cands:
                continue
            n += len(cands)
            R0, c0 = best_candidate(cands, views, obs, X, prior_centre, sig_prior, opts, headings, track)
        info: dict = {}
        R1, c1, _ = _refine_central(views, obs, X, cps, R0, c0, np.ones(len(obs), bool), prior_centre, sig_prior,
                                    opts, headings, info_out=info, track=track)
        if info["cost"] < best_cost:
            best, best_cost = (R1, c1), info["cost"]
    return best, n


def _refine_central(views: Sequence[RigView], obs: list[Pick], X: np.ndarray, cps: Sequence[ControlPoint],
                    R_init: np.ndarray, c_init: np.ndarray, use: np.ndarray, prior_centre: np.ndarray | None,
                    sig_prior: np.ndarray | None, opts: GeorefOptions, headings: Sequence[HeadingPrior] = (),
                    info_out: dict | None = None, track: TrackTerm | None = None, track_use: np.ndarray | None = None,
                    max_nfev: int = 200):
    """Rotation, centre and their (6, 6) covariance (rig-frame rotation vector, centre; None when singular)
    refined on the picks ``use`` and the track picks ``track_use`` (all when None) (robust loss ``opts.loss``),
    with the centre prior when given (an infinite sigma leaves that axis free) and the heading priors. The rows:
    the control-point picks (2 each), the track picks (1 each), the priors. ``info_out`` gets the cost and the
    whitened Jacobian's track rows (``J_track``)."""
    t_use = np.ones(track.n, bool) if track is not None and track_use is None else track_use
    t_sig = None
    if track is not None:
        t_sig = track.sigmas(track.errors(R_init, c_init, views)[1], views)
    sel = [o for o, u_ in zip(obs, use) if u_]
    depths = []
    for o in sel:
        v = views[o.view]
        depths.append(max(float((v.cam_from_rig @ (R_init @ (X[o.point] - c_init)))[2]), 1e-3))
    sig = np.array([pick_sigma(views[o.view].intrinsics, opts.sigma_px, cps[o.point].sigma_m, d)
                    for o, d in zip(sel, depths)])
    h_sig = np.radians([h.sigma_deg for h in headings])
    vi = np.array([o.view for o in sel], int)
    # the picks of each photo, batched: (rows, cam_from_rig^T, intrinsics); one photo's rows are all, in order
    groups = [(np.nonzero(vi == i)[0], np.asarray(views[i].cam_from_rig, float).T, views[i].intrinsics)
              for i in np.unique(vi)]
    whole = len(groups) == 1
    Xs = X[[o.point for o in sel]].reshape(-1, 3)
    UV = np.array([o.uv for o in sel], float).reshape(-1, 2)
    prior = None if prior_centre is None else np.asarray(prior_centre, float)
    sig_col = sig[:, None]

    def fun(p, segments=None):
        R = exp_so3(p[:3]) @ R_init
        c = p[3:]
        P = (Xs - c) @ R.T
        res = np.empty((len(sel), 2))
        for k, C_t, intr in groups:  # intr.project with the depth clipped, without its (n, 2) round trips
            q = (P if whole else P[k]) @ C_t
            z = np.maximum(q[:, 2], 1e-6)
            _, _, xd, yd = brown_distortion(q[:, 0] / z, q[:, 1] / z, intr)
            res[k, 0], res[k, 1] = intr.pixel_coords(xd, yd)
        out = [((res - UV) / sig_col).ravel()]
        if track is not None:
            out.append(track.whitened(R, c, views, t_use, t_sig, segments))
        if sig_prior is not None:
            out.append((c - prior) / sig_prior)
        if headings:
            out.append(heading_errors(R, views, headings) / h_sig)
        return np.concatenate(out)

    def jac(p):  # forward differences; the track picks each against the segment nearest at p
        segments = None if track is None else track.nearest(exp_so3(p[:3]) @ R_init, p[3:], views)
        f0 = fun(p, segments)
        J = np.empty((len(f0), 6))
        for i in range(6):
            h = 1e-7 * max(1.0, abs(float(p[i])))
            dp = p.copy()
            dp[i] += h
            J[:, i] = (fun(dp, segments) - f0) / h
        return J

    x0 = np.concatenate([np.zeros(3), c_init])
    sol = least_squares(fun, x0, jac=jac if track is not None else "2-point", loss=opts.loss, f_scale=opts.loss_scale,
                        x_scale="jac", max_nfev=max_nfev)
    R = exp_so3(sol.x[:3]) @ R_init
    cov = None
    t_rows = None
    if track is not None:
        idx = np.nonzero(t_use)[0]
        pos = {int(k): j for j, k in enumerate(idx)}
        groups = [(np.array([pos[int(k)] for k in ks if int(k) in pos], int), s) for ks, s in track.line_groups()]
        t_rows = (len(idx), (track.sigma_px / t_sig[idx]) ** 2, groups)
    try:
        cov = _shared_point_covariance(sol.jac, [o.point for o in sel], sig, opts.sigma_px,
                                       np.array([cps[o.point].sigma_m for o in sel], float), t_rows)
    except np.linalg.LinAlgError:
        pass
    if info_out is not None:
        info_out["cost"] = float(sol.cost)
        # the rows that measure something (an infinite prior sigma leaves its row at 0)
        free_rows = 0 if sig_prior is None else int(np.sum(~np.isfinite(np.broadcast_to(sig_prior, (3,)))))
        dof = len(sol.fun) - free_rows - 6
        chi2 = float(np.sum(sol.fun ** 2) / dof) if dof > 0 else float("nan")
        # widened where the picks miss by more than they state, never narrowed
        info_out.update(dof=dof, chi2_red=chi2,
                        variance_factor=variance_factor(sol.cost, chi2, dof, opts, narrow=False))
        n2 = 2 * len(sel)
        info_out["J_track"] = sol.jac[n2:n2 + (t_rows[0] if t_rows else 0)]
    return R, sol.x[3:].copy(), cov


def _shared_point_covariance(J: np.ndarray, points: list[int], sig: np.ndarray, sigma_px: float,
                             sigma_m: np.ndarray, track_rows: tuple | None = None) -> np.ndarray:
    """(6, 6) covariance of (rotation vector, centre) from the whitened Jacobian ``J`` (2 n picks + the priors'
    rows, 6) of a fit whose picks were weighted by ``sig`` (n,: the pick's noise and its point's position error
    seen at its depth, :func:`pick_sigma`): the sandwich ``H^-1 G H^-1``, in which a control point's position error
    (``sigma_m`` (n,) m, isotropic) is one error shared by all its picks (a landmark picked in three photos of a
    panorama is off by the same metres in all three), and the pick's own noise (``sigma_px``) is independent. The
    picks' residuals depend on the point less the centre, so a point's pixel Jacobian is minus the centre's.
    ``track_rows`` = (t, own-noise weight (t,), [(rows among the t, (3,) 1-sigma east/north/up)] per line): the t
    track-pick rows after the picks' (each weighted by its noise and its line's error at its depth), their own
    noise independent and each railway line's position error one shift shared by all its picks."""
    n = len(points)
    t = track_rows[0] if track_rows is not None else 0
    Jp, Jt, Jq = J[:2 * n], J[2 * n:2 * n + t], J[2 * n + t:]
    H = J.T @ J
    G = Jq.T @ Jq + shared_point_information(Jp, np.asarray(points), np.tile([3, 4, 5], (n, 1)),
                                             (sigma_px / sig) ** 2, sigma_m)
    if t:
        G += (Jt * track_rows[1][:, None]).T @ Jt
        for rows, s in track_rows[2]:
            A = Jt[rows].T @ (-Jt[rows, 3:6] * s[None, :])
            G += A @ A.T
    Hi = np.linalg.inv(H)
    C = Hi @ G @ Hi
    return 0.5 * (C + C.T)


def _sample_covariance(views: Sequence[RigView], obs: list[Pick], X: np.ndarray, cps: Sequence[ControlPoint],
                       R: np.ndarray, c: np.ndarray, use: np.ndarray, prior_centre: np.ndarray | None,
                       sig_prior: np.ndarray | None, headings: Sequence[HeadingPrior], cov: np.ndarray,
                       opts: GeorefOptions) -> tuple[np.ndarray, dict]:
    """``cov`` widened to the scatter of re-solves on perturbed data (few points: with 2 map points and GPS the
    cost's valley is curved, the camera can slide tens of metres up or down it, and the Jacobian at the solution
    claims more than it knows). Each of ``opts.sample_count`` re-solves (seeded) moves every pick by its noise
    (``sqrt(sigma_px^2 + (f sigma_m / depth)^2)``), the centre prior and each heading prior by theirs, and refits
    from the solution; the second moment of the re-solves about the solution (rotation vector in the rig frame,
    centre) is compared with ``cov`` and, in each direction where it is larger, replaces it (generalised
    eigenvalues clipped at 1, so the linear covariance is never narrowed by the sampling noise)."""
    rng = np.random.default_rng(opts.seed + 1)
    sel = [k for k, u_ in enumerate(use) if u_]
    sig = {}
    for k in sel:
        o = obs[k]
        d = max(float((views[o.view].cam_from_rig @ (R @ (X[o.point] - c)))[2]), 1e-3)
        sig[k] = pick_sigma(views[o.view].intrinsics, opts.sigma_px, cps[o.point].sigma_m, d)
    devs = []
    for _ in range(opts.sample_count):
        obs_k = [Pick(o.point, o.view, o.uv + (rng.normal(0.0, sig[k], 2) if k in sig else 0.0))
                 for k, o in enumerate(obs)]
        prior_k = None
        if prior_centre is not None:
            fin = np.isfinite(sig_prior)
            prior_k = np.asarray(prior_centre, float) + np.where(fin, rng.normal(0.0, 1.0, 3) * np.where(fin, sig_prior,
                                                                                                    0.0), 0.0)
        heads_k = [HeadingPrior(h.view, h.azimuth_deg + float(rng.normal(0.0, h.sigma_deg)), h.sigma_deg, h.photo)
                   for h in headings]
        Rk, ck, _ = _refine_central(views, obs_k, X, cps, R, c, use, prior_k, sig_prior, opts, heads_k)
        devs.append(np.concatenate([log_so3(orthonormal(Rk) @ R.T), ck - c]))
    D = np.array(devs)
    S = D.T @ D / len(D)
    # generalised eigenvalues of S against cov: widen where the samples scatter more
    try:
        L = np.linalg.cholesky(0.5 * (cov + cov.T))
    except np.linalg.LinAlgError:  # the linearisation is singular (as many equations as unknowns): the samples'
        w, U = np.linalg.eigh(0.5 * (cov + cov.T))
        out = U @ np.diag(np.maximum(w, 0.0)) @ U.T + S  # scatter on top of what is left of it
        return 0.5 * (out + out.T), {"sampled_covariance": {"samples": len(D), "widening_sigma_factors": None,
                                                            "note": "linear covariance singular: samples added"}}
    Li = np.linalg.inv(L)
    lam, V = np.linalg.eigh(0.5 * (Li @ S @ Li.T + (Li @ S @ Li.T).T))
    lam_c = np.maximum(lam, 1.0)
    out = L @ V @ np.diag(lam_c) @ V.T @ L.T
    return 0.5 * (out + out.T), {"sampled_covariance": {"samples": len(D),
                                                        "widening_sigma_factors": np.sqrt(lam_c)[::-1].tolist()}}


def pick_sigmas(R: np.ndarray, c: np.ndarray, views: Sequence[RigView], obs: list[Pick], X: np.ndarray,
                cps: Sequence[ControlPoint], opts: GeorefOptions) -> np.ndarray:
    """Each pick's stated sigma (px, :func:`pick_sigma` at its point's depth in the camera ``(R, c)``); NaN for a
    point behind the camera."""
    out = np.full(len(obs), np.nan)
    for k, o in enumerate(obs):
        d = float((views[o.view].cam_from_rig @ (R @ (X[o.point] - c)))[2])
        if d > 1e-3:
            out[k] = pick_sigma(views[o.view].intrinsics, opts.sigma_px, cps[o.point].sigma_m, d)
    return out


def inlier_limits(R: np.ndarray, c: np.ndarray, views: Sequence[RigView], obs: list[Pick], X: np.ndarray,
                  cps: Sequence[ControlPoint], opts: GeorefOptions) -> np.ndarray:
    """Each pick's inlier limit (px, :func:`~workbench.georef.picks.inlier_limit_px` of its stated sigma;
    ``opts.ransac_threshold_px`` for a point behind the camera)."""
    return np.array([float(opts.ransac_threshold_px) if not np.isfinite(s) else inlier_limit_px(s, opts)
                     for s in pick_sigmas(R, c, views, obs, X, cps, opts)])


def _central_residuals(R: np.ndarray, c: np.ndarray, views: Sequence[RigView], obs: list[Pick], X: np.ndarray,
                       bear: np.ndarray, cps: Sequence[ControlPoint], opts: GeorefOptions) -> list[dict]:
    """Every pick's residual (px, and the point's distance from its ray in metres), its stated sigma (px) and
    whether it is an inlier (:func:`inlier_limits`)."""
    err, vec = central_errors(R, c, views, obs, X)
    sig = pick_sigmas(R, c, views, obs, X, cps, opts)
    residuals = []
    for k, o in enumerate(obs):
        v = views[o.view]
        d_world = R.T @ bear[k]
        residuals.append({"point": cps[o.point].name, "view": v.name, "uv": o.uv.tolist(),
                          "residual_px": vec[k].tolist() if np.isfinite(err[k]) else None,
                          "error_px": float(err[k]) if np.isfinite(err[k]) else None,
                          "error_m": point_line_distance(X[o.point], c, d_world),
                          "sigma_px": float(sig[k]) if np.isfinite(sig[k]) else None,
                          "inlier": bool(err[k] < (inlier_limit_px(sig[k], opts) if np.isfinite(sig[k])
                                                   else opts.ransac_threshold_px))})
    return residuals


def _covariance_stats(R: np.ndarray, cov: np.ndarray) -> dict:
    """1-sigma rotation (deg) and centre (m), and the covariance in the scene frame, for the solve to carry into
    the carriages' poses: the rotation was perturbed in the rig frame (rig_from_world <- Exp(x) rig_from_world),
    i.e. by -R^T x in the scene frame (world_from_rig = R^T <- R^T Exp(-x) = Exp(-R^T x) R^T, R =
    rig_from_world); order: rotation vector (rad), centre (m), ENU. The sign is that of the rotation's
    correlation with the centre (a camera shifted sideways is turned back towards the control points), which
    decides how much of the camera's error reaches a carriage near them."""
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    T = np.zeros((6, 6))
    T[:3, :3] = -R.T
    T[3:, 3:] = np.eye(3)
    cw = T @ cov @ T.T
    return {"sigma_rotation_deg": [float(np.degrees(x)) for x in sd[:3]],
            "sigma_centre_m": [float(x) for x in sd[3:]],
            "covariance_world_rotation_centre": (0.5 * (cw + cw.T)).tolist()}


def _too_few_points(where: str, n_pts: int, views: Sequence[RigView]) -> InputError:
    return InputError(f"{where}: {n_pts} control point(s) are picked in the photos {[v.name for v in views]}; "
                      f"placing the camera needs at least 3 (4 or more to check them), or 2 with the camera "
                      f"position known (camera.position_enu or GPS in the photos), or 1 with the GPS position and "
                      f"altitude and the photo's compass direction (EXIF GPSImgDirection, true north); add points "
                      f"to the file")


def _heading_stats(R: np.ndarray, views: Sequence[RigView], headings: Sequence[HeadingPrior]) -> list[dict]:
    """Each heading prior with the fitted azimuth and the residual (degrees)."""
    err = np.degrees(heading_errors(R, views, headings))
    return [{"view": h.view, "photo": h.photo or views[h.view].name, "prior_deg": float(h.azimuth_deg),
             "fitted_deg": float((h.azimuth_deg + e) % 360.0), "residual_deg": float(e),
             "sigma_deg": float(h.sigma_deg)} for h, e in zip(headings, err)]


def _too_few_with_track(where: str, n_pts: int) -> InputError:
    return InputError(f"{where}: track picks and {n_pts} control point(s) do not place the camera: points picked on "
                      f"a track that is straight, or curved at one radius and grade, look the same from anywhere "
                      f"along it, so the camera's place along the track is not fixed by them (docs/gis.md, \"Track "
                      f"picks\"); add a position prior (GPS in the photos, or camera.position_enu), or control "
                      f"points: {max(3 - n_pts, 1)} more (3 in all), or 2 with the prior")


def _track_start(bear, pts, X, views, obs, cps, prior_centre, sig_prior, headings, opts, rng, track):
    """With track picks, a centre prior and fewer than 3 points: at the prior's centre and 1 and 2 sigma above and
    below it, the rotations that fit the track picks best (and, with points, Kabsch on them), each refined briefly
    (40 evaluations); the lowest cost. Returns (R, centre, number of candidates)."""
    centres = prior_grid(prior_centre, sig_prior)[:5]
    cands = track_rotation_candidates(track, views, centres, keep=4)
    if len(pts):
        for c in centres:
            kab = start_candidates(bear, pts, X, 0, c, opts, rng, views, headings, n_pairs=0)
            if kab:
                cands.append(best_candidate(kab, views, obs, X, prior_centre, sig_prior, opts, headings, track))
    best, best_cost = cands[0], np.inf
    for R0, c0 in cands:
        info: dict = {}
        R1, c1, _ = _refine_central(views, obs, X, cps, R0, c0, np.ones(len(obs), bool), prior_centre, sig_prior,
                                    opts, headings, info_out=info, track=track, max_nfev=40)
        if info["cost"] < best_cost:
            best, best_cost = (R1, c1), info["cost"]
    return best[0], best[1], len(cands)


def _start(bear, pts, X, n_pts, views, obs, cps, prior_centre, sig_prior, headings, opts, rng, track, where):
    """The refinement's start (R, centre) and the number of candidates tried (RANSAC, then, with a prior and few
    points, the multi-start over the prior; with track picks and fewer than 3 points, :func:`_track_start`)."""
    if track is not None and prior_centre is not None and n_pts < 3:
        return _track_start(bear, pts, X, views, obs, cps, prior_centre, sig_prior, headings, opts, rng, track)
    candidates = start_candidates(bear, pts, X, n_pts, prior_centre, opts, rng, views, headings)
    if not candidates:
        raise InputError(f"{where}: the control points give no camera pose (degenerate geometry: are the points "
                         f"on one line, or all picked at the same place?); add points spread over the view")
    R0, c0 = best_candidate(candidates, views, obs, X, prior_centre, sig_prior, opts, headings, track)
    n_multi = 0
    if prior_centre is not None and n_pts <= opts.sample_max_points:
        grid_best, n_multi = _multi_start(bear, pts, X, views, obs, cps, prior_centre, sig_prior, headings, opts, rng,
                                          (R0, c0), track)
        if grid_best is not None:
            R0, c0 = grid_best
    return R0, c0, len(candidates) + n_multi


def solve_central(views: Sequence[RigView], cps: Sequence[ControlPoint], *, prior_centre: np.ndarray | None = None,
                  prior_sigma_m: np.ndarray | float | None = None, heading_priors: Sequence[HeadingPrior] = (),
                  opts: GeorefOptions = GeorefOptions(), where: str = "control_points.json",
                  track: TrackTerm | None = None) -> CentralResult:
    """Place a central rig (panorama or single photo) from control points and track picks; see the module
    docstring.

    ``prior_centre`` (3,) ENU metres with ``prior_sigma_m`` (scalar or (3,); ``inf`` leaves that axis free): a
    soft prior on the centre. ``heading_priors``: priors on the azimuth of a view's optical axis. ``track``: points
    picked on the railway line (:mod:`.track_picks`), residuals to the line as projected.
    Needs 3 control points (4 or more to be safe) seen in the photos, or 2 with a centre prior, or 1 with a
    centre prior on all three axes and a heading prior (6 equations for the 6 unknowns); with track picks, a
    centre prior or 2 control points (the track does not fix the camera's place along it).
    """
    obs = picks_in_views(cps, views, where)
    X = np.array([cp.enu for cp in cps], float).reshape(-1, 3)
    n_pts = len({o.point for o in obs})
    has_prior = prior_centre is not None
    headings = list(heading_priors)
    sig_prior = None
    if has_prior:
        sig_prior = np.broadcast_to(np.asarray(prior_sigma_m if prior_sigma_m is not None else opts.prior_sigma_m,
                                               float), (3,)).copy()
    n_fixed = (int(np.isfinite(sig_prior).sum()) if has_prior else 0) + len(headings)

    def enough(n: int) -> bool:  # n distinct points, with the priors (and the track), fix the 6 unknowns
        if track is not None and has_prior:
            return True
        return n >= 3 or (has_prior and n >= 1 and 2 * n + n_fixed >= 6)

    if not enough(n_pts):
        raise _too_few_with_track(where, n_pts) if track is not None else _too_few_points(where, n_pts, views)
    bear = np.array([views[o.view].cam_from_rig.T @ views[o.view].intrinsics.rays(o.uv[None])[0]
                     for o in obs]).reshape(-1, 3)
    pts = np.array([o.point for o in obs], int)
    rng = np.random.default_rng(opts.seed)
    thr = opts.ransac_threshold_px
    R0, c0_est, n_cand = _start(bear, pts, X, n_pts, views, obs, cps, prior_centre, sig_prior, headings, opts, rng,
                                track, where)
    err0, _ = central_errors(R0, c0_est, views, obs, X)
    inl = err0 < thr
    if inl.sum() < min(3, len(obs)) and not has_prior:
        raise InputError(f"{where}: no camera pose agrees with more than {int(inl.sum())} of the {len(obs)} picks "
                         f"(threshold {thr} px); check the point names, coordinates and pixels")
    R1, c1, _ = _refine_central(views, obs, X, cps, R0, c0_est, np.ones(len(obs), bool), prior_centre, sig_prior,
                                opts, headings, track=track)
    err1, _ = central_errors(R1, c1, views, obs, X)
    inl = err1 < inlier_limits(R1, c1, views, obs, X, cps, opts)
    t_inl = None if track is None else track_inliers(track, R1, c1, views, opts)
    sample_info: dict = {}
    info: dict = {}
    if enough(len(set(pts[inl].tolist()))):
        R1, c1, cov = _refine_central(views, obs, X, cps, R1, c1, inl, prior_centre, sig_prior, opts, headings,
                                      info_out=info, track=track, track_use=t_inl)
        # the sampled widening (few map points: a curved valley); with track picks the sandwich alone (measured:
        # scripts/bench_track_georef.py; docs/gis.md)
        if n_pts <= opts.sample_max_points and opts.sample_count > 0 and cov is not None \
                and np.all(np.isfinite(cov)) and track is None:
            cov, sample_info = _sample_covariance(views, obs, X, cps, R1, c1, inl, prior_centre, sig_prior, headings,
                                                  cov, opts)
        if cov is not None:  # the picks' misfit beyond their stated sigma widens the interval by as much
            cov = cov * info["variance_factor"]
            sample_info.update({k: info[k] for k in ("dof", "chi2_red", "variance_factor")})
    else:
        cov = None
    R1 = orthonormal(R1)
    residuals = _central_residuals(R1, c1, views, obs, X, bear, cps, opts)
    stats = summarize_residuals(residuals, opts)
    stats.update({"n_points": n_pts, "n_observations": len(obs), "prior": "yes" if has_prior else "no",
                  "ransac_candidates": n_cand})
    ok_cov = cov is not None and np.all(np.isfinite(cov))
    if ok_cov:
        stats.update(_covariance_stats(R1, cov))
    stats.update(sample_info)
    if has_prior:
        stats["centre_minus_prior_m"] = (c1 - np.asarray(prior_centre, float)).tolist()
    if headings:
        stats["heading_priors"] = _heading_stats(R1, views, headings)
    warns = warn_residuals(residuals, stats, opts, where)
    if track is not None:
        stats["track"] = track_fit_stats(track, R1, c1, views, opts, t_inl, info.get("J_track", np.zeros((0, 6))),
                                         cov[3:6, 3:6] if ok_cov else None, where, warns)
    return CentralResult(R1, c1, residuals, stats, warns)


def refine_resection_focal(intr: CameraIntrinsics, res: CentralResult, cps: Sequence[ControlPoint], name: str,
                           opts: GeorefOptions = GeorefOptions()) -> dict | None:
    """One photo's pose *and focal* (fx, fy scaled together; principal point and distortion kept) refined from
    its inlier control-point picks, starting from a fixed-focal resection ``res`` of that photo alone.

    Returns ``{"intrinsics", "cam_from_world" (4, 4), "focal_px", "sigma_focal_px", "sigma_centre_max_m",
    "covariance_world_rotation_centre" (6, 6: the pose's, the focal's doubt included; as
    :func:`_covariance_stats`), "covariance_pose_focal" (7, 7: the fit's parameters, the pose and the focal
    together), "rms_px", "n_observations"}`` or None (fewer than 6 inlier picks: the focal is not
    determined)."""
    obs = [(cps[k], np.asarray(cp_uv, float)) for k in range(len(cps)) for ph, cp_uv in cps[k].pixels.items()
           if ph == name]
    inl = {(r["point"], r["view"]) for r in res.residuals if r.get("inlier")}
    obs = [(cp, uv) for cp, uv in obs if (cp.name, name) in inl]
    if len(obs) < 6:
        return None
    X = np.array([cp.enu for cp, _ in obs])
    UV = np.array([uv for _, uv in obs])
    R0, c0 = res.rig_from_world, res.centre_enu
    depth = np.maximum((X - c0) @ R0.T, 1e-3)[:, 2]
    sig = np.array([pick_sigma(intr, opts.sigma_px, cp.sigma_m, d) for (cp, _), d in zip(obs, depth)])
    base = intr.to_dict()

    def intr_of(logf):
        k = math.exp(logf)
        return CameraIntrinsics.from_dict({**base, "fx": intr.fx * k, "fy": intr.fy * k})

    def fun(p):
        R = exp_so3(p[:3]) @ R0
        q = (X - p[3:6]) @ R.T
        z = np.maximum(q[:, 2], 1e-6)
        it = intr_of(p[6])
        uv = it.pixels_from_normalized(it.distort(q[:, :2] / z[:, None]))
        return ((uv - UV) / sig[:, None]).ravel()

    sol = least_squares(fun, np.concatenate([np.zeros(3), c0, [0.0]]), loss=opts.loss, f_scale=opts.loss_scale,
                        x_scale="jac", max_nfev=300)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac)
    except np.linalg.LinAlgError:
        return None
    dof = len(sol.fun) - 7
    cov *= variance_factor(sol.cost, float(np.sum(sol.fun ** 2) / dof) if dof > 0 else float("nan"), dof, opts,
                           narrow=False)  # as the fixed-focal fit's
    if not np.all(np.isfinite(cov)):
        return None
    R = orthonormal(exp_so3(sol.x[:3]) @ R0)
    c = sol.x[3:6]
    it = intr_of(sol.x[6])
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, -R @ c
    q = (X - c) @ R.T
    e = np.hypot(*(it.project(q) - UV).T)
    Cc = cov[3:6, 3:6]
    return {"intrinsics": it, "cam_from_world": M, "focal_px": float(it.fx),
            "sigma_focal_px": float(it.fx * math.sqrt(max(cov[6, 6], 0.0))),
            "sigma_centre_max_m": float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (Cc + Cc.T)).max(), 0.0))),
            "covariance_world_rotation_centre": _covariance_stats(R, cov[:6, :6])["covariance_world_rotation_centre"],
            "covariance_pose_focal": cov,  # (7, 7): rotation on the left of cam_from_world, centre, log focal
            "rms_px": float(np.sqrt(np.mean(e ** 2))), "n_observations": len(obs)}
