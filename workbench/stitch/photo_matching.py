"""The stitcher's first steps: every photo read once at the resolutions it is needed at and described (SIFT),
every pair matched as soon as both its photos are described, and the largest confidently connected set
(docs/stitching.md, steps 1-4). OpenCV releases the GIL, so photos are read and pairs matched in threads."""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import Future, ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from ..core.camera import CameraIntrinsics
from ..errors import InputError
from . import register as reg
from .options import ProgressFn, StitchOptions

log = logging.getLogger(__name__)

__all__ = ["Registration", "connected_set", "decode_reduced", "describe_photo", "match_described", "read_and_match",
           "read_reduced", "resize_to"]


def decode_reduced(path: Path, scale: float, *, flags: int = cv2.IMREAD_COLOR) -> tuple[np.ndarray, tuple[int, int]]:
    """The photo at ``path`` decoded at 1/8, 1/4 or 1/2 (JPEG DCT scaling) when that still has ``scale`` (<= 1) of
    its size, else at full size. Returns (image (h', w'[, 3]) uint8, full size (w, h)). :class:`InputError` if
    unreadable."""
    try:
        with Image.open(path) as im:
            w, h = im.size
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read this photo ({exc}); replace it or remove it from the folder") from None
    color = flags == cv2.IMREAD_COLOR
    img = None
    for k, (fc, fg) in ((8, (cv2.IMREAD_REDUCED_COLOR_8, cv2.IMREAD_REDUCED_GRAYSCALE_8)),
                        (4, (cv2.IMREAD_REDUCED_COLOR_4, cv2.IMREAD_REDUCED_GRAYSCALE_4)),
                        (2, (cv2.IMREAD_REDUCED_COLOR_2, cv2.IMREAD_REDUCED_GRAYSCALE_2))):
        if scale * k <= 1.0 and path.suffix.lower() in (".jpg", ".jpeg"):
            img = cv2.imread(str(path), fc if color else fg)
            break
    if img is None:
        img = cv2.imread(str(path), flags)
    if img is None:
        raise InputError(f"{path}: OpenCV cannot decode this photo; convert it to JPEG or PNG")
    return img, (w, h)


def resize_to(img: np.ndarray, full_size: tuple[int, int], scale: float) -> np.ndarray:
    """``img`` (any size) of a photo of ``full_size`` (w, h), area-resampled to (round(w s), round(h s))."""
    w, h = full_size
    tw, th = max(1, int(round(w * scale))), max(1, int(round(h * scale)))
    if (img.shape[1], img.shape[0]) == (tw, th):
        return img
    return cv2.resize(img, (tw, th), interpolation=cv2.INTER_AREA)


def read_reduced(path: Path, scale: float, *, flags: int = cv2.IMREAD_COLOR) -> tuple[np.ndarray, tuple[int, int]]:
    """The photo at ``path`` reduced by ``scale`` (<= 1), decoded at 1/2, 1/4 or 1/8 when that is enough.

    Returns (image (round(h s), round(w s)[, 3]) uint8, full size (w, h)). :class:`InputError` if unreadable.
    """
    img, size = decode_reduced(path, scale, flags=flags)
    return resize_to(img, size, scale), size


def _workers() -> int:
    return max(1, min(4, os.cpu_count() or 1))


@dataclass
class Registration:
    """Per photo (by index): features, seam-size copy, full size (w, h), smoothed grey for the sub-pixel
    refinement, FLANN index, linearised keypoints; the full-resolution photos kept for composition (small photos
    only); every pair's match, sorted by (i, j)."""

    feats: list
    small: list
    sizes: list
    grays: list
    indexes: list
    lin: list
    fulls: dict[int, np.ndarray]
    pairs: list[reg.PairMatch]


def describe_photo(p: Path, name: str, k: int, opts: StitchOptions) -> tuple:
    """What photo ``k`` gives the registration whatever its lens: features, seam-size photo, full size, smoothed
    grey, FLANN index, full photo (or None). Depends only on the photo and ``opts`` (started early by
    :func:`workbench.stitch.stage.prefetch`)."""
    try:
        with Image.open(p) as im:
            w, h = im.size
    except (OSError, ValueError) as exc:
        raise InputError(f"{p}: cannot read this photo ({exc}); replace it or remove it from the folder") from None
    s_work = min(1.0, np.sqrt(opts.work_megapix * 1e6 / (w * h)))
    s_seam = min(1.0, np.sqrt(opts.seam_megapix * 1e6 / (w * h)))
    s_ref = min(1.0, np.sqrt(opts.refine_megapix * 1e6 / (w * h)))
    fine_ref = opts.refine_matches and s_ref > s_work * 1.05  # matches refined on a finer copy than the work copy
    full = dec = None
    if opts.compose and w * h <= opts.keep_full_max_megapix * 1e6:  # small photos: decoded once, kept
        full = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if full is None:
            raise InputError(f"{p}: OpenCV cannot decode this photo; convert it to JPEG or PNG")
        h, w = full.shape[:2]
        dec = full
    else:  # decoded once, reduced by the JPEG decoder as far as the finer of the work and refinement copies allow
        dec, (w, h) = decode_reduced(p, s_ref if fine_ref else s_work)
    # grey once, at the decoded size; the work and seam copies straight from the decoded photo
    gray_dec = cv2.cvtColor(dec, cv2.COLOR_BGR2GRAY)
    gray = resize_to(gray_dec, (w, h), s_work)
    sm = resize_to(dec, (w, h), s_seam)
    # SIFT on a half-size copy only where that copy keeps enough pixels for features (small photos: full size)
    # and for photos that are themselves small: reduced from larger photos, the full SIFT's extra matches
    # constrain the focal of a single row better (docs/stitching.md)
    half = (opts.sift_half and gray.size >= opts.sift_half_min_megapix * 1e6
            and w * h <= opts.sift_half_max_photo_megapix * 1e6)
    f = reg.detect_features(name, gray, (w, h), max_features=opts.max_features, contrast_threshold=opts.sift_contrast,
                            half=half)
    smooth = None
    if opts.refine_matches:
        if fine_ref:  # (a photo within 5 % of the refinement size: refined at full size, not resampled)
            smooth = reg.smooth_for_refinement(resize_to(gray_dec, (w, h), 1.0 if s_ref > 0.95 else s_ref))
        else:
            smooth = reg.smooth_for_refinement(gray)
    del dec, gray_dec
    # FLANN's randomised trees draw from OpenCV's (thread-local) generator: seeded here, the forest is the
    # same whichever thread builds it, so the same photos give the same panorama
    cv2.setRNGSeed(opts.seed + 7 * k + 1)
    index = reg.build_index(f, opts.flann_trees)
    return f, sm, (w, h), smooth, index, full


def _linearised(p: Path, f: reg.PhotoFeatures, size: tuple[int, int], calib: CameraIntrinsics | None) -> np.ndarray:
    """The keypoints to match with: undistorted pixels when the lens is known (``calib``: the photo's calibrated
    intrinsics, route ``calibrated``), else as detected."""
    w, h = size
    if calib is None:
        return f.keypoints
    if (calib.width, calib.height) != (w, h):
        raise InputError(f"{p}: {w}x{h} px, but the camera profile is for {calib.width}x{calib.height}; use "
                         f"photos at the profile's size or recalibrate")
    if calib.has_distortion and len(f.keypoints):
        return calib.pixels_from_normalized(calib.undistort(calib.normalized_from_pixels(f.keypoints)))
    return f.keypoints


def _match(pair: tuple[int, int], found: Registration, opts: StitchOptions) -> reg.PairMatch:
    """Photos i and j matched (ratio test, RANSAC homography, confidence); a confident pair's inliers refined to
    sub-pixel precision (at most ``max_refined_per_pair``)."""
    i, j = pair
    feats, lin = found.feats, found.lin
    pm = reg.match_pair(i, j, feats[i], feats[j], lin[i], lin[j], ratio=opts.match_ratio,
                        ransac_work_px=opts.ransac_work_px, seed=opts.seed, index_i=found.indexes[i],
                        index_j=found.indexes[j], checks=opts.flann_checks)
    if pm.n_inliers < opts.min_inliers:
        pm.confidence = min(pm.confidence, opts.conf_thresh)  # too few to trust
    if opts.refine_matches and pm.confidence > opts.conf_thresh:
        sel = np.arange(pm.n_inliers)
        if len(sel) > opts.max_refined_per_pair:  # a random subset (seeded) is plenty for the adjustment
            sel = np.sort(np.random.default_rng(opts.seed + 7919 * i + j).choice(
                len(sel), opts.max_refined_per_pair, replace=False))
        xi, xj = feats[i].keypoints[pm.idx_i[sel]], feats[j].keypoints[pm.idx_j[sel]]
        J = reg.homography_jacobian(pm.H, lin[i][pm.idx_i[sel]])
        # (a patch of 13 x 13 work pixels and a shift of at most 1.5 work pixels, in the refinement copy's pixels)
        r_ref = max(found.grays[j].shape[1] / found.sizes[j][0] / feats[j].work_scale, 1.0)
        xj_ref, ok = reg.refine_matches(found.grays[i], found.grays[j], xi, xj, found.sizes[i], found.sizes[j], J,
                                        radius=int(round(6 * r_ref)), max_shift_work_px=1.5 * r_ref)
        if ok.sum() >= max(opts.min_inliers, 0.3 * len(ok)):
            pm.x_i, pm.x_j = xi[ok], xj_ref[ok]
    return pm


def match_described(pair: tuple[int, int], described: dict[int, Future], opts: StitchOptions) -> reg.PairMatch:
    """Photos ``pair`` = (i, j), i < j, matched as :func:`read_and_match` matches them when their keypoints are
    matched as detected (no calibrated lens), from ``described``: photo index -> a future of its
    :func:`describe_photo` (with ``opts``). Waits for both descriptions; started ahead of the stage by its
    prefetch, on the threads that describe the photos, while the stages before it run."""
    i, j = pair
    n = max(i, j) + 1
    found = Registration([None] * n, [None] * n, [None] * n, [None] * n, [None] * n, [None] * n, {}, [])
    for k in (i, j):
        f, _, size, smooth, index, _ = described[k].result()
        found.feats[k], found.sizes[k], found.grays[k], found.indexes[k] = f, size, smooth, index
        found.lin[k] = f.keypoints  # (what _linearised gives without a calibrated lens)
    return _match(pair, found, opts)


def read_and_match(photos: list[Path], names: list[str], opts: StitchOptions, calibrated: dict[str, CameraIntrinsics],
                   progress: ProgressFn, timings: dict[str, float],
                   described: dict[int, Future] | None = None,
                   matched: dict[tuple[int, int], Future] | None = None) -> Registration:
    """Every photo read and described, every pair matched (pipelined in threads: a pair as soon as both its photos
    are described; the result does not depend on the order). ``timings`` gets ``features_s`` and ``matching_s``.
    ``described``: photo index -> a future of its :func:`describe_photo` started earlier (with ``opts``);
    ``matched``: pair (i, j), i < j -> a future of its :func:`match_described` started earlier from them (only
    where no photo of the pair has a calibrated lens: its keypoints are matched as detected)."""
    n = len(photos)
    found = Registration([None] * n, [None] * n, [None] * n, [None] * n, [None] * n, [None] * n, {}, [])
    t0 = time.perf_counter()
    n_pairs = n * (n - 1) // 2
    with ThreadPoolExecutor(max_workers=_workers()) as pool:
        described = described or {}
        matched = matched or {}
        futs = {described[k] if k in described else pool.submit(describe_photo, photos[k], names[k], k, opts): k
                for k in range(n)}
        match_futs = []
        ready: list[int] = []
        for fu in as_completed(futs):
            k = futs[fu]
            (found.feats[k], found.small[k], found.sizes[k], found.grays[k], found.indexes[k],
             full) = fu.result()
            found.lin[k] = _linearised(photos[k], found.feats[k], found.sizes[k], calibrated.get(names[k]))
            if full is not None:
                found.fulls[k] = full
            progress(0.02 + 0.18 * (len(ready) + 1) / n, f"features {photos[k].name}")
            for i in ready:
                pair = (min(i, k), max(i, k))
                ahead = matched.get(pair) if not (calibrated.get(names[i]) or calibrated.get(names[k])) else None
                match_futs.append(ahead if ahead is not None else pool.submit(_match, pair, found, opts))
            ready.append(k)
        timings["features_s"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        for mf in match_futs:
            pm = mf.result()
            found.pairs.append(pm)
            progress(0.2 + 0.2 * len(found.pairs) / max(n_pairs, 1), f"matching {names[pm.i]} - {names[pm.j]}")
    found.pairs.sort(key=lambda p: (p.i, p.j))
    timings["matching_s"] = time.perf_counter() - t1  # after the last photo's features (matching overlaps them)
    return found


def connected_set(found: Registration, photos: list[Path], names: list[str],
                  opts: StitchOptions) -> tuple[list[int], list[dict], list[reg.PairMatch]]:
    """(the largest set of photos connected by confident pairs, the others with why, the confident pairs in it);
    :class:`InputError` when fewer than two photos are connected."""
    n = len(photos)
    kept = reg.largest_component(n, found.pairs, opts.conf_thresh)
    rejected = []
    for k in range(n):
        if k in kept:
            continue
        cand = [p for p in found.pairs if k in (p.i, p.j) and (p.j if p.i == k else p.i) in kept]
        best = max(cand, key=lambda p: p.confidence, default=None)
        if best is None or best.n_matches == 0:
            why = "no feature matches with the kept photos"
        else:
            other = names[best.j if best.i == k else best.i]
            why = (f"no confident match with the kept photos (best: {other}, {best.n_inliers} inliers of "
                   f"{best.n_matches} matches, confidence {best.confidence:.2f} <= {opts.conf_thresh})")
        if len(found.feats[k].keypoints) < 20:
            why += f"; only {len(found.feats[k].keypoints)} features (blank or blurred photo?)"
        rejected.append({"name": names[k], "reason": why})
        log.warning("stitch: %s left out: %s", names[k], why)
    if len(kept) < 2:
        raise InputError(f"no two photos of {[str(p) for p in photos]} overlap with enough matches to be stitched "
                         f"({'; '.join(r['name'] + ': ' + r['reason'] for r in rejected)}); take photos with about "
                         f"30 to 50 % overlap, or use camera.source = 'sfm' for photos from different places")
    kept_pairs = [p for p in found.pairs if p.i in kept and p.j in kept and p.confidence > opts.conf_thresh]
    return kept, rejected, kept_pairs
