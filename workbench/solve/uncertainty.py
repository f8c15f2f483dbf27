"""Covariance of the chained pose solution, and the Cramér-Rao bound of the same model.

Parameters: per carriage a scene-frame rotation vector and the origin (6), plus each estimated focal (px).
Held couplings enter as the soft prior ``T ~ N(0, (slack / sqrt 5)^2 I)`` (not the solver's hard bound), the
weighting through the sandwich ``H^-1 G H^-1`` (``H`` the information of the cost the solver minimises, pixels at the
configured sigma against the priors; ``G`` the gradient's covariance, the pixels' noise at the pixel sigma pooled
with the configured one), pose predictions with their face alignment's error (the others not at all), a face's
shared misfit in ``G``. Each carriage's
response to a camera motion (:func:`camera_responses`) for the camera term (:mod:`.camera_term`).
``docs/solver.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy.special import stdtrit  # the quantile as scipy.stats computes it (2 s to import)

from ..core.geometry import skew
from .model import SolveOptions
from .problem import (Chains, Poses, Problem, carriage_weights, focal_groups, held_chains, prepare_cars,
                      record_warning)
from .camera_term import inverse_psd, set_camera_response, set_pose_covariance
from .alignment_covariance import alignment_term, guided_loadings, photo_affine_modes, views_per_face
from .loss import chi2_quantile
from .pose_covariance import carried_rows, merged_rows, pose_rows
from .camera_residual import ViewCameraErrors, camera_directions, camera_shift_rows
from .variance_components import (FALLBACK_FACE_SIGMA_PX, VarianceComponents, estimate_variance_components,
                                  face_modes)

# px of shared misfit (per affine mode) of a face aligned by ECC without matches of its own, per unit of 1 - its
# ECC correlation. Measured against the truth on 91 such faces of the automatic route (seeds 237000-237067, 800 x
# 600 photos; docs/calibration.md, "Session 23"), the points' own noise taken out: 0.12 px at 1 - ecc = 0.014,
# 0.25 at 0.024, 0.45 at 0.036, 0.74 at 0.058 (10 by the moments). The model shares a face's misfit across its
# photos in full, which carries it to the poses more than that: 10 made those carriages' intervals too wide
# (RMS of error over sigma 0.76-0.86 in east, north, up and heading), 4 too narrow in heading (1.16), 6 gave
# 0.86-1.00 there (the same incidents)
ECC_MISFIT_PX = 6.0
# A face aligned from matches of its own takes its points' error from its alignment's loading (docs/
# correspondences.md), which its matches measure; where its reference matched the photo less closely than
# ``1 - ALIGNED_ECC_FREE``, its points are off by more than that (the reference's texture is not the photo's there,
# and the matches' scatter does not show the difference): a misfit shared by the face's points of
# ALIGNED_ECC_MISFIT_PX px per affine mode per unit of ECC correlation below it is added to the loading. Measured
# against the truth on 942 aligned faces of the automatic route (seeds 237000-237067 and 238000-238067, 800 x 600
# photos; docs/calibration.md, "Session 25"): the points' RMS error over the loading's RMS was 0.82-1.01 for
# 1 - ecc under 0.03 (853 faces), 1.33 and 1.83 above (89 faces); with the term 0.82-1.12 in every band
ALIGNED_ECC_FREE = 0.02
ALIGNED_ECC_MISFIT_PX = 5.0
# A guided face's points (aligned by ECC without matches) are placed by one warp: beyond the face's misfit (the six
# affine modes) their errors against the truth have 0.105 px per coordinate (226 guided faces of 4 or more points
# of seeds 237000-, 238000-, 239000-, the least-squares affine fit per face and photo taken out, 2 n - 6 degrees of
# freedom; docs/calibration.md, "Session 25"), where the pooled pixel sigma is 0.35 px (median). Not in the bound
# at a fixed sigma (CRB) nor where the noise and the faces' misfits are estimated together (variance components)
GUIDED_NOISE_PX = 0.1


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
    face_misfit_max: float = math.nan  # the largest of the faces' own misfits from their ECC (face_misfit_px)
    components: VarianceComponents | None = None  # when both were estimated from the residuals
    camera_px: float = math.nan  # the residuals' RMS (px) along the directions the multi-view cameras' errors fill
    aligned_misfit_max: float = math.nan  # the largest misfit added to an aligned face's loading (aligned_misfit_px)


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
                     use_alignments: bool = True, views_shared: bool = True, count_pose: bool = True,
                     camera_errors: ViewCameraErrors | None = None, guided_loading: bool = True,
                     count_carried: bool = True) -> CovarianceModel:
    """Covariance in free-pose parameters at ``R, t, f`` (see the module doc). ``sigma_fixed``: use that pixel
    sigma (CRB); ``face_sigma``: pixels of the misfit shared by each group of points; ``use_alignments``: the
    points with a face alignment's loading (``Problem.loading``) take their error from it (:func:`alignment_term`)
    in place of the pixel sigma and the fixed misfit (docs/correspondences.md, "What a face's alignment
    measures"); ``views_shared``: a face's error is shared by the photos it is aligned in (:func:`views_per_face`),
    not independent from photo to photo; ``count_pose``: the pose predictions too (:mod:`.pose_covariance`);
    ``camera_errors``: the multi-view photos' stated errors; the residual directions they fill are set aside when
    the pixel sigma is pooled (:mod:`.camera_residual`; not in the variance-component split of automatic points'
    noise and faces' misfit, ``face_sigma`` None). ``guided_loading``: a guided face's misfit is its alignment's
    loading, shared by its pose predictions (:func:`.alignment_covariance.guided_loadings`); ``count_carried``: the
    points carried from another photo count with their source's error (:func:`.pose_covariance.carried_rows`); both
    with ``count_pose`` (False: as before session 31, what step 4's decisions judge by: ``steps.DECISIONS_MODEL``)."""
    J, r, col, P = pixel_rows(prob, R, t, f, focal_views)
    D = camera_shift_rows(prob, R, t, J, col, camera_errors) if camera_errors is not None else None
    groups, block, loading, ecc = _row_arrays(prob)
    # points of faces aligned by ECC without matches of their own (an ECC, no alignment): placed by one warp, their
    # error is the face's (the shared misfit below) and a remainder of GUIDED_NOISE_PX, not the pooled pixel noise
    own = block if block is not None and len(block) == len(prob.P) else np.full(len(prob.P), -1)
    guided_pt = np.isfinite(ecc) & (own < 0) & (sigma_fixed is None) & (face_sigma is not None)
    if not use_alignments or block is None or len(block) != len(prob.P) or sigma_fixed is not None \
            or face_sigma is None:
        block, loading = np.full(len(prob.P), -1), np.zeros((len(prob.P), 2, 8))
    own_aligned = block >= 0  # faces aligned from matches of their own
    guided_blk = np.zeros(len(prob.P), dtype=bool)
    if count_pose and use_alignments and guided_loading and guided_pt.any():  # its misfit: its alignment's loading
        block, loading, guided_blk = guided_loadings(block, loading, guided_pt & (groups >= 0), groups, prob.view,
                                                     prob.uv, face_misfit_px(ecc, face_sigma))
    pose = _prediction_rows(prob, J, r, col, block, loading, loss, loss_scale, views_shared, count_carried) \
        if count_pose and (block >= 0).any() else None
    uv_obs, w_row, views = prob.uv, prob.w, prob.view
    # predictions (points projected from a face's pose, points carried from another photo) guide the fit but
    # are functions of the measured points: counting them would claim information twice
    meas = getattr(prob, "measured", None)
    if meas is not None and len(meas) == len(prob.P) and not meas.all():
        keep = np.repeat(meas, 2)
        J, r = J[keep], r[keep]
        D = D[keep] if D is not None else None
        groups, uv_obs, w_row, views = groups[meas], uv_obs[meas], w_row[meas], views[meas]
        block, loading, ecc, guided_pt = block[meas], loading[meas], ecc[meas], guided_pt[meas]
        own_aligned, guided_blk = own_aligned[meas], guided_blk[meas]
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
    guided = np.repeat(guided_pt & (groups >= 0), 2)
    Gp_unit = (J * (rho**2 * w2 * ~aligned * ~guided)[:, None]).T @ J
    Gg_unit = (J * (rho**2 * w2 * guided)[:, None]).T @ J
    Hprior = _prior_info(prob.cars, R, t, chains, slacks, col, P) + _contact_info(contact, R, t, col, P, sigma_cfg)

    def assemble(sig):
        H = Hp_unit / sig**2 + Hprior
        Hi = inverse_psd(H)
        return H, Hi

    cam_dirs = None if D is None else camera_directions(D * np.sqrt(rho)[:, None], J * np.sqrt(rho)[:, None],
                                                        camera_errors.covariance, sigma_cfg**2 * w2, assemble,
                                                        sigma_cfg)
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
    elif own_aligned.all() and len(own_aligned):
        # every measured point's error is its alignment's, known from its matches (2 N - 8 residual degrees of
        # freedom each, N >= 8): the pixel sigma is no point's error (and the cost's weights are the configured's)
        sigma, sigma_hat, dof, q = _pooled_sigma(r, w2, M, Hp_unit, Hprior, sigma_cfg, prior_dof, assemble,
                                                 cam_dirs) + (1.959963984540054,)
    else:
        sigma, sigma_hat, dof = _pooled_sigma(r, w2, M, Hp_unit, Hprior, sigma_cfg, prior_dof, assemble, cam_dirs)
        q = float(stdtrit(dof + prior_dof, 0.975)) if dof + prior_dof > 0 else 1.959963984540054
    Hp_unit = Hp_unit + (pose.info if pose is not None else 0.0)  # the fit's weights on the counted predictions
    # the sandwich of the estimator the solve runs: its cost weighs the pixels at the configured sigma against the
    # priors (the contact's scale, the couplers' prior_px), so H is that cost's information, and G the gradient's
    # covariance with the pixels' noise at ``sigma``; where ``sigma`` is not the configured one, a cost that
    # leans on a prior more (or less) than the noise would have it carries that prior's error to the poses
    sw = sigma if sigma_fixed is not None else sigma_cfg
    H, Hi = assemble(sw)
    G = Gp_unit * (sigma**2 / sw**4) + Gg_unit * (GUIDED_NOISE_PX**2 / sw**4) + Hprior
    misfit_groups = np.where(block >= 0, -1, groups)  # an aligned point's face error is its alignment's
    aligned_max = math.nan
    face_max = float(face_misfit_px(ecc[guided_blk], face_sigma).max()) if guided_blk.any() else math.nan
    if vc is not None and vc.face_sigmas_px:  # each face its own misfit
        G = G + _shared_misfit(J * rho[:, None], groups, views, uv_obs, w_row,
                               np.square(vc.face_sigmas_px)) / sw**4
    elif face_sigma > 0 and (misfit_groups >= 0).any():
        G_face, own_max = _ecc_misfit(J * rho[:, None], misfit_groups, ecc, face_sigma, views, uv_obs, w_row)
        G = G + G_face / sw**4
        face_max = own_max if math.isnan(face_max) else max(face_max, own_max)
    if (block >= 0).any():
        G = G + alignment_term(J * rho[:, None], block, loading, w_row, pose and pose.contrib) / sw**4
        G_excess, aligned_max = _aligned_excess(J * rho[:, None], np.where(guided_blk, -1, block), ecc, groups,
                                                views, uv_obs, w_row)
        G = G + G_excess / sw**4
    cov = Hi @ G @ Hi
    cov = 0.5 * (cov + cov.T)
    camera_px = math.nan if cam_dirs is None or not cam_dirs.shape[1] else \
        math.sqrt(float(np.sum((cam_dirs.T @ r) ** 2)) / (float(np.sum(w2)) * cam_dirs.shape[1] / (2.0 * M)))
    return CovarianceModel(cov, col, sigma, sigma_hat, dof, q, P, Hi, undetermined_parameters(H), face_sigma,
                           face_max, vc, camera_px, aligned_max)


def _prediction_rows(prob, J, r, col, block, loading, loss, loss_scale, views_shared, count_carried):
    """The predictions the covariance counts (:func:`.pose_covariance.pose_rows`, and with ``count_carried`` the
    carried points, :func:`.pose_covariance.carried_rows`), at the robust loss's weights of the residuals ``r``."""
    rho = np.repeat(_robust_weights((r.reshape(-1, 2) ** 2).sum(1), loss, loss_scale), 2)
    pose = pose_rows(prob, J, rho, col, views_shared, block, loading)
    return merged_rows(pose, carried_rows(prob, J, r, rho, col, block, loading, views_shared,
                                          predicted=pose and pose.loadings) if count_carried else None)


def _row_arrays(prob) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray]:
    """Per point of ``prob``: its face group (-1: none), its face alignment and loading (None where the problem
    has none) and its face alignment's ECC correlation (:func:`face_misfit_px`; NaN: none)."""
    M = len(prob.P)
    groups = getattr(prob, "group", None)
    if groups is None or len(groups) != M:
        groups = np.full(M, -1)
    ecc = getattr(prob, "ecc", None)
    if ecc is None or len(ecc) != M:
        ecc = np.full(M, np.nan)
    return groups, getattr(prob, "block", None), getattr(prob, "loading", None), ecc


def _pooled_sigma(r, w2, M, Hp_unit, Hprior, sigma_cfg, prior_dof, assemble, camera_dirs=None
                  ) -> tuple[float, float, float]:
    """(pixel sigma pooled with the configured one at ``prior_dof``, the residuals' own, their degrees of
    freedom). ``camera_dirs`` (2M, m): orthonormal directions of the residuals that the multi-view cameras' stated
    errors fill more than the pixel noise (:func:`.camera_residual.camera_directions`); the residuals' own sigma
    is estimated from the rest (m degrees of freedom fewer), so the cameras' disagreement is not taken for pixel
    noise while the camera term adds their error to the intervals."""
    sig = sigma_cfg
    m = 0 if camera_dirs is None else camera_dirs.shape[1]
    r_own = r if not m else r - camera_dirs @ (camera_dirs.T @ r)
    for _ in range(2):
        H, Hi = assemble(sig)
        p_eff = float(np.trace(Hi @ (Hp_unit / sig**2)))
        dof = max(2.0 * M - p_eff - m, 0.0)
        if dof > 1e-6:
            sigma_hat = math.sqrt(float(np.sum(r_own**2)) / (float(np.sum(w2)) * dof / (2.0 * M)))
        else:
            sigma_hat = float("nan")
        nu0 = prior_dof
        s2 = (dof * (sigma_hat**2 if dof > 1e-6 else 0.0) + nu0 * sigma_cfg**2) / (dof + nu0) if dof + nu0 > 0 \
            else sigma_cfg**2
        sig = max(math.sqrt(s2), 0.1 * sigma_cfg)
    return sig, sigma_hat, dof


def _ecc_misfit(J: np.ndarray, groups: np.ndarray, ecc: np.ndarray, floor_px: float, views: np.ndarray,
                uv: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    """The gradient covariance (as :func:`_shared_misfit`'s, per unit weight) of the faces' misfits on their own
    points (``groups`` >= 0), each face's the mean square over its photos' points of :func:`face_misfit_px`, and
    the largest of them (px per mode)."""
    tau = face_misfit_px(ecc, floor_px)
    scale = [float(np.mean(tau[groups == g] ** 2)) for g in np.unique(groups[groups >= 0])]
    return _shared_misfit(J, groups, views, uv, w, scale), float(tau[groups >= 0].max())


def face_misfit_px(ecc: np.ndarray, floor_px: float) -> np.ndarray:
    """The misfit (px per affine mode, :func:`_shared_misfit`) shared by the points of a face aligned without
    matches of its own (ECC from a predicted pose), from its ECC correlation ``ecc`` (NaN: unknown, the floor):
    :data:`ECC_MISFIT_PX` times ``1 - ecc``, at least ``floor_px`` (``solver.face_sigma_px``)."""
    ecc = np.asarray(ecc, dtype=float)
    return np.where(np.isfinite(ecc), np.maximum(floor_px, ECC_MISFIT_PX * (1.0 - ecc)), floor_px)


def aligned_misfit_px(ecc: np.ndarray) -> np.ndarray:
    """The misfit (px per affine mode) that the points of a face aligned from its own matches share beyond their
    alignment's loading, from the face's ECC correlation ``ecc`` (NaN: none): :data:`ALIGNED_ECC_MISFIT_PX` times
    the correlation below ``1 - ALIGNED_ECC_FREE``, else 0."""
    ecc = np.asarray(ecc, dtype=float)
    below = np.where(np.isfinite(ecc), (1.0 - ALIGNED_ECC_FREE) - ecc, 0.0)
    return ALIGNED_ECC_MISFIT_PX * np.maximum(below, 0.0)


def _aligned_excess(J: np.ndarray, block: np.ndarray, ecc: np.ndarray, groups: np.ndarray, views: np.ndarray,
                    uv: np.ndarray, w: np.ndarray) -> tuple[np.ndarray | float, float]:
    """The gradient covariance (as :func:`_shared_misfit`'s, per unit weight) of the misfit that the aligned faces
    whose reference matched the photo less closely share beyond their loading (:func:`aligned_misfit_px`), and the
    largest such misfit (px per mode; NaN and 0.0 where no face has any)."""
    tau = aligned_misfit_px(np.where(block >= 0, ecc, np.nan))
    excess = np.where(tau > 0, groups, -1)  # aligned faces whose reference matched less closely
    if not (excess >= 0).any():
        return 0.0, math.nan
    scale = [float(np.mean(tau[excess == g] ** 2)) for g in np.unique(excess[excess >= 0])]
    return _shared_misfit(J, excess, views, uv, w, scale), float(tau.max())


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
            B = photo_affine_modes(uv[idx] - uv[idx].mean(0)).reshape(-1, 6)
            rows = np.stack([2 * idx, 2 * idx + 1], axis=1).reshape(-1)
            A += J[rows].T @ (B * np.repeat(w[idx], 2)[:, None])
        out += (1.0 if scale is None else float(scale[i])) * (A @ A.T)
    return out


def body_centre_cov(model: CovarianceModel, cars, R, k: int) -> np.ndarray:
    """(3, 3) covariance of carriage ``k``'s body centre."""
    c = model.col[k]
    Jb = np.hstack([-skew(R[k] @ cars[k].c_body), np.eye(3)])
    C = model.cov[c:c + 6, c:c + 6]
    return Jb @ C @ Jb.T


def solution_model(prob: Problem, poses: Poses, focal_views, chains: Chains, contact,
                   options: SolveOptions, guided_loading: bool = True, count_carried: bool = True) -> CovarianceModel:
    """:func:`covariance_model` at a solution with the solve's options (``guided_loading``, ``count_carried`` as
    there)."""
    return covariance_model(prob, poses.R, poses.t, poses.f, focal_views, chains.members, chains.slacks, contact,
                            options.pixel_sigma_px,
                            options.robust_loss, options.loss_scale_px, options.prior_dof,
                            face_sigma=options.face_sigma_px, camera_errors=options.camera_errors,
                            guided_loading=guided_loading, count_carried=count_carried)


def _carriage_chi2(prob: Problem, poses: Poses, sigma: float) -> dict[int, tuple[float, int, float]]:
    """Per carriage with measured points: (their chi-square at ``sigma``, each point at its own sigma relative to
    the configured, its number of rows 2 n, their RMS residual in px), on the measured points alone (a prediction's
    residual says how far its face's pose was off, not that the fit failed)."""
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
    return chi


def misfit_carriages(prob: Problem, poses: Poses, sigma: float, p_value: float = 1e-4,
                     relative: float = 4.0) -> dict[int, float]:
    """The carriages whose measured points the solution does not fit, as the branch check judges a misfit
    (:func:`.branches.misfit_cars`: chi-square at ``sigma`` beyond its (1 - ``p_value``) quantile with 2 n - 6
    degrees of freedom, *and* more than ``relative`` times the median carriage's misfit per row), on the measured
    points alone (:func:`_carriage_chi2`). Returns carriage -> RMS residual (px) of its measured points. Such a
    carriage sits on a wrong branch or on mismatched points the branch check and the outlier rejection did not cure,
    and the noise model its interval rests on does not hold for it; or its points share a misfit (``face_sigma_px``)
    this test does not model, so it warns and keeps the interval (docs/calibration.md: 1 gross failure and 5 sound
    intervals among 6 flags on the automatic route)."""
    chi = _carriage_chi2(prob, poses, sigma)
    med = float(np.median([x / m for x, m, _ in chi.values()])) if chi else 0.0
    return {k: rms for k, (x, m, rms) in chi.items()
            if x > chi2_quantile(1.0 - p_value, max(m - 6, 1)) and x / m > relative * med}


WHOLE_MISFIT_RATIO = 4.0  # a fit misses as a whole: its residuals' own pixel sigma over this times the configured


def fit_misfit(sigma_hat: float, dof: float, sigma_cfg: float, p_value: float = 1e-4,
               ratio: float = WHOLE_MISFIT_RATIO) -> bool:
    """Whether the marked points as a whole do not fit the solution: their residuals' own pixel sigma ``sigma_hat``
    (px, with ``dof`` degrees of freedom) over ``ratio`` times the configured ``sigma_cfg`` (16 times its variance)
    and its chi-square beyond the (1 - ``p_value``) quantile. Where every carriage misfits alike, the test of
    :func:`misfit_carriages` (against the pooled sigma, relative to the median carriage) passes each; this one sees
    a wrong camera or georeference, a wrong focal or carriage type, or picks much rougher than configured. False
    where the residuals give no sigma of their own (NaN, no degrees of freedom)."""
    if not (math.isfinite(sigma_hat) and dof > 0 and sigma_cfg > 0):
        return False
    r = sigma_hat / sigma_cfg
    return r > ratio and dof * r**2 > chi2_quantile(1.0 - p_value, dof)


def whole_misfit_carriages(prob: Problem, poses: Poses, sigma_cfg: float, named: dict[int, float],
                           p_value: float = 1e-4, ratio: float = WHOLE_MISFIT_RATIO) -> dict[int, float]:
    """Where the fit misses as a whole (:func:`fit_misfit`), the carriages it is doubtful for: every carriage with
    measured points that :func:`misfit_carriages` did not name (``named``), if together their points still miss at
    the configured ``sigma_cfg`` (their chi-square over its (1 - ``p_value``) quantile and over ``ratio`` squared
    times its degrees of freedom, 2 n - 6 a carriage); else none. A wrong camera, focal or type moves every
    carriage's points, each by its own amount; one mismatched carriage that alone lifts the residuals' sigma is
    named by :func:`misfit_carriages`, and the others, whose points fit, are left alone. Returns carriage -> RMS
    residual (px) of its measured points."""
    rest = {k: v for k, v in _carriage_chi2(prob, poses, sigma_cfg).items() if k not in named}
    x = sum(v[0] for v in rest.values())
    dof = sum(max(v[1] - 6, 1) for v in rest.values())
    if not rest or x <= chi2_quantile(1.0 - p_value, dof) or x / dof <= ratio**2:
        return {}
    return {k: v[2] for k, v in rest.items()}


def camera_responses(prob: Problem, poses: Poses, focal_views, chains: Chains, contact,
                     options: SolveOptions) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Each active carriage's first-order pose response (6, 6: scene rotation vector, origin) to a rigid motion of
    the camera about the ENU origin (rotation vector, translation: :func:`.camera_term.motion_about`), as the
    estimator responds: its pixels (the measured points and the predictions it fits, at the fit's weights and
    robust weights) move with the camera, the couplings' offsets do not change when the whole consist moves, and the
    terrain contact and the track prior stay in the world. With ``H = H_moving + H_world`` the information of the
    cost the solver minimises (pixels at ``options.pixel_sigma_px``, the coupler prior, the soft rows), the least
    squares moves by ``H^-1 H_moving A e = (A - H^-1 H_world A) e``, ``A`` every carriage's rigid motion with the
    camera (docs/solver.md, "The camera's uncertainty"). Returns carriage index -> (its response (6, 6), its
    world-fixed information ``H_world`` block (6, 6), in the cost's units: pixels at ``options.pixel_sigma_px``;
    the multi-view cameras' term adds it). Empty where no world-fixed row holds a carriage: every carriage then
    moves rigidly with the camera (``B = A``)."""
    J, r, col, P = pixel_rows(prob, poses.R, poses.t, poses.f, focal_views)
    Jw, _, _ = contact_rows(contact, poses.R, poses.t, col, P, options.pixel_sigma_px)
    if not len(Jw):
        return {}
    rho = np.repeat(_robust_weights((r.reshape(-1, 2) ** 2).sum(1), options.robust_loss, options.loss_scale_px), 2)
    Hw = Jw.T @ Jw
    H = (J * rho[:, None]).T @ J / options.pixel_sigma_px**2 + Hw \
        + _prior_info(prob.cars, poses.R, poses.t, chains.members, chains.slacks, col, P)
    A = np.zeros((P, 6))
    for k in prob.active:
        c = col[k]
        A[c:c + 6] = np.eye(6)
        A[c + 3:c + 6, :3] = -skew(poses.t[k])
    B = A - inverse_psd(0.5 * (H + H.T)) @ (Hw @ A)
    return {k: (B[col[k]:col[k] + 6], Hw[col[k]:col[k] + 6, col[k]:col[k] + 6]) for k in prob.active}


def _pivot(cars, chains: Chains, k: int) -> np.ndarray:
    """Where carriage ``k``'s held couplings hold it (carriage frame, m): its front coupler when held to the
    carriage ahead, its rear one when held to the one behind, their midpoint when both."""
    for ch in chains.members:
        if k in ch:
            j = ch.index(k)
            ends = ([cars[k].c_front] if j > 0 else []) + ([cars[k].c_rear] if j < len(ch) - 1 else [])
            if ends:
                return np.mean(ends, axis=0)
    return np.asarray(cars[k].c_body, dtype=float)  # not held: no swing about a coupler


def attach_covariance(res, prob: Problem, poses: Poses, focal_views, chains: Chains, contact, options: SolveOptions,
                      model: CovarianceModel | None = None) -> None:
    """Fill the covariance fields of a :class:`SolveResult` in place. ``model``: a :func:`solution_model` already
    computed (at the least-squares minimum, when the reported ``poses`` are bias-corrected: the pixel sigma is
    estimated from the minimum's residuals and the intervals are centred on the reported poses). Each carriage result
    also keeps its response to a camera motion (:func:`camera_responses`) for the camera term."""
    if model is None:
        model = solution_model(prob, poses, focal_views, chains, contact, options)
    R = poses.R
    cov, col, q = model.cov, model.col, model.q
    res.sigma_px = model.sigma
    res.sigma_px_estimated = model.sigma_hat
    res.sigma_px_camera = model.camera_px
    res.face_sigma_px = model.face_sigma
    res.face_misfit_max_px = None if math.isnan(model.face_misfit_max) else model.face_misfit_max
    res.aligned_misfit_max_px = None if math.isnan(model.aligned_misfit_max) else model.aligned_misfit_max
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
    whole = whole_misfit_carriages(prob, poses, options.pixel_sigma_px, misfit) \
        if fit_misfit(model.sigma_hat, model.dof, options.pixel_sigma_px) else {}
    for k in prob.active:
        cr = res.carriages[k]
        c = col[k]
        determined = model.undetermined is None or not model.undetermined[c:c + 6].any()
        if cr.status == "carried":
            cr.swing_lever_m = R[k] @ (prob.cars[k].c_body - _pivot(prob.cars, chains, k))
        Jbs[k] = set_pose_covariance(cr, cov[c:c + 6, c:c + 6], R[k], R[k] @ prob.cars[k].c_body, q, determined)
        if k in misfit and cr.covariance_pose is not None:
            record_warning(res.warnings, prob.cars[k], "misfit",
                           f"car {cr.number}: the solution does not fit its points (RMS {misfit[k]:.1f} px against "
                           f"a pixel sigma of {model.sigma:.2f} px): a wrong branch or mismatched points; its "
                           f"pose and its interval are doubtful")
        elif k in whole and cr.covariance_pose is not None:
            record_warning(res.warnings, prob.cars[k], "misfit",
                           f"car {cr.number}: the solution does not fit the marked points as a whole (RMS "
                           f"{whole[k]:.1f} px on this carriage, a pixel sigma of {model.sigma_hat:.1f} px from all "
                           f"residuals, against the {options.pixel_sigma_px:g} px configured): a camera placed wrong, "
                           f"a wrong focal or carriage type, or picks rougher than solver.pixel_sigma_px says; its "
                           f"pose and its interval are doubtful")
        elif cr.covariance_pose is None:
            record_warning(res.warnings, prob.cars[k], "undetermined",
                           f"car {cr.number}: its measured points do not determine its pose (predictions or the "
                           f"chain placed it); no interval is given")
    for k, (B0, Hw_k) in camera_responses(prob, poses, focal_views, chains, contact, options).items():
        set_camera_response(res.carriages[k], B0, Hw_k, options.pixel_sigma_px)
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
