"""The whole pipeline through the command line, as a user runs it: `workbench synth`, `workbench control-points`,
`workbench run`, `workbench status`, on a small generated incident, the solution checked against its truth."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np


def _wb(*args, timeout: int = 600) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": "200"}
    return subprocess.run([sys.executable, "-m", "workbench.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=env)


def test_synth_control_points_run_status(tmp_path: Path):
    root = tmp_path / "projects" / "inc"
    # on 200 m of terrain (the default 500 m: a larger orthophoto and DEM mesh to make, render and read, around the
    # same carriages and cameras)
    r = _wb("synth", root, "--cars", 4, "--width", 800, "--height", 600, "--panorama", 4, "--multiview", 0,
            "--seed", 3, "--terrain-size", 200, "--layers-dir", "../../terrain/e2e")
    assert r.returncode == 0, r.stderr[-2000:]
    r = _wb("control-points", root)
    assert r.returncode == 0, r.stderr[-2000:]
    r = _wb("run", root)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    r = _wb("status", root)
    assert r.returncode == 0 and "stale" not in r.stdout and "failed" not in r.stdout, r.stdout

    sol = json.loads((root / "out/solve/solution.json").read_text())
    truth = {c["number"]: c for c in json.loads((root / "truth/ground_truth.json").read_text())["carriages"]}
    assert sol["status"] == "converged"
    assert 0.2 < sol["sigma_px_estimated"] < 2.0  # automatic points on 800 x 600 renders
    placed = [c for c in sol["carriages"] if c["status"] != "left_out"]
    assert len(placed) >= 3, [(c["number"], c["status"]) for c in sol["carriages"]]
    for c in placed:
        t = truth[c["number"]]
        err = np.subtract(c["body_centre_enu"], t["body_centre_enu"])
        assert np.linalg.norm(err) < 2.0, (c["number"], err)
        if c["ci95_body_centre_m"] is None:  # placed by its chain or predictions: no interval, and said so
            assert any(w["car"] == c["number"] and "do not determine its pose" in w["message"]
                       for w in sol["warnings"]), sol["warnings"]
            continue
        ci = np.asarray(c["ci95_body_centre_m"])
        assert np.all(ci > 0.01) and np.all(ci < 3.0), (c["number"], ci)  # neither absurdly sharp nor vague
        assert np.all(np.abs(err) <= 1.75 * ci + 0.05), (c["number"], err, ci)  # ~3.5 sigma per axis
        dh = (c["heading_deg"] - t["heading_deg"] + 180) % 360 - 180
        assert abs(dh) <= 1.75 * c["ci95_hpr_deg"][0] + 0.1, (c["number"], dh)
    # a car the finder could not place is named for hand picks, not silently dropped
    for c in sol["carriages"]:
        if c["status"] == "left_out":
            assert c["number"] in {n["carriage"] for n in
                                   json.loads((root / "out/correspond/correspondences.json").read_text())
                                   .get("needs_manual", [])}

    # what the user reads and loads: the report and the georeferenced exports
    report = json.loads((root / "out/report/report.json").read_text())
    assert report and (root / "out/report/report.pdf").stat().st_size > 10_000
    gj = json.loads((root / "out/export/carriages.geojson").read_text())
    assert {f["properties"]["number"] for f in gj["features"]} >= {c["number"] for c in placed}
