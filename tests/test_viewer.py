"""The desktop viewer under a virtual X display: a screenshot of the window, picking carriages, layer toggles."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from PIL import Image
from test_report import stages, synth_incident

from workbench.project import Project
from workbench.runner import Runner

pytestmark = pytest.mark.skipif(shutil.which("xvfb-run") is None, reason="xvfb-run (apt: xvfb xauth) not installed")

W, H = 900, 560
SCRIPT = textwrap.dedent("""
    import faulthandler, json, sys
    faulthandler.dump_traceback_later({HANG_S}, exit=True)  # a hang shows where it is, then the process ends
    import numpy as np
    import open3d.visualization.gui as gui
    from workbench.project import Project
    from workbench.viewer.app import IncidentViewer
    root, shot, select = sys.argv[1], sys.argv[2], sys.argv[3]
    app = gui.Application.instance
    app.initialize()
    v = IncidentViewer(Project(root), width={W}, height={H})
    v.select(select)
    v.screenshot(shot)
    f = v.widget.frame
    out = {{"frame": [f.x, f.y, f.width, f.height], "details": v.details.text, "picks": {{}}, "pixels": {{}}}}
    for c in v.sc.carriages:
        px = v.widget_pixel(c.body_centre_enu)
        out["pixels"][c.number] = px
        if px is not None and 0 <= px[0] < f.width and 0 <= px[1] < f.height:
            out["picks"][c.number] = v.carriage_at(*px)
    out["sky"] = v.carriage_at(f.width / 2, 2.0)  # the top of the view looks at the sky
    v.show_layer("carriages", False)
    out["carriages_checked"] = v.checks["carriages"].checked
    v.show_layer("carriages", True)
    v.window.close()
    app.run_one_tick()
    print("RESULT " + json.dumps(out))
""").format(W=W, H=H, HANG_S=120)


def _run_viewer(args: list[str], out_dir, attempt: int) -> tuple[int, str]:
    """Run the viewer script under a fresh virtual display; output to a file, not a pipe (an X server that outlives
    the script would hold a pipe open), the whole process group killed if it is still there after 180 s."""
    log = out_dir / f"viewer-{attempt}.log"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    with open(log, "w") as fh:
        proc = subprocess.Popen(["xvfb-run", "-a", "-s", "-screen 0 1100x700x24", sys.executable, "-c", SCRIPT, *args],
                                stdout=fh, stderr=subprocess.STDOUT, text=True, env=env, start_new_session=True)
        try:
            rc = proc.wait(timeout=180)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            rc = -9
    return rc, log.read_text(errors="replace")


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    root = tmp_path_factory.mktemp("viewer") / "inc"
    shutil.copytree(synth_incident(tmp_path_factory), root)
    project = Project(root)
    Runner(project, stages()).run(until="solve")
    return project


def test_viewer_screenshot_and_picking(solved, tmp_path):
    shot = tmp_path / "viewer.png"
    select = solved.settings.consist[1].number
    rc, out = _run_viewer([str(solved.root), str(shot), select], tmp_path, 1)
    if rc != 0 and ("Timeout (0:" in out or rc == -9):
        # Seen once on CI and never here (idle or loaded): the script hung for 240 s under the virtual display and
        # software Vulkan. One more try on a fresh display; a hang that repeats fails, with the first try's
        # traceback (faulthandler: where it hung) printed in the test's output.
        print("viewer: the first try hung; trying once more. Its output:\n" + out[-3000:])
        rc, out = _run_viewer([str(solved.root), str(shot), select], tmp_path, 2)
    line = next((ln for ln in out.splitlines() if ln.startswith("RESULT ")), None)
    assert rc == 0 and line, out[-4000:]
    res = json.loads(line[len("RESULT "):])

    # the panel shows the selected carriage's numbers, as the solution has them
    sol = json.loads((solved.stage_dir("solve") / "solution.json").read_text())
    car = next(c for c in sol["carriages"] if c["number"] == select)
    assert f"Car {select}" in res["details"]
    assert f"{car['body_centre_crs'][0]:.2f}" in res["details"]
    assert f"{car['heading_deg']:.1f}" in res["details"] and "±" in res["details"]

    # picking: the ray through each carriage's centre finds that carriage; the sky finds none
    assert len(res["picks"]) >= 2
    for number, picked in res["picks"].items():
        assert picked == number
    assert res["sky"] is None
    assert res["carriages_checked"] is False

    # the screenshot: the whole window, the panel on the right, the selection outline around the car's centre
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    assert img.shape[:2] == (H, W)
    fx, fy, fw, fh = res["frame"]
    view, panel = img[:, :fw], img[:, fw:]
    assert view.std() > 20 and panel.std() > 10
    assert abs(panel.mean() - view.mean()) > 10  # a dark panel beside a bright scene
    yellow = (view[..., 0] > 200) & (view[..., 1] > 170) & (view[..., 2] < 90)
    assert yellow.sum() > 40
    ys, xs = np.nonzero(yellow)
    u, v = res["pixels"][select]
    assert xs.min() - 3 <= u <= xs.max() + 3 and ys.min() - 3 <= v <= ys.max() + 3


def test_viewer_before_solve_names_the_stage(solved, tmp_path):
    root = tmp_path / "inc"
    root.mkdir()
    shutil.copy(solved.root / "project.toml", root / "project.toml")
    proc = subprocess.run([sys.executable, "-m", "workbench.viewer", str(root), "--screenshot",
                           str(tmp_path / "x.png")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "'solve' stage" in proc.stderr


def test_viewer_without_display_says_how(solved):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run([sys.executable, "-m", "workbench.viewer", str(solved.root)], capture_output=True, text=True,
                          timeout=120, env=env)
    assert proc.returncode == 2
    assert "xvfb-run" in proc.stderr and "DISPLAY" in proc.stderr
