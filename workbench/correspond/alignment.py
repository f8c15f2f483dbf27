"""What a face's alignment measures: the covariance of the points its homography places (issue 21).

A face's marked points are placed by one homography (``FaceDetection.photo_from_ref``), fitted to its ``N``
inlier matches. The points are functions of that homography's 8 parameters, so their errors are the
homography's error carried to them: correlated within the face and view, of rank at most 8, and as small as
``N`` matches allow. With the matches' residuals at the final homography ``r_i`` (undistorted photo px) and the
Jacobian ``A`` (2 N, 8) of the matches' transfer in the homography's parameters,

    sigma^2 = sum |r_i|^2 / (2 N - 8),    Cov(h) = sigma^2 (A^T A)^-1,

and a point ``x`` placed at ``H x`` has the displacement ``L_x xi`` with ``xi ~ N(0, I_8)`` shared by every point
of the face in that view and the *loading* ``L_x = J_x (A^T A)^{-1/2} sigma`` (2, 8), ``J_x`` the point's
transfer Jacobian. The covariance of the face's points is ``L L^T``. Computed in coordinates centred and scaled
on both sides (Hartley's normalisation; the points' covariance does not depend on the parametrisation), then
carried through the lens distortion to pixels of the photo on disk by the distortion's Jacobian.

Where a face has no matches of its own (a face aligned by ECC from a predicted pose, ``FaceDetection.guided``)
there is nothing to estimate it from and no loading is given: the solve treats such points with its fixed
per-face misfit, as before. See docs/correspondences.md ("What a face's alignment measures").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

MIN_MATCHES = 8  # below this a homography's 8 parameters leave too few residual degrees of freedom (2 N - 8)


@dataclass(frozen=True)
class AlignmentCovariance:
    """The loadings ``loading_px`` (n, 2, 8) of ``n`` points (pixels of the photo on disk per unit of the shared
    standard normal), the matches' residual sigma ``rms_px`` (undistorted px, with ``dof`` = 2 N - 8 degrees of
    freedom) and ``n_matches`` N."""

    loading_px: np.ndarray
    rms_px: float
    dof: int
    n_matches: int


def _normaliser(p: np.ndarray) -> tuple[np.ndarray, float]:
    c = p.mean(0)
    s = float(np.sqrt(np.mean(np.sum((p - c) ** 2, axis=1)) / 2.0)) or 1.0
    return c, s


def _transfer_jacobian(Hn: np.ndarray, x: np.ndarray) -> np.ndarray:
    """(n, 2, 8) d(H x)/d h of points ``x`` (n, 2) for ``H`` with ``H[2, 2] = 1`` and h its other 8 entries in
    row-major order."""
    n = len(x)
    q = np.column_stack([x, np.ones(n)]) @ Hn.T
    w = q[:, 2]
    u, v = q[:, 0] / w, q[:, 1] / w
    J = np.zeros((n, 2, 8))
    J[:, 0, 0:3] = np.column_stack([x, np.ones(n)]) / w[:, None]
    J[:, 1, 3:6] = np.column_stack([x, np.ones(n)]) / w[:, None]
    J[:, 0, 6:8] = -u[:, None] * x / w[:, None]
    J[:, 1, 6:8] = -v[:, None] * x / w[:, None]
    return J


def homography_point_loadings(photo_from_ref: np.ndarray, match_ref_px: np.ndarray, match_photo_px: np.ndarray,
                              ref_px: np.ndarray) -> tuple[np.ndarray, float, int] | None:
    """Loadings (n, 2, 8) in undistorted photo px of the points ``ref_px`` (n, 2) placed by ``photo_from_ref``
    (3, 3), from its ``N`` matches (``match_ref_px``, ``match_photo_px``: (N, 2) each); also the matches' residual
    sigma (px) and its degrees of freedom. None with fewer than :data:`MIN_MATCHES` matches or a degenerate fit."""
    R = np.asarray(match_ref_px, float).reshape(-1, 2)
    P = np.asarray(match_photo_px, float).reshape(-1, 2)
    x = np.asarray(ref_px, float).reshape(-1, 2)
    N = len(R)
    if N < MIN_MATCHES or len(P) != N:
        return None
    H = np.asarray(photo_from_ref, float)
    q = np.column_stack([R, np.ones(N)]) @ H.T
    if np.any(q[:, 2] <= 0) and np.any(q[:, 2] >= 0):
        return None  # the matches straddle the vanishing line: not a face's view
    pred = q[:, :2] / q[:, 2:]
    r = pred - P
    dof = 2 * N - 8
    sigma = float(np.sqrt(np.sum(r**2) / dof))
    cr, sr = _normaliser(R)
    cp, sp = _normaliser(pred)
    Tr = np.array([[1 / sr, 0, -cr[0] / sr], [0, 1 / sr, -cr[1] / sr], [0, 0, 1]])
    Tp = np.array([[1 / sp, 0, -cp[0] / sp], [0, 1 / sp, -cp[1] / sp], [0, 0, 1]])
    Hn = Tp @ H @ np.linalg.inv(Tr)
    if abs(Hn[2, 2]) < 1e-12:
        return None
    Hn = Hn / Hn[2, 2]
    A = _transfer_jacobian(Hn, (R - cr) / sr).reshape(-1, 8)
    U, S, Vt = np.linalg.svd(A, full_matrices=False)
    if S[-1] <= S[0] * 1e-10:
        return None  # the matches do not fix the homography (collinear, too clustered)
    Jx = _transfer_jacobian(Hn, (x - cr) / sr)  # (n, 2, 8) in normalised photo units
    # Cov(h) = (sigma / sp)^2 (A^T A)^-1 in normalised units; (A^T A)^-1/2 = V S^-1; times sp back to px
    L = np.einsum("nij,jk->nik", Jx, Vt.T / S[None, :]) * sigma
    return L, sigma, dof


def distortion_jacobian(distort_px: Callable[[np.ndarray], np.ndarray], uv_und: np.ndarray,
                        step_px: float = 0.05) -> np.ndarray:
    """(n, 2, 2) Jacobian of ``distort_px`` (undistorted px -> px on disk) at ``uv_und`` (n, 2), central
    differences of ``step_px``."""
    uv = np.asarray(uv_und, float).reshape(-1, 2)
    D = np.zeros((len(uv), 2, 2))
    for j in range(2):
        e = np.zeros(2)
        e[j] = step_px
        D[:, :, j] = (distort_px(uv + e) - distort_px(uv - e)) / (2 * step_px)
    return D


def alignment_covariance(det, ref_px: np.ndarray, distort_px: Callable[[np.ndarray], np.ndarray]
                         ) -> AlignmentCovariance | None:
    """:class:`AlignmentCovariance` of the points ``ref_px`` (n, 2, reference px) of a face detection
    (:class:`.match.FaceDetection`), in pixels of the photo on disk; None where the face has no matches of its
    own (``guided``) or too few."""
    if det.guided or det.inlier_ref_px is None or det.inlier_photo_px is None:
        return None
    out = homography_point_loadings(det.photo_from_ref, det.inlier_ref_px, det.inlier_photo_px, ref_px)
    if out is None:
        return None
    L, sigma, dof = out
    D = distortion_jacobian(distort_px, det.transfer(np.asarray(ref_px, float).reshape(-1, 2)))
    return AlignmentCovariance(np.einsum("nij,njk->nik", D, L), sigma, dof, len(det.inlier_ref_px))
