"""Registration: features, pairwise matching, the connected set, the focal from the homographies, the
starting rotations and wave correction; the bundle adjustment between them is in :mod:`.bundle`.

Brown and Lowe, "Automatic panoramic image stitching using invariant features" (IJCV 2007), with the
lens model made explicit: every match is compared in the photos as on disk (distorted pixels, full
resolution), through the photo's :class:`~workbench.core.camera.CameraIntrinsics`. Rotations are
``cam_from_pano`` (3, 3) matrices (``docs/conventions.md``: x right, y down, z forward).

Pixels: keypoints are detected on a reduced copy of each photo (``work`` scale, about 0.6 MP) and stored
as full-resolution pixel coordinates (pixel centres, ``c_full = (c_work + 0.5) / s - 0.5``). Residuals of
the bundle adjustment are multiplied by the work scale, so its robust loss acts in work pixels.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..core.geometry import orthonormal

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------------------
# features
# ----------------------------------------------------------------------------------------------------------
@dataclass
class PhotoFeatures:
    """SIFT keypoints of one photo: ``keypoints`` (N, 2) full-resolution pixels, ``descriptors`` (N, 128)."""

    name: str
    width: int  # full resolution, px
    height: int
    work_scale: float  # work pixels per full-resolution pixel
    keypoints: np.ndarray
    descriptors: np.ndarray


def detect_features(name: str, gray_work: np.ndarray, full_size: tuple[int, int], *, max_features: int = 4000,
                    contrast_threshold: float = 0.04, half: bool = False) -> PhotoFeatures:
    """SIFT on a reduced grey image (h_w, w_w) uint8 of a photo whose full size is ``full_size`` = (w, h) px.

    ``half``: describe a half-size copy (SIFT's first octave, which doubles its input, then works at the
    work resolution itself: about 4 times faster, keypoints localised at the work resolution's octave 0).
    SIFT's doubling keeps pixel centres (``enable_precise_upscale``).
    """
    w, h = full_size
    img = gray_work
    if half:
        img = cv2.resize(gray_work, ((gray_work.shape[1] + 1) // 2, (gray_work.shape[0] + 1) // 2),
                         interpolation=cv2.INTER_AREA)
    hi, wi = img.shape[:2]
    sx, sy = wi / w, hi / h
    sift = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=contrast_threshold, enable_precise_upscale=True)
    kps, desc = sift.detectAndCompute(img, None)
    ws = (gray_work.shape[1] / w + gray_work.shape[0] / h) / 2  # the work scale (residuals are in work pixels)
    if desc is None or len(kps) == 0:
        return PhotoFeatures(name, w, h, ws, np.zeros((0, 2)), np.zeros((0, 128), np.float32))
    pts = cv2.KeyPoint_convert(kps).astype(float)  # (the keypoints' float32 coordinates, as k.pt gives them)
    pts[:, 0] = (pts[:, 0] + 0.5) / sx - 0.5
    pts[:, 1] = (pts[:, 1] + 0.5) / sy - 0.5
    return PhotoFeatures(name, w, h, ws, pts, desc.astype(np.float32, copy=False))


# ----------------------------------------------------------------------------------------------------------
# pairwise matching
# ----------------------------------------------------------------------------------------------------------
@dataclass
class PairMatch:
    """Matches of photos ``i < j``: inlier keypoint indices (n,) into each photo, and the confidence test."""

    i: int
    j: int
    n_matches: int
    n_inliers: int
    confidence: float  # n_inliers / (8 + 0.3 n_matches) (Brown and Lowe); > 1 means the pair is accepted
    H: np.ndarray | None  # homography j_from_i in the linearised pixels used for matching
    idx_i: np.ndarray = field(repr=False)
    idx_j: np.ndarray = field(repr=False)
    # the inliers' pixels (full resolution, as on disk) for the bundle adjustment: photo i's keypoints and
    # photo j's matching points refined to sub-pixel precision (:func:`refine_matches`); None: the keypoints
    x_i: np.ndarray | None = field(default=None, repr=False)
    x_j: np.ndarray | None = field(default=None, repr=False)


def build_index(f: PhotoFeatures, trees: int = 4) -> "cv2.flann_Index | None":
    """A FLANN k-d forest (``trees`` trees) over a photo's descriptors, built once and searched by every pair."""
    if len(f.descriptors) < 8:
        return None
    return cv2.flann_Index(f.descriptors, {"algorithm": 1, "trees": int(trees)})


def unique_sorted(a: np.ndarray) -> np.ndarray:
    """``np.unique(a)`` of a 1-D array, or ``np.unique(a, axis=0)`` of an (n, k) one: the distinct values (rows,
    in lexicographic order), sorted. Without NumPy's ``np.unique``, which imports ``numpy.ma`` (10-16 ms of a
    fresh process's CPU) to ask whether the array is masked."""
    a = np.asarray(a)
    if a.ndim == 1:
        s = np.sort(a)
        keep = np.ones(len(s), dtype=bool)
        keep[1:] = s[1:] != s[:-1]
        return s[keep]
    s = a[np.lexsort(a.T[::-1])] if len(a) else a  # lexsort's last key is the primary one: column 0
    keep = np.ones(len(s), dtype=bool)
    keep[1:] = np.any(s[1:] != s[:-1], axis=1)
    return s[keep]


def median(values) -> float:
    """``float(np.median(values))`` of numbers (any shape, flattened): the middle value, or the mean of the two middle
    ones, NaN if any is NaN. Without ``np.median``, which imports ``numpy.ma`` for its NaN check."""
    a = np.sort(np.asarray(values, dtype=float).ravel())
    n = len(a)
    if n == 0 or np.isnan(a[-1]):  # (np.sort puts NaNs last)
        return float("nan")
    return float(a[n // 2]) if n % 2 else float((a[n // 2 - 1] + a[n // 2]) / 2.0)


def percentile(values, q: float) -> float:
    """``float(np.percentile(values, q))`` (its default, linear interpolation, with its arithmetic) of numbers (any
    shape, flattened), ``q`` in [0, 100]; NaN if any is NaN. Without ``np.percentile``, which imports ``numpy.ma``."""
    a = np.sort(np.asarray(values, dtype=float).ravel())
    n = len(a)
    if n == 0 or np.isnan(a[-1]):
        return float("nan")
    v = (n - 1) * (float(q) / 100.0)  # the virtual index
    if v >= n - 1:
        return float(a[-1])
    lo = np.floor(v)
    g = v - lo
    x0, x1 = a[int(lo)], a[int(lo) + 1]
    d = x1 - x0
    return float(x1 - d * (1.0 - g)) if g >= 0.5 else float(x0 + d * g)


def _ratio_matches(index: "cv2.flann_Index", query: np.ndarray, ratio: float, checks: int) -> tuple[np.ndarray, np.ndarray]:
    """(query indices, train indices) of the query descriptors whose nearest neighbour passes Lowe's ratio test."""
    ind, dist = index.knnSearch(query, 2, params={"checks": checks})
    good = dist[:, 0] < (ratio * ratio) * dist[:, 1]  # FLANN's L2 distances are squared
    return np.flatnonzero(good), ind[good, 0].astype(int)


def match_pair(i: int, j: int, fi: PhotoFeatures, fj: PhotoFeatures, lin_i: np.ndarray, lin_j: np.ndarray, *,
               ratio: float = 0.75, ransac_work_px: float = 3.0, seed: int = 0, index_i=None, index_j=None,
               checks: int = 16) -> PairMatch:
    """Ratio-test matches, both ways (union), then a RANSAC homography on ``lin_*`` (linearised keypoints (N, 2) px).

    ``index_i``, ``index_j``: :func:`build_index` of each photo (built here when not given).
    """
    empty = PairMatch(i, j, 0, 0, 0.0, None, np.zeros(0, int), np.zeros(0, int))
    if len(fi.descriptors) < 8 or len(fj.descriptors) < 8:
        return empty
    index_i = build_index(fi) if index_i is None else index_i
    index_j = build_index(fj) if index_j is None else index_j
    qi, tj = _ratio_matches(index_j, fi.descriptors, ratio, checks)  # i -> j
    qj, ti = _ratio_matches(index_i, fj.descriptors, ratio, checks)  # j -> i
    both = np.concatenate([np.column_stack([qi, tj]), np.column_stack([ti, qj])])
    idx = unique_sorted(both) if len(both) else both.reshape(0, 2)
    if len(idx) < 8:
        return PairMatch(i, j, len(idx), 0, 0.0, None, np.zeros(0, int), np.zeros(0, int))
    src, dst = lin_i[idx[:, 0]], lin_j[idx[:, 1]]
    thresh = ransac_work_px / min(fi.work_scale, fj.work_scale)
    cv2.setRNGSeed(seed)
    H, mask = cv2.findHomography(src, dst, cv2.USAC_MAGSAC, thresh, maxIters=4000, confidence=0.999)
    if H is None or mask is None:
        return PairMatch(i, j, len(idx), 0, 0.0, None, np.zeros(0, int), np.zeros(0, int))
    inl = mask.ravel().astype(bool)
    n_in = int(inl.sum())
    conf = n_in / (8.0 + 0.3 * len(idx))
    return PairMatch(i, j, len(idx), n_in, conf, H, idx[inl, 0], idx[inl, 1])


def homography_jacobian(H: np.ndarray, x: np.ndarray) -> np.ndarray:
    """d(H x)/dx (n, 2, 2) of the homography ``H`` (3, 3) at pixels ``x`` (n, 2)."""
    p = np.column_stack([x, np.ones(len(x))]) @ H.T  # (n, 3)
    w = p[:, 2]
    J = np.empty((len(x), 2, 2))
    for r in range(2):
        J[:, r, :] = (H[r, :2][None, :] * w[:, None] - p[:, r:r + 1] * H[2, :2][None, :]) / (w * w)[:, None]
    return J


def smooth_for_refinement(gray: np.ndarray) -> np.ndarray:
    """The work-resolution grey photo (h, w) uint8 as :func:`refine_matches` wants it: float32, Gaussian sigma 0.8."""
    return cv2.GaussianBlur(gray, (5, 5), 0.8).astype(np.float32)


def refine_matches(gray_a: np.ndarray, gray_b: np.ndarray, xa: np.ndarray, xb: np.ndarray, size_a: tuple[int, int],
                   size_b: tuple[int, int], local_b_from_a: np.ndarray, *, radius: int = 6, iterations: int = 8,
                   max_shift_work_px: float = 1.5, min_ncc: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel refinement of matches ``xa`` -> ``xb`` (n, 2) full-resolution pixels, by Lucas-Kanade.

    ``gray_a``, ``gray_b``: the photos at work resolution, :func:`smooth_for_refinement` (h, w) float32, of
    full sizes ``size_*`` = (w, h).
    ``local_b_from_a`` (n, 2, 2): the local linear map from photo a to photo b at each match (full-resolution
    pixels, e.g. the homography's Jacobian), which shapes the template: a (2 radius + 1)^2 patch of photo b's
    pixel grid around ``xb`` seen in photo a (bilinear). The translation of ``xb`` that best aligns photo b
    with it (intensities normalised to zero mean and unit variance: gains differ between photos) is found
    by inverse-compositional Gauss-Newton (the template's gradients, one resampling per iteration).
    SIFT's keypoints are localised to about 0.3 px; this brings the matches to a few hundredths of a pixel
    on textured patches (``tests/test_stitch.py``). Returns (refined xb (n, 2) full-resolution pixels, ok (n,)
    bool: well conditioned, moved less than ``max_shift_work_px``, normalised cross-correlation > ``min_ncc``).
    """
    n = len(xa)
    if n == 0:
        return xb.copy(), np.zeros(0, bool)
    sa = np.array([gray_a.shape[1] / size_a[0], gray_a.shape[0] / size_a[1]])
    sb = np.array([gray_b.shape[1] / size_b[0], gray_b.shape[0] / size_b[1]])
    pa = (xa + 0.5) * sa - 0.5  # work pixels
    pb = (xb + 0.5) * sb - 0.5
    A = local_b_from_a * sb[None, :, None] / sa[None, None, :]  # work px of b per work px of a
    ok = np.isfinite(A).all(axis=(1, 2)) & (np.abs(np.linalg.det(np.where(np.isfinite(A), A, 0.0))) > 1e-6)
    Ainv = np.linalg.inv(np.where(ok[:, None, None], A, np.eye(2)))
    side = 2 * radius + 1
    g1 = np.arange(-radius, radius + 1, dtype=np.float64)
    gy, gx = (v.ravel() for v in np.meshgrid(g1, g1, indexing="ij"))  # (P,) offsets in photo b
    P = len(gx)

    def sample(img: np.ndarray, qx: np.ndarray, qy: np.ndarray) -> np.ndarray:  # (m, P) pixels -> (m, P) float32
        m = len(qx)
        return cv2.remap(img, qx.reshape(m * side, side).astype(np.float32), qy.reshape(m * side, side).astype(
            np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(m, P)

    def normalise(v: np.ndarray) -> np.ndarray:
        v = v - v.mean(axis=1, keepdims=True)
        return v / (np.sqrt(np.mean(v * v, axis=1, keepdims=True)) + 1e-6)

    # the template: photo b's grid around xb seen in photo a through the local linear map
    qax = pa[:, 0, None] + Ainv[:, 0, 0, None] * gx[None] + Ainv[:, 0, 1, None] * gy[None]
    qay = pa[:, 1, None] + Ainv[:, 1, 0, None] * gx[None] + Ainv[:, 1, 1, None] * gy[None]
    T = normalise(sample(gray_a, qax, qay))
    Ty, Tx = np.gradient(T.reshape(n, side, side), axis=(1, 2))
    Jx, Jy = Tx.reshape(n, P), Ty.reshape(n, P)
    a11, a12, a22 = ((u * v).sum(1, dtype=np.float64) for u, v in ((Jx, Jx), (Jx, Jy), (Jy, Jy)))
    det = a11 * a22 - a12 * a12
    ok &= det > 1e-3 * (a11 + a22) ** 2 + 1e-9  # an edge or a flat patch locates nothing along it
    det = np.where(ok, det, 1.0)
    d = np.zeros((n, 2))
    act = np.flatnonzero(ok)  # Gauss-Newton on the matches that have not converged yet
    for _ in range(iterations):
        if len(act) == 0:
            break
        e = normalise(sample(gray_b, pb[act, 0, None] + d[act, 0, None] + gx[None],
                             pb[act, 1, None] + d[act, 1, None] + gy[None])) - T[act]
        b1, b2 = (Jx[act] * e).sum(1, dtype=np.float64), (Jy[act] * e).sum(1, dtype=np.float64)
        dt = det[act]
        step = np.column_stack([(a22[act] * b1 - a12[act] * b2) / dt, (a11[act] * b2 - a12[act] * b1) / dt])
        d[act] -= np.clip(step, -1.0, 1.0)
        act = act[np.max(np.abs(step), axis=1) >= 2e-3]
    qbx, qby = pb[:, 0, None] + d[:, 0, None] + gx[None], pb[:, 1, None] + d[:, 1, None] + gy[None]
    ncc = np.mean(normalise(sample(gray_b, qbx, qby)) * T, axis=1)
    inside = ((qbx.min(1) >= 0) & (qby.min(1) >= 0) & (qbx.max(1) <= gray_b.shape[1] - 1)
              & (qby.max(1) <= gray_b.shape[0] - 1) & (qax.min(1) >= 0) & (qay.min(1) >= 0)
              & (qax.max(1) <= gray_a.shape[1] - 1) & (qay.max(1) <= gray_a.shape[0] - 1))
    ok &= inside & (np.linalg.norm(d, axis=1) < max_shift_work_px) & (ncc > min_ncc)
    return (pb + d + 0.5) / sb - 0.5, ok


def largest_component(n: int, pairs: list[PairMatch], conf_thresh: float) -> list[int]:
    """Indices of the largest set of photos connected by accepted pairs (ties: more inliers)."""
    parent = list(range(n))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for p in pairs:
        if p.confidence > conf_thresh:
            parent[find(p.i)] = find(p.j)
    comps: dict[int, list[int]] = {}
    for k in range(n):
        comps.setdefault(find(k), []).append(k)
    weight = {r: sum(p.n_inliers for p in pairs if p.confidence > conf_thresh and find(p.i) == r) for r in comps}
    best = max(comps, key=lambda r: (len(comps[r]), weight[r]))
    return sorted(comps[best])


# ----------------------------------------------------------------------------------------------------------
# initial rotations and focal
# ----------------------------------------------------------------------------------------------------------
def focal_from_homographies(pairs: list[PairMatch], centres: dict[int, tuple[float, float]]) -> float | None:
    """Median focal (px) from accepted homographies (Szeliski's formulas, ``cv2.detail.focalsFromHomography``)."""
    fs = []
    for p in pairs:
        if p.H is None:
            continue
        ci, cj = centres[p.i], centres[p.j]
        Ti = np.array([[1, 0, ci[0]], [0, 1, ci[1]], [0, 0, 1.0]])
        Tj_inv = np.array([[1, 0, -cj[0]], [0, 1, -cj[1]], [0, 0, 1.0]])
        Hc = Tj_inv @ p.H @ Ti  # homography between centred coordinates
        f0, f1 = _focals_from_homography(Hc / Hc[2, 2])
        if f0 and f1:
            fs.append(np.sqrt(f0 * f1))
    return median(fs) if fs else None


def _focal_candidate(d1: float, d2: float, v1: float, v2: float) -> float | None:
    if v1 < v2:
        v1, v2 = v2, v1
    if v1 > 0 and v2 > 0:
        return float(np.sqrt(v1 if abs(d1) > abs(d2) else v2))
    return float(np.sqrt(v1)) if v1 > 0 else None


def _focals_from_homography(H: np.ndarray) -> tuple[float | None, float | None]:
    """Focals (f_i, f_j) px of the two photos of a homography ``j_from_i`` between centred pixel coordinates.

    For H = K_j R K_i^-1 with K = diag(f, f, 1), the orthogonality of R's columns / rows gives two
    candidate squares for each focal (Szeliski and Shum 1997); the better-conditioned one is taken.
    """
    h = H.ravel()
    with np.errstate(divide="ignore", invalid="ignore"):
        d1, d2 = h[6] * h[7], (h[7] - h[6]) * (h[7] + h[6])
        fj = _focal_candidate(d1, d2, -(h[0] * h[1] + h[3] * h[4]) / d1,
                              (h[0] ** 2 + h[3] ** 2 - h[1] ** 2 - h[4] ** 2) / d2)
        d1, d2 = h[0] * h[3] + h[1] * h[4], h[0] ** 2 + h[1] ** 2 - h[3] ** 2 - h[4] ** 2
        fi = _focal_candidate(d1, d2, -h[2] * h[5] / d1, (h[5] ** 2 - h[2] ** 2) / d2)
    ok = [f if f is not None and np.isfinite(f) else None for f in (fi, fj)]
    return ok[0], ok[1]


def rotations_from_homographies(kept: list[int], pairs: list[PairMatch], Ks: dict[int, np.ndarray]
                                ) -> dict[int, np.ndarray]:
    """``cam_from_pano`` per kept photo along a maximum spanning tree of inlier counts (root: identity)."""
    kset = set(kept)
    edges = sorted((p for p in pairs if p.H is not None and p.i in kset and p.j in kset),
                   key=lambda p: -p.n_inliers)
    root = max(kept, key=lambda k: sum(p.n_inliers for p in edges if k in (p.i, p.j)))
    R = {root: np.eye(3)}
    while len(R) < len(kept):
        for p in edges:
            if (p.i in R) != (p.j in R):
                # x_j ~ H x_i with x = K R_cam_from_pano d  =>  R_j R_i^T ~ K_j^-1 H K_i
                M = np.linalg.inv(Ks[p.j]) @ p.H @ Ks[p.i]
                M /= np.cbrt(np.linalg.det(M))
                Rji = orthonormal(M)
                if p.i in R:
                    R[p.j] = Rji @ R[p.i]
                else:
                    R[p.i] = Rji.T @ R[p.j]
                break
        else:  # pragma: no cover - kept is connected by construction
            raise RuntimeError("the kept photos are not connected")
    return R


# ----------------------------------------------------------------------------------------------------------
# wave correction and the panorama frame
# ----------------------------------------------------------------------------------------------------------
def wave_correct(cam_from_pano: dict[int, np.ndarray]) -> np.ndarray:
    """``pano_from_pano0`` rotation (3, 3) that levels the panorama (Brown and Lowe's wave correction).

    The new ``pano`` frame's y axis (down) is perpendicular to the photos' x axes (the horizon is level
    when the photographer kept the camera level), pointing the way the photos' y axes point on average;
    its z axis is the photos' mean viewing direction made horizontal.
    """
    Rs = np.stack(list(cam_from_pano.values()))
    xs = Rs[:, 0, :]  # photo x axes in pano0
    ys = Rs[:, 1, :]
    zs = Rs[:, 2, :]
    w, v = np.linalg.eigh(xs.T @ xs)
    down = v[:, 0]
    if w[1] - w[0] < 1e-6 * max(w[2], 1e-12):  # degenerate (e.g. one photo, or a vertical sweep): mean y axis
        down = ys.mean(axis=0)
    if down @ ys.sum(axis=0) < 0:
        down = -down
    down /= np.linalg.norm(down)
    fwd = zs.mean(axis=0)
    fwd = fwd - (fwd @ down) * down
    if np.linalg.norm(fwd) < 1e-9:
        fwd = np.cross(xs.mean(axis=0), down)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(down, fwd)
    return np.vstack([right, down, fwd])  # rows: new axes in pano0 => pano_from_pano0
