"""The multi-view route's camera uncertainty carried into the carriages' intervals (issue 21; docs/calibration.md).

A consist seen by two cameras of one SfM model placed by a similarity: the camera term the solve adds
(:func:`workbench.solve.camera_term.add_view_camera_uncertainty`) against the carriages' actual response to the
similarity's error (finite differences of the solve, and a Monte Carlo of the similarity with the same pixels);
then the georef and solve stages on a small generated multi-view incident."""

from __future__ import annotations

import copy
import json
import shutil
import warnings

import numpy as np
import pytest

from conftest import with_solver_lines

from workbench.core.camera import look_at, project_world
from workbench.core.geometry import exp_so3, log_so3
from workbench.georef.similarity import SimilarityResult
from workbench.solve import SolveOptions, SolveWarning, solve_consist
from workbench.solve.model import CarriageInput, View
from workbench.solve.simulate import simulate_consist
from workbench.solve.camera_term import add_view_camera_uncertainty, camera_pose_jacobian

SIGMA_PX = 0.5


def _similarity_covariance(seed: int) -> np.ndarray:
    """(7, 7): log scale 1e-3, rotation 0.05 deg, translation 4 cm (1 sigma), correlated."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(7, 7))
    Q = A @ A.T + 7.0 * np.eye(7)
    d = np.sqrt(np.diag(Q))
    Q = Q / np.outer(d, d)
    sd = np.array([1e-3] + [np.radians(0.05)] * 3 + [0.04] * 3)
    return Q * np.outer(sd, sd)


@pytest.fixture(scope="module")
def two_views():
    """Three coupled cars, the simulation's camera plus a second one 50 deg round the consist (every marked point
    in front of it and inside its image, + 0.5 px), both of an SfM model placed by a similarity."""
    sim = simulate_consist(3, seed=11, pixel_sigma_px=SIGMA_PX)
    v0 = sim.views[0]
    rng = np.random.default_rng(12)
    centre = np.mean([M[:3, 3] for M in sim.truth], axis=0)
    c0 = v0.camera_centre
    a = np.radians(50.0)
    d = c0 - centre
    c1 = centre + np.array([np.cos(a) * d[0] - np.sin(a) * d[1], np.sin(a) * d[0] + np.cos(a) * d[1], d[2]])
    M1 = look_at(c1, centre)
    cars = []
    for ci, T in zip(sim.carriages, sim.truth):
        pts = ci.carriage_type.marked_points
        X = np.array([T[:3, :3] @ np.asarray(p, float) + T[:3, 3] for p in pts.values()])
        uv, depth = project_world(v0.intrinsics, M1, X)
        ok = (depth > 1.0) & v0.intrinsics.in_image(np.nan_to_num(uv, nan=-1e9))
        obs1 = {n: tuple(u + rng.normal(0.0, SIGMA_PX, 2)) for n, u, k in zip(pts, uv, ok) if k}
        cars.append(CarriageInput(number=ci.number, carriage_type=ci.carriage_type,
                                  observations={**ci.observations, "second": obs1}))
    S = np.eye(4)
    S[:3, :3] = 0.6 * exp_so3(np.radians([20.0, -10.0, 35.0]))
    S[:3, 3] = [30.0, -12.0, 4.0]  # world_from_model
    cam_from_model = {v0.name: np.asarray(v0.cam_from_world, float) @ S, "second": M1 @ S}
    for C in cam_from_model.values():  # rigid: p_cam = R_c p_model + t_c, in the model's units
        C[:3, :] /= 0.6
    sim_res = SimilarityResult(0.6, S[:3, :3] / 0.6, S[:3, 3].copy(), [], {}, [],
                               covariance=_similarity_covariance(3))
    return sim, cars, sim_res, cam_from_model


def _views(sim, sim_res: SimilarityResult, cam_from_model: dict) -> list[View]:
    intr = sim.views[0].intrinsics
    return [View(name=n, intrinsics=intr, cam_from_world=sim_res.cam_from_world(C)) for n, C in cam_from_model.items()]


def _solve(sim, cars, views):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolveWarning)
        return solve_consist(cars, sim.links, views, SolveOptions(pixel_sigma_px=SIGMA_PX, compute_covariance=True))


def _perturbed(sim_res: SimilarityResult, e: np.ndarray) -> SimilarityResult:
    """The similarity moved by ``e`` (log scale, rotation vector on the left, translation)."""
    return SimilarityResult(sim_res.scale * np.exp(e[0]), exp_so3(e[1:4]) @ sim_res.rotation,
                            sim_res.translation + e[4:7], [], {}, [])


def _pose_delta(res, res0) -> np.ndarray:
    """(cars, 6) the carriages' pose change (scene rotation vector, origin) from ``res0`` to ``res``."""
    out = []
    for a, b in zip(res.carriages, res0.carriages):
        Ma, Mb = np.asarray(a.world_from_carriage), np.asarray(b.world_from_carriage)
        out.append(np.r_[log_so3(Ma[:3, :3] @ Mb[:3, :3].T), Ma[:3, 3] - Mb[:3, 3]])
    return np.array(out)


def _camera_terms(sim, cars, sim_res, cam_from_model, independent: bool = False):
    """Each carriage's added covariance (6, 6) and the solution with it."""
    views = _views(sim, sim_res, cam_from_model)
    res = _solve(sim, cars, views)
    fit = [np.asarray(c.covariance_pose, float).copy() for c in res.carriages]
    jac = {v.name: ("main", sim_res.view_jacobian(cam_from_model[v.name])) for v in views}
    if independent:  # what treating the views as independent would give (wrong: they share the similarity)
        own = {n: J @ sim_res.covariance @ J.T for n, (_, J) in jac.items()}
        info = add_view_camera_uncertainty(res, cars, sim.links, views, SIGMA_PX, {}, {}, own)
    else:
        info = add_view_camera_uncertainty(res, cars, sim.links, views, SIGMA_PX, {"main": sim_res.covariance}, jac,
                                           {})
    return [np.asarray(c.covariance_pose) - f for c, f in zip(res.carriages, fit)], res, info


def test_view_jacobian_matches_the_moved_similarity(two_views):
    """A view's pose error (scene rotation vector, centre) against the exact effect of a small similarity error."""
    sim, cars, sim_res, cfm = two_views
    e = np.r_[3e-5, np.radians([0.002, -0.003, 0.001]), 0.002, -0.001, 0.003]
    for C in cfm.values():
        A, B = sim_res.cam_from_world(C), _perturbed(sim_res, e).cam_from_world(C)
        w = log_so3(B[:3, :3].T @ A[:3, :3])  # world_from_cam: R_wc' R_wc^T
        dc = (-B[:3, :3].T @ B[:3, 3]) - (-A[:3, :3].T @ A[:3, 3])
        got = np.r_[w, dc]
        pred = sim_res.view_jacobian(C) @ e
        assert np.allclose(pred, got, rtol=0, atol=2e-3 * np.abs(got).max()), (pred, got)
        assert np.abs(got[3:]).max() > 1e-3  # the lever arm makes it a real test


def test_camera_term_against_the_solve_response(two_views):
    """The added covariance B C B^T against the carriages' actual response to the similarity's error: the solve
    run again with the cameras moved by each of the 7 parameters (finite differences, the same pixels): the
    sigmas agree to 3 % (1.3 % measured); the carriages seen in both views take shares of both; treating the two
    views as independent would misstate the term by more than 1.5 times on some axis (their errors are one
    similarity's)."""
    sim, cars, sim_res, cfm = two_views
    added, res0, info = _camera_terms(sim, cars, sim_res, cfm)
    assert sorted(info) == sorted(c.number for c in res0.carriages)
    both = [n for n, r in info.items() if len(r["views"]) == 2]
    assert both and all(0.05 < min(info[n]["views"].values()) < 0.95 for n in both), info
    eps = np.array([1e-4] + [np.radians(0.005)] * 3 + [0.005] * 3)
    B = np.zeros((len(cars), 6, 7))
    for j in range(7):
        e = np.zeros(7)
        e[j] = eps[j]
        resj = _solve(sim, cars, _views(sim, _perturbed(sim_res, e), cfm))
        B[:, :, j] = _pose_delta(resj, res0) / eps[j]
    indep, _, _ = _camera_terms(sim, cars, sim_res, cfm, independent=True)
    for k, (Ck, Bk) in enumerate(zip(added, B)):
        truth = Bk @ sim_res.covariance @ Bk.T
        ratio = np.sqrt(np.diag(Ck) / np.diag(truth))
        assert np.all((0.97 < ratio) & (ratio < 1.03)), (k, ratio)
        assert np.sqrt(np.diag(Ck)[3:]).max() > 0.01  # centimetres at the origin: a real term
        if res0.carriages[k].number in both:  # independent views: the rotations 1.8-5 times too wide here
            r_ind = np.sqrt(np.diag(indep[k]) / np.diag(truth))
            assert np.abs(np.log(r_ind)).max() > np.log(1.5), (k, r_ind)


def test_camera_term_against_a_monte_carlo_of_the_similarity(two_views):
    """Similarity errors drawn from its covariance (40 draws, the same pixels): the spread of the carriages'
    body centres about the unperturbed solution against the added term's sigmas: ratio 0.75-1.3 per axis
    (40 draws: the sample sigma's own 95 % range is about +-22 %)."""
    sim, cars, sim_res, cfm = two_views
    added, res0, _ = _camera_terms(sim, cars, sim_res, cfm)
    rng = np.random.default_rng(5)
    L = np.linalg.cholesky(sim_res.covariance)
    d = []
    for _ in range(40):
        resi = _solve(sim, cars, _views(sim, _perturbed(sim_res, L @ rng.normal(size=7)), cfm))
        d.append([np.asarray(a.body_centre_m) - np.asarray(b.body_centre_m)
                  for a, b in zip(resi.carriages, res0.carriages)])
    d = np.array(d)  # (draws, cars, 3)
    for k, c in enumerate(res0.carriages):
        M = np.asarray(c.world_from_carriage)
        Jb = np.hstack([-np.asarray(_skew(np.asarray(c.body_centre_m) - M[:3, 3])), np.eye(3)])
        pred = np.sqrt(np.diag(Jb @ added[k] @ Jb.T))
        emp = np.sqrt(np.mean(d[:, k] ** 2, axis=0))
        assert np.all((0.75 < emp / pred) & (emp / pred < 1.3)), (k, emp, pred)


def _skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def test_one_view_carriage_moves_with_its_camera(two_views):
    """Carriages measured in one view only take that camera's pose error whole (the central route's rule), to 0.1 %
    (the couplers' small offsets at the solution turn with the camera, which the linearised prior sees)."""
    sim, cars, sim_res, cfm = two_views
    name = sim.views[0].name
    one = [CarriageInput(number=c.number, carriage_type=c.carriage_type, observations={name: c.observations[name]})
           for c in cars]
    views = _views(sim, sim_res, cfm)
    res = _solve(sim, one, views[:1])
    fit = [np.asarray(c.covariance_pose, float).copy() for c in res.carriages]
    J = sim_res.view_jacobian(cfm[name])
    add_view_camera_uncertainty(res, one, sim.links, views[:1], SIGMA_PX, {"main": sim_res.covariance},
                                {name: ("main", J)}, {})
    Cv = J @ sim_res.covariance @ J.T
    for c, f in zip(res.carriages, fit):
        A = camera_pose_jacobian(np.asarray(c.world_from_carriage), views[0].camera_centre)
        got, want = np.asarray(c.covariance_pose) - f, A @ Cv @ A.T
        assert np.allclose(np.sqrt(np.diag(got) / np.diag(want)), 1.0, rtol=0, atol=1e-3)  # 4e-4 measured


# ----------------------------------------------------------------------------------------------------------
# The stages, on the session's small generated incident
# ----------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def multiview_incident(small_incident, tmp_path_factory):
    """The small incident (4 cars, 8 multi-view photos of 800x600) with an exact SfM model in its own frame, the
    control points' coordinates given their stated survey error, hand picks at 0.5 px; georef and solve run."""
    from workbench.georef.stage import run_georef
    from workbench.project import Project
    from workbench.solve.stage import run_solve
    from workbench.synth.control_points import similarity, true_reconstruction
    from workbench.synth.handpicks import write_true_correspondences
    from workbench.core.io import atomic_write_json

    src, truth = small_incident
    base = tmp_path_factory.mktemp("mv_unc")
    shutil.copytree(src.parent.parent, base, dirs_exist_ok=True, ignore=shutil.ignore_patterns("out"))
    root = base / "projects" / src.name
    t = (root / "project.toml").read_text()
    (root / "project.toml").write_text(with_solver_lines(t.replace('source = "calibrated"', 'source = "sfm"')
                                                         .replace('photos = "photos/panorama"',
                                                                  'photos = "photos/multiview"'),
                                                         "pixel_sigma_px = 0.5"))
    cp = json.loads((root / "control_points.json").read_text())
    rng = np.random.default_rng(7)
    for p in cp["points"]:
        p["coords"] = [x + rng.normal(0.0, p["sigma_m"]) for x in p["coords"]]
    (root / "control_points.json").write_text(json.dumps(cp))
    atomic_write_json(root / "out" / "sfm" / "reconstruction.json",
                      true_reconstruction(root, similarity(0.37, [120.0, 10.0, -20.0], [40.0, -20.0, 5.0])))
    write_true_correspondences(root, "multiview", sigma_px=0.5, seed=3)
    project = Project(root)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_georef(project, lambda *a: None)
        run_solve(project, lambda *a: None)
    return root, truth


def test_cameras_file_states_each_views_share_of_the_similarity(multiview_incident):
    root, _ = multiview_incident
    from workbench.files.cameras import read_cameras

    cams = read_cameras(root / "out" / "georef" / "cameras.json")
    pu = cams.doc["georegistration"]["pose_uncertainty"]
    assert list(pu["models"]) == ["main"] and set(pu["views"]) == set(cams.names)
    C7 = np.asarray(pu["models"]["main"]["covariance"])
    sd = np.sqrt(np.diag(C7))
    assert 1e-5 < sd[0] < 1e-2 and np.all((1e-4 < np.degrees(sd[1:4])) & (np.degrees(sd[1:4]) < 0.5)), sd
    assert np.all((0.003 < sd[4:]) & (sd[4:] < 0.5)), sd
    for n, v in pu["views"].items():
        J, C6 = np.asarray(v["jacobian"]), np.asarray(v["covariance_rotation_centre"])
        assert v["source"] == "similarity" and v["model"] == "main"
        assert np.allclose(C6, J @ C7 @ J.T, rtol=1e-12, atol=1e-18)
        centre_sd = np.sqrt(np.diag(C6)[3:])
        assert np.all((0.003 < centre_sd) & (centre_sd < 0.5)), (n, centre_sd)
    # two views of the model share its error: their centres' errors are correlated (not independent)
    J = [np.asarray(v["jacobian"]) for v in pu["views"].values()]
    Cab = J[0] @ C7 @ J[1].T
    Caa, Cbb = J[0] @ C7 @ J[0].T, J[1] @ C7 @ J[1].T
    corr = np.diag(Cab)[3:] / np.sqrt(np.diag(Caa)[3:] * np.diag(Cbb)[3:])
    assert np.abs(corr).max() > 0.3, corr


def test_solution_includes_the_cameras_and_keeps_the_poses(multiview_incident, tmp_path):
    """``camera_uncertainty.included`` true with the model's figures; every carriage with an interval widened
    (the fit's sigmas kept apart, ci95 = t sigma); the same cameras without the block give the fit's intervals
    (at the pixel sigma with the cameras' disagreement left in) and the same poses (to 1e-5 m)."""
    from workbench.project import Project
    from workbench.solve.stage import run_solve

    root, truth = multiview_incident
    sol = json.loads((root / "out" / "solve" / "solution.json").read_text())
    cu = sol["camera_uncertainty"]
    assert cu["included"] is True and cu["route"] == "multiview" and not cu["views_not_modelled"]
    with_interval = [c for c in sol["carriages"] if c.get("sigma_body_centre_m") is not None]
    assert len(with_interval) >= 2 and sorted(cu["carriages"]) == sorted(c["number"] for c in with_interval)
    for c in with_interval:
        tot, fit = np.asarray(c["sigma_body_centre_m"]), np.asarray(c["sigma_body_centre_fit_m"])
        extra = np.sqrt(tot ** 2 - fit ** 2)
        assert np.all((0.002 < extra) & (extra < 0.5)), (c["number"], extra)
        assert np.allclose(np.asarray(c["ci95_body_centre_m"]) / tot, sol["ci95_factor"], rtol=1e-9)
        assert abs(sum(cu["view_shares"][c["number"]].values()) - 1.0) < 1e-9
    # the same incident without the block: the fit's intervals, the same poses
    other = tmp_path / "inc"
    shutil.copytree(root.parent.parent, tmp_path, dirs_exist_ok=True)
    other = tmp_path / "projects" / root.name
    cams = json.loads((other / "out" / "georef" / "cameras.json").read_text())
    del cams["georegistration"]["pose_uncertainty"]
    (other / "cameras.json").write_text(json.dumps(cams))  # taken as the incident's own cameras
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_solve(Project(other), lambda *a: None)
    sol0 = json.loads((other / "out" / "solve" / "solution.json").read_text())
    assert sol0["camera_uncertainty"]["included"] is False
    # the fit's pixel sigma leaves out what the photos' stated errors fill (solve.camera_residual): the fit's
    # sigmas follow that sigma, and the poses its second-order bias correction (well under a millimetre)
    k = sol["sigma_px"] / sol0["sigma_px"]
    assert sol0["sigma_px_camera"] is None and sol["sigma_px_camera"] is not None and 0.5 < k <= 1.05, k
    for a, b in zip(sol0["carriages"], sol["carriages"]):
        if b.get("sigma_body_centre_m") is None:
            continue
        assert np.allclose(a["world_from_carriage"], b["world_from_carriage"], rtol=0, atol=1e-5)
        assert np.allclose(k * np.asarray(a["sigma_body_centre_m"]), b["sigma_body_centre_fit_m"], rtol=0.05)
        assert np.allclose(k * np.asarray(a["sigma_hpr_deg"]), b["sigma_hpr_fit_deg"], rtol=0.05)


def test_bad_pose_uncertainty_is_named(multiview_incident):
    from workbench.errors import InputError
    from workbench.files.cameras import parse_cameras

    root, _ = multiview_incident
    doc = json.loads((root / "out" / "georef" / "cameras.json").read_text())
    bad = copy.deepcopy(doc)
    bad["georegistration"]["pose_uncertainty"]["models"]["main"]["covariance"] = [[1.0, 2.0]]
    with pytest.raises(InputError, match=r"pose_uncertainty\.models\.main\.covariance"):
        parse_cameras(bad, "cameras.json")
    bad = copy.deepcopy(doc)
    next(iter(bad["georegistration"]["pose_uncertainty"]["views"].values()))["model"] = "other"
    with pytest.raises(InputError, match="is not one of the models"):
        parse_cameras(bad, "cameras.json")


def test_central_route_unchanged(small_incident, tmp_path):
    """A panorama (central) incident with a georegistration covariance and no terrain model: the camera term is
    the central route's rigid one, ``C_fit + A C_cam A^T`` about the common centre, to 1e-9 (with a terrain
    contact, which holds the carriages in the world, the response is ``B``: tests/test_camera_term.py)."""
    from workbench.project import Project
    from workbench.solve.stage import run_solve
    from workbench.solve.camera_term import camera_pose_jacobian as A_of
    from workbench.synth.handpicks import write_known_cameras, write_true_correspondences

    src, _ = small_incident
    shutil.copytree(src.parent.parent, tmp_path, dirs_exist_ok=True, ignore=shutil.ignore_patterns("out"))
    root = tmp_path / "projects" / src.name
    toml = root / "project.toml"
    toml.write_text("".join(ln for ln in toml.read_text().splitlines(True) if not ln.startswith("dem =")))
    write_known_cameras(root, "panorama")
    write_true_correspondences(root, "panorama", sigma_px=1.0, seed=5)
    cams = json.loads((root / "cameras.json").read_text())
    Ccam = np.diag([np.radians(0.02) ** 2] * 3 + [0.05 ** 2] * 3)
    cams["georegistration"] = {"method": "control_points", "covariance_world_rotation_centre": Ccam.tolist()}
    (root / "cameras.json").write_text(json.dumps(cams))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_solve(Project(root), lambda *a: None)
    sol = json.loads((root / "out" / "solve" / "solution.json").read_text())
    cu = sol["camera_uncertainty"]
    assert cu["included"] is True and "route" not in cu and cu["sigma_centre_m"] == pytest.approx([0.05] * 3)
    q = sol["ci95_factor"]
    for c in sol["carriages"]:
        if c.get("covariance_pose") is None:
            continue
        M = np.asarray(c["world_from_carriage"])
        A = A_of(M, cu["centre_enu"])
        C = np.asarray(c["covariance_pose"])
        lever = np.asarray(c["body_centre_enu"]) - M[:3, 3]
        Jb = np.hstack([-_skew(lever), np.eye(3)])
        fit = np.asarray(c["sigma_body_centre_fit_m"])
        cam = np.diag(Jb @ A @ Ccam @ A.T @ Jb.T)
        assert np.allclose(np.asarray(c["sigma_body_centre_m"]), np.sqrt(fit ** 2 + cam), rtol=1e-9)
        assert np.allclose(np.asarray(c["ci95_body_centre_m"]), q * np.asarray(c["sigma_body_centre_m"]), rtol=1e-12)
        assert np.allclose(C, C.T, atol=1e-15)


def test_an_undetermined_similarity_is_said_not_included(multiview_incident, tmp_path):
    """A model whose similarity covariance is null (the fit left it undetermined): its photos are not modelled, the
    solution says the camera term is not included and why, and the intervals are the fit's."""
    from workbench.project import Project
    from workbench.solve.stage import run_solve

    root, _ = multiview_incident
    shutil.copytree(root.parent.parent, tmp_path, dirs_exist_ok=True)
    other = tmp_path / "projects" / root.name
    cams = json.loads((other / "out" / "georef" / "cameras.json").read_text())
    cams["georegistration"]["pose_uncertainty"]["models"]["main"]["covariance"] = None
    (other / "cameras.json").write_text(json.dumps(cams))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_solve(Project(other), lambda *a: None)
    cu = json.loads((other / "out" / "solve" / "solution.json").read_text())["camera_uncertainty"]
    assert cu["included"] is False and "pose_uncertainty states no pose covariance" in cu["note"]


def _moved_view(v: View, dw: np.ndarray, dc: np.ndarray) -> View:
    """``v`` with its scene pose moved: ``world_from_cam`` turned by ``Exp(dw)`` on the left, its centre by ``dc``."""
    M = np.asarray(v.cam_from_world, float)
    c = -M[:3, :3].T @ M[:3, 3]
    R = (exp_so3(dw) @ M[:3, :3].T).T
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, -R @ (c + dc)
    return View(name=v.name, intrinsics=v.intrinsics, cam_from_world=out)


def test_sfm_pose_factor_against_the_solve_response(two_views):
    """The SfM poses' own error as a factor shared by the model's views (``[J_v, F_v]`` on ``[e_sim, z]``,
    ``z ~ N(0, I_r)``: what files.cameras.parse_pose_uncertainty builds from ``sfm_factor``) against the solve run
    again with both views moved by each of the factor's columns and the similarity by each of its parameters
    (finite differences, the same pixels): the added sigmas agree to 3 %, and the factor widens them."""
    sim, cars, sim_res, cfm = two_views
    rng = np.random.default_rng(8)
    r = 4
    sd = np.r_[[np.radians(0.05)] * 3, [0.03] * 3]
    F = {n: rng.normal(size=(6, r)) * sd[:, None] / np.sqrt(r) for n in cfm}
    Cext = np.block([[sim_res.covariance, np.zeros((7, r))], [np.zeros((r, 7)), np.eye(r)]])
    views = _views(sim, sim_res, cfm)
    res0 = _solve(sim, cars, views)
    fit = [np.asarray(c.covariance_pose, float).copy() for c in res0.carriages]
    jac = {v.name: ("main", np.hstack([sim_res.view_jacobian(cfm[v.name]), F[v.name]])) for v in views}
    add_view_camera_uncertainty(res0, cars, sim.links, views, SIGMA_PX, {"main": Cext}, jac, {})
    added = [np.asarray(c.covariance_pose) - f for c, f in zip(res0.carriages, fit)]
    sim_only, _, _ = _camera_terms(sim, cars, sim_res, cfm)
    eps = np.array([1e-4] + [np.radians(0.005)] * 3 + [0.005] * 3 + [0.1] * r)
    B = np.zeros((len(cars), 6, 7 + r))
    for j in range(7 + r):
        if j < 7:
            e = np.zeros(7)
            e[j] = eps[j]
            vj = _views(sim, _perturbed(sim_res, e), cfm)
        else:
            vj = [_moved_view(v, eps[j] * F[v.name][:3, j - 7], eps[j] * F[v.name][3:, j - 7]) for v in views]
        B[:, :, j] = _pose_delta(_solve(sim, cars, vj), res0) / eps[j]
    for k, (Ck, Bk) in enumerate(zip(added, B)):
        ratio = np.sqrt(np.diag(Ck) / np.diag(Bk @ Cext @ Bk.T))
        assert np.all((0.97 < ratio) & (ratio < 1.03)), (k, ratio)
        assert np.all(np.diag(Ck) > 1.05 * np.diag(sim_only[k])), (k, np.diag(Ck) / np.diag(sim_only[k]))


def test_georef_carries_the_sfm_pose_covariance(multiview_incident, tmp_path):
    """A reconstruction whose images state a pose_factor (6 x r in the model frame): the georef writes each view's
    ``sfm_factor`` (the factor turned into the scene by the similarity: R on the rotation, s R on the centre) and
    the model's ``sfm_rank``, the view's covariance with it added; parse_pose_uncertainty extends the model to
    7 + r; the solve's intervals widen and the poses stay (to their bias correction's change, under 1e-5 m: the
    fit's pixel sigma leaves out the residual directions the photos' stated errors fill)."""
    from workbench.files.cameras import parse_pose_uncertainty
    from workbench.georef.stage import run_georef
    from workbench.project import Project
    from workbench.solve.stage import run_solve

    root, _ = multiview_incident
    shutil.copytree(root.parent.parent, tmp_path, dirs_exist_ok=True)
    other = tmp_path / "projects" / root.name
    rec = json.loads((other / "out" / "sfm" / "reconstruction.json").read_text())
    rng = np.random.default_rng(21)
    r = 5
    sd = np.r_[[np.radians(0.05)] * 3, [0.03 / 0.37] * 3]  # model units: the fixture's similarity has scale 0.37
    Fm = {im["name"]: rng.normal(size=(6, r)) * sd[:, None] / np.sqrt(r) for im in rec["images"]}
    for im in rec["images"]:
        im["pose_factor"] = Fm[im["name"]].tolist()
    (other / "out" / "sfm" / "reconstruction.json").write_text(json.dumps(rec))
    sol0 = json.loads((other / "out" / "solve" / "solution.json").read_text())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run_georef(Project(other), lambda *a: None)
        run_solve(Project(other), lambda *a: None)
    cams = json.loads((other / "out" / "georef" / "cameras.json").read_text())
    pu = cams["georegistration"]["pose_uncertainty"]
    A = np.asarray(pu["models"]["main"].get("world_from_model") or cams["georegistration"]["world_from_model"])[:3, :3]
    s = float(np.cbrt(np.linalg.det(A)))
    assert pu["models"]["main"]["sfm_rank"] == r and abs(s - 0.37) < 0.01
    T = np.zeros((6, 6))
    T[:3, :3], T[3:, 3:] = A / s, A
    C7 = np.asarray(pu["models"]["main"]["covariance"])
    S = np.asarray(pu["models"]["main"]["sfm_response"])  # the similarity follows the erring poses' control points
    assert S.shape == (7, r) and np.abs(S).max() > 0
    for n, v in pu["views"].items():
        F, J = np.asarray(v["sfm_factor"]), np.asarray(v["jacobian"])
        assert np.allclose(F, T @ Fm[n] + J @ S, rtol=1e-9, atol=1e-15)
        assert np.allclose(np.asarray(v["covariance_rotation_centre"]), J @ C7 @ J.T + F @ F.T, rtol=1e-9, atol=1e-18)
    parsed = parse_pose_uncertainty(cams, "cameras.json")
    assert parsed.model_covariance["main"].shape == (7 + r, 7 + r)
    assert all(J.shape == (6, 7 + r) for _, J in parsed.jacobian.values())
    sol = json.loads((other / "out" / "solve" / "solution.json").read_text())
    n_wider = 0
    for a, b in zip(sol0["carriages"], sol["carriages"]):
        if b.get("sigma_body_centre_m") is None:
            continue
        assert np.allclose(a["world_from_carriage"], b["world_from_carriage"], rtol=0, atol=1e-5)
        # the SfM poses' stated error fills more residual directions: the fit's pixel sigma leaves them out
        k = sol["sigma_px"] / sol0["sigma_px"]
        assert np.allclose(k * np.asarray(a["sigma_body_centre_fit_m"]), b["sigma_body_centre_fit_m"], rtol=0.05)
        assert np.all(np.asarray(b["sigma_body_centre_m"]) >= k * np.asarray(a["sigma_body_centre_m"]) - 1e-12)
        n_wider += bool(np.any(np.asarray(b["sigma_body_centre_m"]) > 1.01 * np.asarray(a["sigma_body_centre_m"])))
    assert n_wider >= 2, n_wider


def test_sfm_intrinsics_factor_against_the_solve_response(two_views):
    """The SfM model's error moving the views' poses and their shared camera's intrinsics together (``sfm_factor``
    and ``sfm_intrinsics_factor`` on one ``z ~ N(0, I_r)``; parse_pose_uncertainty's ``intrinsics_jacobian``)
    against the solve run again with the poses and the focal and k1 moved by each of the factor's columns (finite
    differences, the same pixels): the added sigmas agree to 3 %, and leaving the intrinsics' rows out misstates
    some carriage's sigma by more than 10 %."""
    sim, cars, sim_res, cfm = two_views
    rng = np.random.default_rng(9)
    r, params = 3, ("f", "k1")
    sd = np.r_[[np.radians(0.05)] * 3, [0.03] * 3]
    F = {n: rng.normal(size=(6, r)) * sd[:, None] / np.sqrt(r) for n in cfm}
    K = rng.normal(size=(2, r)) * np.array([[0.004 * sim.views[0].intrinsics.fx], [0.01]]) / np.sqrt(r)
    Cext = np.block([[np.zeros((7, 7)), np.zeros((7, r))], [np.zeros((r, 7)), np.eye(r)]])
    views = _views(sim, sim_res, cfm)
    res0 = _solve(sim, cars, views)
    fit = [np.asarray(c.covariance_pose, float).copy() for c in res0.carriages]
    jac = {v.name: ("main", np.hstack([sim_res.view_jacobian(cfm[v.name]), F[v.name]])) for v in views}
    jac_k = {v.name: ("main", params, np.hstack([np.zeros((2, 7)), K])) for v in views}
    terms = []
    for with_k in (True, False):
        res = copy.deepcopy(res0)
        add_view_camera_uncertainty(res, cars, sim.links, views, SIGMA_PX, {"main": Cext}, jac, {},
                                    intrinsics_jacobian=jac_k if with_k else None)
        terms.append([np.asarray(c.covariance_pose) - f for c, f in zip(res.carriages, fit)])
    B = np.zeros((len(cars), 6, 7 + r))
    for j in range(r):
        h = 0.1
        vj = [View(name=v.name, intrinsics=v.intrinsics.moved(params, h * K[:, j]),
                   cam_from_world=_moved_view(v, h * F[v.name][:3, j], h * F[v.name][3:, j]).cam_from_world)
              for v in views]
        B[:, :, 7 + j] = _pose_delta(_solve(sim, cars, vj), res0) / h
    off = 0.0
    for k, (Ck, C_no_k, Bk) in enumerate(zip(terms[0], terms[1], B)):
        ratio = np.sqrt(np.diag(Ck) / np.diag(Bk @ Cext @ Bk.T))
        assert np.all((0.97 < ratio) & (ratio < 1.03)), (k, ratio)
        off = max(off, float(np.max(np.abs(np.sqrt(np.diag(C_no_k) / np.diag(Ck)) - 1.0))))
    print(f"largest change without the intrinsics rows: {off:.3f}")
    assert off > 0.10, off
