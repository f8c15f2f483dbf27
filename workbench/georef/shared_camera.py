"""One SfM camera's intrinsics refined jointly with the poses of the placed photos that share it, from their
control-point picks, and the two-fold cross-validation that decides which intrinsics to free (docs/gis.md)."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from ..core.camera import CameraIntrinsics
from ..core.geometry import exp_so3
from ..files.control_points import ControlPoint
from .fitting import orthonormal
from .options import GeorefOptions
from .picks import pick_sigma, shared_point_information, variance_factor

__all__ = ["INTRINSIC_SETS", "adjust_shared_camera", "held_out_errors", "held_out_picks", "held_out_rms",
           "robust_rms"]

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


def _adjusted_picks(intr: CameraIntrinsics, poses: dict[str, np.ndarray], names: list[str],
                    cps: Sequence[ControlPoint], opts: GeorefOptions, use: set[tuple[str, str]] | None):
    """The picks to fit as arrays: photo index (n,), point (n, 3), pixel (n, 2), 1-sigma px (n,), the point's
    index among ``cps`` (n,) and its position error (n,) m."""
    obs = []  # (photo index, X, uv, sigma, point index, sigma_m)
    for j, cp in enumerate(cps):
        for ph, uv in cp.pixels.items():
            if ph in poses and (use is None or (cp.name, ph) in use):
                M = np.asarray(poses[ph], float)
                depth = float((M[:3, :3] @ cp.enu + M[:3, 3])[2])
                obs.append((names.index(ph), np.asarray(cp.enu, float), np.asarray(uv, float),
                            pick_sigma(intr, opts.sigma_px, cp.sigma_m, abs(depth)), j, float(cp.sigma_m)))
    if not obs:
        raise ValueError("no picks to adjust")
    return tuple(np.array([o[i] for o in obs]) for i in range(6))


def _project(it: CameraIntrinsics, Rs: list[np.ndarray], cs: list[np.ndarray], idx: np.ndarray,
             X: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) of points ``X`` (n, 3) in the photos ``idx`` (n,) posed by rotations ``Rs`` and centres ``cs``."""
    q = np.einsum("nij,nj->ni", np.array(Rs)[idx], X - np.array(cs)[idx])
    z = np.maximum(q[:, 2], 1e-6)
    return it.pixels_from_normalized(it.distort(q[:, :2] / z[:, None]))


def adjust_shared_camera(intr: CameraIntrinsics, poses: dict[str, np.ndarray], cps: Sequence[ControlPoint],
                         opts: GeorefOptions = GeorefOptions(), *, free: Sequence[str] = ("f", "cx", "cy", "k1"),
                         use: set[tuple[str, str]] | None = None) -> dict:
    """Least-squares adjustment of one camera's intrinsics (``free`` of focal ``f`` (log), ``cx``, ``cy``,
    ``k1``; the rest kept) jointly with the poses of the photos that share it, from their control-point picks.

    ``poses``: photo -> starting ``cam_from_world`` (4, 4). ``use``: the (point, photo) picks to fit (default
    every pick of those photos). Each pick's residual is divided by ``sqrt(sigma_px^2 + (f sigma_m/depth)^2)``;
    the intrinsics have a loose prior at SfM's values (:func:`_intr_prior_sigmas`); soft-L1 loss. The
    covariance is the sandwich ``H^-1 G H^-1`` in which a control point's position error is one error shared by
    its picks in every photo (:func:`~.picks.shared_point_information`), times the variance factor
    (:func:`~.picks.variance_factor`).

    Returns ``{"intrinsics", "poses" (photo -> (4, 4)), "cov_centre" (photo -> (3, 3) m^2), "sigma_rot_deg"
    (photo -> float), "sigma_intrinsics" (name -> 1-sigma; f in px), "values", "condition" (of the
    column-normalised Jacobian), "chi2_red", "rms_px", "n_observations", "residual" (callable: photo, point
    names -> pixel errors for any picks, held-out ones included)}``."""
    free = tuple(free)
    names = sorted(poses)
    vi, Xa, UV, SG, pid, SM = _adjusted_picks(intr, poses, names, cps, opts, use)
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
            Rs.append(exp_so3(q[:3]) @ R0[i])
            cs.append(c0[i] + q[3:6])
        return it, Rs, cs

    def fun(p):
        it, Rs, cs = unpack(p)
        r = ((_project(it, Rs, cs, vi, Xa) - UV) / SG[:, None]).ravel()
        return np.concatenate([r, p[:ni] / pri])

    p0 = np.zeros(ni + 6 * len(names))
    # which parameters each residual depends on (the shared intrinsics, its own photo's pose): finite
    # differences in groups, so the cost grows with the picks, not with picks x photos
    sp = lil_matrix((2 * len(vi) + ni, len(p0)), dtype=int)
    sp[:, :ni] = 1
    for k, i in enumerate(vi):
        sp[2 * k:2 * k + 2, ni + 6 * i: ni + 6 * i + 6] = 1
    sol = least_squares(fun, p0, loss=opts.loss, f_scale=opts.loss_scale, x_scale="jac", max_nfev=200,
                        jac_sparsity=sp)
    it, Rs, cs = unpack(sol.x)
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac, float)
    n_data = 2 * len(vi)
    dof = n_data - (ni + 6 * len(names))
    chi2 = float(np.sum(sol.fun[:n_data] ** 2) / dof) if dof > 0 else float("nan")
    norms = np.linalg.norm(J, axis=0)
    norms[norms == 0] = 1.0
    cond = float(np.linalg.cond(J / norms))
    try:
        Hi = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        Hi = np.linalg.pinv(J.T @ J)
    # the sandwich: a control point's position error is one error shared by its picks in every photo
    centre_cols = ni + 6 * vi[:, None] + np.array([3, 4, 5])[None, :]
    G = J[n_data:].T @ J[n_data:] + shared_point_information(J[:n_data], pid, centre_cols,
                                                             (opts.sigma_px / SG) ** 2, SM)
    cov = Hi @ G @ Hi
    cov = 0.5 * (cov + cov.T)
    vf = variance_factor(sol.cost, chi2, dof, opts)
    if dof > 0:
        cov *= vf
    err = np.hypot(*(_project(it, Rs, cs, vi, Xa) - UV).T)
    out_poses, cov_c, sig_r = {}, {}, {}
    for i, n in enumerate(names):
        M = np.eye(4)
        M[:3, :3] = orthonormal(Rs[i])
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
        return np.hypot(*(_project(it, Rs, cs, np.full(len(X), i), X) - uv).T)

    return {"intrinsics": it, "poses": out_poses, "cov_centre": cov_c, "sigma_rot_deg": sig_r,
            "sigma_intrinsics": sig_i, "values": values, "free": list(free), "condition": cond, "chi2_red": chi2,
            "rms_px": float(np.sqrt(np.mean(err ** 2))), "n_observations": len(vi), "n_photos": len(names),
            "dof": dof, "variance_factor": vf, "factor": joint_factor(cov, it, free, names, Rs),
            "residual": residual}


def covariance_factor(C: np.ndarray) -> np.ndarray:
    """A factor ``L`` of a covariance (``C = L L^T``, eigen-directions; its null directions left out)."""
    ev, V = np.linalg.eigh(0.5 * (np.asarray(C, float) + np.asarray(C, float).T))
    keep = ev > 1e-12 * max(float(ev.max()), 1e-300)
    return V[:, keep] * np.sqrt(ev[keep])


def joint_factor(cov: np.ndarray, it: CameraIntrinsics, free: Sequence[str], names: list[str],
                 Rs: list[np.ndarray]) -> dict:
    """An adjustment's joint covariance (the free intrinsics first, ``f`` as log(f), then each photo's rotation
    vector on the left of ``cam_from_world`` and centre; ``Rs`` the photos' rotations) as one factor ``L``
    (``C = L L^T``, the photos sharing ``z ~ N(0, I_r)``): ``{"poses": photo -> (6, r)`` in the order of
    ``georegistration.pose_uncertainty`` (rotation vector of ``world_from_cam`` in the scene frame, centre in m),
    ``"params"``: the intrinsics' names (``f`` moving fx and fy together, in px), ``"intrinsics"`` (k, r)}."""
    ni = len(free)
    L = covariance_factor(cov)
    K = L[:ni].copy()
    for j, k in enumerate(free):
        if k == "f":  # the adjustment's focal is log(f / f_sfm): df = f dlog
            K[j] *= it.fx
    poses = {}
    for i, n in enumerate(names):
        b = ni + 6 * i
        T = np.zeros((6, 6))
        T[:3, :3] = -np.asarray(Rs[i], float).T  # cam_from_world' = Exp(q) R: world_from_cam' = Exp(-R^T q) R^T
        T[3:, 3:] = np.eye(3)
        poses[n] = T @ L[b:b + 6]
    return {"poses": poses, "params": list(free), "intrinsics": K}


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
