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
from workbench.solve.uncertainty import camera_pose_jacobian


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
        cps = []
        for k, x in enumerate(X):
            uv = intr.project(((x - centre) @ R.T)[None])[0] + rng.normal(0, 1.0, 2)
            cps.append(ControlPoint(f"p{k}", x + rng.normal(0, 0.05, 3), 0.05, {"a.jpg": uv}))
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
