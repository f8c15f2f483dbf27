"""The solve's error model for automatic points: predictions carry no information, and a face's shared misfit
widens the intervals as much as it moves the poses (coverage checked by Monte Carlo)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import body_centre_z

from workbench.errors import SettingsError
from workbench.solve import Observation, SolveOptions, solve_consist
from workbench.solve.simulate import simulate_consist


def _with(sim, car: int, make) -> None:
    """Replace car ``car``'s observations of every view by ``make(view, {point: (u, v)}, clean)``."""
    c = sim.carriages[car]
    c.observations = {v: make(v, dict(obs), sim.clean_pixels[car]) for v, obs in c.observations.items()}


def _affine_shift(uv: np.ndarray, a: np.ndarray) -> np.ndarray:
    """The common affine displacement (n, 2) of the points ``uv`` (n, 2) with the coefficients ``a`` (6,) of the
    solve's six modes (two shifts; u and v, each over its RMS spread, in u and in v)."""
    d = uv - uv.mean(0)
    s = np.sqrt(np.mean(d**2, axis=0))
    return a[:2] + np.column_stack([d @ (a[2:4] / s), d @ (a[4:6] / s)])


def _sigma_position(sim, opts: SolveOptions) -> np.ndarray:
    res = solve_consist(sim.carriages, sim.links, sim.views, opts, terrain=None)
    assert res.status == "converged"
    return np.array([np.asarray(c.sigma_body_centre_m, float) for c in res.carriages])


def test_predictions_add_no_information():
    """Points flagged ``derived`` (projected from a pose, carried from another photo) leave the covariance as
    it is without them; the same points as measurements would shrink it."""
    opts = SolveOptions(pixel_sigma_px=0.5)
    names = sorted(next(iter(simulate_consist(3, seed=4).carriages[1].observations.values())))

    def measured_only(v, obs, clean):
        return [Observation(n, *obs[n]) for n in names[:5]]

    def plus_predictions(v, obs, clean):  # the others exactly where the pose puts them: no new evidence
        return [Observation(n, *obs[n]) for n in names[:5]] + \
               [Observation(n, *clean[n], derived=True) for n in names[5:]]

    def plus_measurements(v, obs, clean):
        return [Observation(n, *obs[n]) for n in names[:5]] + [Observation(n, *clean[n]) for n in names[5:]]

    sig = {}
    for label, make in (("measured", measured_only), ("predicted", plus_predictions), ("as_measured", plus_measurements)):
        sim = simulate_consist(3, seed=4, pixel_sigma_px=0.5)
        _with(sim, 1, make)
        sig[label] = _sigma_position(sim, opts)[1]
    assert len(names) >= 7
    np.testing.assert_allclose(sig["predicted"], sig["measured"], rtol=0.1)
    assert np.all(sig["as_measured"] < 0.97 * sig["predicted"])


def test_predictions_are_checked_against_the_measured_points():
    """Step 4b: predictions 36 px off (a far corner projected from a face's pose with the wrong roll) pull their
    car (4 measured points) further than its measured points allow (a shift chi-square of about 40), so they
    are released and the pose comes back to the measured points' fit (within 5 % of the pull); predictions
    that agree with the measurements keep their weight (the pose is the one they give at full weight). A shift
    that large (beyond the 1 - 1e-4 point, 27.9) also marks the car doubtful: one of its two poses is wrong."""
    from workbench.files.solution import doubts_of
    names = sorted(next(iter(simulate_consist(3, seed=4).carriages[1].observations.values())))

    def measured_only(v, obs, clean):
        return [Observation(n, *obs[n]) for n in names[:4]]

    def predictions(off):
        def make(v, obs, clean):
            return [Observation(n, *obs[n]) for n in names[:4]] + \
                   [Observation(n, *(np.asarray(clean[n]) + off), sigma_px=2.0, derived=True) for n in names[4:]]
        return make

    centre, note, disagree = {}, {}, {}
    for label, make, release in (("measured", measured_only, 30.0),
                                 ("biased_kept", predictions(np.array([30.0, -20.0])), 1.0),
                                 ("biased", predictions(np.array([30.0, -20.0])), 30.0),
                                 ("good_kept", predictions(np.zeros(2)), 1.0),
                                 ("good", predictions(np.zeros(2)), 30.0)):
        sim = simulate_consist(3, seed=4, pixel_sigma_px=0.5)
        _with(sim, 1, make)
        res = solve_consist(sim.carriages, sim.links, sim.views,
                            SolveOptions(pixel_sigma_px=0.5, prediction_release=release), terrain=None)
        assert res.status == "converged"
        step = {s.name: s for s in res.steps}["4b_predictions_checked"]
        assert step.ran == (label in ("biased", "good"))
        note[label] = step.note
        disagree[label] = [w["car"] for w in res.warnings if w["kind"] == "predictions_disagree"]
        centre[label] = np.asarray(res.carriages[1].body_centre_m, float)
    pull = np.linalg.norm(centre["biased_kept"] - centre["measured"])
    assert pull > 0.005  # the biased predictions do bend the fit
    assert np.linalg.norm(centre["biased"] - centre["measured"]) < 0.05 * pull
    assert "released on every car with some" in note["biased"]
    assert "kept" in note["good"] and "released" not in note["good"]
    number = sim.carriages[1].number
    assert disagree == {"measured": [], "biased_kept": [], "biased": [number], "good_kept": [], "good": []}
    assert set(doubts_of({"warnings": [{"car": number, "kind": "predictions_disagree", "message": "m"}]})) == {number}
    np.testing.assert_allclose(centre["good"], centre["good_kept"], atol=1e-6)
    with pytest.raises(SettingsError, match="prediction_release"):
        SolveOptions(prediction_release=0.5)


def test_shared_misfit_only_widens_grouped_points():
    opts0, opts = SolveOptions(pixel_sigma_px=0.5), SolveOptions(pixel_sigma_px=0.5, face_sigma_px=0.5)

    def grouped(v, obs, clean):
        return [Observation(n, *uv, group="right") for n, uv in obs.items()]

    sim = simulate_consist(3, seed=6, pixel_sigma_px=0.5)
    plain0, plain = _sigma_position(sim, opts0), _sigma_position(sim, opts)
    np.testing.assert_allclose(plain, plain0, rtol=1e-9)  # no groups: the misfit term has nothing to act on
    for k in range(3):
        _with(sim, k, grouped)
    wide = _sigma_position(sim, opts)
    assert np.all(wide > 1.05 * plain0)
    with pytest.raises(SettingsError, match="face_sigma_px"):
        SolveOptions(face_sigma_px=-1.0)


def test_intervals_cover_a_shared_affine_misfit():
    """Monte Carlo: every carriage's points get one common affine displacement (tau = 0.6 px per mode) plus
    0.3 px of independent noise. Solved with face_sigma_px = tau the body-centre errors, divided by their
    sigmas, have an RMS near 1 (two-sided: neither too narrow nor too wide); without the term they are too
    narrow."""
    tau, sig = 0.6, 0.3
    z_with, z_without = [], []
    for trial in range(12):
        sim = simulate_consist(3, seed=500 + trial, pixel_sigma_px=0.0)
        rng = np.random.default_rng(trial)
        for k in range(3):
            a = rng.normal(0.0, tau, 6)

            def misfit(v, obs, clean, a=a):
                uv = np.array([clean[n] for n in obs])
                shift = _affine_shift(uv, a)
                noisy = uv + shift + rng.normal(0.0, sig, uv.shape)
                return [Observation(n, *p, group="side") for n, p in zip(obs, noisy)]

            _with(sim, k, misfit)
        for face_sigma, out in ((tau, z_with), (0.0, z_without)):
            res = solve_consist(sim.carriages, sim.links, sim.views,
                                SolveOptions(pixel_sigma_px=sig, face_sigma_px=face_sigma, prior_dof=1e6),
                                terrain=None)
            for c, ci, M in zip(res.carriages, sim.carriages, sim.truth):
                truth = M[:3, :3] @ [0.0, 0.0, ci.carriage_type.height_m / 2] + M[:3, 3]
                out.extend((np.asarray(c.body_centre_m) - truth) / np.asarray(c.sigma_body_centre_m))
    z_with, z_without = np.array(z_with), np.array(z_without)
    assert len(z_with) == 12 * 3 * 3
    rms_with, rms_without = float(np.sqrt(np.mean(z_with**2))), float(np.sqrt(np.mean(z_without**2)))
    assert 0.7 < rms_with < 1.35, rms_with
    assert rms_without > 1.5 * rms_with


def test_a_face_takes_its_misfit_from_its_ecc_correlation():
    """A face aligned by ECC without matches of its own (no alignment loading) shares a misfit of
    ``ECC_MISFIT_PX (1 - ecc)`` px per mode, at least ``face_sigma_px``: every face at ecc 0.95 gives the
    intervals of ``face_sigma_px`` = 0.5 exactly; at 0.995 the floor's; a face's ecc widens its own carriage
    most. Monte Carlo: faces with misfits of 0.15-0.66 px per mode drawn from their ecc are covered (RMS of error
    over sigma near 1), and too narrow when the ecc is not given (the fixed 0.15 px). The misfits are drawn as the
    solve states them: six affine modes in the face's own axes, those across it smaller
    (``alignment_covariance.guided_loadings``; the same law in every photo)."""
    from workbench.solve.alignment_covariance import guided_loadings
    from workbench.solve.uncertainty import ECC_MISFIT_PX, GUIDED_NOISE_PX, face_misfit_px

    np.testing.assert_allclose(face_misfit_px(np.array([0.95, 0.999, np.nan]), 0.15),
                               [ECC_MISFIT_PX * 0.05, 0.15, 0.15])

    def faces(eccs):
        sim = simulate_consist(3, seed=6, pixel_sigma_px=0.5)
        for k, e in enumerate(eccs):
            _with(sim, k, lambda v, obs, clean, e=e: [Observation(n, *uv, group="left", ecc=e)
                                                      for n, uv in obs.items()])
        return sim

    sim = faces([0.95] * 3)
    at_ecc = _sigma_position(sim, SolveOptions(pixel_sigma_px=0.5, face_sigma_px=0.15))
    fixed = _sigma_position(sim, SolveOptions(pixel_sigma_px=0.5, face_sigma_px=0.05 * ECC_MISFIT_PX))
    np.testing.assert_allclose(at_ecc, fixed, rtol=1e-6)
    floor = _sigma_position(faces([0.995] * 3), SolveOptions(pixel_sigma_px=0.5, face_sigma_px=0.4))  # 0.4 > 0.05
    one_px = 1.0 - 1.0 / ECC_MISFIT_PX  # the ecc of a face with 1 px of misfit per mode
    mixed = _sigma_position(faces([0.995, 0.995, one_px]), SolveOptions(pixel_sigma_px=0.5, face_sigma_px=0.4))
    ratio = mixed / floor
    assert np.all(ratio[2] > 1.2)  # 1 px of misfit on car 2's face
    assert np.all(ratio[1] < ratio[2]) and np.all(ratio >= 1.0 - 1e-9)  # its neighbour along the chain, less
    np.testing.assert_allclose(mixed[0], floor[0], rtol=0.02)  # the far car hardly

    sig = 0.3
    z_with, z_without = [], []
    for trial in range(12):
        sim = simulate_consist(3, seed=800 + trial, pixel_sigma_px=0.0)
        rng = np.random.default_rng(40 + trial)
        for k in range(3):
            ecc = float(rng.choice([0.98, 0.95, 0.92, 0.89]))
            xi = rng.normal(size=8)

            def misfit(v, obs, clean, xi=xi, ecc=ecc):
                uv = np.array([clean[n] for n in obs])
                n = len(uv)
                _, L, _ = guided_loadings(np.full(n, -1), np.zeros((n, 2, 8)), np.ones(n, bool), np.zeros(n, int),
                                          np.zeros(n, int), uv, np.full(n, ECC_MISFIT_PX * (1.0 - ecc)))
                shift = L @ xi
                noisy = uv + shift + rng.normal(0.0, GUIDED_NOISE_PX, uv.shape)  # the warp's remainder
                return [Observation(n, *p, group="side", ecc=ecc) for n, p in zip(obs, noisy)]

            _with(sim, k, misfit)
        for given, out in ((True, z_with), (False, z_without)):
            if not given:
                for c in sim.carriages:
                    c.observations = {v: [Observation(o.point, o.u, o.v, group=o.group) for o in obs]
                                      for v, obs in c.observations.items()}
            res = solve_consist(sim.carriages, sim.links, sim.views,
                                SolveOptions(pixel_sigma_px=sig, face_sigma_px=0.15, prior_dof=1e6), terrain=None)
            for c, ci, M in zip(res.carriages, sim.carriages, sim.truth):
                truth = M[:3, :3] @ [0.0, 0.0, ci.carriage_type.height_m / 2] + M[:3, 3]
                out.extend((np.asarray(c.body_centre_m) - truth) / np.asarray(c.sigma_body_centre_m))
    rms_with, rms_without = float(np.sqrt(np.mean(np.square(z_with)))), float(np.sqrt(np.mean(np.square(z_without))))
    assert len(z_with) == 12 * 3 * 3
    assert 0.7 < rms_with < 1.35, rms_with
    assert rms_without > 1.2 * rms_with, (rms_without, rms_with)  # 1.25 against 0.91 (session 31)


def test_a_guided_faces_points_carry_the_warps_remainder_not_the_pooled_noise(monkeypatch):
    """A face aligned by ECC without matches places its points by one warp: their errors are the face's shared
    misfit and a small remainder (``GUIDED_NOISE_PX``, 0.105 px measured beyond the affine modes), not independent
    noise at the pooled pixel sigma (0.35 px there). At the default the intervals are narrower than those of the
    same points without their ECC, and narrower than with the remainder set to the pixel sigma. Monte Carlo: faces
    whose points move by a misfit drawn from their ECC as the solve states it (six affine modes in the face's own
    axes, ``alignment_covariance.guided_loadings``) and a remainder of ``GUIDED_NOISE_PX``, solved at a pixel sigma
    of 0.35 px: RMS of error over sigma near 1; taken as plain points (no ECC), the intervals are wider than the
    errors. (Until session 31 the guided face's misfit took the plain points' law, and the remainder at the pixel
    sigma gave their intervals exactly.)"""
    from workbench.solve import uncertainty
    from workbench.solve.alignment_covariance import guided_loadings
    from workbench.solve.uncertainty import ECC_MISFIT_PX, GUIDED_NOISE_PX

    assert 0.05 <= GUIDED_NOISE_PX <= 0.2
    opts = SolveOptions(pixel_sigma_px=0.35, face_sigma_px=0.15, prior_dof=1e6)

    def faces(ecc):
        sim = simulate_consist(3, seed=6, pixel_sigma_px=0.35)
        for k in range(3):
            _with(sim, k, lambda v, obs, clean: [Observation(n, *uv, group="left", ecc=ecc) for n, uv in obs.items()])
        return sim

    plain = _sigma_position(faces(None), opts)
    monkeypatch.setattr(uncertainty, "GUIDED_NOISE_PX", 0.35)
    remainder_at_sigma = _sigma_position(faces(0.995), opts)
    monkeypatch.undo()
    guided = _sigma_position(faces(0.995), opts)
    assert np.all(guided < 0.9 * plain)
    assert np.all(guided < remainder_at_sigma)

    z = {True: [], False: []}
    for trial in range(12):
        sim = simulate_consist(3, seed=820 + trial, pixel_sigma_px=0.0)
        rng = np.random.default_rng(60 + trial)
        for k in range(3):
            ecc = float(rng.choice([0.99, 0.97, 0.95]))
            xi = rng.normal(size=8)

            def warp(v, obs, clean, xi=xi, ecc=ecc):
                uv = np.array([clean[n] for n in obs])
                n = len(uv)
                _, L, _ = guided_loadings(np.full(n, -1), np.zeros((n, 2, 8)), np.ones(n, bool), np.zeros(n, int),
                                          np.zeros(n, int), uv, np.full(n, max(0.15, ECC_MISFIT_PX * (1.0 - ecc))))
                p = uv + L @ xi + rng.normal(0.0, GUIDED_NOISE_PX, uv.shape)
                return [Observation(n, *q, group="side", ecc=ecc) for n, q in zip(obs, p)]

            _with(sim, k, warp)
        for given in (True, False):
            if not given:
                for c in sim.carriages:
                    c.observations = {v: [Observation(o.point, o.u, o.v, group=o.group) for o in obs]
                                      for v, obs in c.observations.items()}
            res = solve_consist(sim.carriages, sim.links, sim.views, opts, terrain=None)
            z[given].extend(body_centre_z(res, sim))
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in z.items()}
    assert len(z[True]) == 12 * 3 * 3
    assert 0.8 < rms[True] < 1.3, rms
    assert rms[False] < 0.95 * rms[True], rms


def test_intervals_are_the_estimators_when_the_pixels_are_better_than_configured():
    """Monte Carlo: picks at 0.1 px solved with ``pixel_sigma_px = 1`` on a DEM wrong by N(0, 0.25 m) per carriage,
    as it states. The solver's cost weighs the pixels at 1 px against the contact, so it leans on the DEM more
    than 0.1 px picks would have it: the intervals are those of that estimator (the sandwich at the configured
    weights), and the body centres' errors over their sigmas have an RMS near 1. (The information at the
    estimated 0.1 px, the former model, gave 1.38 on these 160: too narrow.)"""
    from workbench.solve.simulate import dem_with_error

    z = []
    for trial in range(40):
        sim = simulate_consist(4, seed=900 + trial, pixel_sigma_px=0.1)
        res = solve_consist(sim.carriages, sim.links, sim.views,
                            SolveOptions(pixel_sigma_px=1.0, terrain_sigma_m=0.25, prior_dof=0.0),
                            terrain=dem_with_error(sim, 0.25, 77 + trial))
        for c, ci, M in zip(res.carriages, sim.carriages, sim.truth):
            truth = M[:3, :3] @ [0.0, 0.0, ci.carriage_type.height_m / 2] + M[:3, 3]
            z.append((np.asarray(c.body_centre_m) - truth) / np.asarray(c.sigma_body_centre_m))
    z = np.array(z)
    assert z.shape == (160, 3)
    rms = np.sqrt(np.mean(z**2, axis=0))
    assert np.all((rms > 0.7) & (rms < 1.15)), rms


def test_crb_takes_the_estimators_weighting():
    """``crb(weighting=...)``: with equal point counts both weightings give the same (the bound); with unequal
    counts the per-point bound (maximum likelihood) lies below the per-carriage estimator's sandwich covariance,
    carriage by carriage (a PSD difference), and strictly somewhere; an unknown weighting is refused."""
    from workbench.solve import crb

    sim = simulate_consist(4, seed=21, pixel_sigma_px=1.0)
    a = crb(sim.carriages, sim.links, sim.views, sim.truth, 1.0, weighting="per_carriage")
    b = crb(sim.carriages, sim.links, sim.views, sim.truth, 1.0, weighting="per_point")
    for Ca, Cb in zip(a["body_centre_cov"], b["body_centre_cov"]):
        np.testing.assert_allclose(Ca, Cb, rtol=1e-10, atol=1e-14)
    sim = simulate_consist(6, seed=50003, pixel_sigma_px=1.0, n_points=(4, 10, 6, 10, 5, 8))
    for est in (False, True):
        a = crb(sim.carriages, sim.links, sim.views, sim.truth, 1.0, est, weighting="per_carriage")
        b = crb(sim.carriages, sim.links, sim.views, sim.truth, 1.0, est, weighting="per_point")
        excess = []
        for Ca, Cb in zip(a["body_centre_cov"], b["body_centre_cov"]):
            lam = np.linalg.eigvalsh(Ca - Cb)
            assert lam.min() > -1e-9 * np.trace(Cb), lam
            excess.append(np.trace(Ca) / np.trace(Cb))
        assert max(excess) > 1.005, excess
        if est:
            assert b["focal_sigma"][0] <= a["focal_sigma"][0] * (1 + 1e-9)
    with pytest.raises(SettingsError, match="weighting"):
        crb(sim.carriages, sim.links, sim.views, sim.truth, 1.0, weighting="per_face")


def test_predictions_check_is_repeated_on_the_mixed_fit(monkeypatch):
    """Step 4b with some cars released and the others kept checks that mixed fit in turn: a car whose
    predictions were within the limit while its neighbour's pulled the other way, and beyond it once that
    neighbour's are released, is released too (Spuyten Duyvil's 6234 next to 6231: 1.7 and 2.5 m off, 4-5 sigma,
    before this). The shift statistics are scripted here; the fits are real."""
    import workbench.solve.steps as chain

    def predictions(v, obs, clean):
        names = sorted(obs)
        return [Observation(n, *obs[n]) for n in names[:4]] + \
               [Observation(n, *clean[n], sigma_px=2.0, derived=True) for n in names[4:]]

    calls = []

    def scripted(released, R, t, f, R_k, t_k, *a, **k):
        calls.append(1)
        return {1: 20.0, 2: 5.0} if len(calls) == 1 else {1: 0.0, 2: 30.0}

    monkeypatch.setattr(chain, "_prediction_shift", scripted)
    sim = simulate_consist(3, seed=4, pixel_sigma_px=0.5)
    _with(sim, 1, predictions)
    _with(sim, 2, predictions)
    res = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=0.5), terrain=None)
    step = {s.name: s for s in res.steps}["4b_predictions_checked"]
    note = step.note
    assert len(calls) == 2
    assert "released on every car with some" in note and "moved car(s) beyond the limit too" in note
    # each car's shift when it was released: car 1's 20 (within the doubt limit), car 2's 30 in the second round
    assert step.facts["shift_chi2_at_release"] == {sim.carriages[1].number: 20.0, sim.carriages[2].number: 30.0}
    assert step.facts["doubtful"] == [sim.carriages[2].number]
    assert [w["car"] for w in res.warnings if w["kind"] == "predictions_disagree"] == [sim.carriages[2].number]

    calls.clear()
    monkeypatch.setattr(chain, "_prediction_shift", lambda *a, **k: (calls.append(1), {1: 20.0, 2: 5.0})[1])
    res = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=0.5), terrain=None)
    note = {s.name: s for s in res.steps}["4b_predictions_checked"].note
    assert len(calls) == 2 and "kept on the others" in note and "too" not in note


def test_variance_components_recover_noise_and_face_misfit():
    """The method of moments of ``variance_components``: on a linear model with faces (six affine modes each,
    tau = 0.5 px) and independent noise (sigma = 0.2 px), the estimates averaged over 200 draws are unbiased
    (two-sided, 6 % and 10 %); with no face misfit tau comes out near zero and sigma unbiased."""
    from workbench.solve.variance_components import estimate_variance_components, face_modes

    rng = np.random.default_rng(11)
    n_faces, n_pts = 8, 12
    groups = np.repeat(np.arange(n_faces), n_pts)
    views = np.zeros(len(groups), int)
    uv = rng.uniform(0, 800, (len(groups), 2))
    w = np.ones(len(groups))
    J = rng.normal(size=(2 * len(groups), 10))
    modes = face_modes(groups, views, uv, w)
    A = np.hstack(modes)
    Rm = np.eye(len(J)) - J @ np.linalg.solve(J.T @ J, J.T)
    for tau in (0.5, 0.0):
        est = []
        for _ in range(200):
            e = rng.normal(0, 0.2, len(J)) + A @ rng.normal(0, tau, A.shape[1])
            vc = estimate_variance_components(J, Rm @ e, np.ones(len(J)), modes,
                                              lambda s: np.linalg.inv(J.T @ J / s**2), 0.3)
            est.append((vc.sigma_px**2, vc.face_sigma_px**2))
        s2, t2 = np.mean(est, axis=0)
        assert abs(s2 / 0.2**2 - 1) < 0.06, s2
        if tau > 0:
            assert abs(t2 / tau**2 - 1) < 0.10, t2
        else:
            assert t2 < 0.01 * 0.2**2, t2


def test_estimated_components_calibrate_a_shared_affine_misfit():
    """As :func:`test_intervals_cover_a_shared_affine_misfit`, with neither sigma nor tau given: both estimated
    from the residuals (``face_sigma_px=None``; 12 points a face, so that the faces' modes leave the points' own
    noise degrees of freedom), the body-centre errors over their sigmas have an RMS near 1 (two-sided), the
    estimated tau is near the truth (it comes out about 20 % high, so the intervals a little wide), and the
    solution says the noise was estimated."""
    tau, sig = 0.6, 0.3
    z, faces, sigmas = [], [], []
    for trial in range(12):
        sim = simulate_consist(4, seed=700 + trial, pixel_sigma_px=0.0, n_points=12)
        rng = np.random.default_rng(100 + trial)
        for k in range(4):
            a = rng.normal(0.0, tau, 6)

            def misfit(v, obs, clean, a=a, k=k):
                uv = np.array([clean[n] for n in obs])
                shift = _affine_shift(uv, a)
                noisy = uv + shift + rng.normal(0.0, sig, uv.shape)
                return [Observation(n, *p, group=f"car{k}") for n, p in zip(obs, noisy)]

            _with(sim, k, misfit)
        res = solve_consist(sim.carriages, sim.links, sim.views, SolveOptions(pixel_sigma_px=1.0, face_sigma_px=None),
                            terrain=None)
        assert res.noise_estimated
        faces.append(res.face_sigma_px)
        sigmas.append(res.sigma_px)
        for c, ci, M in zip(res.carriages, sim.carriages, sim.truth):
            truth = M[:3, :3] @ [0.0, 0.0, ci.carriage_type.height_m / 2] + M[:3, 3]
            z.extend((np.asarray(c.body_centre_m) - truth) / np.asarray(c.sigma_body_centre_m))
    rms = float(np.sqrt(np.mean(np.square(z))))
    # measured: 0.69 (tau over-estimated by about 20 %: a little wide); with the true sigma and tau 0.85; with
    # no face term 4.1 (far too narrow)
    assert 0.6 < rms < 1.2, rms
    assert 0.4 < float(np.sqrt(np.mean(np.square(faces)))) < 0.8, faces
    assert 0.25 < float(np.sqrt(np.mean(np.square(sigmas)))) < 0.35, sigmas


def test_each_face_gets_its_own_misfit():
    """One face of eight misfits by 2 px, the others by 0.2 px: averaged over 100 draws, its own estimate is
    well above the pooled one and above the others' (two-sided: shrunk, so below its true 2 px)."""
    from workbench.solve.variance_components import estimate_variance_components, face_modes

    rng = np.random.default_rng(5)
    groups = np.repeat(np.arange(8), 12)
    uv = rng.uniform(0, 800, (len(groups), 2))
    J = rng.normal(size=(2 * len(groups), 10))
    modes = face_modes(groups, np.zeros(len(groups), int), uv, np.ones(len(groups)))
    taus = np.array([2.0] + [0.2] * 7)
    Rm = np.eye(len(J)) - J @ np.linalg.solve(J.T @ J, J.T)
    own, pooled = [], []
    for _ in range(100):
        e = rng.normal(0, 0.2, len(J)) + sum(A @ rng.normal(0, t, 6) for A, t in zip(modes, taus))
        vc = estimate_variance_components(J, Rm @ e, np.ones(len(J)), modes,
                                          lambda s: np.linalg.inv(J.T @ J / s**2), 0.3)
        own.append(vc.face_sigmas_px)
        pooled.append(vc.face_sigma_px)
    own = np.sqrt(np.mean(np.square(own), axis=0))
    pooled = float(np.sqrt(np.mean(np.square(pooled))))
    assert 1.3 * pooled < own[0] < 2.0, (own, pooled)
    assert np.all(own[1:] < 0.8 * own[0]), own


def test_a_fit_that_misses_every_carriage_alike_marks_them_all():
    """A camera whose focal is 60 % off (a known focal that is wrong: a cropped photo's EXIF, a wrong profile):
    every carriage misfits alike, so the per-carriage test (against the pooled sigma, relative to the median
    carriage) passes each; the whole-fit test (:func:`fit_misfit`: the residuals' own sigma over 4 times the
    configured, beyond the chi-square's 1 - 1e-4 quantile; then :func:`whole_misfit_carriages`, the carriages
    together at the configured sigma) marks every carriage ``misfit``, a doubt the report, viewer and exports
    show. The true focal, or one 10 % off (sigma 1.2-1.8 px against 1 px), marks none. Seeds
    0-2 of four-carriage consists at 1 px; the multi-view benchmark's one such draw (mv1418000: residuals 7.6 px
    against 0.5 px, two carriages 72 and 105 sigma off) went out unmarked before (docs/calibration.md, session 29)."""
    import warnings
    from dataclasses import replace

    from workbench.files.solution import doubts_of
    from workbench.solve import SolveWarning
    from workbench.solve.uncertainty import fit_misfit

    assert fit_misfit(4.1, 40.0, 1.0) and not fit_misfit(3.9, 40.0, 1.0)
    assert not fit_misfit(float("nan"), 40.0, 1.0) and not fit_misfit(9.0, 0.0, 1.0)
    assert not fit_misfit(4.5, 0.3, 1.0)  # a ratio over 4 that a third of a degree of freedom makes likely
    for seed in range(3):
        sim = simulate_consist(4, seed=seed, pixel_sigma_px=1.0)
        for factor, marked in ((1.0, False), (1.1, False), (1.6, True)):
            K = sim.views[0].intrinsics
            views = [replace(sim.views[0], intrinsics=replace(K, fx=K.fx * factor, fy=K.fy * factor))]
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", SolveWarning)
                res = solve_consist(sim.carriages, sim.links, views, SolveOptions(pixel_sigma_px=1.0),
                                    terrain=sim.terrain)
            marks = [w for w in res.warnings if w["kind"] == "misfit"]
            if not marked:
                assert not marks and res.sigma_px_estimated < 2.0, (seed, factor)
                continue
            assert res.sigma_px_estimated > 4.0, seed
            assert sorted(w["car"] for w in marks) == sorted(c.number for c in res.carriages), seed
            assert all("as a whole" in w["message"] for w in marks)
            doc = {"warnings": res.warnings, "carriages": [], "links": []}
            assert set(doubts_of(doc)) == {c.number for c in res.carriages}
