"""Synthetic photos through a real lens: Brown distortion and skew on top of the pinhole renderer.

A photo of ``CameraIntrinsics`` (distortion k1, k2, k3, p1, p2 and skew, OpenCV conventions) is made by

1. computing, for every output pixel centre, its undistorted normalised coordinate
   (``intrinsics.undistort(intrinsics.normalized_from_pixels(uv))``, the exact inverse of
   ``CameraIntrinsics.project``);
2. rendering an undistorted, unskewed pinhole image whose field of view covers all of them (barrel
   distortion needs a wider one than the nominal), at the same focal length so the centre keeps its
   resolution;
3. warping it with ``cv2.remap`` (bilinear) into the distorted image.

Depth and instance masks are not resampled: rays are cast through each pixel's exact undistorted
direction, so they are exact at every pixel centre. A world point ``X`` appears in the photo at
``intrinsics.project(cam_from_world @ X)``.
"""

from __future__ import annotations

import threading
from functools import lru_cache

import cv2
import numpy as np

from ..core.camera import CameraIntrinsics
from ..errors import RenderError
from .offscreen import OffscreenScene, RenderResult

# The pinhole render may be at most this many times the photo's size per side (strong wide-angle lenses
# lose resolution at the rim rather than exhausting memory).
_MAX_PINHOLE_GROWTH = 2.5
_MARGIN_PX = 3


_GRID_LOCK = threading.Lock()


def _undistorted_grid(intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates (h, w, 2) of all pixel centres, and a validity mask (h, w): computed
    once per lens (the photos of a set share it), also when several threads render photos at once."""
    with _GRID_LOCK:
        return _grid(intrinsics)


@lru_cache(maxsize=8)
def _grid(intrinsics: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    w, h = intrinsics.width, intrinsics.height
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    uv = np.column_stack([u.ravel(), v.ravel()])
    xy_d = intrinsics.normalized_from_pixels(uv)
    xy = intrinsics.undistort(xy_d)
    with np.errstate(invalid="ignore", over="ignore"):
        err = np.linalg.norm(intrinsics.distort(xy) - xy_d, axis=1)
    ok = np.isfinite(err) & (err < 1e-6) & np.all(np.isfinite(xy), axis=1)
    xy[~ok] = np.nan
    xy.setflags(write=False)
    ok.setflags(write=False)
    return xy.reshape(h, w, 2), ok.reshape(h, w)


def pinhole_for(intrinsics: CameraIntrinsics) -> tuple[np.ndarray, int, int]:
    """(K (3, 3) without skew or distortion, width, height) of a pinhole view covering every pixel of ``intrinsics``."""
    xy, ok = _undistorted_grid(intrinsics)
    if not ok.any():
        raise RenderError(f"the lens distortion of {intrinsics} cannot be inverted anywhere in the image")
    pts = xy[ok]
    xmin, ymin = pts.min(axis=0)
    xmax, ymax = pts.max(axis=0)
    f = min(intrinsics.fx, intrinsics.fy)
    # shrink the focal length if the covering view would be unreasonably large
    grow = max((xmax - xmin) * f / intrinsics.width, (ymax - ymin) * f / intrinsics.height)
    if grow > _MAX_PINHOLE_GROWTH:
        f *= _MAX_PINHOLE_GROWTH / grow
    fx = fy = f
    cx = -xmin * fx + _MARGIN_PX
    cy = -ymin * fy + _MARGIN_PX
    width = int(np.ceil((xmax - xmin) * fx)) + 2 * _MARGIN_PX + 1
    height = int(np.ceil((ymax - ymin) * fy)) + 2 * _MARGIN_PX + 1
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return K, width, height


def render_photo(scene: OffscreenScene, intrinsics: CameraIntrinsics, cam_from_world: np.ndarray, *,
                 supersample: int = 2) -> RenderResult:
    """What a real camera with ``intrinsics`` (distortion, skew) at ``cam_from_world`` (4, 4) photographs.

    Colour: a lit pinhole render (``supersample`` x supersampled) warped bilinearly through the lens model.
    Depth (metres along camera z, ``inf`` on a miss) and instance ids (-1 for none): exact per pixel centre.
    """
    M = np.asarray(cam_from_world, dtype=float)
    if M.shape != (4, 4):
        raise ValueError(f"cam_from_world.shape={M.shape} but expected (4, 4)")
    w, h = intrinsics.width, intrinsics.height
    if not intrinsics.has_distortion and intrinsics.skew == 0.0:
        return scene.render(intrinsics.K, M, size=(w, h), supersample=supersample)

    xy, ok = _undistorted_grid(intrinsics)
    if scene.engine == "raytrace":
        # rays straight through the lens model at supersampled positions inside each pixel: no resampling
        def xy_of_uv(uv):
            if supersample == 1:  # the pixel centres: the grid computed once per lens (nan where it cannot invert)
                return xy.reshape(-1, 2)
            return intrinsics.undistort(intrinsics.normalized_from_pixels(uv))

        color = scene.raytrace_color(M, xy_of_uv, w, h, supersample)
        return RenderResult(color, traced=_traced(scene, M, xy, ok))
    Kp, wp, hp = pinhole_for(intrinsics)
    pin = scene.render_color(Kp, M, wp, hp, supersample)
    map_x = (Kp[0, 0] * xy[..., 0] + Kp[0, 2]).astype(np.float32)
    map_y = (Kp[1, 1] * xy[..., 1] + Kp[1, 2]).astype(np.float32)
    map_x[~ok] = -10.0
    map_y[~ok] = -10.0
    bg = tuple(int(round(255 * c)) for c in scene.background_rgb)
    color = cv2.remap(pin, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=bg)
    return RenderResult(np.ascontiguousarray(color, dtype=np.uint8), traced=_traced(scene, M, xy, ok))


def _traced(scene: OffscreenScene, M: np.ndarray, xy: np.ndarray, ok: np.ndarray):
    """The photo's depth and instance ids (exact per pixel centre), cast when first read (``RenderResult``)."""
    trace = scene.tracer()

    def traced() -> tuple[np.ndarray, np.ndarray]:
        depth, instance = trace(M, np.where(ok[..., None], xy, 0.0))
        depth[~ok] = np.inf
        instance[~ok] = -1
        return depth, instance

    return traced
