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
    assert variance_factor(50.0, 1.6, 80, opts) == 1.6  # the plain chi-square where above the robust cost's
