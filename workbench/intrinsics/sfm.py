"""Multi-view structure from motion with pycolmap: intrinsics, distortion and every camera's pose.

Feature extraction (SIFT), matching (exhaustive for small sets, sequential for long ordered sequences),
geometric verification and incremental mapping run in a temporary folder; the largest model (the main one) and
every separate, smaller model COLMAP built from the photos it could not join to it are converted to the
workbench's conventions (``docs/conventions.md``):

* COLMAP's ``SIMPLE_PINHOLE``, ``PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL`` and ``OPENCV`` cameras map exactly
  to our Brown :class:`~workbench.core.camera.CameraIntrinsics` (same distortion polynomial, OpenCV's
  coefficient order); COLMAP puts the centre of the top-left pixel at (0.5, 0.5), we put it at (0, 0), so
  ``cx_ours = cx_colmap - 0.5`` (and the same for cy).
* Image poses become ``cam_from_model`` 4x4 row-major matrices (``p_cam = R p_model + t``); the model frame is
  COLMAP's arbitrary similarity frame (georegistration places it in the scene); each separate model has a frame
  of its own (georegistration places each one from the control points its photos see).

The result is written by the ``sfm`` stage as ``out/sfm/reconstruction.json`` (``docs/intrinsics.md``).
"""

from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Annotated, Callable, Literal, get_args

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.options import Range, check_options
from ..core.settings import options_from_dict
from ..errors import InputError, StageError
from .colmap_camera import CAMERA_MODELS, CameraModel, colmap_params_from_intrinsics, intrinsics_from_colmap
from .sfm_covariance import intrinsic_parameters, reconstruction_pose_covariance

log = logging.getLogger(__name__)

__all__ = ["CAMERA_MODELS", "CameraModel", "SfmOptions", "SfmResult", "colmap_params_from_intrinsics",
           "intrinsics_from_colmap", "run_sfm", "similarity_align"]

Matcher = Literal["auto", "exhaustive", "sequential"]
MATCHERS = get_args(Matcher)


@dataclass(frozen=True, kw_only=True)
class SfmOptions:
    """Options of :func:`run_sfm`. Unknown keys (``from_dict``) and bad values (each field declares what it
    takes: :mod:`workbench.core.options`) raise :class:`~workbench.errors.SettingsError`.

    ``camera_model``: COLMAP camera model, one of :data:`CAMERA_MODELS` (``RADIAL`` = f, cx, cy, k1, k2).
    ``single_camera``: all photos share one camera (same camera, same zoom).
    ``matcher``: ``exhaustive`` (every pair), ``sequential`` (each photo with the next ``sequential_overlap``,
    for photos taken in order along a path) or ``auto`` (exhaustive up to ``exhaustive_max_images``).
    ``max_image_size_px``: photos are downscaled to this long side for feature extraction (keypoints are
    scaled back to full resolution). ``max_num_features``: SIFT features per photo.
    ``sift_peak_threshold``: SIFT's contrast threshold (COLMAP: 0.0067); lower finds features in smooth,
    low-contrast areas (grass, painted car sides, renders). ``sift_affine_shape`` and
    ``sift_domain_size_pooling``: affine-covariant SIFT and domain-size pooling, which keep matching
    across wide changes of viewpoint (photos 30-45 degrees apart around a site) at about twice the
    extraction time.
    ``refine_focal``, ``refine_principal_point``, ``refine_distortion``: what bundle adjustment refines.
    ``verify_min_num_inliers``: a pair of photos counts as matched from this many geometrically verified
    matches. ``init_*``, ``abs_pose_*``: COLMAP's incremental-mapper thresholds (see :meth:`forward_motion`
    for a camera that moves forward along a street or a track). The defaults are stricter than COLMAP's
    (pairs: 40 verified matches instead of 15; registration: 40 inliers and 40 % instead of 30 and 25 %):
    carriages look alike on both sides and from car to car, and a photo registered on look-alike matches is
    placed wrongly (on the synthetic Spuyten Duyvil set, a photo from the far side came out turned by
    150-175 degrees). Stricter thresholds make this rarer, not impossible: fewer photos placed right is better
    than more placed wrong.
    ``min_model_size``: a separate model (photos COLMAP registered together but could not join to the main
    model) is kept from this many photos (COLMAP: 10); every one kept is written (``reconstruction.json``'s
    ``models``) for georegistration to place from the control points its photos see.
    ``forward_motion_retry``: if fewer than half the photos register, map again with the forward-motion
    initial-pair thresholds, and keep that model if it registers clearly more photos (1.5 times, 2 or more).
    ``num_threads``: CPU threads, unless ``deterministic`` (the default), which runs everything on one thread
    so that a run repeats bit for bit (COLMAP's threads share work in an order that changes from run to run,
    and the result with it). ``seed``: random seed.
    ``max_points``: at most this many 3-D points are written (a fixed-seed subsample).
    ``pose_covariance``: state each model's pose covariance after bundle adjustment (each view's
    ``pose_factor``, :mod:`.sfm_covariance`), which the georef stage carries into the photos' pose uncertainty;
    ``pose_covariance_intrinsics``: with the error of the intrinsics bundle adjustment refined marginalised into it
    (else the poses' covariance given the intrinsics).
    ``focal_hold_retry``: where the refined focal runs off the initial one (a profile or EXIF) by a factor over
    :data:`FOCAL_RUN_OFF` (narrow baselines and few photos leave a model whose focal they do not determine), map
    again with the focal held at the initial one and keep that model if it registers more photos, or as many at
    a mean reprojection error within :data:`HELD_ERROR_RATIO` of the free one's (a wrong initial focal registers
    fewer photos or fits them worse, and the free model stays).
    """

    camera_model: CameraModel = "RADIAL"
    single_camera: bool = True
    matcher: Matcher = "auto"
    exhaustive_max_images: Annotated[int, Range(ge=2)] = 60
    sequential_overlap: Annotated[int, Range(ge=1)] = 10
    max_image_size_px: Annotated[int, Range(ge=100)] = 2000
    max_num_features: Annotated[int, Range(ge=100)] = 16384
    sift_peak_threshold: Annotated[float, Range(gt=0.0, lt=0.1)] = 0.002
    sift_affine_shape: bool = True
    sift_domain_size_pooling: bool = True
    refine_focal: bool = True
    refine_principal_point: bool = False
    refine_distortion: bool = True
    init_max_forward_motion: Annotated[float, Range(gt=0.0, le=1.0)] = 0.95
    init_min_tri_angle_deg: Annotated[float, Range(gt=0.0, lt=90.0)] = 16.0
    init_min_num_inliers: Annotated[int, Range(ge=8)] = 100
    verify_min_num_inliers: Annotated[int, Range(ge=8)] = 40
    abs_pose_min_num_inliers: Annotated[int, Range(ge=4)] = 40
    abs_pose_min_inlier_ratio: Annotated[float, Range(gt=0.0, lt=1.0)] = 0.4
    min_model_size: Annotated[int, Range(ge=2)] = 3
    forward_motion_retry: bool = True
    num_threads: Annotated[int, Range(ge=1)] = 2
    deterministic: bool = True
    seed: Annotated[int, Range(ge=0)] = 0
    max_points: Annotated[int, Range(ge=0)] = 20000
    pose_covariance: bool = True
    pose_covariance_intrinsics: bool = True
    focal_hold_retry: bool = True

    def __post_init__(self) -> None:
        check_options(self, "sfm options")

    @classmethod
    def from_dict(cls, d: dict) -> "SfmOptions":
        """From a plain dict; unknown keys are an error."""
        return options_from_dict(cls, d, "sfm options")

    @classmethod
    def forward_motion(cls, **overrides) -> "SfmOptions":
        """Thresholds for a camera moving forward (e.g. photos walked along a street or a track).

        The values that register all 29 photos of OpenSfM's Lund set (``../shared/data/SOURCES.md``).
        """
        base = dict(init_max_forward_motion=1.0, init_min_tri_angle_deg=4.0, init_min_num_inliers=50,
                    verify_min_num_inliers=15,
                    abs_pose_min_num_inliers=15, abs_pose_min_inlier_ratio=0.25, refine_distortion=False)
        base.update(overrides)
        return cls(**base)

    def forward_motion_variant(self) -> "SfmOptions":
        """These options with the initial-pair thresholds of :meth:`forward_motion` (the registration thresholds
        stay: lowering them lets look-alike matches place photos wrongly)."""
        return replace(self, init_max_forward_motion=1.0, init_min_tri_angle_deg=min(self.init_min_tri_angle_deg, 4.0),
                       init_min_num_inliers=min(self.init_min_num_inliers, 50), refine_distortion=False)


def similarity_align(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ~ s R src + t`` of (n, 3) point sets, n >= 3 (Umeyama 1991).

    Returns (s, R (3, 3), t (3,), residuals (n,) in ``dst`` units). Points on a line leave the rotation about
    that line free (any solution is returned; the residuals are still the least-squares ones).
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"{src.shape=} and {dst.shape=} must be equal (n, 3) with n >= 3")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    var_s = float(np.mean(np.sum(a * a, axis=1)))
    if var_s <= 0:
        raise ValueError("similarity alignment: the source points coincide")
    U, D, Vt = np.linalg.svd(b.T @ a / len(src))
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_s)
    t = mu_d - s * R @ mu_s
    res = np.linalg.norm(src @ (s * R).T + t - dst, axis=1)
    return s, R, t, res


# --------------------------------------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------------------------------------
@dataclass
class SfmView:
    name: str
    path: Path
    intrinsics: CameraIntrinsics
    cam_from_model: np.ndarray  # (4, 4)
    n_points: int  # 3-D points it observes
    pose_factor: np.ndarray | None = None  # (6, r): its rows of the model's pose covariance factor (.sfm_covariance)
    # (k, r): its camera's refined intrinsics' rows of the same factor, ``intrinsics_params`` naming them
    intrinsics_factor: np.ndarray | None = None
    intrinsics_params: tuple[str, ...] = ()

    @property
    def center_model(self) -> np.ndarray:
        M = self.cam_from_model
        return -M[:3, :3].T @ M[:3, 3]


def _images_json(views: list[SfmView], relative: Callable[[Path], str]) -> list[dict]:
    out = []
    for v in views:
        d = {"name": v.name, "image": relative(v.path), "intrinsics": v.intrinsics.to_dict(),
             "cam_from_model": np.asarray(v.cam_from_model).tolist(), "n_points": v.n_points}
        if v.pose_factor is not None:
            F = np.asarray(v.pose_factor, float)
            d["pose_factor"] = F.tolist()
            d["covariance_rotation_centre"] = (F @ F.T).tolist()
            if v.intrinsics_factor is not None and v.intrinsics_params:
                d["intrinsics_factor"] = {"params": list(v.intrinsics_params),
                                          "factor": np.asarray(v.intrinsics_factor, float).tolist()}
        out.append(d)
    return out


def _points_json(xyz: np.ndarray, rgb: np.ndarray, n_total: int) -> dict:
    return {"xyz": np.round(xyz, 5).tolist(), "rgb": rgb.astype(int).tolist(), "n": int(len(xyz)),
            "n_total": int(n_total)}


@dataclass
class SfmModel:
    """A separate, smaller model: photos COLMAP registered together but could not join to the main model.

    Its frame is a similarity frame of its own (not the main model's): ``cam_from_model`` of its views and its
    points are in it. A photo may be in the main model and in a separate one (COLMAP lets models overlap).
    """

    views: list[SfmView]
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    n_points_total: int
    stats: dict = field(default_factory=dict)

    def to_json(self, relative: Callable[[Path], str] = lambda p: str(p)) -> dict:
        return {"images": _images_json(self.views, relative),
                "points": _points_json(self.points_xyz, self.points_rgb, self.n_points_total), "stats": self.stats}


@dataclass
class SfmResult:
    views: list[SfmView]  # the main (largest) model
    unregistered: list[dict]  # {"name", "reason"[, "model"]}: every photo not in the main model
    points_xyz: np.ndarray  # (n, 3) model frame
    points_rgb: np.ndarray  # (n, 3) uint8
    n_points_total: int
    stats: dict = field(default_factory=dict)
    models: list[SfmModel] = field(default_factory=list)  # the separate models, largest first

    def to_json(self, relative: Callable[[Path], str] = lambda p: str(p), *, prior: dict | None = None) -> dict:
        """The ``reconstruction.json`` object (``docs/intrinsics.md``)."""
        return {
            "images": _images_json(self.views, relative),
            "unregistered": self.unregistered,
            "points": _points_json(self.points_xyz, self.points_rgb, self.n_points_total),
            "models": [m.to_json(relative) for m in self.models],
            "intrinsics_source": "sfm",
            "prior": prior,
            "stats": self.stats,
        }


def _quiet_colmap() -> None:
    try:
        import pycolmap

        pycolmap.logging.minloglevel = 2  # errors only on stderr; progress goes through our logging
    except Exception:  # noqa: BLE001 - older pycolmap without logging control
        pass


def _pipeline_options(opts: SfmOptions, intrinsics_fixed: bool):
    import pycolmap

    po = pycolmap.IncrementalPipelineOptions()
    threads = 1 if opts.deterministic else opts.num_threads
    po.num_threads = threads
    po.random_seed = opts.seed
    po.min_model_size = opts.min_model_size
    po.ba_refine_focal_length = opts.refine_focal and not intrinsics_fixed
    po.ba_refine_principal_point = opts.refine_principal_point and not intrinsics_fixed
    po.ba_refine_extra_params = opts.refine_distortion and not intrinsics_fixed
    m = po.mapper
    m.num_threads = threads
    m.random_seed = opts.seed
    m.init_max_forward_motion = opts.init_max_forward_motion
    m.init_min_tri_angle = opts.init_min_tri_angle_deg
    m.init_min_num_inliers = opts.init_min_num_inliers
    m.abs_pose_min_num_inliers = opts.abs_pose_min_num_inliers
    m.abs_pose_min_inlier_ratio = opts.abs_pose_min_inlier_ratio
    m.abs_pose_refine_focal_length = po.ba_refine_focal_length
    m.abs_pose_refine_extra_params = po.ba_refine_extra_params
    po.triangulation.random_seed = opts.seed
    po.mapper = m
    return po


def _map(db: Path, image_dir: Path, out: Path, opts: SfmOptions, intrinsics_fixed: bool):
    import pycolmap

    out.mkdir(parents=True, exist_ok=True)
    pycolmap.set_random_seed(opts.seed)
    recs = pycolmap.incremental_mapping(db, image_dir, out, options=_pipeline_options(opts, intrinsics_fixed))
    if not recs:
        return None, []
    ordered = sorted(recs.values(), key=lambda r: r.num_reg_images(), reverse=True)
    return ordered[0], ordered[1:]


def _photo_sizes(images: list[Path]) -> tuple[Path, dict[str, tuple[int, int]]]:
    """The one folder of the photos, and each photo's size (name -> (width, height))."""
    from PIL import Image

    if len(images) < 2:
        raise InputError(f"structure from motion needs at least 2 photos, got {len(images)}")
    folders = {p.parent for p in images}
    if len(folders) != 1:
        raise InputError(f"structure from motion: the photos must be in one folder, got {sorted(map(str, folders))}")
    sizes = {}
    for p in images:
        try:
            with Image.open(p) as im:
                sizes[p.name] = im.size
        except OSError as exc:
            raise InputError(f"{p}: cannot read this photo ({exc})") from None
    return folders.pop(), sizes


def _reader_options(opts: SfmOptions, prior: CameraIntrinsics | None, distinct: set[tuple[int, int]],
                    warnings: list[str]):
    """COLMAP's image-reader options: the camera model, and the prior as its initial parameters when the photos
    have one size that the prior fits (scaled to it if of the same aspect); and the prior used, or None."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = opts.camera_model
    prior_used = None
    if prior is not None and len(distinct) == 1:
        w, h = next(iter(distinct))
        pr = prior
        if (pr.width, pr.height) != (w, h):
            if abs(pr.width / pr.height - w / h) < 1e-3:
                pr = pr.scaled(w / pr.width)
            else:
                warnings.append(f"prior is for {prior.width}x{prior.height} but the photos are {w}x{h}; unused")
                pr = None
        if pr is not None:
            params, dropped = colmap_params_from_intrinsics(opts.camera_model, pr)
            if dropped:
                warnings.append(f"the {opts.camera_model} model cannot hold the prior's {', '.join(dropped)}")
            reader.camera_params = ",".join(f"{x:.10g}" for x in params)
            prior_used = pr
    elif prior is not None:
        warnings.append("photos of several sizes: the intrinsics prior is unused")
    return reader, prior_used


def _extract_features(db: Path, image_dir: Path, names: list[str], reader, single: bool, opts: SfmOptions) -> None:
    import pycolmap

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = 1 if opts.deterministic else opts.num_threads
    extraction.max_image_size = opts.max_image_size_px
    extraction.sift.max_num_features = opts.max_num_features
    extraction.sift.peak_threshold = opts.sift_peak_threshold
    extraction.sift.estimate_affine_shape = opts.sift_affine_shape
    extraction.sift.domain_size_pooling = opts.sift_domain_size_pooling
    extraction.use_gpu = False
    pycolmap.extract_features(db, image_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE if single else pycolmap.CameraMode.AUTO,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)


def _matcher(opts: SfmOptions, n_images: int) -> str:
    """``opts.matcher``, with ``auto`` resolved: exhaustive up to ``opts.exhaustive_max_images`` photos."""
    if opts.matcher == "auto":
        return "exhaustive" if n_images <= opts.exhaustive_max_images else "sequential"
    return opts.matcher


def _match_features(db: Path, matcher: str, opts: SfmOptions) -> None:
    """Matches between the photos (``exhaustive`` or ``sequential``), verified geometrically, into ``db``."""
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1 if opts.deterministic else opts.num_threads
    matching.use_gpu = False
    verification = pycolmap.TwoViewGeometryOptions()
    verification.min_num_inliers = opts.verify_min_num_inliers
    verification.ransac.random_seed = opts.seed
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = opts.sequential_overlap
        pairing.num_threads = matching.num_threads
        pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                                  verification_options=verification, device=pycolmap.Device.cpu)


# the refined focal this many times the initial one, or less than its inverse: a model the photos may not determine
FOCAL_RUN_OFF = 1.5
# the model mapped with the focal held is kept at as many photos registered when its mean reprojection error is at
# most this many times the free model's
HELD_ERROR_RATIO = 2.0  # wrong initial focals (0.55-0.65 times, test set): 2.6-3.2; a run-off one (seed 967): 1.45


def _main_focal(rec) -> float:
    """The focal (px) of the camera of a model's first registered image."""
    c = rec.camera(rec.image(next(iter(rec.reg_image_ids()))).camera_id)
    return float(intrinsics_from_colmap(c.model.name, c.width, c.height, c.params).fx)


def _map_focal_held(db: Path, image_dir: Path, tmp: Path, opts: SfmOptions, rec, f_initial: float,
                    progress: Callable[[float, str], None], warnings: list[str],
                    focal_sd: float | None = None) -> tuple | None:
    """Where ``rec``'s refined focal ran off ``f_initial`` (:data:`FOCAL_RUN_OFF`): the model mapped again with
    the focal held at the initial one, if kept (``SfmOptions.focal_hold_retry``): (main model, other models, the
    options, a record of the check); ``(None, None, None, record)`` where the held model is not kept; None where the
    focal did not run off."""
    f_free = _main_focal(rec)
    if max(f_free / f_initial, f_initial / f_free) <= FOCAL_RUN_OFF:
        return None
    held = replace(opts, refine_focal=False)
    log.info("sfm: the focal ran off to %.0f px from %.0f px; mapping again with it held", f_free, f_initial)
    progress(0.85, "incremental mapping (the focal held at the initial one)")
    rec2, others2 = _map(db, image_dir, tmp / "sparse_held", held, False)
    n_free, e_free = rec.num_reg_images(), float(rec.compute_mean_reprojection_error())
    n2 = rec2.num_reg_images() if rec2 is not None else 0
    e2 = float(rec2.compute_mean_reprojection_error()) if n2 else float("inf")
    kept = n2 >= 2 and (n2 > n_free or (n2 == n_free and e2 <= HELD_ERROR_RATIO * e_free))
    record = {"focal_free_px": f_free, "focal_initial_px": f_initial, "n_registered_free": n_free,
              "n_registered_held": n2, "mean_reprojection_error_free_px": e_free,
              "mean_reprojection_error_held_px": e2 if n2 else None, "kept": bool(kept)}
    if kept:
        warnings.append(f"the SfM focal ran off to {f_free:.0f} px from the initial {f_initial:.0f} px (a model its "
                        f"photos do not determine: narrow baselines, few photos); mapped again with the focal held at "
                        f"{f_initial:.0f} px: {n2} photos registered (free: {n_free}), mean reprojection error "
                        f"{e2:.2f} px (free: {e_free:.2f} px). "
                        + (f"The poses' covariance carries that focal's own error (1-sigma {focal_sd:.0f} px, the "
                           f"initial camera's)" if focal_sd else
                           "The poses' covariance is given that focal: its own error is not in it (the initial "
                           "camera states none: a camera profile is taken as exact)"))
        return rec2, others2, held, record
    return None, None, None, record


def _map_or_retry(db: Path, image_dir: Path, tmp: Path, opts: SfmOptions, prior_fixed: bool, n_images: int,
                  progress: Callable[[float, str], None], warnings: list[str]):
    """Incremental mapping; again with the forward-motion thresholds if fewer than half the photos register
    (kept if clearly better). (main model, other models, the options that built them, whether it retried)."""
    used_opts = opts
    rec, others = _map(db, image_dir, tmp / "sparse", opts, prior_fixed)
    n_reg = rec.num_reg_images() if rec is not None else 0
    retried = False
    if opts.forward_motion_retry and n_reg < max(opts.min_model_size, (n_images + 1) // 2):
        fm = opts.forward_motion_variant()
        log.info("sfm: %d/%d photos registered; mapping again with the forward-motion thresholds", n_reg, n_images)
        progress(0.8, "incremental mapping (forward-motion thresholds)")
        rec2, others2 = _map(db, image_dir, tmp / "sparse_fm", fm, prior_fixed)
        retried = True
        n_reg2 = rec2.num_reg_images() if rec2 is not None else 0
        if n_reg2 >= max(n_reg + 2, 1.5 * n_reg):  # clearly better, not one more photo on weaker evidence
            rec, others, used_opts = rec2, others2, fm
            warnings.append(f"only {n_reg}/{n_images} photos registered with the default thresholds; the "
                            f"forward-motion thresholds registered {rec2.num_reg_images()}")
    return rec, others, used_opts, retried


def run_sfm(images: list[Path], *, options: SfmOptions | None = None, prior: CameraIntrinsics | None = None,
            prior_fixed: bool = False, prior_focal_sigma_px: float | None = None, work_dir: Path | None = None,
            progress: Callable[[float, str], None] | None = None) -> SfmResult:
    """Structure from motion on ``images`` (paths in one folder, at least 2).

    ``prior``: initial intrinsics (a camera profile, or an EXIF focal with the principal point at the centre),
    for the photos' size (scaled if the photos have the same aspect but another size); ``prior_fixed``: keep
    it fixed (a trusted calibration) instead of refining it; ``prior_focal_sigma_px``: the prior focal's 1-sigma
    (an EXIF focal's), carried into the poses' covariance where the focal is held at it (not refined:
    ``SfmOptions.refine_focal`` false, or the focal-hold retry); None: a held focal is taken as exact. ``work_dir``: where COLMAP's database goes
    (default: a temporary folder, removed afterwards).
    Raises :class:`InputError` for bad inputs and :class:`StageError` when no model could be built.
    """
    import pycolmap

    opts = options or SfmOptions()
    progress = progress or (lambda f, m="": None)
    images = [Path(p).resolve() for p in images]
    image_dir, sizes = _photo_sizes(images)
    names = [p.name for p in images]
    distinct = set(sizes.values())
    single = opts.single_camera
    if single and len(distinct) > 1:
        log.warning("sfm: photos have %d different sizes; one camera per photo size", len(distinct))
        single = False
    timings: dict[str, float] = {}
    warnings: list[str] = []
    _quiet_colmap()
    pycolmap.set_random_seed(opts.seed)  # RANSAC in matching and mapping

    with tempfile.TemporaryDirectory(prefix="workbench-sfm-", dir=work_dir) as tmp:
        tmp = Path(tmp)
        db = tmp / "database.db"
        reader, prior_used = _reader_options(opts, prior, distinct, warnings)
        if prior_fixed and prior_used is None:
            prior_fixed = False
        focal_sd = None  # the held focal's 1-sigma (px), scaled with the prior to the photos' size
        if prior_used is not None and not prior_fixed and prior_focal_sigma_px:
            focal_sd = float(prior_focal_sigma_px) / prior.fx * prior_used.fx
        t0 = time.perf_counter()
        progress(0.05, "features")
        log.info("sfm: extracting features from %d photos", len(names))
        _extract_features(db, image_dir, names, reader, single, opts)
        timings["features_s"] = time.perf_counter() - t0

        matcher = _matcher(opts, len(names))
        t0 = time.perf_counter()
        progress(0.35, f"matching ({matcher})")
        log.info("sfm: %s matching", matcher)
        _match_features(db, matcher, opts)
        timings["matching_s"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        progress(0.6, "incremental mapping")
        log.info("sfm: incremental mapping")
        rec, others, used_opts, retried = _map_or_retry(db, image_dir, tmp, opts, prior_fixed, len(names), progress,
                                                        warnings)
        timings["mapping_s"] = time.perf_counter() - t0
        if rec is None or rec.num_reg_images() < 2:
            raise StageError(f"structure from motion built no model from the {len(names)} photos in {image_dir}: "
                             f"too few matches between them. Take photos with more overlap (each part of the "
                             f"scene in 3 or more photos, 60-80 % overlap), or use another camera.source")
        focal_check = None
        if opts.focal_hold_retry and prior_used is not None and not prior_fixed and used_opts.refine_focal:
            held = _map_focal_held(db, image_dir, tmp, used_opts, rec, prior_used.fx, progress, warnings, focal_sd)
            if held is not None:
                focal_check = held[3]
                if held[0] is not None:
                    rec, others, used_opts = held[0], held[1], held[2]
            timings["mapping_s"] = time.perf_counter() - t0
        result = _convert(rec, others, db, images, used_opts, prior_fixed, focal_sd)

    n_reg = len(result.views)
    if prior_used is not None and not prior_fixed and used_opts.refine_focal:
        f_sfm = result.views[0].intrinsics.fx
        change = f_sfm / prior_used.fx - 1
        if abs(change) > 0.15:
            warnings.append(f"the SfM focal {f_sfm:.1f} px differs from the initial {prior_used.fx:.1f} px by "
                            f"{100 * change:+.0f} %: check the EXIF tags or the profile (or the photos' geometry: "
                            f"forward motion and narrow baselines leave the focal poorly determined)")
    result.stats.update({
        "n_images": len(names), "n_registered": n_reg, "matcher": matcher, "camera_model": opts.camera_model,
        "single_camera": single, "retried_forward_motion": retried,
        "options": asdict(used_opts), "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "time_s": round(sum(timings.values()), 3),
        "prior": None if prior_used is None else {**prior_used.to_dict(), "fixed": bool(prior_fixed), "focal_sigma_px": focal_sd},
        "focal_held": focal_check,
        "warnings": warnings,
    })
    log.info("sfm: %d/%d photos registered, %d points, mean reprojection error %.2f px, f = %.1f px",
             n_reg, len(names), result.n_points_total, result.stats["mean_reprojection_error_px"],
             result.views[0].intrinsics.fx)
    progress(1.0, "done")
    return result


def _pose_covariance(rec, views: list[SfmView], opts: SfmOptions, intrinsics_fixed: bool,
                     focal_sd: float | None = None) -> dict | None:
    """Each view's ``pose_factor`` set from the model's pose covariance (:mod:`.sfm_covariance`, in place); its
    statistics, or None (not asked for, or not determined: logged, the views keep no factor). A focal held at
    a prior of 1-sigma ``focal_sd`` (px) is an unknown of the covariance with that prior's information."""
    if not opts.pose_covariance:
        return None
    cam = rec.camera(rec.image(next(iter(rec.reg_image_ids()))).camera_id)
    held: dict[str, float] = {}
    if intrinsics_fixed or not opts.pose_covariance_intrinsics:
        params = []
    else:
        params = intrinsic_parameters(cam.model.name, opts.refine_focal, opts.refine_principal_point,
                                      opts.refine_distortion)
        if not opts.refine_focal and focal_sd:
            params, held = ["f"] + params, {"f": float(focal_sd)}
    try:
        pc = reconstruction_pose_covariance(
            rec, {i: rec.image(i).name for i in rec.reg_image_ids()},
            lambda c: intrinsics_from_colmap(c.model.name, c.width, c.height, c.params), params, prior_sd=held)
    except (ValueError, np.linalg.LinAlgError) as exc:
        log.warning("sfm: no pose covariance for a model of %d photos: %s", len(views), exc)
        return {"error": str(exc)}
    for v in views:
        v.pose_factor = pc.factor.get(v.name)
        v.intrinsics_factor = pc.intrinsics_factor.get(v.name)
        v.intrinsics_params = pc.params if v.intrinsics_factor is not None else ()
    return pc.stats


def _model_parts(rec, by_name: dict[str, Path], opts: SfmOptions, intrinsics_fixed: bool = False,
                 focal_sd: float | None = None):
    """Views (sorted by name), points (a fixed-seed subsample of at most ``opts.max_points``), their total and
    the model's statistics (with its pose covariance's: :func:`_pose_covariance`), of one COLMAP
    reconstruction."""
    views = []
    for image_id in sorted(rec.reg_image_ids()):
        im = rec.image(image_id)
        cam = rec.camera(im.camera_id)
        intr = intrinsics_from_colmap(cam.model.name, cam.width, cam.height, cam.params)
        M = np.eye(4)
        M[:3, :] = np.asarray(im.cam_from_world().matrix())
        views.append(SfmView(name=im.name, path=by_name[im.name], intrinsics=intr, cam_from_model=M,
                             n_points=int(im.num_points3D)))
    views.sort(key=lambda v: v.name)
    ids = np.array(sorted(rec.point3D_ids()), dtype=np.int64)
    xyz = np.array([rec.point3D(int(i)).xyz for i in ids]).reshape(-1, 3)
    rgb = np.array([rec.point3D(int(i)).color for i in ids], dtype=np.uint8).reshape(-1, 3)
    track = np.array([rec.point3D(int(i)).track.length() for i in ids]) if len(ids) else np.zeros(0)
    err = np.array([rec.point3D(int(i)).error for i in ids]) if len(ids) else np.zeros(0)
    n_total = len(ids)
    if n_total > opts.max_points:
        keep = np.sort(np.random.default_rng(opts.seed).choice(n_total, opts.max_points, replace=False))
        xyz, rgb = xyz[keep], rgb[keep]
    stats = {
        "n_registered": len(views),
        "n_points": int(n_total), "n_points_written": int(len(xyz)),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()) if n_total else 0.0,
        "median_point_error_px": float(np.median(err)) if n_total else 0.0,
        "mean_track_length": float(track.mean()) if n_total else 0.0,
        "mean_observations_per_image": float(rec.compute_mean_observations_per_reg_image()),
        "pose_covariance": _pose_covariance(rec, views, opts, intrinsics_fixed, focal_sd),
    }
    return views, xyz, rgb, n_total, stats


def _convert(rec, others, db_path: Path, images: list[Path], opts: SfmOptions,
             intrinsics_fixed: bool = False, focal_sd: float | None = None) -> SfmResult:
    """The main model ``rec`` and the separate ``others`` (largest first) as an :class:`SfmResult`, with the
    reason every photo is not in the main model."""
    import pycolmap

    by_name = {p.name: p for p in images}
    views, xyz, rgb, n_total, model_stats = _model_parts(rec, by_name, opts, intrinsics_fixed, focal_sd)
    registered = {v.name for v in views}
    models = []
    covered = set(registered)
    n_dropped = 0
    for r in others:  # largest first; COLMAP lets models overlap: one that adds no photo is of no use
        names_r = {r.image(i).name for i in r.reg_image_ids()}
        if names_r <= covered:
            n_dropped += 1
            continue
        covered |= names_r
        v2, xyz2, rgb2, n2, st2 = _model_parts(r, by_name, opts, intrinsics_fixed, focal_sd)
        models.append(SfmModel(views=v2, points_xyz=xyz2, points_rgb=rgb2, n_points_total=n2, stats=st2))

    # why were the others left out?
    in_other: dict[str, int] = {}  # photo -> index of the largest separate model that has it
    for k, m in enumerate(models):
        for v in m.views:
            in_other.setdefault(v.name, k)
    db = pycolmap.Database.open(db_path)
    try:
        id_of = {im.name: im.image_id for im in db.read_all_images()}
        n_kp = {n: db.num_keypoints_for_image(i) for n, i in id_of.items()}
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
        inl_to_model: dict[str, int] = {n: 0 for n in id_of}
        name_of = {i: n for n, i in id_of.items()}
        for pid, k in zip(pair_ids, inliers):
            a, b = pycolmap.pair_id_to_image_pair(pid)
            na, nb = name_of.get(a), name_of.get(b)
            if na is None or nb is None:
                continue
            if nb in registered:
                inl_to_model[na] += int(k)
            if na in registered:
                inl_to_model[nb] += int(k)
    finally:
        db.close()
    unregistered = []
    for p in images:
        if p.name in registered:
            continue
        entry = {"name": p.name}
        if n_kp.get(p.name, 0) == 0:
            reason = "no features found (blank, blurred or tiny photo)"
        elif p.name in in_other:
            k = in_other[p.name]
            reason = (f"registered only in a separate model of {len(models[k].views)} photos (models[{k}]; no "
                      f"overlap with the main one: too few points seen in 3 or more photos across them)")
            entry["model"] = k
        else:
            reason = (f"too few verified matches with the registered photos ({inl_to_model.get(p.name, 0)} inlier "
                      f"matches in all; {n_kp.get(p.name, 0)} features)")
        entry["reason"] = reason
        unregistered.append(entry)

    cams = {}
    for cid, cam in rec.cameras.items():
        cams[str(cid)] = {"model": cam.model.name, "params_colmap": [float(x) for x in cam.params],
                          "width": int(cam.width), "height": int(cam.height)}
    stats = {k: v for k, v in model_stats.items() if k != "n_registered"}
    stats.update({"n_models": 1 + len(models), "n_in_separate_models": len(set(in_other) - registered),
                  "n_models_dropped_as_contained": n_dropped,
                  "separate_models": [m.stats["n_registered"] for m in models], "colmap_cameras": cams})
    return SfmResult(views=views, unregistered=unregistered, points_xyz=xyz, points_rgb=rgb, n_points_total=n_total,
                     stats=stats, models=models)
