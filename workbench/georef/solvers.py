"""Camera georegistration solvers: place cameras in the scene frame from ground control points.

Two problems, both robust (RANSAC for the start, a robust loss in the refinement) and both reporting every
control point's residual in pixels and metres:

* :func:`solve_central` -- a *central* rig: one projection centre, several photos that only turned (a
  panorama, its frame ``pano`` = ``rig``), or a single photo (``rig`` = the camera). Unknowns: ``rig_from_world``
  (rotation) and the centre (3). Start: P3P (OpenCV) on the control-point rays in the rig frame, each triple
  seen through a virtual pinhole looking along their mean direction; with a centre prior (``camera.position_enu``
  or EXIF GPS) also the rotation that best aligns the rays with the directions to the points (Kabsch).
  Refinement: reprojection error in every source photo (its own intrinsics and distortion), each residual
  divided by ``sqrt(sigma_px^2 + (f sigma_m / depth)^2)``, plus the prior.
* :func:`solve_similarity` -- an SfM model in its own frame (arbitrary scale): ``world_from_model``
  (scale, rotation, translation) from control points triangulated in the model and/or SfM camera centres
  with GPS. Start: Umeyama on triples (RANSAC); refinement: reprojection error of every control-point pixel
  (single-view points count too) plus the GPS centres in metres.

Frames and names follow docs/conventions.md: ``cam_from_rig`` (3, 3) rotations, ``cam_from_model`` (4, 4),
``p_b = b_from_a @ p_a``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..core.camera import CameraIntrinsics
from ..core.geometry import skew
from ..errors import InputError, WorkbenchWarning
from .control_points import ControlPoint

log = logging.getLogger(__name__)

__all__ = ["GeorefOptions", "RigView", "SfmView", "CentralResult", "SimilarityResult", "GeorefResidualsLarge",
           "solve_central", "solve_similarity", "umeyama", "triangulate_rays", "refine_resection_focal"]

_LOSSES = ("linear", "huber", "soft_l1", "cauchy")


class GeorefResidualsLarge(WorkbenchWarning):
    """Control-point residuals after georegistration are larger than expected: a point or a pick is wrong."""


@dataclass(frozen=True, kw_only=True)
class GeorefOptions:
    """Options of the georegistration solvers (units in the names)."""

    sigma_px: float = 1.0  # a priori pixel noise of a pick
    loss: str = "soft_l1"  # robust loss of the refinement (scipy least_squares)
    loss_scale: float = 3.0  # in units of the residuals' sigma
    ransac_threshold_px: float = 12.0  # an observation is an inlier below this reprojection error
    ransac_iterations: int = 400
    prior_sigma_m: float = 1.0  # camera.position_enu
    gps_sigma_m: tuple[float, float, float] = (5.0, 5.0, 10.0)  # EXIF GPS, east/north/up 1-sigma
    warn_rms_px: float = 3.0
    warn_point_px: float = 6.0
    warn_point_m: float = 0.5
    min_triangulation_angle_deg: float = 2.0
    seed: int = 0
    # a separate SfM model (photos SfM could not join to the main model) is placed only when its own control
    # points fix it: this many triangulated in it and fitting (all their picks inliers), spread this far from
    # the line through them (RMS, metres), an RMS pick residual within ``warn_rms_px``, at most this fraction of
    # its picks outliers, and every camera centre within this 1-sigma (from the fit's covariance, metres)
    model_min_points: int = 3
    # a photo in no placed model (SfM left it out, or its model could not be placed) is placed on its own from
    # its control points (resection, as the single-photo route) when ``resect_unplaced``, it has picks of this
    # many points, and the same residual and 1-sigma checks pass; intrinsics: SfM's for that photo, else the
    # main model's camera when all photos share one (``single_camera``) and the photo has its size
    resect_unplaced: bool = True
    # leave out of a placed SfM model every photo whose own picks mostly disagree with it (2 or more, and more
    # than half, beyond ``ransac_threshold_px``): SfM placed it wrongly
    reject_disagreeing_views: bool = True
    resect_min_points: int = 4
    # with 6 or more fitting picks the photo's focal is refined too (fx, fy scaled together): when it differs
    # from SfM's by more than this many sigma, the photo takes the refined focal (and the 1-sigma check then
    # counts the focal's uncertainty)
    resect_focal_disagree_sigma: float = 2.0
    # multiview: the photos sharing one SfM camera adjusted together with its intrinsics (focal, principal point,
    # k1) from their picks; their stated uncertainty then counts the intrinsics' (docs/gis.md)
    adjust_camera: bool = True
    # its covariance is scaled by the reduced chi-square when above 1, and also when below with this many
    # degrees of freedom or more
    variance_factor_min_dof: int = 50
    model_min_spread_m: float = 1.0
    model_max_outlier_fraction: float = 0.25
    model_max_sigma_centre_m: float = 0.5

    def __post_init__(self) -> None:
        if self.loss not in _LOSSES:
            raise ValueError(f"loss={self.loss!r}; choose one of {_LOSSES}")
        if not (isinstance(self.model_min_points, int) and self.model_min_points >= 3):
            raise ValueError(f"model_min_points={self.model_min_points} must be an integer >= 3")
        if not (isinstance(self.resect_min_points, int) and self.resect_min_points >= 3):
            raise ValueError(f"resect_min_points={self.resect_min_points} must be an integer >= 3")
        if not (0.0 <= self.model_max_outlier_fraction < 1.0):
            raise ValueError(f"model_max_outlier_fraction={self.model_max_outlier_fraction} must be in [0, 1)")
        for name in ("sigma_px", "loss_scale", "ransac_threshold_px", "prior_sigma_m", "warn_rms_px",
                     "warn_point_px", "warn_point_m", "model_min_spread_m", "model_max_sigma_centre_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}={getattr(self, name)} must be positive")


@dataclass(frozen=True)
class RigView:
    """A photo of a central rig: its name, intrinsics and ``cam_from_rig`` rotation (3, 3)."""

    name: str
    intrinsics: CameraIntrinsics
    cam_from_rig: np.ndarray = field(default_factory=lambda: np.eye(3))


@dataclass(frozen=True)
class SfmView:
    """A photo of an SfM model: its name, intrinsics and ``cam_from_model`` (4, 4), model units."""

    name: str
    intrinsics: CameraIntrinsics
    cam_from_model: np.ndarray


@dataclass
class _Obs:
    point: int  # index into the control points
    view: int  # index into the views
    uv: np.ndarray  # (2,) pixels


def _observations(cps: Sequence[ControlPoint], views: Sequence, where: str) -> list[_Obs]:
    """Every pick of a control point in one of ``views``; pixels outside a photo are an error."""
    by_name = {v.name: i for i, v in enumerate(views)}
    obs: list[_Obs] = []
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
            obs.append(_Obs(k, i, np.asarray(uv, float)))
    if ignored:
        log.info("%s: pixels in photo(s) %s are not used by this route (its photos: %s)", where, sorted(ignored),
                 sorted(by_name))
    return obs


def _rotation_kabsch(a: np.ndarray, b: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Rotation R (3, 3) minimising sum w |R a_k - b_k|^2 for (n, 3) vectors a, b."""
    w = np.ones(len(a)) if w is None else w
    H = (a * w[:, None]).T @ b
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    return Vt.T @ D @ U.T


def umeyama(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) with ``dst ~ s R src + t`` for (n, 3) points (weighted Umeyama 1991)."""
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    w = np.ones(len(src)) if w is None else np.asarray(w, float)
    w = w / w.sum()
    ms, md = w @ src, w @ dst
    xs, xd = src - ms, dst - md
    cov = (xd * w[:, None]).T @ xs
    U, S, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    D = np.diag([1.0, 1.0, d])
    R = U @ D @ Vt
    var = float(w @ np.sum(xs * xs, axis=1))
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    t = md - s * R @ ms
    return s, R, t


def triangulate_rays(centres: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares intersection of rays (n, 3) centres, (n, 3) unit directions -> (point (3,), max angle deg)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centres, dirs):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    X = np.linalg.lstsq(A, b, rcond=None)[0]
    cosines = np.clip(dirs @ dirs.T, -1.0, 1.0)
    return X, float(np.degrees(np.arccos(cosines.min())))


def _robust_sigma(intr: CameraIntrinsics, sigma_px: float, sigma_m: float, depth_m: float) -> float:
    f = 0.5 * (intr.fx + intr.fy)
    return math.sqrt(sigma_px ** 2 + (f * sigma_m / max(depth_m, 1e-3)) ** 2)


def _point_line_distance(X: np.ndarray, c: np.ndarray, d: np.ndarray) -> float:
    v = X - c
    return float(np.linalg.norm(v - (v @ d) * d))


# ----------------------------------------------------------------------------------------------------------
# Central rig (panorama or single photo)
# ----------------------------------------------------------------------------------------------------------
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


def _p3p_candidates(bearings: np.ndarray, X: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(rig_from_world R, centre)`` candidates from 3 bearings (3, 3) in the rig frame and 3 world points."""
    import cv2

    m = bearings.sum(axis=0)
    if np.linalg.norm(m) < 1e-6:
        return []
    z = m / np.linalg.norm(m)
    x = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    Q = np.vstack([x, y, z])  # virtual_from_rig
    b = bearings @ Q.T
    if np.any(b[:, 2] <= 1e-3):
        return []
    img = np.ascontiguousarray(b[:, :2] / b[:, 2:3])
    try:
        n, rvecs, tvecs = cv2.solveP3P(np.ascontiguousarray(X, dtype=np.float64), img, np.eye(3), None,
                                       flags=cv2.SOLVEPNP_P3P)
    except cv2.error:
        return []
    out = []
    for rv, tv in zip(rvecs or [], tvecs or []):
        Rv = cv2.Rodrigues(np.asarray(rv, float))[0]
        R = Q.T @ Rv
        t = Q.T @ np.asarray(tv, float).reshape(3)
        out.append((R, -R.T @ t))
    return out


def _central_errors(R: np.ndarray, c: np.ndarray, views: Sequence[RigView], obs: list[_Obs],
                    X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection errors (n,) px (inf when behind) and the residual vectors (n, 2) of every observation."""
    err = np.full(len(obs), np.inf)
    vec = np.full((len(obs), 2), np.nan)
    vi = np.array([o.view for o in obs])
    P = (X[[o.point for o in obs]] - c) @ R.T  # rig frame
    UV = np.array([o.uv for o in obs]).reshape(-1, 2)
    for i in np.unique(vi):
        k = np.nonzero(vi == i)[0]
        v = views[i]
        q = P[k] @ np.asarray(v.cam_from_rig, float).T
        front = q[:, 2] > 1e-6
        if not front.any():
            continue
        kk = k[front]
        vec[kk] = v.intrinsics.project(q[front]) - UV[kk]
        err[kk] = np.hypot(vec[kk, 0], vec[kk, 1])
    return err, vec


def solve_central(views: Sequence[RigView], cps: Sequence[ControlPoint], *, prior_centre: np.ndarray | None = None,
                  prior_sigma_m: np.ndarray | float | None = None, opts: GeorefOptions = GeorefOptions(),
                  where: str = "control_points.json") -> CentralResult:
    """Place a central rig (panorama or single photo) from control points; see the module docstring.

    ``prior_centre`` (3,) ENU metres with ``prior_sigma_m`` (scalar or (3,)): a soft prior on the centre.
    Needs 3 control points (4 or more to be safe) seen in the photos, or 2 with a centre prior.
    """
    obs = _observations(cps, views, where)
    X = np.array([cp.enu for cp in cps], float)
    n_pts = len({o.point for o in obs})
    has_prior = prior_centre is not None
    if n_pts < 3 and not (has_prior and n_pts >= 2):
        raise InputError(f"{where}: {n_pts} control point(s) are picked in the photos {[v.name for v in views]}; "
                         f"placing the camera needs at least 3 (4 or more to check them), or 2 with the camera "
                         f"position known (camera.position_enu or GPS in the photos); add points to the file")
    bear = np.array([views[o.view].cam_from_rig.T @ views[o.view].intrinsics.rays(o.uv[None])[0] for o in obs])
    pts = np.array([o.point for o in obs])
    rng = np.random.default_rng(opts.seed)
    candidates: list[tuple[np.ndarray, np.ndarray]] = []
    if has_prior:
        c0 = np.asarray(prior_centre, float)
        u = X[pts] - c0
        ok = np.linalg.norm(u, axis=1) > 1e-3
        u[ok] /= np.linalg.norm(u[ok], axis=1, keepdims=True)
        if ok.sum() >= 2:
            candidates.append((_rotation_kabsch(u[ok], bear[ok]), c0))  # rig_from_world maps world dirs to bearings
            for _ in range(min(opts.ransac_iterations, 100)):
                i, j = rng.choice(np.nonzero(ok)[0], 2, replace=False)
                if pts[i] != pts[j]:
                    candidates.append((_rotation_kabsch(u[[i, j]], bear[[i, j]]), c0))
    if n_pts >= 3:
        by_point: dict[int, list[int]] = {}
        for k, p in enumerate(pts):
            by_point.setdefault(int(p), []).append(k)
        keys = sorted(by_point)
        for _ in range(opts.ransac_iterations):
            trip = rng.choice(len(keys), 3, replace=False)
            ks = [by_point[keys[t]][rng.integers(len(by_point[keys[t]]))] for t in trip]
            candidates.extend(_p3p_candidates(bear[ks], X[pts[ks]]))
    if not candidates:
        raise InputError(f"{where}: the control points give no camera pose (degenerate geometry: are the points "
                         f"on one line, or all picked at the same place?); add points spread over the view")
    best, best_score = None, -np.inf
    thr = opts.ransac_threshold_px
    for R, c in candidates:
        err, _ = _central_errors(R, c, views, obs, X)
        score = float(np.sum(np.maximum(0.0, 1.0 - (np.minimum(err, thr) / thr) ** 2)))  # MSAC-like, bounded
        if has_prior:
            sig = np.broadcast_to(np.asarray(prior_sigma_m if prior_sigma_m is not None else opts.prior_sigma_m,
                                             float), (3,))
            score -= 0.01 * float(np.sum(((c - c0) / sig) ** 2)) / max(len(obs), 1)
        if score > best_score:
            best, best_score = (R, c), score
    R0, c0_est = best
    err0, _ = _central_errors(R0, c0_est, views, obs, X)
    inl = err0 < thr
    if inl.sum() < min(3, len(obs)) and not has_prior:
        raise InputError(f"{where}: no camera pose agrees with more than {int(inl.sum())} of the {len(obs)} picks "
                         f"(threshold {thr} px); check the point names, coordinates and pixels")

    sig_prior = None
    if has_prior:
        sig_prior = np.broadcast_to(np.asarray(prior_sigma_m if prior_sigma_m is not None else opts.prior_sigma_m,
                                               float), (3,)).copy()

    def refine(R_init, c_init, use: np.ndarray, loss: str):
        sel = [o for o, u_ in zip(obs, use) if u_]
        depths = []
        for o in sel:
            v = views[o.view]
            depths.append(max(float((v.cam_from_rig @ (R_init @ (X[o.point] - c_init)))[2]), 1e-3))
        sig = np.array([_robust_sigma(views[o.view].intrinsics, opts.sigma_px, cps[o.point].sigma_m, d)
                        for o, d in zip(sel, depths)])

        def fun(p):
            R = Rotation.from_rotvec(p[:3]).as_matrix() @ R_init
            c = p[3:]
            res = []
            for o, s in zip(sel, sig):
                v = views[o.view]
                q = v.cam_from_rig @ (R @ (X[o.point] - c))
                z = max(q[2], 1e-6)
                xy = v.intrinsics.distort(np.array([[q[0] / z, q[1] / z]]))
                uv = v.intrinsics.pixels_from_normalized(xy)[0]
                res.extend((uv - o.uv) / s)
            if sig_prior is not None:
                res.extend((c - np.asarray(prior_centre, float)) / sig_prior)
            return np.asarray(res)

        x0 = np.concatenate([np.zeros(3), c_init])
        sol = least_squares(fun, x0, loss=loss, f_scale=opts.loss_scale, x_scale="jac", max_nfev=200)
        R = Rotation.from_rotvec(sol.x[:3]).as_matrix() @ R_init
        cov = None
        try:
            J = sol.jac
            cov = np.linalg.inv(J.T @ J)
        except np.linalg.LinAlgError:
            pass
        return R, sol.x[3:].copy(), cov

    R1, c1, _ = refine(R0, c0_est, np.ones(len(obs), bool), opts.loss)
    err1, _ = _central_errors(R1, c1, views, obs, X)
    inl = err1 < thr
    if inl.sum() >= (2 if has_prior else 3):
        R1, c1, cov = refine(R1, c1, inl, opts.loss)
    else:
        cov = None
    R1 = _orthonormal(R1)
    err, vec = _central_errors(R1, c1, views, obs, X)
    residuals = []
    for k, o in enumerate(obs):
        v = views[o.view]
        d_world = R1.T @ bear[k]
        residuals.append({"point": cps[o.point].name, "view": v.name, "uv": o.uv.tolist(),
                          "residual_px": vec[k].tolist() if np.isfinite(err[k]) else None,
                          "error_px": float(err[k]) if np.isfinite(err[k]) else None,
                          "error_m": _point_line_distance(X[o.point], c1, d_world),
                          "inlier": bool(err[k] < thr)})
    stats = _summary(residuals, opts)
    stats.update({"n_points": n_pts, "n_observations": len(obs), "prior": "yes" if has_prior else "no",
                  "ransac_candidates": len(candidates)})
    if cov is not None and np.all(np.isfinite(cov)):
        sd = np.sqrt(np.clip(np.diag(cov), 0, None))
        stats["sigma_rotation_deg"] = [float(np.degrees(x)) for x in sd[:3]]
        stats["sigma_centre_m"] = [float(x) for x in sd[3:]]
        # the same covariance in the scene frame, for the solve to carry into the carriages' poses: the rotation
        # was perturbed in the rig frame (rig_from_world <- Exp(x) rig_from_world), i.e. by R^T x in the scene
        # frame (world_from_rig <- Exp(R^T x) world_from_rig); order: rotation vector (rad), centre (m), ENU
        T = np.zeros((6, 6))
        T[:3, :3] = R1.T
        T[3:, 3:] = np.eye(3)
        cw = T @ cov @ T.T
        stats["covariance_world_rotation_centre"] = (0.5 * (cw + cw.T)).tolist()
    if has_prior:
        stats["centre_minus_prior_m"] = (c1 - np.asarray(prior_centre, float)).tolist()
    warns = _warnings(residuals, stats, opts, where)
    return CentralResult(R1, c1, residuals, stats, warns)


def _orthonormal(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    return U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt


def _summary(residuals: list[dict], opts: GeorefOptions) -> dict:
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


def _warnings(residuals: list[dict], stats: dict, opts: GeorefOptions, where: str) -> list[str]:
    import warnings as _w

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
        _w.warn(msg, GeorefResidualsLarge, stacklevel=3)
    return out


# ----------------------------------------------------------------------------------------------------------
# SfM model: similarity world_from_model
# ----------------------------------------------------------------------------------------------------------
@dataclass
class SimilarityResult:
    """``world_from_model``: ``p_world = scale * R @ p_model + t``; residuals and statistics."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    residuals: list[dict]
    stats: dict
    warnings: list[str]
    # (7, 7) covariance of (log scale, rotation vector applied on the left in the scene frame, translation),
    # scaled by the reduced chi-square when above 1; None when the fit leaves it undetermined
    covariance: np.ndarray | None = None
    triangulated: dict[str, np.ndarray] = field(default_factory=dict)  # control point -> (3,) model frame

    def centre_sigma_m(self, cam_from_model: np.ndarray) -> float | None:
        """1-sigma (square root of the largest eigenvalue, metres) of an SfM camera's centre in the scene, from
        the similarity's covariance (the model's own uncertainty not included)."""
        if self.covariance is None:
            return None
        q = self.scale * self.rotation @ _model_centre_m(cam_from_model)  # world centre minus translation
        J = np.hstack([q[:, None], -skew(q), np.eye(3)])
        C = J @ self.covariance @ J.T
        return float(np.sqrt(max(np.linalg.eigvalsh(0.5 * (C + C.T)).max(), 0.0)))

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


def _model_centre_m(cam_from_model: np.ndarray) -> np.ndarray:
    M = np.asarray(cam_from_model, float)
    return -M[:3, :3].T @ M[:3, 3]


def _model_centre(v: SfmView) -> np.ndarray:
    return _model_centre_m(v.cam_from_model)


def solve_similarity(views: Sequence[SfmView], cps: Sequence[ControlPoint], *,
                     gps_centres: dict[str, np.ndarray] | None = None, opts: GeorefOptions = GeorefOptions(),
                     where: str = "control_points.json") -> SimilarityResult:
    """``world_from_model`` of an SfM model from control points and/or GPS camera centres (module docstring).

    ``gps_centres``: photo name -> (3,) ENU metres of the camera centre (EXIF GPS), 1-sigma ``opts.gps_sigma_m``.
    """
    obs = _observations(cps, views, where) if cps else []
    gps_centres = dict(gps_centres or {})
    X = np.array([cp.enu for cp in cps], float).reshape(-1, 3)
    # 1. control points seen in two or more photos, triangulated in the model frame
    by_point: dict[int, list[_Obs]] = {}
    for o in obs:
        by_point.setdefault(o.point, []).append(o)
    src, dst, sig, label = [], [], [], []
    tri_model: dict[int, np.ndarray] = {}
    for k, lst in sorted(by_point.items()):
        if len({o.view for o in lst}) < 2:
            continue
        cs, ds = [], []
        for o in lst:
            v = views[o.view]
            M = np.asarray(v.cam_from_model, float)
            cs.append(_model_centre(v))
            ds.append(M[:3, :3].T @ v.intrinsics.rays(o.uv[None])[0])
        cs_a, ds_a = np.array(cs), np.array(ds)
        use = list(range(len(lst)))
        while True:  # a ray from a wrongly posed photo (or a wrong pick) is dropped while 3 or more remain
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
        if errs[worst] > opts.ransac_threshold_px:
            log.info("%s: control point %s: its rays do not meet (%.1f px apart); not triangulated", where,
                     cps[k].name, errs[worst])
            continue
        if angle < opts.min_triangulation_angle_deg:
            log.info("%s: control point %s: rays meet at %.2f deg; not triangulated", where, cps[k].name, angle)
            continue
        tri_model[k] = Xm
        src.append(Xm)
        dst.append(X[k])
        sig.append(max(cps[k].sigma_m, 0.01))
        label.append(("point", cps[k].name))
    # 2. camera centres with GPS
    gsig = np.asarray(opts.gps_sigma_m, float)
    name_to_view = {v.name: v for v in views}
    for name, g in sorted(gps_centres.items()):
        if name in name_to_view:
            src.append(_model_centre(name_to_view[name]))
            dst.append(np.asarray(g, float))
            sig.append(float(np.mean(gsig)))
            label.append(("gps", name))
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
    rng = np.random.default_rng(opts.seed)
    w = 1.0 / sig_a ** 2
    best = umeyama(src_a, dst_a, w)
    if len(src) >= 4:
        def n_in(s, R, t):
            d = np.linalg.norm(s * src_a @ R.T + t - dst_a, axis=1)
            return int(np.sum(d < 3.0 * sig_a + 0.05)), float(np.sum(np.minimum(d / (3 * sig_a + 0.05), 1.0)))

        bs = n_in(*best)
        for _ in range(min(opts.ransac_iterations, 200)):
            idx = rng.choice(len(src), 3, replace=False)
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
    s0, R0, t0 = best

    # 3. refinement: pixels of every control point (single-view ones too) + GPS centres in metres
    def sim_from(p):
        return s0 * math.exp(p[0]), Rotation.from_rotvec(p[1:4]).as_matrix() @ R0, t0 + p[4:7]

    obs_sig = []
    for o in obs:
        v = views[o.view]
        Xm = R0.T @ (X[o.point] - t0) / s0
        depth = float((np.asarray(v.cam_from_model)[:3, :3] @ Xm + np.asarray(v.cam_from_model)[:3, 3])[2]) * s0
        obs_sig.append(_robust_sigma(v.intrinsics, opts.sigma_px, cps[o.point].sigma_m, abs(depth)))
    gps_items = [(name_to_view[n], np.asarray(g, float)) for n, g in sorted(gps_centres.items()) if n in name_to_view]

    def fun(p):
        s, R, t = sim_from(p)
        res = []
        for o, sg in zip(obs, obs_sig):
            v = views[o.view]
            M = np.asarray(v.cam_from_model, float)
            q = M[:3, :3] @ (R.T @ (X[o.point] - t) / s) + M[:3, 3]
            z = q[2] if q[2] > 1e-9 else 1e-9
            uv = v.intrinsics.pixels_from_normalized(v.intrinsics.distort(np.array([[q[0] / z, q[1] / z]])))[0]
            res.extend((uv - o.uv) / sg)
        for v, g in gps_items:
            res.extend((s * R @ _model_centre(v) + t - g) / gsig)
        return np.asarray(res)

    sol = least_squares(fun, np.zeros(7), loss=opts.loss, f_scale=opts.loss_scale, x_scale="jac", max_nfev=300)
    s, R, t = sim_from(sol.x)
    R = _orthonormal(R)
    cov = None
    dof = len(sol.fun) - 7
    try:
        J = np.asarray(sol.jac, float)
        cov = np.linalg.inv(J.T @ J)
        if dof > 0:
            cov *= max(1.0, 2.0 * float(sol.cost) / dof)
        if not np.all(np.isfinite(cov)):
            cov = None
    except np.linalg.LinAlgError:
        cov = None
    if cov is not None:  # d(log s), d(rotvec), d(t) of the parametrisation at the solution
        cov = cov.copy()
    result = SimilarityResult(s, R, t, [], {}, [], covariance=cov,
                              triangulated={cps[k].name: Xm for k, Xm in tri_model.items()})
    residuals = []
    for o in obs:
        v = views[o.view]
        Mw = result.cam_from_world(v.cam_from_model)
        q = Mw[:3, :3] @ X[o.point] + Mw[:3, 3]
        if q[2] > 1e-6:
            vec = v.intrinsics.project(q[None])[0] - o.uv
            e_px = float(np.hypot(*vec))
        else:
            vec, e_px = None, None
        c_w = -Mw[:3, :3].T @ Mw[:3, 3]
        d_w = Mw[:3, :3].T @ v.intrinsics.rays(o.uv[None])[0]
        e_m = _point_line_distance(X[o.point], c_w, d_w)  # the known point's distance from the observed ray
        tri_m = float(np.linalg.norm(result.apply(tri_model[o.point]) - X[o.point])) if o.point in tri_model else None
        residuals.append({"point": cps[o.point].name, "view": v.name, "uv": o.uv.tolist(),
                          "residual_px": None if vec is None else vec.tolist(), "error_px": e_px, "error_m": e_m,
                          "triangulated_error_m": tri_m,
                          "inlier": e_px is not None and e_px < opts.ransac_threshold_px})
    gps_res = {v.name: (result.apply(_model_centre(v)) - g).tolist() for v, g in gps_items}
    stats = _summary(residuals, opts)
    stats.update({"n_points": len(by_point), "n_triangulated": len(tri_model), "n_observations": len(obs),
                  "n_gps_centres": len(gps_items), "scale": s, "gps_residuals_m": gps_res,
                  "gps_rms_m": float(np.sqrt(np.mean([np.sum(np.square(r)) for r in gps_res.values()])))
                  if gps_res else None})
    warns = _warnings(residuals, stats, opts, where) if residuals else []
    result.residuals, result.stats, result.warnings = residuals, stats, warns
    return result


def refine_resection_focal(intr: CameraIntrinsics, res: CentralResult, cps: Sequence[ControlPoint], name: str,
                           opts: GeorefOptions = GeorefOptions()) -> dict | None:
    """One photo's pose *and focal* (fx, fy scaled together; principal point and distortion kept) refined from
    its inlier control-point picks, starting from a fixed-focal resection ``res`` of that photo alone.

    Returns ``{"intrinsics", "cam_from_world" (4, 4), "focal_px", "sigma_focal_px", "sigma_centre_max_m",
    "rms_px", "n_observations"}`` or None (fewer than 6 inlier picks: the focal is not determined)."""
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
    sig = np.array([_robust_sigma(intr, opts.sigma_px, cp.sigma_m, d) for (cp, _), d in zip(obs, depth)])
    base = intr.to_dict()

    def intr_of(logf):
        k = math.exp(logf)
        return CameraIntrinsics.from_dict({**base, "fx": intr.fx * k, "fy": intr.fy * k})

    def fun(p):
        R = Rotation.from_rotvec(p[:3]).as_matrix() @ R0
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
    if dof > 0:
        cov *= max(1.0, 2.0 * float(sol.cost) / dof)
    if not np.all(np.isfinite(cov)):
        return None
    R = _orthonormal(Rotation.from_rotvec(sol.x[:3]).as_matrix() @ R0)
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
            "rms_px": float(np.sqrt(np.mean(e ** 2))), "n_observations": len(obs)}


# ----------------------------------------------------------------------------------------------------------
# Shared camera: intrinsics refined jointly with the placed photos' poses from their control-point picks
# ----------------------------------------------------------------------------------------------------------
INTRINSIC_SETS = {"f": ("f",), "f_pp": ("f", "cx", "cy"), "f_pp_k1": ("f", "cx", "cy", "k1")}


def _intr_prior_sigmas(intr: CameraIntrinsics) -> dict[str, float]:
    """A priori 1-sigma of SfM's intrinsics, deliberately loose (SfM reports none): focal 10 % (log), principal
    point 3 % of the larger image side, k1 0.1. They keep an adjustment from wandering where the picks say
    little; where the picks determine a parameter, they decide."""
    return {"f": 0.10, "cx": 0.03 * max(intr.width, intr.height), "cy": 0.03 * max(intr.width, intr.height),
            "k1": 0.10}


def _with_intr(intr: CameraIntrinsics, free: Sequence[str], d: np.ndarray) -> CameraIntrinsics:
    base = intr.to_dict()
    dd = dict(zip(free, d))
    k = math.exp(dd.get("f", 0.0))
    return CameraIntrinsics.from_dict({**base, "fx": intr.fx * k, "fy": intr.fy * k, "cx": intr.cx + dd.get("cx", 0.0),
                                       "cy": intr.cy + dd.get("cy", 0.0), "k1": intr.k1 + dd.get("k1", 0.0)})


def adjust_shared_camera(intr: CameraIntrinsics, poses: dict[str, np.ndarray], cps: Sequence[ControlPoint],
                         opts: GeorefOptions = GeorefOptions(), *, free: Sequence[str] = ("f", "cx", "cy", "k1"),
                         use: set[tuple[str, str]] | None = None) -> dict:
    """Least-squares adjustment of one camera's intrinsics (``free`` of focal ``f`` (log), ``cx``, ``cy``,
    ``k1``; the rest kept) jointly with the poses of the photos that share it, from their control-point picks.

    ``poses``: photo -> starting ``cam_from_world`` (4, 4). ``use``: the (point, photo) picks to fit (default
    every pick of those photos). Each pick's residual is divided by ``sqrt(sigma_px^2 + (f sigma_m/depth)^2)``;
    the intrinsics have a loose prior at SfM's values (:func:`_intr_prior_sigmas`); soft-L1 loss. The
    covariance is ``(J^T J)^-1`` times the variance factor: the reduced chi-square of the picks when above 1,
    and also when below 1 with ``opts.variance_factor_min_dof`` or more degrees of freedom.

    Returns ``{"intrinsics", "poses" (photo -> (4, 4)), "cov_centre" (photo -> (3, 3) m^2), "sigma_rot_deg"
    (photo -> float), "sigma_intrinsics" (name -> 1-sigma; f in px), "values", "condition" (of the
    column-normalised Jacobian), "chi2_red", "rms_px", "n_observations", "residual" (callable: photo, point
    names -> pixel errors for any picks, held-out ones included)}``."""
    free = tuple(free)
    names = sorted(poses)
    obs = []  # (photo index, X, uv, sigma)
    for cp in cps:
        for ph, uv in cp.pixels.items():
            if ph in poses and (use is None or (cp.name, ph) in use):
                M = np.asarray(poses[ph], float)
                depth = float((M[:3, :3] @ cp.enu + M[:3, 3])[2])
                obs.append((names.index(ph), np.asarray(cp.enu, float), np.asarray(uv, float),
                            _robust_sigma(intr, opts.sigma_px, cp.sigma_m, abs(depth))))
    if not obs:
        raise ValueError("no picks to adjust")
    vi = np.array([o[0] for o in obs])
    Xa = np.array([o[1] for o in obs])
    UV = np.array([o[2] for o in obs])
    SG = np.array([o[3] for o in obs])
    R0 = [np.asarray(poses[n], float)[:3, :3] for n in names]
    c0 = [-R0[i].T @ np.asarray(poses[n], float)[:3, 3] for i, n in enumerate(names)]
    psig = _intr_prior_sigmas(intr)
    pri = np.array([psig[k] for k in free])
    ni = len(free)

    def unpack(p):
        it = _with_intr(intr, free, p[:ni])
        Rs, cs = [], []
        for i in range(len(names)):
            q = p[ni + 6 * i: ni + 6 * i + 6]
            Rs.append(Rotation.from_rotvec(q[:3]).as_matrix() @ R0[i])
            cs.append(c0[i] + q[3:6])
        return it, Rs, cs

    def project(it, Rs, cs, idx, X):
        q = np.einsum("nij,nj->ni", np.array(Rs)[idx], X - np.array(cs)[idx])
        z = np.maximum(q[:, 2], 1e-6)
        return it.pixels_from_normalized(it.distort(q[:, :2] / z[:, None]))

    def fun(p):
        it, Rs, cs = unpack(p)
        r = ((project(it, Rs, cs, vi, Xa) - UV) / SG[:, None]).ravel()
        return np.concatenate([r, p[:ni] / pri])

    p0 = np.zeros(ni + 6 * len(names))
    # which parameters each residual depends on (the shared intrinsics, its own photo's pose): finite
    # differences in groups, so the cost grows with the picks, not with picks x photos
    from scipy.sparse import lil_matrix

    sp = lil_matrix((2 * len(obs) + ni, len(p0)), dtype=int)
    sp[:, :ni] = 1
    for k, i in enumerate(vi):
        sp[2 * k:2 * k + 2, ni + 6 * i: ni + 6 * i + 6] = 1
    sol = least_squares(fun, p0, loss=opts.loss, f_scale=opts.loss_scale, x_scale="jac", max_nfev=200,
                        jac_sparsity=sp)
    it, Rs, cs = unpack(sol.x)
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac, float)
    n_data = 2 * len(obs)
    dof = n_data - (ni + 6 * len(names))
    chi2 = float(np.sum(sol.fun[:n_data] ** 2) / dof) if dof > 0 else float("nan")
    norms = np.linalg.norm(J, axis=0)
    norms[norms == 0] = 1.0
    cond = float(np.linalg.cond(J / norms))
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(J.T @ J)
    # the variance factor: the reduced chi-square when above 1; with many degrees of freedom
    # (``opts.variance_factor_min_dof``) also when below (the a posteriori variance of unit weight, well
    # determined there: relative 1-sigma sqrt(2/dof)), so that a pessimistic sigma_px does not inflate the sigmas
    vf = 1.0
    if dof > 0:
        vf = max(1.0, 2.0 * float(sol.cost) / dof)
        if dof >= opts.variance_factor_min_dof and np.isfinite(chi2):
            vf = max(vf, chi2) if chi2 >= 1.0 else chi2
        cov *= vf
    err = np.hypot(*(project(it, Rs, cs, vi, Xa) - UV).T)
    out_poses, cov_c, sig_r = {}, {}, {}
    for i, n in enumerate(names):
        M = np.eye(4)
        M[:3, :3] = _orthonormal(Rs[i])
        M[:3, 3] = -M[:3, :3] @ cs[i]
        out_poses[n] = M
        b = ni + 6 * i
        cov_c[n] = 0.5 * (cov[b + 3:b + 6, b + 3:b + 6] + cov[b + 3:b + 6, b + 3:b + 6].T)
        sig_r[n] = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[b:b + 3, b:b + 3]).max(), 0.0))))
    sig_i = {}
    for j, k in enumerate(free):
        s = math.sqrt(max(cov[j, j], 0.0))
        sig_i[k] = s * it.fx if k == "f" else s
    values = {"f": it.fx, "cx": it.cx, "cy": it.cy, "k1": it.k1}
    pt_idx = {cp.name: cp for cp in cps}

    def residual(photo: str, points: Sequence[str]) -> np.ndarray:
        i = names.index(photo)
        X = np.array([pt_idx[p].enu for p in points], float).reshape(-1, 3)
        uv = np.array([pt_idx[p].pixels[photo] for p in points], float).reshape(-1, 2)
        return np.hypot(*(project(it, Rs, cs, np.full(len(X), i), X) - uv).T)

    return {"intrinsics": it, "poses": out_poses, "cov_centre": cov_c, "sigma_rot_deg": sig_r,
            "sigma_intrinsics": sig_i, "values": values, "free": list(free), "condition": cond, "chi2_red": chi2,
            "rms_px": float(np.sqrt(np.mean(err ** 2))), "n_observations": len(obs), "n_photos": len(names),
            "dof": dof, "variance_factor": vf,
            "residual": residual}


def held_out_errors(intr: CameraIntrinsics, poses: dict[str, np.ndarray], cps: Sequence[ControlPoint],
                    opts: GeorefOptions, free: Sequence[str], min_train: int = 4) -> dict[str, np.ndarray]:
    """Two-fold cross-validation over the picks: every photo's picks split in two alternately (sorted by point
    name); the adjustment (intrinsics ``free``, or none: ``free=()``, SfM's kept) is fitted on one half of every
    photo and predicts the other half, then the halves swap. Only photos with ``min_train`` picks in each half
    are scored (the others are fitted on all their picks both times, and not scored). Returns photo -> pixel
    errors of its held-out picks (every pick of a scored photo, once), in :func:`held_out_picks` order."""
    picks = held_out_picks(poses, cps, min_train)
    errs: dict[str, list[float]] = {n: [] for n in picks}
    if not picks:
        return {}
    for fold in (0, 1):
        use, test = set(), {}
        for n in poses:
            ps = sorted(cp.name for cp in cps if n in cp.pixels)
            if n in picks:
                use |= {(p, n) for k, p in enumerate(ps) if k % 2 != fold}
                test[n] = [p for k, p in enumerate(ps) if k % 2 == fold]
            else:
                use |= {(p, n) for p in ps}
        adj = adjust_shared_camera(intr, poses, cps, opts, free=free, use=use)
        for n, ps in test.items():
            errs[n].extend(adj["residual"](n, ps))
    # back in held_out_picks order (fold 0 took the even picks, fold 1 the odd ones)
    out = {}
    for n, ps in picks.items():
        e = np.asarray(errs[n], float)
        n0 = (len(ps) + 1) // 2
        order = np.empty(len(ps), float)
        order[0::2], order[1::2] = e[:n0], e[n0:]
        out[n] = order
    return out


def held_out_picks(poses: dict[str, np.ndarray], cps: Sequence[ControlPoint], min_train: int = 4) -> dict[str, list[str]]:
    """The photos :func:`held_out_errors` scores (``2 min_train`` picks or more) -> their picks' point names."""
    out = {}
    for n in poses:
        ps = sorted(cp.name for cp in cps if n in cp.pixels)
        if len(ps) >= 2 * min_train:
            out[n] = ps
    return out


def robust_rms(errors: Sequence[float] | np.ndarray, opts: GeorefOptions) -> float | None:
    """RMS of pixel errors with those beyond the outlier threshold counted at the threshold (None: no errors)."""
    e = np.minimum(np.asarray(errors, float).ravel(), opts.ransac_threshold_px)
    return float(np.sqrt(np.mean(e ** 2))) if e.size else None


def held_out_rms(intr: CameraIntrinsics, poses: dict[str, np.ndarray], cps: Sequence[ControlPoint],
                 opts: GeorefOptions, free: Sequence[str], min_train: int = 4) -> tuple[float | None, int]:
    """(robust RMS px of the held-out picks of :func:`held_out_errors`, their number)."""
    per = held_out_errors(intr, poses, cps, opts, free, min_train)
    if not per:
        return None, 0
    e = np.concatenate(list(per.values()))
    return robust_rms(e, opts), len(e)
