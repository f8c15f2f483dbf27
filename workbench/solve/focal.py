"""Starting focal for an unknown focal: the per-carriage PnP sweep and, on a chained consist, the chained profile.

One carriage seen from afar shows too little perspective for its PnP error to tell the focal (the error falls
towards the affine limit, the longest focal); the couplers tell it well. ``docs/solver.md``, "Unknown focal".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .active_set import ChainedProblem
from .branches import retry_branches
from .model import SolveOptions
from .pnp import place_carried, pnp, pnp_start, refine_alone, undistorted
from .problem import Car, Chains, Poses, Problem, chain_cost


def focal_grid(width_px: int, hfov_range_deg: tuple[float, float], step_ratio: float) -> np.ndarray:
    """Focals (px) from the widest field of view to the narrowest, log-spaced, neighbours ``step_ratio`` apart."""
    lo, hi = hfov_range_deg
    half_w = 0.5 * width_px
    f_short, f_long = half_w / math.tan(math.radians(hi) / 2.0), half_w / math.tan(math.radians(lo) / 2.0)
    n = max(3, int(math.ceil(math.log(f_long / f_short) / math.log(step_ratio))) + 1)
    return np.geomspace(f_short, f_long, n)


def focal_sweep(prob: Problem, cars: list[Car], solo: list[int], group: list[int],
                options: SolveOptions) -> float | None:
    """The focal (px) of least total PnP reprojection error over the views of ``group`` (one camera), swept
    over the horizontal field-of-view range; None when no carriage has 4 points in one of its views."""
    intr0 = prob.views[group[0]].intrinsics
    fs = focal_grid(intr0.width, options.hfov_range_deg, options.hfov_step_ratio)
    members = [(k, v) for v in group for k in solo if np.sum(cars[k].views == v) >= 4]
    if not members:
        return None
    best = (np.inf, None)
    for fv in fs:
        tot = 0.0
        xy = undistorted(prob, cars, members, np.full(len(prob.views), fv))
        for k, v in members:
            sel = cars[k].views == v
            r = pnp(cars[k].P[sel], cars[k].uv[sel], prob.intrinsics(v, fv), prob.views[v].cam_from_world,
                    xy[(k, v)])
            tot += r[2] if r is not None else 1e12
        if tot < best[0]:
            best = (tot, fv)
    return best[1]


@dataclass
class FocalProfile:
    """The best fixed-focal chained solve of the profile (no terrain), its cost (:func:`.problem.chain_cost`) and
    the number of fixed-focal chained solves it took."""

    poses: Poses
    cost: float
    evaluations: int = 0


class _Profiler:
    """Ranks a focal by a quick fixed-focal chained solve from PnP (see :func:`chained_focal_profile`)."""

    def __init__(self, prob: Problem, cars: list[Car], chains: Chains, solo: list[int], options: SolveOptions,
                 max_evaluations: int):
        self.prob, self.cars, self.chains, self.solo, self.options = prob, cars, chains, solo, options
        # a ranking, not a solve: a few LM evaluations per focal (near the right focal the cost is then within a
        # few per cent of its fixed-focal minimum; far off it is an upper bound, far above)
        opt = replace(options, max_iterations=min(int(options.max_iterations), max_evaluations))
        self.cp = ChainedProblem(prob, cars, chains, [], None, opt)
        self.solo_prob = prob.subset(solo)

    def evaluate(self, fv: np.ndarray) -> FocalProfile:
        prob, cars, solo, cp = self.prob, self.cars, self.solo, self.cp
        N = len(cars)
        p = Poses(np.tile(np.eye(3), (N, 1, 1)), np.zeros((N, 3)), fv)
        pnp_start(prob, cars, solo, p)
        # step 1's unchained refinement (as at a known focal): SQPnP's algebraic fit alone can leave a distant
        # carriage in the mirrored-tilt basin, from which the chained solve does not return
        p, *_ = refine_alone(self.solo_prob, cars, solo, p, [], cp.options)
        place_carried(p, cars, self.chains.members, solo)
        start = Poses(p.R.copy(), p.t.copy(), fv)
        fit = cp.solve(Poses(p.R, p.t, fv))
        # a carriage on the wrong branch of its PnP would spoil this focal's cost: its other branches are tried
        # (the few-point carriages' check is left to the final solve's: here it would multiply the profile's cost)
        retry = retry_branches(cp, solo, start, fit.poses, None, max_cars=1, few_points=False)
        if retry.fit is not None:
            fit = retry.fit
        poses = Poses(fit.poses.R, fit.poses.t, fit.poses.f.copy())
        return FocalProfile(poses, chain_cost(prob, poses, fit.links, self.chains.slacks,
                                              self.options.pixel_sigma_px))

    def group(self, grp: list[int], f: np.ndarray, n_grid: int) -> tuple[FocalProfile, int]:
        """The best focal of one focal group (the others at ``f``): ``n_grid`` focals log-spaced over the range
        plus the current one, then the two log-midpoints beside the best. Also the number of focals tried."""
        lo_deg, hi_deg = self.options.hfov_range_deg
        half_w = 0.5 * self.prob.views[grp[0]].intrinsics.width
        lf = np.log(half_w / np.tan(np.deg2rad(np.array([hi_deg, lo_deg])) / 2.0))
        grid = list(np.linspace(lf[0], lf[1], n_grid))
        ls = math.log(f[grp[0]])
        if min(abs(ls - g) for g in grid) > 0.01:
            grid.append(ls)
        tried: dict[float, FocalProfile] = {}
        calls = []

        def at(lg: float) -> None:
            fv = f.copy()
            fv[grp] = math.exp(lg)
            tried[lg] = self.evaluate(fv)
            calls.append(lg)

        for lg in grid:
            at(lg)
        srt = sorted(tried)
        lb = min(tried, key=lambda k: tried[k].cost)
        i = srt.index(lb)
        for j in (i - 1, i + 1):
            if 0 <= j < len(srt):
                at(0.5 * (lb + srt[j]))
        return min(tried.values(), key=lambda e: e.cost), len(calls)


def chained_focal_profile(prob: Problem, cars: list[Car], chains: Chains, solo: list[int],
                          focal_views: list[list[int]], f0: np.ndarray, options: SolveOptions, n_grid: int = 9,
                          max_evaluations: int = 10) -> FocalProfile:
    """Start for an unknown focal on a chained consist: the chained cost (every pose optimised, couplers on, no
    terrain) profiled over the focal of each focal group in turn; at each focal PnP, the carriage-by-carriage
    refinement and ``max_evaluations`` evaluations of the fixed-focal chained solve rank it. The best is then
    solved to convergence and returned."""
    profiler = _Profiler(prob, cars, chains, solo, options, max_evaluations)
    f = f0.copy()
    best: FocalProfile | None = None
    n_eval = 0
    for grp in focal_views:
        best, n = profiler.group(grp, f, n_grid)
        n_eval += n
        f = best.poses.f.copy()
    assert best is not None
    # the best focal's chained solve run to convergence: the reference of step 4's basin check
    fit = ChainedProblem(prob, cars, chains, [], None, options).solve(best.poses)
    poses = Poses(fit.poses.R, fit.poses.t, fit.poses.f.copy())
    return FocalProfile(poses, chain_cost(prob, poses, fit.links, chains.slacks, options.pixel_sigma_px),
                        n_eval + 1)
