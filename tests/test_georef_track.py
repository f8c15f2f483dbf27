"""Track picks as a georeferencing feature (issue 17): the format, the residual against the synthetic truth, the
camera placed from track picks with a position prior, what track picks cannot fix (the place along the track), and
the panorama route reading them from control_points.json."""

from __future__ import annotations

import json
import math
import shutil
import warnings

import numpy as np
import pytest

from workbench.core.io import atomic_write_json
from workbench.core.track import RailwayLine
from workbench.errors import InputError
from workbench.files.control_points import parse_control_points, parse_track_picks
from workbench.core.frames import SceneFrame
from workbench.georef.central import solve_central
from workbench.georef.options import GeorefOptions
from workbench.georef.stage import run_georef
from workbench.project import Project
from workbench.synth.control_points import track_picks_document, true_panorama_model
from workbench.synth.track_georef import chainage_errors, noisy_track_term, panorama_truth, rotation_error

FRAME = SceneFrame("EPSG:32618", 40.878, -73.9215, 4.0)


# ----------------------------------------------------------------------------------------------------------
# The format
# ----------------------------------------------------------------------------------------------------------
def test_track_picks_format_and_bad_input():
    doc = {"crs": "EPSG:32618", "track_picks": [
        {"photo": "a.jpg", "pixels": [[1.0, 2.0], [3.0, 4.0]]},
        {"photo": "a.jpg", "line": "L1", "rail": "left", "gauge_m": 1.0, "pixels": [[5.0, 6.0]]}]}
    picks = parse_track_picks(doc)
    assert [p.rail for p in picks] == ["centre", "left"] and picks[0].line == "" and picks[1].line == "L1"
    assert picks[0].offset_m == 0.0 and picks[0].gauge_m == 1.435
    assert picks[1].offset_m == pytest.approx((1.0 + 0.07) / 2)
    assert parse_control_points(doc, FRAME) == []  # track picks alone: no landmark needed in the file
    bad = [({"crs": "EPSG:32618"}, "neither 'points' nor 'track_picks'"),
           ({"crs": "EPSG:32618", "track_picks": [{"photo": "a.jpg", "rail": "middle", "pixels": [[1, 2]]}]}, "rail"),
           ({"crs": "EPSG:32618", "track_picks": [{"photo": "a.jpg", "pixels": []}]}, "pixels"),
           ({"crs": "EPSG:32618", "track_picks": [{"photo": "a.jpg", "pixels": [[1, 2, 3]]}]}, "pixels"),
           ({"crs": "EPSG:32618", "track_picks": [{"photo": "a.jpg", "gauge_m": 14.35, "pixels": [[1, 2]]}]},
            "gauge_m"),
           ({"crs": "EPSG:32618", "track_picks": [{"photo": "a.jpg", "pixel": [[1, 2]]}]}, "pixel")]
    for d, key in bad:
        with pytest.raises(InputError) as ei:
            parse_track_picks(d, "cp.json")
        assert "cp.json" in str(ei.value) and key in str(ei.value)


def test_rail_polyline_is_offset_by_the_rail_distance():
    th = np.radians(np.arange(0.0, 60.0, 2.0))  # a left-hand 300 m curve drawn with 10.5 m chords
    line = RailwayLine("c", None, np.column_stack([300 * np.cos(th), 300 * np.sin(th), np.full(th.size, 5.0)]))
    for off in (0.7525, -0.7525):
        P = line.rail_polyline(off, 0.5)
        r = np.hypot(P[:, 0], P[:, 1])
        # left of the direction of travel (anticlockwise) is towards the centre; chords sag by up to 0.05 m
        assert np.all(np.abs(r[::21] - (300.0 - off)) < 1e-6)
        assert np.all((r - (300.0 - off) < 1e-6) & (r - (300.0 - off) > -0.05))
        assert np.max(np.linalg.norm(np.diff(P[:, :2], axis=0), axis=1)) <= 0.5 + 1e-9
        assert np.all(P[:, 2] == 5.0)


# ----------------------------------------------------------------------------------------------------------
# Against the synthetic truth (the session's small incident: 4 panorama photos of 800x600)
# ----------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def track_truth(small_incident):
    root, _ = small_incident
    pt = panorama_truth(root)
    entries = track_picks_document(root, sigma_px=0.0)
    return root, pt, entries


def test_true_track_picks_lie_on_their_rails(track_truth):
    _, pt, entries = track_truth
    assert len(entries) >= 4 and sum(len(e["pixels"]) for e in entries) >= 40
    term = noisy_track_term(pt, entries, np.random.default_rng(0), 1e-9)
    r, depth = term.errors(pt.rig_from_world, pt.centre_enu, pt.views)
    assert np.all(np.isfinite(r)) and np.max(np.abs(r)) < 0.05  # rounding of the pixels to 0.01 px
    assert 10.0 < np.min(depth) and np.max(depth) < 260.0
    # turned 0.3 deg about the vertical, or the rails swapped: the picks are off their lines
    th = math.radians(0.3)
    Rz = np.array([[math.cos(th), -math.sin(th), 0], [math.sin(th), math.cos(th), 0], [0, 0, 1]])
    r2, _ = term.errors(pt.rig_from_world @ Rz, pt.centre_enu, pt.views)
    assert np.median(np.abs(r2)) > 1.0
    swapped = [{**e, "rail": {"left": "right", "right": "left"}[e["rail"]]} for e in entries]
    r3, _ = noisy_track_term(pt, swapped, np.random.default_rng(0), 1e-9).errors(pt.rig_from_world, pt.centre_enu,
                                                                               pt.views)
    assert np.median(np.abs(r3)) > 1.0


def test_track_picks_with_gps_place_the_camera_but_not_along_the_track(track_truth):
    """Track picks (2 px) and a GPS prior (5 m, 5 m, 15 m): the rotation and the place across the track come from
    the picks; the place along the track stays the prior's (the track is an arc at one grade), and the solver says
    so; the stated covariance holds the truth. With two map points added the place along the track is fixed."""
    _, pt, entries = track_truth
    opts = GeorefOptions(sigma_px=2.0, track_sigma_px=2.0)
    sig = np.array([5.0, 5.0, 15.0])
    rng = np.random.default_rng(7)
    term = noisy_track_term(pt, entries, rng, 2.0, line_sigma_m=0.02, height_sigma_m=0.02)
    prior = pt.centre_enu + np.array([3.0, -4.0, 6.0])
    t = term.tangent_at(pt.centre_enu)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = solve_central(pt.views, [], prior_centre=prior, prior_sigma_m=sig, opts=opts, track=term)
    tr = res.stats["track"]
    assert tr["n_picks"] == term.n and tr["n_outliers"] <= 2 and 1.0 < tr["rms_px"] < 3.0
    ob = tr["observability"]
    assert ob["rank"] == 6 and (ob["sigma_along_track_from_track_m"] is None or ob["sigma_along_track_from_track_m"] > 20)
    assert 3.0 < ob["sigma_along_track_m"] < 5.5  # what the prior gives
    dc = res.centre_enu - pt.centre_enu
    along_prior = float((prior - pt.centre_enu)[:2] @ t)
    assert abs(float(dc[:2] @ t) - along_prior) < 1.5  # the place along the track: the prior's
    C = np.asarray(res.stats["covariance_world_rotation_centre"])
    assert float(dc @ np.linalg.solve(C[3:, 3:], dc)) < 7.81
    rv, rdeg = rotation_error(res.rig_from_world, pt.rig_from_world)
    assert 0.01 < rdeg < 8.0 and float(rv @ np.linalg.solve(C[:3, :3], rv)) < 7.81
    err, sig_ch = chainage_errors(pt, res.rig_from_world, res.centre_enu, C)
    assert np.all(np.abs(err) < 1.96 * sig_ch + 0.05)


def test_track_picks_alone_are_refused_with_the_reason(track_truth):
    _, pt, entries = track_truth
    term = noisy_track_term(pt, entries, np.random.default_rng(1), 1.0)
    with pytest.raises(InputError, match="along the track"):
        solve_central(pt.views, [], opts=GeorefOptions(), track=term, where="cp.json")


# ----------------------------------------------------------------------------------------------------------
# The panorama route reads them from control_points.json
# ----------------------------------------------------------------------------------------------------------
def test_panorama_route_uses_track_picks_from_the_file(small_incident, track_truth, tmp_path):
    src, truth = small_incident
    shutil.copytree(src.parent.parent, tmp_path, dirs_exist_ok=True, ignore=shutil.ignore_patterns("out", "photos"))
    root = tmp_path / "projects" / src.name
    (root / "photos").mkdir(exist_ok=True)
    for sub in ("panorama", "multiview"):
        (root / "photos" / sub).symlink_to(src / "photos" / sub)
    doc = json.loads((root / "control_points.json").read_text())
    rng = np.random.default_rng(3)
    entries = [{**e, "pixels": np.clip(np.asarray(e["pixels"]) + rng.normal(0.0, 1.0, (len(e["pixels"]), 2)), 0.0,
                                       [799.0, 599.0]).round(2).tolist()} for e in track_truth[2]]
    assert {e["rail"] for e in entries} == {"left", "right"} and {e["photo"] for e in entries} <= {
        f"pano_0{i}.jpg" for i in range(4)}
    doc["track_picks"] = entries
    atomic_write_json(root / "control_points.json", doc)
    atomic_write_json(root / "out" / "stitch" / "panorama.json", true_panorama_model(root))
    project = Project(root)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = run_georef(project, lambda f, m="": None)
    st = result.stats
    assert st["route"] == "panorama" and st["track"]["n_picks"] == sum(len(e["pixels"]) for e in entries)
    assert st["track"]["rms_px"] < 2.5 and st["track"]["sigma_px"] == 2.0
    assert np.linalg.norm(np.asarray(st["centre_enu"]) - np.asarray(truth["panorama_center_enu"])) < 0.3
    cams = json.loads((root / "out" / "georef" / "cameras.json").read_text())
    assert cams["georegistration"]["track"]["n_picks"] == st["track"]["n_picks"]
    # a line the layer does not have: the error names the file, the entry and the layer's lines
    doc["track_picks"][0]["line"] = "no-such-line"
    atomic_write_json(root / "control_points.json", doc)
    with pytest.raises(InputError, match=r"control_points.json: track_picks\[0\].*no-such-line.*spuyten-duyvil-track"):
        run_georef(Project(root), lambda f, m="": None)
    # no railway layer: the error says which setting to give
    toml = root / "project.toml"
    toml.write_text("\n".join(ln for ln in toml.read_text().splitlines() if not ln.startswith("railways")))
    with pytest.raises(InputError, match=r"control_points.json: has track_picks.*terrain.railways"):
        run_georef(Project(root), lambda f, m="": None)


def test_picker_save_keeps_the_files_track_picks(small_incident, tmp_path):
    """The picker's control-point page edits the points only; saving from it keeps the file's track picks."""
    from workbench.picker.control import ControlPointsApi

    src, _ = small_incident
    shutil.copytree(src.parent.parent, tmp_path, dirs_exist_ok=True, ignore=shutil.ignore_patterns("out", "photos"))
    root = tmp_path / "projects" / src.name
    doc = json.loads((root / "control_points.json").read_text())
    tp = [{"photo": "pano_00.jpg", "rail": "left", "pixels": [[10.0, 20.0]]}]
    atomic_write_json(root / "control_points.json", {**doc, "track_picks": tp})
    api = ControlPointsApi(Project(root), lambda: {"pano_00.jpg": (800, 600)})
    points = [{k: p[k] for k in ("name", "coords", "sigma_m")} for p in doc["points"][:3]]
    api.save({"crs": doc["crs"], "points": points})
    saved = json.loads((root / "control_points.json").read_text())
    assert [p["name"] for p in saved["points"]] == [p["name"] for p in points]
    assert saved["track_picks"] == tp


def test_control_points_command_writes_track_picks(small_incident, tmp_path):
    """`workbench control-points PATH --force --track-picks` writes the landmarks and the rails' true pixels; the
    file then reads back with its track picks."""
    import subprocess
    import sys

    src, _ = small_incident
    shutil.copytree(src.parent.parent, tmp_path, dirs_exist_ok=True, ignore=shutil.ignore_patterns("out", "photos"))
    root = tmp_path / "projects" / src.name
    (root / "photos").mkdir(exist_ok=True)
    (root / "photos" / "panorama").symlink_to(src / "photos" / "panorama")
    before = json.loads((root / "control_points.json").read_text())
    assert not before.get("track_picks")
    r = subprocess.run([sys.executable, "-m", "workbench.cli", "control-points", str(root), "--force", "--track-picks"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    doc = json.loads((root / "control_points.json").read_text())
    assert [p["name"] for p in doc["points"]] == [p["name"] for p in before["points"]]
    picks = parse_track_picks(doc, "control_points.json")
    assert len(picks) >= 2 and {p.rail for p in picks} == {"left", "right"}
