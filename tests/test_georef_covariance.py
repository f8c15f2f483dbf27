"""The central route's stated camera covariance (``georegistration.covariance_world_rotation_centre``) is honest
as a whole, not only axis by axis: the rotation's correlation with the centre has the right sign, which decides
how much of the camera's error reaches a carriage near the control points (a Monte Carlo against the truth)."""

from __future__ import annotations

import numpy as np

from workbench.core.camera import CameraIntrinsics, look_at
from workbench.core.geometry import log_so3
from workbench.files.control_points import ControlPoint
from workbench.files.panorama import RigView
from workbench.georef.central import solve_central
from workbench.georef.options import GeorefOptions
from workbench.solve.camera_term import camera_pose_jacobian


def _picked_in_one_photo(intr: CameraIntrinsics, R: np.ndarray, centre: np.ndarray, X: np.ndarray,
                         rng: np.random.Generator) -> list[ControlPoint]:
    """Control points ``X`` (n, 3) picked in one photo ``a.jpg`` (``cam_from_world`` rotation ``R``, ``centre``):
    each pick its true pixel + N(0, 1 px), each point surveyed with N(0, 5 cm) per axis (stated 5 cm)."""
    cps = []
    for k, x in enumerate(X):
        uv = intr.project(((x - centre) @ R.T)[None])[0] + rng.normal(0, 1.0, 2)
        cps.append(ControlPoint(f"p{k}", x + rng.normal(0, 0.05, 3), 0.05, {"a.jpg": uv}))
    return cps


def test_camera_covariance_is_honest_jointly_and_at_the_carriages():
    """One 1600 x 1200 photo from 12 m up, 8 control points 60-160 m away (1 px picks, 5 cm survey error): over
    60 draws the camera's 6-d error has a mean squared Mahalanobis distance near 6 (chi-square, 6 dof; the sign
    of the rotation-centre block flipped gave a median near 180 on the automatic-point benchmark), and a point
    among the control points moves with the camera error as much as ``A C A^T`` says (RMS z in 0.75-1.3 per
    axis; with the sign flipped it is about 0.2-0.5)."""
    rng = np.random.default_rng(7)
    intr = CameraIntrinsics(width=1600, height=1200, fx=1400.0, fy=1400.0, cx=799.5, cy=599.5)
    centre = np.array([0.0, 0.0, 12.0])
    M = look_at(centre, np.array([0.0, 110.0, 0.0]))
    R = M[:3, :3]
    X = np.column_stack([rng.uniform(-40, 40, 8), rng.uniform(60, 160, 8), rng.uniform(0, 6, 8)])
    target = np.array([5.0, 105.0, 1.5])  # a carriage among the control points
    m2, z = [], []
    for _ in range(60):
        cps = _picked_in_one_photo(intr, R, centre, X, rng)
        res = solve_central([RigView("a.jpg", intr, np.eye(3))], cps, opts=GeorefOptions())
        C = np.asarray(res.stats["covariance_world_rotation_centre"], float)
        # the error as the scene's rigid motion that takes the true camera onto the estimate (the bench's)
        Re = res.rig_from_world
        e = np.concatenate([log_so3(Re.T @ R), res.centre_enu - centre])
        m2.append(float(e @ np.linalg.solve(C, e)))
        moved = Re.T @ R @ (target - centre) + res.centre_enu - target
        Mt = np.eye(4)
        Mt[:3, 3] = target
        Cp = (camera_pose_jacobian(Mt, res.centre_enu) @ C @ camera_pose_jacobian(Mt, res.centre_enu).T)[3:, 3:]
        z.append(moved / np.sqrt(np.diag(Cp)))
    m2, z = np.array(m2), np.array(z)
    assert 4.5 < m2.mean() < 8.0, (m2.mean(), np.median(m2))
    rms = np.sqrt(np.mean(z**2, axis=0))
    assert np.all((0.75 < rms) & (rms < 1.3)), rms


def test_a_landmark_picked_in_several_photos_counts_once():
    """A three-photo panorama (each photo turned 25 deg from the next, overlapping), 10 landmarks 30-90 m away
    placed on a map at 0.3 m (as the picker's map picks) and each picked in every photo that sees it (1 px): the landmark's map
    error is one error shared by its picks, and the stated covariance says so (mean squared Mahalanobis distance
    over 60 draws in 4.5-8; counting each pick's share of it as independent gave a covariance too narrow)."""
    rng = np.random.default_rng(11)
    intr = CameraIntrinsics(width=1200, height=900, fx=1100.0, fy=1100.0, cx=599.5, cy=449.5)
    centre = np.array([0.0, 0.0, 8.0])
    M = look_at(centre, np.array([0.0, 90.0, 0.0]))
    R = M[:3, :3]  # rig = the middle photo
    from workbench.core.geometry import rot_y

    rigs = [RigView(f"p{k}.jpg", intr, rot_y(np.radians(25.0 * (k - 1)))) for k in range(3)]
    ang = np.radians(rng.uniform(-40, 40, 10))
    dist = rng.uniform(30, 90, 10)
    X = np.column_stack([dist * np.sin(ang), dist * np.cos(ang), rng.uniform(0, 12, 10)])
    m2, n_multi = [], 0
    for _ in range(60):
        cps = []
        for k, x in enumerate(X):
            xm = x + rng.normal(0, 0.3, 3)  # placed on the map
            obs = {}
            for v in rigs:
                q = np.asarray(v.cam_from_rig) @ (R @ (x - centre))
                if q[2] <= 0:
                    continue
                uv = intr.project(q[None])[0]
                if intr.in_image(uv[None], margin=5.0)[0]:
                    obs[v.name] = uv + rng.normal(0, 1.0, 2)
            n_multi += len(obs) > 1
            cps.append(ControlPoint(f"p{k}", xm, 0.3, obs))
        res = solve_central(rigs, [c for c in cps if c.pixels], opts=GeorefOptions())
        C = np.asarray(res.stats["covariance_world_rotation_centre"], float)
        e = np.concatenate([log_so3(res.rig_from_world.T @ R), res.centre_enu - centre])
        m2.append(float(e @ np.linalg.solve(C, e)))
    assert n_multi > 150, n_multi  # landmarks seen in two photos or three
    m2 = np.array(m2)
    assert 4.5 < m2.mean() < 8.0, (m2.mean(), np.median(m2))


def test_a_resection_with_its_focal_refined_states_pose_and_focal_together():
    """One photo placed on its own from 12 control points (1 px picks, 5 cm survey) with a focal 5 % off, the
    focal refined with the pose (``refine_resection_focal``) and the two written as one factor
    (``shared_camera.joint_factor``, what ``pose_uncertainty`` carries as a group of one photo): over 30 draws the
    7-d error (the scene rotation vector of ``world_from_cam``, the centre, the focal in px) has a mean squared
    Mahalanobis distance near 7 (6.1 measured over 40), the factor's pose rows reproduce the stated 6 x 6
    covariance and its focal row the stated focal sigma."""
    from workbench.georef.central import refine_resection_focal
    from workbench.georef.shared_camera import joint_factor

    rng = np.random.default_rng(17)
    true = CameraIntrinsics(width=1600, height=1200, fx=1400.0, fy=1400.0, cx=799.5, cy=599.5)
    start = CameraIntrinsics.from_dict({**true.to_dict(), "fx": 1470.0, "fy": 1470.0})
    centre = np.array([0.0, 0.0, 12.0])
    M = look_at(centre, np.array([0.0, 110.0, 0.0]))
    R = M[:3, :3]
    X = np.column_stack([rng.uniform(-40, 40, 12), rng.uniform(60, 160, 12), rng.uniform(0, 8, 12)])
    m2 = []
    for _ in range(30):
        cps = _picked_in_one_photo(true, R, centre, X, rng)
        res = solve_central([RigView("a.jpg", start, np.eye(3))], cps, opts=GeorefOptions())
        ff = refine_resection_focal(start, res, cps, "a.jpg", GeorefOptions())
        assert ff is not None
        order = [6, 0, 1, 2, 3, 4, 5]
        Me = ff["cam_from_world"]
        j = joint_factor(np.asarray(ff["covariance_pose_focal"])[np.ix_(order, order)], ff["intrinsics"], ("f",),
                         ["a.jpg"], [Me[:3, :3]])
        F, K = j["poses"]["a.jpg"], j["intrinsics"]
        assert np.allclose(F @ F.T, ff["covariance_world_rotation_centre"], rtol=1e-6, atol=1e-14)
        assert np.isclose(float(np.sqrt((K @ K.T)[0, 0])), ff["sigma_focal_px"], rtol=1e-6)
        Re = Me[:3, :3]
        e = np.concatenate([log_so3(Re.T @ R), -Re.T @ Me[:3, 3] - centre, [ff["focal_px"] - true.fx]])
        L = np.vstack([F, K])
        m2.append(float(e @ np.linalg.solve(L @ L.T, e)))
    assert 5.0 < float(np.mean(m2)) < 9.5, (np.mean(m2), np.median(m2))


def test_a_resection_with_sfm_intrinsics_carries_their_error():
    """One photo resected with SfM's intrinsics (12 control points, 1 px picks, 5 cm survey) where SfM's focal and
    k1 are off by a drawn error of their stated covariance (2 % and 0.02, correlated): the pose's error is its own
    fit's plus its response to that error (``resection.intrinsics_response``, ``D``): over 30 draws the mean squared
    Mahalanobis distance of the 6-d error against ``C_own + D C_k D^T`` is near 6 (5.3 measured), against ``C_own``
    alone it is far above (147: the fit alone takes the intrinsics as exact)."""
    from workbench.georef.resection import intrinsics_response

    rng = np.random.default_rng(23)
    true = CameraIntrinsics(width=1600, height=1200, fx=1400.0, fy=1400.0, cx=799.5, cy=599.5, k1=-0.05)
    Ck = np.array([[28.0 ** 2, 0.3 * 28.0 * 0.02], [0.3 * 28.0 * 0.02, 0.02 ** 2]])  # f (px), k1
    Lk = np.linalg.cholesky(Ck)
    centre = np.array([0.0, 0.0, 12.0])
    M = look_at(centre, np.array([0.0, 110.0, 0.0]))
    R = M[:3, :3]
    X = np.column_stack([rng.uniform(-40, 40, 12), rng.uniform(60, 160, 12), rng.uniform(0, 8, 12)])
    with_k, own_only = [], []
    for _ in range(30):
        sfm = true.moved(("f", "k1"), Lk @ rng.normal(size=2))
        cps = _picked_in_one_photo(true, R, centre, X, rng)
        res = solve_central([RigView("a.jpg", sfm, np.eye(3))], cps, opts=GeorefOptions())
        Me = res.cam_from_world(np.eye(3))
        C = np.asarray(res.stats["covariance_world_rotation_centre"], float)
        D = intrinsics_response(sfm, Me, cps, "a.jpg", res.residuals, ("f", "k1"), GeorefOptions())
        Re = Me[:3, :3]
        e = np.concatenate([log_so3(Re.T @ R), res.centre_enu - centre])
        with_k.append(float(e @ np.linalg.solve(C + D @ Ck @ D.T, e)))
        own_only.append(float(e @ np.linalg.solve(C, e)))
    assert 4.0 < float(np.mean(with_k)) < 8.5, (np.mean(with_k), np.mean(own_only))
    assert float(np.mean(own_only)) > 3.0 * float(np.mean(with_k)), (np.mean(with_k), np.mean(own_only))
