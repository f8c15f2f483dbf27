"""Composition: warp every kept photo into the panorama through its exact model, compensate, seam, blend.

Each photo is resampled once (``cv2.remap``) by maps computed straight from
:class:`~workbench.core.panorama.PanoramaModel`: panorama pixel -> ray -> ``cam_from_pano`` -> the photo's
lens (distortion included) -> pixel, evaluated exactly on a grid of every 8th panorama pixel over the photo's
footprint (finer where the mapping curves strongly) and interpolated bilinearly in between, within 0.02 px of
the exact map (``tests/test_stitch.py``). For undistorted photos that is OpenCV's rotation warpers' mapping (``tests/test_panorama.py`` checks the model
against ``cv2.PyRotationWarper``). Gain compensation and seam finding run on small copies (about 0.1 MP per
photo); the full-resolution photos are then read, warped and gain-compensated one at a time, the next one in a
second thread while the previous one is fed to OpenCV's multi-band blender, so memory holds two
full-resolution photos and the blender's pyramid.
"""

from __future__ import annotations

import logging
from concurrent.futures import Future, ThreadPoolExecutor
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


def _fold_radius(intr: CameraIntrinsics, r_search: float = 4.0) -> float:
    """The undistorted normalised radius up to which the radial distortion is monotone (inf: beyond ``r_search``)."""
    r = np.linspace(0.0, r_search, 4001)[1:]
    r2 = r * r
    slope = 1.0 + r2 * (3.0 * intr.k1 + r2 * (5.0 * intr.k2 + r2 * 7.0 * intr.k3))  # d(r (1 + k1 r^2 + ...))/dr
    bad = np.flatnonzero(slope <= 0.05)
    return float(r[bad[0]]) if len(bad) else np.inf


def source_pixels(intr: CameraIntrinsics, cam: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) of the photo as on disk along directions ``cam`` (n, 3) in its camera frame (any length).

    :meth:`CameraIntrinsics.project`, made one-to-one everywhere so that a map sampled on a grid may be
    interpolated: beyond the radius where the radial distortion stops being monotone (:func:`_fold_radius`)
    it is continued linearly outward along the ray, and directions at or behind the image plane
    (``z <= 1e-3 |(x, y)|``) go far out in their own direction. Either way the pixel lies outside the photo,
    and nothing folds back into it (except the axis backwards itself, which :func:`source_maps` masks).
    """
    x, y, z = cam[:, 0], cam[:, 1], cam[:, 2]
    rho = np.hypot(x, y)
    zc = np.maximum(z, 1e-3 * rho)
    zc[zc <= 0] = 1.0  # (0, 0, z <= 0), the optical axis backwards: finite (source_maps masks what is behind)
    xy = np.column_stack([x / zc, y / zc])
    if not intr.has_distortion:
        return intr.pixels_from_normalized(xy)
    r = np.hypot(xy[:, 0], xy[:, 1])
    t = np.minimum(1.0, _fold_radius(intr) / np.maximum(r, 1e-300))[:, None]  # < 1: clamped to the fold radius
    return intr.pixels_from_normalized(intr.distort(xy * t) / t)


def footprint(model: PanoramaModel, index: int, intr: CameraIntrinsics, margin: int = 2) -> tuple[int, int, int, int]:
    """Panorama pixel box (x0, y0, x1, y1), ends exclusive, of source ``index`` (seen through ``intr``) plus ``margin``.

    Not clipped to the panorama. From 129 points along each side of the photo's border, and for the
    cylindrical and spherical projections widened to the full circle (and the pole's row) when the photo
    sees a pole.
    """
    w, h = intr.width, intr.height
    t = np.linspace(0.0, 1.0, 129)
    b = np.concatenate([np.column_stack([t * w - 0.5, np.full_like(t, -0.5)]),
                        np.column_stack([t * w - 0.5, np.full_like(t, h - 0.5)]),
                        np.column_stack([np.full_like(t, -0.5), t * h - 0.5]),
                        np.column_stack([np.full_like(t, w - 0.5), t * h - 0.5])])
    R = model.sources[index].cam_from_pano
    uv = model.project(intr.rays(b) @ R)
    if not np.all(np.isfinite(uv)):
        raise ValueError(f"source {model.sources[index].name}: its border does not project into the "
                         f"{model.projection} panorama")
    lo, hi = np.floor(uv.min(axis=0)) - margin, np.ceil(uv.max(axis=0)) + margin + 1
    if model.projection != "planar":
        for pole in (-1.0, 1.0):  # a photo that sees a pole spans every longitude
            px = source_pixels(intr, (R @ np.array([0.0, pole, 0.0]))[None])
            if (R @ np.array([0.0, pole, 0.0]))[2] > 0 and intr.in_image(px)[0]:
                a0 = -np.pi * model.scale - model.offset[0]
                lo[0], hi[0] = np.floor(a0) - margin, np.ceil(a0 + 2 * np.pi * model.scale) + margin + 1
                # the pole's row: b = s (pi/2 + asin(y)) (spherical); cylindrical: unbounded (clipped below)
                pole_v = model.scale * (np.pi / 2 + np.arcsin(pole)) - model.offset[1] \
                    if model.projection == "spherical" else pole * np.inf
                lo[1], hi[1] = min(lo[1], np.floor(pole_v) - margin), max(hi[1], np.ceil(pole_v) + margin + 1)
    big = 1 << 30
    lo, hi = np.clip(lo, -big, big), np.clip(hi, -big, big)
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


def source_maps(model: PanoramaModel, index: int, intr: CameraIntrinsics, box: tuple[int, int, int, int], *,
                step: int = 8, max_error_px: float = 0.02) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Resampling maps of source ``index`` over the panorama box (x0, y0, x1, y1) (ends exclusive).

    For every panorama pixel of the box: its ray (the model's projection), ``cam_from_pano``, the photo's
    lens (:func:`source_pixels`), computed in one pass. The mapping is smooth, so it is evaluated exactly on
    a grid of every ``step``-th pixel and interpolated bilinearly (``cv2.resize`` places the grid's nodes so
    that the result is exact at them). The grid is made finer (step halved, down to every pixel) until the
    interpolation error that its second differences predict, where the photo is, is below ``max_error_px``
    (under ``cv2.remap``'s own 1/32 px; every 8th pixel is enough unless the mapping curves strongly, as near
    a spherical panorama's poles; ``tests/test_stitch.py`` checks the maps against the model).
    Returns (map_x, map_y (H, W) float32 photo pixels, mask (H, W) uint8, 255 where the pixel's centre falls
    in the photo: [-0.5, w - 0.5] x [-0.5, h - 0.5], and the ray is within 89 degrees of the photo's axis).
    """
    x0, y0, x1, y1 = box
    W, H = x1 - x0, y1 - y0
    if W <= 0 or H <= 0:
        raise ValueError(f"empty box {box}")
    w, h = intr.width, intr.height
    step = max(1, int(step))
    while True:
        # grid node k sits at box pixel step (k + 0.5) - 0.5 - step: one node beyond each side, so that resize's
        # clamped border stays outside the box
        nx, ny = int(np.ceil((W - 0.5) / step + 1.5)), int(np.ceil((H - 0.5) / step + 1.5))
        gx = x0 - step + step * (np.arange(nx) + 0.5) - 0.5
        gy = y0 - step + step * (np.arange(ny) + 0.5) - 0.5
        uu, vv = np.meshgrid(gx, gy)
        cam = model.rays(np.column_stack([uu.ravel(), vv.ravel()])) @ model.sources[index].cam_from_pano.T
        px = source_pixels(intr, cam)
        if step == 1 or _interpolation_error(px.reshape(ny, nx, 2), w, h) <= max_error_px:
            break
        step //= 2
    px = px.astype(np.float32)
    if step == 1:
        mx, my = px[:, 0].reshape(ny, nx)[1:1 + H, 1:1 + W], px[:, 1].reshape(ny, nx)[1:1 + H, 1:1 + W]
    else:
        big = (nx * step, ny * step)
        mx = cv2.resize(px[:, 0].reshape(ny, nx), big, interpolation=cv2.INTER_LINEAR)[step:step + H, step:step + W]
        my = cv2.resize(px[:, 1].reshape(ny, nx), big, interpolation=cv2.INTER_LINEAR)[step:step + H, step:step + W]
    mask = cv2.bitwise_and(cv2.inRange(mx, -0.5, w - 0.5), cv2.inRange(my, -0.5, h - 0.5))
    # rays more than 89 degrees off the axis (no pinhole photo sees them; the backward axis would map onto the
    # photo's centre): masked out with every pixel interpolated from them
    ahead = cam[:, 2] > 0.0175 * np.linalg.norm(cam, axis=1)
    if not ahead.all():
        a = ahead.astype(np.float32).reshape(ny, nx)
        if step == 1:
            a = a[1:1 + H, 1:1 + W]
        else:
            a = cv2.resize(a, (nx * step, ny * step), interpolation=cv2.INTER_LINEAR)[step:step + H, step:step + W]
        mask[a < 1.0 - 1e-6] = 0
    return mx, my, mask


def _interpolation_error(px: np.ndarray, w: int, h: int) -> float:
    """Largest error (px) of bilinear interpolation between the nodes of a map ``px`` (ny, nx, 2) of photo pixels
    that the second differences predict (h^2 |f''| / 8 per axis), over the cells near the photo (w x h)."""
    near = np.all((px > -0.25 * np.array([w, h])) & (px < 1.25 * np.array([w, h])), axis=2)
    err = np.zeros(near.shape)
    if px.shape[1] >= 3:
        err[:, 1:-1] += np.abs(px[:, :-2] - 2 * px[:, 1:-1] + px[:, 2:]).max(axis=2) / 8
    if px.shape[0] >= 3:
        err[1:-1, :] += np.abs(px[:-2] - 2 * px[1:-1] + px[2:]).max(axis=2) / 8
    err = np.where(near, err, 0.0)
    return float(np.nanmax(err)) if err.size else 0.0


def warp_source(model: PanoramaModel, index: int, image: np.ndarray, intr: CameraIntrinsics, *,
                interpolation: int = cv2.INTER_LINEAR, clip: bool = True, step: int = 8,
                box: tuple[int, int, int, int] | None = None) -> tuple[np.ndarray, np.ndarray, tuple[int, int]] | None:
    """Warp ``image`` (h, w, 3) uint8, seen through ``intr``, of source ``index`` into the panorama.

    The photo is resampled once (``cv2.remap``) by :func:`source_maps` over ``box`` (default: its
    :func:`footprint`), i.e. by the model's own mapping, lens included. Returns (warped (H, W, 3) uint8, mask
    (H, W) uint8, top-left corner (x, y) in panorama pixels), clipped to the panorama when ``clip``; None if
    the photo does not reach into it.
    """
    x0, y0, x1, y1 = footprint(model, index, intr) if box is None else box
    if clip:
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, model.width), min(y1, model.height)
        if x1 <= x0 or y1 <= y0:
            return None
    mx, my, mask = source_maps(model, index, intr, (x0, y0, x1, y1), step=step)
    warped = cv2.remap(image, mx, my, interpolation, borderMode=cv2.BORDER_REFLECT)
    return warped, mask, (x0, y0)


def apply_block_gains(img: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """``img`` (H, W, 3) uint8 times the block gains (rows, cols) float32, stretched bilinearly over it.

    Bit for bit ``cv2.detail_BlocksGainCompensator.apply`` (whose per-pixel loop is 3 to 4 times slower).
    """
    g = cv2.resize(gains, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_LINEAR)
    out = np.empty_like(img)
    rows = max(1, (1 << 20) // (12 * img.shape[1]))  # in strips of about 1 MB of 3-channel gains: no big temporaries
    for y in range(0, img.shape[0], rows):
        gs = g[y:y + rows]
        out[y:y + rows] = cv2.multiply(img[y:y + rows], cv2.merge([gs, gs, gs]), dtype=cv2.CV_8U)
    return out


def _clip(img: np.ndarray, mask: np.ndarray, corner: tuple[int, int], width: int, height: int):
    """The part of a warped image (and mask) inside the panorama [0, width) x [0, height), or None."""
    x0, y0 = corner
    h, w = mask.shape
    cx0, cy0 = max(x0, 0), max(y0, 0)
    cx1, cy1 = min(x0 + w, width), min(y0 + h, height)
    if cx1 <= cx0 or cy1 <= cy0:
        return None
    sl = (slice(cy0 - y0, cy1 - y0), slice(cx0 - x0, cx1 - x0))
    return img[sl], mask[sl], (cx0, cy0)  # views: the blender takes strided rows (no copy of the warped photo)


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
    lr = scale_model(model, seam_scale)
    intr_lr = [scale_intrinsics(model.sources[i].intrinsics, small[i].shape[1], small[i].shape[0]) for i in range(n)]
    keep, boxes_lr = [], []  # the photos that reach into the panorama, and their boxes in it (low resolution)
    for i in range(n):
        # (clipped to the panorama plus a pixel: scaled to full resolution, the box still covers its edges)
        x0, y0, x1, y1 = footprint(lr, i, intr_lr[i])
        box = (max(x0, -1), max(y0, -1), min(x1, lr.width + 1), min(y1, lr.height + 1))
        if box[2] > box[0] and box[3] > box[1]:
            keep.append(i)
            boxes_lr.append(box)
        else:
            log.warning("photo %s does not reach into the panorama", model.sources[i].name)

    def warp_full(k: int) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """Photo ``keep[k]`` read at full size and warped (unclipped)."""
        i = keep[k]
        full = read_full(paths[i])
        intr = model.sources[i].intrinsics
        if full is None or (full.shape[1], full.shape[0]) != (intr.width, intr.height):
            raise ValueError(f"{paths[i]}: size changed since registration")
        # the box of the low-resolution warp, scaled (its pixel edges x - 0.5 are at x / r - 0.5 at full
        # resolution): the seam mask found there is stretched onto exactly the same part of the panorama
        box = tuple(int(round(c / seam_scale)) for c in boxes_lr[k])
        return warp_source(model, i, full, intr, clip=False, box=box)

    def prepare(k: int, warped: "Future | None" = None) -> tuple[np.ndarray, np.ndarray, tuple[int, int]] | None:
        """Photo ``keep[k]`` warped (``warped``: already under way), masked by its seam, gain-compensated, clipped."""
        img, m, corner = warped.result() if warped is not None else warp_full(k)
        # the seam mask was found at low resolution: bring it to this photo's warped size (as OpenCV does)
        seam = cv2.resize(cv2.dilate(seams[k], None), (m.shape[1], m.shape[0]), interpolation=cv2.INTER_LINEAR_EXACT)
        m = cv2.bitwise_and(seam, m)
        del seam
        # gains before clipping: the gain map covers the whole warped photo
        if block_gains is not None:
            img = apply_block_gains(img, block_gains[k])
        else:
            img = comp.apply(k, corner, img, m)
            if isinstance(img, cv2.UMat):
                img = img.get()
        return _clip(img, m, corner, model.width, model.height)

    # a second thread reads and warps the photos at full resolution: the first one (then the gains) while the
    # low-resolution photos are warped and the seams found, each next one while the previous one is fed to the
    # blender (OpenCV releases the GIL); the blender is fed in the same order as ever, so the result does not
    # depend on the threads
    with ThreadPoolExecutor(max_workers=1) as pool:
        first = pool.submit(warp_full, 0) if keep else None
        # -- low resolution: gains and seams ----------------------------------------------------------------
        corners_lr, imgs_lr, masks_lr = [], [], []
        for k, i in enumerate(keep):
            img, m, corner = warp_source(lr, i, small[i], intr_lr[i], clip=False, box=boxes_lr[k])
            corners_lr.append(corner)
            imgs_lr.append(img)
            masks_lr.append(m)
        progress(0.1, "exposure compensation and seams")
        if exposure == "gain_blocks":
            comp = cv2.detail_BlocksGainCompensator()
        elif exposure == "gain":
            comp = cv2.detail_GainCompensator()
        else:
            comp = cv2.detail.ExposureCompensator_createDefault(cv2.detail.ExposureCompensator_NO)
        # the gains in the second thread while the seams are found here (independent; OpenCV releases the GIL)
        gains_fed = pool.submit(comp.feed, corners=corners_lr, images=imgs_lr, masks=[cv2.UMat(m) for m in masks_lr])
        if seam_finder == "gc_color":
            finder = cv2.detail_GraphCutSeamFinder("COST_COLOR")
        elif seam_finder == "dp_color":
            finder = cv2.detail_DpSeamFinder("COLOR")
        else:
            finder = cv2.detail.SeamFinder_createDefault(cv2.detail.SeamFinder_VORONOI_SEAM)
        seams = finder.find([im.astype(np.float32) for im in imgs_lr], corners_lr,
                            [cv2.UMat(m) for m in masks_lr])
        seams = [s.get() if isinstance(s, cv2.UMat) else s for s in seams]
        gains_fed.result()
        del imgs_lr
        block_gains = None
        if exposure == "gain_blocks":  # one (rows, cols) float32 gain per block of each warped photo
            block_gains = [np.asarray(g.get() if isinstance(g, cv2.UMat) else g, np.float32)
                           for g in comp.getMatGains()]
            if any(g.ndim != 2 for g in block_gains):
                block_gains = None  # (an OpenCV whose block gains have channels: its own apply)
        # -- full resolution: warp, compensate, blend --------------------------------------------------------
        blender = cv2.detail_MultiBandBlender()
        blend_width = np.sqrt(model.width * model.height) * blend_strength / 100.0
        bands = int(max(1, np.log2(max(blend_width, 2.0)) - 1))
        blender.setNumBands(bands)
        blender.prepare((0, 0, model.width, model.height))
        fed = 0
        nxt = pool.submit(prepare, 0, first) if keep else None
        for k in range(len(keep)):
            progress(0.25 + 0.7 * k / max(len(keep), 1), f"compose {model.sources[keep[k]].name}")
            clipped = nxt.result()
            nxt = pool.submit(prepare, k + 1) if k + 1 < len(keep) else None
            if clipped is None:
                log.warning("photo %s does not reach into the panorama", model.sources[keep[k]].name)
                continue
            img, m, corner = clipped
            blender.feed(img, m, corner)  # uint8: the blender's pyramid is int16 either way
            fed += 1
            del img, m, clipped
    progress(0.95, "blend")
    result, result_mask = blender.blend(None, None)
    if isinstance(result, cv2.UMat):
        result, result_mask = result.get(), result_mask.get()
    # int16 -> uint8, saturated (the blender has already set what no photo sees to 0); negatives clipped in place
    pano = cv2.convertScaleAbs(np.maximum(result, 0, out=result))
    coverage = float(np.count_nonzero(result_mask)) / result_mask.size
    return pano, {"n_blended": fed, "bands": bands, "coverage": round(coverage, 4)}
