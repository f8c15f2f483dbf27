"""Starting poses from a carriage's own points: SQPnP (step 1), carried poses, and a pose's other PnP branches.

OpenCV (``cv2``) is imported where it is used: importing the solver should not pay for it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.geometry import exp_so3, rotation_angle_deg
from .layout import ChainLayout
from .model import SolveOptions
from .problem import Car, Chains, Poses, Problem, pixel_cost
from .trust_region import levenberg_marquardt

log = logging.getLogger(__name__)


def pnp(P: np.ndarray, uv: np.ndarray, intr: CameraIntrinsics, cam_from_world: np.ndarray,
        xy: np.ndarray | None = None):
    """world_from_carriage (R, t) from SQPnP on undistorted normalised points and the reprojection sum of squares
    (px^2), or None on failure. ``xy``: the pixels ``uv`` already undistorted and normalised."""
    import cv2

    if xy is None:
        xy = intr.undistort(intr.normalized_from_pixels(uv))
    try:
        ok, rvec, tvec = cv2.solvePnP(P.astype(np.float64), xy.astype(np.float64).reshape(-1, 1, 2), np.eye(3),
                                      None, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return None
    if not ok:
        return None
    Rcc = cv2.Rodrigues(rvec)[0]
    tcc = tvec.reshape(3)
    Pc = P @ Rcc.T + tcc
    if np.any(Pc[:, 2] <= 0):
        return None
    e = intr.project(Pc) - uv
    sse = float(np.sum(e * e))
    M = np.asarray(cam_from_world, float)
    Rw, tw = M[:3, :3].T, -M[:3, :3].T @ M[:3, 3]
    return Rw @ Rcc, Rw @ tcc + tw, sse


def undistorted(prob: Problem, cars: list[Car], members, f: np.ndarray) -> dict:
    """(car, view) -> its pixels in that view undistorted and normalised at the focal ``f[view]``, computed one
    view at a time (the iterative undistortion is vectorised; per carriage it would cost ~10x more)."""
    out = {}
    for v in sorted({v for _, v in members}):
        mv = [(k, cars[k].views == v) for k, w in members if w == v]
        uv = np.concatenate([cars[k].uv[sel] for k, sel in mv])
        intr = prob.intrinsics(v, f[v])
        xy = intr.undistort(intr.normalized_from_pixels(uv))
        o = 0
        for k, sel in mv:
            n = int(sel.sum())
            out[(k, v)] = xy[o:o + n]
            o += n
    return out


def pnp_start(prob: Problem, cars: list[Car], solo: list[int], poses: Poses) -> None:
    """Step 1's start (in place): every carriage of ``solo`` from SQPnP in the view where it has most points (at
    the focal ``poses.f``); one with no view of 4 points starts 30 m in front of its first camera."""
    views, f, R, t = prob.views, poses.f, poses.R, poses.t
    members = [(k, v) for k in solo for v in range(len(views)) if np.sum(cars[k].views == v) >= 4]
    xy = undistorted(prob, cars, members, f) if members else {}
    for k in solo:
        c = cars[k]
        best = None
        for v in range(len(views)):
            sel = c.views == v
            if sel.sum() < 4:
                continue
            r = pnp(c.P[sel], c.uv[sel], prob.intrinsics(v, f[v]), views[v].cam_from_world, xy[(k, v)])
            if r is not None and (best is None or sel.sum() > best[3]):
                best = (r[0], r[1], r[2], sel.sum())
        if best is None:  # no single view with 4 points: start in front of the first camera
            v = int(c.views[0])
            cc = views[v].camera_centre
            M = np.asarray(views[v].cam_from_world)
            R[k] = np.eye(3)
            t[k] = cc + M[2, :3] * 30.0
        else:
            R[k], t[k] = best[0], best[1]


def place_carried(poses: Poses, cars: list[Car], chains: list[list[int]], solved) -> None:
    """Pose every carriage not in ``solved`` from its chain neighbours (in place): same rotation, front coupler
    on the neighbour's rear coupler; forwards then backwards along each chain."""
    R, t = poses.R, poses.t
    placed = set(solved)
    for ch in chains:
        for _ in range(2):
            for j in range(1, len(ch)):
                a, b = ch[j - 1], ch[j]
                if a in placed and b not in placed:
                    R[b] = R[a]
                    t[b] = t[a] + R[a] @ cars[a].c_rear - R[b] @ cars[b].c_front
                    placed.add(b)
            for j in range(len(ch) - 2, -1, -1):
                a, b = ch[j], ch[j + 1]
                if b in placed and a not in placed:
                    R[a] = R[b]
                    t[a] = t[b] + R[b] @ cars[b].c_front - R[a] @ cars[a].c_rear
                    placed.add(a)


def refine_alone(prob: Problem, cars: list[Car], solo: list[int], poses: Poses, focal_views: list[list[int]],
                 options: SolveOptions):
    """Every carriage of ``solo`` refined on its own pixels (couplers off; the focal of ``focal_views`` shared):
    a block-diagonal problem, one loop of the sparse solver. Returns (poses, evaluations, message, ok)."""
    lay = ChainLayout(Chains.singletons(solo), True, focal_views, cars, poses)
    res = levenberg_marquardt(prob, lay, None, options)
    return lay.poses(res.x), res.nfev, res.message, res.ok


def _branch_starts(P: np.ndarray, xy: np.ndarray, Rc0: np.ndarray, tc0: np.ndarray, number: str):
    """Camera-frame poses (R, t) of a carriage's points ``P`` that fit its normalised pixels ``xy``: OpenCV's
    EPnP and iterative PnP, IPPE on the best-fit plane of the points, and the pose ``(Rc0, tc0)`` mirrored in
    the line of sight (the weak-perspective ambiguity)."""
    import cv2

    starts: list[tuple[np.ndarray, np.ndarray]] = []

    def add(rvec, tvec):
        Rc = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
        tc = np.asarray(tvec, np.float64).reshape(3)
        if np.all((P @ Rc.T + tc)[:, 2] > 0):
            starts.append((Rc, tc))

    for flag in (cv2.SOLVEPNP_EPNP, cv2.SOLVEPNP_ITERATIVE):
        try:
            n, rv, tv, _ = cv2.solvePnPGeneric(P, xy, np.eye(3), None, flags=flag)
            for r_, t_ in zip(rv, tv):
                add(r_, t_)
        except cv2.error as exc:  # that solver gives no branch here; the others may
            log.debug("car %s: PnP flag %d failed: %s", number, flag, exc)
    mu = P.mean(0)
    _, sv, Vt = np.linalg.svd(P - mu)
    if np.linalg.det(Vt) < 0:
        Vt[2] *= -1
    if sv[0] > 0 and sv[2] / sv[0] < 0.3:  # near planar: the two poses of the plane
        Q = (P - mu) @ Vt.T
        Q[:, 2] = 0.0
        try:
            n, rv, tv, _ = cv2.solvePnPGeneric(Q, xy, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
            for r_, t_ in zip(rv, tv):
                Rc = cv2.Rodrigues(r_)[0] @ Vt
                add(cv2.Rodrigues(Rc)[0], t_.reshape(3) - Rc @ mu)
        except cv2.error as exc:  # no planar branches here; the others may still be tried
            log.debug("car %s: IPPE on its best-fit plane failed: %s", number, exc)
    # the current pose mirrored in the line of sight: the best-fit plane's normal reflected about the viewing ray
    cen = Rc0 @ mu + tc0
    ray = cen / np.linalg.norm(cen)
    nrm = Rc0 @ Vt[2]
    nm = 2.0 * float(nrm @ ray) * ray - nrm
    ax = np.cross(nrm, nm)
    sa, ca = float(np.linalg.norm(ax)), float(nrm @ nm)
    if sa > 1e-9:
        Rc = exp_so3(ax / sa * math.atan2(sa, ca)) @ Rc0
        add(cv2.Rodrigues(Rc)[0], cen - Rc @ mu)
    return starts


def pnp_branches(prob: Problem, cars: list[Car], k: int, poses: Poses, options: SolveOptions,
                 max_iterations: int = 30) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Other poses of carriage ``k`` that fit its own pixels in its view with most points (its PnP's other
    branches, :func:`_branch_starts`), each refined alone and kept when it fits about as well as the best of
    them (chi-square) and differs from the others and from ``poses.R[k]`` by more than 5 degrees. Returns
    ``[(R, t, sum of squared weighted residuals)]``."""
    c = cars[k]
    R, t, f = poses.R, poses.t, poses.f
    vs = [v for v in range(len(prob.views)) if np.sum(c.views == v) >= 4]
    if not vs:
        return []
    v = max(vs, key=lambda v: int(np.sum(c.views == v)))
    sel = c.views == v
    P, uv = c.P[sel].astype(np.float64), c.uv[sel]
    intr = prob.intrinsics(v, f[v])
    xy = intr.undistort(intr.normalized_from_pixels(uv)).astype(np.float64).reshape(-1, 1, 2)
    Mv = np.asarray(prob.views[v].cam_from_world, float)
    Rcw, tcw = Mv[:3, :3], Mv[:3, 3]
    starts = _branch_starts(P, xy, Rcw @ R[k], Rcw @ t[k] + tcw, c.number)
    if not starts:
        return []
    Rw, tw = Rcw.T, -Rcw.T @ tcw
    w = float(prob.w_noise[prob.by_car[k][0]]) if len(prob.by_car.get(k, [])) else 1.0
    one = Problem(cars, [k], prob.views, {k: w})
    opt = replace(options, max_iterations=max_iterations, robust_loss="linear")
    out: list[tuple[np.ndarray, np.ndarray, float]] = []
    for Rc, tc in starts:
        p2 = Poses(R.copy(), t.copy(), f)
        p2.R[k], p2.t[k] = Rw @ Rc, Rw @ tc + tw
        p2, *_ = refine_alone(one, cars, [k], p2, [], opt)
        out.append((p2.R[k].copy(), p2.t[k].copy(), pixel_cost(one, p2)))
    best = min(c_ for _, _, c_ in out)
    # about as good as the best: within its chi-square spread (sse / sigma^2 within 3 sqrt(2 dof) + 9)
    sig2 = options.pixel_sigma_px ** 2
    dof = max(2 * int(np.sum(sel)) - 6, 1)
    keep: list[tuple[np.ndarray, np.ndarray, float]] = []
    for Rk, tk, c_ in sorted(out, key=lambda e: e[2]):
        if 2.0 * (c_ - best) / sig2 > 3.0 * math.sqrt(2.0 * dof) + 9.0:
            continue
        if rotation_angle_deg(Rk, R[k]) < 5.0 or any(rotation_angle_deg(Rk, o[0]) < 5.0 for o in keep):
            continue
        keep.append((Rk, tk, c_))
    return keep
