"""``stitch_photos``: unordered photos from one place -> panorama image + exact panorama model + statistics.

Steps (Brown and Lowe 2007; ``docs/stitching.md``): photos read at reduced resolution (JPEG DCT scaling,
then area resampling), SIFT, pairwise ratio-test matching and RANSAC homographies with the confidence
test ``n_inliers > 8 + 0.3 n_matches``, the largest connected set (the others are reported with why),
focal from the homographies (or the calibration / EXIF), rotations along a maximum spanning tree, a
rotation-only bundle adjustment through the lens model, the parallax check, a last adjustment robust at
the matches' precision, wave correction, the projection (planar when the field of view allows), composition
at full resolution.
"""

from __future__ import annotations

import logging
import os
import resource
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Literal

import cv2
import numpy as np
from PIL import Image
# loaded with the module, not in the first stitch (a JPEG's EXIF, read by Image.open, loads TiffImagePlugin)
from PIL import JpegImagePlugin, PngImagePlugin, TiffImagePlugin  # noqa: F401

from ..core.camera import CameraIntrinsics
from ..core.panorama import PanoramaModel, PanoramaSource
from ..errors import InputError
from . import register as reg
from .bundle import BAResult, BundleOptions, bundle_adjust, stack_observations
from .bundle_problem import Observations, min_work_scale
from .compose import compose

log = logging.getLogger(__name__)

ProgressFn = Callable[[float, str], None]


@dataclass(frozen=True, kw_only=True)
class StitchOptions:
    """Options of :func:`stitch_photos` (keyword-only; unknown keys are a TypeError)."""

    work_megapix: float = 0.6  # registration resolution per photo, megapixels
    seam_megapix: float = 0.1  # gains and seams, megapixels per photo
    max_features: int = 1200  # SIFT keypoints per photo (the strongest)
    sift_half: bool = True  # SIFT on a half-size copy (no doubled first octave at work scale): 3x faster; the
    # matches are then refined to sub-pixel precision at the work scale (refine_matches)
    sift_half_min_megapix: float = 0.3  # ... when the photo at work scale has at least this many megapixels
    sift_half_max_photo_megapix: float = 1.2  # ... and the photo itself at most this many
    sift_contrast: float = 0.02  # SIFT contrast threshold (lower: more keypoints on low-contrast scenes)
    match_ratio: float = 0.75  # Lowe's ratio test
    flann_trees: int = 2  # randomised k-d trees of each photo's FLANN index
    flann_checks: int = 16  # leaves visited per nearest-neighbour search
    ransac_work_px: float = 3.0  # RANSAC homography threshold, work pixels
    conf_thresh: float = 1.0  # Brown and Lowe's confidence: n_inliers / (8 + 0.3 n_matches) must exceed it
    min_inliers: int = 15
    estimate_distortion: bool = True  # estimate k1 when the intrinsics are not calibrated
    projection: Literal["auto", "planar", "cylindrical", "spherical"] = "auto"
    planar_max_deg: float = 50.0  # planar when every ray is within this angle of the panorama's axis
    cylindrical_max_deg: float = 50.0  # cylindrical when every ray is within this elevation
    wave_correct: bool = True
    max_output_megapix: float = 400.0  # larger panoramas are composed at a reduced scale
    parallax_rms_work_px: float = 3.0  # rotation-only fit worse than this (work pixels, RMS): parallax
    parallax_p90_work_px: float = 5.0
    check_parallax: bool = True  # raise when the verdict is "parallax"
    compose: bool = True
    refine_matches: bool = True  # sub-pixel Lucas-Kanade refinement of the inliers before the bundle adjustment
    max_refined_per_pair: int = 300  # inliers refined (and adjusted) per pair, at most
    refine_megapix: float = 0.9  # matches refined on a copy of this size (at least the work copy's; full size when
    # smaller): finer than the work copy, the single row's focal and rotations are better pinned (docs/stitching.md)
    final_loss_median: float = 1.0  # with estimated intrinsics, a last adjustment (after the parallax check): soft L1
    # of this scale in multiples of the median residual, so that the residuals' tail weighs less (0: none;
    # docs/stitching.md)
    keep_full_max_megapix: float = 2.0  # photos up to this size are decoded once, at full size, and kept for composition
    seed: int = 0

    def __post_init__(self) -> None:
        if not (0.05 <= self.work_megapix <= 50 and 0.01 <= self.seam_megapix <= 5):
            raise ValueError(f"work_megapix={self.work_megapix}, seam_megapix={self.seam_megapix} out of range")
        if self.projection not in ("auto", "planar", "cylindrical", "spherical"):
            raise ValueError(f"projection={self.projection!r}; choose auto, planar, cylindrical or spherical")


@dataclass
class StitchResult:
    model: PanoramaModel | None  # None when fewer than two photos could be registered
    image: np.ndarray | None  # (height, width, 3) uint8 BGR, or None when not composed
    rejected: list[dict] = field(default_factory=list)  # {"name", "reason"}
    intrinsics_source: str = "fallback"
    parallax: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)


def _workers() -> int:
    return max(1, min(4, os.cpu_count() or 1))


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


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


def _choose_frame_and_projection(cam_from_pano: dict[int, np.ndarray], intr: dict[int, CameraIntrinsics],
                                 opts: StitchOptions) -> tuple[str, np.ndarray, dict]:
    """(projection, pano_from_pano_wc rotation, extents in degrees) from the photos' border rays."""
    rays = []
    for k, R in cam_from_pano.items():
        w, h = intr[k].width, intr[k].height
        t = np.linspace(0, 1, 17)
        b = np.concatenate([np.column_stack([t * w - 0.5, np.full_like(t, -0.5)]),
                            np.column_stack([t * w - 0.5, np.full_like(t, h - 0.5)]),
                            np.column_stack([np.full_like(t, -0.5), t * h - 0.5]),
                            np.column_stack([np.full_like(t, w - 0.5), t * h - 0.5])])
        rays.append(intr[k].rays(b) @ R)
    d = np.concatenate(rays)
    yaw = np.degrees(np.arctan2(d[:, 0], d[:, 2]))
    elev = np.degrees(np.arctan2(-d[:, 1], np.hypot(d[:, 0], d[:, 2])))
    # centre the yaw range (the photos never span the +-180 seam after wave correction faces their mean)
    yaw_mid = 0.5 * (yaw.min() + yaw.max())
    elev_mid = 0.5 * (elev.min() + elev.max())
    ext = {"yaw_deg": [float(yaw.min()), float(yaw.max())], "elevation_deg": [float(elev.min()), float(elev.max())]}
    Ry = cv2.Rodrigues(np.array([0.0, np.radians(yaw_mid), 0.0]))[0]  # pano_wc_from_panoY
    proj = opts.projection
    # planar candidate: axis through the centre of the extents
    Rx = cv2.Rodrigues(np.array([np.radians(elev_mid), 0.0, 0.0]))[0]
    R_planar = (Ry @ Rx).T  # pano_from_pano_wc
    dp = d @ R_planar.T
    max_off = float(np.degrees(np.max(np.arccos(np.clip(dp[:, 2], -1, 1)))))
    ext["planar_max_off_axis_deg"] = max_off
    if proj == "auto":
        if max_off <= opts.planar_max_deg:
            proj = "planar"
        elif max(abs(elev.min()), abs(elev.max())) <= opts.cylindrical_max_deg and yaw.max() - yaw.min() < 359:
            proj = "cylindrical"
        else:
            proj = "spherical"
    if proj == "planar":
        if max_off >= 89.0:
            raise InputError(f"the photos span {max_off:.0f} degrees from the panorama's axis: too wide for a planar "
                             f"panorama; use projection 'cylindrical' or 'spherical'")
        return proj, R_planar, ext
    return proj, Ry.T, ext


def stitch_photos(photos: list[Path], *, names: list[str] | None = None, options: StitchOptions = StitchOptions(),
                  calibrated: dict[str, CameraIntrinsics] | None = None,
                  focal_priors_px: dict[str, float | None] | None = None, image_refs: list[str] | None = None,
                  progress: ProgressFn = lambda f, m="": None) -> StitchResult:
    """Stitch ``photos`` (paths) into one panorama.

    ``calibrated``: name -> intrinsics of the photo as on disk (route ``calibrated``: fixed, only rotations
    are estimated). ``focal_priors_px``: name -> EXIF focal in pixels or None (route ``exif``). Neither:
    focal (and k1) estimated (``fallback``). ``image_refs``: the path written into the model for each photo
    (default: the path as given). Raises :class:`InputError` if fewer than two photos can be registered or
    when the parallax check fails (``options.check_parallax``).
    """
    t_start = time.perf_counter()
    photos = [Path(p) for p in photos]
    names = names or [p.name for p in photos]
    image_refs = image_refs or [str(p) for p in photos]
    n = len(photos)
    if n < 2:
        raise InputError(f"stitching needs at least two photos, got {n}")
    opts = options
    timings: dict[str, float] = {}

    # -- intrinsics route ---------------------------------------------------------------------------------------
    calibrated = calibrated or {}
    focal_priors_px = focal_priors_px or {}
    init: dict[int, CameraIntrinsics] = {}
    fixed = bool(calibrated)
    if fixed:
        for nm in names:
            if nm not in calibrated:
                raise InputError(f"no calibrated intrinsics for photo {nm}")
        source = "calibrated"
    else:
        source = "exif" if focal_priors_px and all(focal_priors_px.get(nm) for nm in names) else "fallback"

    # -- read at work and seam resolution, features ------------------------------------------------------------
    def read_and_detect(k: int) -> tuple:
        """features, seam-size photo, full size, smoothed grey, FLANN index, linearised keypoints, full photo"""
        p = photos[k]
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
        f = reg.detect_features(names[k], gray, (w, h), max_features=opts.max_features,
                                contrast_threshold=opts.sift_contrast, half=half)
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
        lin_k = f.keypoints  # linearised keypoints for matching: undistorted pixels when the lens is known
        if fixed:
            ci = calibrated[names[k]]
            if (ci.width, ci.height) != (w, h):
                raise InputError(f"{p}: {w}x{h} px, but the camera profile is for {ci.width}x{ci.height}; use "
                                 f"photos at the profile's size or recalibrate")
            if ci.has_distortion and len(f.keypoints):
                lin_k = ci.pixels_from_normalized(ci.undistort(ci.normalized_from_pixels(f.keypoints)))
        return f, sm, (w, h), smooth, index, lin_k, full

    feats: list = [None] * n
    small: list = [None] * n
    sizes: list = [None] * n
    grays: list = [None] * n  # work resolution, for the sub-pixel refinement of the matches
    indexes: list = [None] * n  # FLANN forests of the descriptors
    lin: list = [None] * n
    fulls: dict[int, np.ndarray] = {}  # full-resolution photos kept for composition (small photos only)

    def match(pair: tuple[int, int]) -> reg.PairMatch:
        i, j = pair
        pm = reg.match_pair(i, j, feats[i], feats[j], lin[i], lin[j], ratio=opts.match_ratio,
                            ransac_work_px=opts.ransac_work_px, seed=opts.seed, index_i=indexes[i],
                            index_j=indexes[j], checks=opts.flann_checks)
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
            r_ref = max(grays[j].shape[1] / sizes[j][0] / feats[j].work_scale, 1.0)
            xj_ref, ok = reg.refine_matches(grays[i], grays[j], xi, xj, sizes[i], sizes[j], J,
                                            radius=int(round(6 * r_ref)), max_shift_work_px=1.5 * r_ref)
            if ok.sum() >= max(opts.min_inliers, 0.3 * len(ok)):
                pm.x_i, pm.x_j = xi[ok], xj_ref[ok]
        return pm

    # OpenCV releases the GIL: photos are read and described in parallel threads, and each pair is matched as
    # soon as both its photos are described (pipelined; the result does not depend on the order)
    t0 = time.perf_counter()
    n_pairs = n * (n - 1) // 2
    pairs: list[reg.PairMatch] = []
    with ThreadPoolExecutor(max_workers=_workers()) as pool:
        futs = {pool.submit(read_and_detect, k): k for k in range(n)}
        match_futs = []
        ready: list[int] = []
        for fu in as_completed(futs):
            k = futs[fu]
            feats[k], small[k], sizes[k], grays[k], indexes[k], lin[k], full = fu.result()
            if full is not None:
                fulls[k] = full
            progress(0.02 + 0.18 * (len(ready) + 1) / n, f"features {photos[k].name}")
            match_futs += [pool.submit(match, (min(i, k), max(i, k))) for i in ready]
            ready.append(k)
        timings["features_s"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        for mf in match_futs:
            pm = mf.result()
            pairs.append(pm)
            progress(0.2 + 0.2 * len(pairs) / max(n_pairs, 1), f"matching {names[pm.i]} - {names[pm.j]}")
    pairs.sort(key=lambda p: (p.i, p.j))
    timings["matching_s"] = time.perf_counter() - t1  # after the last photo's features (matching overlaps them)
    kept = reg.largest_component(n, pairs, opts.conf_thresh)
    rejected = []
    for k in range(n):
        if k in kept:
            continue
        cand = [p for p in pairs if k in (p.i, p.j) and (p.j if p.i == k else p.i) in kept]
        best = max(cand, key=lambda p: p.confidence, default=None)
        if best is None or best.n_matches == 0:
            why = "no feature matches with the kept photos"
        else:
            other = names[best.j if best.i == k else best.i]
            why = (f"no confident match with the kept photos (best: {other}, {best.n_inliers} inliers of "
                   f"{best.n_matches} matches, confidence {best.confidence:.2f} <= {opts.conf_thresh})")
        if len(feats[k].keypoints) < 20:
            why += f"; only {len(feats[k].keypoints)} features (blank or blurred photo?)"
        rejected.append({"name": names[k], "reason": why})
        log.warning("stitch: %s left out: %s", names[k], why)
    if len(kept) < 2:
        raise InputError(f"no two photos of {[str(p) for p in photos]} overlap with enough matches to be stitched "
                         f"({'; '.join(r['name'] + ': ' + r['reason'] for r in rejected)}); take photos with about "
                         f"30 to 50 % overlap, or use camera.source = 'sfm' for photos from different places")
    kept_pairs = [p for p in pairs if p.i in kept and p.j in kept and p.confidence > opts.conf_thresh]

    # -- initial intrinsics and rotations --------------------------------------------------------------------
    progress(0.42, "rotations and focal")
    if fixed:
        init = {k: calibrated[names[k]] for k in range(n)}
    else:
        centres = {k: ((sizes[k][0] - 1) / 2.0, (sizes[k][1] - 1) / 2.0) for k in range(n)}
        f_h = reg.focal_from_homographies(kept_pairs, centres)
        for k in kept:
            w, h = sizes[k]
            prior = focal_priors_px.get(names[k])
            f = prior or f_h or float(w + h)  # OpenCV's fallback when the homographies say nothing
            init[k] = CameraIntrinsics(width=w, height=h, fx=f, fy=f, cx=centres[k][0], cy=centres[k][1])
        if source == "fallback" and f_h is None:
            log.warning("stitch: the homographies do not determine the focal length; starting from w + h")
    # camera groups (one focal and lens per group): photos of about the same size (1 %) and the same EXIF focal
    groups: dict[int, int] = {}
    reps: list[int] = []
    for k in kept:
        for g, r in enumerate(reps):
            fk, fr = focal_priors_px.get(names[k]) or 0.0, focal_priors_px.get(names[r]) or 0.0
            same = (abs(sizes[k][0] / sizes[r][0] - 1) < 0.01 and abs(sizes[k][1] / sizes[r][1] - 1) < 0.01
                    and round(fk, 1) == round(fr, 1))
            if same and not fixed:
                groups[k] = g
                break
        else:
            groups[k] = len(reps)
            reps.append(k)
    Ks = {k: init[k].K for k in kept}
    R0 = reg.rotations_from_homographies(kept, kept_pairs, Ks)

    # -- bundle adjustment ------------------------------------------------------------------------------------------
    t0 = time.perf_counter()
    progress(0.45, "bundle adjustment")
    obs = stack_observations(kept_pairs, feats, kept, seed=opts.seed, max_per_pair=opts.max_refined_per_pair)
    wscale = {k: feats[k].work_scale for k in kept}
    prior = None
    if source == "exif":
        prior = {groups[k]: focal_priors_px[names[k]] for k in kept}
    root_first = sorted(kept, key=lambda k: -sum(p.n_inliers for p in kept_pairs if k in (p.i, p.j)))
    # focal and distortion trade off along a shallow valley: the lens fit starts from the initial focal
    # (EXIF or homographies), not from a pinhole fit, whose focal has absorbed the distortion
    lens = not fixed and opts.estimate_distortion
    ba = bundle_adjust(obs, root_first, groups, init, R0, wscale,
                       BundleOptions(fixed_intrinsics=fixed, estimate_k1=lens), focal_prior=prior)
    focal_model = "fixed" if fixed else "shared"
    if not fixed and len(set(groups.values())) < len(kept) and _rms_work(ba, obs, wscale) > 0.8:
        # one focal per photo when that fits clearly better (zoom changed between photos; no k1 then)
        own = {k: n_ for n_, k in enumerate(kept)}
        # from the shared fit's rotations and focal (the root keeps its rotation in both fits)
        init_own = {k: replace(init[k], fx=ba.intrinsics[k].fx, fy=ba.intrinsics[k].fx) for k in kept}
        # (its robust pass only: the final pass runs when this model is chosen; the RMS after the robust pass is at
        # least the final one's, so the comparison leans towards the shared camera)
        ba_own = bundle_adjust(obs, root_first, own, init_own, ba.cam_from_pano, wscale,
                               BundleOptions(fixed_intrinsics=False, estimate_k1=False, final_pass=False))
        rms_shared, rms_own = _rms_work(ba, obs, wscale), _rms_work(ba_own, obs, wscale)
        log.info("stitch: RMS %.3f (one camera: f %.1f, k1 %.4f) vs %.3f work px (one focal per photo)", rms_shared,
                 ba.intrinsics[kept[0]].fx, ba.intrinsics[kept[0]].k1, rms_own)
        if rms_shared > 1.3 * rms_own + 0.2:
            ba = bundle_adjust(obs, root_first, own, ba_own.intrinsics, ba_own.cam_from_pano, wscale,
                               BundleOptions(fixed_intrinsics=False, estimate_k1=False, robust_pass=False),
                               used=ba_own.used)
            groups, focal_model = own, "per_photo"
    timings["bundle_adjustment_s"] = time.perf_counter() - t0

    # -- residuals and the parallax check ------------------------------------------------------------------------
    s_obs = min_work_scale(obs, wscale)
    err_full = np.linalg.norm(ba.residuals_px, axis=2)  # (M, 2)
    err_work = err_full * s_obs[:, None]
    f_obs = np.array([ba.intrinsics[a].fx for a in obs.a])
    err_deg = np.degrees(err_full / f_obs[:, None])
    u = ba.used
    rms_w = float(np.sqrt(np.mean(err_work[u] ** 2)))
    p90_w = float(np.percentile(err_work[u], 90))
    per_pair = []
    for pid in np.unique(obs.pair):
        m = (obs.pair == pid) & u
        p = kept_pairs[pid]
        if m.any():
            per_pair.append({"photos": [names[p.i], names[p.j]], "n": int(m.sum()),
                             "rms_work_px": round(float(np.sqrt(np.mean(err_work[m] ** 2))), 3)})
    verdict = "ok" if (rms_w <= opts.parallax_rms_work_px and p90_w <= opts.parallax_p90_work_px) else "parallax"
    parallax = {
        "verdict": verdict, "n_observations": int(len(u)), "n_used": int(u.sum()),
        "rms_work_px": round(rms_w, 4), "p90_work_px": round(p90_w, 4),
        "median_work_px": round(float(np.median(err_work[u])), 4),
        "rms_full_px": round(float(np.sqrt(np.mean(err_full[u] ** 2))), 4),
        "rms_deg": round(float(np.sqrt(np.mean(err_deg[u] ** 2))), 5),
        "threshold_rms_work_px": opts.parallax_rms_work_px, "threshold_p90_work_px": opts.parallax_p90_work_px,
        "per_pair": per_pair,
    }
    if verdict == "parallax":
        msg = (f"the photos do not fit a camera turning about one point (rotation-only residuals: RMS "
               f"{rms_w:.2f} px, 90th percentile {p90_w:.2f} px at registration scale, above "
               f"{opts.parallax_rms_work_px} / {opts.parallax_p90_work_px}): they were taken from different positions "
               f"(parallax), and a "
               f"panorama of them would ghost. Set camera.source = \"sfm\" in project.toml to use the multi-view "
               f"route, or retake the photos turning the camera about its lens")
        log.warning("stitch: %s", msg)
        if opts.check_parallax:
            raise InputError(msg)

    # -- a last adjustment, robust at the scale of the matches' precision -------------------------------------------
    if not fixed and opts.final_loss_median > 0:
        # (from where the adjustment is, on its inliers: their median residual is the matches' precision, under 0.1 px
        # on the ground-truth sets, but a tail of mismatches and poorly textured or occluded patches, up to the 4 px
        # outlier threshold, pulls the weakly determined focal of a single row; the parallax check above keeps the
        # least-squares residuals)
        t0 = time.perf_counter()
        last = BundleOptions(fixed_intrinsics=False, estimate_k1=lens and focal_model == "shared", robust_pass=False,
                             final_loss_median=opts.final_loss_median)
        ba = bundle_adjust(obs, root_first, groups, init, ba.cam_from_pano, wscale, last,
                           focal_prior=prior if focal_model == "shared" else None, used=ba.used, start=ba.intrinsics)
        timings["last_adjustment_s"] = time.perf_counter() - t0

    # -- wave correction, projection, model --------------------------------------------------------------------------
    Rs = dict(ba.cam_from_pano)
    if opts.wave_correct:
        W = reg.wave_correct(Rs)  # pano_from_pano0
        Rs = {k: R @ W.T for k, R in Rs.items()}
    proj, R_axis, extents = _choose_frame_and_projection(Rs, ba.intrinsics, opts)
    Rs = {k: R @ R_axis.T for k, R in Rs.items()}
    sources = tuple(PanoramaSource(name=names[k], image=image_refs[k], intrinsics=ba.intrinsics[k],
                                   cam_from_pano=reg.nearest_rotation(Rs[k])) for k in kept)
    scale = float(np.median([ba.intrinsics[k].fx for k in kept]))
    model = _fit_extent(PanoramaModel(projection=proj, scale=scale, offset=(0.0, 0.0), width=1, height=1,
                                      sources=sources))
    out_scale = 1.0
    if model.width * model.height > opts.max_output_megapix * 1e6:
        out_scale = float(np.sqrt(opts.max_output_megapix * 1e6 / (model.width * model.height)))
        model = _fit_extent(PanoramaModel(projection=proj, scale=scale * out_scale, offset=(0.0, 0.0), width=1,
                                          height=1, sources=sources))
        log.warning("stitch: panorama reduced by %.3f to stay under %.0f MP", out_scale, opts.max_output_megapix)

    image = None
    comp_stats: dict = {}
    if opts.compose:
        t0 = time.perf_counter()
        progress(0.55, "composing")
        # seam-resolution panorama: the photos' seam scale relative to the output panorama's scale
        seam_scale = float(np.median([small[k].shape[1] / sizes[k][0] for k in kept])) / out_scale
        paths_kept = [photos[k] for k in kept]
        kept_full = {str(photos[k]): fulls.pop(k) for k in kept if k in fulls}
        fulls.clear()

        def read_full(p: Path) -> np.ndarray:  # the photo decoded at registration, else read now
            img = kept_full.pop(str(p), None)
            return img if img is not None else cv2.imread(str(p), cv2.IMREAD_COLOR)

        image, comp_stats = compose(model, paths_kept, [small[k] for k in kept], seam_scale=seam_scale,
                                    read_full=read_full,
                                    progress=lambda f, m="": progress(0.55 + 0.43 * f, m))
        timings["compose_s"] = time.perf_counter() - t0
    progress(1.0, "done")
    stats = {
        "n_photos": n, "n_kept": len(kept), "n_rejected": len(rejected), "kept": [names[k] for k in kept],
        "rejected": rejected, "intrinsics_source": source, "focal_model": focal_model, "projection": proj,
        "scale": scale * out_scale,
        "size": [model.width, model.height], "output_scale": out_scale, "extents": extents,
        "focal_px": {names[k]: round(ba.intrinsics[k].fx, 3) for k in kept},
        "k1": {names[k]: round(ba.intrinsics[k].k1, 5) for k in kept},
        "pairs": [{"photos": [names[p.i], names[p.j]], "matches": p.n_matches, "inliers": p.n_inliers,
                   "confidence": round(p.confidence, 3)} for p in pairs if p.n_matches > 0],
        "ba": {"cost": ba.cost, "nfev": ba.n_iterations},
        "parallax": {k: v for k, v in parallax.items() if k != "per_pair"},
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "time_s": round(time.perf_counter() - t_start, 3), "peak_rss_mb": round(_peak_rss_mb(), 1),
        **({"compose": comp_stats} if comp_stats else {}),
    }
    return StitchResult(model=model, image=image, rejected=rejected, intrinsics_source=source, parallax=parallax,
                        stats=stats)


def _rms_work(ba: BAResult, obs: Observations, wscale: dict[int, float]) -> float:
    e = np.linalg.norm(ba.residuals_px, axis=2) * min_work_scale(obs, wscale)[:, None]
    return float(np.sqrt(np.mean(e[ba.used] ** 2)))


def _fit_extent(model: PanoramaModel) -> PanoramaModel:
    """The model with offset, width and height set to the bounding box of every source photo's border."""

    pts = []
    for i, s in enumerate(model.sources):
        w, h = s.intrinsics.width, s.intrinsics.height
        t = np.linspace(0, 1, 65)
        b = np.concatenate([np.column_stack([t * w - 0.5, np.full_like(t, -0.5)]),
                            np.column_stack([t * w - 0.5, np.full_like(t, h - 0.5)]),
                            np.column_stack([np.full_like(t, -0.5), t * h - 0.5]),
                            np.column_stack([np.full_like(t, w - 0.5), t * h - 0.5])])
        pts.append(model.project(s.intrinsics.rays(b) @ s.cam_from_pano))
    uv = np.concatenate(pts)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    # warped = uv (offset 0); pixel centres from floor(min) + 0.5 ... keep pixel edges at the border
    lo = np.floor(uv.min(axis=0) + 0.5)
    hi = np.ceil(uv.max(axis=0) - 0.5)
    width, height = int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1
    return replace(model, offset=(float(lo[0]), float(lo[1])), width=width, height=height)
