"""What a face's alignment measures (``workbench.correspond.alignment``): the loadings of the points a homography
places, from its matches, against the scatter of those points over repeated noisy fits (Monte Carlo)."""

from __future__ import annotations

import cv2
import numpy as np
from workbench.correspond.alignment import MIN_MATCHES, distortion_jacobian, homography_point_loadings
from workbench.correspond.match import apply_h


def _fit(R, P):
    H, _ = cv2.findHomography(R, P, 0)  # least squares (then refined), every match an inlier
    return H / H[2, 2]


def test_loadings_match_the_scatter_of_refitted_points():
    """A side face 400 x 60 reference px seen in perspective; 40 matches with 0.5 px of noise. The points' covariance
    ``L L^T`` from one fit's matches (at the true noise) agrees with the scatter of the points over 300 fits to fresh noise (each
    coordinate's variance within 25 %, and the u-v correlation of the two end points within 0.15); and the
    residual sigma estimates the noise (0.4-0.6 px)."""
    rng = np.random.default_rng(3)
    H_true = np.array([[0.9, 0.05, 300.0], [-0.12, 1.1, 200.0], [-4e-4, 1e-5, 1.0]])
    R = np.column_stack([rng.uniform(0, 400, 40), rng.uniform(0, 60, 40)])
    x = np.array([[0.0, 0.0], [400.0, 0.0], [400.0, 60.0], [200.0, 30.0], [0.0, 60.0]])
    clean = apply_h(H_true, R)
    pts = []
    for _ in range(300):
        H = _fit(R, clean + rng.normal(0.0, 0.5, clean.shape))
        pts.append(apply_h(H, x).reshape(-1))
    C_mc = np.cov(np.array(pts).T)
    P = clean + rng.normal(0.0, 0.5, clean.shape)
    L, sigma, dof = homography_point_loadings(_fit(R, P), R, P, x)
    assert L.shape == (5, 2, 8) and dof == 2 * 40 - 8
    assert 0.4 < sigma < 0.6, sigma
    Lf = L.reshape(10, 8)
    C = Lf @ Lf.T * (0.5 / sigma) ** 2  # the shape at the true noise (the sigma estimate is checked above)
    ratio = np.diag(C) / np.diag(C_mc)
    assert np.all((ratio > 0.75) & (ratio < 1.25)), ratio
    corr = C / np.sqrt(np.outer(np.diag(C), np.diag(C)))
    corr_mc = C_mc / np.sqrt(np.outer(np.diag(C_mc), np.diag(C_mc)))
    assert np.max(np.abs(corr - corr_mc)) < 0.15
    assert np.linalg.matrix_rank(C, tol=1e-9 * C.max()) <= 8  # ten coordinates, one homography's 8 parameters


def test_too_few_matches_give_no_loading_and_distortion_is_carried():
    R = np.array([[0, 0], [10, 0], [10, 5], [0, 5], [5, 2], [3, 4], [7, 1]], float)
    assert len(R) < MIN_MATCHES
    assert homography_point_loadings(np.eye(3), R, R, R[:2]) is None
    D = distortion_jacobian(lambda p: p * 1.5 + p[:, ::-1] * 0.1, np.array([[10.0, 20.0]]))
    np.testing.assert_allclose(D[0], [[1.5, 0.1], [0.1, 1.5]], atol=1e-9)
    R9 = np.vstack([R, [[2.0, 1.0], [8.0, 4.0]]])
    assert homography_point_loadings(np.eye(3), R9, R9[:5], R9[:2]) is None  # matches and pixels disagree in number
