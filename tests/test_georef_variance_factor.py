"""The central route's camera covariance is widened by the picks' a posteriori variance factor when they miss by more
than they state (a pick sigma set too small, a lens the camera model cannot hold), and never narrowed: a Monte Carlo
against the truth (``georef.central``, ``georef.picks.variance_factor``)."""

from __future__ import annotations

import numpy as np

from workbench.core.camera import CameraIntrinsics, look_at
from workbench.core.geometry import log_so3
from workbench.files.control_points import ControlPoint
from workbench.files.panorama import RigView
from workbench.georef.central import solve_central
from workbench.georef.options import GeorefOptions
from workbench.georef.picks import variance_factor


def _draws(noise_px: float, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` resections of one 1600 x 1200 photo from 12 m up on 8 control points 60-160 m away, each pick its true
    pixel + N(0, ``noise_px``) per axis, the points exact and stated at 5 cm, the picks stated at 1 px (the
    default ``sigma_px``). Returns each draw's squared Mahalanobis distance of the camera's 6-d error under the
    stated covariance (n,), and the variance factor each applied (n,)."""
    rng = np.random.default_rng(seed)
    intr = CameraIntrinsics(width=1600, height=1200, fx=1400.0, fy=1400.0, cx=799.5, cy=599.5)
    centre = np.array([0.0, 0.0, 12.0])
    R = look_at(centre, np.array([0.0, 110.0, 0.0]))[:3, :3]
    X = np.column_stack([rng.uniform(-40, 40, 8), rng.uniform(60, 160, 8), rng.uniform(0, 6, 8)])
    m2, vf = [], []
    for _ in range(n):
        cps = [ControlPoint(f"p{k}", x, 0.05, {"a.jpg": intr.project(((x - centre) @ R.T)[None])[0]
                                                + rng.normal(0.0, noise_px, 2)}) for k, x in enumerate(X)]
        res = solve_central([RigView("a.jpg", intr, np.eye(3))], cps, opts=GeorefOptions())
        C = np.asarray(res.stats["covariance_world_rotation_centre"], float)
        e = np.concatenate([log_so3(res.rig_from_world.T @ R), res.centre_enu - centre])
        m2.append(float(e @ np.linalg.solve(C, e)))
        vf.append(res.stats["variance_factor"])
    return np.array(m2), np.array(vf)


def test_picks_that_miss_by_more_than_stated_widen_the_camera_interval():
    """Picks at 3 px stated at 1 px (10 degrees of freedom a draw): the camera's error has a mean squared
    Mahalanobis distance of 6 (6-d) under the widened covariance (3.5-9 over 24 draws), where the covariance the
    stated sigma gives alone puts it near 25 (over 18: the test fails without the factor)."""
    m2, vf = _draws(3.0, 24, 11)
    assert 3.5 < m2.mean() < 9.0, (m2.mean(), np.median(m2), vf.mean())
    assert (m2 * vf).mean() > 18.0, (m2 * vf).mean()  # the stated sigma's covariance alone: far too narrow
    assert 4.0 < np.median(vf) < 12.0, np.median(vf)


def test_picks_that_fit_as_stated_keep_the_camera_interval():
    """Picks at 0.7 px stated at 1 px: the factor is 1 (never below: a survey's stated error is partly common to
    its points, which no residual shows) in most draws and small in the rest."""
    m2, vf = _draws(0.7, 12, 12)
    assert np.all(vf >= 1.0) and np.mean(vf == 1.0) > 0.7 and vf.max() < 2.0, vf
    assert m2.mean() < 6.0, m2.mean()


def test_variance_factor_rules():
    opts = GeorefOptions()
    assert variance_factor(10.0, 2.0, 0, opts) == 1.0  # no degree of freedom
    assert variance_factor(10.0, 2.0, 10, opts) == 2.0  # 2 cost / dof
    assert variance_factor(2.0, 0.4, 10, opts) == 1.0  # few degrees of freedom: not narrowed
    assert variance_factor(20.0, 0.5, 80, opts) == 0.5  # many: the plain chi-square, below 1 too
    assert variance_factor(20.0, 0.5, 80, opts, narrow=False) == 1.0  # the central fits: never below 1
    assert variance_factor(50.0, 1.6, 80, opts) == 1.6  # the plain chi-square where above the robust cost's


def test_shared_camera_adjustment_covariance_is_honest():
    """Four photos of one camera on a 120 deg arc 45 m from 12 map points (0.5 m each, picked in every photo that
    sees them at 0.5 px), adjusted with focal, principal point and k1 free: over 20 draws the photos' centre errors
    have a mean squared Mahalanobis distance near 3 (3-d) under the stated covariance (the sandwich with each
    point's error shared by its picks, times the variance factor): 2-4.5 (measured 3.40; 3.58 with the points'
    errors taken as independent per pick, as before session 19: the arc's diverse views make that close)."""
    from workbench.georef.shared_camera import adjust_shared_camera

    rng = np.random.default_rng(5)
    intr = CameraIntrinsics(width=1600, height=1200, fx=1500.0, fy=1500.0, cx=799.5, cy=599.5)
    X = np.column_stack([rng.uniform(-20, 20, 12), rng.uniform(-20, 20, 12), rng.uniform(0, 8, 12)])
    poses = {f"v{k}.jpg": look_at(np.array([45 * np.cos(a), 45 * np.sin(a), 10.0]), np.array([0.0, 0.0, 2.0]))
             for k, a in enumerate(np.radians([0, 40, 80, 120]))}
    m2 = []
    for _ in range(20):
        cps = []
        for j, x in enumerate(X):
            pix = {}
            for n, M in poses.items():
                uv = intr.project((M[:3, :3] @ x + M[:3, 3])[None])[0]
                if intr.in_image(uv[None], margin=5.0)[0]:
                    pix[n] = uv + rng.normal(0, 0.5, 2)
            cps.append(ControlPoint(f"p{j}", x + rng.normal(0, 0.5, 3), 0.5, pix))
        adj = adjust_shared_camera(intr, poses, cps, GeorefOptions(sigma_px=0.5))
        for n, M in poses.items():
            Me = adj["poses"][n]
            e = (-Me[:3, :3].T @ Me[:3, 3]) - (-M[:3, :3].T @ M[:3, 3])
            m2.append(float(e @ np.linalg.solve(adj["cov_centre"][n], e)))
    assert 2.0 < np.mean(m2) < 4.5, (np.mean(m2), np.median(m2))
