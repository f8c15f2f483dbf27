"""Pose-guided completion of a found car: its other faces, aligned where the pose predicts them.

SIFT finds a car by the face it sees best (usually a long side). Its other faces that turn to the camera
(an end seen at an angle, the roof seen from above, the second side of a car lying on its side) are often
too small or too foreshortened for SIFT to pass the inlier threshold alone, yet the car's pose from the
found face predicts each of them to a few pixels. Each such face's reference is aligned to the photo by
dense ECC (homography) started from that prediction, and kept only if the alignment correlates well and
stayed near the prediction. The car's pose is then re-estimated from all its faces together (the points
are no longer coplanar: roll about the long axis, weak from one thin side, becomes well determined), which
also improves the points projected from the pose (couplers, corners of faces not aligned).

Pixels are undistorted photo pixels (``match.PhotoFeatures``); ``cam_from_carriage`` is (4, 4), metres.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from ..core.camera import CameraIntrinsics
from ..rolling_stock import CarriageType
from .match import FaceDetection, MatchOptions, PhotoFeatures, apply_h, ecc_refine, plausible_homography
from .references import FaceReference

log = logging.getLogger(__name__)

GRID = 5  # a guided face contributes a GRID x GRID lattice of its reference to the joint pose


def predicted_homography(cam_from_carriage: np.ndarray, ref: FaceReference, K: CameraIntrinsics) -> np.ndarray:
    """photo_from_ref (3, 3) in undistorted photo px, from the car's pose and the face's plane mapping.

    A reference pixel (u, v) is the carriage point ``origin + u axis_u + v axis_v``; in the camera it is
    ``R (origin + u axis_u + v axis_v) + t = [R axis_u | R axis_v | R origin + t] (u, v, 1)``.
    """
    R, t = cam_from_carriage[:3, :3], cam_from_carriage[:3, 3]
    A = np.empty((3, 3))  # (np.column_stack's columns, without its overhead: this runs for every hypothesis)
    A[:, 0] = R @ ref.axis_u_m
    A[:, 1] = R @ ref.axis_v_m
    A[:, 2] = R @ ref.origin_m + t
    H = K.K @ A  # the pinhole matrix (K.without_distortion().K: the same numbers)
    return H / H[2, 2]


def facing_cosine(cam_from_carriage: np.ndarray, ct: CarriageType, ref: FaceReference) -> float:
    """Cosine between the face's outward normal and the direction from the face's centre to the camera."""
    h, w = ref.image.shape[:2]
    c = ref.carriage_from_ref(np.array([[(w - 1) / 2, (h - 1) / 2]]))[0]
    R, t = cam_from_carriage[:3, :3], cam_from_carriage[:3, 3]
    Xc = R @ c + t
    n = R @ ct.face_normal(ref.face)
    return float(-(n @ Xc) / max(np.linalg.norm(Xc), 1e-9))


def guided_face(photo: PhotoFeatures, ref: FaceReference, cam_from_carriage: np.ndarray, ct: CarriageType,
                opts: MatchOptions) -> FaceDetection | None:
    """The face ``ref`` aligned by ECC where the pose puts it, or None when it is not convincingly there."""
    K = photo.intrinsics
    if facing_cosine(cam_from_carriage, ct, ref) < opts.guided_min_cosine:
        return None
    H0 = predicted_homography(cam_from_carriage, ref, K)
    size = (K.width, K.height)
    if not plausible_homography(H0, ref, size):
        return None
    poly0 = apply_h(H0, ref.corners())
    if not np.all(K.without_distortion().in_image(poly0, margin=2.0)):
        return None  # a face cut by the image border: ECC would align what is not there
    e = np.linalg.norm(np.roll(poly0, -1, axis=0) - poly0, axis=1)
    if min(e) < opts.guided_min_edge_px:
        return None
    res = ecc_refine(photo, ref, H0, min_cc=opts.guided_min_ecc)
    if res is None:
        return None
    H, cc = res
    if cc < opts.guided_min_ecc or not plausible_homography(H, ref, size):
        return None
    # ECC must have refined the prediction, not wandered off: the corners stay within a share of the face
    moved = np.linalg.norm(apply_h(H, ref.corners()) - poly0, axis=1)
    if moved.max() > max(opts.guided_max_shift_px, 0.25 * min(e)):
        return None
    h, w = ref.image.shape[:2]
    g = np.stack(np.meshgrid(np.linspace(0, w - 1, GRID), np.linspace(0, h - 1, GRID)), -1).reshape(-1, 2)
    return FaceDetection(ref, photo.name, H / H[2, 2], 0, 0.0, float(cc), apply_h(H, g), g, guided=True)


def joint_pose(detections: list[FaceDetection], K: CameraIntrinsics, start: np.ndarray) -> np.ndarray | None:
    """cam_from_carriage (4, 4) from the inliers of several faces of one car (undistorted px), or None."""
    X = np.vstack([d.ref.carriage_from_ref(d.inlier_ref_px) for d in detections])
    x = np.vstack([d.inlier_photo_px for d in detections])
    if len(X) < 6:
        return None
    rvec, _ = cv2.Rodrigues(start[:3, :3])
    tvec = start[:3, 3].reshape(3, 1).copy()
    ok, rvec, tvec = cv2.solvePnP(X.astype(np.float64), x.astype(np.float64), K.without_distortion().K, None,
                                  rvec, tvec, useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return None
    M = np.eye(4)
    M[:3, :3] = cv2.Rodrigues(rvec)[0]
    M[:3, 3] = tvec.ravel()
    if M[2, 3] <= 0:
        return None
    proj = K.without_distortion().K @ (M[:3, :3] @ X.T + M[:3, 3:4])
    resid = np.linalg.norm(proj[:2].T / proj[2:].T - x, axis=1)
    if np.sqrt(np.mean(resid ** 2)) > 3.0:  # the faces disagree: keep the single-face pose
        return None
    return M
