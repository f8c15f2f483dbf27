"""``stitch_photos``: unordered photos from one place -> panorama image + exact panorama model + statistics.

Steps (Brown and Lowe 2007; ``docs/stitching.md``): photos read at reduced resolution (JPEG DCT scaling,
then area resampling), SIFT, pairwise ratio-test matching and RANSAC homographies with the confidence
test ``n_inliers > 8 + 0.3 n_matches``, the largest connected set (the others are reported with why)
(:mod:`.photo_matching`), focal from the homographies (or the calibration / EXIF), rotations along a maximum
spanning tree, a rotation-only bundle adjustment through the lens model (:mod:`.bundle`), the parallax check, a
last adjustment robust at the matches' precision, wave correction, the projection (planar when the field of view
allows), composition at full resolution (:mod:`.compose`).
"""

from __future__ import annotations

import logging
import resource
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
# loaded with the module, not in the first stitch (a JPEG's EXIF, read by Image.open, loads TiffImagePlugin)
from PIL import JpegImagePlugin, PngImagePlugin, TiffImagePlugin  # noqa: F401

from ..core.camera import CameraIntrinsics
from ..core.geometry import orthonormal, rot_x, rot_y
from ..core.panorama import PanoramaModel, PanoramaSource
from ..errors import InputError
from . import register as reg
from .bundle import BAResult, BundleOptions, bundle_adjust, load_solver, stack_observations
from .bundle_problem import Observations, min_work_scale
from .compose import compose
from .options import ProgressFn, StitchOptions, StitchResult
from .photo_matching import Registration, connected_set, read_and_match

log = logging.getLogger(__name__)

__all__ = ["StitchOptions", "StitchResult", "stitch_photos"]


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


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
    Ry = rot_y(np.radians(yaw_mid))  # pano_wc_from_panoY
    proj = opts.projection
    # planar candidate: axis through the centre of the extents
    Rx = rot_x(np.radians(elev_mid))
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


def _intrinsics_route(names: list[str], calibrated: dict[str, CameraIntrinsics],
                      focal_priors_px: dict[str, float | None]) -> tuple[bool, str]:
    """(intrinsics fixed, source): ``calibrated`` for every photo, else ``exif`` when every photo has an EXIF
    focal, else ``fallback``."""
    fixed = bool(calibrated)
    if fixed:
        for nm in names:
            if nm not in calibrated:
                raise InputError(f"no calibrated intrinsics for photo {nm}")
        return fixed, "calibrated"
    return fixed, "exif" if focal_priors_px and all(focal_priors_px.get(nm) for nm in names) else "fallback"


def _initial_cameras(kept: list[int], kept_pairs: list[reg.PairMatch], sizes: list, names: list[str],
                     calibrated: dict[str, CameraIntrinsics], focal_priors_px: dict[str, float | None], fixed: bool,
                     source: str) -> tuple[dict[int, CameraIntrinsics], dict[int, int], dict[int, np.ndarray]]:
    """(starting intrinsics, camera groups, starting rotations) of the kept photos. A group (one focal and lens)
    holds photos of about the same size (1 %) and the same EXIF focal; calibrated photos are each their own."""
    init: dict[int, CameraIntrinsics] = {}
    if fixed:
        init = {k: calibrated[names[k]] for k in range(len(names))}
    else:
        centres = {k: ((sizes[k][0] - 1) / 2.0, (sizes[k][1] - 1) / 2.0) for k in range(len(names))}
        f_h = reg.focal_from_homographies(kept_pairs, centres)
        for k in kept:
            w, h = sizes[k]
            prior = focal_priors_px.get(names[k])
            f = prior or f_h or float(w + h)  # OpenCV's fallback when the homographies say nothing
            init[k] = CameraIntrinsics(width=w, height=h, fx=f, fy=f, cx=centres[k][0], cy=centres[k][1])
        if source == "fallback" and f_h is None:
            log.warning("stitch: the homographies do not determine the focal length; starting from w + h")
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
    return init, groups, reg.rotations_from_homographies(kept, kept_pairs, Ks)


def _adjust(obs: Observations, root_first: list[int], kept: list[int], groups: dict[int, int],
            init: dict[int, CameraIntrinsics], R0: dict[int, np.ndarray], wscale: dict[int, float], fixed: bool,
            lens: bool, prior: dict[int, float] | None) -> tuple[BAResult, dict[int, int], str]:
    """The bundle adjustment with one camera per group, or with one focal per photo when that fits clearly better
    (zoom changed between photos; no k1 then): (result, the groups used, ``focal_model``)."""
    ba = bundle_adjust(obs, root_first, groups, init, R0, wscale,
                       BundleOptions(fixed_intrinsics=fixed, estimate_k1=lens), focal_prior=prior)
    focal_model = "fixed" if fixed else "shared"
    if not fixed and len(set(groups.values())) < len(kept) and _rms_work(ba, obs, wscale) > 0.8:
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
    return ba, groups, focal_model


def _parallax(ba: BAResult, obs: Observations, wscale: dict[int, float], kept_pairs: list[reg.PairMatch],
              names: list[str], opts: StitchOptions) -> dict:
    """The rotation-only fit's residuals (work px, full px, degrees; per pair) and the verdict ``ok`` or
    ``parallax`` (an :class:`InputError` with ``opts.check_parallax``)."""
    s_obs = min_work_scale(obs, wscale)
    err_full = np.linalg.norm(ba.residuals_px, axis=2)  # (M, 2)
    err_work = err_full * s_obs[:, None]
    f_obs = np.array([ba.intrinsics[a].fx for a in obs.a])
    err_deg = np.degrees(err_full / f_obs[:, None])
    u = ba.used
    rms_w = float(np.sqrt(np.mean(err_work[u] ** 2)))
    p90_w = reg.percentile(err_work[u], 90)
    per_pair = []
    for pid in reg.unique_sorted(obs.pair):
        m = (obs.pair == pid) & u
        p = kept_pairs[pid]
        if m.any():
            per_pair.append({"photos": [names[p.i], names[p.j]], "n": int(m.sum()),
                             "rms_work_px": round(float(np.sqrt(np.mean(err_work[m] ** 2))), 3)})
    verdict = "ok" if (rms_w <= opts.parallax_rms_work_px and p90_w <= opts.parallax_p90_work_px) else "parallax"
    parallax = {
        "verdict": verdict, "n_observations": int(len(u)), "n_used": int(u.sum()),
        "rms_work_px": round(rms_w, 4), "p90_work_px": round(p90_w, 4),
        "median_work_px": round(reg.median(err_work[u]), 4),
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
    return parallax


def _panorama_model(ba: BAResult, kept: list[int], names: list[str], image_refs: list[str],
                    opts: StitchOptions) -> tuple[PanoramaModel, str, dict, float, float]:
    """(the panorama model, its projection, the extents, its scale (px per radian), the output scale): wave
    corrected, the frame and projection chosen, reduced below ``max_output_megapix``."""
    Rs = dict(ba.cam_from_pano)
    if opts.wave_correct:
        W = reg.wave_correct(Rs)  # pano_from_pano0
        Rs = {k: R @ W.T for k, R in Rs.items()}
    proj, R_axis, extents = _choose_frame_and_projection(Rs, ba.intrinsics, opts)
    Rs = {k: R @ R_axis.T for k, R in Rs.items()}
    sources = tuple(PanoramaSource(name=names[k], image=image_refs[k], intrinsics=ba.intrinsics[k],
                                   cam_from_pano=orthonormal(Rs[k])) for k in kept)
    scale = reg.median([ba.intrinsics[k].fx for k in kept])
    model = _fit_extent(PanoramaModel(projection=proj, scale=scale, offset=(0.0, 0.0), width=1, height=1,
                                      sources=sources))
    out_scale = 1.0
    if model.width * model.height > opts.max_output_megapix * 1e6:
        out_scale = float(np.sqrt(opts.max_output_megapix * 1e6 / (model.width * model.height)))
        model = _fit_extent(PanoramaModel(projection=proj, scale=scale * out_scale, offset=(0.0, 0.0), width=1,
                                          height=1, sources=sources))
        log.warning("stitch: panorama reduced by %.3f to stay under %.0f MP", out_scale, opts.max_output_megapix)
    return model, proj, extents, scale, out_scale


def _compose_kept(model: PanoramaModel, photos: list[Path], kept: list[int], found: Registration, out_scale: float,
                  progress: ProgressFn) -> tuple[np.ndarray, dict]:
    """The panorama composed at full resolution from the kept photos (the small ones as decoded at registration)."""
    # seam-resolution panorama: the photos' seam scale relative to the output panorama's scale
    seam_scale = reg.median([found.small[k].shape[1] / found.sizes[k][0] for k in kept]) / out_scale
    paths_kept = [photos[k] for k in kept]
    kept_full = {str(photos[k]): found.fulls.pop(k) for k in kept if k in found.fulls}
    found.fulls.clear()

    def read_full(p: Path) -> np.ndarray:  # the photo decoded at registration, else read now
        img = kept_full.pop(str(p), None)
        return img if img is not None else cv2.imread(str(p), cv2.IMREAD_COLOR)

    return compose(model, paths_kept, [found.small[k] for k in kept], seam_scale=seam_scale, read_full=read_full,
                   progress=lambda f, m="": progress(0.55 + 0.43 * f, m))


def stitch_photos(photos: list[Path], *, names: list[str] | None = None, options: StitchOptions = StitchOptions(),
                  calibrated: dict[str, CameraIntrinsics] | None = None,
                  focal_priors_px: dict[str, float | None] | None = None, image_refs: list[str] | None = None,
                  progress: ProgressFn = lambda f, m="": None, described: dict | None = None,
                  matched: dict | None = None) -> StitchResult:
    """Stitch ``photos`` (paths) into one panorama.

    ``calibrated``: name -> intrinsics of the photo as on disk (route ``calibrated``: fixed, only rotations
    are estimated). ``focal_priors_px``: name -> EXIF focal in pixels or None (route ``exif``). Neither:
    focal (and k1) estimated (``fallback``). ``image_refs``: the path written into the model for each photo
    (default: the path as given). ``described``: photo index -> a future of its ``photo_matching.describe_photo``
    with ``options``, started earlier; ``matched``: pair (i, j), i < j -> a future of its
    ``photo_matching.match_described`` from them (used for the pairs without a calibrated lens). Raises :class:`InputError` if fewer than two photos can be registered or
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
    calibrated = calibrated or {}
    focal_priors_px = focal_priors_px or {}
    fixed, source = _intrinsics_route(names, calibrated, focal_priors_px)
    if described:  # the photos are being described on other threads (a prefetch): the adjustment's libraries
        load_solver()  # loaded meanwhile, not after them
    found = read_and_match(photos, names, opts, calibrated, progress, timings, described, matched)
    kept, rejected, kept_pairs = connected_set(found, photos, names, opts)
    progress(0.42, "rotations and focal")
    init, groups, R0 = _initial_cameras(kept, kept_pairs, found.sizes, names, calibrated, focal_priors_px, fixed,
                                        source)
    t0 = time.perf_counter()
    progress(0.45, "bundle adjustment")
    obs = stack_observations(kept_pairs, found.feats, kept, seed=opts.seed, max_per_pair=opts.max_refined_per_pair)
    wscale = {k: found.feats[k].work_scale for k in kept}
    prior = {groups[k]: focal_priors_px[names[k]] for k in kept} if source == "exif" else None
    root_first = sorted(kept, key=lambda k: -sum(p.n_inliers for p in kept_pairs if k in (p.i, p.j)))
    # focal and distortion trade off along a shallow valley: the lens fit starts from the initial focal
    # (EXIF or homographies), not from a pinhole fit, whose focal has absorbed the distortion
    lens = not fixed and opts.estimate_distortion
    ba, groups, focal_model = _adjust(obs, root_first, kept, groups, init, R0, wscale, fixed, lens, prior)
    timings["bundle_adjustment_s"] = time.perf_counter() - t0
    parallax = _parallax(ba, obs, wscale, kept_pairs, names, opts)
    if not fixed and opts.final_loss_median > 0:
        # a last adjustment, robust at the scale of the matches' precision (from where the adjustment is, on its
        # inliers: their median residual is the matches' precision, under 0.1 px on the ground-truth sets, but a
        # tail of mismatches and poorly textured or occluded patches, up to the 4 px outlier threshold, pulls the
        # weakly determined focal of a single row; the parallax check above keeps the least-squares residuals)
        t0 = time.perf_counter()
        last = BundleOptions(fixed_intrinsics=False, estimate_k1=lens and focal_model == "shared", robust_pass=False,
                             final_loss_median=opts.final_loss_median)
        ba = bundle_adjust(obs, root_first, groups, init, ba.cam_from_pano, wscale, last,
                           focal_prior=prior if focal_model == "shared" else None, used=ba.used, start=ba.intrinsics)
        timings["last_adjustment_s"] = time.perf_counter() - t0
    model, proj, extents, scale, out_scale = _panorama_model(ba, kept, names, image_refs, opts)
    image, comp_stats = None, {}
    if opts.compose:
        t0 = time.perf_counter()
        progress(0.55, "composing")
        image, comp_stats = _compose_kept(model, photos, kept, found, out_scale, progress)
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
                   "confidence": round(p.confidence, 3)} for p in found.pairs if p.n_matches > 0],
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
