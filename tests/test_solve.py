"""Tests of the chained pose solver (workbench.solve)."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from workbench.core.camera import CameraIntrinsics
from workbench.errors import InputError
from workbench.solve import (CarriageInput, ChainLink, SolveOptions, SolveWarning, crb, project_with_jacobians,
                             refine_from, rest_on_terrain, solve_consist)
from workbench.core.geometry import exp_so3
from workbench.solve.simulate import PlaneTerrain, simulate_consist
from workbench.rolling_stock import get_type


def _intr():
    return CameraIntrinsics(width=4000, height=3000, fx=3000.0, fy=3000.0, cx=2010.0, cy=1490.0, skew=0.0,
                            k1=-0.05, k2=0.01, k3=0.002, p1=0.001, p2=-0.0008)


def test_projection_matches_opencv_and_jacobians_match_finite_differences():
    rng = np.random.default_rng(0)
    P = rng.uniform([-12, -1.6, 0], [12, 1.6, 4], (9, 3))
    R = exp_so3(np.array([0.1, -0.3, 1.2]))
    t = np.array([3.0, 40.0, 1.0])
    cam = np.eye(4)
    cam[:3, :3] = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float)  # looking along +y
    intr = _intr()
    names = ("f", "cx", "cy", "k1", "k2")
    uv, Jp, Ji = project_with_jacobians(P, R, t, cam, intr, names)
    Xc = (P @ R.T + t) @ cam[:3, :3].T + cam[:3, 3]
    np.testing.assert_allclose(uv, intr.project(Xc), atol=1e-9)
    cv, _ = cv2.projectPoints(Xc, np.zeros(3), np.zeros(3), intr.K, intr.dist_coeffs)
    np.testing.assert_allclose(uv, cv.reshape(-1, 2), atol=1e-6)
    h = 1e-6
    for i in range(6):
        d = np.zeros(6)
        d[i] = h
        up = project_with_jacobians(P, exp_so3(d[:3]) @ R, t + d[3:], cam, intr)[0]
        um = project_with_jacobians(P, exp_so3(-d[:3]) @ R, t - d[3:], cam, intr)[0]
        num = (up - um) / (2 * h)
        np.testing.assert_allclose(Jp[:, :, i], num, rtol=1e-6, atol=1e-6 * np.abs(num).max())
    from dataclasses import replace
    for i, n in enumerate(names):
        hh = 1e-3  # uv is linear in each of these: the central difference is exact up to rounding
        kw = lambda s: ({"fx": intr.fx + s, "fy": intr.fy + s} if n == "f" else {n: getattr(intr, n) + s})  # noqa
        up = project_with_jacobians(P, R, t, cam, replace(intr, **kw(hh)))[0]
        um = project_with_jacobians(P, R, t, cam, replace(intr, **kw(-hh)))[0]
        num = (up - um) / (2 * hh)
        np.testing.assert_allclose(Ji[:, :, i], num, rtol=1e-6, atol=1e-6 * np.abs(num).max())


def _body_err(res, sim):
    out = []
    for c, M, ci in zip(res.carriages, sim.truth, sim.carriages):
        bt = M[:3, :3] @ [0, 0, ci.carriage_type.height_m / 2] + M[:3, 3]
        out.append(c.body_centre_m - bt)
    return np.array(out)


def test_noiseless_recovers_truth():
    sim = simulate_consist(5, seed=3, pixel_sigma_px=0.0)
    res = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=1e-7), terrain=None)
    assert res.status == "converged"
    for c, M in zip(res.carriages, sim.truth):
        assert np.abs(c.world_from_carriage - M).max() < 1e-6
    for L in res.links:
        assert L["offset_norm_m"] <= L["slack_m"] + 1e-9


def test_noisy_errors_within_crb_band_and_constraint_honoured():
    e2, b2 = [], []
    for s in range(8):
        sim = simulate_consist(6, seed=200 + s, pixel_sigma_px=1.0)
        res = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=1.0))
        assert res.status == "converged"
        for L in res.links:
            assert L["offset_norm_m"] <= L["slack_m"] + 1e-9
        e = _body_err(res, sim)
        bound = crb(sim.carriages, sim.links, sim.views, sim.truth, 1.0)
        e2 += list((e**2).sum(1))
        b2 += [np.trace(C) for C in bound["body_centre_cov"]]
    ratio = np.sqrt(np.mean(e2) / np.mean(b2))
    assert 0.5 < ratio < 2.0, ratio


def test_unknown_focal_recovered():
    errs, sig = [], []
    for s in range(4):
        sim = simulate_consist(6, seed=300 + s, pixel_sigma_px=0.5)
        res = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=0.5, estimate_focal=True))
        errs.append(res.focal_px["photo"] - sim.views[0].intrinsics.fx)
        sig.append(res.sigma_focal_px["photo"])
    errs, sig = np.array(errs), np.array(sig)
    assert np.all(np.abs(errs) < 4 * sig + 1.0), (errs, sig)
    assert np.sqrt(np.mean(errs**2)) < 0.05 * 3000


@pytest.mark.parametrize("seed", [125281, 125208])
def test_unknown_focal_long_consist_found_by_the_chained_profile(seed):
    """12 cars from ~1.1 train lengths at 2 px (benchmark trials): each carriage shows so little perspective that
    its PnP error falls towards the longest focal, and the per-carriage sweep ran the focal to the field-of-view
    limit (11343 px against ~3000). The chained focal profile starts in the truth's basin: the solver ends at the
    minimum the same cost has when started from the truth, with the focal within its bound of the truth."""
    sim = simulate_consist(12, seed=seed, pixel_sigma_px=2.0)
    opts = SolveOptions(pixel_sigma_px=2.0, estimate_focal=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        res = solve_consist(sim.carriages, sim.links, sim.views, opts)
    assert res.converged
    ml = refine_from(sim.carriages, sim.links, sim.views, sim.truth, opts)
    assert abs(res.cost_at_minimum - ml["cost"]) < 1e-6 * ml["cost"], (res.final_cost, ml["cost"])
    assert abs(res.focal_px["photo"] - ml["focal_px"]["photo"]) < 0.5
    f_true = sim.views[0].intrinsics.fx
    bound = crb(sim.carriages, sim.links, sim.views, sim.truth, 2.0, True)
    sf = bound["focal_sigma"][0]
    assert 20.0 < sf < 400.0, sf
    assert 0.0 < abs(res.focal_px["photo"] - f_true) < 3.0 * sf, (res.focal_px["photo"], f_true, sf)
    e = _body_err(res, sim)
    ratio = np.sqrt(np.mean((e**2).sum(1)) / np.mean([np.trace(C) for C in bound["body_centre_cov"]]))
    assert 0.05 < ratio < 2.5, ratio
    assert res.steps[0].facts["focal_start"] == "chained_profile"


def test_known_focal_solver_reaches_the_truth_started_minimum():
    """12 cars at 2 px, known focal: the solver (which starts without help) ends where the same cost ends when
    started from the truth — the excess over the Cramér-Rao bound in this cell is the estimator's, not a wrong
    basin. Seed 120279 is the benchmark's worst trial (error^2 8.6x the bound's trace)."""
    for seed in (120279, 120227):
        sim = simulate_consist(12, seed=seed, pixel_sigma_px=2.0)
        opts = SolveOptions(pixel_sigma_px=2.0)
        res = solve_consist(sim.carriages, sim.links, sim.views, opts)
        ml = refine_from(sim.carriages, sim.links, sim.views, sim.truth, opts)
        assert res.converged and ml["converged"]
        assert abs(res.cost_at_minimum - ml["cost"]) < 1e-6 * ml["cost"]
        for c, M in zip(res.carriages, ml["world_from_carriage"]):
            assert np.abs(c.world_from_carriage[:3, 3] - M[:3, 3]).max() < 1e-3
        e = _body_err(res, sim)
        assert 0.3 < np.sqrt(np.mean((e**2).sum(1))) < 6.0  # metres: a far, noisy consist


def test_broken_couplings_split_chains():
    sim = simulate_consist(6, seed=11, pixel_sigma_px=0.5, broken=(2,))
    res = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=0.5))
    fronts = sorted(L["front"] for L in res.links)
    assert fronts == [0, 1, 3, 4]  # no link across the break
    e = np.linalg.norm(_body_err(res, sim), axis=1)
    assert np.all(e < 1.5)
    # no correlation reported across the break
    pairs = {(d["front"], d["rear"]) for d in res.neighbour_correlation}
    assert ("102", "103") not in pairs and ("101", "102") in pairs


def test_observability_warnings():
    sim = simulate_consist(4, seed=5, pixel_sigma_px=0.5)
    cars = sim.carriages
    obs1 = cars[1].observations["photo"]
    cars[1].observations["photo"] = dict(list(obs1.items())[:2])  # chained, 2 points: carried
    links = list(sim.links)
    links[2] = ChainLink(2, 3, None)  # car 3 unlinked ...
    cars[3].observations["photo"] = dict(list(cars[3].observations["photo"].items())[:3])  # ... with 3 points
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        res = solve_consist(cars, links, sim.views, SolveOptions(pixel_sigma_px=0.5))
    kinds = {(d["car"], d["kind"]) for d in res.warnings}
    assert ("101", "carried") in kinds and ("103", "left_out") in kinds
    assert any(issubclass(x.category, SolveWarning) and "103" in str(x.message) for x in w)
    assert res.carriage("101").status == "carried" and res.carriage("101").world_from_carriage is not None
    assert res.carriage("103").status == "left_out" and res.carriage("103").world_from_carriage is None
    assert np.linalg.norm(res.carriage("101").world_from_carriage[:3, 3] - sim.truth[1][:3, 3]) < 1.0


@pytest.mark.parametrize("case", ["view", "point", "nan", "twice", "outside", "link"])
def test_bad_input_raises(case):
    sim = simulate_consist(3, seed=1, pixel_sigma_px=0.5)
    cars, links = sim.carriages, list(sim.links)
    obs = cars[1].observations["photo"]
    name = next(iter(obs))
    if case == "view":
        cars[1].observations["other_photo"] = dict(obs)
        match = "other_photo"
    elif case == "point":
        obs["no_such_point"] = (100.0, 100.0)
        match = "no_such_point"
    elif case == "nan":
        obs[name] = (np.nan, 5.0)
        match = name
    elif case == "twice":
        from workbench.solve import Observation
        cars[1].observations["photo"] = [Observation(name, *obs[name]), Observation(name, *obs[name])]
        match = "twice"
    elif case == "outside":
        obs[name] = (5000.0, 10.0)
        match = "outside"
    else:
        links.append(ChainLink(2, 3, 0.05))
        match = "not in the consist"
    with pytest.raises(InputError, match=match):
        solve_consist(cars, links, sim.views, SolveOptions())


def test_step2_flat_terrain_rests_on_ground():
    ct = get_type("shoreliner")
    M = np.eye(4)
    M[:3, :3] = exp_so3(np.array([0.05, -0.3, 0.7]))
    M[:3, 3] = [5.0, 3.0, 2.7]
    flat = PlaneTerrain(0.0, 0.0, 0.0)
    M2, dz = rest_on_terrain(M, ct, flat)
    assert np.allclose(M2[:2], M[:2]) and np.allclose(M2[:3, :3], M[:3, :3])
    S = ct.sample_surface(400) @ M2[:3, :3].T + M2[:3, 3]
    assert abs(S[:, 2].min()) < 1e-3
    # and inside the solver: the step runs and is recorded; without a terrain it is skipped
    sim = simulate_consist(3, seed=2, pixel_sigma_px=0.5, slope_deg=0.0)
    res = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=0.5), terrain=flat)
    st = {s.name: s for s in res.steps}
    assert st["2_terrain"].ran and len(st["2_terrain"].per_carriage) == 3
    for c in res.carriages:
        assert abs(c.clearance_m) < 0.05
    res2 = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=0.5))
    assert not {s.name: s for s in res2.steps}["2_terrain"].ran
    d = res2.to_dict()
    import json
    json.dumps(d)


def test_coverage_of_95_intervals():
    """Honest and sharp: the truth inside the 95 % interval 88-99 % of the time per axis, and the errors in units
    of the stated sigma with an RMS near 1 (0.94-1.03 measured): not merely wide enough."""
    z = []
    for s in range(200):
        sim = simulate_consist(3, seed=5000 + s, pixel_sigma_px=1.0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SolveWarning)
            res = solve_consist(sim.carriages, sim.links, sim.views,
                                SolveOptions(pixel_sigma_px=1.0, compute_covariance=True))
        e = _body_err(res, sim)
        z += [ei / (np.asarray(c.ci95_body_centre_m) / 1.96) for c, ei in zip(res.carriages, e)]
    z = np.array(z)
    cov = np.mean(np.abs(z) <= 1.96, axis=0)
    assert np.all((cov >= 0.88) & (cov <= 0.99)), cov
    rms = np.sqrt(np.mean(z ** 2, axis=0))
    assert np.all((rms > 0.8) & (rms < 1.2)), rms


def test_30_car_chain_converges_quickly():
    import time

    sim = simulate_consist(30, seed=7, pixel_sigma_px=1.0)
    opts = SolveOptions(pixel_sigma_px=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        t0 = time.perf_counter()
        res = solve_consist(sim.carriages, sim.links, sim.views, opts, terrain=sim.terrain)
        dt = time.perf_counter() - t0
    assert res.status == "converged", res.message
    assert {s.name: s for s in res.steps}["4_all"].status.startswith("converged")
    for L in res.links:
        assert L["offset_norm_m"] <= L["slack_m"] + 1e-9
    assert dt < 5.0, dt  # ~0.5 s on one core; generous for loaded CI machines


def test_dense_and_sparse_trust_region_systems_give_the_same_solution(monkeypatch):
    """The small-system dense path (``chain.DENSE_KKT_MAX``) solves the same KKT system as SuperLU: a 6-car solve
    (steps 1-4, terrain contact, bias correction) ends at the same poses to rounding either way."""
    from workbench.solve import trust_region as chain

    sim = simulate_consist(6, seed=11, pixel_sigma_px=1.0, max_distance_m=400.0)
    opts = SolveOptions(pixel_sigma_px=1.0)
    poses = {}
    for name, limit in (("dense", 10**6), ("sparse", 0)):
        monkeypatch.setattr(chain, "DENSE_KKT_MAX", limit)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SolveWarning)
            res = solve_consist(sim.carriages, sim.links, sim.views, opts, terrain=sim.terrain)
        assert res.status == "converged", res.message
        poses[name] = np.array([c.world_from_carriage for c in res.carriages])
    assert 0 <= np.abs(poses["dense"] - poses["sparse"]).max() < 1e-6


def test_couplers_at_the_slack_converge_in_few_evaluations():
    """Step 3 (rotations held) pins most offsets on the sphere |T| = slack with large multipliers; with the
    sphere's curvature in the Gauss-Newton matrix it converges in a few evaluations per active set (11 here; 37
    before, linearly convergent, in rounds capped at 40 evaluations)."""
    sim = simulate_consist(10, seed=7, pixel_sigma_px=1.0, max_distance_m=400.0)
    opts = SolveOptions(pixel_sigma_px=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        res = solve_consist(sim.carriages, sim.links, sim.views, opts, terrain=sim.terrain)
    s3 = {s.name: s for s in res.steps}["3_chain_translations"]
    assert s3.status.startswith("converged"), s3.status
    assert s3.facts["links_at_slack"] > 0  # the case this is about: offsets on the sphere
    assert 3 <= s3.iterations <= 20, s3.iterations


def test_photos_of_one_camera_share_one_focal():
    """The photos of a panorama (identical intrinsics, known relative rotations) get one focal parameter: the
    estimate is the same for all of them, near the truth within its own sigma, and far sharper than a focal
    estimated from the carriages of one photo alone."""
    sim = simulate_consist(20, seed=3, pixel_sigma_px=1.0, max_distance_m=250.0)
    assert len(sim.views) >= 2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        res = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=1.0, estimate_focal=True),
                            terrain=sim.terrain)
    assert res.converged
    f_true = sim.views[0].intrinsics.fx
    fs = {round(v, 9) for v in res.focal_px.values()}
    assert len(fs) == 1
    f = fs.pop()
    sig = res.sigma_focal_px[sim.views[0].name]
    assert 0.05 < sig < 0.01 * f_true
    assert abs(f - f_true) < 4.0 * sig + 0.5


def test_points_with_their_own_sigma_weigh_less():
    """A point declared with a larger sigma_px is down-weighted: with one badly placed point per carriage
    (6 px off), declaring their sigma brings the poses closer to the truth, and declaring every point's sigma
    equal to the solve's pixel sigma changes nothing."""
    from workbench.solve.model import Observation

    sim = simulate_consist(6, seed=3, pixel_sigma_px=0.5)
    rng = np.random.default_rng(9)

    def inputs(declare_bad: float | None, declare_all: float | None):
        cars = []
        for c in sim.carriages:
            obs = {}
            for v, pts in c.observations.items():
                names = sorted(pts)
                o = {}
                for j, p in enumerate(names):
                    u, vv = pts[p]
                    if j == 0:  # the bad one
                        u, vv = u + 6.0 * np.cos(rng.uniform(0, 6.3)), vv + 6.0 * np.sin(rng.uniform(0, 6.3))
                        o[p] = Observation(p, u, vv, True, declare_bad)
                    else:
                        o[p] = Observation(p, u, vv, True, declare_all)
                obs[v] = o
            cars.append(CarriageInput(number=c.number, carriage_type=c.carriage_type, observations=obs))
        return cars

    def err(cars):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SolveWarning)
            res = solve_consist(cars, sim.links, sim.views, SolveOptions(pixel_sigma_px=0.5))
        assert res.converged
        return res, sum(float(np.linalg.norm(c.world_from_carriage[:3, 3] - M[:3, 3]))
                        for c, M in zip(res.carriages, sim.truth))

    rng = np.random.default_rng(9)
    res_a, e_plain = err(inputs(None, None))
    rng = np.random.default_rng(9)
    res_b, e_declared = err(inputs(6.0, None))
    rng = np.random.default_rng(9)
    res_c, e_same = err(inputs(0.5, 0.5))
    assert e_declared < 0.8 * e_plain
    assert abs(e_same - e_plain) < 1e-6


def test_weighting_option():
    """``SolveOptions.weighting``: "per_carriage" (the default, each carriage's term normalised by its number of
    points) and "per_point" (every point 1 / sigma^2, maximum likelihood) are the same estimator when every
    carriage shows the same number of points, and differ when the counts differ; anything else is refused."""
    from workbench.errors import SettingsError

    sim = simulate_consist(4, seed=21, pixel_sigma_px=1.0)
    a = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=1.0))
    b = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=1.0, weighting="per_point"))
    for ca, cb in zip(a.carriages, b.carriages):
        np.testing.assert_allclose(ca.world_from_carriage, cb.world_from_carriage, atol=1e-9)
        np.testing.assert_allclose(ca.ci95_body_centre_m, cb.ci95_body_centre_m, rtol=1e-9)
    sim = simulate_consist(4, seed=21, pixel_sigma_px=1.0, n_points=(5, 9))
    assert [len(c.observations["photo"]) for c in sim.carriages] == [5, 9, 5, 9]
    a = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=1.0))
    b = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=1.0, weighting="per_point"))
    assert a.converged and b.converged
    d = max(np.abs(ca.world_from_carriage[:3, 3] - cb.world_from_carriage[:3, 3]).max()
            for ca, cb in zip(a.carriages, b.carriages))
    assert d > 1e-4
    with pytest.raises(SettingsError, match="weighting"):
        SolveOptions(weighting="per_face")


def test_redraw_keeps_the_geometry():
    from workbench.solve.simulate import redraw

    base = simulate_consist(5, seed=8, pixel_sigma_px=0.0)
    sim = redraw(base, 3, pixel_sigma_px=1.0)
    for Ma, Mb in zip(base.truth, sim.truth):
        np.testing.assert_allclose(Ma[:3, :3], Mb[:3, :3])
        assert np.linalg.norm(Ma[:3, 3] - Mb[:3, 3]) < 0.2  # offsets differ by at most 2 x 3 cm per link
    np.testing.assert_allclose(base.truth[0], sim.truth[0])
    for T in sim.offsets:
        assert np.linalg.norm(T) <= 0.03 + 1e-12
    for a, b, cl in zip(base.carriages, sim.carriages, sim.clean_pixels):
        assert list(a.observations["photo"]) == list(b.observations["photo"])
        e = np.array([np.subtract(b.observations["photo"][n], cl[n]) for n in cl])
        assert 0.3 < np.sqrt(np.mean(e**2)) < 3.0
    res = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=1.0))
    assert res.converged and np.linalg.norm(_body_err(res, sim), axis=1).max() < 2.0


@pytest.mark.parametrize("case", [(12, 125327, 2.0, None, False), (12, 125327, 2.0, None, True),
                                  (6, 50003, 1.0, (4, 10, 6, 10, 5, 8), False),
                                  (6, 50012, 1.0, (4, 10, 6, 10, 5, 8), False)])
def test_carriage_on_the_wrong_pnp_branch_is_restarted(case):
    """A carriage that shows only its end face (or 4 points) fits two poses ~90 deg apart; SQPnP picked the wrong
    one and the chain dragged its followers metres away (benchmark seed 125327: car 109 rotated 91 deg, 22 px
    RMS, cost 2019 against 304; with an unknown focal the focal profile ran to 7035 px against 3040). Its
    chi-square after the chained solve flags it, the solve restarts from its other branches, and ends at the
    minimum the same cost has from the truth."""
    n, seed, sigma, points, est = case
    sim = simulate_consist(n, seed=seed, pixel_sigma_px=sigma, n_points=points if points else 7)
    opts = SolveOptions(pixel_sigma_px=sigma, estimate_focal=est)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        res = solve_consist(sim.carriages, sim.links, sim.views, opts)
    ml = refine_from(sim.carriages, sim.links, sim.views, sim.truth, opts)
    assert res.converged
    assert abs(res.cost_at_minimum - ml["cost"]) < 1e-5 * ml["cost"], (res.cost_at_minimum, ml["cost"])
    assert max(c.rms_px for c in res.carriages) < 4 * sigma
    if not est:
        assert "another PnP branch" in [r["from"] for r in res.steps[3].facts["restarted"]]


def _brute_force_bias(prob, cars, R, t, f, chains, slacks, sigma, focal=False, h=1e-4):
    """Second-order bias of the free-pose parameters (and the focal, px) by the textbook expansion with every
    row's Hessian taken by finite differences of the whole residual vector (independent of the sigma-point
    implementation)."""
    from workbench.solve.problem import SQRT5

    N = len(R)

    def rho(th):
        fn = f + th[-1] if focal else f
        th = th[:6 * N].reshape(N, 6)
        Rn = exp_so3(th[:, :3]) @ R
        tn = t + th[:, 3:]
        uv = prob.project(Rn, tn, fn)[0]
        out = [((uv - prob.uv) * prob.w[:, None]).reshape(-1) / sigma]
        for ch, sl in zip(chains, slacks):
            for j in range(len(ch) - 1):
                a, b = ch[j], ch[j + 1]
                T = tn[b] + Rn[b] @ cars[b].c_front - tn[a] - Rn[a] @ cars[a].c_rear
                out.append(T * SQRT5 / sl[j])
        return np.concatenate(out)

    P = 6 * N + (1 if focal else 0)
    E = np.eye(P) * np.where(np.arange(P) < 6 * N, h, 1.0)  # steps: 1e-4 rad / m, 1 px of focal
    hs = np.diag(E)
    r0 = rho(np.zeros(P))
    J = np.column_stack([(rho(E[k]) - rho(-E[k])) / (2 * hs[k]) for k in range(P)])
    Hs = np.zeros((len(r0), P, P))
    for a in range(P):
        for b in range(a, P):
            v = (rho(E[a] + E[b]) - rho(E[a] - E[b]) - rho(E[b] - E[a]) + rho(-(E[a] + E[b]))) / (4 * hs[a] * hs[b])
            Hs[:, a, b] = Hs[:, b, a] = v
    S = np.concatenate([np.repeat(prob.w_noise**2, 2), np.ones(len(r0) - 2 * len(prob.P))])
    Hi = np.linalg.inv(J.T @ J)
    C = Hi @ (J.T * S) @ J @ Hi
    d = np.einsum("ab,iab->i", C, Hs)
    M = np.eye(len(r0)) - J @ Hi @ J.T
    Cc = -Hi @ (J.T * S) @ M
    cross = np.einsum("iab,bi->a", Hs, Cc)
    return -Hi @ (0.5 * J.T @ d + cross), -Hi @ (0.5 * J.T @ d)


@pytest.mark.parametrize("weighting, points, focal", [("per_point", 7, False), ("per_carriage", (4, 9, 6), False),
                                                     ("per_point", 7, True)])
def test_bias_estimate_matches_the_second_order_expansion(weighting, points, focal):
    """``bias.estimate_bias`` (sigma-point differences of the residuals, local blocks, the weighting's cross term)
    against the textbook second-order expansion (Box 1971; with unequal per-carriage weights the cross term
    -H^-1 sum_i H_i c_i) with every row's Hessian from finite differences of the whole residual vector. At a small
    pixel sigma the sigma points are small and the two agree closely; with unequal counts the cross term is a
    visible part of the bias (it is zero for the per-point weighting). ``focal``: the focal estimated too."""
    from workbench.solve.bias import estimate_bias
    from workbench.solve.problem import Problem as _Problem, carriage_weights, held_chains, prepare_cars as _prepare
    from workbench.solve.uncertainty import covariance_model

    sigma = 0.1
    sim = simulate_consist(3, seed=5, pixel_sigma_px=sigma, n_points=points)
    opts = SolveOptions(pixel_sigma_px=sigma, weighting=weighting, check_image_bounds=False)
    cars = _prepare(sim.carriages, sim.views, opts)
    active = [0, 1, 2]
    prob = _Problem(cars, active, sim.views, carriage_weights(cars, active, weighting))
    R = np.array([M[:3, :3] for M in sim.truth])
    t = np.array([M[:3, 3] for M in sim.truth])
    f = np.array([v.intrinsics.fx for v in sim.views])
    chains, slacks = held_chains(3, sim.links)
    fv = [[0]] if focal else []
    model = covariance_model(prob, R, t, f, fv, chains, slacks, None, sigma, sigma_fixed=sigma)
    b, diag = estimate_bias(prob, cars, R, t, f, fv, chains, slacks, None, model, sigma)
    ref, ref_box = _brute_force_bias(prob, cars, R, t, f, chains, slacks, sigma, focal)
    assert np.linalg.norm(b - ref) < 1e-3 * np.linalg.norm(ref), (b, ref)
    if weighting == "per_point":
        assert diag["cross_term_norm"] == 0.0
    else:
        assert np.linalg.norm(ref - ref_box) > 0.05 * np.linalg.norm(ref)
        assert diag["cross_term_norm"] > 0.05 * np.linalg.norm(b)


def test_bias_correction_option():
    """``SolveOptions.bias_correction``: the minimum is the same (``cost_at_minimum``), the reported poses move by
    what step "5_bias_correction" records, the couplers stay inside their slack, the intervals are the
    minimum's (centred on the corrected poses); a non-boolean is refused."""
    from workbench.errors import SettingsError

    assert SolveOptions().bias_correction is True  # on by default (as the stage's solver.bias_correction)
    sim = simulate_consist(6, seed=60100, pixel_sigma_px=2.0)
    a = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=2.0, bias_correction=False))
    b = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=2.0))
    assert a.converged and b.converged
    assert a.bias_correction == {} and a.steps[-1].name == "4b_predictions_checked"  # no step 5
    assert a.cost_at_minimum == a.final_cost
    assert abs(b.cost_at_minimum - a.final_cost) < 1e-6 * a.final_cost
    assert b.final_cost > b.cost_at_minimum  # moved off the minimum
    st = b.steps[5]
    assert st.name == "5_bias_correction" and st.ran and b.bias_correction["applied"]
    shifts = [np.linalg.norm(cb.body_centre_m - ca.body_centre_m) for ca, cb in zip(a.carriages, b.carriages)]
    assert 1e-4 < max(shifts) < 1.0
    assert abs(max(shifts) - b.bias_correction["max_shift_m"]) < 1e-9
    for L in b.links:
        assert L["offset_norm_m"] <= L["slack_m"] + 1e-12
    for ca, cb in zip(a.carriages, b.carriages):
        np.testing.assert_allclose(cb.ci95_body_centre_m, ca.ci95_body_centre_m, rtol=1e-3)
    # with a terrain the contact rows join the expansion: it still runs and moves the poses by a similar amount
    c = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=2.0, bias_correction=True),
                      terrain=sim.terrain)
    assert c.converged and c.bias_correction["applied"] and c.steps[5].ran
    assert 1e-4 < c.bias_correction["max_shift_m"] < 3 * b.bias_correction["max_shift_m"]
    # not applied with an estimated focal (the expansion fails there, docs/solver.md) nor with a robust loss
    for kw in ({"estimate_focal": True}, {"robust_loss": "huber"}):
        ml = refine_from(sim.carriages, sim.links, sim.views, sim.truth,
                         SolveOptions(pixel_sigma_px=2.0, bias_correction=True, **kw))
        assert ml["bias_correction"]["applied"] is False and "not applied" in ml["bias_correction"]["note"]
        assert "world_from_carriage_minimum" not in ml
    with pytest.raises(SettingsError, match="bias_correction"):
        SolveOptions(bias_correction="yes")
    with pytest.raises(TypeError):
        SolveOptions(bias_corection=True)
    for bad in (0.0, -1.0, float("nan"), "1"):
        with pytest.raises(SettingsError, match="bias_max_over_sd"):
            SolveOptions(bias_max_over_sd=bad)


def test_bias_correction_skips_carriages_where_the_expansion_fails():
    """The safeguard: a carriage whose predicted bias exceeds ``bias_max_over_sd`` standard deviations in a pose
    component is not corrected (the step's note and ``skipped`` name it, with its ratio); the others are. With a
    limit below every carriage's ratio nothing is applied; with an estimated focal the step is skipped."""
    sim = simulate_consist(6, seed=60100, pixel_sigma_px=2.0)
    full = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=2.0))
    bc = full.bias_correction
    assert bc["applied"] and bc["skipped"] == [] and 0 < bc["max_bias_over_sd"] < 1.0
    st = full.steps[5]
    assert all(p["corrected"] for p in st.per_carriage)
    # a limit at half the largest ratio: the worst carriage (at least) is left uncorrected, the rest corrected
    lim = 0.5 * bc["max_bias_over_sd"]
    part = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=2.0, bias_max_over_sd=lim))
    pb = part.bias_correction
    assert pb["applied"] and 1 <= len(pb["skipped"]) < 6
    assert all(e["bias_over_sd"] >= lim for e in pb["skipped"])
    assert max(e["bias_over_sd"] for e in pb["skipped"]) == pytest.approx(bc["max_bias_over_sd"], rel=1e-9)
    names = {e["number"] for e in pb["skipped"]}
    assert set(part.steps[5].facts["not_corrected"]) == names and "not applied to car(s)" in part.steps[5].note
    moved = {p["number"]: p for p in part.steps[5].per_carriage}
    for cp in part.carriages:
        assert moved[cp.number]["corrected"] == (cp.number not in names)
        if cp.number in names and pb["links_clipped"] == 0:
            assert moved[cp.number]["moved_m"] < 1e-9  # its pose is the minimum's
    for L in part.links:
        assert L["offset_norm_m"] <= L["slack_m"] + 1e-12
    # a limit below every carriage's ratio: nothing applied, the reported poses are the minimum's
    none = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=2.0, bias_max_over_sd=1e-9))
    assert none.bias_correction["applied"] is False and len(none.bias_correction["skipped"]) == 6
    assert not none.steps[5].ran and none.final_cost == none.cost_at_minimum
    assert len(none.steps[5].facts["not_corrected"]) == 6 and none.steps[5].facts["applied"] is False
    # an estimated focal: skipped, said so
    est = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=2.0, estimate_focal=True))
    assert est.bias_correction["applied"] is False and "focal" in est.bias_correction["note"]
    assert est.steps[5].name == "5_bias_correction" and not est.steps[5].ran


@pytest.mark.parametrize("seed, car", [(120226, "100"), (120242, "104")])
def test_a_few_point_carriage_on_a_wrong_branch_is_judged_by_the_chain(seed, car):
    """12 cars showing 4, 10, 6, 10, 5, 8 points at 2 px (benchmark seeds of ``--cells 12:2:known --points
    4,10,6,10,5,8``): a 4- or 5-point carriage fits a wrong PnP branch with a chi-square its own pixels cannot
    flag, and the chain then ended above the truth-started minimum (seed 120226: car 100, 4 points, 30 deg off,
    cost 333.3 against 283.6; seed 120242: car 104, 5 points, 50 deg off, cost 326.5 against 280.3). Every
    chained carriage with at most FEW_POINTS points is now tried on its other branches and on a pose carried from
    its neighbours, the chained cost judging: the solve ends at the truth-started minimum."""
    sim = simulate_consist(12, seed=seed, pixel_sigma_px=2.0, n_points=[4, 10, 6, 10, 5, 8])
    opts = SolveOptions(pixel_sigma_px=2.0, bias_correction=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        res = solve_consist(sim.carriages, sim.links, sim.views, opts)
    ml = refine_from(sim.carriages, sim.links, sim.views, sim.truth, opts)
    assert res.converged
    assert res.cost_at_minimum <= ml["cost"] * (1 + 1e-6) + 1e-6, (res.cost_at_minimum, ml["cost"])
    facts = {st.name: st.facts for st in res.steps}["4_all"]
    assert car in [r["car"] for r in facts["restarted"]]
    for c, M in zip(res.carriages, ml["world_from_carriage"]):
        R = c.world_from_carriage[:3, :3]
        assert np.degrees(np.arccos(np.clip((np.trace(R.T @ M[:3, :3]) - 1) / 2, -1, 1))) < 0.5


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_telephoto_focal_is_not_clamped(seed):
    """A 15 deg photo from 6 train lengths, focal unknown (issue 16: railway photos are often telephoto): the
    default search range (3-120 deg) recovers the focal within 3 sigma, with no warning; the old range (20-100 deg)
    stuck at its 20 deg limit and the warning named the setting that widens it."""
    sim = simulate_consist(3, seed=seed, pixel_sigma_px=0.5, focal_px=15000.0, distance_factor=6.0)
    f_true = sim.views[0].intrinsics.fx
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SolveWarning)
        res = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=0.5, estimate_focal=True))
    assert res.converged
    f, sf = res.focal_px["photo"], res.sigma_focal_px["photo"]
    assert 200.0 < sf < 4000.0 and abs(f - f_true) < 3.0 * sf, (f, f_true, sf)
    assert not [w for w in caught if "edge of the search range" in str(w.message)]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", SolveWarning)
        old = solve_consist(sim.carriages, sim.links, sim.views,
                            SolveOptions(pixel_sigma_px=0.5, estimate_focal=True, hfov_range_deg=(20.0, 100.0)))
    assert abs(old.focal_px["photo"] - 2000.0 / np.tan(np.radians(10.0))) < 1.0  # at the 20 deg limit
    assert [w for w in caught if "solver.hfov_range_deg" in str(w.message)]


def test_each_view_carries_its_own_focal_known():
    """A photo marked ``focal_known = False`` has its focal estimated; the calibrated photos beside it keep
    theirs exactly (one unknown view used to switch focal estimation on for every view)."""
    from dataclasses import replace

    sim = simulate_consist(8, seed=5, pixel_sigma_px=0.5, max_distance_m=60.0)
    f_true = sim.views[0].intrinsics.fx
    views = [replace(sim.views[0], intrinsics=sim.views[0].intrinsics.with_focal(1.1 * f_true), focal_known=False),
             *sim.views[1:]]
    res = solve_consist(sim.carriages, sim.links, views, SolveOptions(pixel_sigma_px=0.5, estimate_focal=True))
    assert res.converged
    for v in views[1:]:
        assert res.focal_px[v.name] == v.intrinsics.fx  # held, to the bit
    name = views[0].name
    err = res.focal_px[name] - f_true
    assert abs(err) < 4 * res.sigma_focal_px[name] + 1.0, (err, res.sigma_focal_px[name])
    assert abs(err) < 0.03 * f_true  # the 10 % wrong start is corrected
    assert set(res.sigma_focal_px) == {name}
