"""Ground truth for stitching: views cut out of one real photo by known rotations (pure rotation, exactly).

A photo is treated as a pinhole image (focal ``src_focal_px``, principal point at its centre); every view
is rendered from it through a chosen :class:`~workbench.core.camera.CameraIntrinsics` (distortion
included) and rotation ``cam_from_src``. The views are then an exact rotation-only photo set of the
scene the photo shows (whatever its own lens did), with known focal, distortion and rotations.
Used by the tests and ``scripts/bench_stitch.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from ..core.camera import CameraIntrinsics
from ..core.geometry import log_so3, orthonormal, rot_x, rot_y, rot_z


@dataclass(frozen=True)
class CutView:
    name: str
    image: np.ndarray  # (h, w, 3) uint8, same channel order as the source
    intrinsics: CameraIntrinsics
    cam_from_src: np.ndarray  # (3, 3)


def grid_rotations(yaws_deg: list[float], pitches_deg: list[float], roll_sigma_deg: float = 1.5,
                   seed: int = 0) -> list[np.ndarray]:
    """``cam_from_src`` rotations on a yaw x pitch grid (camera axes: x right, y down, z forward), small rolls."""
    rng = np.random.default_rng(seed)
    out = []
    for p in pitches_deg:
        for y in yaws_deg:
            # src_from_cam: turn right by yaw (about +y, down), up by pitch (about -x), roll about z
            roll = rng.normal(0.0, roll_sigma_deg)
            src_from_cam = rot_y(np.radians(y)) @ rot_x(np.radians(-p)) @ rot_z(np.radians(roll))
            out.append(src_from_cam.T)
    return out


def cut_views(src: np.ndarray, src_focal_px: float, rotations: list[np.ndarray], intrinsics: CameraIntrinsics,
              *, prefix: str = "view") -> list[CutView]:
    """Render one view per ``cam_from_src`` rotation from ``src`` (H, W, 3) uint8 with focal ``src_focal_px``.

    The source is first reduced (area filter) to about 1.5 times the views' focal, then sampled bilinearly.
    Raises ValueError if a view looks outside the source photo.
    """
    H, W = src.shape[:2]
    r = min(1.0, 1.5 * intrinsics.fx / src_focal_px)
    if r < 1.0:
        src = cv2.resize(src, (int(round(W * r)), int(round(H * r))), interpolation=cv2.INTER_AREA)
    h_s, w_s = src.shape[:2]
    f_s = src_focal_px * w_s / W
    cx_s, cy_s = (w_s - 1) / 2.0, (h_s - 1) / 2.0
    w, h = intrinsics.width, intrinsics.height
    vv, uu = np.meshgrid(np.arange(h, dtype=float), np.arange(w, dtype=float), indexing="ij")
    rays = intrinsics.rays(np.column_stack([uu.ravel(), vv.ravel()]))
    views = []
    for k, R in enumerate(rotations):
        d = rays @ R  # src_from_cam = R.T: d_src = R.T @ ray
        x = f_s * d[:, 0] / d[:, 2] + cx_s
        y = f_s * d[:, 1] / d[:, 2] + cy_s
        if d[:, 2].min() <= 0 or x.min() < 0 or y.min() < 0 or x.max() > w_s - 1 or y.max() > h_s - 1:
            raise ValueError(f"view {k} looks outside the source photo; use smaller rotations or a narrower view")
        img = cv2.remap(src, x.reshape(h, w).astype(np.float32), y.reshape(h, w).astype(np.float32),
                        cv2.INTER_LINEAR)
        views.append(CutView(f"{prefix}_{k:02d}.jpg", img, intrinsics, np.asarray(R, float)))
    return views


def align_rotation(estimated: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> np.ndarray:
    """``pano_from_ref`` (3, 3): the rotation that best aligns ``estimated`` (name -> ``cam_from_pano``) with
    ``truth`` (name -> ``cam_from_ref``), i.e. minimises sum ||est_i A - truth_i||^2 (orthogonal Procrustes)."""
    names = [n for n in estimated if n in truth]
    if not names:
        raise ValueError("no photo in common between the estimated and the true rotations")
    return orthonormal(sum(estimated[n].T @ truth[n] for n in names))


def rotation_errors_deg(estimated: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> dict[str, float]:
    """Per photo, the angle (degrees) of ``est_i @ A @ truth_i^T`` after the best global alignment ``A``.

    ``estimated``: name -> ``cam_from_pano``; ``truth``: name -> ``cam_from_ref`` (any common reference frame);
    ``A = align_rotation(estimated, truth)``.
    """
    A = align_rotation(estimated, truth)
    # the nearest rotation first: an estimate need not be exactly orthonormal (cv2's are single precision)
    return {n: float(np.degrees(np.linalg.norm(log_so3(orthonormal(estimated[n] @ A @ truth[n].T)))))
            for n in estimated if n in truth}
