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
from scipy.optimize._numdiff import approx_derivative, group_columns
from scipy.sparse import coo_matrix
from scipy.spatial.transform import Rotation

from ..core.camera import CameraIntrinsics

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
    pts = np.array([k.pt for k in kps], dtype=float)
    pts[:, 0] = (pts[:, 0] + 0.5) / sx - 0.5
    pts[:, 1] = (pts[:, 1] + 0.5) / sy - 0.5
    return PhotoFeatures(name, w, h, ws, pts, desc.astype(np.float32))


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


def match_pair(i: int, j: int, fi: PhotoFeatures, fj: PhotoFeatures, lin_i: np.ndarray, lin_j: np.ndarray, *,
               ratio: float = 0.75, ransac_work_px: float = 3.0, seed: int = 0) -> PairMatch:
    """Ratio-test matches, both ways (union), then a RANSAC homography on ``lin_*`` (linearised keypoints (N, 2) px)."""
    empty = PairMatch(i, j, 0, 0, 0.0, None, np.zeros(0, int), np.zeros(0, int))
    if len(fi.descriptors) < 8 or len(fj.descriptors) < 8:
        return empty
    matcher = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 32})
    pairs: set[tuple[int, int]] = set()
    for a, b, flip in ((fi.descriptors, fj.descriptors, False), (fj.descriptors, fi.descriptors, True)):
        for m in matcher.knnMatch(a, b, k=2):
            if len(m) == 2 and m[0].distance < ratio * m[1].distance:
                pairs.add((m[0].trainIdx, m[0].queryIdx) if flip else (m[0].queryIdx, m[0].trainIdx))
    if len(pairs) < 8:
        return PairMatch(i, j, len(pairs), 0, 0.0, None, np.zeros(0, int), np.zeros(0, int))
    idx = np.array(sorted(pairs))
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
                       max_per_pair: int = 200, seed: int = 0) -> Observations:
    rng = np.random.default_rng(seed)
    kset = set(kept)
    a, b, xa, xb, pid = [], [], [], [], []
    for k, p in enumerate(pairs):
        if p.i not in kset or p.j not in kset or p.n_inliers == 0:
            continue
        sel = np.arange(p.n_inliers)
        if len(sel) > max_per_pair:
            sel = np.sort(rng.choice(len(sel), max_per_pair, replace=False))
        a.append(np.full(len(sel), p.i))
        b.append(np.full(len(sel), p.j))
        xa.append(feats[p.i].keypoints[p.idx_i[sel]])
        xb.append(feats[p.j].keypoints[p.idx_j[sel]])
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


def _undistort_radial(xd: np.ndarray, k1: np.ndarray, k2: np.ndarray, iterations: int = 8) -> np.ndarray:
    x = xd.copy()
    for _ in range(iterations):
        r2 = np.sum(x * x, axis=1)
        x = xd / (1.0 + r2 * (k1 + k2 * r2))[:, None]
    return x


def bundle_adjust(obs: Observations, kept: list[int], groups: dict[int, int], init: dict[int, CameraIntrinsics],
                  R0: dict[int, np.ndarray], work_scale: dict[int, float], *, fixed_intrinsics: bool,
                  estimate_k1: bool, focal_prior: dict[int, float] | None = None, focal_prior_sigma: float = 0.05,
                  k1_prior_sigma: float = 0.25, pp_prior_sigma: float = 0.05, k2_prior_sigma: float = 0.25,
                  loss_scale_work_px: float = 1.0, reject_work_px: float = 4.0, max_nfev: int = 60) -> BAResult:
    """Refine rotations (and, unless ``fixed_intrinsics``, one focal, optionally k1, k2 and the principal
    point, per camera group).

    ``groups``: photo -> camera group (photos of one group share focal and distortion). ``init``: starting
    intrinsics per photo (fixed ones are used as they are, with their full distortion). Estimated
    intrinsics are fx = fy = f, radial k1 and k2, and the principal point (``estimate_k1``), with weak priors
    (k: 0 +- ``k1_prior_sigma``; principal point: ``init``'s +- ``pp_prior_sigma`` x focal).
    The root (first kept photo) keeps its rotation: the panorama's rotation is fixed later by wave correction.
    """
    kept = list(kept)
    pos = {k: n for n, k in enumerate(kept)}
    root = kept[0]
    free = [k for k in kept if k != root]
    gids = sorted({groups[k] for k in kept})
    gpos = {g: n for n, g in enumerate(gids)}
    n_rot = 3 * len(free)
    n_gp = 0 if fixed_intrinsics else (5 if estimate_k1 else 1)  # log f [, k1, k2, dcx / f0, dcy / f0]
    f0 = {g: np.mean([init[k].fx for k in kept if groups[k] == g]) for g in gids}

    a_pos = np.array([pos[k] for k in obs.a])
    b_pos = np.array([pos[k] for k in obs.b])
    s_obs = np.array([min(work_scale[x], work_scale[y]) for x, y in zip(obs.a, obs.b)])

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

    def unpack(x):
        Rs = R0s.copy()
        if free:
            dR = Rotation.from_rotvec(x[:n_rot].reshape(-1, 3)).as_matrix()
            for n, k in enumerate(free):
                Rs[pos[k]] = dR[n] @ R0s[pos[k]]
        gp = x[n_rot:].reshape(len(gids), n_gp) if n_gp else np.zeros((len(gids), 0))
        return Rs, gp

    cx0 = np.array([init[k].cx for k in kept])
    cy0 = np.array([init[k].cy for k in kept])

    grp_of_pos = np.array([gpos[groups[k]] for k in kept])
    f0_of_pos = np.array([f0[groups[k]] for k in kept])

    def cam_params(gp, photo_pos_arr):
        """Per observation row: f, k1, k2, cx, cy for the photo at each position."""
        g = grp_of_pos[photo_pos_arr]
        f0r = f0_of_pos[photo_pos_arr]
        f = f0r * np.exp(gp[g, 0])
        if n_gp == 5:
            return f, gp[g, 1], gp[g, 2], cx0[photo_pos_arr] + gp[g, 3] * f0r, cy0[photo_pos_arr] + gp[g, 4] * f0r
        z = np.zeros(len(g))
        return f, z, z, cx0[photo_pos_arr], cy0[photo_pos_arr]

    def rays_est(x_px, ppos, gp):
        f, k1, k2, cx, cy = cam_params(gp, ppos)
        xd = np.column_stack([(x_px[:, 0] - cx) / f, (x_px[:, 1] - cy) / f])
        xu = _undistort_radial(xd, k1, k2) if n_gp == 5 else xd
        d = np.column_stack([xu, np.ones(len(xu))])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def project_est(d, ppos, gp):
        f, k1, k2, cx, cy = cam_params(gp, ppos)
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = d[:, :2] / d[:, 2:3]
        if n_gp == 5:
            r2 = np.sum(xy * xy, axis=1)
            xy = xy * (1.0 + r2 * (k1 + k2 * r2))[:, None]
        return np.column_stack([f * xy[:, 0] + cx, f * xy[:, 1] + cy])

    def project_fixed(d, ppos):
        out = np.zeros((len(d), 2))
        for k in kept:
            m = ppos == pos[k]
            if m.any():
                out[m] = init[k].project(d[m])
        return out

    def transfer(Rs, gp, idx):
        """(n, 2, 2) residuals a->b and b->a, full-res pixels, for observation rows ``idx``."""
        ap, bp = a_pos[idx], b_pos[idx]
        if fixed_intrinsics:
            ra, rb = ray_a[idx], ray_b[idx]
        else:
            ra = rays_est(obs.xa[idx], ap, gp)
            rb = rays_est(obs.xb[idx], bp, gp)
        # d_b = R_b R_a^T r_a
        da = np.einsum("nij,nj->ni", Rs[bp], np.einsum("nji,nj->ni", Rs[ap], ra))
        db = np.einsum("nij,nj->ni", Rs[ap], np.einsum("nji,nj->ni", Rs[bp], rb))
        if fixed_intrinsics:
            pa, pb = project_fixed(da, bp), project_fixed(db, ap)
        else:
            pa, pb = project_est(da, bp, gp), project_est(db, ap, gp)
        res = np.stack([pa - obs.xb[idx], pb - obs.xa[idx]], axis=1)
        res[da[:, 2] <= 0, 0] = 1e3  # behind the other camera: a large, finite residual
        res[db[:, 2] <= 0, 1] = 1e3
        return np.where(np.isfinite(res), res, 1e3)

    def fun(x, idx):
        Rs, gp = unpack(x)
        r = (transfer(Rs, gp, idx) * s_obs[idx, None, None]).reshape(-1)
        extra = []
        if n_gp and focal_prior:
            for g in gids:
                if g in focal_prior:
                    f_g = f0[g] * np.exp(gp[gpos[g], 0])
                    extra.append((f_g - focal_prior[g]) / (focal_prior_sigma * focal_prior[g]))
        if n_gp == 5:
            extra.extend(gp[:, 1] / k1_prior_sigma)
            extra.extend(gp[:, 2] / k2_prior_sigma)
            extra.extend(gp[:, 3] / pp_prior_sigma)
            extra.extend(gp[:, 4] / pp_prior_sigma)
        return np.concatenate([r, np.asarray(extra, dtype=float)]) if extra else r

    def sparsity(idx):
        n_extra = (sum(1 for g in gids if focal_prior and g in focal_prior) if n_gp else 0) \
            + (4 * len(gids) if n_gp == 5 else 0)
        n_par = n_rot + n_gp * len(gids)
        fpos = {k: n for n, k in enumerate(free)}
        rows, cols = [], []
        base = 4 * np.arange(len(idx))
        for photos in (obs.a[idx], obs.b[idx]):
            for k in np.unique(photos):
                sel = base[photos == k]
                r4 = (sel[:, None] + np.arange(4)).ravel()
                if k in fpos:
                    for c in range(3):
                        rows.append(r4)
                        cols.append(np.full(len(r4), 3 * fpos[k] + c))
                if n_gp:
                    g = gpos[groups[k]]
                    for c in range(n_gp):
                        rows.append(r4)
                        cols.append(np.full(len(r4), n_rot + n_gp * g + c))
        r = 4 * len(idx)
        if n_gp and focal_prior:
            for g in gids:
                if g in focal_prior:
                    rows.append(np.array([r]))
                    cols.append(np.array([n_rot + n_gp * gpos[g]]))
                    r += 1
        if n_gp == 5:
            for q in range(1, 5):
                for g in gids:
                    rows.append(np.array([r]))
                    cols.append(np.array([n_rot + n_gp * gpos[g] + q]))
                    r += 1
        rr, cc = np.concatenate(rows), np.concatenate(cols)
        S = coo_matrix((np.ones(len(rr), np.int8), (rr, cc)), shape=(4 * len(idx) + n_extra, n_par)).tocsr()
        S.data[:] = 1
        return S

    x = np.zeros(n_rot + n_gp * len(gids))
    used = np.ones(len(obs.a), dtype=bool)
    nfev = 0
    cost = 0.0
    for rnd in range(2):
        idx = np.flatnonzero(used)
        if len(x) == 0:
            break
        if rnd == 0:  # robust first pass (soft L1), then plain least squares on the inliers
            sol = least_squares(fun, x, args=(idx,), jac_sparsity=sparsity(idx), method="trf", loss="soft_l1",
                                f_scale=loss_scale_work_px, x_scale="jac", xtol=1e-8, ftol=1e-6, max_nfev=30)
        else:
            # Levenberg-Marquardt (MINPACK) walks the focal / distortion valley far better than trf; its
            # Jacobian comes from finite differences grouped by the sparsity (a few evaluations per step)
            S = sparsity(idx)
            groups_fd = group_columns(S)

            def jac(xx, idx_=idx, S_=S, g_=groups_fd):
                return approx_derivative(fun, xx, method="2-point", sparsity=(S_, g_), args=(idx_,)).toarray()

            sol = least_squares(fun, x, jac=jac, args=(idx,), method="lm", xtol=1e-12, ftol=1e-12,
                                max_nfev=max_nfev * 4)
        x, cost, nfev = sol.x, float(sol.cost), nfev + sol.nfev
        log.debug("BA round %d: %d evaluations, cost %.4g, %s", rnd, sol.nfev, sol.cost, sol.message)
        Rs, gp = unpack(x)
        res = transfer(Rs, gp, np.arange(len(obs.a))) * s_obs[:, None, None]
        err = np.max(np.linalg.norm(res, axis=2), axis=1)
        new_used = err < reject_work_px
        if rnd == 0 and new_used.sum() >= 0.5 * len(used):
            used = new_used  # else: the robust pass has not converged yet; LM goes on with every inlier
    Rs, gp = unpack(x)
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
    res = transfer(Rs, gp, np.arange(len(obs.a)))
    return BAResult(out_R, out_K, res, used, cost, nfev)


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
