"""The solve stage on a small synthetic incident: known cameras + hand picks (true pixels + 1 px) -> poses."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import hand_picked_incident, with_solver_lines

from workbench.errors import InputError, WorkbenchError
from workbench.pipeline import STAGES
from workbench.project import Project
from workbench.runner import Runner


@pytest.fixture(scope="module")
def incident(tmp_path_factory) -> Path:
    """A copy of conftest's hand-picked incident (3 cars, 3 panorama photos of 480x360, known cameras, true picks
    with 1 px of noise), solved."""
    root = tmp_path_factory.mktemp("solve_stage") / "inc"
    shutil.copytree(hand_picked_incident(tmp_path_factory), root)
    Runner(Project(root), STAGES).run(until="solve")  # what these tests read (the stages after: test_report's)
    return root


def _truth(root: Path) -> dict:
    return json.loads((root / "truth" / "ground_truth.json").read_text())


def test_solution_against_truth(incident):
    sol = json.loads((incident / "out" / "solve" / "solution.json").read_text())
    truth = {c["number"]: c for c in _truth(incident)["carriages"]}
    assert sol["status"] == "converged"
    assert 0.4 < sol["sigma_px_estimated"] < 1.8  # 1 px noise was added
    solved = [c for c in sol["carriages"] if c["status"] == "solved"]
    assert len(solved) >= 2
    for c in sol["carriages"]:
        if c["status"] == "left_out":
            continue
        t = truth[c["number"]]
        err = np.asarray(c["body_centre_enu"]) - np.asarray(t["body_centre_enu"])
        ci = np.asarray(c["ci95_body_centre_m"])
        assert np.all(ci > 0.005) and np.all(ci < 5.0)  # not absurd intervals
        # within the stated uncertainty (1.75 x the 95 % half width: about 3.5 sigma per axis)
        assert np.all(np.abs(err) <= 1.75 * ci + 0.02), (c["number"], err, ci)
        assert np.linalg.norm(err) < 3.0
        dh = (c["heading_deg"] - t["heading_deg"] + 180) % 360 - 180
        assert abs(dh) <= 1.75 * c["ci95_hpr_deg"][0] + 0.1
        assert c["rms_px"] is not None and 0.1 < c["rms_px"] < 4.0


def test_solution_frames_round_trip(incident):
    from workbench.core.frames import rotation_from_hpr

    p = Project(incident)
    sol = json.loads((incident / "out" / "solve" / "solution.json").read_text())
    for c in sol["carriages"]:
        if "body_centre_enu" not in c:
            continue
        enu = np.asarray(c["body_centre_enu"])[None]
        assert np.allclose(p.frame.enu_from_crs(np.asarray(c["body_centre_crs"])[None]), enu, atol=1e-6)
        assert np.allclose(p.frame.enu_from_wgs84(np.asarray(c["body_centre_wgs84"])[None]), enu, atol=1e-6)
        R = np.asarray(c["world_from_carriage"])[:3, :3]
        assert np.allclose(rotation_from_hpr(c["heading_deg"], c["pitch_deg"], c["roll_deg"]), R, atol=1e-9)


def test_coupler_gaps_respect_the_slack(incident):
    p = Project(incident)
    sol = json.loads((incident / "out" / "solve" / "solution.json").read_text())
    for car, rec in zip(p.settings.consist, sol["carriages"]):
        if car.coupling_to_next is not None and car.coupling_to_next.value == "held" and \
                rec["coupler_gap_to_next_m"] is not None:
            assert 0.0 <= rec["coupler_gap_to_next_m"] <= p.settings.solver.slack_held_m + 1e-6


def test_second_run_is_skipped(incident):
    before = (incident / "out" / "solve" / "solution.json").read_bytes()
    statuses = Runner(Project(incident), STAGES).run(until="solve")
    assert {s.name: s.status for s in statuses}["solve"] == "done"
    assert (incident / "out" / "solve" / "solution.json").read_bytes() == before


def _copy_with_corr(incident: Path, tmp_path: Path, edit, with_out: bool = False) -> Path:
    """A copy of the incident with its correspondences.json edited; ``with_out``: with the fixture's outputs, so
    that a run redoes only the stages the edit makes stale (the correspond stage and those after it), as a user's
    run would (the stages' fingerprints are of the files' contents: a copied incident's done stages stay done)."""
    root = tmp_path / "inc"
    shutil.copytree(incident, root, ignore=None if with_out else shutil.ignore_patterns("out"))
    doc = json.loads((root / "correspondences.json").read_text())
    edit(doc["observations"])
    (root / "correspondences.json").write_text(json.dumps(doc))
    return root


BAD = [
    (lambda o: o[0].update(carriage="9999"), ["9999", "consist"]),
    (lambda o: o[0].update(point="chimney"), ["chimney"]),
    (lambda o: o[0].update(uv=[5000.0, 10.0]), ["outside", "480"]),
    (lambda o: o[0].update(uv=[float("nan"), 3.0]), ["finite"]),
    (lambda o: o.append(dict(o[0])), ["observations[0]"]),
    (lambda o: o[0].update(view="nope.jpg"), ["nope.jpg"]),
    (lambda o: o[0].update(source="sift", method="homography", face="left", ecc=1.5), ["ecc", "1.5"]),
]


@pytest.mark.parametrize("edit, words", BAD)
def test_bad_correspondences_are_named(incident, tmp_path, edit, words):
    """Through the pipeline (the correspond stage checks the hand-written file first)."""
    root = _copy_with_corr(incident, tmp_path, edit, with_out=True)
    with pytest.raises(InputError) as exc:
        Runner(Project(root), STAGES).run()
    msg = str(exc.value)
    assert "correspondences.json" in msg and "observations[" in msg
    for w in words:
        assert w in msg


@pytest.mark.parametrize("edit, words", BAD)
def test_the_solve_stage_checks_correspondences_itself(incident, tmp_path, edit, words):
    """The solve stage's own reader (it also reads files that did not pass through the correspond stage)."""
    from workbench.solve.stage import read_correspondences, read_views

    root = _copy_with_corr(incident, tmp_path, edit)
    p = Project(root)
    views, _ = read_views(p, root / "cameras.json")
    with pytest.raises(InputError) as exc:
        read_correspondences(p, root / "correspondences.json", views)
    msg = str(exc.value)
    assert "correspondences.json" in msg and "observations[" in msg
    for w in words:
        assert w in msg


def test_missing_cameras_says_what_to_do(incident, tmp_path):
    root = _copy_with_corr(incident, tmp_path, lambda o: None)
    (root / "cameras.json").unlink()
    (root / "control_points.json").unlink(missing_ok=True)  # nothing to place the cameras with
    with pytest.raises(WorkbenchError) as exc:
        Runner(Project(root), STAGES).run(only=["inputs", "terrain", "correspond", "solve"])
    assert "cameras" in str(exc.value) and "georef" in str(exc.value)


def test_not_converged_keeps_the_previous_solution(incident, tmp_path, monkeypatch):
    root = _copy_with_corr(incident, tmp_path, lambda o: None, with_out=True)
    Runner(Project(root), STAGES).run(until="solve")
    good = (root / "out" / "solve" / "solution.json").read_bytes()
    text = with_solver_lines((root / "project.toml").read_text(), "max_iterations = 1")
    (root / "project.toml").write_text(text)
    with pytest.raises(WorkbenchError) as exc:
        Runner(Project(root), STAGES).run(until="solve")
    assert "did not converge" in str(exc.value)
    assert (root / "out" / "solve" / "solution.json").read_bytes() == good
    assert (root / "out" / "solve" / "attempt.json").is_file()


def test_a_wrong_point_is_rejected(incident, tmp_path):
    def edit(o):
        o[0]["uv"] = [min(o[0]["uv"][0] + 30.0, 470.0), o[0]["uv"][1]]

    root = _copy_with_corr(incident, tmp_path, edit, with_out=True)
    first = json.loads((root / "correspondences.json").read_text())["observations"][0]
    Runner(Project(root), STAGES).run(until="solve")
    sol = json.loads((root / "out" / "solve" / "solution.json").read_text())
    rej = [(r["carriage"], r["view"], r["point"]) for r in sol["rejected_points"]]
    assert (first["carriage"], first["view"], first["point"]) in rej
    assert len(rej) <= 2  # the honest points stay
    car = next(c for c in sol["carriages"] if c["number"] == first["carriage"])
    assert first["point"] not in car["residuals_px"].get(first["view"], {})


def test_predictions_are_recorded_apart(incident, tmp_path):
    """Points marked as predictions (method "pose" / "carried") are solved as guides: solution.json lists them per
    carriage and view, and gives their RMS residual apart from the measured points'."""
    root = tmp_path / "inc"
    shutil.copytree(incident, root)
    doc = json.loads((root / "correspondences.json").read_text())
    car = doc["observations"][0]["carriage"]
    mine = [o for o in doc["observations"] if o["carriage"] == car]
    for o in mine[:2]:
        o.update(source="sift", method="pose", face="left")
    (root / "correspondences.json").write_text(json.dumps(doc))
    Runner(Project(root), STAGES).run(until="solve")
    sol = json.loads((root / "out" / "solve" / "solution.json").read_text())
    rec = next(c for c in sol["carriages"] if c["number"] == car)
    listed = sorted(p for ps in rec["predicted"].values() for p in ps)
    assert listed == sorted(o["point"] for o in mine[:2])
    rms = sol["residual_rms_px"]
    assert rms["n_predicted"] == 2 and rms["n_measured"] == len(doc["observations"]) - 2
    assert 0.3 < rms["measured"] < 3.0  # the fixture's picks carry 1 px of noise
    assert all(not c.get("predicted") for c in sol["carriages"] if c["number"] != car)


def test_unknown_point_method_is_named(incident, tmp_path):
    from workbench.solve.stage import read_correspondences, read_views

    root = _copy_with_corr(incident, tmp_path, lambda o: o[0].update(method="guess"))
    p = Project(root)
    views, _ = read_views(p, root / "cameras.json")
    with pytest.raises(InputError, match=r"observations\[0\]\.method: .*'guess'"):
        read_correspondences(p, root / "correspondences.json", views)


def test_solution_records_the_bias_correction(incident, tmp_path):
    """``solver.bias_correction`` (on by default, known cameras here): solution.json records ``cost_at_minimum``,
    ``bias_correction`` and the step ``5_bias_correction``; with the setting off the same solve reports the
    minimum itself (no step 5), and the two differ per carriage by what the step says it moved."""
    assert Project(incident).settings.solver.bias_correction is True
    sol = json.loads((incident / "out" / "solve" / "solution.json").read_text())
    bc = sol["bias_correction"]
    steps = {s["name"]: s for s in sol["steps"]}
    assert [s["name"] for s in sol["steps"]][-1] == "5_bias_correction"
    assert bc["applied"] is True and steps["5_bias_correction"]["ran"] is True
    assert bc["skipped"] == [] and 0.0 <= bc["max_bias_over_sd"] < 1.0
    assert sol["final_cost"] >= sol["cost_at_minimum"] > 0
    moved = {p["number"]: p["moved_m"] for p in steps["5_bias_correction"]["per_carriage"]}
    assert max(moved.values()) == pytest.approx(bc["max_shift_m"], abs=1e-12)

    root = tmp_path / "inc"
    shutil.copytree(incident, root)  # with its outputs: the setting makes the solve alone stale
    text = (root / "project.toml").read_text()
    assert "bias_correction" not in text
    (root / "project.toml").write_text(with_solver_lines(text, "bias_correction = false"))
    Runner(Project(root), STAGES).run(until="solve")
    off = json.loads((root / "out" / "solve" / "solution.json").read_text())
    assert off["bias_correction"] == {} and "5_bias_correction" not in [s["name"] for s in off["steps"]]
    assert off["final_cost"] == pytest.approx(off["cost_at_minimum"], rel=1e-12)
    assert off["cost_at_minimum"] == pytest.approx(sol["cost_at_minimum"], rel=1e-6)  # the same minimum
    for a, b in zip(sol["carriages"], off["carriages"]):
        if "body_centre_enu" in a:
            d = float(np.linalg.norm(np.subtract(a["body_centre_enu"], b["body_centre_enu"])))
            assert d == pytest.approx(moved[a["number"]], abs=1e-6)


def test_camera_pose_jacobian_matches_the_composition():
    """The first-order map from a camera-pose error (scene rotation about its centre, centre shift) to a carriage's
    pose parameters, against the exact composition with a small error."""
    from scipy.spatial.transform import Rotation

    from workbench.solve.camera_term import camera_pose_jacobian

    rng = np.random.default_rng(3)
    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    M[:3, 3] = [80.0, -40.0, 3.0]
    c = np.array([5.0, 2.0, 15.0])
    d = np.r_[rng.normal(size=3) * 1e-6, rng.normal(size=3) * 1e-4]
    dR = Rotation.from_rotvec(d[:3]).as_matrix()
    R2 = dR @ M[:3, :3]
    t2 = c + d[3:] + dR @ (M[:3, 3] - c)
    w = Rotation.from_matrix(R2 @ M[:3, :3].T).as_rotvec()
    got = np.r_[w, t2 - M[:3, 3]]
    assert np.allclose(camera_pose_jacobian(M, c) @ d, got, rtol=1e-4, atol=1e-10)


def test_georegistration_uncertainty_widens_the_intervals(incident, tmp_path):
    """A cameras file with the georegistration's camera-pose covariance (as georef writes it): every carriage's
    intervals include it (a centre error of 0.2 m per axis adds 0.2 m in quadrature to the body centre's sigma in
    east and north, the up sigma at least as much as that), the fit's own sigmas are kept apart, and the poses are
    unchanged. Cameras without it are taken as exact, and the solution says so. Without a terrain model: there the
    carriages move rigidly with the camera (with one, the contact holds them: tests/test_camera_term.py)."""
    root = tmp_path / "inc"
    shutil.copytree(incident, root, ignore=shutil.ignore_patterns("out"))
    toml = root / "project.toml"
    toml.write_text("".join(ln for ln in toml.read_text().splitlines(True) if not ln.startswith("dem =")))
    Runner(Project(root), STAGES).run(until="solve")
    sol0 = json.loads((root / "out" / "solve" / "solution.json").read_text())
    assert sol0["camera_uncertainty"]["included"] is False
    cams = json.loads((root / "cameras.json").read_text())
    s_rot, s_c = np.radians(0.01), 0.2
    cams["georegistration"] = {"method": "control_points",
                               "covariance_world_rotation_centre": np.diag([s_rot**2] * 3 + [s_c**2] * 3).tolist()}
    (root / "cameras.json").write_text(json.dumps(cams))
    Runner(Project(root), STAGES).run(until="solve")
    sol = json.loads((root / "out" / "solve" / "solution.json").read_text())
    cu = sol["camera_uncertainty"]
    assert cu["included"] is True and cu["sigma_centre_m"] == pytest.approx([s_c] * 3)
    solved = [c for c in sol["carriages"] if c.get("sigma_body_centre_m") is not None]
    assert solved and sorted(cu["carriages"]) == sorted(c["number"] for c in solved)
    for a, b in zip(sol0["carriages"], sol["carriages"]):
        if b.get("sigma_body_centre_m") is None:
            continue
        assert np.allclose(a["body_centre_enu"], b["body_centre_enu"], atol=1e-9)
        fit = np.asarray(b["sigma_body_centre_fit_m"])
        assert np.allclose(fit, a["sigma_body_centre_m"], rtol=1e-9)
        tot = np.asarray(b["sigma_body_centre_m"])
        lever = np.linalg.norm(np.asarray(b["body_centre_enu"]) - cu["centre_enu"])
        extra = np.sqrt(tot**2 - fit**2)
        assert np.all(extra >= s_c - 1e-9) and np.all(extra <= np.hypot(s_c, 2 * lever * s_rot) + 1e-9)
        assert np.allclose(np.asarray(b["ci95_body_centre_m"]) / tot, sol["ci95_factor"], rtol=1e-9)
        assert np.all(np.asarray(b["sigma_hpr_deg"]) >= np.asarray(b["sigma_hpr_fit_deg"]) - 1e-12)


def test_a_hand_written_incident_solves_without_photo_files(incident, tmp_path):
    """cameras.json + correspondences.json written by hand, no photo files (issue 16): `workbench solve` through
    the CLI places the carriages within their intervals of the truth; the automatic finder does not apply."""
    import subprocess
    import sys

    work = tmp_path / "inc"
    shutil.copytree(incident, work, ignore=shutil.ignore_patterns("out", "photos", "masks"))
    assert not (work / "photos").exists()
    r = subprocess.run([sys.executable, "-m", "workbench.cli", "solve", str(work)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    status = {s.name: s.status for s in Runner(Project(work), STAGES).status()}
    assert status["correspond"] == "skipped" and status["solve"] == "done" and status["stitch"] == "skipped"
    sol = json.loads((work / "out" / "solve" / "solution.json").read_text())
    truth = {c["number"]: c for c in _truth(work)["carriages"]}
    assert sum(c["status"] == "solved" for c in sol["carriages"]) >= 2
    for c in sol["carriages"]:
        if c["status"] != "left_out":
            err = np.asarray(c["body_centre_enu"]) - np.asarray(truth[c["number"]]["body_centre_enu"])
            ci = np.asarray(c["ci95_body_centre_m"])
            assert np.all(ci > 0.005) and np.all(np.abs(err) <= 1.75 * ci + 0.02), (c["number"], err, ci)
    stats = json.loads((work / "out" / "solve" / "stats.json").read_text())
    assert stats["correspondences_file"] == "correspondences.json"  # the hand-written file, read directly
    # a photo-less incident without hand-written cameras is still told where its photos should be
    (work / "cameras.json").unlink()
    r = subprocess.run([sys.executable, "-m", "workbench.cli", "status", str(work)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0
    r = subprocess.run([sys.executable, "-m", "workbench.cli", "run", str(work)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 2 and "camera.photos" in r.stderr and "is not a folder" in r.stderr, r.stderr
