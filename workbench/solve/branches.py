"""After a chained solve: carriages that may sit on the wrong branch of their own PnP, restarted elsewhere.

A carriage whose pixels the chained solution does not fit (chi-square), or one with too few points for its fit
to tell (:data:`FEW_POINTS`), is restarted from its other PnP branches (and, for the latter, from poses carried
from its chain neighbours); the chained cost judges. A carriage ``carried`` by its chain (too few points to be posed
alone) is restarted from turns about its held couplings and from either side and its roof. Where a restart ends
in another minimum that fits nearly as well (:data:`AMBIGUOUS_CHI2`), the carriage's pose is ambiguous: the
stage marks it doubtful. ``docs/solver.md``, "A carriage on the wrong branch".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from ..core.geometry import boxes_depth, boxes_overlap, exp_so3, log_so3, rot_x, rot_z, rotation_angle_deg
from .active_set import ChainedFit, ChainedProblem
from .layout import ChainLayout, residuals_and_jacobian
from .loss import chi2_quantile
from .pnp import pnp_branches
from .problem import Car, Poses, Problem
from .terrain import rest_on_terrain

# A carriage with at most this many distinct points cannot show a wrong PnP branch in its own pixels (4 or 5
# points fit P3P's other poses with a chi-square of 2 to 4 degrees of freedom): the chained cost judges them
FEW_POINTS = 5

# Another minimum of the chained cost is a rival to the solution when its chi-square is at most this much higher:
# with equal prior odds its posterior probability is then at least 1 % (2 ln 99). A carriage with a rival 10 deg or
# more away, beyond a ridge of the cost (not the same valley), is marked ambiguous.
AMBIGUOUS_CHI2 = 2.0 * math.log(99.0)
RIVAL_MIN_DEG = 10.0
# a rival that puts the carriage's body this deep (m, along every axis) into another carriage's is no rival: two
# bodies cannot share that much space (a telescoped car, one body driven into the next, is not covered)
RIVAL_OVERLAP_M = 0.5
# a carried carriage's starts about each held coupling: turned about the scene's up (a jack-knife), and rolled
# about its own length onto either side or its roof
COUPLER_TURNS_DEG = (-135.0, -90.0, -60.0, -30.0, 30.0, 60.0, 90.0, 135.0, 180.0)
COUPLER_ROLLS_DEG = (-90.0, 90.0, 180.0)


def car_chi2(prob: Problem, poses: Poses, sigma: float) -> dict[int, tuple[float, int]]:
    """Per carriage of ``prob``: (sum of its whitened squared pixel residuals at sigma, its number of rows)."""
    uv, *_ = prob.project(poses.R, poses.t, poses.f)
    e = (uv - prob.uv) * (prob.w / np.where(prob.w_noise > 0, prob.w_noise, 1.0))[:, None] / sigma
    e2 = np.sum(e * e, axis=1)
    return {k: (float(np.sum(e2[idx])), 2 * len(idx)) for k, idx in prob.by_car.items()}


def misfit_cars(prob: Problem, poses: Poses, sigma: float, cands: Sequence[int], p_value: float = 1e-4,
                relative: float = 4.0) -> list[int]:
    """The carriages of ``cands`` whose pixels the solution does not fit, worst first: chi-square beyond its
    (1 - ``p_value``) quantile with 2 n - 6 degrees of freedom, *and* more than ``relative`` times the median
    carriage's misfit per row (so that a wrongly configured pixel sigma does not flag every carriage)."""
    c2 = car_chi2(prob, poses, sigma)
    per = [c2[k][0] / max(c2[k][1], 1) for k in c2]
    med = float(np.median(per)) if per else 0.0
    out = []
    for k in cands:
        x, m = c2[k]
        if x > chi2_quantile(1.0 - p_value, max(m - 6, 1)) and x / m > relative * med:
            out.append(k)
    return sorted(out, key=lambda k: -c2[k][0] / c2[k][1])


def held_couplings(cars: list[Car], chains: list[list[int]], k: int, poses: Poses) -> list[tuple]:
    """Carriage ``k``'s held couplings at ``poses``: ``(neighbour index, the coupling's point in the world (3,),
    k's coupler there in its own frame (3,))`` for each chain neighbour, front then rear."""
    R, t = poses.R, poses.t
    out = []
    for ch in chains:
        if k not in ch or len(ch) < 2:
            continue
        j = ch.index(k)
        if j > 0:
            a = ch[j - 1]
            out.append((a, t[a] + R[a] @ cars[a].c_rear, cars[k].c_front))
        if j < len(ch) - 1:
            b = ch[j + 1]
            out.append((b, t[b] + R[b] @ cars[b].c_front, cars[k].c_rear))
    return out


def neighbour_poses(cars: list[Car], chains: list[list[int]], k: int, poses: Poses):
    """Poses of carriage ``k`` carried from each chain neighbour over the held coupling: the neighbour's rotation
    (the jack-knife angle is what is lost) and the coupler on the neighbour's."""
    return [(poses.R[a].copy(), p - poses.R[a] @ c) for a, p, c in held_couplings(cars, chains, k, poses)]


def coupler_starts(cars: list[Car], chains: list[list[int]], k: int, poses: Poses) -> list[tuple]:
    """Starts of carriage ``k`` about each of its held couplings at ``poses``: its rotation turned about the scene's
    up by :data:`COUPLER_TURNS_DEG` and rolled about its x axis by :data:`COUPLER_ROLLS_DEG`, its coupler kept on
    the neighbour's. ``[(R (3, 3), t (3,), how)]``."""
    Rk0 = poses.R[k]
    out = []
    for a, p, c in held_couplings(cars, chains, k, poses):
        other = cars[a].number
        turns = [(rot_z(math.radians(d)) @ Rk0, f"turned {d:+.0f} deg about its coupling with {other}")
                 for d in COUPLER_TURNS_DEG]
        rolls = [(Rk0 @ rot_x(math.radians(d)), f"rolled {d:+.0f} deg at its coupling with {other}")
                 for d in COUPLER_ROLLS_DEG]
        out += [(Rk, p - Rk @ c, how) for Rk, how in turns + rolls]
    return out


def chi2_of(cp: ChainedProblem, poses: Poses) -> float:
    """The chained problem's chi-square at ``poses``: its whitened pixel residuals (each row's own noise, at the
    pixel sigma) and its terrain contact and coupler prior rows (in units of the pixel sigma), unweighted by the
    per-carriage normalisation and without the robust loss."""
    prob, sig = cp.prob, cp.options.pixel_sigma_px
    lay = ChainLayout(cp.chains, True, [], cp.cars, poses, None, sig)
    r, _ = residuals_and_jacobian(prob, lay, lay.x0, cp.contact, False)
    m = 2 * len(prob.P)
    noise = np.repeat(np.where(prob.w_noise > 0, prob.w_noise, 1.0), 2)
    return float(np.sum((r[:m] / noise) ** 2) + np.sum(r[m:] ** 2)) / sig**2


def body_box(car: Car, poses: Poses, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Carriage ``i``'s body at ``poses`` as an oriented box (its type's first collision box): centre (3,), rotation
    box -> scene (3, 3), half extents (3,), as :func:`core.geometry.boxes_overlap` takes it."""
    c, h = car.ctype.collision_boxes()[0]
    return poses.R[i] @ np.asarray(c, float) + poses.t[i], poses.R[i], np.asarray(h, float)


def body_inside(cp: ChainedProblem, poses: Poses, k: int, depth_m: float = RIVAL_OVERLAP_M) -> str | None:
    """The number of a carriage whose body carriage ``k``'s body enters by more than ``depth_m`` at ``poses``
    (:func:`body_box`), or None."""
    ck, Rk, hk = body_box(cp.cars[k], poses, k)
    for i in cp.prob.active:
        if i != k and boxes_overlap(ck, Rk, hk, *body_box(cp.cars[i], poses, i), margin=-depth_m):
            return cp.cars[i].number
    return None


def overlapping_bodies(cars: Sequence[Car], poses: Poses, placed: Sequence[int],
                       depth_m: float = RIVAL_OVERLAP_M) -> list[tuple[int, int, float]]:
    """The pairs ``(i, j, depth)`` (``i < j``, of ``placed``) whose bodies (:func:`body_box`) share space more than
    ``depth_m`` deep along every axis at ``poses``: two carriages where one body stands. At most one of the two is
    where its pose says (a face matched on the other carriage, a wrong branch), unless one body was driven into the
    other (telescoping), which the solver does not model. Neighbours in the consist count
    only deeper than the narrower body's half width (or height): at a coupling, the inner corners of two jack-knifed
    boxes cross (a box is not the body's plan, which narrows at its ends), by up to about 1 m in the simulated
    consists (``solve.simulate``, jack-knives of 20-80 deg); a carriage placed on its neighbour shares its width."""
    boxes = {i: body_box(cars[i], poses, i) for i in placed}
    out = []
    ids = sorted(boxes)
    for a, i in enumerate(ids):
        for j in ids[a + 1:]:
            if np.linalg.norm(boxes[i][0] - boxes[j][0]) >= np.linalg.norm(boxes[i][2]) + np.linalg.norm(boxes[j][2]):
                continue  # their bounding spheres are apart (a long consist: most pairs)
            limit = depth_m if j - i > 1 else max(depth_m, float(min(boxes[i][2][1:].min(), boxes[j][2][1:].min())))
            d = boxes_depth(*boxes[i], *boxes[j])
            if d > limit:
                out.append((i, j, d))
    return out


def _between(a: Poses, b: Poses, s: float) -> Poses:
    """The poses a fraction ``s`` of the way from ``a`` to ``b`` (rotations along their geodesic)."""
    R = np.stack([Ra @ exp_so3(s * log_so3(Ra.T @ Rb)) for Ra, Rb in zip(a.R, b.R)])
    return Poses(R, (1.0 - s) * a.t + s * b.t, (1.0 - s) * a.f + s * b.f)


def ridge_between(cp: ChainedProblem, a: Poses, b: Poses, n: int = 7) -> float:
    """How far the chi-square rises between the minima ``a`` and ``b`` above the higher of the two, along the
    straight path between them (``n`` inner points): 0 where the path stays in one valley."""
    ends = max(chi2_of(cp, a), chi2_of(cp, b))
    inner = max(chi2_of(cp, _between(a, b, s)) for s in np.linspace(0.0, 1.0, n + 2)[1:-1])
    return max(inner - ends, 0.0)


@dataclass
class BranchRetry:
    """What :func:`retry_branches` found: the cheaper solution (None: none), evaluations spent, notes."""

    fit: ChainedFit | None = None
    nfev: int = 0
    notes: list[str] = field(default_factory=list)
    restarted: list[dict] = field(default_factory=list)  # {"car", "from"}: cars restarted from another start
    not_tried: list[str] = field(default_factory=list)  # cars the evaluation cap left untried
    # {"car" (index), "number", "angle_deg", "shift_m", "delta_chi2", "ridge_chi2", "from", "world_from_carriage"}:
    # a rival minimum
    ambiguous: list[dict] = field(default_factory=list)


@dataclass
class _Candidate:
    fit: ChainedFit
    cost: float
    R: np.ndarray  # the restarted carriage's start
    t: np.ndarray
    how: str


def _restarts(cp: ChainedProblem, k: int, alts: list, sol: Poses, cost: float, terrain, nfev: int,
              max_nfev: int) -> tuple[_Candidate | None, list[_Candidate], int]:
    """Step 4 (capped at 40 evaluations) from ``sol`` with carriage ``k`` on each start of ``alts`` (rested on the
    terrain when given): the cheapest if cheaper than ``cost`` (converged) and its body not inside another
    carriage's (:func:`body_inside`), every restart, and the evaluations spent so far."""
    options = cp.options
    opt3 = replace(options, max_iterations=min(int(options.max_iterations), 40))
    best: _Candidate | None = None
    best_cost = cost
    every = []
    for Rk, tk, how in alts:
        start = sol.copy()
        start.R[k], start.t[k] = Rk, tk
        if terrain is not None:
            M = np.eye(4)
            M[:3, :3], M[:3, 3] = Rk, tk
            M, dz = rest_on_terrain(M, cp.cars[k].ctype, terrain, options.terrain_samples)
            if np.isfinite(dz):
                start.t[k] = M[:3, 3]
        fit = cp.solve(start, options=opt3)
        nfev += fit.nfev
        c2 = cp.cost(fit.poses)
        every.append(_Candidate(fit, c2, Rk, start.t[k].copy(), how))
        if c2 < best_cost * (1.0 - 1e-9) and body_inside(cp, fit.poses, k) is None:  # not folded into another
            best_cost = c2
            best = every[-1]
        if nfev >= max_nfev:
            break
    if best is not None and (not best.fit.ok or opt3.max_iterations < options.max_iterations):
        fit = cp.solve(best.fit.poses)  # the cheapest, converged
        nfev += fit.nfev
        c2 = cp.cost(fit.poses)
        if c2 <= best.cost and body_inside(cp, fit.poses, k) is None:
            best = _Candidate(fit, c2, best.R, best.t, best.how)
    return best, every, nfev


def _rival(cp: ChainedProblem, k: int, every: list[tuple[Poses, str]], sol: Poses, nfev: int,
           max_tries: int = 3) -> tuple[dict | None, int]:
    """Among the restarts ``every`` (``(poses, how)``) of carriage ``k``, the lowest chi-square one that ends
    :data:`RIVAL_MIN_DEG` or more from ``sol``'s pose, converged, at most :data:`AMBIGUOUS_CHI2` above ``sol``'s
    chi-square (or below it: a carried carriage's restart better by less than that is not taken),
    beyond a ridge of the cost (one unit of chi-square or more: another valley, not the far end of the solution's
    own), its body not inside another carriage's (:func:`body_inside`) unless it fits better than the solution by
    more than :data:`AMBIGUOUS_CHI2` (then ``inside`` names that carriage: the solution's own fit is what the mark
    doubts; the pose that fits puts the body inside another, which only telescoped bodies or mismatched points
    explain); None if none. At most ``max_tries`` restarts are converged, each ending elsewhere than the others."""
    chi_sol = chi2_of(cp, sol)
    cands = sorted(((chi2_of(cp, P), P, how) for P, how in every
                    if rotation_angle_deg(P.R[k], sol.R[k]) >= RIVAL_MIN_DEG), key=lambda x: x[0])
    seen: list[np.ndarray] = []
    for chi, P, how in cands:
        if chi - chi_sol > 2.0 * AMBIGUOUS_CHI2 or len(seen) >= max_tries:  # capped fits: their minima may be
            break  # lower, but not by that much
        folded_ok = chi - chi_sol < -AMBIGUOUS_CHI2  # far better than the solution: named even inside another body
        if (body_inside(cp, P, k) is not None and not folded_ok) or \
                any(rotation_angle_deg(P.R[k], R) < RIVAL_MIN_DEG for R in seen):
            continue  # folded into another carriage, or a restart that ended where one already examined did
        seen.append(P.R[k])
        fit = cp.solve(P)
        nfev += fit.nfev
        angle = rotation_angle_deg(fit.poses.R[k], sol.R[k])
        d = chi2_of(cp, fit.poses) - chi_sol
        inside = body_inside(cp, fit.poses, k)
        if angle < RIVAL_MIN_DEG or d > AMBIGUOUS_CHI2 or (inside is not None and d >= -AMBIGUOUS_CHI2):
            continue
        ridge = ridge_between(cp, sol, fit.poses)
        if ridge < 1.0:
            continue
        car = cp.cars[k]
        shift = float(np.linalg.norm(fit.poses.R[k] @ car.c_body + fit.poses.t[k] - sol.R[k] @ car.c_body - sol.t[k]))
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = fit.poses.R[k], fit.poses.t[k]
        return {"car": k, "number": car.number, "angle_deg": angle, "shift_m": shift, "delta_chi2": d,
                "ridge_chi2": ridge, "from": how, "inside": inside, "world_from_carriage": M.tolist()}, nfev
    return None, nfev


def retry_branches(cp: ChainedProblem, solo: Sequence[int], start: Poses, sol: Poses, terrain=None,
                   max_cars: int = 3, max_nfev: int = 10**9, few_points: bool = True,
                   one_face: Sequence[int] = ()) -> BranchRetry:
    """Restart carriages of the chained solution ``sol`` (found from step 3's ``start``) on other poses and keep
    the cheapest chained solution: the misfit carriages (worst first, at most ``max_cars``) from their other PnP
    branches (from ``start``), and with ``few_points`` every chained carriage with at most :data:`FEW_POINTS`
    points (fewest first) and every carriage of ``one_face`` (one-face carriages posed at an estimated focal,
    chained or not: a plane's two PnP poses fit about equally) also from its neighbours' poses (from ``sol``), and
    every carried carriage (on its chain, not observable alone) from turns and rolls about its held couplings
    (:func:`coupler_starts`), whose restart is kept only when its chi-square is lower by more than
    :data:`AMBIGUOUS_CHI2` (the pose carried from its neighbour, the smaller jack-knife, stays where the data cannot
    tell). A carriage of the latter two kinds whose restarts find a rival minimum (:func:`_rival`) is listed in
    ``ambiguous``. No new start once ``max_nfev`` evaluations are spent."""
    cars, options = cp.cars, cp.options
    solo_set = set(solo)
    in_chains = [k for ch in cp.chains.members if len(ch) > 1 for k in ch]
    chained = [k for k in in_chains if k in solo_set]
    sig = options.pixel_sigma_px
    flagged = misfit_cars(cp.prob, sol, sig, chained)
    few = sorted((k for k in chained if len(cars[k].distinct) <= FEW_POINTS),
                 key=lambda k: len(cars[k].distinct)) if few_points else []
    few += [k for k in one_face if k in solo_set and k not in few]
    carried = [k for k in in_chains if k not in solo_set and k in cp.prob.by_car] if few_points else []
    if not flagged and not few and not carried:
        return BranchRetry()
    cost = cp.cost(sol)
    out = BranchRetry()
    tried: set[int] = set()
    n_flag_tried = 0
    start = Poses(start.R.copy(), start.t.copy(), start.f)
    spent = 0  # the evaluations of the misfit and few-point carriages (capped); a carried one runs all its starts
    while True:
        k = next((i for i in flagged if i not in tried), None) if n_flag_tried < max_cars and spent < max_nfev \
            else None
        if k is not None:
            n_flag_tried += 1
        elif spent < max_nfev:
            k = next((i for i in few if i not in tried), None)
        if k is None:
            k = next((i for i in carried if i not in tried), None)
        if k is None:
            break
        tried.add(k)
        if k in carried:
            alts = [(Rk, tk, "a pose carried from its neighbour")
                    for Rk, tk in neighbour_poses(cars, cp.chains.members, k, sol)
                    if rotation_angle_deg(Rk, sol.R[k]) >= 5.0]
            alts += coupler_starts(cars, cp.chains.members, k, sol)
        else:
            alts = [(Rk, tk, "another PnP branch") for Rk, tk, _ in pnp_branches(cp.prob, cars, k, start, options)]
        if k in few:
            alts += [(Rk, tk, "a pose carried from its neighbour")
                     for Rk, tk in neighbour_poses(cars, cp.chains.members, k, sol)
                     if rotation_angle_deg(Rk, sol.R[k]) >= 5.0]
        n0 = out.nfev
        # a carried carriage's starts all run (each capped at 40 evaluations): its rivals are what they find
        cap = n0 + max(max_nfev, 40 * len(alts)) if k in carried else n0 + max(max_nfev - spent, 0)
        best, every, out.nfev = _restarts(cp, k, alts, sol, cost, terrain, out.nfev, cap)
        ends = [(c.fit.poses, c.how) for c in every]
        if best is not None and k in carried and chi2_of(cp, best.fit.poses) > chi2_of(cp, sol) - AMBIGUOUS_CHI2:
            best = None  # cheaper, but not by what tells two poses apart: the carried pose stays, the rival is named
        if best is not None:
            ends.append((sol, "the solution before the restart"))
            out.restarted.append({"car": cars[k].number, "from": best.how})
            out.notes.append(f"car {cars[k].number} restarted from {best.how} "
                             f"({rotation_angle_deg(best.R, sol.R[k]):.0f} deg from the solution's): cost "
                             f"{cost:.1f} -> {best.cost:.1f}")
            cost, out.fit = best.cost, best.fit
            sol = best.fit.poses
            start.R[k], start.t[k] = best.R, best.t
            flagged = misfit_cars(cp.prob, sol, sig, chained)
        if k in few or k in carried:
            rival, out.nfev = _rival(cp, k, ends, sol, out.nfev)
            if rival is not None:
                out.ambiguous.append(rival)
        if k not in carried:
            spent += out.nfev - n0
    left = [i for i in (flagged[:max_cars] + few) if i not in tried]
    if spent >= max_nfev and left:
        out.not_tried = [cars[i].number for i in dict.fromkeys(left)]
        out.notes.append(f"branch check stopped after {out.nfev} evaluations (its cap): car(s) "
                         f"{', '.join(cars[i].number for i in dict.fromkeys(left))} not tried on other poses")
    return out
