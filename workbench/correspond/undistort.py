"""Photos resampled to their pinhole camera (the lens's distortion removed), for the finder's matching."""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from ..core.camera import CameraIntrinsics

MAP_BLOCK_PX = 2_000_000  # pixels per block when the undistortion maps are computed


@lru_cache(maxsize=8)
def undistortion_maps(K: CameraIntrinsics, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (h, w) float32 from the pinhole camera's pixels to the photo's (cached per camera:
    the photos of a set share them; the stage computes them before its workers start)."""
    mx, my = np.empty((h, w), np.float32), np.empty((h, w), np.float32)
    u = np.arange(w, dtype=float)
    rows = max(1, MAP_BLOCK_PX // max(w, 1))  # in blocks of rows: the float64 work stays ~100 MB on a 100 MP photo
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        uu, vv = np.meshgrid(u, np.arange(r0, r1, dtype=float))
        xy = K.distort(K.normalized_from_pixels(np.column_stack([uu.ravel(), vv.ravel()])))
        src = K.pixels_from_normalized(xy).astype(np.float32)
        mx[r0:r1], my[r0:r1] = src[:, 0].reshape(r1 - r0, w), src[:, 1].reshape(r1 - r0, w)
    mx.setflags(write=False)
    my.setflags(write=False)
    return mx, my


def undistorted_image(image: np.ndarray, K: CameraIntrinsics) -> np.ndarray:
    """The photo resampled to the pinhole camera (same K, no distortion), same size."""
    if not K.has_distortion:
        return image
    h, w = image.shape[:2]
    mx, my = undistortion_maps(K, w, h)
    return cv2.remap(image, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
