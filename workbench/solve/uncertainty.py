"""Covariance of the chained pose solution, and the Cramér-Rao bound of the same model.

Parameters: per carriage a scene-frame rotation vector and the origin (6), plus each estimated focal (px).
Held couplings enter as the soft prior ``T ~ N(0, (slack / sqrt 5)^2 I)`` (not the solver's hard bound), the
weighting through the sandwich ``H^-1 G H^-1``, pose predictions with their face alignment's error (the others not
at all), a face's shared misfit in ``G``; the pixel sigma is pooled with the configured one. ``docs/solver.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy.special import gammaincinv, stdtrit  # quantiles as scipy.stats computes them (2 s to import)

from ..core.frames import hpr_from_rotation
from ..core.geometry import exp_so3, skew
from .model import SolveOptions
from .problem import (Chains, Poses, Problem, carriage_weights, focal_groups, held_chains, prepare_cars,
                      record_warning)
from .projection import project_with_jacobians
from .alignment_covariance import alignment_term, views_per_face
from .pose_covariance import pose_rows
from .variance_components import (FALLBACK_FACE_SIGMA_PX, VarianceComponents, estimate_variance_components,
                                  face_modes)


def pixel_rows(prob, R, t, f, focal_views):
    """Weighted pixel Jacobian (2M, P) in free-pose parameters, the weighted residuals (2M,), each carriage's
    first column and P."""
    act = prob.active
    col = {k: 6 * i for i, k in enumerate(act)}
    P = 6 * len(act) + len(focal_views)
    uv, Xw, JX, Jf = prob.project(R, t, f, jac=True)
    M = len(prob.P)
    J = np.zeros((2 * M, P))
    w = prob.w
    q = np.einsum("nij,nj->ni", R[prob.car], prob.P)
    Jr = -np.einsum("nab,nbc->nac", JX, skew(q))
    for k in act:
        idx = prob.by_car[k]
        c = col[k]
        J[2 * idx, c:c + 3] = Jr[idx, 0] * w[idx, None]
        J[2 * idx + 1, c:c + 3] = Jr[idx, 1] * w[idx, None]
        J[2 * idx, c + 3:c + 6] = JX[idx, 0] * w[idx, None]
        J[2 * idx + 1, c + 3:c + 6] = JX[idx, 1] * w[idx, None]
    for i, grp in enumerate(focal_views):
        idx = np.concatenate([prob.by_view[v] for v in grp])
        J[2 * idx, 6 * len(act) + i] = Jf[idx, 0] * w[idx]
        J[2 * idx + 1, 6 * len(act) + i] = Jf[idx, 1] * w[idx]
    r = ((uv - prob.uv) * w[:, None]).reshape(-1)
    return J, r, col, P


def prior_rows(cars, R, t, chains, slacks, col, P) -> np.ndarray:
    """Whitened Jacobian rows (3 per held link, ``T / sigma_T``) of the couplers' offset prior in free-pose
    parameters; ``T = t_b + R_b c_front - t_a - R_a c_rear``."""
    rows = []
    for ch, sl in zip(chains, slacks):
        for j in range(len(ch) - 1):
            a, b = ch[j], ch[j + 1]
            sT = sl[j] / math.sqrt(5.0)
            JT = np.zeros((3, P))
            ra, rb = R[a] @ cars[a].c_rear, R[b] @ cars[b].c_front
            ca, cb = col[a], col[b]
            JT[:, ca:ca + 3] = skew(ra)  # d(-R_a c_r)/d omega_a = +[R_a c_r]x
            JT[:, ca + 3:ca + 6] = -np.eye(3)
            JT[:, cb:cb + 3] = -skew(rb)
            JT[:, cb + 3:cb + 6] = np.eye(3)
            rows.append(JT / sT)
    return np.vstack(rows) if rows else np.zeros((0, P))


def _prior_info(cars, R, t, chains, slacks, col, P):
    Jp = prior_rows(cars, R, t, chains, slacks, col, P)
    return Jp.T @ Jp


def contact_rows(contact, R, t, col, P, sigma_cfg) -> tuple[np.ndarray, list[int], np.ndarray]:
    """Whitened Jacobian rows of the soft per-carriage rows (the terrain contact, ``clearance / sigma_z``, one per
    carriage on the terrain; the track prior's, two per carriage on the rails), the carriages they belong to and
    their indices among ``contact.cars`` (a carriage off the terrain has no contact row)."""
    if contact is None or not contact.cars:
        return np.zeros((0, P)), [], np.zeros(0, dtype=int)
    cars_c = contact.cars
    _, a, q, on = contact.rows(R[cars_c], t[cars_c])
    ks = [k for k, o in zip(cars_c, on) if o]
    rows = np.zeros((len(ks), P))
    for i, (k, a_k, q_k) in enumerate(zip(ks, a[on], q[on])):
        c = col[k]
        rows[i, c:c + 3] = np.cross(q_k, a_k)  # -(a x-matrix(R s))
        rows[i, c + 3:c + 6] = a_k
    return rows / sigma_cfg, ks, np.nonzero(on)[0]


def _contact_info(contact, R, t, col, P, sigma_cfg):
    Jc, _, _ = contact_rows(contact, R, t, col, P, sigma_cfg)
    return Jc.T @ Jc


def _robust_weights(r2: np.ndarray, loss: str, scale: float) -> np.ndarray:
    z = r2 / scale**2
    if loss == "linear":
        return np.ones_like(z)
    if loss == "huber":
        return np.where(z <= 1, 1.0, 1.0 / np.sqrt(np.maximum(z, 1e-300)))
    if loss == "soft_l1":
        return 1.0 / np.sqrt(1.0 + z)
    if loss == "cauchy":
        return 1.0 / (1.0 + z)
    raise ValueError(loss)


def inverse_psd(H: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive (semi-)definite matrix: by Cholesky, else the pseudo-inverse."""
    try:
        L = np.linalg.cholesky(H)
        Li = np.linalg.solve(L, np.eye(len(H)))
        return Li.T @ Li
    except np.linalg.LinAlgError:
        return np.linalg.pinv(H)


@dataclass
class CovarianceModel:
    """The covariance ``cov`` (P, P) of the free-pose parameters (carriage ``k``'s six from ``col[k]``, then the
    focal groups'), the pixel sigma used and estimated, its degrees of freedom, the 95 % factor ``q`` (Student's
    t), the inverse information ``H_inv`` and the parameters the information leaves ``undetermined`` (P,) bool
    (:func:`undetermined_parameters`; None: none)."""

    cov: np.ndarray
    col: dict[int, int]
    sigma: float
    sigma_hat: float
    dof: float
    q: float
    P: int
    H_inv: np.ndarray
    undetermined: np.ndarray | None = None
    face_sigma: float = 0.0  # the faces' shared misfit used (px per affine mode)
    components: VarianceComponents | None = None  # when both were estimated from the residuals


def undetermined_parameters(H: np.ndarray) -> np.ndarray | None:
    """The parameters (P,) bool that a singular information ``H`` leaves undetermined (a component on its null
    space), or None when ``H`` is positive definite (its Cholesky factorisation exists). The pseudo-inverse that
    :func:`inverse_psd` falls back on gives such a parameter a finite variance, as if the data had fixed it;
    its variance is infinite."""
    try:
        np.linalg.cholesky(H)
        return None
    except np.linalg.LinAlgError:
        pass
    ev, V = np.linalg.eigh(0.5 * (H + H.T))
    null = ev <= max(ev[-1], 0.0) * len(H) * np.finfo(float).eps
    if not null.any():
        return None
    return np.sum(V[:, null] ** 2, axis=1) > 1e-6


def covariance_model(prob, R, t, f, focal_views, chains, slacks, contact, sigma_cfg: float,
                     loss: str = "linear", loss_scale: float = 1.0, prior_dof: float = 5.0,
                     sigma_fixed: float | None = None, face_sigma: float | None = 0.0,
                     use_alignments: bool = True, views_shared: bool = True, count_pose: bool = True
                     ) -> CovarianceModel:
    """Covariance in free-pose parameters at ``R, t, f`` (see the module doc). ``sigma_fixed``: use that pixel
    sigma (CRB); ``face_sigma``: pixels of the misfit shared by each group of points; ``use_alignments``: the
    points with a face alignment's loading (``Problem.loading``) take their error from it (:func:`alignment_term`)
    in place of the pixel sigma and the fixed misfit (docs/correspondences.md, "What a face's alignment
    measures"); ``views_shared``: a face's error is shared by the photos it is aligned in (:func:`views_per_face`),
    not independent from photo to photo; ``count_pose``: the pose predictions too (:mod:`.pose_covariance`)."""
    J, r, col, P = pixel_rows(prob, R, t, f, focal_views)
    groups = getattr(prob, "group", None)
    if groups is None or len(groups) != len(prob.P):
        groups = np.full(len(prob.P), -1)
    block = getattr(prob, "block", None)
    loading = getattr(prob, "loading", None)
    if not use_alignments or block is None or len(block) != len(prob.P) or sigma_fixed is not None \
            or face_sigma is None:
        block, loading = np.full(len(prob.P), -1), np.zeros((len(prob.P), 2, 8))
    pose = pose_rows(prob, J, np.repeat(_robust_weights((r.reshape(-1, 2) ** 2).sum(1), loss, loss_scale), 2), col,
                     views_shared) if count_pose and (block >= 0).any() else None
    uv_obs, w_row, views = prob.uv, prob.w, prob.view
    # predictions (points projected from a face's pose, points carried from another photo) guide the fit but
    # are functions of the measured points: counting them would claim information twice
    meas = getattr(prob, "measured", None)
    if meas is not None and len(meas) == len(prob.P) and not meas.all():
        keep = np.repeat(meas, 2)
        J, r = J[keep], r[keep]
        groups, uv_obs, w_row, views = groups[meas], uv_obs[meas], w_row[meas], views[meas]
        block, loading = block[meas], loading[meas]
        w2 = np.repeat(prob.w_noise[meas] ** 2, 2)
        M = int(meas.sum())
    else:
        w2 = np.repeat(prob.w_noise**2, 2)  # variance factor of the weighted rows (whitened points keep w_i^2)
        M = len(prob.P)
    r2pt = (r.reshape(-1, 2) ** 2).sum(1)
    rho = np.repeat(_robust_weights(r2pt, loss, loss_scale), 2)
    Hp_unit = (J * rho[:, None]).T @ J
    if views_shared and (block >= 0).any():
        loading = loading * np.sqrt(views_per_face(block, groups, views))[:, None, None]
    aligned = np.repeat(block >= 0, 2)  # rows whose error their face alignment gives (not the fixed misfit)
    Gp_unit = (J * (rho**2 * w2 * ~aligned)[:, None]).T @ J
    Hprior = _prior_info(prob.cars, R, t, chains, slacks, col, P) + _contact_info(contact, R, t, col, P, sigma_cfg)

    def assemble(sig):
        H = Hp_unit / sig**2 + Hprior
        Hi = inverse_psd(H)
        return H, Hi

    vc = None
    if face_sigma is None and sigma_fixed is None:  # the automatic points' noise and faces' misfit from the data
        modes = face_modes(groups, views, uv_obs, w_row)
        vc = estimate_variance_components(J * np.sqrt(rho)[:, None], r * np.sqrt(rho), w2, modes,
                                          lambda s: assemble(s)[1], sigma_cfg)
    if face_sigma is None:  # not separable from the points' noise (too few points a face): the former default
        face_sigma = vc.face_sigma_px if vc is not None else FALLBACK_FACE_SIGMA_PX
    if sigma_fixed is not None:
        sigma, sigma_hat, dof, q = float(sigma_fixed), float("nan"), 0.0, 1.959963984540054
    elif vc is not None:
        sigma, sigma_hat, dof = vc.sigma_px, vc.sigma_px, vc.dof
        q = float(stdtrit(dof, 0.975))
    elif aligned.all() and len(aligned):
        # every measured point's error is its alignment's, known from its matches (2 N - 8 residual degrees of
        # freedom each, N >= 8): the pixel sigma only weights the pixels against the priors in the information
        sigma, sigma_hat, dof, q = _pooled_sigma(r, w2, M, Hp_unit, Hprior, sigma_cfg, prior_dof, assemble) \
            + (1.959963984540054,)
    else:
        sigma, sigma_hat, dof = _pooled_sigma(r, w2, M, Hp_unit, Hprior, sigma_cfg, prior_dof, assemble)
        q = float(stdtrit(dof + prior_dof, 0.975)) if dof + prior_dof > 0 else 1.959963984540054
    Hp_unit = Hp_unit + (pose.info if pose is not None else 0.0)  # the fit's weights on the counted predictions
    H, Hi = assemble(sigma)
    G = Gp_unit / sigma**2 + Hprior
    misfit_groups = np.where(block >= 0, -1, groups)  # an aligned point's face error is its alignment's
    if vc is not None and vc.face_sigmas_px:  # each face its own misfit
        G = G + _shared_misfit(J * rho[:, None], groups, views, uv_obs, w_row,
                               np.square(vc.face_sigmas_px)) / sigma**4
    elif face_sigma > 0:
        G = G + face_sigma**2 / sigma**4 * _shared_misfit(J * rho[:, None], misfit_groups, views, uv_obs, w_row)
    if (block >= 0).any():
        G = G + alignment_term(J * rho[:, None], block, loading, w_row, pose and pose.contrib) / sigma**4
    cov = Hi @ G @ Hi
    cov = 0.5 * (cov + cov.T)
    return CovarianceModel(cov, col, sigma, sigma_hat, dof, q, P, Hi, undetermined_parameters(H), face_sigma, vc)


def _pooled_sigma(r, w2, M, Hp_unit, Hprior, sigma_cfg, prior_dof, assemble) -> tuple[float, float, float]:
    """(pixel sigma pooled with the configured one at ``prior_dof``, the residuals' own, their degrees of
    freedom)."""
    sig = sigma_cfg
    for _ in range(2):
        H, Hi = assemble(sig)
        p_eff = float(np.trace(Hi @ (Hp_unit / sig**2)))
        dof = max(2.0 * M - p_eff, 0.0)
        if dof > 1e-6:
            sigma_hat = math.sqrt(float(np.sum(r**2)) / (float(np.sum(w2)) * dof / (2.0 * M)))
        else:
            sigma_hat = float("nan")
        nu0 = prior_dof
        s2 = (dof * (sigma_hat**2 if dof > 1e-6 else 0.0) + nu0 * sigma_cfg**2) / (dof + nu0) if dof + nu0 > 0 \
            else sigma_cfg**2
        sig = max(math.sqrt(s2), 0.1 * sigma_cfg)
    return sig, sigma_hat, dof


def _shared_misfit(J: np.ndarray, groups: np.ndarray, views: np.ndarray, uv: np.ndarray,
                   w: np.ndarray, scale: Sequence[float] | None = None) -> np.ndarray:
    """``sum_g (J_g^T W_g B_g)(J_g^T W_g B_g)^T`` (P, P): the gradient covariance, per pixel^2 of shared misfit,
    of each group's common affine displacement. ``J``: weighted rows (2M, P); ``groups`` (M,) with -1 for none;
    ``views`` (M,) view index; ``uv`` (M, 2) observed pixels; ``w`` (M,) row weights.

    Six modes, their coefficients shared by the group's points in every view (a face's misfit is in the face,
    so it repeats from photo to photo): a shift in u and in v, and the four affine terms ``(u - u_c) / s_u``,
    ``(v - v_c) / s_v`` in u and in v, with the centroid and the RMS spreads ``s_u``, ``s_v`` of the group's
    points in that view (each mode of unit RMS size there; only the shifts where a view has fewer than 3).
    ``scale``: per group (in sorted order) a factor on its term (its own misfit variance), else 1."""
    P = J.shape[1]
    out = np.zeros((P, P))
    for i, g in enumerate(np.unique(groups[groups >= 0])):
        A = np.zeros((P, 6))
        for v in np.unique(views[groups == g]):
            idx = np.nonzero((groups == g) & (views == v))[0]
            n = len(idx)
            d = uv[idx] - uv[idx].mean(0)
            s = np.sqrt(np.mean(d**2, axis=0))
            B = np.zeros((2 * n, 6))
            B[0::2, 0] = 1.0
            B[1::2, 1] = 1.0
            if n >= 3:
                for j in range(2):
                    if s[j] > 1e-6:
                        B[0::2, 2 + j] = d[:, j] / s[j]
                        B[1::2, 4 + j] = d[:, j] / s[j]
            rows = np.stack([2 * idx, 2 * idx + 1], axis=1).reshape(-1)
            A += J[rows].T @ (B * np.repeat(w[idx], 2)[:, None])
        out += (1.0 if scale is None else float(scale[i])) * (A @ A.T)
    return out


def _hpr_jac(Rk: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """d (heading, pitch, roll) / d scene rotation vector (degrees per radian), central differences."""
    J = np.zeros((3, 3))
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        hp = np.array(hpr_from_rotation(exp_so3(d) @ Rk))
        hm = np.array(hpr_from_rotation(exp_so3(-d) @ Rk))
        diff = hp - hm
        diff[0] = (diff[0] + 180.0) % 360.0 - 180.0
        diff[2] = (diff[2] + 180.0) % 360.0 - 180.0
        J[:, i] = diff / (2 * eps)
    return J  # degrees per radian


def body_centre_cov(model: CovarianceModel, cars, R, k: int) -> np.ndarray:
    """(3, 3) covariance of carriage ``k``'s body centre."""
    c = model.col[k]
    Jb = np.hstack([-skew(R[k] @ cars[k].c_body), np.eye(3)])
    C = model.cov[c:c + 6, c:c + 6]
    return Jb @ C @ Jb.T


def solution_model(prob: Problem, poses: Poses, focal_views, chains: Chains, contact,
                   options: SolveOptions) -> CovarianceModel:
    """:func:`covariance_model` at a solution with the solve's options."""
    return covariance_model(prob, poses.R, poses.t, poses.f, focal_views, chains.members, chains.slacks, contact,
                            options.pixel_sigma_px,
                            options.robust_loss, options.loss_scale_px, options.prior_dof,
                            face_sigma=options.face_sigma_px)


def pose_determined(C: np.ndarray, rtol: float = 1e-9) -> bool:
    """Whether a carriage's (6, 6) pose covariance is a covariance: finite and positive semi-definite to within
    rounding (its least eigenvalue no lower than ``-rtol`` times its largest). Not so when the information it
    inverts is numerically singular (a carriage whose measured points do not fix its pose: its predictions
    placed it), where the computed variances are rounding noise, some of them negative."""
    C = np.asarray(C, dtype=float)
    if not np.all(np.isfinite(C)):
        return False
    ev = np.linalg.eigvalsh(0.5 * (C + C.T))
    return bool(ev[0] >= -rtol * max(ev[-1], 0.0))


def _set_pose_covariance(cr: Any, C: np.ndarray, R: np.ndarray, lever: np.ndarray, q: float,
                         determined: bool = True) -> np.ndarray:
    """Set a carriage result's ``covariance_pose`` (6, 6: scene rotation vector, origin) and the sigmas and 95 %
    half widths (``q`` sigmas) of its origin, body centre and heading / pitch / roll that follow from it (all None,
    no interval, when the data leave the pose ``determined`` False or the covariance is not one:
    :func:`pose_determined`).
    ``R`` (3, 3) its rotation, ``lever`` (3,) the body centre minus the origin in the scene frame (m). Returns
    the body centre's Jacobian (3, 6)."""
    if not (determined and pose_determined(C)):
        # the measured points leave a direction of the pose undetermined (the inverse of a numerically singular
        # information): its variances are rounding noise, and negative ones clipped to 0 would read "exact"
        cr.covariance_pose = None
        cr.sigma_position_m = cr.ci95_position_m = cr.sigma_body_centre_m = cr.ci95_body_centre_m = None
        cr.sigma_hpr_deg = cr.ci95_hpr_deg = None
        return np.hstack([-skew(lever), np.eye(3)])
    cr.covariance_pose = C
    sp = np.sqrt(np.maximum(np.diag(C[3:, 3:]), 0))
    cr.sigma_position_m, cr.ci95_position_m = sp, q * sp
    Jb = np.hstack([-skew(lever), np.eye(3)])
    sb = np.sqrt(np.maximum(np.diag(Jb @ C @ Jb.T), 0))
    cr.sigma_body_centre_m, cr.ci95_body_centre_m = sb, q * sb
    Jh = _hpr_jac(R)
    sh = np.sqrt(np.maximum(np.diag(Jh @ C[:3, :3] @ Jh.T), 0))
    cr.sigma_hpr_deg, cr.ci95_hpr_deg = sh, q * sh
    return Jb


def misfit_carriages(prob: Problem, poses: Poses, sigma: float, p_value: float = 1e-4,
                     relative: float = 4.0) -> dict[int, float]:
    """The carriages whose measured points the solution does not fit, as the branch check judges a misfit
    (:func:`.branches.misfit_cars`: chi-square at ``sigma`` beyond its (1 - ``p_value``) quantile with 2 n - 6
    degrees of freedom, *and* more than ``relative`` times the median carriage's misfit per row), on the measured
    points alone (a prediction's residual says how far its face's pose was off, not that the fit failed).
    Returns carriage -> RMS residual (px) of its measured points. Such a carriage sits on a wrong branch or on
    mismatched points the branch check and the outlier rejection did not cure, and the noise model its interval
    rests on does not hold for it; or its points share a misfit (``face_sigma_px``) this test does not model,
    so it warns and keeps the interval (docs/calibration.md: 1 gross failure and 5 sound intervals among 6 flags
    on the automatic route)."""
    uv, *_ = prob.project(poses.R, poses.t, poses.f)
    scale = prob.w / np.where(prob.w_noise > 0, prob.w_noise, 1.0)  # each point's own sigma, relative
    e2 = np.sum(((uv - prob.uv) * scale[:, None] / sigma) ** 2, axis=1)
    r2 = np.sum((uv - prob.uv) ** 2, axis=1)
    meas = getattr(prob, "measured", None)
    meas = np.ones(len(e2), bool) if meas is None or len(meas) != len(e2) else meas
    chi = {}
    for k, idx in prob.by_car.items():
        idx = idx[meas[idx]]
        if len(idx):
            chi[k] = (float(np.sum(e2[idx])), 2 * len(idx), float(np.sqrt(np.mean(r2[idx]))))
    med = float(np.median([x / m for x, m, _ in chi.values()])) if chi else 0.0
    return {k: rms for k, (x, m, rms) in chi.items()
            if x > 2.0 * float(gammaincinv(max(m - 6, 1) / 2, 1.0 - p_value)) and x / m > relative * med}


def attach_covariance(res, prob: Problem, poses: Poses, focal_views, chains: Chains, contact, options: SolveOptions,
                      model: CovarianceModel | None = None) -> None:
    """Fill the covariance fields of a :class:`SolveResult` in place. ``model``: a :func:`solution_model` already
    computed (at the least-squares minimum, when the reported ``poses`` are bias-corrected: the pixel sigma is
    estimated from the minimum's residuals and the intervals are centred on the reported poses)."""
    if model is None:
        model = solution_model(prob, poses, focal_views, chains, contact, options)
    R = poses.R
    cov, col, q = model.cov, model.col, model.q
    res.sigma_px = model.sigma
    res.sigma_px_estimated = model.sigma_hat
    res.face_sigma_px = model.face_sigma
    res.noise_estimated = model.components is not None
    res.dof = model.dof
    res.ci95_factor = q
    res.covariance = cov
    order = []
    for k in prob.active:
        n = prob.cars[k].number
        order += [f"{n}.omega_x", f"{n}.omega_y", f"{n}.omega_z", f"{n}.x", f"{n}.y", f"{n}.z"]
    order += ["focal." + "+".join(prob.views[v].name for v in grp) for grp in focal_views]
    res.covariance_order = order
    Jbs = {}
    misfit = misfit_carriages(prob, poses, model.sigma)
    for k in prob.active:
        cr = res.carriages[k]
        c = col[k]
        determined = model.undetermined is None or not model.undetermined[c:c + 6].any()
        Jbs[k] = _set_pose_covariance(cr, cov[c:c + 6, c:c + 6], R[k], R[k] @ prob.cars[k].c_body, q, determined)
        if k in misfit and cr.covariance_pose is not None:
            record_warning(res.warnings, prob.cars[k], "misfit",
                           f"car {cr.number}: the solution does not fit its points (RMS {misfit[k]:.1f} px against "
                           f"a pixel sigma of {model.sigma:.2f} px): a wrong branch or mismatched points; its "
                           f"pose and its interval are doubtful")
        elif cr.covariance_pose is None:
            record_warning(res.warnings, prob.cars[k], "undetermined",
                           f"car {cr.number}: its measured points do not determine its pose (predictions or the "
                           f"chain placed it); no interval is given")
    for i, grp in enumerate(focal_views):
        j = 6 * len(prob.active) + i
        for v in grp:
            res.sigma_focal_px[prob.views[v].name] = float(math.sqrt(max(cov[j, j], 0.0))) \
                if model.undetermined is None or not model.undetermined[j] else math.inf
    for ch in chains.members:
        for j in range(len(ch) - 1):
            a, b = ch[j], ch[j + 1]
            if res.carriages[a].covariance_pose is None or res.carriages[b].covariance_pose is None:
                continue  # no interval, no correlation
            ca, cb = col[a], col[b]
            Caa = Jbs[a] @ cov[ca:ca + 6, ca:ca + 6] @ Jbs[a].T
            Cbb = Jbs[b] @ cov[cb:cb + 6, cb:cb + 6] @ Jbs[b].T
            Cab = Jbs[a] @ cov[ca:ca + 6, cb:cb + 6] @ Jbs[b].T
            sa, sb = np.sqrt(np.diag(Caa)), np.sqrt(np.diag(Cbb))
            corr = Cab / np.outer(sa, sb)
            res.neighbour_correlation.append({"front": prob.cars[a].number, "rear": prob.cars[b].number,
                                              "body_centre_corr_enu": corr,
                                              "axis_corr_enu": np.diag(corr)})


def crb(carriages: Sequence[Any], links: Sequence[Any], views: Sequence[Any], world_from_carriage: Sequence[np.ndarray],
        sigma_px: float, estimate_focal: bool = False, weighting: str = "per_carriage") -> dict:
    """Cramér-Rao bound of the chained problem at the truth (noise-free pixels are not needed: only the
    Jacobian is used). Held couplings (links with a slack) are modelled as in the covariance (soft prior,
    sigma_T = slack/sqrt(5)); ``estimate_focal`` adds one focal per view as a parameter.

    ``weighting`` (as :attr:`SolveOptions.weighting`): ``"per_point"`` gives the bound proper (every point
    1 / sigma^2: the maximum-likelihood information, the least covariance any unbiased estimator can have);
    ``"per_carriage"`` weights each carriage's rows as the solver's per-carriage normalisation does
    (``w_i = sqrt(n_mean / n_i)``) and returns *that estimator's* asymptotic (sandwich) covariance
    ``H^-1 G H^-1``, which is the bound when every carriage shows the same number of points (all weights 1) and
    exceeds it otherwise. Compare an estimator with the covariance of its own weighting, and both with the
    ``"per_point"`` bound.

    Returns ``{"body_centre_cov": [(3, 3)] per carriage, "rotation_cov": [(3, 3)], "origin_cov": [(3, 3)],
    "focal_sigma": [...], "weighting": weighting}``.
    """
    opts = SolveOptions(check_image_bounds=False, weighting=weighting)  # validates ``weighting``
    cars = prepare_cars(carriages, views, opts)
    N = len(cars)
    active = list(range(N))
    prob = Problem(cars, active, views, carriage_weights(cars, active, opts.weighting))
    R = np.array([np.asarray(M, float)[:3, :3] for M in world_from_carriage])
    t = np.array([np.asarray(M, float)[:3, 3] for M in world_from_carriage])
    f = np.array([v.intrinsics.fx for v in views], dtype=float)
    chains, slacks = held_chains(N, links)

    fv = focal_groups(views, list(range(len(views)))) if estimate_focal else []
    prob.uv = prob.project(R, t, f)[0]  # residuals zero at the truth
    model = covariance_model(prob, R, t, f, fv, chains, slacks, None, sigma_px, sigma_fixed=sigma_px)
    out = {"body_centre_cov": [], "rotation_cov": [], "origin_cov": [], "focal_sigma": [], "weighting": weighting}
    for k in active:
        c = model.col[k]
        out["body_centre_cov"].append(body_centre_cov(model, cars, R, k))
        out["rotation_cov"].append(model.cov[c:c + 3, c:c + 3])
        out["origin_cov"].append(model.cov[c + 3:c + 6, c + 3:c + 6])
    for i in range(len(fv)):
        j = 6 * N + i
        out["focal_sigma"].append(float(math.sqrt(model.cov[j, j])))
    return out


def camera_pose_jacobian(world_from_carriage: np.ndarray, centre_enu: np.ndarray) -> np.ndarray:
    """(6, 6) derivative of a carriage's pose parameters (scene rotation vector ``w``, origin ``t``: the order of
    ``covariance_pose``) with respect to a rigid error of the camera (rig) pose: a rotation ``d_theta`` (rad,
    scene frame) about the camera centre ``centre_enu`` (3,) and a shift ``d_c`` (m) of that centre.

    Poses solved from pixels move with the camera: ``R' = Exp(d_theta) R``, ``t' = c + d_c + Exp(d_theta) (t - c)``,
    so ``d_w = d_theta`` and ``d_t = d_c - [t - c]x d_theta``."""
    M = np.asarray(world_from_carriage, dtype=float)
    A = np.eye(6)
    A[3:, :3] = -skew(M[:3, 3] - np.asarray(centre_enu, dtype=float))
    return A


def add_camera_uncertainty(res: Any, centre_enu: np.ndarray, cov_camera: np.ndarray) -> list[str]:
    """Add the georegistration's uncertainty of the camera pose to every carriage's covariance, in place.

    ``cov_camera`` (6, 6): covariance of the camera's scene rotation vector (rad) and centre (m, ENU), as the
    georef stage writes it (``georegistration.covariance_world_rotation_centre``). The fit's covariance
    (``covariance_pose``) is that of the poses *relative to the camera*; a carriage's scene pose is the camera's
    pose composed with it, so to first order its covariance is ``C_fit + A C_cam A^T``
    (:func:`camera_pose_jacobian`; the two errors are independent: the control points are not the marked
    points). The sigmas and 95 % intervals (position, body centre, heading / pitch / roll) are recomputed from
    the sum with the fit's ``ci95_factor``; ``res.covariance`` (the fit's joint covariance, of which the
    neighbour correlations are computed) stays the fit's: the camera moves every carriage together and does not
    change where one lies relative to the next. Returns the numbers of the carriages changed."""
    C_cam = np.asarray(cov_camera, dtype=float)
    if C_cam.shape != (6, 6) or not np.all(np.isfinite(C_cam)):
        raise ValueError(f"camera covariance must be a finite (6, 6) matrix, got shape {C_cam.shape}")
    extra = {}
    for cr in res.carriages:
        if cr.world_from_carriage is not None:
            A = camera_pose_jacobian(np.asarray(cr.world_from_carriage, dtype=float), centre_enu)
            extra[cr.number] = A @ C_cam @ A.T
    return list(add_pose_covariance(res, extra))


def add_pose_covariance(res: Any, extra: dict[str, np.ndarray]) -> dict[str, dict]:
    """Add ``extra[number]`` (6, 6: scene rotation vector, origin) to that carriage's ``covariance_pose``, in place,
    and recompute its sigmas and 95 % intervals with the fit's ``ci95_factor`` (carriages without an interval
    are left as they are). Returns, per carriage changed, the sigmas of the term alone: ``sigma_hpr_deg`` (3,),
    ``sigma_body_centre_m`` (3,)."""
    q = float(res.ci95_factor) if getattr(res, "ci95_factor", None) else 1.959963984540054
    out = {}
    for cr in res.carriages:
        if cr.number not in extra or cr.covariance_pose is None or cr.world_from_carriage is None \
                or cr.body_centre_m is None:
            continue
        M = np.asarray(cr.world_from_carriage, dtype=float)
        X = np.asarray(extra[cr.number], dtype=float)
        C = np.asarray(cr.covariance_pose, dtype=float) + X
        Jb = _set_pose_covariance(cr, 0.5 * (C + C.T), M[:3, :3],
                                  np.asarray(cr.body_centre_m, dtype=float) - M[:3, 3], q)
        Jh = _hpr_jac(M[:3, :3])
        out[cr.number] = {"sigma_hpr_deg": np.sqrt(np.maximum(np.diag(Jh @ X[:3, :3] @ Jh.T), 0.0)).tolist(),
                          "sigma_body_centre_m": np.sqrt(np.maximum(np.diag(Jb @ X @ Jb.T), 0.0)).tolist()}
    return out


def view_information(world_from_carriage: np.ndarray, rows: dict[int, tuple[np.ndarray, np.ndarray]],
                     views: Sequence[Any]) -> dict[int, np.ndarray]:
    """Each view's pixel information (6, 6) on one carriage's pose parameters (scene rotation vector, origin: the
    order of ``covariance_pose``) at ``world_from_carriage`` (4, 4). ``rows``: view index -> (the measured
    points (n, 3) in the carriage frame, their weights (n,): 1 / sigma^2 in px^-2)."""
    M = np.asarray(world_from_carriage, dtype=float)
    out = {}
    for v, (P, w) in rows.items():
        _, J, _ = project_with_jacobians(P, M[:3, :3], M[:3, 3], views[v].cam_from_world, views[v].intrinsics, ())
        out[v] = np.einsum("nai,n,naj->ij", J, np.asarray(w, float), J)
    return out


def view_shares(info: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """``W_v = H^-1 H_v`` (6, 6) per view, ``H = sum_v H_v``: how a carriage's pose follows each view's camera
    when the cameras move apart (the first-order response of its least-squares pose to a shift of view ``v``'s
    pixels, each view's shift being the one that camera's own error would cause); the ``W_v`` sum to I, so a
    motion common to every camera moves the carriage with it exactly. Where ``H`` is singular (the pose rests on
    the chain as well), scalar shares ``trace H_v / trace H`` times I."""
    H = sum(info.values())
    ev = np.linalg.eigvalsh(0.5 * (H + H.T))
    if ev[0] > 1e-10 * max(ev[-1], 1e-300):
        return {v: np.linalg.solve(H, Hv) for v, Hv in info.items()}
    tr = float(np.trace(H))
    return {v: (float(np.trace(Hv)) / tr if tr > 0 else 1.0 / len(info)) * np.eye(6) for v, Hv in info.items()}


def _measured_rows(cin: Any, cr: Any, vindex: dict[str, int], pixel_sigma_px: float
                   ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """A solved carriage's measured points in its final fit (its residuals' rows, predictions left out), per view
    index: (points (n, 3) in the carriage frame, weights (n,): (pixel sigma / the point's sigma)^2)."""
    rows: dict[int, tuple[list, list]] = {}
    for vname, pts in (cr.residuals_px or {}).items():
        for p in pts:
            o = (cin.observations.get(vname) or {}).get(p)
            if o is None or getattr(o, "derived", False) or vname not in vindex:
                continue
            sig = getattr(o, "sigma_px", None) or pixel_sigma_px
            P, w = rows.setdefault(vindex[vname], ([], []))
            P.append(cin.carriage_type.marked_points[p])
            w.append((pixel_sigma_px / float(sig)) ** 2)
    return {v: (np.asarray(P, float), np.asarray(w, float)) for v, (P, w) in rows.items()}


def _coupler_information(links: Sequence[Any], carriages: Sequence[Any], res: Any, pos: dict[int, int],
                         P: int) -> np.ndarray:
    """(P, P) information of the held couplings' offset prior (``T ~ N(0, (slack / sqrt 5)^2 I)``, as the
    covariance) between carriages both in ``pos`` (consist index -> block)."""
    H = np.zeros((P, P))
    for L in links:
        a, b = int(L.front), int(L.rear)
        if L.slack_m is None or a not in pos or b not in pos:
            continue
        Ra = np.asarray(res.carriages[a].world_from_carriage, float)[:3, :3]
        Rb = np.asarray(res.carriages[b].world_from_carriage, float)[:3, :3]
        JT = np.zeros((3, P))
        ca, cb = 6 * pos[a], 6 * pos[b]
        JT[:, ca:ca + 3] = skew(Ra @ np.asarray(carriages[a].carriage_type.coupler_rear, float))
        JT[:, ca + 3:ca + 6] = -np.eye(3)
        JT[:, cb:cb + 3] = -skew(Rb @ np.asarray(carriages[b].carriage_type.coupler_front, float))
        JT[:, cb + 3:cb + 6] = np.eye(3)
        H += JT.T @ JT / (float(L.slack_m) / math.sqrt(5.0)) ** 2
    return H


def add_view_camera_uncertainty(res: Any, carriages: Sequence[Any], links: Sequence[Any], views: Sequence[Any],
                                pixel_sigma_px: float, model_covariance: dict[str, np.ndarray],
                                jacobian: dict[str, tuple[str, np.ndarray]], own_covariance: dict[str, np.ndarray],
                                weighting: str = "per_carriage") -> dict[str, dict]:
    """Add the multi-view cameras' pose uncertainty to every carriage's covariance, in place (first order).

    A view's pose error ``e_v`` (6: scene rotation vector of ``world_from_cam``, centre) is ``J_v e_m`` for a view
    placed by SfM model ``m``'s similarity (``jacobian[view] = (m, J_v)``; ``e_m`` of covariance
    ``model_covariance[m]`` (7, 7), shared by all of ``m``'s views, so their errors are correlated) or its own
    (``own_covariance[view]`` (6, 6), independent). The carriages' poses respond as the least squares does:
    ``dx = H^-1 sum_v H_v A_v e_v``, with ``H_v`` view ``v``'s pixel information on every carriage's pose
    (their measured points, the carriage weighting, the pixel sigma ``res.sigma_px``), ``H`` all of it plus the
    held couplings' prior, and ``A_v`` (:func:`camera_pose_jacobian` about view ``v``'s centre) the poses that keep
    view ``v``'s pixels: a carriage seen in one view moves with that camera (as the central route's
    :func:`add_camera_uncertainty`), a motion common to all cameras moves every carriage rigidly with it, and the
    scale moves each by its cameras' information-weighted shifts. The terrain contact's resistance is not
    modelled (the carriages move as on pixels alone, as on the central route). Predictions
    (``Observation.derived``) carry no information and take no share. The fit's joint covariance
    ``res.covariance`` stays the fit's. Returns carriage number -> {"views": view -> its share of the carriage's
    own information (trace of ``H_k^-1 H_kv`` / 6), "not_modelled": the views it is measured in whose error is
    not modelled}."""
    q = float(res.ci95_factor) if getattr(res, "ci95_factor", None) else 1.959963984540054
    vindex = {v.name: i for i, v in enumerate(views)}
    centres = [-np.asarray(v.cam_from_world, float)[:3, :3].T @ np.asarray(v.cam_from_world, float)[:3, 3]
               for v in views]
    info: dict[int, dict[int, np.ndarray]] = {}
    counts: dict[int, int] = {}
    for k, (cin, cr) in enumerate(zip(carriages, res.carriages)):
        if cr.covariance_pose is None or cr.world_from_carriage is None or cr.body_centre_m is None:
            continue
        rows = _measured_rows(cin, cr, vindex, pixel_sigma_px)
        if rows:
            info[k] = view_information(cr.world_from_carriage, rows, views)
            counts[k] = sum(len(w) for _, w in rows.values())
    if not info:
        return {}
    pos = {k: i for i, k in enumerate(info)}
    P = 6 * len(pos)
    n_mean = float(np.mean(list(counts.values())))
    sig = float(res.sigma_px) if math.isfinite(float(getattr(res, "sigma_px", math.nan))) else pixel_sigma_px
    H = _coupler_information(links, carriages, res, pos, P)
    G = {v: np.zeros((P, 6)) for v in range(len(views))}  # H_v A_v
    for k, per_view in info.items():
        c = 6 * pos[k]
        w2 = (n_mean / counts[k] if weighting == "per_carriage" else 1.0) / sig**2
        M = np.asarray(res.carriages[k].world_from_carriage, float)
        for v, Hkv in per_view.items():
            H[c:c + 6, c:c + 6] += w2 * Hkv
            G[v][c:c + 6] += w2 * Hkv @ camera_pose_jacobian(M, centres[v])
    Hi = inverse_psd(0.5 * (H + H.T))
    C_cam = np.zeros((P, P))
    B: dict[str, np.ndarray] = {}
    missing: set[str] = set()
    for v, Gv in G.items():
        if not Gv.any():
            continue
        Rv = Hi @ Gv  # (P, 6): every carriage's response to view v's pose error
        name = views[v].name
        if name in jacobian:
            label, J = jacobian[name]
            B[label] = B.get(label, np.zeros((P, np.shape(J)[1]))) + Rv @ np.asarray(J, float)
        elif name in own_covariance:
            C_cam += Rv @ np.asarray(own_covariance[name], float) @ Rv.T
        else:
            missing.add(name)
    for label, Bm in B.items():
        C_cam += Bm @ np.asarray(model_covariance[label], float) @ Bm.T
    out = {}
    for k, i in pos.items():
        cr = res.carriages[k]
        M = np.asarray(cr.world_from_carriage, dtype=float)
        C = np.asarray(cr.covariance_pose, dtype=float) + C_cam[6 * i:6 * i + 6, 6 * i:6 * i + 6]
        _set_pose_covariance(cr, 0.5 * (C + C.T), M[:3, :3], np.asarray(cr.body_centre_m, dtype=float) - M[:3, 3], q)
        shares = view_shares(info[k])
        out[cr.number] = {"views": {views[v].name: float(np.trace(W)) / 6.0 for v, W in shares.items()},
                          "not_modelled": sorted(views[v].name for v in info[k] if views[v].name in missing)}
    return out
