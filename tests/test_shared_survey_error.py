"""A control point's survey error is one error, the same in every photo it is picked in (issue 21).

Monte Carlo against the truth, the survey's error dominating the picks' (5 cm at 40 m is about 2 px; picks at
0.5 px), six photos on an arc round ten control points each picked in every photo:

- the similarity that places an exact SfM model of the six must not count a point once per photo: its 7-d error
  and each placed photo's 6-d pose error, whitened by the stated covariances, must have the chi-square's mean (a
  fit that counted each point six times states intervals about twice too narrow);
- photos placed on their own (resected) from the same points move together: the joint error of all six, whitened
  by the group's stated covariance, must have the chi-square's mean (taken as independent, the mean of their
  centres' errors is far outside what the photos' own covariances give it).
"""

from __future__ import annotations

import numpy as np

from workbench.core.camera import CameraIntrinsics
from workbench.core.geometry import exp_so3, log_so3
from workbench.files.control_points import ControlPoint
from workbench.files.reconstruction import SfmView
from workbench.georef.options import GeorefOptions
from workbench.georef.similarity import model_centre, solve_similarity

SIGMA_M = 0.05  # the survey's 1-sigma per axis (m)
SIGMA_PX = 0.5  # the picks' noise (px)
DRAWS = 60


def _cam_from_world(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """A camera at ``centre`` looking at ``target`` (x right, y down, z forward; the scene's z up)."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    M = np.eye(4)
    M[:3, :3] = np.stack([x, y, z])
    M[:3, 3] = -M[:3, :3] @ centre
    return M


def _scene(rng: np.random.Generator):
    """Six photos on an arc 40 m from the site, ten control points on it, and a model frame (the truth's
    ``world_from_model``: scale 0.3, turned, moved)."""
    intr = CameraIntrinsics(width=1600, height=1200, fx=1500.0, fy=1500.0, cx=799.5, cy=599.5)
    cams = []
    for a in np.radians(np.linspace(-60, 60, 6)):
        c = np.array([40 * np.sin(a), -40 * np.cos(a), 6.0])
        cams.append(_cam_from_world(c, np.array([0.0, 0.0, 1.0])))
    X = np.column_stack([rng.uniform(-15, 15, 10), rng.uniform(-10, 10, 10), rng.uniform(0, 3, 10)])
    s, R, t = 0.3, exp_so3(np.array([0.4, -0.2, 1.1])), np.array([5.0, -3.0, 2.0])
    views = []
    for i, M in enumerate(cams):  # the model's cameras in model units: p_cam = (M_R (s R p + t) + M_t) / s
        C = np.eye(4)
        C[:3, :3], C[:3, 3] = M[:3, :3] @ R, (M[:3, :3] @ t + M[:3, 3]) / s
        views.append(SfmView(f"v{i}.jpg", intr, C))
    return intr, cams, X, (s, R, t), views


def _pixels(intr: CameraIntrinsics, M: np.ndarray, X: np.ndarray) -> np.ndarray:
    q = X @ M[:3, :3].T + M[:3, 3]
    return intr.project(q)


def test_similarity_counts_a_control_point_once():
    rng = np.random.default_rng(21)
    intr, cams, X, (s0, R0, t0), views = _scene(rng)
    opts = GeorefOptions(sigma_px=SIGMA_PX, ransac_iterations=30)  # no outlier here: a short start
    m7, m6 = [], []
    for _ in range(DRAWS):
        cps = []
        for k, x in enumerate(X):
            pix = {v.name: _pixels(intr, M, x[None])[0] + rng.normal(0, SIGMA_PX, 2) for v, M in zip(views, cams)}
            assert all(intr.in_image(np.array([p]))[0] for p in pix.values())
            cps.append(ControlPoint(f"p{k}", x + rng.normal(0, SIGMA_M, 3), SIGMA_M, pix))
        res = solve_similarity(views, cps, opts=opts, where="test")
        assert res.covariance is not None
        # the error in the covariance's order: log scale, rotation vector on the left (scene frame), translation
        e = np.concatenate([[np.log(res.scale / s0)], log_so3(res.rotation @ R0.T), res.translation - t0])
        m7.append(float(e @ np.linalg.solve(res.covariance, e)))
        for v, M in zip(views, cams):  # each placed photo's pose (rotation vector, centre) against its stated error
            Mw = res.cam_from_world(v.cam_from_model)
            d = np.concatenate([log_so3(Mw[:3, :3].T @ M[:3, :3]),
                                res.apply(model_centre(v.cam_from_model)) - (-M[:3, :3].T @ M[:3, 3])])
            m6.append(float(d @ np.linalg.solve(res.view_covariance(v.cam_from_model), d)))
    r7, r6 = np.mean(m7) / 7.0, np.mean(m6) / 6.0
    print(f"\nsimilarity: mean Mahalanobis^2 / 7 {r7:.2f}; placed photos: mean Mahalanobis^2 / 6 {r6:.2f}")
    # the chi-square's mean within its sampling error (60 draws: relative sd about 0.07 for 7 dof, the photos'
    # draws correlated through their similarity) and the robust loss's small loss of efficiency
    assert 0.75 < r7 < 1.35
    assert 0.7 < r6 < 1.4

