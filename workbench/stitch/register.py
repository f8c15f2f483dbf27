"""Registration: features, pairwise matching, the connected set, rotations, focal, bundle adjustment.

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
from scipy.optimize import least_squares

from ..core.camera import CameraIntrinsics
from ..core.geometry import exp_and_left_jacobian_so3

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
    idx = np.unique(both, axis=0) if len(both) else both.reshape(0, 2)
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


def _homography_jacobian(H: np.ndarray, x: np.ndarray) -> np.ndarray:
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
    return float(np.median(fs)) if fs else None


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


def _nearest_rotation(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1, 1, -1]) @ Vt
    return R


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
                Rji = _nearest_rotation(M)
                if p.i in R:
                    R[p.j] = Rji @ R[p.i]
                else:
                    R[p.i] = Rji.T @ R[p.j]
                break
        else:  # pragma: no cover - kept is connected by construction
            raise RuntimeError("the kept photos are not connected")
    return R


# ----------------------------------------------------------------------------------------------------------
# bundle adjustment (rotation only: one camera centre)
# ----------------------------------------------------------------------------------------------------------
@dataclass
class Observations:
    """Inlier matches stacked: photo ``a`` (M,), ``b`` (M,), pixels as on disk ``xa``, ``xb`` (M, 2), pair id (M,)."""

    a: np.ndarray
    b: np.ndarray
    xa: np.ndarray
    xb: np.ndarray
    pair: np.ndarray


def stack_observations(pairs: list[PairMatch], feats: list[PhotoFeatures], kept: list[int], *,
                       max_per_pair: int = 300, seed: int = 0) -> Observations:
    rng = np.random.default_rng(seed)
    kset = set(kept)
    a, b, xa, xb, pid = [], [], [], [], []
    for k, p in enumerate(pairs):
        if p.i not in kset or p.j not in kset or p.n_inliers == 0:
            continue
        x_i = feats[p.i].keypoints[p.idx_i] if p.x_i is None else p.x_i
        x_j = feats[p.j].keypoints[p.idx_j] if p.x_j is None else p.x_j
        sel = np.arange(len(x_i))
        if len(sel) > max_per_pair:
            sel = np.sort(rng.choice(len(sel), max_per_pair, replace=False))
        a.append(np.full(len(sel), p.i))
        b.append(np.full(len(sel), p.j))
        xa.append(x_i[sel])
        xb.append(x_j[sel])
        pid.append(np.full(len(sel), k))
    return Observations(np.concatenate(a), np.concatenate(b), np.concatenate(xa), np.concatenate(xb),
                        np.concatenate(pid))


@dataclass
class BAResult:
    cam_from_pano: dict[int, np.ndarray]
    intrinsics: dict[int, CameraIntrinsics]  # per photo, full resolution, as on disk
    residuals_px: np.ndarray  # (M, 2, 2): per observation, a->b and b->a residual, full-resolution pixels
    used: np.ndarray  # (M,) bool: observations kept after outlier rejection
    cost: float
    n_iterations: int


def _undistort_radial(xd: np.ndarray, k1: np.ndarray, k2: np.ndarray, iterations: int = 6) -> np.ndarray:
    """Undistorted normalised (n, 2) of distorted ``xd`` (n, 2) under ``x (1 + k1 r^2 + k2 r^4)``, by Newton."""
    u, v = xd[:, 0], xd[:, 1]
    x, y = u.copy(), v.copy()
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for _ in range(iterations):
            r2 = x * x + y * y
            s = 1.0 + r2 * (k1 + k2 * r2)
            ds = k1 + 2.0 * k2 * r2
            gx, gy = x * s - u, y * s - v
            # A = s I + 2 ds x x^T; A^-1 g by Sherman-Morrison
            c = 2.0 * ds * (x * gx + y * gy) / (s + 2.0 * ds * r2)
            sx, sy = (gx - x * c) / s, (gy - y * c) / s
            ok = np.isfinite(sx) & np.isfinite(sy)
            x = x - np.where(ok, sx, 0.0)
            y = y - np.where(ok, sy, 0.0)
    return np.column_stack([x, y])


def bundle_adjust(obs: Observations, kept: list[int], groups: dict[int, int], init: dict[int, CameraIntrinsics],
                  R0: dict[int, np.ndarray], work_scale: dict[int, float], *, fixed_intrinsics: bool,
                  estimate_k1: bool, focal_prior: dict[int, float] | None = None, focal_prior_sigma: float = 0.05,
                  k1_prior_sigma: float = 0.25, pp_prior_sigma: float = 0.05, k2_prior_sigma: float = 0.25,
                  loss_scale_work_px: float = 1.0, reject_work_px: float = 4.0, max_nfev: int = 60,
                  robust_per_pair: int = 100, robust_pass: bool = True, final_pass: bool = True,
                  used: np.ndarray | None = None, robust_tol: float = 1e-6,
                  start: dict[int, CameraIntrinsics] | None = None, final_loss_median: float = 0.0) -> BAResult:
    """Refine rotations (and, unless ``fixed_intrinsics``, one focal, optionally k1, k2 and the principal
    point, per camera group).

    ``groups``: photo -> camera group (photos of one group share focal and distortion). ``init``: starting
    intrinsics per photo (fixed ones are used as they are, with their full distortion). Estimated
    intrinsics are fx = fy = f, radial k1 and k2, and the principal point (``estimate_k1``), with weak priors
    (k: 0 +- ``k1_prior_sigma``; principal point: ``init``'s +- ``pp_prior_sigma`` x focal).
    The root (first kept photo) keeps its rotation: the panorama's rotation is fixed later by wave correction.
    Residuals: every observation transferred a -> b and b -> a (4 per observation, work pixels); the
    Jacobian is analytic (rotations through SO(3)'s left Jacobian, the lens by implicit differentiation of
    the undistortion), so each step costs one evaluation.
    Two passes: ``robust_pass`` (soft L1 on at most ``robust_per_pair`` observations per pair, to tolerance
    ``robust_tol``; its inliers are kept) and ``final_pass`` (least squares on the inliers: ``used`` (M,) bool when
    there is no robust pass, else every observation).
    ``final_loss_median``: when > 0, the final pass minimises the soft-L1 loss of scale ``final_loss_median`` times
    the inliers' median residual (at its start) instead of their sum of squares: the residuals' tail (mismatches
    within ``reject_work_px``, occluded or poorly textured patches) weighs less.
    ``start``: estimated intrinsics to start from (per photo; the priors stay those of ``init``), e.g. a previous
    adjustment's, with ``R0`` its rotations.
    """
    kept = list(kept)
    pos = {k: n for n, k in enumerate(kept)}
    root = kept[0]
    free = [k for k in kept if k != root]
    gids = sorted({groups[k] for k in kept})
    gpos = {g: n for n, g in enumerate(gids)}
    n_rot = 3 * len(free)
    n_gp = 0 if fixed_intrinsics else (5 if estimate_k1 else 1)  # log f [, k1, k2, dcx / f0, dcy / f0]
    n_par = n_rot + n_gp * len(gids)
    f0 = {g: np.mean([init[k].fx for k in kept if groups[k] == g]) for g in gids}

    pos_of = np.zeros(max(kept) + 1, dtype=int)  # photo -> position, as an array (looked up per observation)
    pos_of[kept] = np.arange(len(kept))
    a_pos, b_pos = pos_of[obs.a], pos_of[obs.b]
    s_obs = min_work_scale(obs, work_scale)
    # parameter column of each photo position's rotation (-1: the root) and of its group's first parameter
    rot_col = np.full(len(kept), -1)
    for n_, k in enumerate(free):
        rot_col[pos[k]] = 3 * n_
    grp_of_pos = np.array([gpos[groups[k]] for k in kept])
    f0_of_pos = np.array([f0[groups[k]] for k in kept])
    gp_col = n_rot + n_gp * grp_of_pos
    cx0 = np.array([init[k].cx for k in kept])
    cy0 = np.array([init[k].cy for k in kept])

    if fixed_intrinsics:  # rays of the observations once, exactly
        ray_a = np.zeros((len(obs.a), 3))
        ray_b = np.zeros((len(obs.a), 3))
        for k in kept:
            m = obs.a == k
            if m.any():
                ray_a[m] = init[k].rays(obs.xa[m])
            m = obs.b == k
            if m.any():
                ray_b[m] = init[k].rays(obs.xb[m])

    R0s = np.stack([R0[k] for k in kept])
    free_pos = np.array([pos[k] for k in free], dtype=int)

    def unpack(x):
        Rs = R0s.copy()
        Jl = np.zeros((len(kept), 3, 3))
        if free:
            phi = x[:n_rot].reshape(-1, 3)
            dR, Jf = exp_and_left_jacobian_so3(phi)
            Rs[free_pos] = dR @ R0s[free_pos]
            Jl[free_pos] = Jf
        gp = x[n_rot:].reshape(len(gids), n_gp) if n_gp else np.zeros((len(gids), 0))
        return Rs, Jl, gp

    def cam_params(gp, ppos):
        """Per row: f, k1, k2, cx, cy of the photo at each position (computed per position, then gathered)."""
        f = (f0_of_pos * np.exp(gp[grp_of_pos, 0]))[ppos]
        if n_gp == 5:
            g = gp[grp_of_pos]
            return (f, g[:, 1][ppos], g[:, 2][ppos], (cx0 + g[:, 3] * f0_of_pos)[ppos],
                    (cy0 + g[:, 4] * f0_of_pos)[ppos])
        z = np.zeros(len(ppos))
        return f, z, z, cx0[ppos], cy0[ppos]

    def rays_est(x_px, ppos, gp, jac):
        """Rays (n, 3) (z = 1) of pixels ``x_px`` and, with ``jac``, d ray / d group parameters (n, 3, n_gp)."""
        f, k1, k2, cx, cy = cam_params(gp, ppos)
        xd = np.column_stack([(x_px[:, 0] - cx) / f, (x_px[:, 1] - cy) / f])
        xu = _undistort_radial(xd, k1, k2) if n_gp == 5 else xd
        r = np.column_stack([xu, np.ones(len(xu))])
        if not jac:
            return r, None
        n = len(xu)
        # d xd / d params: log f -> -xd; dcx/f0 -> (-f0/f, 0); dcy/f0 -> (0, -f0/f)
        dxd = np.zeros((n, 2, n_gp))
        dxd[:, :, 0] = -xd
        if n_gp == 5:
            q = f0_of_pos[ppos] / f
            dxd[:, 0, 3] = -q
            dxd[:, 1, 4] = -q
            r2 = np.sum(xu * xu, axis=1)
            s = 1.0 + r2 * (k1 + k2 * r2)
            ds = k1 + 2.0 * k2 * r2
            rhs = dxd.copy()
            rhs[:, :, 1] -= xu * r2[:, None]
            rhs[:, :, 2] -= xu * (r2 * r2)[:, None]
            # A^-1 rhs, A = s I + 2 ds xu xu^T (Sherman-Morrison)
            xr = xu[:, 0, None] * rhs[:, 0, :] + xu[:, 1, None] * rhs[:, 1, :]
            dxu = (rhs - xu[:, :, None] * (2.0 * ds / (s + 2.0 * ds * r2))[:, None, None] * xr[:, None, :]) \
                / s[:, None, None]
        else:
            dxu = dxd
        dr = np.zeros((n, 3, n_gp))
        dr[:, :2, :] = dxu
        return r, dr

    def project_est(d, ppos, gp, jac):
        """Pixels (n, 2) of directions ``d`` (n, 3); with ``jac``: d p / d d (n, 2, 3), d p / d params (n, 2, n_gp)."""
        f, k1, k2, cx, cy = cam_params(gp, ppos)
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = 1.0 / d[:, 2]
        y = d[:, :2] * iz[:, None]
        r2 = np.sum(y * y, axis=1)
        s = 1.0 + r2 * (k1 + k2 * r2) if n_gp == 5 else np.ones(len(y))
        yd = y * s[:, None]
        p = f[:, None] * yd + np.column_stack([cx, cy])
        if not jac:
            return p, None, None
        n = len(y)
        # d y / d d = iz [I | -y]; d yd / d y = s I + 2 ds y y^T, so d yd / d d = iz [s I + 2 ds y y^T | -(s + 2 ds r2) y]
        fi = f * iz
        dp_dd = np.empty((n, 2, 3))
        if n_gp == 5:
            ds = k1 + 2.0 * k2 * r2
            c = (2.0 * fi * ds)[:, None, None] * y[:, :, None]
            dp_dd[:, :, :2] = c * y[:, None, :]
            dp_dd[:, 0, 0] += fi * s
            dp_dd[:, 1, 1] += fi * s
            dp_dd[:, :, 2] = -(fi * (s + 2.0 * ds * r2))[:, None] * y
        else:
            dp_dd[:, :, :2] = 0.0
            dp_dd[:, 0, 0] = dp_dd[:, 1, 1] = fi
            dp_dd[:, :, 2] = -fi[:, None] * y
        dp_dg = np.zeros((n, 2, n_gp))
        dp_dg[:, :, 0] = f[:, None] * yd
        if n_gp == 5:
            dp_dg[:, :, 1] = f[:, None] * y * r2[:, None]
            dp_dg[:, :, 2] = f[:, None] * y * (r2 * r2)[:, None]
            dp_dg[:, 0, 3] = f0_of_pos[ppos]
            dp_dg[:, 1, 4] = f0_of_pos[ppos]
        return p, dp_dd, dp_dg

    def project_fixed(d, ppos, jac):
        out = np.zeros((len(d), 2))
        J = np.zeros((len(d), 2, 3)) if jac else None
        for k in kept:
            m = ppos == pos[k]
            if not m.any():
                continue
            out[m] = init[k].project(d[m])
            if jac:  # d p / d d by central differences (the full Brown-Conrady model; exact to ~1e-9 px)
                dm = d[m]
                h = 1e-6 * np.linalg.norm(dm, axis=1)
                for c in range(3):
                    e = np.zeros(3)
                    e[c] = 1.0
                    J[m, :, c] = (init[k].project(dm + h[:, None] * e) - init[k].project(dm - h[:, None] * e)) \
                        / (2.0 * h[:, None])
        return out, J

    def transfer(gp, M, src_pos, dst_pos, x_src, x_dst, ray_src, jac):
        """Residuals (n, 2) (full-resolution px) of pixels ``x_src`` (n, 2) of photos ``src_pos`` transferred into
        photos ``dst_pos`` (``M`` (n, 3, 3): dst_from_src per observation; ``ray_src``: the rays of ``x_src`` when the
        intrinsics are fixed) and, with ``jac``: A (n, 2, 3) with d res / d rot(dst) = -A J_l(dst) and
        d res / d rot(src) = A M J_l(src); d res / d group(src) (n, 2, n_gp); d res / d group(dst).
        Both directions of every observation go through one call (elementwise: the same numbers as one call each)."""
        if fixed_intrinsics:
            r, dr = ray_src, None
        else:
            r, dr = rays_est(x_src, src_pos, gp, jac)
        d = M[:, :, 0] * r[:, 0, None] + M[:, :, 1] * r[:, 1, None] + M[:, :, 2] * r[:, 2, None]
        if fixed_intrinsics:
            p, dp_dd = project_fixed(d, dst_pos, jac)
            dp_dg = None
        else:
            p, dp_dd, dp_dg = project_est(d, dst_pos, gp, jac)
        res = p - x_dst
        bad = (d[:, 2] <= 0) | ~np.all(np.isfinite(res), axis=1)
        res[bad] = 1e3  # behind the other camera: a large, finite residual
        if not jac:
            return res, None
        # d d / d (dst rotation perturbation) = -[d]x, d d / d (src) = M [r]x = [d]x M; rows of dp_dd [d]x are
        # dp_dd[r] x d
        A = np.empty_like(dp_dd)  # np.cross(dp_dd, d[:, None, :]), the same products, without its overhead
        d0, d1, d2 = d[:, None, 0], d[:, None, 1], d[:, None, 2]
        A[:, :, 0] = dp_dd[:, :, 1] * d2 - dp_dd[:, :, 2] * d1
        A[:, :, 1] = dp_dd[:, :, 2] * d0 - dp_dd[:, :, 0] * d2
        A[:, :, 2] = dp_dd[:, :, 0] * d1 - dp_dd[:, :, 1] * d0
        J_gs = None
        if dr is not None:  # dp_dd M dr, with dr's z row zero
            DM = [dp_dd[:, :, 0, None] * M[:, 0, c, None, None] + dp_dd[:, :, 1, None] * M[:, 1, c, None, None]
                  + dp_dd[:, :, 2, None] * M[:, 2, c, None, None] for c in range(2)]  # 2 x (n, 2, 1)
            J_gs = DM[0] * dr[:, None, 0, :] + DM[1] * dr[:, None, 1, :]
        blocks = [A, J_gs, dp_dg]
        for B in blocks:
            if B is not None:
                B[bad] = 0.0
        return res, blocks

    n_prior = ((sum(1 for g in gids if focal_prior and g in focal_prior) if n_gp else 0)
               + (4 * len(gids) if n_gp == 5 else 0))
    single_group = len(gids) == 1

    layouts: dict[int, tuple] = {}

    def layout(idx):
        """What :func:`evaluate` needs of the observations ``idx`` that does not depend on the parameters (once per
        set): the blocks of consecutive observations of one pair of photos (stacked pair by pair: one block per
        pair), and both directions' positions and pixels stacked, a -> b (rows :n) then b -> a (rows n:)."""
        hit = layouts.get(id(idx))
        if hit is not None and hit[0] is idx:
            return hit[1]
        ap, bp = a_pos[idx], b_pos[idx]
        cut = np.flatnonzero((np.diff(ap) != 0) | (np.diff(bp) != 0)) + 1
        starts = np.concatenate([[0], cut]).astype(int)
        ends = np.concatenate([cut, [len(idx)]]).astype(int)
        xa, xb = obs.xa[idx], obs.xb[idx]
        lay = (starts, ends, ap[starts], bp[starts], np.concatenate([ap, bp]), np.concatenate([bp, ap]),
               np.concatenate([xa, xb]), np.concatenate([xb, xa]),
               np.concatenate([ray_a[idx], ray_b[idx]]) if fixed_intrinsics else None, s_obs[idx])
        layouts[id(idx)] = (idx, lay)  # (idx kept alive: its id is not reused while cached)
        return lay

    def evaluate(x, idx, jac):
        Rs, Jl, gp = unpack(x)
        starts, ends, pa, pb, src2, dst2, xsrc2, xdst2, ray2, s = layout(idx)
        M_ba = Rs[pb] @ np.transpose(Rs[pa], (0, 2, 1))  # per pair: b_from_a
        M_ab = np.transpose(M_ba, (0, 2, 1))
        lens_ = ends - starts
        Mo_ba, Mo_ab = np.repeat(M_ba, lens_, axis=0), np.repeat(M_ab, lens_, axis=0)
        n = len(idx)
        res2, B2 = transfer(gp, np.concatenate([Mo_ba, Mo_ab]), src2, dst2, xsrc2, xdst2, ray2, jac)
        res_ab, res_ba = res2[:n], res2[n:]
        if jac:
            B_ab = [None if b_ is None else b_[:n] for b_ in B2]
            B_ba = [None if b_ is None else b_[n:] for b_ in B2]
        r = (np.stack([res_ab, res_ba], axis=1) * s[:, None, None]).reshape(-1)
        extra, Jx = [], []
        if n_gp and focal_prior:
            for g in gids:
                if g in focal_prior:
                    f_g = f0[g] * np.exp(gp[gpos[g], 0])
                    sig = focal_prior_sigma * focal_prior[g]
                    extra.append((f_g - focal_prior[g]) / sig)
                    Jx.append((n_rot + n_gp * gpos[g], f_g / sig))
        if n_gp == 5:
            for q, sig in ((1, k1_prior_sigma), (2, k2_prior_sigma), (3, pp_prior_sigma), (4, pp_prior_sigma)):
                for g in gids:
                    extra.append(gp[gpos[g], q] / sig)
                    Jx.append((n_rot + n_gp * gpos[g] + q, 1.0 / sig))
        r = np.concatenate([r, np.asarray(extra, dtype=float)])
        if not jac:
            return r, None
        J = np.zeros((n + (len(extra) + 3) // 4, 2, 2, n_par))  # rows: observation, direction, x / y
        for w, (src, dst, Mp, B) in enumerate(((pa, pb, M_ba, B_ab), (pb, pa, M_ab, B_ba))):
            A, J_gs, J_gd = (None if b_ is None else b_ * s[:, None, None] for b_ in B)
            for q, (s0, e0) in enumerate(zip(starts, ends)):
                cs, cd = rot_col[src[q]], rot_col[dst[q]]
                if cs >= 0:
                    J[s0:e0, w, :, cs:cs + 3] = A[s0:e0] @ (Mp[q] @ Jl[src[q]])
                if cd >= 0:
                    J[s0:e0, w, :, cd:cd + 3] = -(A[s0:e0] @ Jl[dst[q]])
                if n_gp and not single_group:
                    gs, gd = gp_col[src[q]], gp_col[dst[q]]
                    if J_gs is not None:
                        J[s0:e0, w, :, gs:gs + n_gp] += J_gs[s0:e0]
                    J[s0:e0, w, :, gd:gd + n_gp] += J_gd[s0:e0]
            if n_gp and single_group:
                J[:n, w, :, n_rot:] = J_gd if J_gs is None else J_gs + J_gd
        J = J.reshape(-1, n_par)[:4 * n + len(extra)]
        for q, (c, v) in enumerate(Jx):
            J[4 * n + q, c] = v
        return r, J

    c_loss = loss_scale_work_px

    def soft_l1(r, J, n_obs):
        """Residuals and Jacobian rescaled so that their sum of squares is the soft-L1 loss of the observations'
        residuals (scale ``c_loss``: ``loss_scale_work_px``, or the final pass's):
        rho(z) = 2 (sqrt(1 + z^2) - 1) = g(z)^2, g(z) = z sqrt(2 / (1 + sqrt(1 + z^2)))."""
        z = r[:n_obs] / c_loss
        rho = np.sqrt(1.0 + z * z)
        sq = np.sqrt(2.0 / (1.0 + rho))
        r = r.copy()
        r[:n_obs] = c_loss * z * sq
        if J is not None:
            J = J.copy()
            J[:n_obs] *= (sq - z * z / (sq * rho * (1.0 + rho) ** 2))[:, None]
        return r, J

    # MINPACK asks for the Jacobian at almost every point whose residuals it has just asked for (each accepted step):
    # both come from one evaluation, the Jacobian kept for that point (the same numbers as evaluating it again)
    last: dict = {}

    def fun(x, idx, robust):
        r, J = evaluate(x, idx, True)
        if robust:
            r, J = soft_l1(r, J, 4 * len(idx))
        r, J = _compress_least_squares(r, J)
        last.update(x=x.copy(), idx=idx, J=J)
        return r

    def jac(x, idx, robust):
        if last.get("idx") is idx and np.array_equal(last["x"], x):
            return last["J"]
        r, J = evaluate(x, idx, True)
        return _compress_least_squares(*(soft_l1(r, J, 4 * len(idx)) if robust else (r, J)))[1]

    x = np.zeros(n_par)
    if start is not None and n_gp:
        for g in gids:
            k = next(k for k in kept if groups[k] == g)
            c = start[k]
            x[n_rot + n_gp * gpos[g]] = np.log(c.fx / f0[g])
            if n_gp == 5:
                x[n_rot + n_gp * gpos[g] + 1:n_rot + n_gp * (gpos[g] + 1)] = (
                    c.k1, c.k2, (c.cx - init[k].cx) / f0[g], (c.cy - init[k].cy) / f0[g])
    used = np.ones(len(obs.a), dtype=bool) if used is None else used.copy()
    nfev = 0
    cost = 0.0
    # the robust pass walks from the initial guess on at most ``robust_per_pair`` observations of each pair; the
    # final pass starts next to the minimum with every inlier, and converges in a few steps
    rng = np.random.default_rng(0)
    sub = np.zeros(len(obs.a), dtype=bool)
    for pid in np.unique(obs.pair):
        rows = np.flatnonzero(obs.pair == pid)
        sub[rng.permutation(rows)[:robust_per_pair]] = True
    for rnd in range(2):
        if len(x) == 0:
            break
        if (rnd == 0 and not robust_pass) or (rnd == 1 and not final_pass):
            continue
        # Levenberg-Marquardt (MINPACK) with the analytic Jacobian: a robust first pass (soft L1, by rescaling the
        # residuals: the loss is their sum of squares), then least squares on the inliers (or soft L1 at the scale of
        # their median residual: final_loss_median). LM walks the focal / distortion valley far better than trf.
        idx = np.flatnonzero(sub if rnd == 0 else used)
        robust = rnd == 0 or final_loss_median > 0
        if rnd == 1 and robust:
            err = np.max(np.linalg.norm(_transfer_all(evaluate, x, len(obs.a)), axis=2), axis=1)
            c_loss = final_loss_median * float(np.median(err[idx]))
        # the robust pass only has to find the inliers and come near the minimum: a looser tolerance
        tol = robust_tol if rnd == 0 else 1e-10
        sol = least_squares(fun, x, jac=jac, args=(idx, robust), method="lm", xtol=tol, ftol=tol,
                            max_nfev=max_nfev * 2)
        x, cost, n_ev, msg = sol.x, float(sol.cost), sol.nfev, sol.message
        nfev += n_ev
        log.debug("BA round %d: %d evaluations, cost %.4g, %s", rnd, n_ev, cost, msg)
        if rnd == 0:
            res = _transfer_all(evaluate, x, len(obs.a))
            new_used = np.max(np.linalg.norm(res, axis=2), axis=1) < reject_work_px
            if new_used.sum() >= 0.5 * len(used):
                used = new_used  # else: the robust pass has not converged yet; LM goes on with every inlier
    Rs, _, gp = unpack(x)
    out_R = {k: Rs[pos[k]] for k in kept}
    out_K = {}
    for k in kept:
        if fixed_intrinsics:
            out_K[k] = init[k]
        else:
            g = gpos[groups[k]]
            f = float(f0[groups[k]] * np.exp(gp[g, 0]))
            lens = gp[g, 1:5] if n_gp == 5 else np.zeros(4)
            out_K[k] = CameraIntrinsics(width=init[k].width, height=init[k].height, fx=f, fy=f,
                                        cx=init[k].cx + lens[2] * f0[groups[k]],
                                        cy=init[k].cy + lens[3] * f0[groups[k]],
                                        k1=float(lens[0]), k2=float(lens[1]))
    res = _transfer_all(evaluate, x, len(obs.a)) / s_obs[:, None, None]
    return BAResult(out_R, out_K, res, used, cost, nfev)


def min_work_scale(obs: Observations, work_scale: dict[int, float]) -> np.ndarray:
    """(M,) the smaller work scale of each observation's two photos (residuals in work pixels use it)."""
    ws = np.zeros(max(work_scale) + 1)
    ws[list(work_scale)] = list(work_scale.values())
    return np.minimum(ws[obs.a], ws[obs.b])


def _compress_least_squares(r: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (m,) and Jacobian (m, n) replaced by (n + 1,) and (n + 1, n) ones that Levenberg-Marquardt cannot
    tell apart: with R (n + 1, n + 1) upper triangular, R^T R = [J | r]^T [J | r] (so [J | r] = Q R, Q with
    orthonormal columns), r' = R[:, n] and J' = R[:, :n] give |J' p + r'| = |J p + r| for every step p, |r'| = |r|
    and J' has J's column norms (MINPACK's scaling): the same steps and tests up to rounding, but MINPACK factorises
    n + 1 rows instead of m = 4 per match (its own time was about 30 % of budapest's adjustment).
    R from the Cholesky factor of the column-equilibrated Gram matrix (QR when that is not positive definite)."""
    m, n = J.shape
    if m <= 2 * (n + 1):
        return r, J
    A = np.empty((m, n + 1))
    A[:, :n] = J
    A[:, n] = r
    G = A.T @ A
    c = np.sqrt(np.diag(G))
    c[c == 0] = 1.0
    try:
        L = np.linalg.cholesky(G / np.outer(c, c))
        R = L.T * c[None, :]
        if not np.all(np.isfinite(R)):
            raise np.linalg.LinAlgError
    except np.linalg.LinAlgError:
        R = np.linalg.qr(A, mode="r")
    return np.ascontiguousarray(R[:, n]), np.ascontiguousarray(R[:, :n])


def _transfer_all(evaluate, x: np.ndarray, m: int) -> np.ndarray:
    """(m, 2, 2) residuals (work pixels) of every observation, a -> b and b -> a."""
    r, _ = evaluate(x, np.arange(m), False)
    return r[:4 * m].reshape(m, 2, 2)


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
