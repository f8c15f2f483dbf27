"""The real-photo sample incident (``projects/keikyu-n1000-photo``, issue 16): one Wikimedia Commons photo of a
Keikyu N1000 train (no EXIF, telephoto), the two leading cars' corners picked by hand in ``workbench pick``, no
survey. Run when ``../shared/data`` (the photo) is beside the repository; the incident's own files are copied to
a temporary folder, so ``projects/`` is never written.

There is no ground truth for a real photo: the checks are the physical facts the photo must satisfy (a plausible
telephoto field of view, a fit at the level of the picks' and the models' accuracy, the held coupling closed,
both cars upright and on one line) and the consistency of what renders draw (the solution's camera, levelled
frame and solved focal put every marked point back on its pick).
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from workbench.core.camera import project_world
from workbench.pipeline import STAGES
from workbench.project import Project
from workbench.runner import Runner

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "projects" / "keikyu-n1000-photo"
PHOTOS = [REPO / line.strip() for line in (SAMPLE / "photos.txt").read_text().splitlines()
          if line.strip() and not line.startswith("#")]
pytestmark = pytest.mark.skipif(not all(p.is_file() for p in PHOTOS), reason="../shared/data (the real photo) absent")


@pytest.fixture(scope="module")
def solved(tmp_path_factory) -> Project:
    root = tmp_path_factory.mktemp("real") / "keikyu-n1000-photo"
    root.mkdir()
    for name in ("project.toml", "correspondences.json"):
        shutil.copy(SAMPLE / name, root / name)
    (root / "photos").mkdir()
    for p in PHOTOS:
        shutil.copy(p, root / "photos" / p.name)
    project = Project(root)
    Runner(project, STAGES).run(only=["inputs", "georef", "correspond", "solve"])
    return project


def test_real_photo_fit_and_physical_facts(solved):
    sol = solved.solution("test")
    doc = sol.doc
    assert doc["status"] == "converged" and sol.relative
    # car 2 shows one side only (coplanar points): solved through the focal car 1 pins (joint observability)
    assert [c.status for c in sol.carriages] == ["solved", "solved"]
    (view, f), = doc["focal_px"].items()
    hfov = math.degrees(2 * math.atan(0.5 * 800 / f))
    print(f"\nreal photo: focal {f:.0f} px (hfov {hfov:.2f} deg, sigma {doc['sigma_focal_px'][view]:.0f} px), "
          f"RMS {doc['residual_rms_px']['measured']:.2f} px over {doc['residual_rms_px']['n_measured']} picks")
    assert 2.0 < hfov < 10.0  # a telephoto shot: the cars barely shrink along the train
    # the fit is at the level of the picks (rounded corners, 800 px) and the models (some dimensions estimated):
    # measured 2.6 px (3.8 px with the eave and window line from memory); a wrong pose or focal would be tens of
    # pixels off
    assert 1.0 < doc["residual_rms_px"]["measured"] < 5.0
    c1, c2 = sol.carriages
    assert c1.record["coupler_gap_to_next_m"] < 0.05 + 1e-6  # the held coupling's slack
    h1, h2 = c1.record["heading_deg"], c2.record["heading_deg"]
    assert abs((h1 - h2 + 180) % 360 - 180) < 3.0  # one straight track
    for c in (c1, c2):
        assert abs(c.record["pitch_deg"]) < 2.0 and abs(c.record["roll_deg"]) < 2.0  # standing on their wheels
    # 75 m from the camera (18 m cars, a 7 deg field of view; the distance follows the focal, which the picks fix
    # to +-5 %, and the models' heights: 113 m with the eave from memory), the cars one behind the other
    d1 = np.linalg.norm(c1.record["body_centre_enu"])
    assert 50.0 < d1 < 150.0
    assert np.linalg.norm(np.subtract(c2.record["body_centre_enu"], c1.record["body_centre_enu"])) == \
        pytest.approx(18.0, abs=0.5)


def test_what_renders_draw_puts_every_point_on_its_pick(solved):
    """The scene's camera (the cameras file's, turned into the levelled frame, with the solved focal) projects
    each car's marked points onto the picks to the solution's own residuals."""
    from workbench.report.scene import load_scene

    sol = solved.solution("test")
    scene = load_scene(solved, textured=False, with_terrain=False)
    cam = scene.cameras[0]
    types = solved.carriage_types()
    picks = json.loads((solved.root / "correspondences.json").read_text())["observations"]
    by_car = {c.number: c for c in sol.carriages}
    for o in picks:
        c = by_car[o["carriage"]]
        X = c.world_from_carriage @ np.append(types[c.number].marked_points[o["point"]], 1.0)
        uv, depth = project_world(cam.intrinsics, cam.cam_from_world, X[None, :3])
        res = c.record["residuals_px"][o["view"]][o["point"]]
        assert depth[0] > 0
        assert np.allclose(uv[0] - np.asarray(o["uv"]), res, atol=0.05)  # residual = projected - picked
