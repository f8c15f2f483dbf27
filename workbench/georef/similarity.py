"""Placing an SfM model (its own frame, arbitrary scale) by a similarity ``world_from_model`` (scale, rotation,
translation) from control points triangulated in the model and/or SfM camera centres with GPS.

Start: Umeyama on triples (RANSAC); refinement: reprojection error of every control-point pixel (single-view
points count too) plus the GPS centres in metres, robust loss (docs/gis.md).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares

from ..core.geometry import exp_so3, skew
from ..errors import InputError
from ..files.control_points import ControlPoint
from .fitting import orthonormal, point_line_distance, triangulate_rays, umeyama
from ..files.reconstruction import SfmView
from .options import GeorefOptions
from .picks import (Pick, inlier_limit_px, pick_sigma, picks_in_views, shared_point_information,
                    summarize_residuals, warn_residuals)

log = logging.getLogger(__name__)

__all__ = ["SimilarityResult", "solve_similarity", "model_centre"]


@dataclass
class SimilarityResult:
    """``world_from_model``: ``p_world = scale * R @ p_model + t``; residuals and statistics."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    residuals: list[dict]
    stats: dict
    warnings: list[str]
    # (7, 7) covariance of (log scale, rotation vector applied on the left in the scene frame, translation): the
    # sandwich in which a control point's survey error is shared by its picks in every photo, scaled by the reduced
    # chi-square when above 1; None when the fit leaves it undetermined
    covariance: np.ndarray | None = None
    triangulated: dict[str, np.ndarray] = field(default_factory=dict)  # control point -> (3,) model frame
    # (7, r) the fit's response (the order of ``covariance``) to the SfM poses' own error ``z`` (each view's
    # ``pose_factor``, z ~ N(0, I_r) shared by the model's views): the control points and GPS centres seen through
    # the erring poses pull the similarity with them (:func:`sfm_sensitivity`); None when SfM stated no factor
    sfm_sensitivity: np.ndarray | None = None

    def centre_sigma_m(self, cam_from_model: np.ndarray) -> float | None:
        """1-sigma (square root of the largest eigenvalue, metres) of an SfM camera's centre in the scene, from
        the similarity's covariance (the model's own uncertainty not included)."""
        if self.covariance is None:
            return None
        q = self.scale * self.rotation @ model_centre(cam_from_model)  # world centre minus translation
        J = np.hstack([q[:, None], -skew(q), np.eye(3)])
        C = J @ self.covariance @ J.T
        return float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (C + C.T)).max(), 0.0)))

    def view_jacobian(self, cam_from_model: np.ndarray) -> np.ndarray:
        """(6, 7) first-order map from an error of the similarity (the order of ``covariance``: log scale,
        rotation vector on the left in the scene frame, translation) to the error of an SfM camera's scene pose
        placed by it: the scene rotation vector of ``world_from_cam`` (rad) and the centre (m, ENU), the
        parametrisation of ``georegistration.covariance_world_rotation_centre`` (docs/formats.md).

        The similarity moves every scene point ``p`` by ``dl (p - t) + dtheta x (p - t) + dt``; a camera turns by
        ``dtheta`` and its centre ``c`` moves as a point: ``[[0, I, 0], [c - t, -[c - t]x, I]]``."""
        d = self.scale * self.rotation @ model_centre(cam_from_model)  # centre minus translation, scene frame
        J = np.zeros((6, 7))
        J[:3, 1:4] = np.eye(3)
        J[3:, 0] = d
        J[3:, 1:4] = -skew(d)
        J[3:, 4:7] = np.eye(3)
        return J

    def view_covariance(self, cam_from_model: np.ndarray) -> np.ndarray | None:
        """(6, 6) covariance of an SfM camera's scene pose (rotation vector, centre) from the similarity's alone
        (:meth:`view_jacobian`; the SfM pose's own error not included); None when the fit leaves it undetermined."""
        if self.covariance is None:
            return None
        J = self.view_jacobian(cam_from_model)
        C = J @ self.covariance @ J.T
        return 0.5 * (C + C.T)

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) similarity ``world_from_model`` (scale in the upper-left block)."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.rotation
        M[:3, 3] = self.translation
        return M

    def apply(self, p_model: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(p_model, float) @ self.rotation.T + self.translation

    def cam_from_world(self, cam_from_model: np.ndarray) -> np.ndarray:
        """(4, 4) rigid, metric ``cam_from_world`` of an SfM camera."""
        M = np.asarray(cam_from_model, float)
        Rc, tc = M[:3, :3], M[:3, 3]
        R = Rc @ self.rotation.T
        out = np.eye(4)
        out[:3, :3] = R
        out[:3, 3] = self.scale * tc - R @ self.translation
        return out


def model_centre(cam_from_model: np.ndarray) -> np.ndarray:
    """The camera centre (3,) in the model frame of a ``cam_from_model`` (4, 4)."""
    M = np.asarray(cam_from_model, float)
    return -M[:3, :3].T @ M[:3, 3]


def _triangulate_point(lst: list[Pick], views: Sequence[SfmView], opts: GeorefOptions) -> tuple[np.ndarray, float,
                                                                                                  float]:
    """A control point's rays intersected in the model frame: (point, angle deg, worst reprojection error px);
    a ray from a wrongly posed photo (or a wrong pick) is dropped while 3 or more remain."""
    cs, ds = [], []
    for o in lst:
        v = views[o.view]
        M = np.asarray(v.cam_from_model, float)
        cs.append(model_centre(v.cam_from_model))
        ds.append(M[:3, :3].T @ v.intrinsics.rays(o.uv[None])[0])
    cs_a, ds_a = np.array(cs), np.array(ds)
    use = list(range(len(lst)))
    while True:
        Xm, angle = triangulate_rays(cs_a[use], ds_a[use])
        errs = []
        for i in use:
            M = np.asarray(views[lst[i].view].cam_from_model, float)
            q = M[:3, :3] @ Xm + M[:3, 3]
            errs.append(float(np.hypot(*(views[lst[i].view].intrinsics.project(q[None])[0] - lst[i].uv)))
                        if q[2] > 1e-9 else np.inf)
        worst = int(np.argmax(errs))
        if errs[worst] <= opts.ransac_threshold_px or len(use) <= 2:
            break
        use.pop(worst)
    return Xm, angle, errs[worst]


def _triangulate_control_points(obs: list[Pick], views: Sequence[SfmView], cps: Sequence[ControlPoint],
                                opts: GeorefOptions, where: str) -> tuple[dict[int, list[Pick]], dict[int, np.ndarray]]:
    """The picks per point, and the control points seen in two or more photos whose rays meet, triangulated in
    the model frame (point index -> (3,), in point order)."""
    by_point: dict[int, list[Pick]] = {}
    for o in obs:
        by_point.setdefault(o.point, []).append(o)
    tri_model: dict[int, np.ndarray] = {}
    for k, lst in sorted(by_point.items()):
        if len({o.view for o in lst}) < 2:
            continue
        Xm, angle, worst = _triangulate_point(lst, views, opts)
        if worst > opts.ransac_threshold_px:
            log.info("%s: control point %s: its rays do not meet (%.1f px apart); not triangulated", where,
                     cps[k].name, worst)
            continue
        if angle < opts.min_triangulation_angle_deg:
            log.info("%s: control point %s: rays meet at %.2f deg; not triangulated", where, cps[k].name, angle)
            continue
        tri_model[k] = Xm
    return by_point, tri_model


def _robust_start(src_a: np.ndarray, dst_a: np.ndarray, sig_a: np.ndarray,
                  opts: GeorefOptions) -> tuple[float, np.ndarray, np.ndarray]:
    """Weighted Umeyama on every correspondence; with 4 or more, RANSAC on triples and Umeyama on the inliers."""
    rng = np.random.default_rng(opts.seed)
    w = 1.0 / sig_a ** 2
    best = umeyama(src_a, dst_a, w)
    if len(src_a) < 4:
        return best

    def n_in(s, R, t):
        d = np.linalg.norm(s * src_a @ R.T + t - dst_a, axis=1)
        return int(np.sum(d < 3.0 * sig_a + 0.05)), float(np.sum(np.minimum(d / (3 * sig_a + 0.05), 1.0)))

    bs = n_in(*best)
    for _ in range(min(opts.ransac_iterations, 200)):
        idx = rng.choice(len(src_a), 3, replace=False)
        if np.linalg.svd(dst_a[idx] - dst_a[idx].mean(axis=0), compute_uv=False)[1] < 1e-3:
            continue
        cand = umeyama(src_a[idx], dst_a[idx])
        sc = n_in(*cand)
        if sc[0] > bs[0] or (sc[0] == bs[0] and sc[1] < bs[1]):
            best, bs = cand, sc
    d = np.linalg.norm(best[0] * src_a @ best[1].T + best[2] - dst_a, axis=1)
    inl = d < 3.0 * sig_a + 0.05
    if inl.sum() >= 3:
        best = umeyama(src_a[inl], dst_a[inl], w[inl])
    return best


def _pick_sigmas(sim: tuple[float, np.ndarray, np.ndarray], obs: list[Pick], views: Sequence[SfmView],
                 X: np.ndarray, cps: Sequence[ControlPoint], opts: GeorefOptions) -> list[float]:
    """Each pick's stated sigma (px, :func:`pick_sigma`) at its point's depth in its camera placed by ``sim`` =
    (s, R, t): the weights the refinement and its sensitivity share."""
    s0, R0, t0 = sim
    out = []
    for o in obs:
        v = views[o.view]
        Mv = np.asarray(v.cam_from_model, float)
        depth = float((Mv[:3, :3] @ (R0.T @ (X[o.point] - t0) / s0) + Mv[:3, 3])[2]) * s0
        out.append(pick_sigma(v.intrinsics, opts.sigma_px, cps[o.point].sigma_m, abs(depth)))
    return out


def _refine_similarity(start: tuple[float, np.ndarray, np.ndarray], obs: list[Pick], views: Sequence[SfmView],
                       X: np.ndarray, cps: Sequence[ControlPoint], gps_items: list[tuple[SfmView, np.ndarray]],
                       opts: GeorefOptions):
    """(s, R, t, covariance (7, 7) or None) refined on every pick's pixels and the GPS centres (metres). Each pick
    is weighted by its own noise and its point's survey error seen at its depth (:func:`pick_sigma`); the
    covariance counts that survey error once per point, however many photos the point is picked in (the sandwich
    ``H^-1 G H^-1``, :func:`shared_point_information`), the GPS centres' errors independent."""
    s0, R0, t0 = start
    gsig = np.asarray(opts.gps_sigma_m, float)

    def sim_from(p):
        return s0 * math.exp(p[0]), exp_so3(p[1:4]) @ R0, t0 + p[4:7]

    obs_sig = _pick_sigmas(start, obs, views, X, cps, opts)

    def fun(p):
        return _weighted_residuals(sim_from(p), obs, obs_sig, views, X, gps_items, gsig)

    sol = least_squares(fun, np.zeros(7), loss=opts.loss, f_scale=opts.loss_scale, x_scale="jac", max_nfev=300)
    s, R, t = sim_from(sol.x)
    R = orthonormal(R)
    cov = None
    dof = len(sol.fun) - 7
    try:
        J = np.asarray(sol.jac, float)
        n = len(obs)  # the sandwich H^-1 G H^-1: a control point's survey error is one error shared by its picks
        sig = np.asarray(obs_sig, float)
        # a pick's residual depends on the point less the translation, so its Jacobian in the point is minus t's
        G = J[2 * n:].T @ J[2 * n:] + shared_point_information(
            J[:2 * n], np.array([o.point for o in obs], int), np.tile([4, 5, 6], (n, 1)),
            (opts.sigma_px / sig) ** 2, np.array([cps[o.point].sigma_m for o in obs], float))
        Hi = np.linalg.inv(J.T @ J)
        cov = Hi @ G @ Hi
        cov = 0.5 * (cov + cov.T)
        if dof > 0:
            cov *= max(1.0, 2.0 * float(sol.cost) / dof)
        if not np.all(np.isfinite(cov)):
            cov = None
    except np.linalg.LinAlgError:
        cov = None
    if cov is not None:  # d(log s), d(rotvec), d(t) of the parametrisation at the solution
        cov = cov.copy()
    return s, R, t, cov


def _weighted_residuals(sim: tuple[float, np.ndarray, np.ndarray], obs: list[Pick], obs_sig: list[float],
                        views: Sequence[SfmView], X: np.ndarray, gps_items: list[tuple[SfmView, np.ndarray]],
                        gsig: np.ndarray) -> np.ndarray:
    """The refinement's residuals at the similarity ``sim`` = (s, R, t): every pick's pixel error over its sigma
    (2 per pick), then every GPS centre's error over its sigma (3 per centre)."""
    s, R, t = sim
    res = np.zeros((len(obs), 2))
    if obs:
        pts = np.array([o.point for o in obs], int)
        in_view = np.array([o.view for o in obs], int)
        Xm = (X[pts] - t) @ R / s  # R^T (X - t) / s per row: the points in the model frame
        for i in np.unique(in_view):  # each photo's picks projected at once
            k = np.nonzero(in_view == i)[0]
            v = views[i]
            M = np.asarray(v.cam_from_model, float)
            q = Xm[k] @ M[:3, :3].T + M[:3, 3]
            z = np.where(q[:, 2] > 1e-9, q[:, 2], 1e-9)
            uv = v.intrinsics.pixel_coords(*v.intrinsics.distort(q[:, :2] / z[:, None]).T)
            res[k] = (np.column_stack(uv) - np.array([obs[j].uv for j in k])) / np.asarray(obs_sig)[k, None]
    out = [res.ravel()]
    for v, g in gps_items:
        out.append((s * R @ model_centre(v.cam_from_model) + t - g) / gsig)
    return np.concatenate(out)


def _moved_view(v: SfmView, z: np.ndarray) -> SfmView:
    """``v`` moved by the SfM error ``z`` (r,) of its model: its pose by ``pose_factor @ z`` (the rotation vector of
    ``model_from_cam`` applied on the left (rad, model frame), then the centre (model units)) and its intrinsics by
    ``intrinsics_factor @ z`` where the file states them."""
    d = np.asarray(v.pose_factor, float) @ z
    M = np.asarray(v.cam_from_model, float)
    R = M[:3, :3] @ exp_so3(-d[:3])  # model_from_cam' = Exp(d) model_from_cam
    out = np.eye(4)
    out[:3, :3] = R
    out[:3, 3] = -R @ (model_centre(M) + d[3:])
    intr = v.intrinsics
    if v.intrinsics_factor is not None:
        intr = intr.moved(v.intrinsics_params, np.asarray(v.intrinsics_factor, float) @ z)
    return replace(v, cam_from_model=out, intrinsics=intr)


_LOSS_WEIGHT = {  # sqrt(rho'(z)), z the squared residual over the loss scale squared (scipy's losses)
    "linear": lambda z: np.ones_like(z),
    "huber": lambda z: np.where(z <= 1.0, 1.0, z ** -0.25),
    "soft_l1": lambda z: (1.0 + z) ** -0.25,
    "cauchy": lambda z: (1.0 + z) ** -0.5,
    "arctan": lambda z: (1.0 + z ** 2) ** -0.5,
}


def sfm_sensitivity(sim: tuple[float, np.ndarray, np.ndarray], obs: list[Pick], views: Sequence[SfmView],
                    X: np.ndarray, cps: Sequence[ControlPoint], gps_centres: dict[str, np.ndarray],
                    opts: GeorefOptions, h: float = 1e-3) -> np.ndarray | None:
    """(7, r) the refined similarity's first-order response to the SfM model's own error ``z`` (``pose_factor``
    (6, r) of every view and, where stated, its ``intrinsics_factor``; z ~ N(0, I_r) shared by the model's views):
    ``dp = -(J^T W J)^-1 J^T W dr/dz``, with ``J`` the refinement's residuals' Jacobian in its 7 parameters (log
    scale, rotation vector on the left in the scene frame, translation), ``W`` its robust loss's weights at the
    solution, and ``dr/dz`` the residuals' change when the views' poses and intrinsics move along each factor
    column (central differences, ``h`` in units of z).

    Why it matters: the similarity is fitted to the control points (and GPS centres) *seen through the SfM
    poses*; where a pose errs, the fit follows, so a view's scene pose error is ``jacobian @ (dp_picks + S z) +
    T F z``, not ``jacobian @ dp_picks + T F z``. Near the control points the two SfM terms largely cancel (the
    fit puts the model where its control points are), which is what the carriages among them see. None when a
    view has no factor or the fit has no residuals."""
    if not views or any(v.pose_factor is None for v in views) or (not obs and not gps_centres):
        return None
    F = [np.asarray(v.pose_factor, float) for v in views]
    r = F[0].shape[1]
    if any(f.shape != (6, r) for f in F):
        return None
    s0, R0, t0 = sim
    gsig = np.asarray(opts.gps_sigma_m, float)
    by_name = {v.name: i for i, v in enumerate(views)}
    gps_idx = [(by_name[n], np.asarray(g, float)) for n, g in sorted(gps_centres.items()) if n in by_name]
    obs_sig = _pick_sigmas(sim, obs, views, X, cps, opts)

    def resid(p: np.ndarray, vs: Sequence[SfmView]) -> np.ndarray:
        sim_p = (s0 * math.exp(p[0]), exp_so3(p[1:4]) @ R0, t0 + p[4:7])
        return _weighted_residuals(sim_p, obs, obs_sig, vs, X, [(vs[i], g) for i, g in gps_idx], gsig)

    r0 = resid(np.zeros(7), views)
    w = _LOSS_WEIGHT.get(opts.loss, _LOSS_WEIGHT["linear"])((r0 / opts.loss_scale) ** 2)
    J = np.zeros((len(r0), 7))
    for j in range(7):
        e = np.zeros(7)
        e[j] = 1e-6
        J[:, j] = (resid(e, views) - resid(-e, views)) / (2 * e[j])
    Jz = np.zeros((len(r0), r))
    for j in range(r):
        e = np.zeros(r)
        e[j] = h
        up = [_moved_view(v, e) for v in views]
        dn = [_moved_view(v, -e) for v in views]
        Jz[:, j] = (resid(np.zeros(7), up) - resid(np.zeros(7), dn)) / (2 * h)
    A = J * w[:, None]
    if np.linalg.matrix_rank(A) < 7:
        return None
    return -np.linalg.lstsq(A, Jz * w[:, None], rcond=None)[0]


def _similarity_residuals(result: SimilarityResult, obs: list[Pick], views: Sequence[SfmView], X: np.ndarray,
                          cps: Sequence[ControlPoint], tri_model: dict[int, np.ndarray],
                          opts: GeorefOptions) -> list[dict]:
    """Every pick's residual (px; the known point's distance from the observed ray, m; the triangulated point's
    distance from the known one, m), its stated sigma (px: :func:`pick_sigma` at its depth) and whether it is an
    inlier (:func:`inlier_limit_px`)."""
    residuals = []
    for o in obs:
        v = views[o.view]
        Mw = result.cam_from_world(v.cam_from_model)
        q = Mw[:3, :3] @ X[o.point] + Mw[:3, 3]
        if q[2] > 1e-6:
            vec = v.intrinsics.project(q[None])[0] - o.uv
            e_px = float(np.hypot(*vec))
            sig = pick_sigma(v.intrinsics, opts.sigma_px, cps[o.point].sigma_m, float(q[2]))
        else:
            vec, e_px, sig = None, None, None
        c_w = -Mw[:3, :3].T @ Mw[:3, 3]
        d_w = Mw[:3, :3].T @ v.intrinsics.rays(o.uv[None])[0]
        e_m = point_line_distance(X[o.point], c_w, d_w)  # the known point's distance from the observed ray
        tri_m = float(np.linalg.norm(result.apply(tri_model[o.point]) - X[o.point])) if o.point in tri_model else None
        residuals.append({"point": cps[o.point].name, "view": v.name, "uv": o.uv.tolist(),
                          "residual_px": None if vec is None else vec.tolist(), "error_px": e_px, "error_m": e_m,
                          "triangulated_error_m": tri_m, "sigma_px": sig,
                          "inlier": e_px is not None and e_px < inlier_limit_px(sig, opts)})
    return residuals


def solve_similarity(views: Sequence[SfmView], cps: Sequence[ControlPoint], *,
                     gps_centres: dict[str, np.ndarray] | None = None, opts: GeorefOptions = GeorefOptions(),
                     where: str = "control_points.json") -> SimilarityResult:
    """``world_from_model`` of an SfM model from control points and/or GPS camera centres (module docstring).

    ``gps_centres``: photo name -> (3,) ENU metres of the camera centre (EXIF GPS), 1-sigma ``opts.gps_sigma_m``.
    """
    obs = picks_in_views(cps, views, where) if cps else []
    gps_centres = dict(gps_centres or {})
    X = np.array([cp.enu for cp in cps], float).reshape(-1, 3)
    by_point, tri_model = _triangulate_control_points(obs, views, cps, opts, where)
    src = list(tri_model.values())
    dst = [X[k] for k in tri_model]
    sig = [max(cps[k].sigma_m, 0.01) for k in tri_model]
    gsig = np.asarray(opts.gps_sigma_m, float)
    name_to_view = {v.name: v for v in views}
    for name, g in sorted(gps_centres.items()):  # camera centres with GPS
        if name in name_to_view:
            src.append(model_centre(name_to_view[name].cam_from_model))
            dst.append(np.asarray(g, float))
            sig.append(float(np.mean(gsig)))
    if len(src) < 3:
        raise InputError(f"{where}: {len(src)} correspondence(s) between the SfM model and the scene (control points "
                         f"picked in two or more photos: {len(tri_model)}, photos with GPS: {len(gps_centres)}); the "
                         f"similarity needs at least 3 not on one line; pick each control point in two or more "
                         f"photos, or add points")
    src_a, dst_a, sig_a = np.array(src), np.array(dst), np.array(sig)
    spread = np.linalg.svd(dst_a - dst_a.mean(axis=0), compute_uv=False)
    if spread[1] < 1e-3 * max(spread[0], 1e-9):
        raise InputError(f"{where}: the {len(src)} correspondences lie on one line; the rotation about it is unknown; "
                         f"add a control point off that line")
    gps_items = [(name_to_view[n], np.asarray(g, float)) for n, g in sorted(gps_centres.items()) if n in name_to_view]
    s, R, t, cov = _refine_similarity(_robust_start(src_a, dst_a, sig_a, opts), obs, views, X, cps, gps_items, opts)
    result = SimilarityResult(s, R, t, [], {}, [], covariance=cov,
                              triangulated={cps[k].name: Xm for k, Xm in tri_model.items()},
                              sfm_sensitivity=sfm_sensitivity((s, R, t), obs, views, X, cps, gps_centres, opts))
    residuals = _similarity_residuals(result, obs, views, X, cps, tri_model, opts)
    gps_res = {v.name: (result.apply(model_centre(v.cam_from_model)) - g).tolist() for v, g in gps_items}
    stats = summarize_residuals(residuals, opts)
    stats.update({"n_points": len(by_point), "n_triangulated": len(tri_model), "n_observations": len(obs),
                  "n_gps_centres": len(gps_items), "scale": s, "gps_residuals_m": gps_res,
                  "gps_rms_m": float(np.sqrt(np.mean([np.sum(np.square(r)) for r in gps_res.values()])))
                  if gps_res else None})
    warns = warn_residuals(residuals, stats, opts, where, n_params=7) if residuals else []
    result.residuals, result.stats, result.warnings = residuals, stats, warns
    return result
