"""The real CLI entry point on small incidents: bad input gives a one-line error, exit 2, nothing lost."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from workbench.render.exif import write_jpeg

WB = [sys.executable, "-m", "workbench.cli"]
FIRST = ("--only", "inputs", "--only", "terrain")  # noise photos: the later stages rightly refuse them


def wb(*args, cwd=None):
    return subprocess.run([*WB, *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=300)


def small_incident(tmp_path: Path) -> Path:
    root = tmp_path / "inc"
    r = wb("init", root, "--lat", "40.878", "--lon", "-73.9215", "--date", "2013-12-01")
    assert r.returncode == 0, r.stderr
    toml = (root / "project.toml").read_text()
    toml = toml.replace('[[consist]]\nnumber = "1"\ntype = "shoreliner"',
                        '[[consist]]\nnumber = "1"\ntype = "p32ac-dm"\ncoupling_to_next = "held"\n\n'
                        '[[consist]]\nnumber = "2"\ntype = "shoreliner"')
    (root / "project.toml").write_text(toml)
    rng = np.random.default_rng(0)
    for i in range(2):
        img = (rng.uniform(0, 255, (60, 80, 3))).astype(np.uint8)
        write_jpeg(root / "photos/panorama" / f"p{i}.jpg", img, focal_length_mm=20.0, sensor_width_mm=23.5)
    return root


def one_line_error(r, *needles):
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = [line for line in r.stderr.strip().splitlines() if line.startswith("error:")]
    assert len(lines) == 1, r.stderr  # one error line (progress lines of stages that ran may precede it)
    for n in needles:
        assert n in lines[0], (n, lines[0])


def test_run_status_and_skip(tmp_path):
    root = small_incident(tmp_path)
    r = wb("run", root, *FIRST)
    assert r.returncode == 0, r.stderr
    assert "inputs" in r.stdout and "out/inputs/inputs.json" in r.stdout
    data = json.loads((root / "out/inputs/inputs.json").read_text())
    assert data["n_photos"] == 2 and data["n_chains"] == 1
    assert abs(data["photos"]["photos/panorama/p0.jpg"]["exif_focal_px"] - 20.0 / 23.5 * 80) < 0.5
    r = wb("run", root, *FIRST)
    assert "up to date, skipped" in r.stdout + r.stderr
    r = wb("status", root)
    assert r.returncode == 0 and "done" in r.stdout


def test_bad_inputs_fail_cleanly_and_lose_nothing(tmp_path):
    root = small_incident(tmp_path)
    assert wb("run", root, *FIRST).returncode == 0
    good = (root / "out/inputs/inputs.json").read_bytes()
    settings = (root / "project.toml").read_text()

    # a corrupt photo
    (root / "photos/panorama/p1.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    one_line_error(wb("run", root, *FIRST), "p1.jpg", "cannot read this photo")
    assert (root / "out/inputs/inputs.json").read_bytes() == good
    (root / "photos/panorama/p1.jpg").unlink()

    # a typo in the settings
    (root / "project.toml").write_text(settings.replace("estimate_focal", "estimate_focl"))
    one_line_error(wb("run", root, *FIRST), "project.toml", "unknown key 'solver.estimate_focl'")
    # a CRS that is not projected
    (root / "project.toml").write_text(settings.replace('crs = "EPSG:32618"', 'crs = "EPSG:4326"'))
    one_line_error(wb("run", root, *FIRST), "project.toml", "location.crs", "not a projected CRS")
    # an unknown model type
    (root / "project.toml").write_text(settings.replace('type = "shoreliner"', 'type = "shorliner"'))
    one_line_error(wb("run", root, *FIRST), "consist[1].type = 'shorliner'", "shoreliner")
    # an empty consist
    head = settings.split("[[consist]]")[0]
    tail = "[camera]" + settings.split("[camera]")[1]
    (root / "project.toml").write_text("consist = []\n" + head + tail)
    one_line_error(wb("run", root, *FIRST), "consist is empty")
    # an unreadable DEM
    (root / "project.toml").write_text(settings.replace('# dem = "../../terrain/<region>/dem.tif"', 'dem = "dem.tif"'))
    (root / "dem.tif").write_bytes(b"II*\x00garbage")
    one_line_error(wb("run", root, *FIRST), "dem.tif")
    # a missing photo folder
    (root / "project.toml").write_text(settings.replace('photos = "photos/panorama"', 'photos = "photos/none"'))
    one_line_error(wb("run", root, *FIRST), "camera.photos = 'photos/none'")

    # the last good run (one photo, after p1 was removed) is intact; the failed terrain stage wrote nothing
    assert json.loads((root / "out/inputs/inputs.json").read_text())["n_photos"] == 1
    assert not (root / "out/terrain/terrain.ply").exists()
    assert json.loads((root / "out/state.json").read_text())["terrain"]["status"] == "failed"


def test_init_refuses_to_overwrite(tmp_path):
    root = small_incident(tmp_path)
    before = (root / "project.toml").read_text()
    one_line_error(wb("init", root), "already exists")
    assert (root / "project.toml").read_text() == before


def test_types_lists_the_library():
    r = wb("types")
    assert r.returncode == 0
    for t in ("shoreliner", "p32ac-dm", "amfleet-i", "acs-64"):
        assert t in r.stdout


def test_synth_bad_options(tmp_path):
    one_line_error(wb("synth", tmp_path / "x", "--scenario", "nowhere"), "unknown scenario 'nowhere'", "spuyten-duyvil")
    one_line_error(wb("synth", tmp_path / "x", "--cars", "0"), "--cars 0")
