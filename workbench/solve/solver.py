"""The solver's entry points: :func:`solve_consist` (the steps, then the results) and :func:`refine_from`.

Simultaneous pose of all carriages of a consist from a few 2D-3D marked points each, chained at the couplers;
the method is in ``docs/solver.md``.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import Any, Sequence

import numpy as np

from ..core.frames import hpr_from_rotation
from .active_set import ChainedFit, ChainedProblem
from .bias import correct
from .branches import overlapping_bodies
from .layout import full_cost
from .model import CarriageInput, CarriageResult, ChainLink, SolveOptions, SolveResult, View
from .plan import Plan, plan_consist
from .problem import (Car, Chains, Poses, Problem, carriage_weights, chain_cost, focal_groups, held_chains,
                      prepare_cars, record_warning)
from .steps import (SolveContext, bias_skip_reason, one_face_check, step_alone, step_all, step_bias, step_predictions,
                    step_terrain, step_translations)
from .terrain import Contact
from .uncertainty import attach_covariance, solution_model


def _carriage_results(cars: list[Car], plan: Plan, prob: Problem, poses: Poses, views: list[View],
                      contact: Contact | None) -> list[CarriageResult]:
    """Every carriage's result: pose, heading / pitch / roll, body centre, pixel residuals, terrain clearance."""
    R, t = poses.R, poses.t
    uv_all, *_ = prob.project(R, t, poses.f)
    results = []
    for k, c in enumerate(cars):
        cr = CarriageResult(index=k, number=c.number, type_id=str(c.ctype.id), status=plan.status[k],
                            n_points=plan.n_points[k])
        if plan.status[k] != "left_out":
            M = np.eye(4)
            M[:3, :3], M[:3, 3] = R[k], t[k]
            cr.world_from_carriage = M
            cr.hpr_deg = hpr_from_rotation(R[k])
            cr.body_centre_m = R[k] @ c.c_body + t[k]
            idx = prob.by_car[k]
            e = uv_all[idx] - prob.uv[idx]
            for i, row in enumerate(idx):
                vn = views[prob.view[row]].name
                cr.residuals_px.setdefault(vn, {})[c.names[i]] = (float(e[i, 0]), float(e[i, 1]))
            cr.rms_px = float(np.sqrt(np.mean(np.sum(e * e, axis=1)))) if len(idx) else None
            if contact is not None:
                cl = contact.clearance(R, t, k)
                cr.clearance_m = cl[0] if cl is not None else None
        results.append(cr)
    return results


def _link_records(chains: Chains, links: list[list[np.ndarray]]) -> list[dict]:
    out = []
    for c_, ch in enumerate(chains.members):
        for j in range(len(ch) - 1):
            T = links[c_][j]
            out.append({"front": ch[j], "rear": ch[j + 1], "slack_m": chains.slacks[c_][j],
                        "offset_m": T.tolist(), "offset_norm_m": float(np.linalg.norm(T))})
    return out


def _warn_focal_at_limit(s: SolveContext, f: np.ndarray) -> None:
    """Warn where an estimated focal ran to the edge of the search range."""
    lo_deg, hi_deg = s.options.hfov_range_deg
    views = s.views
    for grp in s.focal_views:
        intr = views[grp[0]].intrinsics
        hfov = math.degrees(2.0 * math.atan(0.5 * intr.width / f[grp[0]]))
        if hfov < lo_deg * 1.02 or hfov > hi_deg * 0.98:
            record_warning(
                s.warnings, None, "focal_at_limit",
                f"view(s) {', '.join(views[v].name for v in grp)}: the estimated focal ({f[grp[0]]:.0f} px, "
                f"{hfov:.1f} deg field of view) ran to the edge of the search range {lo_deg:g}-{hi_deg:g} deg "
                f"(solver.hfov_range_deg in project.toml): if the photo's field of view lies outside it, widen "
                f"it; else the photo shows too little perspective to tell the focal from the distance, and the "
                f"positions along the viewing direction are not determined: give the focal (a camera profile or "
                f"EXIF)")


def _warn_overlaps(s: SolveContext, poses: Poses) -> None:
    """Mark both carriages of every pair whose placed bodies share space (:func:`.branches.overlapping_bodies`):
    e.g. one carriage's face found on the other in a photo (the same type looks the same), so that its points put
    it where the other stands and fit there as well as the other's do."""
    placed = [k for k in range(len(s.cars)) if s.plan.status[k] != "left_out"]
    for i, j, depth in overlapping_bodies(s.cars, poses, placed):
        a, b = s.cars[i].number, s.cars[j].number
        for k, other in ((i, b), (j, a)):
            record_warning(
                s.warnings, s.cars[k], "overlap",
                f"car {s.cars[k].number}: its body and car {other}'s share space where the solution places them "
                f"({depth:.1f} m deep along every axis): at most one of the two "
                f"is where its pose says (one's points may lie on the other in a photo, a carriage that looks "
                f"alike), unless one body was driven into the other; its pose and its interval are doubtful: check "
                f"both against their photo overlays and pick their points by hand")


def _context(carriages: Sequence[CarriageInput], links: Sequence[ChainLink], views: list[View],
             options: SolveOptions, terrain: Any, refused: dict[int, str] | None = None,
             railways: Sequence[Any] = ()) -> SolveContext:
    cars = prepare_cars(carriages, views, options)
    wl: list[dict] = []
    plan = plan_consist(cars, links, options, wl, views, refused)
    weights = carriage_weights(cars, plan.active, options.weighting)
    prob = Problem(cars, plan.active, views, weights)
    used = [v for v in range(len(views)) if len(prob.by_view[v]) > 0]
    free = [v for v in used if not views[v].focal_known] or used  # the views marked unknown, else every one
    focal_views = focal_groups(views, free) if options.estimate_focal else []
    return SolveContext(cars, views, plan, prob, weights, focal_views, options, terrain, wl, railways=railways)


def _step4_facts(s: SolveContext) -> dict:
    return next(st for st in s.steps if st.name == "4_all").facts


def _steps_1_to_4(s: SolveContext) -> ChainedFit:
    poses, profile = step_alone(s)
    step_terrain(s, poses)
    fit3 = step_translations(s, poses)
    return step_all(s, fit3, poses, profile)


def solve_consist(carriages: Sequence[CarriageInput], links: Sequence[ChainLink], views: Sequence[View],
                  options: SolveOptions | None = None, terrain: Any = None,
                  railways: Sequence[Any] = ()) -> SolveResult:
    """Solve the poses of all carriages (and optionally the focal) from marked-point pixels: the steps of
    :mod:`.steps`, then the results and (``options.compute_covariance``) their covariance. ``railways``: the
    railway lines (scene frame) that the carriages marked ``on_track`` keep to (:mod:`.track_prior`)."""
    t_start = time.perf_counter()
    options = options or SolveOptions()
    views = list(views)
    s = _context(carriages, links, views, options, terrain, railways=railways)
    fit = _steps_1_to_4(s)
    refused: dict[int, str] = {}
    while True:  # one-face carriages whose focal the joint problem fixes too weakly: solved again without them
        more = one_face_check(s, fit.poses)
        if not more:
            break
        refused.update(more)
        rel, nfev, issued = _step4_facts(s)["focal_rel_sd"], s.nfev, {w["message"] for w in s.warnings}
        with warnings.catch_warnings(record=True) as caught:  # the plan's warnings again: issue the new ones only
            warnings.simplefilter("always")
            s = _context(carriages, links, views, options, terrain, refused, railways)
        for w in caught:
            if str(w.message) not in issued:
                warnings.warn(w.message, w.category, stacklevel=2)
        s.nfev += nfev
        fit = _steps_1_to_4(s)
        _step4_facts(s).setdefault("focal_rel_sd", rel)  # the figures that refused them
    fit, prob = step_predictions(s, fit)
    cost_at_minimum = full_cost(prob, s.cars, s.plan.chains, fit.poses, s.contact, options)
    bias = step_bias(s, prob, fit, cost_at_minimum)
    fit = bias.fit
    results = _carriage_results(s.cars, s.plan, prob, fit.poses, views, s.contact)
    _warn_overlaps(s, fit.poses)
    _warn_focal_at_limit(s, fit.poses.f)
    status = "converged" if not s.failures else "not_converged"
    if s.failures:
        record_warning(s.warnings, None, "not_converged", "solve did not converge: " + "; ".join(s.failures))
    f = fit.poses.f
    res = SolveResult(carriages=results, status=status, message="; ".join(s.failures) or "converged",
                      warnings=s.warnings, steps=s.steps, iterations=s.nfev, time_s=0.0, final_cost=bias.final_cost,
                      focal_px={views[v].name: float(f[v]) for v in range(len(views))}, sigma_focal_px={},
                      links=_link_records(s.plan.chains, fit.links), cost_at_minimum=cost_at_minimum,
                      bias_correction=bias.summary, track_prior=[r.to_dict() for r in s.track_records])
    if options.compute_covariance and s.plan.active:
        # with the bias correction: the covariance (and the pixel sigma) of the minimum, centred on the corrected
        # poses
        attach_covariance(res, prob, fit.poses, s.focal_views, s.plan.chains, s.contact, options, model=bias.model)
    res.time_s = time.perf_counter() - t_start
    return res


def _pose_matrices(poses: Poses) -> list[np.ndarray]:
    out = []
    for k in range(len(poses.R)):
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = poses.R[k], poses.t[k]
        out.append(M)
    return out


def refine_from(carriages: Sequence[CarriageInput], links: Sequence[ChainLink], views: Sequence[View],
                world_from_carriage: Sequence[np.ndarray], options: SolveOptions | None = None) -> dict:
    """Diagnostic, not a solve: step 4 alone (every pose, and the focal when ``options.estimate_focal``, couplers
    on, no terrain) started from the given poses (4, 4) and the views' focal: for a benchmark, from the truth,
    to tell a solver failure (a higher cost) from the estimator's own spread. Every carriage must be observable
    alone and every link held or absent. Returns ``{"world_from_carriage", "focal_px", "cost" (pixels + coupler
    prior), "converged"}``, with ``options.bias_correction`` the corrected poses and focal (and
    ``"world_from_carriage_minimum"`` / ``"focal_px_minimum"`` those of the minimum) and ``"bias_correction"``."""
    options = options or SolveOptions()
    views = list(views)
    cars = prepare_cars(carriages, views, options)
    N = len(cars)
    chains = Chains(*held_chains(N, links))
    active = list(range(N))
    prob = Problem(cars, active, views, carriage_weights(cars, active, options.weighting))
    start = Poses(np.array([np.asarray(M, float)[:3, :3] for M in world_from_carriage]),
                  np.array([np.asarray(M, float)[:3, 3] for M in world_from_carriage]),
                  np.array([v.intrinsics.fx for v in views], dtype=float))
    used = [v for v in range(len(views)) if len(prob.by_view[v]) > 0]
    fv = focal_groups(views, [v for v in used if not views[v].focal_known] or used) if options.estimate_focal else []
    fit = ChainedProblem(prob, cars, chains, fv, None, options).solve(start)
    res = {"world_from_carriage": _pose_matrices(fit.poses),
           "focal_px": {v.name: float(fit.poses.f[i]) for i, v in enumerate(views)},
           "cost": chain_cost(prob, fit.poses, fit.links, chains.slacks, options.pixel_sigma_px),
           "converged": bool(fit.ok)}
    skip = bias_skip_reason(options, fv) if options.bias_correction else "off"
    if options.bias_correction and skip:
        res["bias_correction"] = {"applied": False, "note": skip}
    elif options.bias_correction:
        model = solution_model(prob, fit.poses, fv, chains, None, options)
        bc = correct(prob, cars, fit.poses, fv, chains, None, model, options.pixel_sigma_px,
                     max_over_sd=options.bias_max_over_sd)
        if bc.applied:
            res["world_from_carriage_minimum"], res["focal_px_minimum"] = res["world_from_carriage"], res["focal_px"]
            res["world_from_carriage"] = _pose_matrices(Poses(bc.R, bc.t, bc.f))
            res["focal_px"] = {v.name: float(bc.f[i]) for i, v in enumerate(views)}
        res["bias_correction"] = bc.summary()
    return res
