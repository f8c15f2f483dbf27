"""Points found in one photo of a panorama set, carried into the other photos that see them.

Photos taken from one place (the panorama route) differ by a rotation only, so in undistorted pixels two
of them are related by one homography ``K_b R K_a^-1`` that holds for every scene point, near or far.
It is estimated from the photos' own SIFT matches (RANSAC), and kept only if it explains them to a
fraction of a pixel. A point found in photo a is then placed in photo b exactly (no planar-face
assumption), which recovers carriages that SIFT found in one photo but not in its neighbour.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from .assign import PointObservation
from .match import PhotoFeatures, apply_h

log = logging.getLogger(__name__)

MIN_INLIERS = 60
MAX_MEDIAN_RESIDUAL_PX = 0.6


def photo_homography(a: PhotoFeatures, b: PhotoFeatures) -> tuple[np.ndarray, dict] | None:
    """``b_from_a`` (3, 3) between the undistorted photos, or None if they do not overlap or are not related
    by a homography (e.g. taken from different places)."""
    if len(a.keypoints) < MIN_INLIERS or len(b.keypoints) < MIN_INLIERS:
        return None
    flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    knn = flann.knnMatch(a.descriptors, b.descriptors, k=2)
    good = [p[0] for p in knn if len(p) == 2 and p[0].distance < 0.75 * p[1].distance]
    if len(good) < MIN_INLIERS:
        return None
    pa = a.keypoints[[m.queryIdx for m in good]]
    pb = b.keypoints[[m.trainIdx for m in good]]
    H, mask = cv2.findHomography(pa, pb, cv2.USAC_MAGSAC, 1.0, maxIters=10000, confidence=0.9999)
    if H is None:
        return None
    inl = mask.ravel() > 0
    res = np.linalg.norm(apply_h(H, pa[inl]) - pb[inl], axis=1)
    info = {"matches": len(good), "inliers": int(inl.sum()), "median_residual_px": float(np.median(res))}
    if inl.sum() < MIN_INLIERS or info["median_residual_px"] > MAX_MEDIAN_RESIDUAL_PX:
        return None
    return H, info


class PairHomographies:
    """The homographies between every two photos of a set (:func:`photo_homography`), pair after pair in the
    photos' order: ``advance`` computes the next pairs whose two photos are both given, so the stage can
    compute them while later photos are still being matched (always in the same order: the FLANN matcher's
    trees are randomised, and the same order gives the same trees)."""

    def __init__(self, names: list[str]) -> None:
        self.pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
        self.k = 0
        self.Hs: dict[tuple[str, str], np.ndarray] = {}
        self.stats: dict[str, dict] = {}

    def advance(self, photos: dict[str, PhotoFeatures]) -> None:
        while self.k < len(self.pairs) and all(n in photos for n in self.pairs[self.k]):
            a, b = self.pairs[self.k]
            self.k += 1
            res = photo_homography(photos[a], photos[b])
            if res is None:
                continue
            H, info = res
            self.Hs[(b, a)] = H
            self.Hs[(a, b)] = np.linalg.inv(H)
            self.stats[f"{a}->{b}"] = info

    @property
    def complete(self) -> bool:
        return self.k == len(self.pairs)


def carry(observations: dict[str, list[PointObservation]], photos: dict[str, PhotoFeatures],
          margin_px: float = 2.0, pairs: PairHomographies | None = None) -> tuple[dict[str, list[PointObservation]], dict]:
    """Each photo's observations, completed with the points found in the other photos of the set.

    A point already found in a photo keeps its own observation; a carried one gets 0.9 x the confidence
    and 0.3 px more sigma of its source; when several photos could supply it, the most confident does.
    ``pairs``: the photos' homographies computed so far (:class:`PairHomographies` of these photos, in
    this order); the rest are computed here.
    """
    names = list(photos)
    if pairs is None:
        pairs = PairHomographies(names)
    pairs.advance(photos)
    Hs, stats = pairs.Hs, pairs.stats
    out = {n: list(observations.get(n, [])) for n in names}
    n_carried = 0
    for b in names:
        have = {(o.carriage, o.point) for o in out[b]}
        best: dict[tuple[str, str], PointObservation] = {}
        pb = photos[b]
        for a in names:
            H = Hs.get((b, a))
            if H is None:
                continue
            for o in observations.get(a, []):
                k = (o.carriage, o.point)
                if k in have:
                    continue
                uv_b = pb.distort_px(apply_h(H, photos[a].undistort_px(np.array([o.uv]))))[0]
                if not np.all(np.isfinite(uv_b)) or not pb.intrinsics.in_image(uv_b[None], margin_px)[0]:
                    continue
                c = PointObservation(o.carriage, o.point, b, (float(uv_b[0]), float(uv_b[1])),
                                     round(0.9 * o.confidence, 3), round(o.sigma_px + 0.3, 2), o.face, "carried")
                if k not in best or c.confidence > best[k].confidence:
                    best[k] = c
        out[b].extend(best.values())
        n_carried += len(best)
    return out, {"pairs": stats, "n_carried": n_carried}
