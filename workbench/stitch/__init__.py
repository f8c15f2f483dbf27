"""Panorama stitching (Brown and Lowe's automatic panorama stitching, on OpenCV's stitching detail API).

* :mod:`.register`: SIFT features, pairwise matching with RANSAC homographies and Brown and Lowe's
  confidence test, the largest connected set, rotation and focal estimation, a rotation-only bundle
  adjustment with the lens model (fixed when calibrated, focal and k1 estimated otherwise), wave
  correction, and the parallax check.
* :mod:`.compose`: warping at full resolution through the exact :class:`~workbench.core.panorama.PanoramaModel`
  (one resampling from the distorted photo), gain compensation, seam finding, multi-band blending.
* :mod:`.stitcher`: :func:`stitch_photos`, the library entry point.
* :mod:`.stage`: the ``stitch`` stage of ``workbench run``.

Method and file format: ``docs/stitching.md``.
"""

from .stitcher import StitchOptions, StitchResult, stitch_photos

__all__ = ["StitchOptions", "StitchResult", "stitch_photos"]
