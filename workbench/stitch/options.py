"""The options and the result of :func:`~workbench.stitch.stitcher.stitch_photos` (docs/stitching.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np

from ..core.panorama import PanoramaModel

__all__ = ["ProgressFn", "StitchOptions", "StitchResult"]

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
    max_output_megapix: float = 100.0  # larger panoramas are composed at a reduced scale (memory: docs/stitching.md)
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
    """The panorama model, the composed image, the photos left out and why, and the run's figures."""

    model: PanoramaModel | None  # None when fewer than two photos could be registered
    image: np.ndarray | None  # (height, width, 3) uint8 BGR, or None when not composed
    rejected: list[dict] = field(default_factory=list)  # {"name", "reason"}
    intrinsics_source: str = "fallback"
    parallax: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
