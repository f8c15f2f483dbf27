"""After a chained solve: carriages that may sit on the wrong branch of their own PnP, restarted elsewhere.

A carriage whose pixels the chained solution does not fit (chi-square), or one with too few points for its fit
to tell (:data:`FEW_POINTS`), is restarted from its other PnP branches (and, for the latter, from poses carried
from its chain neighbours); the chained cost judges. ``docs/solver.md``, "A carriage on the wrong branch".
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np
from scipy.special import gammaincinv  # the chi-square quantile as scipy.stats computes it, without its import

from ..core.geometry import rotation_angle_deg
from .active_set import ChainedFit, ChainedProblem
from .pnp import pnp_branches
from .problem import Car, Poses, Problem
from .terrain import rest_on_terrain

# A carriage with at most this many distinct points cannot show a wrong PnP branch in its own pixels (4 or 5
# points fit P3P's other poses with a chi-square of 2 to 4 degrees of freedom): the chained cost judges them
FEW_POINTS = 5


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
        if x > 2.0 * float(gammaincinv(max(m - 6, 1) / 2, 1.0 - p_value)) and x / m > relative * med:
            out.append(k)
    return sorted(out, key=lambda k: -c2[k][0] / c2[k][1])


def neighbour_poses(cars: list[Car], chains: list[list[int]], k: int, poses: Poses):
    """Poses of carriage ``k`` carried from each chain neighbour over the held coupling: the neighbour's rotation
    (the jack-knife angle is what is lost) and the coupler on the neighbour's."""
    R, t = poses.R, poses.t
    out = []
    for ch in chains:
        if k not in ch or len(ch) < 2:
            continue
        j = ch.index(k)
        if j > 0:
            a = ch[j - 1]
            out.append((R[a].copy(), t[a] + R[a] @ cars[a].c_rear - R[a] @ cars[k].c_front))
        if j < len(ch) - 1:
            b = ch[j + 1]
            out.append((R[b].copy(), t[b] + R[b] @ cars[b].c_front - R[b] @ cars[k].c_rear))
    return out


@dataclass
class BranchRetry:
    """What :func:`retry_branches` found: the cheaper solution (None: none), evaluations spent, notes."""

    fit: ChainedFit | None = None
    nfev: int = 0
    notes: list[str] = field(default_factory=list)
    restarted: list[dict] = field(default_factory=list)  # {"car", "from"}: cars restarted from another start
    not_tried: list[str] = field(default_factory=list)  # cars the evaluation cap left untried


@dataclass
class _Candidate:
    fit: ChainedFit
    cost: float
    R: np.ndarray  # the restarted carriage's start
    t: np.ndarray
    how: str


def _cheapest_restart(cp: ChainedProblem, k: int, alts: list, sol: Poses, cost: float, terrain, nfev: int,
                      max_nfev: int) -> tuple[_Candidate | None, int]:
    """Step 4 (capped at 40 evaluations) from ``sol`` with carriage ``k`` on each start of ``alts`` (rested on the
    terrain when given); the cheapest if cheaper than ``cost``, and the evaluations spent so far."""
    options = cp.options
    opt3 = replace(options, max_iterations=min(int(options.max_iterations), 40))
    best: _Candidate | None = None
    best_cost = cost
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
        if c2 < best_cost * (1.0 - 1e-9):
            best_cost = c2
            best = _Candidate(fit, c2, Rk, start.t[k].copy(), how)
        if nfev >= max_nfev:
            break
    if best is not None and (not best.fit.ok or opt3.max_iterations < options.max_iterations):
        fit = cp.solve(best.fit.poses)  # the cheapest, converged
        nfev += fit.nfev
        c2 = cp.cost(fit.poses)
        if c2 <= best.cost:
            best.fit, best.cost = fit, c2
    return best, nfev


def retry_branches(cp: ChainedProblem, solo: Sequence[int], start: Poses, sol: Poses, terrain=None,
                   max_cars: int = 3, max_nfev: int = 10**9, few_points: bool = True,
                   one_face: Sequence[int] = ()) -> BranchRetry:
    """Restart carriages of the chained solution ``sol`` (found from step 3's ``start``) on other poses and keep
    the cheapest chained solution: the misfit carriages (worst first, at most ``max_cars``) from their other PnP
    branches (from ``start``), and with ``few_points`` every chained carriage with at most :data:`FEW_POINTS`
    points (fewest first) and every carriage of ``one_face`` (one-face carriages posed at an estimated focal,
    chained or not: a plane's two PnP poses fit about equally) also from its neighbours' poses (from ``sol``).
    No new start once ``max_nfev`` evaluations are spent."""
    cars, options = cp.cars, cp.options
    solo_set = set(solo)
    chained = [k for ch in cp.chains.members if len(ch) > 1 for k in ch if k in solo_set]
    sig = options.pixel_sigma_px
    flagged = misfit_cars(cp.prob, sol, sig, chained)
    few = sorted((k for k in chained if len(cars[k].distinct) <= FEW_POINTS),
                 key=lambda k: len(cars[k].distinct)) if few_points else []
    few += [k for k in one_face if k in solo_set and k not in few]
    if not flagged and not few:
        return BranchRetry()
    cost = cp.cost(sol)
    out = BranchRetry()
    tried: set[int] = set()
    n_flag_tried = 0
    start = Poses(start.R.copy(), start.t.copy(), start.f)
    while out.nfev < max_nfev:
        k = next((i for i in flagged if i not in tried), None) if n_flag_tried < max_cars else None
        if k is not None:
            n_flag_tried += 1
        else:
            k = next((i for i in few if i not in tried), None)
        if k is None:
            break
        tried.add(k)
        alts = [(Rk, tk, "another PnP branch") for Rk, tk, _ in pnp_branches(cp.prob, cars, k, start, options)]
        if k in few:
            alts += [(Rk, tk, "a pose carried from its neighbour")
                     for Rk, tk in neighbour_poses(cars, cp.chains.members, k, sol)
                     if rotation_angle_deg(Rk, sol.R[k]) >= 5.0]
        best, out.nfev = _cheapest_restart(cp, k, alts, sol, cost, terrain, out.nfev, max_nfev)
        if best is not None:
            out.restarted.append({"car": cars[k].number, "from": best.how})
            out.notes.append(f"car {cars[k].number} restarted from {best.how} "
                             f"({rotation_angle_deg(best.R, sol.R[k]):.0f} deg from the solution's): cost "
                             f"{cost:.1f} -> {best.cost:.1f}")
            cost, out.fit = best.cost, best.fit
            sol = best.fit.poses
            start.R[k], start.t[k] = best.R, best.t
            flagged = misfit_cars(cp.prob, sol, sig, chained)
    left = [i for i in (flagged[:max_cars] + few) if i not in tried]
    if out.nfev >= max_nfev and left:
        out.not_tried = [cars[i].number for i in dict.fromkeys(left)]
        out.notes.append(f"branch check stopped after {out.nfev} evaluations (its cap): car(s) "
                         f"{', '.join(cars[i].number for i in dict.fromkeys(left))} not tried on other poses")
    return out
