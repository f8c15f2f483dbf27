"""A one-face pose's two branches (``correspond.ground``): the terrain tells them apart where the face's fit cannot.

A shoreliner rolled 21.5 deg on flat ground, its left side seen from a camera 15 m up. Its face is aligned with the
misfit of an ECC alignment (each corner of the face moved 0.15 px, the lattice mapped by the homography that
makes), as the finder's lattice is.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from workbench.core.camera import CameraIntrinsics, look_at
from workbench.core.geometry import rot_x, rot_z, rotation_angle_deg
from workbench.correspond.ground import FIT_DOF, Ground, planar_pose
from workbench.correspond.references import face_reference
from workbench.correspond.resting import collision_corners, rest
from workbench.rolling_stock import get_type

K = CameraIntrinsics(width=800, height=600, fx=858.0, fy=858.0, cx=399.5, cy=299.5)


class Flat:
    """A terrain model at height 0 everywhere."""

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        return np.zeros(len(xy))


def _scene(distance_m: float, yaw_deg: float, lift_m: float = 0.0):
    """(X (65, 3) the left side's lattice in the carriage frame, its true pixels (65, 2), its corners' pixels
    (4, 2), the true cam_from_carriage, the ground): the car rolled -21.5 deg, resting on flat ground (raised by
    ``lift_m``: on debris), the camera ``distance_m`` off its side, turned ``yaw_deg`` from square-on."""
    ct = get_type("shoreliner")
    ref = face_reference(ct, "6100", "left", 25.0)
    h, w = ref.image.shape[:2]
    g = np.stack(np.meshgrid(np.linspace(0, w - 1, 13), np.linspace(0, h - 1, 5)), -1).reshape(-1, 2)
    X = ref.carriage_from_ref(g)
    corners = ref.carriage_from_ref(np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], float))
    W = np.eye(4)
    W[:3, :3] = rot_z(np.radians(140.0)) @ rot_x(np.radians(-21.5))
    W = rest(W, collision_corners(ct), Flat())
    W[2, 3] += lift_m
    n = W[:3, :3] @ ct.face_normal("left")
    c = W[:3, :3] @ X.mean(0) + W[:3, 3]
    side = np.array([n[0], n[1], 0.0]) / np.hypot(n[0], n[1])
    cam_from_world = look_at(c + distance_m * (rot_z(np.radians(yaw_deg)) @ side) + [0.0, 0.0, 15.0], c)
    M = cam_from_world @ W
    px = K.project(X @ M[:3, :3].T + M[:3, 3])
    return ct, X, px, K.project(corners @ M[:3, :3].T + M[:3, 3]), M, Ground(cam_from_world, Flat(), 0.25)


def _aligned(px: np.ndarray, corners_px: np.ndarray, seed: int, sigma_px: float = 0.15) -> np.ndarray:
    """The lattice as an alignment with misfit finds it: the homography that moves each corner by ``sigma_px``."""
    rng = np.random.default_rng(seed)
    H, _ = cv2.findHomography(corners_px, corners_px + rng.normal(0.0, sigma_px, (4, 2)), 0)
    return cv2.perspectiveTransform(px.reshape(-1, 1, 2), H).reshape(-1, 2)


def _right(pose, M, X, x) -> bool:
    """Whether ``pose`` is on the true branch: of IPPE's two branches (refined), the one nearer the truth ``M``
    (a far face's branch may itself be several degrees off)."""
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(X, x, K.K, None, flags=cv2.SOLVEPNP_IPPE)
    Rs = [cv2.Rodrigues(cv2.solvePnPRefineLM(X, x, K.K, None, r.copy(), t.copy())[0])[0] for r, t in zip(rvecs, tvecs)]
    true_R = min(Rs, key=lambda R: rotation_angle_deg(R, M[:3, :3]))
    return rotation_angle_deg(pose.cam_from_carriage[:3, :3], true_R) < 1e-3


def test_a_far_thin_side_takes_the_branch_that_rests_on_the_ground():
    """A side 107 px by 10 px at 200 m: on 40 alignments the face's fit alone takes the mirrored branch (the car
    rolled the other way, its body into the ground) 8 times; judged with the terrain, never. Where the
    terrain decided, the pose says so (``chosen_by``)."""
    ct, X, px, corners_px, M, ground = _scene(200.0, 0.0)
    assert ground.clearance(ct, M) == pytest.approx(0.0, abs=1e-9)
    fit_wrong, chosen = 0, set()
    for seed in range(40):
        x = _aligned(px, corners_px, seed)
        alone = planar_pose(X, x, K.K, dof=FIT_DOF)
        judged = planar_pose(X, x, K.K, dof=FIT_DOF, ct=ct, ground=ground)
        fit_wrong += not _right(alone, M, X, x)
        assert _right(judged, M, X, x), (seed, judged.rms_px, judged.clearance_m)
        chosen.add(judged.chosen_by)
        assert len(judged.rms_px) == 2 and min(abs(c) for c in judged.clearance_m) < 0.5
    assert 3 <= fit_wrong <= 20, fit_wrong
    assert chosen == {"fit", "ground"}


def test_a_decisive_face_is_not_overruled_by_the_ground():
    """A side seen nearer and turned 25 deg (its perspective tells the branches apart) on a car raised 1.5 m onto
    debris the DEM does not hold: the ground's term is capped at 3 sigma, so the face's fit keeps the true branch,
    as it does alone."""
    ct, X, px, corners_px, M, ground = _scene(130.0, 25.0, lift_m=1.5)
    assert ground.clearance(ct, M) == pytest.approx(1.5, abs=1e-6)
    for seed in range(20):
        x = _aligned(px, corners_px, seed)
        assert _right(planar_pose(X, x, K.K, dof=FIT_DOF), M, X, x)
        judged = planar_pose(X, x, K.K, dof=FIT_DOF, ct=ct, ground=ground)
        assert _right(judged, M, X, x) and judged.chosen_by == "fit", (seed, judged.rms_px, judged.clearance_m)


def test_without_a_terrain_the_face_alone_decides_by_its_refined_fit():
    """No ground: of IPPE's two branches, both refined, the one with the smaller residual (IPPE's own order, of its
    closed-form poses, is reversed by the refinement in some alignments of a far, thin face); off the terrain
    model (NaN heights) the ground scores nothing and the result is the same."""
    ct, X, px, corners_px, M, ground = _scene(200.0, 0.0)

    class Nowhere:
        def height_at(self, xy):
            return np.full(len(xy), np.nan)

    off = Ground(ground.cam_from_world, Nowhere(), 0.25)
    reversed_ = 0
    for seed in range(40):
        x = _aligned(px, corners_px, seed)
        alone = planar_pose(X, x, K.K, dof=FIT_DOF)
        assert alone.chosen_by == "fit" and np.all(np.isnan(alone.clearance_m))
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(X, x, K.K, None, flags=cv2.SOLVEPNP_IPPE)
        refined = [cv2.solvePnPRefineLM(X, x, K.K, None, r.copy(), t.copy()) for r, t in zip(rvecs, tvecs)]
        i = int(np.argmin(alone.rms_px))
        assert np.allclose(alone.cam_from_carriage[:3, 3], refined[i][1].ravel())
        reversed_ += i != 0
        blind = planar_pose(X, x, K.K, dof=FIT_DOF, ct=ct, ground=off)
        assert blind.chosen_by == "fit" and np.all(np.isnan(blind.clearance_m))
        assert np.array_equal(blind.cam_from_carriage, alone.cam_from_carriage)
    assert reversed_ >= 1


BOARD = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "calibration" / "opencv_stereo_chessboard"


@pytest.mark.skipif(not BOARD.is_dir(), reason="../shared/data/calibration is not here")
def test_on_real_chessboard_photos_the_chosen_branch_is_the_boards_pose():
    """Real photos (OpenCV's 13 left chessboard views, its known-good intrinsics; ../shared/data/SOURCES.md): the
    board is a plane, and the branch ``planar_pose`` chooses is the pose the whole board's iterative PnP gives, to
    0.01 deg; from a strip of two rows of corners (18 of 54), still within 1 deg (measured: at most 0.64)."""
    K = np.array([[535.9157, 0.0, 342.2832], [0.0, 535.9157, 235.5708], [0.0, 0.0, 1.0]])
    dist = np.array([-0.26637, -0.03859, 0.001783, -0.000281, 0.23839])
    obj = np.zeros((54, 3))
    obj[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 0.025
    strip = np.r_[18:36]
    n = 0
    for f in sorted(BOARD.glob("left*.jpg")):
        g = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCorners(g, (9, 6))
        if not ok:
            continue
        c = cv2.cornerSubPix(g, c, (11, 11), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01))
        und = cv2.undistortPoints(c, K, dist, P=K).reshape(-1, 2)
        ok, rvec, _ = cv2.solvePnP(obj, und, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
        R = cv2.Rodrigues(rvec)[0]
        full = planar_pose(obj, und, K, dof=2 * 54 - 6)
        thin = planar_pose(obj[strip], und[strip], K, dof=2 * len(strip) - 6)
        assert rotation_angle_deg(full.cam_from_carriage[:3, :3], R) < 0.01, f.name
        assert rotation_angle_deg(thin.cam_from_carriage[:3, :3], R) < 1.0, f.name
        n += 1
    assert n == 13
