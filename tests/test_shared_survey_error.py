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
from workbench.georef.model_checks import model_verdict
from workbench.georef.options import GeorefOptions
from workbench.georef.resection import IncidentPhotos, resect_unplaced
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


def _draw_points(intr, views, cams, X, rng, sigma_m: float) -> list[ControlPoint]:
    """The points surveyed with N(0, ``sigma_m``) per axis (one error per point), picked in every photo at its true
    pixel + N(0, SIGMA_PX)."""
    cps = []
    for k, x in enumerate(X):
        pix = {v.name: _pixels(intr, M, x[None])[0] + rng.normal(0, SIGMA_PX, 2) for v, M in zip(views, cams)}
        assert all(intr.in_image(np.array([p]))[0] for p in pix.values())
        cps.append(ControlPoint(f"p{k}", x + rng.normal(0, sigma_m, 3), sigma_m, pix))
    return cps


def test_photos_placed_on_their_own_share_their_points_errors():
    """Four photos taken a few metres apart, 40 m from ten control points (3 cm survey error: 1.1 px there, a
    resection's 3 px RMS check refuses photos whose points miss by 5 cm), each placed on its own: the same points'
    errors move all four alike, so the mean of their centres (what a carriage seen in all four follows) errs about
    as much as one centre. The group's stated covariance must say so; the photos' own covariances taken as
    independent say a quarter of it."""
    rng = np.random.default_rng(22)
    intr = CameraIntrinsics(width=1600, height=1200, fx=1500.0, fy=1500.0, cx=799.5, cy=599.5)
    cams = [_cam_from_world(np.array([x, -40.0, 6.0]), np.array([0.0, 0.0, 1.0])) for x in (-4.5, -1.5, 1.5, 4.5)]
    X = np.column_stack([rng.uniform(-15, 15, 10), rng.uniform(-10, 10, 10), rng.uniform(0, 3, 10)])
    views = [SfmView(f"v{i}.jpg", intr, M) for i, M in enumerate(cams)]  # SfM's cameras: not used but for intrinsics
    names = [v.name for v in views]
    photos = IncidentPhotos(frozenset(names), True, lambda n: (intr.width, intr.height), lambda n: f"photos/{n}")
    # no outlier (a short start); the focal SfM gave is the truth here, and its check (which refines a focal
    # that disagrees: a group of its own) is another test's matter
    opts = GeorefOptions(sigma_px=SIGMA_PX, resect_focal_disagree_sigma=1e9, ransac_iterations=30)
    A = np.zeros((3, 24))  # the mean of the four centres
    for i in range(4):
        A[:, 6 * i + 3:6 * i + 6] = np.eye(3) / 4
    m_joint, m_mean_joint, m_mean_own = [], [], []
    for _ in range(30):
        cps = _draw_points(intr, views, cams, X, rng, 0.03)
        out, why = resect_unplaced(photos, [("main", views)], {}, cps, {}, opts, "test")
        assert sorted(out) == names, why
        assert {out[n]["joint"]["group"] for n in names} == {f"resection[shared errors of {', '.join(names)}]"}
        F = np.vstack([np.asarray(out[n]["joint"]["pose_factor"], float) for n in names])  # (24, r)
        C = F @ F.T
        own = np.zeros((24, 24))
        e = []
        for i, (n, M) in enumerate(zip(names, cams)):
            Mw = np.asarray(out[n]["entry"]["cam_from_world"], float)
            e.append(np.concatenate([log_so3(Mw[:3, :3].T @ M[:3, :3]),
                                     -Mw[:3, :3].T @ Mw[:3, 3] - (-M[:3, :3].T @ M[:3, 3])]))
            own[6 * i:6 * i + 6, 6 * i:6 * i + 6] = out[n]["covariance"]
        # each photo's marginal is its own fit's stated covariance
        assert np.allclose(np.diag(C), np.diag(own), rtol=1e-6, atol=1e-14)
        e = np.concatenate(e)
        m_joint.append(float(e @ np.linalg.lstsq(C, e, rcond=None)[0]))
        d = A @ e
        m_mean_joint.append(float(d @ np.linalg.solve(A @ C @ A.T, d)))
        m_mean_own.append(float(d @ np.linalg.solve(A @ own @ A.T, d)))
    r24, r3, r3own = np.mean(m_joint) / 24, np.mean(m_mean_joint) / 3, np.mean(m_mean_own) / 3
    print(f"\nresections: joint mean Mahalanobis^2 / 24 {r24:.2f}; the centres' mean: / 3 {r3:.2f} jointly, "
          f"{r3own:.2f} taken as independent")
    assert 0.6 < r24 < 1.3
    assert 0.6 < r3 < 1.5
    assert r3own > 2.0


def test_a_model_placed_by_points_from_a_map_is_kept_and_a_wrong_one_refused():
    """Points read off an orthophoto and a DEM (0.15 m) miss an SfM model by 5-10 px at 40 m: a right model is
    kept and its photos placed within what the points allow (a fixed 3 px RMS limit refused it, and every photo
    resected from the same points too); a model whose focal is 15 % off is still refused by points surveyed to
    1 cm. (At 0.3 m the cameras are fixed to 0.7 m only, which ``model_max_sigma_centre_m`` refuses, saying so.)"""
    rng = np.random.default_rng(24)
    intr, cams, X, _, views = _scene(rng)
    opts = GeorefOptions(sigma_px=SIGMA_PX, ransac_iterations=30)
    cps = _draw_points(intr, views, cams, X, rng, 0.15)
    res = solve_similarity(views, cps, opts=opts, where="test")
    verdict, figures = model_verdict(res, views, opts)
    assert res.stats["rms_px"] > 1.5 * GeorefOptions().warn_rms_px, res.stats["rms_px"]  # over the fixed limit
    assert verdict is None, verdict
    assert figures["n_outliers"] == 0
    for v, M in zip(views, cams):  # the photos within 3 sigma of their stated centre error
        d = res.apply(model_centre(v.cam_from_model)) - (-M[:3, :3].T @ M[:3, 3])
        C = res.view_covariance(v.cam_from_model)[3:, 3:]
        assert float(d @ np.linalg.solve(C, d)) < 14.2  # chi-square 3 dof, 0.997
    photos = IncidentPhotos(frozenset(v.name for v in views), True, lambda n: (intr.width, intr.height),
                            lambda n: n)
    out, why = resect_unplaced(photos, [("main", views)], {}, cps, {}, opts, "test")
    assert len(out) == len(views), why
    # a second pass (the georef's, with the refined camera) over the photos a first one left makes a group of its
    # own: one name for both would give their photos one shared error of two ranks
    first = {n: out[n] for n in sorted(out)[:3]}
    again, _ = resect_unplaced(photos, [("main", views)], first, cps, {}, opts, "test")
    assert sorted(again) == sorted(out)[3:]
    assert {r["joint"]["group"] for r in again.values()}.isdisjoint({r["joint"]["group"] for r in out.values()})
    # SfM's focal 15 % long: the model's cameras see the scene narrower; surveyed points refuse it
    wrong_intr = CameraIntrinsics(width=1600, height=1200, fx=1725.0, fy=1725.0, cx=799.5, cy=599.5)
    wrong = [SfmView(v.name, wrong_intr, v.cam_from_model) for v in views]
    fine = _draw_points(intr, views, cams, X, rng, 0.01)
    verdict, _ = model_verdict(solve_similarity(wrong, fine, opts=opts, where="test"), wrong, opts)
    assert verdict is not None and ("the model or a point is wrong" in verdict or "disagrees" in verdict), verdict
