"""The automatic points' two error components estimated from the residuals: each point's own pixel noise and the
misfit a face's points share (docs/solver.md, "Covariance"; issue 21).

Model of the weighted residual rows ``e`` (2M,): ``e = n + sum_g A_g c_g`` with ``n ~ N(0, sigma^2 D)`` (``D``
the rows' variance factors) and, per face ``g``, six affine coefficients ``c_g ~ N(0, tau^2 I)`` shared by its
points in every view (``A_g`` the modes of :func:`face_modes`). At the fit, the residuals are ``r = R e`` with
``R = I - J H^-1 J^T / sigma^2`` the residual maker (``H`` the information, the priors included). Split the
residuals into their part in the span of the faces' modes ``R A`` and the rest: the rest holds the points' own
noise alone (``E = sigma^2 tr((I - P) R D R^T)``), which gives sigma with the rest's degrees of freedom; the
part in the span holds both (``E = sigma^2 tr(P R D R^T) + tau^2 ||R A||^2``), which gives tau (the method of
moments; a negative tau^2, no shared misfit to see, is set to zero). ``R`` is recomputed with the new sigma
until both settle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .alignment_covariance import photo_affine_modes

__all__ = ["FALLBACK_FACE_SIGMA_PX", "VarianceComponents", "face_modes", "estimate_variance_components"]

# the face misfit used where the residuals cannot tell it from the points' noise (the faces' modes take all
# their degrees of freedom): the value configured before the estimate, chosen on the samples' automatic points
FALLBACK_FACE_SIGMA_PX = 0.15


@dataclass(frozen=True)
class VarianceComponents:
    """``sigma_px``: a point's own noise (px, 1-sigma); ``face_sigma_px``: the misfit a face's points share (px per
    affine mode, pooled over the faces); ``dof``: the degrees of freedom of ``sigma_px``'s estimate; ``n_faces``:
    the faces seen; ``iterations`` to settle; ``face_sigmas_px``: each face's own misfit (:func:`per_face`)."""

    sigma_px: float
    face_sigma_px: float
    dof: float
    n_faces: int
    iterations: int
    face_sigmas_px: tuple[float, ...] = ()  # per face (in the order of :func:`face_modes`), shrunk to the pooled


def face_modes(groups: np.ndarray, views: np.ndarray, uv: np.ndarray, w: np.ndarray) -> list[np.ndarray]:
    """Per face (``groups`` >= 0) the (2M, 6) modes of its shared misfit in the weighted rows: a shift in u and in
    v, and the four affine terms ``(u - u_c) / s_u``, ``(v - v_c) / s_v`` in u and in v (centroid and RMS spread
    of the face's points in each view; only the shifts where a view has fewer than 3). ``groups``, ``views``
    (M,); ``uv`` (M, 2) observed pixels; ``w`` (M,) row weights."""
    M = len(groups)
    out = []
    for g in np.unique(groups[groups >= 0]):
        A = np.zeros((2 * M, 6))
        for v in np.unique(views[groups == g]):
            idx = np.nonzero((groups == g) & (views == v))[0]
            B = photo_affine_modes(uv[idx] - uv[idx].mean(0)) * w[idx, None, None]
            A[2 * idx], A[2 * idx + 1] = B[:, 0], B[:, 1]
        out.append(A)
    return out


def estimate_variance_components(J: np.ndarray, r: np.ndarray, d: np.ndarray, modes: list[np.ndarray],
                                 h_inverse: Callable[[float], np.ndarray], sigma0: float,
                                 iterations: int = 6, prior_modes: float = 6.0) -> VarianceComponents | None:
    """``(sigma, tau)`` from the weighted residual rows ``r`` (2M,) at the fit, the weighted Jacobian ``J``
    (2M, P), the rows' variance factors ``d`` (2M,), the faces' ``modes`` (:func:`face_modes`) and
    ``h_inverse(sigma)``: the inverse information (P, P) at a pixel sigma (the priors' share depends on it).
    ``sigma0``: the starting sigma (px). None when the residuals leave no degree of freedom or no face is seen."""
    if not modes or len(r) == 0:
        return None
    A = np.hstack(modes)  # (2M, 6 G)
    G = len(modes)
    sig2, tau2, it = float(sigma0) ** 2, 0.0, 0
    dof = 0.0
    for it in range(1, iterations + 1):
        Hi = h_inverse(math.sqrt(sig2))
        Rm = np.eye(len(r)) - (J @ Hi / sig2) @ J.T  # the residual maker (2M, 2M)
        RA = Rm @ A
        U, sv, _ = np.linalg.svd(RA, full_matrices=False)
        Q = U[:, sv > sv[0] * 1e-9] if len(sv) and sv[0] > 0 else U[:, :0]  # the faces' modes among the residuals
        QR = Q.T @ Rm
        tr_all = float(np.sum(Rm * Rm * d[None, :]))  # tr(R D R^T)
        tr_faces = float(np.sum(QR**2 * d[None, :]))  # tr(Q^T R D R^T Q)
        tr_rest = tr_all - tr_faces
        if tr_rest <= 1e-6:
            return None
        Qr = Q.T @ r
        q_faces = float(Qr @ Qr)
        q_rest = float(r @ r) - q_faces
        # the residuals off the faces' modes hold the points' own noise alone; on them, both
        s2 = max(q_rest, 0.0) / tr_rest
        t2 = max((q_faces - s2 * tr_faces) / float(np.sum(RA**2)), 0.0) if len(sv) and sv[0] > 0 else 0.0
        if not (np.isfinite(s2) and s2 > 0):
            return None
        done = abs(s2 - sig2) <= 1e-6 * sig2 and abs(t2 - tau2) <= 1e-6 * max(tau2, 1e-12)
        sig2, tau2, dof = float(s2), float(t2), tr_rest
        if done:
            break
    taus = per_face(RA, Rm, r, d, sig2, tau2, G, prior_modes)
    return VarianceComponents(math.sqrt(sig2), math.sqrt(tau2), dof, G, it, tuple(np.sqrt(taus).tolist()))


def per_face(RA: np.ndarray, Rm: np.ndarray, r: np.ndarray, d: np.ndarray, sig2: float, tau2: float, G: int,
             prior_modes: float) -> np.ndarray:
    """Each face's misfit variance (G,) px^2: its residuals on its own modes, less the points' noise and the other
    faces' pooled misfit there, over its modes' size; each face's six (or fewer) modes say little alone, so the
    estimate is shrunk to the pooled ``tau2`` as if the pooled value were ``prior_modes`` more modes' worth."""
    out = np.full(G, tau2)
    for g in range(G):
        RAg = RA[:, 6 * g:6 * g + 6]
        U, sv, _ = np.linalg.svd(RAg, full_matrices=False)
        keep = sv > (sv[0] * 1e-9 if len(sv) and sv[0] > 0 else np.inf)
        k = int(keep.sum())
        if k == 0:
            continue
        Q = U[:, keep]
        t_noise = float(np.sum((Q.T @ Rm) ** 2 * d[None, :]))
        cross = Q.T @ RA
        t_other = float(np.sum(cross**2)) - float(np.sum(cross[:, 6 * g:6 * g + 6] ** 2))
        qg = float(np.sum((Q.T @ r) ** 2))
        own = max((qg - sig2 * t_noise - tau2 * t_other) / float(np.sum(RAg**2)), 0.0)
        out[g] = (prior_modes * tau2 + k * own) / (prior_modes + k)
    return out
