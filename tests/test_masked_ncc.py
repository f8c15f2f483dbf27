"""The pose search's masked correlation (``search.masked_ncc``) against OpenCV's masked ``TM_CCOEFF_NORMED``, which it
replaces, and against the definition summed in float64."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from workbench.correspond.search import MIN_STD, masked_ncc


def _definition(img: np.ndarray, tmpl: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """The zero-mean normalised correlation over the mask at every shift, summed in float64 (nan where flat)."""
    h, w = tmpl.shape
    a = tmpl.astype(np.float64)[inside]
    a = a - a.mean()
    out = np.full((img.shape[0] - h + 1, img.shape[1] - w + 1), np.nan)
    for y in range(out.shape[0]):
        for x in range(out.shape[1]):
            b = img[y:y + h, x:x + w].astype(np.float64)[inside]
            b = b - b.mean()
            den = np.sqrt((a * a).sum() * (b * b).sum())
            if b.std() >= MIN_STD:
                out[y, x] = (a * b).sum() / den
    return out


def _tile(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A tile's mask as the search makes it: a warped third of a face, eroded off its edges."""
    quad = np.array([[rng.uniform(0, 4), rng.uniform(0, 3)], [w - rng.uniform(1, 5), rng.uniform(0, 3)],
                     [w - rng.uniform(1, 4), h - rng.uniform(1, 3)], [rng.uniform(0, 5), h - rng.uniform(1, 3)]])
    m = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(m, np.round(quad).astype(np.int32), 1)
    return cv2.erode(m, np.ones((3, 3), np.uint8)) > 0


@pytest.mark.parametrize("seed", range(6))
def test_masked_ncc_is_opencvs_masked_correlation(seed):
    rng = np.random.default_rng(seed)
    h, w, r = int(rng.integers(10, 30)), int(rng.integers(20, 60)), int(rng.integers(3, 14))
    # a photo with texture, blurred as the search blurs it, centred on its mean as the search holds it
    photo = cv2.GaussianBlur(rng.uniform(0, 255, (h + 2 * r, 2 * w + 2 * r)).astype(np.float32), (0, 0), 1.5)
    # the search area's right part past the photo's border (the constant padding, and flat where the tile at the
    # last r + 1 shifts lies wholly on it) and a strip of its top
    photo[:, w + r:] = photo[: r // 2] = photo.mean()
    photo -= np.float32(photo.mean())
    inside = _tile(rng, h, w)
    tmpl = np.where(inside, photo[r:r + h, r:r + w] + rng.normal(0, 4, (h, w)).astype(np.float32), 0)
    got = masked_ncc(photo, photo * photo, tmpl.astype(np.float32), inside)
    want = _definition(photo, tmpl, inside)
    assert got.shape == want.shape == (2 * r + 1, w + 2 * r + 1)
    ok = np.isfinite(want)
    assert 0.3 < ok.mean() < 0.99
    assert np.abs(got[ok] - want[ok]).max() < 2e-4
    assert np.all(got[~ok] == 0)  # a flat window correlates with nothing
    assert got[r, r] == got.max() and got[r, r] > 0.9  # the template's own place
    ref = cv2.matchTemplate(photo, tmpl.astype(np.float32), cv2.TM_CCOEFF_NORMED,
                            mask=inside.astype(np.uint8) * 255)
    both = ok & np.isfinite(ref)
    assert np.abs(got[both] - ref[both]).max() < 2e-4


def test_masked_ncc_refuses_a_flat_template():
    photo = np.random.default_rng(0).normal(0, 20, (40, 60)).astype(np.float32)
    inside = np.ones((10, 20), bool)
    assert masked_ncc(photo, photo * photo, np.full((10, 20), 90.0, np.float32), inside) is None
    flat_inside = np.full((10, 20), 90.0, np.float32)
    flat_inside[0] = 250.0  # the contrast lies outside the mask
    inside[0] = False
    assert masked_ncc(photo, photo * photo, flat_inside, inside) is None
