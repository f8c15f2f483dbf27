"""The start of a central rig's fit (:mod:`.central`): candidate poses ``(rig_from_world, centre)`` from the
control-point picks and the priors, and the choice among them by a bounded (MSAC-like) score.

Candidates: P3P (OpenCV) on random triples of distinct points, each triple seen through a virtual pinhole looking
along the mean of its rays; with a centre prior, Kabsch on all picks and on random pairs; with a heading prior, the
compass starts. The score of every candidate is computed in one batch (:func:`candidate_errors`: the stack of
candidates against every pick, per photo), with the same arithmetic per candidate as :func:`central_errors` on
one, so the candidate chosen is the one a loop over them would choose (docs/performance.md, twelfth pass).
"""

from __future__ import annotations

import math
from typing import Sequence

import cv2
import numpy as np

from ..files.panorama import RigView
from .fitting import rotation_kabsch
from .options import GeorefOptions, HeadingPrior
from .picks import Pick
from .track_picks import TrackTerm

__all__ = ["central_errors", "candidate_errors", "heading_errors", "p3p_candidates", "p3p_candidates_batch",
           "compass_candidates", "start_candidates", "prior_grid", "best_candidate"]

_EYE3 = np.eye(3)
_CHUNK_VALUES = 1 << 16  # candidates x picks scored at once (memory, not results: each candidate's row is alone)


def p3p_candidates(bearings: np.ndarray, X: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(rig_from_world R, centre)`` candidates from 3 bearings (3, 3) in the rig frame and 3 world points."""
    return p3p_candidates_batch(np.asarray(bearings, float)[None], np.asarray(X, float)[None])


def p3p_candidates_batch(bearings: np.ndarray, X: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The candidates of T triples (bearings (T, 3, 3) in the rig frame, world points (T, 3, 3)), in the triples'
    order: each triple seen through a virtual pinhole looking along the mean of its rays, P3P (OpenCV) there.
    The virtual frames of all triples are computed at once, each with the arithmetic of one (the same sums,
    products and norms, ``np.linalg.norm``'s ``sqrt(v.dot(v))`` as the plain sum of squares it equals)."""
    m = bearings.sum(axis=1)
    nm = np.sqrt((m * m).sum(axis=1))
    ok = nm >= 1e-6
    with np.errstate(invalid="ignore", divide="ignore"):
        z = m / nm[:, None]
        e = np.where((np.abs(z[:, 1]) < 0.9)[:, None], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0])
        x = np.cross(e, z)
        x /= np.sqrt((x * x).sum(axis=1))[:, None]
        y = np.cross(z, x)
        Q = np.stack([x, y, z], axis=1)  # (T, 3, 3) virtual_from_rig
        b = np.matmul(bearings, Q.transpose(0, 2, 1))
        ok &= ~(b[:, :, 2] <= 1e-3).any(axis=1)
        img = b[:, :, :2] / b[:, :, 2:3]
    out = []
    for t in np.nonzero(ok)[0]:
        try:
            n, rvecs, tvecs = cv2.solveP3P(np.ascontiguousarray(X[t], dtype=np.float64), np.ascontiguousarray(img[t]),
                                           _EYE3, None, flags=cv2.SOLVEPNP_P3P)
        except cv2.error:
            continue
        Qt = Q[t].T
        for rv, tv in zip(rvecs or [], tvecs or []):
            Rv = cv2.Rodrigues(np.asarray(rv, float))[0]
            R = Qt @ Rv
            tt = Qt @ np.asarray(tv, float).reshape(3)
            out.append((R, -R.T @ tt))
    return out


def _wrap(a: float) -> float:
    """An angle (rad) wrapped to [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def heading_errors(R: np.ndarray, views: Sequence[RigView], headings: Sequence[HeadingPrior]) -> np.ndarray:
    """Each heading prior's residual (rad, wrapped): the azimuth of its photo's optical axis (clockwise from north,
    +y) with ``rig_from_world`` R, less the prior's."""
    out = []
    for h in headings:
        a = (np.asarray(views[h.view].cam_from_rig, float) @ R)[2]  # the optical axis in the scene frame
        out.append(_wrap(math.atan2(a[0], a[1]) - math.radians(h.azimuth_deg)))
    return np.asarray(out, float)


def compass_candidates(bear: np.ndarray, pts: np.ndarray, X: np.ndarray, c0: np.ndarray,
                       views: Sequence[RigView], headings: Sequence[HeadingPrior],
                       rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """Starts at the centre prior ``c0`` from a heading prior: the optical axis on the heading at a pitch from
    -60 to 60 deg, and one pick's bearing on its point's direction (Kabsch on the two pairs)."""
    out = []
    ks = np.arange(len(pts)) if len(pts) <= 8 else rng.choice(len(pts), 8, replace=False)
    for h in headings[:3]:
        z_rig = np.asarray(views[h.view].cam_from_rig, float)[2]  # the photo's optical axis in the rig frame
        az = math.radians(h.azimuth_deg)
        for k in ks:
            u = X[pts[k]] - c0
            if np.linalg.norm(u) < 1e-3:
                continue
            u = u / np.linalg.norm(u)
            for pitch in np.radians(np.arange(-60.0, 61.0, 5.0)):
                a = np.array([math.sin(az) * math.cos(pitch), math.cos(az) * math.cos(pitch), math.sin(pitch)])
                out.append((rotation_kabsch(np.array([u, a]), np.array([bear[k], z_rig])), c0))
    return out


def central_errors(R: np.ndarray, c: np.ndarray, views: Sequence[RigView], obs: list[Pick],
                   X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reprojection errors (n,) px (inf when behind) and the residual vectors (n, 2) of every observation."""
    err = np.full(len(obs), np.inf)
    vec = np.full((len(obs), 2), np.nan)
    vi = np.array([o.view for o in obs])
    P = (X[[o.point for o in obs]] - c) @ R.T  # rig frame
    UV = np.array([o.uv for o in obs]).reshape(-1, 2)
    for i in np.unique(vi):
        k = np.nonzero(vi == i)[0]
        v = views[i]
        q = P[k] @ np.asarray(v.cam_from_rig, float).T
        front = q[:, 2] > 1e-6
        if not front.any():
            continue
        kk = k[front]
        vec[kk] = v.intrinsics.project(q[front]) - UV[kk]
        err[kk] = np.hypot(vec[kk, 0], vec[kk, 1])
    return err, vec


def candidate_errors(Rs: np.ndarray, cs: np.ndarray, views: Sequence[RigView], obs: list[Pick],
                     X: np.ndarray) -> np.ndarray:
    """The reprojection errors (K, n) px (inf when behind) of every observation at each of K candidates
    (``rig_from_world`` Rs (K, 3, 3), centres cs (K, 3)): row k is :func:`central_errors` of candidate k, the
    same numbers (per candidate the same matrix products, and element by element the same projection)."""
    K, n = len(Rs), len(obs)
    err = np.full((K, n), np.inf)
    if K == 0 or n == 0:
        return err
    vi = np.array([o.view for o in obs])
    P = np.matmul(X[[o.point for o in obs]][None] - cs[:, None, :], Rs.transpose(0, 2, 1))  # (K, n, 3) rig frame
    UV = np.array([o.uv for o in obs]).reshape(-1, 2)
    for i in np.unique(vi):
        k = np.nonzero(vi == i)[0]
        v = views[i]
        q = np.matmul(P[:, k], np.asarray(v.cam_from_rig, float).T)  # (K, m, 3), each slice as P[k] @ C.T
        front = q[:, :, 2] > 1e-6
        vec = v.intrinsics.project(q[front]) - np.broadcast_to(UV[k], q.shape[:2] + (2,))[front]
        sub = np.full(front.shape, np.inf)
        sub[front] = np.hypot(vec[:, 0], vec[:, 1])
        err[:, k] = sub
    return err


def _msac(err: np.ndarray, thr: float) -> np.ndarray:
    """The bounded score of error rows (K, n): sum of ``max(0, 1 - (min(e, thr) / thr)^2)`` per row."""
    return np.sum(np.maximum(0.0, 1.0 - (np.minimum(err, thr) / thr) ** 2), axis=1)


def start_candidates(bear: np.ndarray, pts: np.ndarray, X: np.ndarray, n_pts: int, prior_centre: np.ndarray | None,
                     opts: GeorefOptions, rng: np.random.Generator, views: Sequence[RigView] = (),
                     headings: Sequence[HeadingPrior] = (), n_pairs: int = 100) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(rig_from_world, centre)`` starts: with a centre prior, Kabsch on all picks and on random pairs, with
    a heading prior too the compass starts (:func:`compass_candidates`); with 3 or more points, P3P on random
    triples of distinct points."""
    candidates: list[tuple[np.ndarray, np.ndarray]] = []
    if prior_centre is not None:
        c0 = np.asarray(prior_centre, float)
        if headings:
            candidates.extend(compass_candidates(bear, pts, X, c0, views, headings, rng))
        u = X[pts] - c0
        ok = np.linalg.norm(u, axis=1) > 1e-3
        u[ok] /= np.linalg.norm(u[ok], axis=1, keepdims=True)
        if ok.sum() >= 2:
            candidates.append((rotation_kabsch(u[ok], bear[ok]), c0))  # rig_from_world maps world dirs to bearings
            for _ in range(min(opts.ransac_iterations, n_pairs)):
                i, j = rng.choice(np.nonzero(ok)[0], 2, replace=False)
                if pts[i] != pts[j]:
                    candidates.append((rotation_kabsch(u[[i, j]], bear[[i, j]]), c0))
    if n_pts >= 3:
        by_point: dict[int, list[int]] = {}
        for k, p in enumerate(pts):
            by_point.setdefault(int(p), []).append(k)
        keys = sorted(by_point)
        trips = []  # the draws first (the same calls in the same order), then the triples' P3P together
        for _ in range(opts.ransac_iterations):
            trip = rng.choice(len(keys), 3, replace=False)
            trips.append([by_point[keys[t]][rng.integers(len(by_point[keys[t]]))] for t in trip])
        ks = np.array(trips, int).reshape(-1, 3)
        candidates.extend(p3p_candidates_batch(bear[ks], X[pts[ks]]))
    return candidates


def prior_grid(prior_centre: np.ndarray, sig_prior: np.ndarray) -> list[np.ndarray]:
    """Centres spread over the prior: 0, +-1, +-2 sigma up (+-10, 20, 40 m when the height is free), and +-1
    sigma east and north."""
    c0 = np.asarray(prior_centre, float)
    sh = [float(x) if np.isfinite(x) else 0.0 for x in sig_prior[:2]]
    dz = [k * float(sig_prior[2]) for k in (0, -1, 1, -2, 2)] if np.isfinite(sig_prior[2]) \
        else [0.0, -10.0, 10.0, -20.0, 20.0, -40.0, 40.0]
    return [c0 + np.array([0.0, 0.0, z]) for z in dz] + [c0 + np.array([i * sh[0], j * sh[1], 0.0])
                                                         for i, j in ((1, 0), (-1, 0), (0, 1), (0, -1))]


def best_candidate(candidates: list[tuple[np.ndarray, np.ndarray]], views: Sequence[RigView], obs: list[Pick],
                   X: np.ndarray, prior_centre: np.ndarray | None, prior_sigma_m: np.ndarray | float | None,
                   opts: GeorefOptions, headings: Sequence[HeadingPrior] = (),
                   track: TrackTerm | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """The candidate with the best bounded (MSAC-like) score over the control-point and track picks, less a small
    penalty for leaving the priors; the first of equal scores (None when no score is above -inf)."""
    if not candidates:
        return None
    thr = opts.ransac_threshold_px
    Rs = np.array([R for R, _ in candidates], float).reshape(-1, 3, 3)
    cs = np.array([c for _, c in candidates], float).reshape(-1, 3)
    step = max(1, _CHUNK_VALUES // max(len(obs), 1))
    score = np.concatenate([_msac(candidate_errors(Rs[a:a + step], cs[a:a + step], views, obs, X), thr)
                            for a in range(0, len(Rs), step)])
    m = max(len(obs), 1)
    if track is not None:
        coarse = track.coarse()
        for k, (R, c) in enumerate(candidates):
            e_t = np.abs(np.nan_to_num(coarse.errors(R, c, views)[0], nan=np.inf))
            score[k] += float(np.sum(np.maximum(0.0, 1.0 - (np.minimum(e_t, thr) / thr) ** 2)))
    if prior_centre is not None:
        sig = np.broadcast_to(np.asarray(prior_sigma_m if prior_sigma_m is not None else opts.prior_sigma_m,
                                         float), (3,))
        score -= 0.01 * np.sum(((cs - np.asarray(prior_centre, float)) / sig) ** 2, axis=1) / m
    if headings:
        hs = np.radians([h.sigma_deg for h in headings])
        for k, (R, _) in enumerate(candidates):
            score[k] -= 0.01 * float(np.sum((heading_errors(R, views, headings) / hs) ** 2)) / m
    score[np.isnan(score)] = -np.inf
    best = int(np.argmax(score))
    return candidates[best] if score[best] > -np.inf else None
