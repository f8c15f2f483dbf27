"""Conventions (docs/conventions.md): round trips between CRS, WGS84, ENU, camera and pixel."""

import numpy as np
import pytest
import cv2

from workbench.core.camera import CameraIntrinsics, look_at, project_world
from workbench.core.frames import (Rigid, SceneFrame, hpr_from_rotation, is_rotation, rotation_from_hpr)
from workbench.errors import SettingsError

BRONX = dict(crs="EPSG:32618", lat_deg=40.8780, lon_deg=-73.9215, height_m=3.0)


def test_enu_origin_and_axes():
    f = SceneFrame(**BRONX)
    assert np.allclose(f.enu_from_wgs84(np.array([BRONX["lon_deg"], BRONX["lat_deg"], 3.0])), 0, atol=1e-6)
    # 0.001 deg north is ~111 m north, no east; 0.001 deg east is ~84 m east at 40.9 N
    n = f.enu_from_wgs84(np.array([BRONX["lon_deg"], BRONX["lat_deg"] + 0.001, 3.0]))
    e = f.enu_from_wgs84(np.array([BRONX["lon_deg"] + 0.001, BRONX["lat_deg"], 3.0]))
    assert 110.9 < n[1] < 111.2 and abs(n[0]) < 1e-6
    assert 83.8 < e[0] < 84.5 and abs(e[1]) < 1e-3  # a parallel curves away from the tangent plane
    # up: a point 10 m higher
    u = f.enu_from_wgs84(np.array([BRONX["lon_deg"], BRONX["lat_deg"], 13.0]))
    assert np.allclose(u, [0, 0, 10], atol=1e-6)


def test_crs_enu_round_trip_and_convergence():
    f = SceneFrame(**BRONX)
    rng = np.random.default_rng(0)
    enu = rng.uniform([-500, -500, -20], [500, 500, 40], (200, 3))
    back = f.enu_from_crs(f.crs_from_enu(enu))
    assert np.max(np.abs(back - enu)) < 1e-6
    assert np.max(np.abs(f.enu_from_wgs84(f.wgs84_from_enu(enu)) - enu)) < 1e-6
    # UTM 18N central meridian is 75 W; at 73.92 W grid north is rotated clockwise... convergence ~ +0.7 deg
    conv = f.grid_convergence_deg()
    assert 0.6 < conv < 0.8
    # a CRS offset of 100 m east is ~100 m in ENU (scale factor ~0.9996 + rotation)
    o = f.origin_crs
    d = f.enu_from_crs(np.array([o[0] + 100.0, o[1], o[2]]))
    assert 99.9 < np.hypot(d[0], d[1]) < 100.1
    assert np.isclose(np.rad2deg(np.arctan2(-d[1], d[0])), conv, atol=0.01)


def test_not_projected_crs_refused():
    with pytest.raises(SettingsError, match="not a projected CRS"):
        SceneFrame("EPSG:4326", 40.0, -74.0)
    with pytest.raises(SettingsError, match="not a CRS"):
        SceneFrame("EPSG:999999", 40.0, -74.0)


@pytest.mark.parametrize("hpr", [(0, 0, 0), (90, 0, 0), (123.4, 5.6, -78.9), (359.0, -30.0, 170.0), (10, 89.0, 0)])
def test_heading_pitch_roll_round_trip(hpr):
    R = rotation_from_hpr(*hpr)
    assert is_rotation(R)
    h, p, r = hpr_from_rotation(R)
    assert np.allclose(rotation_from_hpr(h, p, r), R, atol=1e-9)
    if abs(hpr[1]) < 89:
        assert np.isclose((h - hpr[0] + 180) % 360 - 180, 0, atol=1e-9)
        assert np.isclose(p, hpr[1]) and np.isclose(r, hpr[2])


def test_heading_pitch_roll_meaning():
    # heading 90 (east): the carriage's x axis points east
    assert np.allclose(rotation_from_hpr(90, 0, 0) @ [1, 0, 0], [1, 0, 0], atol=1e-12)
    # heading 0 (north)
    assert np.allclose(rotation_from_hpr(0, 0, 0) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    # pitch +10: nose up
    assert (rotation_from_hpr(0, 10, 0) @ [1, 0, 0])[2] > 0.17
    # roll +20: right side (-y) goes down
    assert (rotation_from_hpr(0, 0, 20) @ [0, -1, 0])[2] < -0.3


def test_rigid_frames_checked():
    a = Rigid(rotation_from_hpr(30, 0, 0), [1, 2, 3], "world", "carriage")
    cam = Rigid(rotation_from_hpr(0, 10, 0), [0, 0, 5], "cam", "world")
    cam_from_carriage = cam @ a
    assert cam_from_carriage.name == "cam_from_carriage"
    p = np.array([1.0, -2.0, 0.5])
    assert np.allclose(cam_from_carriage.apply(p), cam.apply(a.apply(p)))
    assert np.allclose((a.inverse() @ a).matrix, np.eye(4), atol=1e-12)
    with pytest.raises(ValueError, match="cannot compose"):
        a @ cam  # carriage <- world, then cam <- world: mismatched


def test_camera_matches_opencv_and_rays_round_trip():
    c = CameraIntrinsics(width=800, height=600, fx=700, fy=702, cx=410.3, cy=296.8,
                         k1=-0.1, k2=0.03, k3=-0.002, p1=0.0008, p2=-0.0005)
    rng = np.random.default_rng(1)
    pts = rng.uniform([-3, -2, 4], [3, 2, 12], (300, 3))
    uv = c.project(pts)
    uv_cv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), c.K, c.dist_coeffs)
    assert np.max(np.abs(uv - uv_cv[:, 0])) < 1e-9
    rays = c.rays(uv)
    assert np.max(np.abs(rays - pts / np.linalg.norm(pts, axis=1, keepdims=True))) < 1e-10


def test_world_to_pixel_chain():
    """CRS point -> ENU -> camera -> pixel, and the pixel ray back hits the point."""
    f = SceneFrame(**BRONX)
    c = CameraIntrinsics(width=640, height=480, fx=500, fy=500, cx=319.5, cy=239.5, k1=-0.05)
    eye = np.array([-40.0, -30.0, 12.0])
    target_crs = f.origin_crs + np.array([5.0, 8.0, 1.0])
    target_enu = f.enu_from_crs(target_crs)
    M = look_at(eye, target_enu)
    uv, depth = project_world(c, M, target_enu[None])
    assert np.allclose(uv[0], [c.cx, c.cy], atol=1e-9)  # looked-at point is at the principal point
    ray_world = M[:3, :3].T @ c.rays(uv)[0]
    assert np.allclose(eye + ray_world * np.linalg.norm(target_enu - eye), target_enu, atol=1e-9)
    # camera axes: a point right of the target projects right of centre; a point above projects higher (smaller v)
    right = np.cross(target_enu - eye, [0, 0, 1.0])
    uv2, _ = project_world(c, M, np.array([target_enu + 0.5 * right / np.linalg.norm(right), target_enu + [0, 0, 1]]))
    assert uv2[0, 0] > c.cx and uv2[1, 1] < c.cy


def test_scaled_intrinsics_keep_pixel_centres():
    c = CameraIntrinsics(width=100, height=80, fx=90, fy=90, cx=49.5, cy=39.5)
    s = c.scaled(2.0)
    assert (s.width, s.height) == (200, 160)
    assert np.isclose(s.cx, 99.5) and np.isclose(s.cy, 79.5)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 0.3, 2.0, np.pi - 1e-2, np.pi - 1e-5, np.pi - 1e-9, np.pi])
def test_so3_log_inverts_exp_at_every_angle(angle):
    """``log_so3(exp_so3(w)) = w`` for angles in [0, pi) (at pi, either sign of the axis), and it agrees with
    scipy's rotation vectors, which the georef solvers used before (the one geometry module, issue 19)."""
    from scipy.spatial.transform import Rotation

    from workbench.core.geometry import exp_so3, log_so3

    rng = np.random.default_rng(7)
    for _ in range(50):
        a = rng.normal(size=3)
        w = a / np.linalg.norm(a) * angle
        R = exp_so3(w)
        lw = log_so3(R)
        assert np.linalg.norm(exp_so3(lw) - R) < 1e-12
        assert np.linalg.norm(np.cross(lw, w)) < 1e-9 * max(angle, 1.0)  # the same axis
        if angle < np.pi - 1e-6:
            assert np.allclose(lw, w, atol=1e-12) and np.allclose(lw, Rotation.from_matrix(R).as_rotvec(), atol=1e-12)
        else:
            assert abs(np.linalg.norm(lw) - angle) < 1e-9


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 0.3, 2.0, np.pi - 1e-5, np.pi])
def test_rotation_angle_is_exact_at_every_angle(angle):
    """``rotation_angle_deg`` between two rotations that differ by ``angle`` about a random axis: to 1e-12
    relative at every angle, small ones too (the arccos of the trace alone gave 1.2e-6 deg for a turn of
    zero in the solution's step diagnostics)."""
    from workbench.core.geometry import exp_so3, rotation_angle_deg

    rng = np.random.default_rng(11)
    for _ in range(20):
        a = rng.normal(size=3)
        Rb = exp_so3(rng.normal(size=3))
        Ra = exp_so3(a / np.linalg.norm(a) * angle) @ Rb
        for got in (rotation_angle_deg(Ra, Rb), rotation_angle_deg(Rb, Ra)):
            assert abs(got - np.rad2deg(angle)) <= 1e-12 * max(np.rad2deg(angle), 1e-3) + 1e-14


def test_exp_so3_one_vector_equals_many():
    """The one-vector path of ``exp_so3`` (the solvers' inner loops) gives the batch path's matrices to the bit."""
    from workbench.core.geometry import exp_so3

    rng = np.random.default_rng(3)
    ws = np.concatenate([rng.normal(size=(400, 3)) * s for s in (0.0, 1e-9, 1e-7, 1e-3, 1.0, 3.0)])
    assert np.array_equal(np.array([exp_so3(w) for w in ws]), exp_so3(ws))


def test_axis_rotations_match_scipy_euler_angles():
    """``rot_x``, ``rot_y``, ``rot_z`` composed as SciPy's intrinsic (upper case) and extrinsic (lower case)
    Euler sequences give its matrices to 1e-12 (synth/control_points.similarity, stitch/cutviews)."""
    from scipy.spatial.transform import Rotation

    from workbench.core.geometry import rot_x, rot_y, rot_z

    rot = {"x": rot_x, "y": rot_y, "z": rot_z}
    rng = np.random.default_rng(5)
    for _ in range(50):
        ang = rng.uniform(-180.0, 180.0, 3)
        for seq in ("YXZ", "ZYX", "zyx", "xyz"):
            Rs = [rot[a.lower()](np.radians(t)) for a, t in zip(seq, ang)]
            R = Rs[0] @ Rs[1] @ Rs[2] if seq.isupper() else Rs[2] @ Rs[1] @ Rs[0]
            assert np.abs(R - Rotation.from_euler(seq, ang, degrees=True).as_matrix()).max() < 1e-12


@pytest.mark.parametrize("angle", [0.0, 1e-9, 0.3, 2.0, np.pi - 1e-6, np.pi])
def test_quaternion_from_matrix_matches_scipy(angle):
    """``quaternion_xyzw_from_matrix`` (the glTF export's node rotations) is SciPy's ``as_quat`` to 1e-12, sign
    included, at every angle; it rotates as the matrix does."""
    from scipy.spatial.transform import Rotation

    from workbench.core.geometry import exp_so3, quaternion_xyzw_from_matrix

    rng = np.random.default_rng(11)
    for _ in range(50):
        a = rng.normal(size=3)
        R = exp_so3(a / np.linalg.norm(a) * angle)
        q = quaternion_xyzw_from_matrix(R)
        assert np.abs(q - Rotation.from_matrix(R).as_quat()).max() < 1e-12
        assert abs(np.linalg.norm(q) - 1.0) < 1e-15
        assert np.abs(Rotation.from_quat(q).as_matrix() - R).max() < 1e-12
    with pytest.raises(ValueError, match="expected"):
        quaternion_xyzw_from_matrix(np.eye(4))


def test_rotation_between_is_the_smallest_rotation():
    """``rotation_between(a, b)`` is a rotation that takes ``a``'s direction to ``b``'s, about their common normal
    (the smallest: its angle is the angle between them), at every angle including opposite directions."""
    from workbench.core.geometry import log_so3, rotation_between

    rng = np.random.default_rng(3)
    cases = [(rng.normal(size=3), rng.normal(size=3)) for _ in range(200)]
    cases += [(np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, -1.0])), (np.array([1.0, 0, 0]), np.array([3.0, 0, 0])),
              (np.array([0.3, -0.2, 0.9]), -np.array([0.3, -0.2, 0.9]) + 1e-9)]
    for a, b in cases:
        R = rotation_between(a, b)
        ua, ub = a / np.linalg.norm(a), b / np.linalg.norm(b)
        assert is_rotation(R)
        assert np.abs(R @ ua - ub).max() < 1e-7
        angle = np.arccos(np.clip(ua @ ub, -1.0, 1.0))
        w = log_so3(R)
        assert abs(np.linalg.norm(w) - angle) < 1e-6
        if 1e-6 < angle < np.pi - 1e-6:  # the axis: the common normal
            assert abs(w @ ua) < 1e-9 and abs(w @ ub) < 1e-9


def test_orthonormal_is_the_nearest_rotation():
    """``orthonormal(M)`` is a rotation (R R^T = I to 1e-14, det +1), nearer to M (Frobenius) than any rotation
    about it, for M a rotation with noise and any scale (a homography's ``K_j^-1 H K_i``) and for M with a
    reflection (det < 0); a rotation comes back as it is to 1e-14."""
    from workbench.core.geometry import exp_so3, orthonormal

    rng = np.random.default_rng(13)
    for k in range(60):
        R = exp_so3(rng.normal(size=3))
        M = rng.uniform(0.2, 5.0) * (R + rng.normal(scale=0.05, size=(3, 3)))
        if k % 3 == 0:
            M = M @ np.diag([1.0, 1.0, -1.0])
        Q = orthonormal(M)
        assert np.abs(Q @ Q.T - np.eye(3)).max() < 1e-14 and abs(np.linalg.det(Q) - 1.0) < 1e-14
        s = np.trace(Q.T @ M) / 3.0  # the scale that best fits M to Q
        d0 = np.linalg.norm(s * Q - M)
        for _ in range(20):
            assert d0 <= np.linalg.norm(s * exp_so3(rng.normal(scale=0.02, size=3)) @ Q - M) + 1e-12
        if k % 3:
            assert np.linalg.norm(Q - R) < 0.2  # near the rotation the noise was added to
        assert np.abs(orthonormal(R) - R).max() < 1e-14
