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
from scipy.spatial.transform import Rotation

from workbench.core.camera import project_world
from workbench.core.geometry import skew
from workbench.pipeline import STAGES
from workbench.project import Project
from workbench.runner import Runner

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "projects" / "keikyu-n1000-photo"
PHOTOS = [REPO / line.strip() for line in (SAMPLE / "photos.txt").read_text().splitlines()
          if line.strip() and not line.startswith("#")]
pytestmark = pytest.mark.skipif(not all(p.is_file() for p in PHOTOS), reason="../shared/data (the real photo) absent")


def _solve_copy(root: Path, unlinked: bool) -> Project:
    root.mkdir()
    shutil.copy(SAMPLE / "correspondences.json", root / "correspondences.json")
    toml = (SAMPLE / "project.toml").read_text()
    if unlinked:  # the coupling declared broken, no link: each car placed by its own picks
        assert 'coupling_to_next = "held"' in toml
        toml = toml.replace('coupling_to_next = "held"', 'coupling_to_next = "broken"')
    (root / "project.toml").write_text(toml)
    (root / "photos").mkdir()
    for p in PHOTOS:
        shutil.copy(p, root / "photos" / p.name)
    project = Project(root)
    Runner(project, STAGES).run(only=["inputs", "georef", "correspond", "solve"])
    return project


@pytest.fixture(scope="module")
def solved(tmp_path_factory) -> Project:
    return _solve_copy(tmp_path_factory.mktemp("real") / "keikyu-n1000-photo", unlinked=False)


def test_the_picks_six_or_more_a_car_rounded_corners_from_edges():
    """Issue 16's protocol: 6-10 hand picks a car; the rounded or hidden corners picked from two drawn edges."""
    obs = json.loads((SAMPLE / "correspondences.json").read_text())["observations"]
    per_car = {c: [o for o in obs if o["carriage"] == c] for c in ("1", "2")}
    assert all(6 <= len(v) <= 10 for v in per_car.values()), {c: len(v) for c, v in per_car.items()}
    edges = [o for o in obs if (o.get("construction") or {}).get("method") == "edges"]
    assert len(edges) >= 8  # car 2's six and car 1's far corners and rear corners


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
    assert 5.0 < hfov < 10.0  # a telephoto shot: the cars barely shrink along the train (measured 7.4 deg)
    # measured 0.87 px over 13 picks (2026-11-26; 2.56 px over the 11 picks before; 1.62 px with the cab front flat
    # in plan, its corner setback measured since on another photo: README.md); a wrong pose or focal would be tens
    # of pixels off, a model point on the wrong feature (the door's axis for its rear edge) 2-3 px
    assert 0.6 < doc["residual_rms_px"]["measured"] < 1.2
    c1, c2 = sol.carriages
    assert c1.record["coupler_gap_to_next_m"] < 0.05 + 1e-6  # the held coupling's slack
    h1, h2 = c1.record["heading_deg"], c2.record["heading_deg"]
    # one behind the other (measured 0.60 deg apart: the track curves there, tests/test_real_photo_track.py)
    assert abs((h1 - h2 + 180) % 360 - 180) < 1.5
    for c in (c1, c2):
        assert abs(c.record["pitch_deg"]) < 2.0 and abs(c.record["roll_deg"]) < 2.0  # standing on their wheels
    # 75 m from the camera (18 m cars, a 7 deg field of view; the distance follows the focal, which the picks fix
    # to +-4 %, and the models' heights: 113 m with the eave from memory), the cars one behind the other
    d1 = np.linalg.norm(c1.record["body_centre_enu"])
    assert 50.0 < d1 < 150.0
    assert np.linalg.norm(np.subtract(c2.record["body_centre_enu"], c1.record["body_centre_enu"])) == \
        pytest.approx(18.0, abs=0.5)


def test_unlinked_the_cars_come_out_coupled_and_in_line(tmp_path):
    """The same picks with the coupling declared broken and no link (issue 16's check; as
    scripts/bench_real_photo.py): car 2 relative to car 1 within 1.5 deg in roll, pitch and yaw (measured -1.28,
    -0.00, 0.60 deg; zero is not inside their 95 % region: the yaw's is +-0.20 deg, and the cars are turned by
    about that much, the track curving: tests/test_real_photo_track.py); the coupler gap (measured 0.504 m, along
    the line of sight, where the focal leaves metres of doubt) with zero inside its 95 % region."""
    sol = _solve_copy(tmp_path / "unlinked", unlinked=True).solution("test")
    a, b = sol.posed
    types = Project(tmp_path / "unlinked").carriage_types()
    Ma, Mb = a.world_from_carriage, b.world_from_carriage
    Ca, Cb = np.asarray(a.record["covariance_pose"], float), np.asarray(b.record["covariance_pose"], float)
    pa, pb = Ma[:3, :3] @ types[a.number].coupler_rear, Mb[:3, :3] @ types[b.number].coupler_front
    gap = (pa + Ma[:3, 3]) - (pb + Mb[:3, 3])
    Ja, Jb = np.hstack([-skew(pa), np.eye(3)]), np.hstack([-skew(pb), np.eye(3)])
    Cg = Ja @ Ca @ Ja.T + Jb @ Cb @ Jb.T
    rel = Rotation.from_matrix(Ma[:3, :3].T @ Mb[:3, :3]).as_rotvec()
    Cr = Ma[:3, :3].T @ (Ca[:3, :3] + Cb[:3, :3]) @ Ma[:3, :3]
    print(f"\nunlinked: gap {np.linalg.norm(gap):.2f} m, roll/pitch/yaw {np.degrees(rel).round(2)} deg")
    print(f"relative rotation chi-square {rel @ np.linalg.solve(Cr, rel):.1f} (95 %: 7.8)")
    assert np.all(np.abs(np.degrees(rel)) < 1.5)
    assert np.linalg.norm(gap) < 0.8  # the target, 0.5 m, missed by 4 mm (README.md); 2.3 m with the 11 picks before
    assert gap @ np.linalg.solve(Cg, gap) < 7.8147  # chi-square, 3 dof, 95 %


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
