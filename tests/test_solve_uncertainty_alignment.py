"""The automatic points' face alignments in the solve's covariance (issue 21): a point placed by its face's
homography carries that homography's error, shared with the face's other points and, the same reference against
the same livery, with the face's points in the other photos (``workbench.correspond.alignment``;
``uncertainty.alignment_term``, ``alignment_covariance.views_per_face``). Checked by Monte Carlo against the
truth."""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import numpy as np

from workbench.solve import Observation, SolveOptions, solve_consist, uncertainty
from workbench.solve.problem import AlignedObservation
from workbench.solve.simulate import simulate_consist


def _z_body_centre(aligned: bool, trials: int = 10, scale_px: float = 0.25, shared: bool = True) -> np.ndarray:
    """Body-centre errors over their sigmas when each carriage's points move by ``L xi`` (``xi ~ N(0, I_8)`` per
    carriage, the same in both photos when ``shared``, else drawn per photo; each point's loading ``L`` (2, 8) drawn
    once per trial and varied by 10 % from photo to photo), solved with the loadings given (``aligned``) or as plain
    points with a shared face misfit of 0.15 px. Two photos from the same place (a panorama's), the simulated
    one twice."""
    z = []
    for trial in range(trials):
        sim = simulate_consist(3, seed=700 + trial, pixel_sigma_px=0.0)
        rng = np.random.default_rng(900 + trial)
        views = [sim.views[0], replace(sim.views[0], name="photo_b")]
        for k, c in enumerate(sim.carriages):
            base = {n: rng.normal(0.0, scale_px / np.sqrt(8.0), (2, 8)) for n in sim.clean_pixels[k]}
            xi = rng.normal(size=8)
            obs = {}
            for v in (views[0].name, views[1].name):
                names = list(dict(c.observations[views[0].name]))
                L = np.array([base[n] * (1 + 0.1 * rng.normal(size=(2, 8))) for n in names])
                uv = np.array([sim.clean_pixels[k][n] for n in names]) + np.einsum(
                    "nij,j->ni", L, xi if shared else rng.normal(size=8))
                obs[v] = [AlignedObservation(n, *p, group="side", loading=tuple(map(tuple, Li))) if aligned
                          else Observation(n, *p, group="side") for n, p, Li in zip(names, uv, L)]
            c.observations = obs
        res = solve_consist(sim.carriages, sim.links, views,
                            SolveOptions(pixel_sigma_px=0.3, face_sigma_px=0.15), terrain=None)
        assert res.status == "converged"
        for c, ci, M in zip(res.carriages, sim.carriages, sim.truth):
            truth = M[:3, :3] @ [0.0, 0.0, ci.carriage_type.height_m / 2] + M[:3, 3]
            z.extend((np.asarray(c.body_centre_m) - truth) / np.asarray(c.sigma_body_centre_m))
    return np.array(z)


def test_alignment_loadings_calibrate_a_shared_face_error(monkeypatch):
    """A face's error shared by its photos: with the loadings (the default) the errors over the sigmas have an
    RMS near 1 (two-sided); with each photo's alignment taken as independent (``views_shared=False``) the
    intervals are too narrow."""
    z_al = _z_body_centre(True)
    monkeypatch.setattr(uncertainty, "covariance_model", partial(uncertainty.covariance_model, views_shared=False))
    z_indep = _z_body_centre(True)
    assert len(z_al) == 10 * 3 * 3
    rms = [float(np.sqrt(np.mean(z**2))) for z in (z_al, z_indep)]
    assert 0.75 < rms[0] < 1.3, rms
    assert rms[1] > 1.25 * rms[0], rms
