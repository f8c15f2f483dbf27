"""Composition: warp every kept photo into the panorama through its exact model, compensate, seam, blend.

Each photo is warped by OpenCV's rotation warper for the model's projection and scale (composed with the
undistortion map when its lens has distortion, so it is resampled once), whose mapping is exactly
:class:`~workbench.core.panorama.PanoramaModel`'s (``tests/test_panorama.py`` checks it against
``cv2.PyRotationWarper``). Gain compensation and seam finding run on small copies (about 0.1 MP per
photo); the full-resolution photos are then read one at a time, warped, and fed to OpenCV's multi-band
blender, so memory holds one full-resolution photo and the blender's pyramid.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.panorama import PanoramaModel

log = logging.getLogger(__name__)


def scale_intrinsics(intr: CameraIntrinsics, width: int, height: int) -> CameraIntrinsics:
    """The same camera for the image resized to ``width`` x ``height`` (pixel centres kept consistent)."""
    sx, sy = width / intr.width, height / intr.height
    return replace(intr, width=int(width), height=int(height), fx=intr.fx * sx, fy=intr.fy * sy,
                   skew=intr.skew * sx, cx=(intr.cx + 0.5) * sx - 0.5, cy=(intr.cy + 0.5) * sy - 0.5)


def scale_model(model: PanoramaModel, r: float) -> PanoramaModel:
    """The panorama model for the panorama image resized by ``r`` (sources unchanged)."""
    w, h = max(1, int(round(model.width * r))), max(1, int(round(model.height * r)))
    # uv_r = (uv + 0.5) r - 0.5 = r s a - (r x0 - 0.5 r + 0.5)
    off = (r * model.offset[0] - 0.5 * r + 0.5, r * model.offset[1] - 0.5 * r + 0.5)
    return replace(model, scale=model.scale * r, offset=off, width=w, height=h)


CV2_WARPER = {"planar": "plane", "cylindrical": "cylindrical", "spherical": "spherical"}


def undistort_maps(intr: CameraIntrinsics, max_growth: float = 1.5
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, CameraIntrinsics]:
    """Maps from a pinhole canvas with the same focal (grown to keep every pixel) into the photo.

    Returns (map_x, map_y (h', w') float32 photo pixels, mask (h', w') uint8 of canvas pixels the photo
    covers, pinhole intrinsics of the canvas). Pixel centres as in ``docs/conventions.md``.
    """
    w, h = intr.width, intr.height
    t = np.linspace(0.0, 1.0, 65)
    border = np.concatenate([np.column_stack([t * w - 0.5, np.full_like(t, -0.5)]),
                             np.column_stack([t * w - 0.5, np.full_like(t, h - 0.5)]),
                             np.column_stack([np.full_like(t, -0.5), t * h - 0.5]),
                             np.column_stack([np.full_like(t, w - 0.5), t * h - 0.5])])
    pin = intr.without_distortion()
    und = pin.pixels_from_normalized(intr.undistort(intr.normalized_from_pixels(border)))
    lo = np.maximum(np.floor(und.min(axis=0)), [-(max_growth - 1) / 2 * w, -(max_growth - 1) / 2 * h])
    hi = np.minimum(np.ceil(und.max(axis=0)), [w - 1 + (max_growth - 1) / 2 * w, h - 1 + (max_growth - 1) / 2 * h])
    W, H = int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1
    new = replace(pin, width=W, height=H, cx=pin.cx - lo[0], cy=pin.cy - lo[1])
    mx, my = cv2.initUndistortRectifyMap(intr.K, intr.dist_coeffs, None, new.K, (W, H), cv2.CV_32FC1)
    inside = (mx >= -0.5) & (mx <= w - 0.5) & (my >= -0.5) & (my <= h - 0.5)
    return mx, my, cv2.erode(inside.astype(np.uint8) * 255, None), new


def warp_source(model: PanoramaModel, index: int, image: np.ndarray, intr: CameraIntrinsics, *,
                interpolation: int = cv2.INTER_LINEAR, clip: bool = True
                ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]] | None:
    """Warp ``image`` (h, w, 3) uint8, seen through ``intr``, of source ``index`` into the panorama.

    OpenCV's rotation warper of the model's projection and scale (whose mapping is the model's, as
    tests/test_panorama.py checks) maps the panorama to a pinhole view of the photo; when ``intr`` has
    distortion, that map is composed with the undistortion map, so the photo is resampled once.
    Returns (warped (H, W, 3) uint8, mask (H, W) uint8, top-left corner (x, y) in panorama pixels), clipped
    to the panorama when ``clip``; None if the photo does not reach into it.
    """
    warper = cv2.PyRotationWarper(CV2_WARPER[model.projection], float(model.scale))
    R = model.sources[index].cam_from_pano.T.astype(np.float32)  # OpenCV's camera R is pano_from_cam
    if intr.has_distortion:
        ux, uy, mask_src, pin = undistort_maps(intr)
        tl, wx, wy = warper.buildMaps((pin.width, pin.height), pin.K.astype(np.float32), R)
        mx = cv2.remap(ux, wx, wy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-10.0)
        my = cv2.remap(uy, wx, wy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-10.0)
        mask = cv2.remap(mask_src, wx, wy, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        del ux, uy, wx, wy, mask_src
        warped = cv2.remap(image, mx, my, interpolation, borderMode=cv2.BORDER_REFLECT)
        del mx, my
    else:
        K = intr.K.astype(np.float32)
        tl, warped = warper.warp(image, K, R, interpolation, cv2.BORDER_REFLECT)
        _, mask = warper.warp(np.full(image.shape[:2], 255, np.uint8), K, R, cv2.INTER_NEAREST,
                              cv2.BORDER_CONSTANT)
    corner = (int(round(tl[0] - model.offset[0])), int(round(tl[1] - model.offset[1])))
    return _clip(warped, mask, corner, model.width, model.height) if clip else (warped, mask, corner)


def _clip(img: np.ndarray, mask: np.ndarray, corner: tuple[int, int], width: int, height: int):
    """The part of a warped image (and mask) inside the panorama [0, width) x [0, height), or None."""
    x0, y0 = corner
    h, w = mask.shape
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x0 + w, width), min(y0 + h, height)
    if cx1 <= cx0 or cy1 <= cy0:
        return None
    sl = (slice(cy0 - y0, cy1 - y0), slice(cx0 - x0, cx1 - x0))
    return np.ascontiguousarray(img[sl]), np.ascontiguousarray(mask[sl]), (cx0, cy0)


def compose(model: PanoramaModel, paths: list[Path], small: list[np.ndarray], *, seam_scale: float,
            blend_strength: float = 5.0, seam_finder: str = "dp_color", exposure: str = "gain_blocks",
            read_full: Callable[[Path], np.ndarray] | None = None,
            progress: Callable[[float, str], None] = lambda f, m="": None) -> tuple[np.ndarray, dict]:
    """Blend the panorama of ``model`` (full resolution) from the photos at ``paths`` (one per source).

    ``small``: the photos reduced by ``seam_scale`` (h, w, 3) uint8 BGR, for gains and seams.
    Returns the panorama (height, width, 3) uint8 BGR (black where no photo sees) and statistics.
    """
    read_full = read_full or (lambda p: cv2.imread(str(p), cv2.IMREAD_COLOR))
    n = len(model.sources)
    # -- low resolution: gains and seams --------------------------------------------------------------------
    lr = scale_model(model, seam_scale)
    corners_lr, imgs_lr, masks_lr, keep = [], [], [], []
    for i in range(n):
        intr = scale_intrinsics(model.sources[i].intrinsics, small[i].shape[1], small[i].shape[0])
        res = warp_source(lr, i, small[i], intr, clip=False)  # relative corners are all that matter here
        if res is None:
            continue
        img, m, corner = res
        corners_lr.append(corner)
        imgs_lr.append(img)
        masks_lr.append(m)
        keep.append(i)
    progress(0.1, "exposure compensation")
    if exposure == "gain_blocks":
        comp = cv2.detail_BlocksGainCompensator()
    elif exposure == "gain":
        comp = cv2.detail_GainCompensator()
    else:
        comp = cv2.detail.ExposureCompensator_createDefault(cv2.detail.ExposureCompensator_NO)
    comp.feed(corners=corners_lr, images=imgs_lr, masks=[cv2.UMat(m) for m in masks_lr])
    progress(0.2, "seams")
    if seam_finder == "gc_color":
        finder = cv2.detail_GraphCutSeamFinder("COST_COLOR")
    elif seam_finder == "dp_color":
        finder = cv2.detail_DpSeamFinder("COLOR")
    else:
        finder = cv2.detail.SeamFinder_createDefault(cv2.detail.SeamFinder_VORONOI_SEAM)
    seams = finder.find([im.astype(np.float32) for im in imgs_lr], corners_lr, [cv2.UMat(m) for m in masks_lr])
    seams = [s.get() if isinstance(s, cv2.UMat) else s for s in seams]
    del imgs_lr
    # -- full resolution: warp, compensate, blend ------------------------------------------------------------
    blender = cv2.detail_MultiBandBlender()
    blend_width = np.sqrt(model.width * model.height) * blend_strength / 100.0
    bands = int(max(1, np.log2(max(blend_width, 2.0)) - 1))
    blender.setNumBands(bands)
    blender.prepare((0, 0, model.width, model.height))
    fed = 0
    for n_done, i in enumerate(keep):
        progress(0.25 + 0.7 * n_done / max(len(keep), 1), f"compose {model.sources[i].name}")
        full = read_full(paths[i])
        intr = model.sources[i].intrinsics
        if full is None or (full.shape[1], full.shape[0]) != (intr.width, intr.height):
            raise ValueError(f"{paths[i]}: size changed since registration")
        img, m, corner = warp_source(model, i, full, intr, clip=False)
        del full
        k = keep.index(i)
        # the seam mask was found at low resolution: bring it to this photo's warped size (as OpenCV does)
        seam = cv2.resize(cv2.dilate(seams[k], None), (m.shape[1], m.shape[0]), interpolation=cv2.INTER_LINEAR_EXACT)
        m = cv2.bitwise_and(seam, m)
        del seam
        clipped = _clip(img, m, corner, model.width, model.height)
        if clipped is None:
            log.warning("photo %s does not reach into the panorama", model.sources[i].name)
            continue
        img, m, corner = clipped
        img = comp.apply(k, corner, img, m)
        if isinstance(img, cv2.UMat):
            img = img.get()
        blender.feed(img.astype(np.int16), m, corner)
        fed += 1
        del img, m
    progress(0.95, "blend")
    result, result_mask = blender.blend(None, None)
    if isinstance(result, cv2.UMat):
        result, result_mask = result.get(), result_mask.get()
    pano = np.clip(result, 0, 255).astype(np.uint8)
    pano[result_mask == 0] = 0
    coverage = float(np.count_nonzero(result_mask)) / result_mask.size
    return pano, {"n_blended": fed, "bands": bands, "coverage": round(coverage, 4)}
