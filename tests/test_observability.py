"""Observability on the whole problem (issue 16): with an unknown focal, a carriage that shows one face only
(coplanar points: a side in a 3/4 view) is solved when the joint problem pins the focal of its photo, e.g. another
carriage there shows two faces; refused, naming what is missing, when nothing does."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

from workbench.core.camera import project_world
from workbench.core.frames import hpr_from_rotation
from workbench.core.geometry import exp_so3
from workbench.solve import CarriageInput, SolveOptions, SolveWarning, solve_consist
from workbench.solve.plan import information_matrix, marginal_sd
from workbench.solve.problem import Chains, Poses, Problem, degeneracy, prepare_cars
from workbench.solve.simulate import simulate_consist

SIGMA = 1.0


def _side_only(sim, i: int, rng: np.random.Generator) -> dict:
    """Carriage ``i``'s marked points on the side that faces the camera (one plane), with pixel noise."""
    ct, M, view = sim.carriages[i].carriage_type, sim.truth[i], sim.views[0]
    facing_left = (M[:3, :3] @ [0.0, 1.0, 0.0]) @ (view.camera_centre - M[:3, 3]) > 0
    names = [n for n, p in ct.marked_points.items() if abs(p[1]) > 1.0 and (p[1] > 0) == facing_left]
    P = np.array([ct.marked_points[n] for n in names])
    uv, _ = project_world(view.intrinsics, view.cam_from_world, P @ M[:3, :3].T + M[:3, 3])
    uv = uv + rng.normal(0.0, SIGMA, uv.shape)
    return {n: tuple(map(float, u)) for n, u in zip(names, uv)}


def _two_cars(seed: int, held: bool, first_side_only: bool = False):
    """Two carriages in one photo: the first shows front and side (points off one plane; with
    ``first_side_only`` its side alone), the second its side alone; the photo's focal starts 15 % off."""
    sim = simulate_consist(2, seed=seed, pixel_sigma_px=SIGMA, broken=() if held else (0,))
    rng = np.random.default_rng(seed + 1000)
    c0, c1 = sim.carriages
    first = (CarriageInput(number=c0.number, carriage_type=c0.carriage_type, observations={"photo": _side_only(sim, 0, rng)})
             if first_side_only else c0)
    second = CarriageInput(number=c1.number, carriage_type=c1.carriage_type, observations={"photo": _side_only(sim, 1, rng)})
    view = sim.views[0]
    views = [replace(view, intrinsics=view.intrinsics.with_focal(1.15 * view.intrinsics.fx))]
    return sim, [first, second], views


def _solve(cars, links, views):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        return solve_consist(cars, links, views, SolveOptions(pixel_sigma_px=SIGMA, estimate_focal=True,
                                                              compute_covariance=True))


@pytest.mark.parametrize("seed,held", [(0, False), (1, False), (2, False), (0, True), (3, True)])
def test_a_one_face_car_is_solved_when_another_car_pins_the_focal(seed, held):
    """Before: the side-only car was left out ('not observable alone ... coplanar and the focal is unknown'),
    or, coupled, only carried. Now both are solved; the focal and the poses lie within bands of the truth and
    within their 95 % intervals."""
    sim, cars, views = _two_cars(seed, held)
    assert degeneracy(cars[0].carriage_type, sorted(cars[0].observations["photo"])) == ""
    assert degeneracy(cars[1].carriage_type, sorted(cars[1].observations["photo"])) == "coplanar"
    res = _solve(cars, sim.links, views)
    assert res.converged, res.message
    assert [c.status for c in res.carriages] == ["solved", "solved"], res.warnings
    assert not [w for w in res.warnings if w["kind"] in ("left_out", "carried")]
    facts = res.steps[0].facts
    assert facts["one_face"] == ["101"] and facts["one_face_admitted"] == ["101"]
    rel = {st.name: st.facts for st in res.steps}["4_all"]["focal_rel_sd"]["photo"]  # checked at the solution
    assert 0.01 < rel < 0.05, rel
    f_true = sim.views[0].intrinsics.fx
    f, sf = res.focal_px["photo"], res.sigma_focal_px["photo"]
    assert 30.0 < sf < 150.0, sf  # the focal is pinned to ~2-3 % (1 sd) at 1 px
    assert abs(f - f_true) < res.ci95_factor * sf, (f, f_true, sf)  # from 15 % off
    for c, M in zip(res.carriages, sim.truth):
        ct = c.world_from_carriage
        body_true = M[:3, :3] @ [0.0, 0.0, 0.5 * cars[c.index].carriage_type.height_m] + M[:3, 3]
        e = c.body_centre_m - body_true
        assert np.linalg.norm(e) < 2.0, (c.number, e)
        assert np.all(np.abs(e) <= c.ci95_body_centre_m), (c.number, e, c.ci95_body_centre_m)
        assert np.all(c.ci95_body_centre_m < 4.0) and np.all(c.ci95_body_centre_m > 0.05), c.ci95_body_centre_m
        d_hpr = (np.array(c.hpr_deg) - np.array(hpr_from_rotation(M[:3, :3])) + 180.0) % 360.0 - 180.0
        assert np.all(np.abs(d_hpr) <= c.ci95_hpr_deg), (c.number, d_hpr, c.ci95_hpr_deg)
        assert np.all(np.abs(d_hpr) < 10.0), (c.number, d_hpr)  # one side alone: heading and roll to ~9 deg (1 sd)
        assert np.all(c.ci95_hpr_deg < 40.0), c.ci95_hpr_deg
        assert np.isfinite(ct).all()


@pytest.mark.parametrize("seed,held", [(0, False), (2, False), (0, True)])
def test_no_car_pins_the_focal_refuses_and_names_what_is_missing(seed, held):
    """Every carriage shows its side alone: the focal of the photo is pinned by no car (coupled or not, the joint
    problem fixes it to no better than ~13 %), so both are left out, and the warning says why."""
    sim, cars, views = _two_cars(seed, held, first_side_only=True)
    res = _solve(cars, sim.links, views)
    assert [c.status for c in res.carriages] == ["left_out", "left_out"]
    for number in ("100", "101"):
        msgs = [w["message"] for w in res.warnings if w["car"] == number and w["kind"] == "left_out"]
        assert len(msgs) == 1, res.warnings
        assert "the focal of view(s) photo is pinned by no car" in msgs[0]
        assert "coplanar" in msgs[0] and "no carriage there shows points off one plane" in msgs[0]
        if held:
            assert "no carriage of its chain" in msgs[0]


def test_a_focal_pinned_too_weakly_admits_no_one_face_car():
    """The two-face carriage is there, but at a configured pixel sigma of 20 px it fixes the focal to ~49 %
    only: the one-face carriage is left out, and the warning says how weakly the focal is pinned."""
    sim, cars, views = _two_cars(0, False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        res = solve_consist(cars, sim.links, views, SolveOptions(pixel_sigma_px=20.0, estimate_focal=True))
    assert [c.status for c in res.carriages] == ["solved", "left_out"]
    msg = next(w["message"] for w in res.warnings if w["car"] == "101")
    assert "the focal of view(s) photo is pinned too weakly" in msg and "10 % needed" in msg, msg


def test_the_known_focal_case_is_unchanged():
    """At a known focal a one-face car was observable alone before and still is (no joint check runs)."""
    sim, cars, views = _two_cars(2, False, first_side_only=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        res = solve_consist(cars, sim.links, sim.views, SolveOptions(pixel_sigma_px=SIGMA))
    assert [c.status for c in res.carriages] == ["solved", "solved"]
    assert "one_face_admitted" not in res.steps[0].facts


def test_information_matrix_matches_finite_differences():
    """The joint information (pixel rows, the coupling prior, the shared focal) equals J^T J / sigma^2 of the
    residuals differentiated numerically; a one-face car alone leaves its focal far less determined than a car
    showing two faces."""
    sim = simulate_consist(2, seed=4, pixel_sigma_px=SIGMA)
    views = sim.views
    cars = prepare_cars(sim.carriages, views, SolveOptions())
    prob = Problem(cars, [0, 1], views, {0: 1.0, 1: 1.0})
    R = np.array([M[:3, :3] for M in sim.truth])
    t = np.array([M[:3, 3] for M in sim.truth])
    poses = Poses(R, t, np.array([views[0].intrinsics.fx]))
    chains = Chains([[0, 1]], [[0.03]])
    H = information_matrix(prob, poses, chains, [[0]], SIGMA)

    def resid(x):
        Rx = np.array([exp_so3(x[6 * k:6 * k + 3]) @ R[k] for k in range(2)])
        tx = t + x[:12].reshape(2, 6)[:, 3:]
        uv, *_ = prob.project(Rx, tx, np.array([poses.f[0] + x[12]]))
        T = tx[1] + Rx[1] @ cars[1].c_front - tx[0] - Rx[0] @ cars[0].c_rear
        return np.concatenate([(uv / SIGMA).ravel(), T * np.sqrt(5.0) / 0.03])

    h = 1e-6
    J = np.array([(resid(h * e) - resid(-h * e)) / (2 * h) for e in np.eye(13)]).T
    np.testing.assert_allclose(H, J.T @ J, rtol=1e-5, atol=1e-6 * np.abs(H).max())
    sd = marginal_sd(H)
    assert np.all(np.isfinite(sd)) and sd[12] / poses.f[0] < 0.05
    assert np.isinf(marginal_sd(np.diag([1.0, 0.0]))[1])  # a parameter no row sees is undetermined


@pytest.mark.parametrize("seed", [116, 121])
def test_a_one_face_car_at_a_known_focal_gets_the_branch_check(seed):
    """At a known focal a one-face car (four coplanar side points) has two PnP poses that fit about equally; the
    branch check after step 4 now tries the other one there too (it ran for one-face cars at an estimated focal
    only). In these seeds the solve ended 47-55 deg from the truth without it; with it, within 5 deg."""
    sim, cars, _ = _two_cars(seed, False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        res = solve_consist(cars, sim.links, sim.views, SolveOptions(pixel_sigma_px=SIGMA))
    notes = " ".join(st.note or "" for st in res.steps)
    assert f"car {cars[1].number} restarted from another PnP branch" in notes
    R, Rt = np.asarray(res.carriages[1].world_from_carriage)[:3, :3], sim.truth[1][:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(R @ Rt.T) - 1) / 2, -1, 1))) < 5.0
