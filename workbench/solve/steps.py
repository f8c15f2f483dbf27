"""The steps of a solve, settling the consist on its photos and the terrain (``docs/solver.md``, "The steps").

1. each carriage alone (PnP, then a joint refinement; an unknown focal from a sweep or the chained profile);
2. each carriage rested on the terrain along gravity;
3. couplers on, rotations held; 4. everything (with the terrain contact term), then the branch check;
4b. the predicted points checked against the measured ones; 5. the second-order bias removed.
Each step appends its :class:`StepStats` to the :class:`SolveContext`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from ..core.geometry import log_so3, rotation_angle_deg
from .active_set import ChainedFit, ChainedProblem
from .bias import correct
from .branches import retry_branches
from .focal import FocalProfile, chained_focal_profile, focal_sweep
from .layout import full_cost
from .model import SolveOptions, StepStats, View
from .plan import FOCAL_PINNED_REL_SD, Plan, best_view, focal_reason, focal_rel_sd
from .pnp import place_carried, pnp_start, refine_alone
from .problem import Car, Poses, Problem, chain_cost, pixel_cost, pose_changes, record_warning
from .terrain import Contact, rest_on_terrain, surface_samples, wheel_contact, wheel_points
from .track_prior import SoftRows, TrackPriorRecord, track_prior
from .uncertainty import CovarianceModel, pixel_rows, solution_model

CHI2_6_95 = 12.5916  # 95 % point of the chi-square distribution with 6 degrees of freedom
# beyond this (the 1 - 1e-4 point, as the misfit check's p-value) a released car's two poses, its measured points'
# and its face's, disagree more than the noise model allows once in 10,000 carriages: one of them is wrong
CHI2_6_DOUBT = 27.8563
# Step 4's decisions (step 4b's release of a car's predictions, the second look at a level carriage's wheels) judge
# by the covariance with a guided face's misfit on its own points and the carried points left out
# (uncertainty.covariance_model's guided_loading and count_carried False), the yardstick their limits were set
# with; the intervals count the guided faces' predictions and the carried points. Judged by the intervals'
# covariance, step 4b released the predictions of 3 more pose-search carriages on seeds 240000- to 242000- (the
# measured points alone then placed one 3.7 m off), and 3 carriages ended 5.3-6.0 sigma off unmarked where none
# had (docs/calibration.md, "Session 31")
DECISIONS_MODEL = {"guided_loading": False, "count_carried": False}


@dataclass
class SolveContext:
    """One solve's inputs and its running record (steps, warnings, evaluations, failure messages)."""

    cars: list[Car]
    views: list[View]
    plan: Plan
    prob: Problem
    weights: dict[int, float]
    focal_views: list[list[int]]
    options: SolveOptions
    terrain: Any
    warnings: list[dict]
    steps: list[StepStats] = field(default_factory=list)
    nfev: int = 0
    failures: list[str] = field(default_factory=list)
    samples: dict[int, np.ndarray] = field(default_factory=dict)  # step 2: each carriage's surface samples
    contact: Contact | SoftRows | None = None  # step 4's terrain contact term (and the track prior's rows)
    railways: Sequence[Any] = ()  # the railway lines (core.track.RailwayLine) for carriages on the rails
    track_records: list[TrackPriorRecord] = field(default_factory=list)

    def chained(self, prob: Problem | None = None, contact: Contact | None = None) -> ChainedProblem:
        return ChainedProblem(self.prob if prob is None else prob, self.cars, self.plan.chains, self.focal_views,
                              contact, self.options)

    def changes(self, before: Poses, after: Poses) -> list[dict]:
        return pose_changes(self.cars, self.plan.active, before, after)


def _initial_focal(s: SolveContext, f: np.ndarray) -> tuple[np.ndarray, FocalProfile | None, str]:
    """An unknown focal's start: the per-carriage sweep, then on a chained consist the chained profile."""
    views, plan, options = s.views, s.plan, s.options
    for grp in s.focal_views:
        # the carriages that pin the focal by themselves; a one-face carriage's PnP fits any focal about as well
        fb = focal_sweep(s.prob, s.cars, plan.pinning, grp, options)
        if fb is None and len(plan.pinning) < len(plan.solo):
            fb = focal_sweep(s.prob, s.cars, plan.solo, grp, options)
        names = ", ".join(views[v].name for v in grp)
        if fb is not None:
            f[grp] = fb
        else:
            record_warning(s.warnings, None, "focal", f"view(s) {names}: no carriage with 4 points in one photo; the "
                                                      f"focal sweep kept the given focal {f[grp[0]]:.1f} px")
    note = "focal sweep: " + ", ".join(f"{'+'.join(views[v].name for v in grp)}={f[grp[0]]:.1f}px"
                                       for grp in s.focal_views)
    profile = None
    if s.focal_views and any(len(ch) > 1 for ch in plan.chains.members):
        profile = chained_focal_profile(s.prob, s.cars, plan.chains, plan.solo, s.focal_views, f, options)
        f = profile.poses.f.copy()
        note += "; chained focal profile: " + ", ".join(
            f"{'+'.join(views[v].name for v in grp)}={f[grp[0]]:.1f}px" for grp in s.focal_views) + \
            f" ({profile.evaluations} fixed-focal chained solves)"
    return f, profile, note


def _pin_focal_first(s: SolveContext, poses: Poses, one_face: list[int]) -> str:
    """Step 1 with one-face carriages and an unknown focal (in place): the carriages that pin the focal posed by
    PnP and refined with it, then the one-face ones posed by PnP at that focal (the joint refinement follows)."""
    cars, pins = s.cars, s.plan.pinning
    pnp_start(s.prob, cars, pins, poses)
    fv = [g for g in s.focal_views if any(np.isin(cars[k].views, g).any() for k in pins)]
    poses_pin, nfev, *_ = refine_alone(Problem(cars, pins, s.views, s.weights), cars, pins, poses, fv, s.options)
    s.nfev += nfev
    poses.R[pins], poses.t[pins], poses.f[:] = poses_pin.R[pins], poses_pin.t[pins], poses_pin.f
    pnp_start(s.prob, cars, one_face, poses)
    return (f"{len(pins)} car(s) with points off one plane refined with the focal first ({nfev} evaluations), then "
            f"the one-face car(s) {', '.join(cars[k].number for k in one_face)} posed by PnP at that focal")


def step_alone(s: SolveContext) -> tuple[Poses, FocalProfile | None]:
    """Step 1: every carriage observable alone from PnP, then refined on its own pixels (and the focal); the
    carried ones placed from their neighbours. Returns the poses and the chained focal profile (or None)."""
    t1 = time.perf_counter()
    cars, plan, options = s.cars, s.plan, s.options
    N = len(cars)
    f = np.array([v.intrinsics.fx for v in s.views], dtype=float)
    note, profile = "", None
    if options.estimate_focal:
        f, profile, note = _initial_focal(s, f)
    poses = Poses(np.tile(np.eye(3), (N, 1, 1)), np.zeros((N, 3)), f)
    one_face = plan.one_face
    if one_face and profile is None and plan.pinning:
        note += ("; " if note else "") + _pin_focal_first(s, poses, one_face)
    else:
        pnp_start(s.prob, cars, plan.solo, poses)
    place_carried(poses, cars, plan.chains.members, plan.solo)
    init = poses.copy()
    cost0 = pixel_cost(s.prob, poses)
    # after a chained focal profile the focal is held here: unchained, the cost would pull it to the affine limit
    solo_prob = Problem(cars, plan.solo, s.views, s.weights)
    poses, nfev, msg, ok = refine_alone(solo_prob, cars, plan.solo, poses,
                                        s.focal_views if profile is None else [], options)
    s.nfev += nfev
    place_carried(poses, cars, plan.chains.members, plan.solo)  # carried ones follow their refined neighbours
    s.steps.append(StepStats("1_alone", True, (note + "; " if note else "") + "PnP (SQPnP) then joint refinement, "
                             "constraints off" + ("; carried cars placed from their neighbours"
                                                  if len(plan.solo) < len(plan.active) else ""),
                             cost0, pixel_cost(s.prob, poses), nfev, msg, time.perf_counter() - t1,
                             s.changes(init, poses),
                             {"focal_start": None if not options.estimate_focal else
                              "chained_profile" if profile is not None else "sweep",
                              "n_carried": len(plan.active) - len(plan.solo),
                              **({"one_face": [cars[k].number for k in one_face]} if options.estimate_focal else {}),
                              **plan.observability}))
    return poses, profile


def one_face_check(s: SolveContext, poses: Poses) -> dict[int, str]:
    """After step 4, with one-face carriages admitted: each estimated focal's relative sd in the joint problem at
    its solution ``poses`` (:func:`.plan.focal_rel_sd`: every active carriage's measured points, the couplings,
    one focal per camera, at the configured pixel sigma); the one-face carriages whose focal it fixes worse than
    :data:`.plan.FOCAL_PINNED_REL_SD` are returned with what they miss (the solve starts again without them). The
    figures go to step 4's facts."""
    plan = s.plan
    if not plan.one_face or not s.focal_views:
        return {}
    sigma = s.options.pixel_sigma_px
    rel = focal_rel_sd(s.cars, plan.active, s.views, poses, plan.chains, s.focal_views, sigma)
    names = [", ".join(s.views[v].name for v in g) for g in s.focal_views]
    next(st for st in s.steps if st.name == "4_all").facts.update(
        {"focal_rel_sd": dict(zip(names, rel)), "focal_pinned_rel_sd": FOCAL_PINNED_REL_SD})
    group_of = {v: i for i, g in enumerate(s.focal_views) for v in g}
    out = {}
    for k in plan.one_face:
        g = group_of.get(best_view(s.cars[k]))
        if g is not None and not rel[g] <= FOCAL_PINNED_REL_SD:
            out[k] = focal_reason(names[g], True, rel[g], sigma)
    return out


def step_terrain(s: SolveContext, poses: Poses) -> None:
    """Step 2 (in place): every carriage moved along gravity until it rests on the terrain."""
    t2 = time.perf_counter()
    cars, options, terrain = s.cars, s.options, s.terrain
    if terrain is None:
        s.steps.append(StepStats("2_terrain", False, "skipped: no terrain given"))
        return
    s.samples = {k: surface_samples(cars[k].ctype, options.terrain_samples) for k in s.plan.active}
    before = poses.copy()
    c0 = pixel_cost(s.prob, poses)
    for k in s.plan.active:
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = poses.R[k], poses.t[k]
        M, dz = rest_on_terrain(M, cars[k].ctype, terrain, options.terrain_samples)
        if not np.isfinite(dz):
            record_warning(s.warnings, cars[k], "terrain", f"car {cars[k].number}: outside the terrain; not moved "
                                                           f"in step 2")
            continue
        poses.t[k] = M[:3, 3]
    s.steps.append(StepStats("2_terrain", True, "lowered/raised along gravity (-z) onto the terrain", c0,
                             pixel_cost(s.prob, poses), 0, "done", time.perf_counter() - t2,
                             s.changes(before, poses)))


def step_translations(s: SolveContext, poses: Poses) -> ChainedFit:
    """Step 3: couplers on, rotations held, translations (and focal) optimised. It only starts step 4: with the
    rotations held (noisy) offsets often sit on the sphere where it converges slowly, so it is capped at 40."""
    t3 = time.perf_counter()
    c0 = pixel_cost(s.prob, poses)
    opt3 = replace(s.options, max_iterations=min(int(s.options.max_iterations), 40))
    fit = s.chained().solve(poses, rot_free=False, options=opt3)
    s.nfev += fit.nfev
    s.steps.append(StepStats("3_chain_translations", True, "couplers on, rotations held, translations"
                             + (" and focal" if s.focal_views else "") + f" optimised ({fit.rounds} active-set "
                             f"round(s), {fit.n_active} coupler(s) at the slack)", c0, pixel_cost(s.prob, fit.poses),
                             fit.nfev, fit.message, time.perf_counter() - t3, s.changes(poses, fit.poses),
                             {"active_set_rounds": fit.rounds, "links_at_slack": fit.n_active}))
    return fit


def _profile_check(s: SolveContext, cp: ChainedProblem, fit: ChainedFit,
                   profile: FocalProfile) -> tuple[ChainedFit, str]:
    """The solution (focal free) can cost no more than the profile's best fixed-focal solve; if it does, step 4
    ended in another basin: restart from the profile's, keep the cheaper. Returns the fit and a note."""
    c_sol = chain_cost(s.prob, fit.poses, fit.links, s.plan.chains.slacks, s.options.pixel_sigma_px)
    if not c_sol > profile.cost * (1.0 + 1e-6) + 1e-9:
        return fit, ""
    fit2 = cp.solve(profile.poses)
    s.nfev += fit2.nfev
    c_old, c2 = cp.cost(fit.poses), cp.cost(fit2.poses)
    note = (f"; ended at cost {c_sol:.1f} above the focal profile's best {profile.cost:.1f}: restarted from it, "
            f"cost {c2:.1f} (was {c_old:.1f})")
    return (fit2 if c2 < c_old else fit), note


def _rotation_covariances(s: SolveContext, poses: Poses) -> dict[int, np.ndarray]:
    """Each active carriage's rotation covariance (3, 3), rad^2, from its own pixels alone at ``poses`` (the focal
    held; its translation marginalised): what step 3's held rotation may be off by, for :func:`.terrain.wheel_contact`.
    Not finite where its pixels do not fix its pose."""
    J, _, col, _ = pixel_rows(s.prob, poses.R, poses.t, poses.f, [])
    w_noise = np.repeat(s.prob.w_noise, 2)
    sig = float(s.options.pixel_sigma_px)
    out = {}
    for k in s.plan.active:
        idx = [i for i in s.prob.by_car[k] if s.prob.measured[i]]  # predicted points carry no information
        rows = np.concatenate([2 * np.asarray(idx, dtype=int), 2 * np.asarray(idx, dtype=int) + 1])
        Jk = J[rows, col[k]:col[k] + 6] / (w_noise[rows, None] * sig)  # whitened: a weighted row's sd is w_noise sig
        H = Jk.T @ Jk
        if len(rows) < 6 or np.linalg.cond(H) > 1e12:
            out[k] = np.full((3, 3), np.nan)
            continue
        out[k] = np.linalg.inv(H)[:3, :3]
    return out


def _relevel(s: SolveContext, fit: ChainedFit, start: Poses, level: list[int], track: Any):
    """Step 4's second look at the carriages given their wheels' row unconfirmed (``level``: their wheels as level
    as their rotations from their own pixels could tell, not to within twice the terrain's stated accuracy): each
    judged again (:func:`.terrain.wheel_contact`'s spread test) at step 4's solution ``fit`` with its rotation's
    covariance there (the whole problem's: pixels, couplers, contact; the chain makes it tighter than its own
    pixels'), its wheels' tilt taken together too (:func:`.terrain.tilt_explained`: each wheel can pass alone while
    the roll is many sd off level; asked here, where the covariance is the one the intervals use, and not at step
    3, whose own-pixel covariance refused a level carriage in 1 of 301 at a 3 cm DEM). One whose wheels are then
    seen not level (a derailed carriage the step-3 test could not tell) goes
    back to the lowest point's row, and step 4 is solved again from step 3's ``start``. Returns (problem, fit,
    wheels, dropped carriages)."""
    model = solution_model(s.prob, fit.poses, s.focal_views, s.plan.chains, s.contact, s.options, **DECISIONS_MODEL)
    contact = s.contact.terrain_contact if isinstance(s.contact, SoftRows) else s.contact
    wheels, dropped = dict(contact.wheels), []
    for k in level:
        c = model.col.get(k)
        C = model.cov[c:c + 3, c:c + 3] if c is not None else np.full((3, 3), np.nan)
        if np.all(np.isfinite(C)) and wheel_contact(s.samples[k], fit.poses.R[k], fit.poses.t[k], s.terrain, C,
                                                    np.inf, tilt_test=True) == "lowest":
            wheels.pop(k)
            dropped.append(k)
    if not dropped:
        return s.chained(contact=s.contact), fit, wheels, dropped
    s.contact = Contact(s.terrain, s.samples, contact.scale, wheels=wheels)
    if track is not None:
        s.contact = SoftRows(s.contact, track)
    cp = s.chained(contact=s.contact)
    fit2 = cp.solve(start)
    s.nfev += fit2.nfev
    return cp, fit2, wheels, dropped


def step_all(s: SolveContext, fit3: ChainedFit, start3: Poses, profile: FocalProfile | None) -> ChainedFit:
    """Step 4: everything optimised (with the terrain contact term), the profile's basin check, then the branch
    check (:func:`.branches.retry_branches`, restarting from step 3's start ``start3``)."""
    t4 = time.perf_counter()
    options, terrain = s.options, s.terrain
    c0 = pixel_cost(s.prob, fit3.poses)
    wheels: dict[int, np.ndarray] = {}
    level: list[int] = []
    dropped: list[int] = []
    if terrain is not None and options.use_terrain_contact:
        # a carriage whose wheels are level at step 3's poses to within what its rotation's uncertainty explains
        # gets its wheels' contact row (unbiased by a noisy rotation; confirmed, or judged again at the solution:
        # _relevel); any other (derailed onto one end or side, on its side or roof) the lowest sample's
        cov_rot = _rotation_covariances(s, fit3.poses)
        nan3 = np.full((3, 3), np.nan)
        kinds = {k: wheel_contact(S, fit3.poses.R[k], fit3.poses.t[k], terrain, cov_rot.get(k, nan3),
                                  options.terrain_sigma_m) for k, S in s.samples.items()}
        level = [k for k, kind in kinds.items() if kind == "level"]
        wheels = {k: wheel_points(s.samples[k]) for k, kind in kinds.items() if kind != "lowest"}
        s.contact = Contact(terrain, s.samples, options.pixel_sigma_px / options.terrain_sigma_m, wheels=wheels)
    track, s.track_records = track_prior(s.cars, s.plan.active, fit3.poses.R, fit3.poses.t, s.railways,
                                         options.track_sigma_m, options.pixel_sigma_px, options.track_gate_m)
    for rec in s.track_records:
        if not rec.applied:
            record_warning(s.warnings, s.cars[rec.index], "track_prior", f"car {rec.number} is marked on the rails "
                           f"(on_track) but gets no track prior: {rec.reason}")
    if track is not None:
        s.contact = SoftRows(s.contact, track)
    cp = s.chained(contact=s.contact)
    fit = cp.solve(fit3.poses)
    s.nfev += fit.nfev
    nfev = fit.nfev
    if level:
        cp, fit, wheels, dropped = _relevel(s, fit, fit3.poses, level, track)
        nfev += fit.nfev
    nfev_34 = fit3.nfev + fit.nfev
    note = ""
    if profile is not None:
        fit, note = _profile_check(s, cp, fit, profile)
    retry = retry_branches(cp, s.plan.solo, start3, fit.poses, terrain, max_nfev=max(200, nfev_34),
                           one_face=sorted(set(s.plan.one_face) | set(s.plan.coplanar)))
    s.nfev += retry.nfev
    nfev += retry.nfev
    if retry.fit is not None:
        fit = retry.fit
    if retry.notes:
        note += "; " + "; ".join(retry.notes)
    for a in retry.ambiguous:
        where = f"{a['angle_deg']:.0f} deg and {a['shift_m']:.1f} m from the solution's"
        record_warning(s.warnings, s.cars[a["car"]], "ambiguous",
                       f"car {a['number']}: another pose, {where}, fits its points about as well (chi-square "
                       f"{a['delta_chi2']:+.1f}; restarted from {a['from']}): too few points tell them apart; its pose "
                       f"and its interval are doubtful (a measured point on another face would settle it)"
                       if a.get("inside") is None else
                       f"car {a['number']}: another pose, {where}, fits its points, couplings and the terrain far "
                       f"better (chi-square {a['delta_chi2']:+.1f}; restarted from {a['from']}), but puts its body "
                       f"inside car {a['inside']}'s: telescoped bodies, or mismatched points; its pose and its "
                       f"interval are doubtful (check its points; a measured point on another face would settle it)")
    terrain_contact = s.contact.terrain_contact if isinstance(s.contact, SoftRows) else s.contact
    note += (f"; soft terrain contact (sigma_z = {options.terrain_sigma_m} m; {len(wheels)} car(s) on all their "
             f"wheels: their wheels' mean clearance ({len(level) - len(dropped)} of them level to within their "
             f"attitude's uncertainty, confirmed at step 4's solution; {len(dropped)} dropped there), "
             f"{len(s.samples) - len(wheels)}: their lowest point's)"
             if terrain_contact is not None else
             ("; no terrain contact term (no terrain)" if terrain is None else "; terrain contact term off"))
    if track is not None:
        note += (f"; track prior for {len(track.cars) // 2} carriage(s) on the rails (bogie pivots over the line, "
                 f"sigma {options.track_sigma_m:g} m)")
    s.steps.append(StepStats("4_all", True, f"everything optimised ({fit.rounds} active-set round(s), "
                             f"{fit.n_active} coupler(s) at the slack)" + note, c0, pixel_cost(s.prob, fit.poses),
                             nfev, fit.message, time.perf_counter() - t4, s.changes(fit3.poses, fit.poses),
                             {"active_set_rounds": fit.rounds, "links_at_slack": fit.n_active,
                              "restarted": retry.restarted, "branch_check_not_tried": retry.not_tried,
                              "ambiguous": [{k: v for k, v in a.items() if k != "car"} for a in retry.ambiguous],
                              "terrain_contact": terrain_contact is not None,
                              "contact_on_wheels": [s.cars[k].number for k in sorted(wheels)],
                              "contact_level": [s.cars[k].number for k in sorted(set(level) - set(dropped))],
                              "contact_level_dropped": [s.cars[k].number for k in sorted(dropped)],
                              "track_prior_cars": [r.number for r in s.track_records if r.applied]}))
    if not fit.ok:
        s.failures.append(f"step 4: {fit.message}")
    return fit


def _prediction_shift(released: Problem, R, t, f, R_kept, t_kept, model: CovarianceModel) -> dict[int, float]:
    """Per carriage with predicted points: the squared Mahalanobis length of the shift from the fit with the
    predictions released (``R, t, f``: the measured points' fit, where ``model`` was taken) to the fit with them
    kept, in the released fit's pose covariance. About chi-square with 6 degrees of freedom or less under the
    noise model; larger: the predictions pulled the car where its measured points do not put it."""

    cov, col = model.cov, model.col
    out = {}
    for k in released.active:
        if released.measured[released.by_car[k]].all():
            continue
        d = np.concatenate([log_so3(R_kept[k] @ R[k].T), t_kept[k] - t[k]])
        C = cov[col[k]:col[k] + 6, col[k]:col[k] + 6]
        out[k] = float(d @ np.linalg.pinv(C, rcond=1e-12) @ d) if np.all(np.isfinite(C)) else float("inf")
    return out


def _release_in_turn(s: SolveContext, kept: ChainedFit, d2: dict[int, float], shift) -> tuple:
    """With some cars' predictions released and the others kept, the kept ones can pull further: the mixed fit
    is checked in turn and a car it moves beyond the limit is released too. Returns (cars released, the mixed
    problem and fit (None if not fitted), evaluations, the rounds' notes, each released car's shift chi-square when
    it was released)."""
    off = sorted(k for k, v in d2.items() if not v <= CHI2_6_95)
    at_release = {k: d2[k] for k in off}
    prob_m, fit_m, nfev, notes = None, None, 0, []
    while off and len(off) < len(d2):
        prob_m = s.prob.with_predictions_scaled(s.options.prediction_release, off)
        fit_m = s.chained(prob_m, s.contact).solve(kept.poses)
        nfev += fit_m.nfev
        d2m = shift(fit_m.poses)
        more = sorted(k for k, v in d2m.items() if k not in off and not v <= CHI2_6_95)
        if not more:
            break
        notes.append(", ".join(f"{s.cars[k].number} {d2m[k]:.1f}" for k in more))
        at_release.update({k: d2m[k] for k in more})
        off = sorted(set(off) | set(more))
    return off, prob_m, fit_m, nfev, notes, at_release


def _flag_disagreements(s: SolveContext, at_release: dict[int, float], kept: Poses, final: Poses) -> list[str]:
    """Warn (kind ``predictions_disagree``, a doubt: ``files.solution.DOUBT_KINDS``) on each released car whose
    shift chi-square exceeded :data:`CHI2_6_DOUBT`: its measured points put it in one place, the pose of the face
    they were matched on in another, and the noise model cannot explain the gap, so one of the two is wrong (a
    face's mirrored pose, points matched on the wrong face or car). The solve keeps the measured points' pose and
    their interval, which describe that pose's noise and not the choice between the two. Returns the cars'
    numbers. On the fresh-seed automatic incidents (docs/calibration.md) this names all 4 carriages 7-70 sigmas
    off, among 13 of 200."""
    out = []
    for k, d2 in sorted(at_release.items()):
        if not d2 > CHI2_6_DOUBT:
            continue
        car = s.cars[k]
        c = np.asarray(car.c_body, dtype=float)  # the body centre, carriage frame
        moved = float(np.linalg.norm(kept.R[k] @ c + kept.t[k] - final.R[k] @ c - final.t[k]))
        turned = rotation_angle_deg(kept.R[k], final.R[k])
        record_warning(s.warnings, car, "predictions_disagree",
                       f"car {car.number}: its measured points and the pose of the face they were matched on "
                       f"disagree (shift chi-square {d2:.0f} with 6 degrees of freedom, limit {CHI2_6_DOUBT:.1f}): "
                       f"the face's pose would put it {moved:.2f} m and {turned:.1f} deg from where its points "
                       f"do; one of the two is wrong (points matched on the wrong face or car, or a pose on the wrong "
                       f"branch); its pose and its interval are doubtful")
        out.append(car.number)
    return out


def step_predictions(s: SolveContext, fit: ChainedFit) -> tuple[ChainedFit, Problem]:
    """Step 4b: fit again with the predictions' sigmas x ``prediction_release``; a car whose predictions moved it
    beyond its covariance from that fit (chi-square, 6 dof, 95 %) keeps them released. Returns the fit and the
    problem (rows weighted as chosen)."""
    prob, options, cars = s.prob, s.options, s.cars
    n_pred = int((~prob.measured).sum())
    if n_pred == 0 or options.prediction_release <= 1.0:
        s.steps.append(StepStats("4b_predictions_checked", False, "skipped: no predicted points" if n_pred == 0
                                 else "skipped: solver.prediction_release = 1 (predictions keep their weight)"))
        return fit, prob
    t4b = time.perf_counter()
    kept = replace(fit, poses=fit.poses.copy())
    released = prob.with_predictions_scaled(options.prediction_release)
    rel = s.chained(released, s.contact).solve(fit.poses)
    nfev = rel.nfev
    s.nfev += rel.nfev
    rel_model = solution_model(released, rel.poses, s.focal_views, s.plan.chains, s.contact, options,
                               **DECISIONS_MODEL)
    rel_sol = replace(rel, poses=rel.poses.copy())

    def shift(p: Poses) -> dict[int, float]:
        return _prediction_shift(released, rel_sol.poses.R, rel_sol.poses.t, rel_sol.poses.f, p.R, p.t, rel_model)

    d2 = shift(kept.poses)
    listed = ", ".join(f"{cars[k].number} {d2[k]:.1f}" for k in sorted(d2))
    off, prob_m, fit_m, nfev_m, rounds_note, at_release = _release_in_turn(s, kept, d2, shift)
    nfev += nfev_m
    s.nfev += nfev_m
    extra = (f"; then, with those released, the remaining predictions moved car(s) beyond the limit too "
             f"(chi-square {'; '.join(rounds_note)}): released") if rounds_note else ""
    if not off:  # every car's predictions agree with its measured points: step 4's fit stands
        fit = kept
        note = f"predictions agree with the measured points on every car (shift chi-square {listed}): kept"
    elif len(off) == len(d2):
        prob, fit = released, rel_sol
        note = (f"predictions released on every car with some (shift chi-square {listed}, 95 % limit "
                f"{CHI2_6_95:.1f}){extra}")
    else:
        prob, fit = prob_m, fit_m
        note = (f"predictions released on car(s) {', '.join(cars[k].number for k in off)}, kept on the others "
                f"(shift chi-square {listed}, 95 % limit {CHI2_6_95:.1f}){extra}")
    disagree = _flag_disagreements(s, at_release if off else {}, kept.poses, fit.poses)
    s.steps.append(StepStats("4b_predictions_checked", True, f"{n_pred} predicted point(s) checked: fitted again "
                             f"with their sigmas x {options.prediction_release:g}; " + note,
                             pixel_cost(prob, kept.poses), pixel_cost(prob, fit.poses), nfev, fit.message,
                             time.perf_counter() - t4b, s.changes(kept.poses, fit.poses),
                             {"released": [cars[k].number for k in off],
                              "shift_chi2_at_release": {cars[k].number: round(v, 3) for k, v in at_release.items()}
                              if off else {},
                              "doubtful": disagree}))
    if not fit.ok:
        s.failures.append(f"step 4b: {fit.message}")
    return fit, prob


def bias_skip_reason(options: SolveOptions, focal_views) -> str:
    """Why the bias correction is not applied ("" when it is): a robust loss (its IRLS weights are not a fixed
    noise model); an estimated focal (there the second-order expansion fails, docs/solver.md)."""
    if options.robust_loss != "linear":
        return "not applied: a robust loss is not a fixed noise model"
    if focal_views:
        return ("not applied: with the focal estimated the second-order expansion does not hold (positions along "
                "the line of sight scale with the focal; see docs/solver.md)")
    return ""


@dataclass
class BiasStep:
    """Step 5's outcome: the reported fit, its cost, the covariance model of the minimum (None if not taken) and
    ``SolveResult.bias_correction``."""

    fit: ChainedFit
    final_cost: float
    model: CovarianceModel | None = None
    summary: dict = field(default_factory=dict)


def step_bias(s: SolveContext, prob: Problem, fit: ChainedFit, cost_at_minimum: float) -> BiasStep:
    """Step 5: the second-order bias of the least-squares estimate removed (:mod:`.bias`), the corrected poses
    put back on the chain; the covariance model is the minimum's."""
    out = BiasStep(fit, cost_at_minimum)
    if not (s.options.bias_correction and s.plan.active):
        return out
    t5 = time.perf_counter()
    skip = bias_skip_reason(s.options, s.focal_views)
    if skip:
        out.summary = {"applied": False, "note": skip}
        s.steps.append(StepStats("5_bias_correction", False, skip, facts={"applied": False, "skipped_because": skip}))
        return out
    chains, cars = s.plan.chains, s.cars
    out.model = solution_model(prob, fit.poses, s.focal_views, chains, s.contact, s.options)
    bc = correct(prob, cars, fit.poses, s.focal_views, chains, s.contact, out.model, s.options.pixel_sigma_px,
                 max_over_sd=s.options.bias_max_over_sd)
    out.summary = bc.summary()
    if bc.applied:
        R, t = bc.R, bc.t
        links = [[t[b] + R[b] @ cars[b].c_front - t[a] - R[a] @ cars[a].c_rear for a, b in zip(ch[:-1], ch[1:])]
                 for ch in chains.members]
        out.fit = replace(fit, poses=Poses(bc.R, bc.t, bc.f), links=links)
        out.final_cost = full_cost(prob, cars, chains, out.fit.poses, s.contact, s.options)
    s.steps.append(StepStats("5_bias_correction", bc.applied, bc.note, cost_at_minimum, out.final_cost, 0,
                             "done" if bc.applied else "skipped", time.perf_counter() - t5, bc.per_carriage,
                             {"applied": bc.applied, "not_corrected": [c["number"] for c in bc.skipped]}))
    return out
