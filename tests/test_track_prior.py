"""The railway line as a prior for carriages on the rails (workbench/solve/track_prior.py): its rows against their
numerical derivatives, a carriage on a curve, the gate, and the calibration of the solve with it (simulated)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from workbench.core.geometry import exp_so3, rot_z
from workbench.core.track import RailwayLine, centre_heading_covariance
from workbench.rolling_stock import get_type
from workbench.solve.model import SolveOptions
from workbench.solve.simulate import simulate_consist
from workbench.solve.solver import solve_consist
from workbench.core.track import bogie_pivots
from workbench.solve.track_prior import SoftRows, TrackPrior, track_prior


def _arc(radius: float, n: int = 400) -> RailwayLine:
    """A circular track of ``radius`` m about (0, radius), through the origin heading east, 1 m vertices."""
    phi = np.arange(-n, n + 1) / radius
    P = np.column_stack([radius * np.sin(phi), radius - radius * np.cos(phi), np.zeros(len(phi))])
    return RailwayLine("arc", None, P)


def test_rows_are_the_offsets_and_their_derivatives():
    ct = get_type("shoreliner")
    line = _arc(300.0)
    rng = np.random.default_rng(2)
    R = rot_z(0.2) @ exp_so3(rng.normal(0, 0.02, 3))
    t = np.array([5.0, 1.5, 0.3])
    prior = TrackPrior({0: line}, {0: bogie_pivots(ct)}, scale=2.0)
    Rr, tr = np.stack([R, R]), np.stack([t, t])
    r, a, q, on = prior.rows(Rr, tr)
    assert on.all() and np.allclose(q, bogie_pivots(ct) @ R.T)
    X = q + t
    assert np.allclose(r, 2.0 * np.array([line.foot(x[:2]).offset_m for x in X]))
    assert np.allclose(prior.residuals(Rr[1:], tr[1:], [1]), r[1:])
    h = 1e-5
    # d r / d t = a; d r / d omega = (R s x a) (R' = exp(omega) R); to the 1 m chords of the curve (the foot's
    # blended tangent is the normal's direction, within a few mrad of the chord's)
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        num_t = (prior.rows(Rr, tr + e)[0] - prior.rows(Rr, tr - e)[0]) / (2 * h)
        assert np.allclose(num_t, a[:, j], atol=0.01)
        Rp, Rm = exp_so3(e) @ R, exp_so3(-e) @ R
        num_w = (prior.rows(np.stack([Rp, Rp]), tr)[0] - prior.rows(np.stack([Rm, Rm]), tr)[0]) / (2 * h)
        assert np.allclose(num_w, np.cross(q, a)[:, j], atol=0.01 * np.abs(q).max())
    both = SoftRows(None, prior)
    assert both.cars == [0, 0] and np.allclose(both.rows(Rr, tr)[0], r) and both.clearance(R, t, 0) is None


def test_a_carriage_on_a_curve_sits_inside_by_the_versine():
    """Both pivots on the line: no residual, and the body centre inside the curve by c^2 / (8 radius)."""
    ct = get_type("shoreliner")
    radius = 200.0
    line = _arc(radius)
    c = bogie_pivots(ct)[0, 0] * 2.0  # bogie centres
    half = math.asin(0.5 * c / radius)
    a, b = np.array([radius * math.sin(half), radius - radius * math.cos(half)]), \
        np.array([-radius * math.sin(half), radius - radius * math.cos(half)])
    R, t = np.eye(3), np.array([0.0, 0.5 * (a[1] + b[1]), 0.0])
    prior = TrackPrior({0: line}, {0: bogie_pivots(ct)}, scale=1.0)
    r, *_ = prior.rows(np.stack([R, R]), np.stack([t, t]))
    assert np.abs(r).max() < 2e-3  # the polyline's 1 m chords against the arc
    versine = c * c / (8 * radius)
    assert line.foot(t[:2]).offset_m == pytest.approx(versine, rel=0.02)  # left of the line = inside this curve


def test_gate_and_missing_line_are_recorded_not_applied():
    ct = get_type("shoreliner")

    class C:  # the fields track_prior reads of a solve Car
        def __init__(self, number, on_track):
            self.number, self.on_track, self.ctype = number, on_track, ct

    cars = [C("1", True), C("2", True), C("3", False), C("4", True)]
    R = np.stack([np.eye(3)] * 4)
    t = np.array([[0.0, 0.3, 0.0], [0.0, 12.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    prior, recs = track_prior(cars, [0, 1, 2], R, t, [_arc(1000.0)], 0.2, 1.0, 5.0)
    assert [r.number for r in recs] == ["1", "2", "4"]
    assert recs[0].applied and recs[0].sigma_m == 0.2 and prior.cars == [0, 0]
    assert not recs[1].applied and "beyond 5 m" in recs[1].reason and recs[1].start_offsets_m[0] > 11  # left of the line
    assert not recs[2].applied and recs[2].reason == "the carriage is not solved"
    none, recs = track_prior(cars, [0, 1, 2], R, t, [], 0.2, 1.0, 5.0)
    assert none is None and "no railway line" in recs[0].reason
    with pytest.raises(Exception, match="track_sigma_m"):
        SolveOptions(track_sigma_m=0.0)


def test_the_prior_sharpens_the_lateral_place_and_keeps_the_truth_inside():
    """Simulated (3 cars, 5 points each at 1.5 px): the last carriage on a line through its true pivots, each moved
    across by N(0, 0.1 m). With the prior its lateral error and interval shrink; the truth stays inside."""
    sim = simulate_consist(3, seed=1003, pixel_sigma_px=1.5, n_points=5, distance_factor=1.6)
    k = 2
    ct = sim.carriages[k].carriage_type
    M = sim.truth[k]
    X = bogie_pivots(ct) @ M[:3, :3].T + M[:3, 3]
    u = (X[0, :2] - X[1, :2]) / np.linalg.norm(X[0, :2] - X[1, :2])
    n = np.array([-u[1], u[0]])
    e = np.random.default_rng(0).normal(0.0, 0.1, 2)
    a, b = X[0, :2] + e[0] * n, X[1, :2] + e[1] * n
    d = (a - b) / np.linalg.norm(a - b)
    line = RailwayLine("t", None, np.column_stack([b + np.arange(-150.0, 151.0, 10.0)[:, None] * d,
                                                   np.zeros(31)]))
    body = M[:3, :3] @ np.array([0.0, 0.0, 0.5 * ct.height_m]) + M[:3, 3]
    out = {}
    for on in (False, True):
        cars = list(sim.carriages)
        cars[k] = replace(cars[k], on_track=on)
        res = solve_consist(cars, sim.links, sim.views, SolveOptions(pixel_sigma_px=1.5, track_sigma_m=0.1),
                            sim.terrain, (line,) if on else ())
        cr = res.carriages[k]
        assert res.converged and cr.status == "solved"
        C = centre_heading_covariance(cr.world_from_carriage, cr.body_centre_m, cr.covariance_pose)
        out[on] = (float((cr.body_centre_m[:2] - body[:2]) @ n), math.sqrt(float(n @ C[:2, :2] @ n)))
        assert bool(res.track_prior) == on and (not on or res.track_prior[0]["applied"])
    (e0, s0), (e1, s1) = out[False], out[True]
    assert s1 < 0.5 * s0 and 0.05 < s1 < 0.1, out  # the pivots' mean is known to 0.1 / sqrt 2 at most
    assert abs(e1) <= 1.96 * s1 and abs(e1) < abs(e0), out


def test_rails_check_tells_on_off_and_undecided():
    from workbench.core.track import rails_check

    ct = get_type("shoreliner")
    line = _arc(2000.0)
    M = np.eye(4)
    M[:3, 3] = [0.0, 0.01, 0.0]  # on the (nearly straight) line
    small = np.diag([1e-6] * 3 + [0.02**2] * 3)
    on = rails_check(line, M, bogie_pivots(ct), small, 0.05)
    assert on.decided and on.consistent and on.chi2 < 1 and on.verdict == "yes"
    M2 = M.copy()
    M2[:3, 3] = [0.0, 0.4, 0.0]  # 0.4 m off: 8 sigmas of the line
    off = rails_check(line, M2, bogie_pivots(ct), small, 0.05)
    sag = bogie_pivots(ct)[0, 0] ** 2 / (2 * 2000.0)  # the arc below the pivots' chord
    assert off.decided and not off.consistent and off.offsets_m[0] == pytest.approx(0.4 - sag, abs=0.002)
    assert off.verdict == "no"
    wide = rails_check(line, M2, bogie_pivots(ct), np.diag([1e-6] * 3 + [0.5**2] * 3), 0.05)
    assert not wide.decided and wide.consistent and wide.chi2 < 5.99 and wide.verdict == "cannot tell"
    far = rails_check(line, M2, bogie_pivots(ct), np.diag([1e-6] * 3 + [0.1**2] * 3), 0.05, resolution_m=0.1)
    assert far.decided and far.verdict == "no" and 1.96 * far.sigma_m[0] > 0.1  # wide, but the data reject the rails
    shared = rails_check(line, M, bogie_pivots(ct), small, 0.05, common_cov_en=np.diag([0.0, 0.4**2]))
    assert not shared.decided and shared.sigma_m[0] == pytest.approx(math.hypot(0.02, 0.05, 0.4), rel=0.01)
