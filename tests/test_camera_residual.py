"""The multi-view cameras' disagreement is not taken for pixel noise (workbench.solve.camera_residual).

Two photos of three coupled cars; in every draw each photo's pose is off by its own error drawn from the covariance
the georegistration states for it, and every pick by fresh pixel noise. Against the truth: the fit's pixel sigma
comes out as the pixel noise with the cameras' stated errors set aside (and inflated without), and the carriages'
intervals with the camera term then contain the truth as often as they say.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from workbench.core.camera import look_at, project_world
from workbench.core.geometry import exp_so3, log_so3
from workbench.files.cameras import PoseUncertainty
from workbench.solve import SolveOptions, SolveWarning, solve_consist
from workbench.solve.camera_residual import camera_directions, view_camera_errors
from workbench.solve.camera_term import add_view_camera_uncertainty
from workbench.solve.model import CarriageInput, View
from workbench.solve.simulate import simulate_consist

SIGMA_PX = 0.5
# each photo's own pose error (1 sigma): 0.03 deg about each axis, 2 cm of its centre: 1-2 px at the carriages,
# a few times the picks' noise (the real-SfM sample's cameras leave 0.7-3 px; much larger errors than these leave
# residuals the first-order split does not hold: a tenth of them at 0.02 deg, a fifth at 0.08 deg)
POSE_SD = np.r_[[np.radians(0.03)] * 3, [0.02] * 3]


@pytest.fixture(scope="module")
def scene():
    """The simulation's consist and camera, a second camera 50 deg round it; the marked points each sees."""
    sim = simulate_consist(3, seed=21, pixel_sigma_px=SIGMA_PX)
    v0 = sim.views[0]
    centre = np.mean([M[:3, 3] for M in sim.truth], axis=0)
    d = v0.camera_centre - centre
    a = np.radians(50.0)
    c1 = centre + np.array([np.cos(a) * d[0] - np.sin(a) * d[1], np.sin(a) * d[0] + np.cos(a) * d[1], d[2]])
    views = [View(name="first", intrinsics=v0.intrinsics, cam_from_world=np.asarray(v0.cam_from_world, float)),
             View(name="second", intrinsics=v0.intrinsics, cam_from_world=look_at(c1, centre))]
    exact = []
    for ci, T in zip(sim.carriages, sim.truth):
        pts = ci.carriage_type.marked_points
        X = np.array([T[:3, :3] @ np.asarray(p, float) + T[:3, 3] for p in pts.values()])
        per_view = {}
        for v in views:
            uv, depth = project_world(v.intrinsics, v.cam_from_world, X)
            ok = (depth > 1.0) & v.intrinsics.in_image(np.nan_to_num(uv, nan=-1e9))
            per_view[v.name] = {n: u for n, u, k in zip(pts, uv, ok) if k}
        exact.append(per_view)
    return sim, views, exact


def _moved(v: View, e: np.ndarray) -> View:
    """``v`` with ``world_from_cam`` turned by ``Exp(e[:3])`` on the left and its centre moved by ``e[3:]``."""
    M = np.asarray(v.cam_from_world, float)
    c = -M[:3, :3].T @ M[:3, 3]
    R = (exp_so3(e[:3]) @ M[:3, :3].T).T
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, -R @ (c + e[3:])
    return View(name=v.name, intrinsics=v.intrinsics, cam_from_world=out)


def _draws(scene, n: int, with_errors: bool):
    sim, views, exact = scene
    own = {v.name: np.diag(POSE_SD**2) for v in views}
    pu = PoseUncertainty(model_covariance={}, jacobian={}, own_covariance=own, not_modelled=())
    errors = view_camera_errors(pu)
    rng = np.random.default_rng(5)
    sig, z = [], []
    for _ in range(n):
        cams = [_moved(v, rng.normal(0.0, POSE_SD)) for v in views]
        cars = [CarriageInput(number=ci.number, carriage_type=ci.carriage_type,
                              observations={vn: {p: tuple(u + rng.normal(0.0, SIGMA_PX, 2)) for p, u in obs.items()}
                                            for vn, obs in ex.items()})
                for ci, ex in zip(sim.carriages, exact)]
        opts = SolveOptions(pixel_sigma_px=SIGMA_PX, camera_errors=errors if with_errors else None)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SolveWarning)
            res = solve_consist(cars, sim.links, cams, opts)
        sig.append(res.sigma_px_estimated)
        add_view_camera_uncertainty(res, cars, sim.links, cams, SIGMA_PX, {}, {}, own)
        for c, T in zip(res.carriages, sim.truth):
            M = np.asarray(c.world_from_carriage, float)
            e = np.r_[log_so3(M[:3, :3] @ T[:3, :3].T), M[:3, 3] - T[:3, 3]]
            C = np.asarray(c.covariance_pose, float)
            z.append(e / np.sqrt(np.diag(C)))
    return np.array(sig), np.array(z)


def test_cameras_disagreement_is_not_taken_for_pixel_noise(scene):
    """40 draws: the pixel sigma's estimate is the picks' noise (RMS 0.5 px, within 15 %) with the cameras' stated
    errors set aside; without, the disagreement of the photos inflates it (by more than 30 %; measured 0.514 and
    1.13 px). With the camera term, the carriages' errors over their sigmas: RMS within 0.8-1.2 per parameter (120
    carriage-draws; measured 0.87-1.06, and 0.61-0.70 for the rotations without the split)."""
    sig, z = _draws(scene, 40, True)
    rms = float(np.sqrt(np.mean(sig**2)))
    assert 0.85 * SIGMA_PX < rms < 1.15 * SIGMA_PX, rms
    zr = np.sqrt(np.mean(z**2, axis=0))
    assert np.all((0.8 < zr) & (zr < 1.2)), zr
    sig0, z0 = _draws(scene, 40, False)
    rms0 = float(np.sqrt(np.mean(sig0**2)))
    assert rms0 > 1.3 * SIGMA_PX, rms0  # the photos' disagreement counted as pixel noise ...
    zr0 = np.sqrt(np.mean(z0**2, axis=0))
    assert np.all(zr0[:3] < 0.85), zr0  # ... and again by the camera term: the rotations' intervals too wide


def test_directions_only_where_the_cameras_fill_more_than_the_noise():
    """:func:`camera_directions` on a made-up linear problem: with the cameras' error far below the noise it sets
    nothing aside; far above, one direction per camera parameter the fit cannot follow, orthonormal."""
    rng = np.random.default_rng(1)
    J = rng.normal(size=(40, 4))
    D = rng.normal(size=(40, 3))

    def assemble(s):
        H = J.T @ J / s**2
        return H, np.linalg.inv(H)

    none = camera_directions(D, J, 1e-6 * np.eye(3), np.ones(40), assemble, 1.0)
    assert none.shape == (40, 0)
    U = camera_directions(D, J, 1e4 * np.eye(3), np.ones(40), assemble, 1.0)
    assert U.shape == (40, 3)
    assert np.allclose(U.T @ U, np.eye(3), atol=1e-10)
    assert np.allclose(J.T @ U, 0.0, atol=1e-8)  # in the residual space: nothing the fit follows
