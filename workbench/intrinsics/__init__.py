"""Intrinsics: where a run's camera model comes from.

Four routes, recorded in the outputs as ``intrinsics_source`` (see ``docs/intrinsics.md``):

* ``calibrated``: a camera profile made before the incident from chessboard photos (:mod:`.calibrate`);
* ``exif``: a focal-length prior from the photos' EXIF tags (:mod:`workbench.files.exif`);
* ``sfm``: intrinsics, distortion and every camera's pose from multi-view structure from motion (:mod:`.sfm`,
  the ``sfm`` stage in :mod:`.stage`);
* ``fallback``: a simplified pinhole whose focal the pose solver estimates.

Importing this package imports neither OpenCV nor pycolmap; the submodules do, on use.
"""

from __future__ import annotations

ROUTES = ("calibrated", "exif", "sfm", "fallback")
