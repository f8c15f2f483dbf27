"""The pinned environment: OpenCV's stitching detail API works from Python (it did not with 5.0.0)."""

from pathlib import Path

import cv2
import numpy as np
import pytest

WEIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "stitching" / "opencv_weir"


def test_opencv_major_version_pinned_below_5():
    assert int(cv2.__version__.split(".")[0]) == 4, cv2.__version__


@pytest.mark.skipif(not WEIR.is_dir(), reason=f"real test data not found at {WEIR}")
def test_stitching_detail_bundle_adjuster_runs_from_python():
    imgs = [cv2.imread(str(WEIR / f"weir_{i}.jpg")) for i in (1, 2, 3)]
    imgs = [cv2.resize(im, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA) for im in imgs]
    sift = cv2.SIFT_create()
    feats = [cv2.detail.computeImageFeatures2(sift, im) for im in imgs]
    matcher = cv2.detail_BestOf2NearestMatcher(False, 0.3)
    pairs = matcher.apply2(feats)
    matcher.collectGarbage()
    ok, cams = cv2.detail_HomographyBasedEstimator().apply(feats, pairs, None)
    assert ok
    for c in cams:
        c.R = c.R.astype(np.float32)
    ba = cv2.detail_BundleAdjusterRay()
    ba.setConfThresh(1.0)
    ok, cams = ba.apply(feats, pairs, cams)
    assert ok
    focals = [c.focal for c in cams]
    assert all(np.isfinite(focals)) and min(focals) > 100
