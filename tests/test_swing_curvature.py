"""A carried carriage's body-centre interval counts its swing about the held coupling to second order
(``camera_term.swing_second_moment``): the arc's sagitta, which the first-order covariance draws straight (seed 992
of the multi-view benchmark: a carriage carried on 2 points, 8.5 deg of heading sigma, 0.58 m off across its swing
at 0.13 m of sigma)."""

from __future__ import annotations

import warnings

import numpy as np

from workbench.core.geometry import exp_so3
from workbench.solve import SolveOptions, SolveWarning, solve_consist
from workbench.solve.camera_term import swing_second_moment
from workbench.solve.simulate import simulate_consist


def test_swing_second_moment_against_sampling():
    """The closed form (Isserlis) against 200 000 sampled rotations, for a full rotation covariance and a lever:
    every entry within 2 % of the largest; for one axis normal to the lever, 3 sigma^4 l l^T / 4."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3))
    S = (A @ A.T + np.diag([0.5, 0.5, 4.0])) * 1e-3  # rad^2: 2-6 deg, the heading the loosest
    lever = np.array([11.0, -3.0, 0.8])
    d = rng.multivariate_normal(np.zeros(3), S, size=200_000)
    s = np.array([exp_so3(x) @ lever for x in d[:20000]]) - lever - np.cross(d[:20000], lever)
    quad = 0.5 * np.cross(d, np.cross(d, lever))
    M = swing_second_moment(S, lever)
    assert np.allclose(quad.T @ quad / len(quad), M, atol=0.02 * np.abs(M).max())
    # the exact rotation's remainder is that quadratic term to within third order
    assert np.sqrt(np.mean(np.sum((s - quad[:20000]) ** 2, 1))) < 0.1 * np.sqrt(np.trace(M))
    sig = np.radians(8.0)
    M1 = swing_second_moment(np.diag([0.0, 0.0, sig**2]), np.array([12.0, 0.0, 0.0]))
    assert np.isclose(M1[0, 0], 0.75 * sig**4 * 144.0) and np.isclose(M1[1, 1], 0.0) and np.isclose(M1[2, 2], 0.0)


def test_a_carried_carriage_states_its_swing_and_a_solved_one_none():
    """In a solved consist the carried carriage's body-centre sigma is its first-order one with the swing's
    second moment added (under its stated rotation covariance, about its held coupler); a carriage solved on
    its own points carries none."""
    sim = simulate_consist(3, seed=4, pixel_sigma_px=3.0, n_points=(7, 7, 2), jackknife_deg=(10.0, 40.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        res = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=3.0), terrain=sim.terrain)
    solved, carried = res.carriages[0], res.carriages[2]
    assert solved.status == "solved" and solved.centre_curvature_m2 is None
    assert carried.status == "carried" and carried.centre_curvature_m2 is not None
    C = np.asarray(carried.covariance_pose)
    M = np.asarray(carried.world_from_carriage)
    lever = np.asarray(carried.body_centre_m) - M[:3, 3]
    from workbench.core.geometry import skew

    Jb = np.hstack([-skew(lever), np.eye(3)])
    lin = np.diag(Jb @ C @ Jb.T)
    curv = np.diag(swing_second_moment(C[:3, :3], carried.swing_lever_m))
    assert np.allclose(carried.sigma_body_centre_m, np.sqrt(lin + curv))
    assert np.all(curv > 0) and np.all(np.sqrt(curv) < 0.5 * np.sqrt(lin))  # second order: small here
    # the lever runs from the front coupler (held to the carriage ahead) to the body centre
    assert 5.0 < np.linalg.norm(carried.swing_lever_m) < 20.0
