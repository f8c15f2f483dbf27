"""Panorama stitching (Brown and Lowe's automatic panorama stitching, on OpenCV's stitching detail API).

* :mod:`.register`: SIFT features, pairwise matching with RANSAC homographies and Brown and Lowe's
  confidence test, the largest connected set, rotation and focal estimation, wave correction.
* :mod:`.photo_matching`: every photo read and described, every pair matched (in threads), the connected set.
* :mod:`.bundle` (:mod:`.bundle_problem`: its residuals and Jacobian): the rotation-only bundle adjustment with
  the lens model (fixed when calibrated, focal, k1, k2 and principal point estimated otherwise).
* :mod:`.compose`: warping at full resolution through the exact :class:`~workbench.core.panorama.PanoramaModel`
  (one resampling from the distorted photo), gain compensation, seam finding, multi-band blending.
* :mod:`.stitcher`: :func:`stitch_photos`, the library entry point (with the parallax check);
  :mod:`.options`: its options and result.
* :mod:`.stage`: the ``stitch`` stage of ``workbench run``.

Method and file format: ``docs/stitching.md``.
"""

from .options import StitchOptions, StitchResult

__all__ = ["StitchOptions", "StitchResult", "stitch_photos"]


def __getattr__(name: str):
    """``stitch_photos`` imported on first use: the stage's prefetch (:mod:`.stage`) starts describing the photos
    before the bundle adjustment and the composition are imported."""
    if name == "stitch_photos":
        from .stitcher import stitch_photos

        return stitch_photos
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
