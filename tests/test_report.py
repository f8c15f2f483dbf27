"""Render and report stages on a small synthetic incident: renders against the truth masks, the PDF's pages
and text, the index files, and the errors for missing stages and missing rendering libraries."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from conftest import built_once

from workbench import pipeline
from workbench.errors import InputError, RenderError, StageError
from workbench.project import Project
from workbench.report import render_stage, report_stage
from workbench.runner import Runner

SYNTH = dict(n_cars=3, photo_width=320, photo_height=240, n_panorama=2, n_multiview=0)  # `workbench synth` options
SMALL = {"OVERVIEW_SIZE": (480, 300), "MAP_SIZE": (360, 360), "CLOSEUP_SIZE": (320, 200), "ORBIT_SIZE": (200, 125),
         "ORBIT_FRAMES": 6}


def synth_incident(tmp_path_factory) -> Path:
    """A 3-carriage synthetic incident with known cameras and true picks (1 px noise; the automatic finder off),
    generated once per test run (``conftest.built_once``: shared by the pytest-xdist workers). Read-only: copy it
    before running stages."""

    def build(base: Path) -> None:
        from workbench.synth.generate import SynthOptions, generate_incident
        from workbench.synth.handpicks import write_known_cameras, write_true_correspondences

        root = base / "report_incident"
        generate_incident(root, SynthOptions(**SYNTH))
        write_known_cameras(root)
        write_true_correspondences(root, sigma_px=1.0, seed=0)
        # the hand picks only: every car has them, and they override whatever the automatic finder places (12
        # points here, in the fixture's, the viewer's and the solved-focal test's runs, all overridden: the same
        # correspondences.json without it; docs/performance.md, the thirteenth pass)
        toml = root / "project.toml"
        assert "[correspond]" not in toml.read_text()
        toml.write_text(toml.read_text() + '\n[correspond]\nfinder = "off"\n')

    return built_once(tmp_path_factory, "report_incident", build) / "report_incident"


def stages() -> list:
    """The pipeline's stages but the export, which neither the render and report stages nor a test here reads
    (tests/test_export.py checks the exports)."""
    return [s for s in pipeline.STAGES if s.name != "export"]


@pytest.fixture(scope="module")
def incident(tmp_path_factory):
    root = synth_incident(tmp_path_factory)
    work = tmp_path_factory.mktemp("report") / "inc"
    shutil.copytree(root, work, ignore=shutil.ignore_patterns("out"))
    project = Project(work)
    with pytest.MonkeyPatch.context() as mp:
        for k, v in SMALL.items():
            mp.setattr(render_stage, k, v)
        events = []
        Runner(project, stages()).run(until="report", on_event=lambda kind, spec, rec: events.append((kind, spec.name)))
    assert ("done", "render") in events and ("done", "report") in events
    return project


def test_renders_index(incident):
    idx = json.loads((incident.stage_dir("render") / "renders.json").read_text())
    kinds = [r["kind"] for r in idx["renders"]]
    assert kinds.count("overview") == 1 and kinds.count("map") == 1 and kinds.count("orbit") == 1
    assert kinds.count("photo") == 2
    assert sorted(r["carriage"] for r in idx["renders"] if r["kind"] == "closeup") == \
        sorted(c.number for c in incident.settings.consist)
    for r in idx["renders"]:
        with Image.open(incident.path(r["path"])) as im:
            if r["kind"] in ("overview", "closeup", "photo"):
                assert im.size == (r["width"], r["height"])
            # not a blank picture
            assert np.asarray(im.convert("L")).std() > 10.0
    m = next(r for r in idx["renders"] if r["kind"] == "map")
    x0, x1, y0, y1 = m["extent_enu"]
    sol = json.loads((incident.stage_dir("solve") / "solution.json").read_text())
    for c in sol["carriages"]:
        e, n = c["body_centre_enu"][:2]
        assert x0 < e < x1 and y0 < n < y1
    assert 0.3 < m["grid_convergence_deg"] < 1.1  # UTM 18N at the Bronx: about +0.7 degrees
    stats = json.loads((incident.stage_dir("render") / "stats.json").read_text())
    assert stats["terrain_textured"] is True and stats["n_renders"] == len(idx["renders"])


def _overlays_and_truth(project: Project):
    """(render record, truth photo, truth instance mask, rendered carriage ids, truth) of every photo overlay."""
    truth = json.loads((project.truth_dir / "ground_truth.json").read_text())
    idx = json.loads((project.stage_dir("render") / "renders.json").read_text())
    for r in (r for r in idx["renders"] if r["kind"] == "photo"):
        ph = next(p for p in truth["photos"] if Path(p["photo"]).name == r["view"])
        yield (r, ph, np.asarray(Image.open(project.path(ph["mask"]))), np.asarray(Image.open(project.path(r["ids"]))),
               truth)


def test_photo_overlay_matches_truth_masks(incident):
    """The carriages rendered from each photo's own camera cover the truth instance masks (solved poses, 1 px noise)."""
    checked = 0
    for r, ph, true_ids, ids, truth in _overlays_and_truth(incident):
        assert ids.shape == true_ids.shape
        for c in truth["carriages"]:
            t = true_ids == c["instance_id"]
            if t.sum() < 150:
                continue
            k = c["index"]
            mine = ids == k
            iou = (t & mine).sum() / (t | mine).sum()
            assert 0.80 < iou <= 1.0, (r["view"], c["number"], iou)
            assert 0.8 < mine.sum() / t.sum() < 1.2
            # and against the other carriages' masks: nearly no overlap
            for o in truth["carriages"]:
                if o["index"] != k and (true_ids == o["instance_id"]).sum() >= 150:
                    assert ((true_ids == o["instance_id"]) & mine).sum() / mine.sum() < 0.1
            checked += 1
        overlay = np.asarray(Image.open(incident.path(r["path"])).convert("RGB")).astype(int)
        photo = np.asarray(Image.open(incident.path(ph["photo"])).convert("RGB")).astype(int)
        # the overlay changes the photo on carriage pixels only
        changed = np.abs(overlay - photo).sum(axis=2) > 40
        assert changed[ids == 255].mean() < 0.02
    assert checked >= 2


def test_overlays_draw_with_the_solved_focal(incident, tmp_path):
    """A camera whose focal the solve estimated (cameras.json says 0.7x the truth, focal_known false): the photo
    overlays draw with the solved focal, so the carriages cover their truth masks (drawn with the starting focal,
    issue 16, they came out at 0.7x their size)."""
    from workbench.report.scene import load_scene

    work = tmp_path / "inc"
    shutil.copytree(incident.root, work)  # with its outputs: the stages the new cameras make stale run again
    doc = json.loads((work / "cameras.json").read_text())
    true_fx = {}
    for v in doc["views"]:
        true_fx[v["name"]] = v["intrinsics"]["fx"]
        v["intrinsics"]["fx"] *= 0.7
        v["intrinsics"]["fy"] *= 0.7
        v["focal_known"] = False
    (work / "cameras.json").write_text(json.dumps(doc))
    project = Project(work)
    with pytest.MonkeyPatch.context() as mp:
        for k, v in SMALL.items():
            mp.setattr(render_stage, k, v)
        Runner(project, stages()).run(until="render")
    sol = json.loads(project.solution_path.read_text())
    for name, f in sol["focal_px"].items():
        assert 0.97 < f / true_fx[name] < 1.03, (name, f, true_fx[name])
    cams = {c.name: c for c in load_scene(project, with_terrain=False).cameras}
    assert {n: c.intrinsics.fx for n, c in cams.items()} == pytest.approx(sol["focal_px"])
    checked = 0
    for r, _ph, true_ids, ids, truth in _overlays_and_truth(project):
        for c in truth["carriages"]:
            t = true_ids == c["instance_id"]
            if t.sum() < 150:
                continue
            mine = ids == c["index"]
            assert 0.75 < (t & mine).sum() / (t | mine).sum() <= 1.0, (r["view"], c["number"])
            checked += 1
    assert checked >= 2


def test_terrain_texture_matches_photos(incident):
    """The orthophoto is draped where the synthetic photos saw it: the render from a photo's camera matches the photo
    on terrain pixels, and worse when shifted by 3 px."""
    from workbench.render.lens import render_photo
    from workbench.report.scene import load_scene

    sc = load_scene(incident)
    sr = render_stage.SceneRenderer(sc, camera_glyphs=False)
    cam = sc.cameras[0]
    res = render_photo(sr.scene, cam.intrinsics, cam.cam_from_world, supersample=1)
    photo = np.asarray(Image.open(cam.image).convert("RGB")).astype(float)
    ground = (res.instance < 0) & np.isfinite(res.depth)
    assert ground.mean() > 0.2
    err = np.abs(res.color.astype(float) - photo).mean(axis=2)[ground].mean()
    shifted = np.abs(np.roll(res.color.astype(float), 3, axis=1) - photo).mean(axis=2)[ground].mean()
    assert 0.5 < err < 10.0 and err < shifted - 0.5


def _pdftotext(pdf: Path) -> str:
    return subprocess.run(["pdftotext", "-layout", str(pdf), "-"], check=True, capture_output=True, text=True).stdout


@pytest.mark.skipif(shutil.which("pdftotext") is None, reason="poppler-utils (pdftotext) not installed")
def test_pdf_pages_and_text(incident):
    out = incident.stage_dir("report")
    pdf = out / "report.pdf"
    text = _pdftotext(pdf)
    facts = json.loads((out / "report.json").read_text())
    info = subprocess.run(["pdfinfo", str(pdf)], check=True, capture_output=True, text=True).stdout
    pages = int(re.search(r"Pages:\s+(\d+)", info).group(1))
    assert pages == facts["pages"] and 6 <= pages <= 14
    assert f"Page 1 of {pages}" in text and f"Page {pages} of {pages}" in text
    s = incident.settings
    assert s.incident.name.split(",")[0] in text
    assert "SYNTHETIC INCIDENT" in text and s.incident.date.isoformat() in text
    for title in ("Site plan", "Carriages", "Measurements in the photographs", "Reconstruction against the",
                  "Provenance", "Software", "Settings"):
        assert title in text
    sol = json.loads((incident.stage_dir("solve") / "solution.json").read_text())
    for c in sol["carriages"]:
        assert c["number"] in text
        # the table shows the solution's coordinates (cm) and heading (0.1 degree)
        e, n, _h = c["body_centre_crs"]
        assert f"{e:.2f}" in text and f"{n:.2f}" in text
        assert f"{c['heading_deg']:.1f}" in text
    # "in brief": the wreck's extent from the body centres
    P = np.array([c["body_centre_enu"] for c in sol["carriages"] if c["status"] != "left_out"])
    span = np.max(np.linalg.norm(P[:, None, :2] - P[None, :, :2], axis=2))
    assert f"lie within {span:.0f} m of one another" in " ".join(facts["findings"])
    assert "In brief".upper() in text.upper()
    # provenance: the hash of the solution file the render stage read
    state = json.loads(incident.state_path.read_text())
    assert state["render"]["inputs"]["solution"][:16] in text


def test_panorama_figure_carries_every_point(incident):
    """With a stitched panorama, every marked point of every photo is drawn in it (through the panorama model)."""
    if not (incident.stage_dir("stitch") / "panorama.json").is_file():
        pytest.skip("the stitch stage made no panorama here")
    facts = json.loads((incident.stage_dir("report") / "report.json").read_text())
    sol = json.loads((incident.stage_dir("solve") / "solution.json").read_text())
    n = sum(len(pts) for c in sol["carriages"] for pts in (c.get("observations") or {}).values())
    assert facts["panorama"] is not None and facts["panorama"]["n_points"] == n
    # the residuals keep their size through the (nearly pinhole) panorama: RMS within 25% of the photos' RMS
    assert 0.75 < facts["panorama"]["rms_px"] / facts["residuals"]["rms_px"] < 1.25
    assert sum(o["n_points"] for o in facts["observations"]) == n


def test_html_links_exist(incident):
    out = incident.stage_dir("report")
    html = (out / "report.html").read_text()
    assert "{&#39;" not in html and "{'" not in html  # warnings are shown as sentences, not as Python dicts
    srcs = re.findall(r'src="([^"]+)"', html)
    assert len(srcs) >= 8
    for s in srcs:
        assert (out / s).is_file(), s


def test_missing_stages_are_named(incident, tmp_path):
    work = tmp_path / "inc"
    shutil.copytree(incident.root, work, ignore=shutil.ignore_patterns("out"))
    project = Project(work)
    with pytest.raises(InputError, match="'solve' stage"):
        render_stage.run_render(project, lambda f, m="": None)
    with pytest.raises(InputError, match="'solve' stage"):
        report_stage.run_report(project, lambda f, m="": None)
    with pytest.raises(StageError, match="'solve'"):
        Runner(project, stages()).run(only=["render"])
    # a solution but no renders: the report names the render stage
    (project.stage_dir("solve")).mkdir(parents=True)
    shutil.copy(incident.stage_dir("solve") / "solution.json", project.stage_dir("solve") / "solution.json")
    with pytest.raises(InputError, match="'render' stage"):
        report_stage.run_report(project, lambda f, m="": None)


def test_missing_open3d_names_debian_packages(monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # import open3d now raises ImportError
    with pytest.raises(RenderError, match="apt-get install -y .*mesa-vulkan-drivers"):
        render_stage._require_open3d()


def test_bad_engine_is_refused(monkeypatch):
    monkeypatch.setenv(render_stage.ENGINE_ENV, "opengl")
    with pytest.raises(RenderError, match="raytrace"):
        render_stage._engine()


def test_nice_length_and_top_down_camera():
    assert [render_stage._nice_length(x) for x in (0.9, 1.0, 3.7, 19.0, 60.0)] == [0.5, 1.0, 2.0, 10.0, 50.0]
    K, M, mpp = render_stage.top_down_camera(np.array([10.0, -5.0]), 50.0, 500, ground_z=2.0)
    # a ground point 40 m east and 20 m north of the centre lands 200 px right and 100 px up of the image centre
    from workbench.core.camera import CameraIntrinsics, project_world

    intr = CameraIntrinsics.from_K(K, 500, 500)
    uv, depth = project_world(intr, M, np.array([[50.0, 15.0, 2.0]]))
    assert np.allclose(uv[0], [249.5 + 200.0, 249.5 - 100.0], atol=1e-6)
    assert mpp == pytest.approx(0.2) and depth[0] > 0


def test_solver_warnings_read_as_sentences():
    """The solution lists warnings as {car, index, kind, message} records: the report shows the message."""
    from workbench.report.report_stage import _warning_text

    rec = {"car": "6240", "index": 5, "kind": "left_out", "message": "car 6240: 0 visible marked point(s); left out"}
    assert _warning_text(rec) == "car 6240: 0 visible marked point(s); left out"
    assert _warning_text({"car": "6240", "kind": "left_out"}) == "car: 6240; kind: left_out"
    assert _warning_text("focal at the edge of the plausible range") == "focal at the edge of the plausible range"


def test_a_carriage_its_points_do_not_fit_is_marked_doubtful(incident):
    """A carriage the solver flags as not fitting its measured points (a warning of kind ``misfit``) is marked
    doubtful in the carriages table, named in the first page's findings and flagged in the exports' properties;
    the others are not."""
    from workbench.export.geojson import carriage_properties
    from workbench.files.scene import scene_carriages
    from workbench.files.solution import parse_solution

    sol = json.loads((incident.stage_dir("solve") / "solution.json").read_text())
    placed = [c["number"] for c in sol["carriages"] if c.get("world_from_carriage")]
    assert len(placed) >= 2
    msg = f"car {placed[0]}: the solution does not fit its points (RMS 4.9 px against a pixel sigma of 2.17 px)"
    sol["warnings"] = list(sol.get("warnings") or []) + [{"car": placed[0], "index": 0, "kind": "misfit",
                                                          "message": msg}]
    rows = {r["number"]: r for r in report_stage.carriage_rows(incident, sol)}
    assert rows[placed[0]]["doubt"] == msg.removeprefix(f"car {placed[0]}: ") and not any(rows[n]["doubt"] for n in placed[1:])
    from workbench.viewer.app import carriage_text  # the viewer's card of a picked carriage says so too

    assert "DOUBTFUL: the solution does not fit" in carriage_text(rows[placed[0]], "EPSG:32618")
    assert "DOUBTFUL" not in carriage_text(rows[placed[1]], "EPSG:32618")
    found = [f for f in report_stage.findings(incident, sol) if f.startswith("Doubtful")]
    assert len(found) == 1 and f"car {placed[0]}:" in found[0]
    cars, _ = scene_carriages(parse_solution(sol, "solution.json"), incident.carriage_types())
    props = {c.number: carriage_properties(c, incident.frame) for c in cars}
    assert props[placed[0]]["doubtful"] is True and props[placed[0]]["doubt"] == msg
    assert all(props[n]["doubtful"] is False and props[n]["doubt"] is None for n in placed[1:])
    # a car carried through a held coupling from the doubtful one is doubtful too (not one with its own points)
    from workbench.files.solution import doubts_of

    idx = {c["number"]: c["index"] for c in sol["carriages"]}
    chained = dict(sol, links=[{"front": idx[placed[0]], "rear": idx[placed[1]]}],
                   carriages=[dict(c, status="carried") if c["number"] == placed[1] else c for c in sol["carriages"]])
    assert set(doubts_of(chained)) == {placed[0], placed[1]} and f"car {placed[0]}" in doubts_of(chained)[placed[1]]
    assert set(doubts_of(dict(chained, carriages=sol["carriages"]))) == {placed[0]}
    del sol["warnings"][-1]
    assert not any(r["doubt"] for r in report_stage.carriage_rows(incident, sol))
    assert not any(f.startswith("Doubtful") for f in report_stage.findings(incident, sol))


def test_the_report_names_the_georegistrations_priors():
    """The priors the georegistration used (cameras.json georegistration.priors: EXIF GPS, compass) and those it
    left out are one line under the facts; none, no line."""
    from workbench.report.report_stage import priors_text

    g = {"priors": {"used": ["centre", "heading"],
                    "centre": {"source": "exif_gps", "sigma_enu_m": [3.54, 3.54, 15.0]},
                    "heading": [{"photo": "p1.jpg", "azimuth_deg": 123.4, "sigma_deg": 15.0}],
                    "notes": ["p2.jpg: GPSImgDirection 80.0 deg is magnetic (GPSImgDirectionRef = M); not used"]}}
    t = priors_text(g)
    assert "the photos' EXIF GPS (±3.5 m, 1σ)" in t and "p1.jpg's compass 123° (±15°)" in t
    assert "Not used: p2.jpg: GPSImgDirection 80.0 deg is magnetic" in t
    assert priors_text({}) is None and priors_text({"priors": {"used": [], "notes": []}}) is None


def test_renders_read_ahead_are_the_same(incident, tmp_path):
    """The render stage's work ahead (the runner does it while the correspond stage runs, and stops it at the stage's
    turn): with all of it done (the carriages' models, the terrain layers and their shading), or only up to the
    terrain layer, the stage draws every picture the same, to the pixel."""
    from workbench.render.ahead import shaded_ahead

    pictures = sorted(p.name for p in incident.stage_dir("render").glob("*.png"))
    assert len(pictures) >= 8
    for how in ("all", "up to the terrain"):
        work = tmp_path / how.replace(" ", "_")
        shutil.copytree(incident.root, work)
        project = Project(work)
        with pytest.MonkeyPatch.context() as mp:
            for k, v in SMALL.items():
                mp.setattr(render_stage, k, v)
            steps = render_stage.ahead(project)
            for _ in steps:
                if how != "all" and "terrain" in render_stage._AHEAD.get("layers", {}):
                    break
            layers = dict(render_stage._AHEAD["layers"])
            assert render_stage._AHEAD["root"] == project.root and layers["terrain"] is not None
            assert (len(layers) == 3) == (how == "all")
            assert (shaded_ahead(layers["terrain"]) is not None) == (how == "all")
            render_stage.run_render(project, lambda f, m="": None)
        assert not render_stage._AHEAD  # taken by the stage
        for name in pictures:
            a = np.asarray(Image.open(incident.stage_dir("render") / name))
            b = np.asarray(Image.open(project.stage_dir("render") / name))
            assert a.shape == b.shape and np.array_equal(a, b), (how, name)


def test_figures_beside_come_back_in_order():
    """The report's figures drawn in two processes beside the stage: the results in the jobs' order, and a job's error
    raised once both processes have ended."""
    from workbench.report.beside import run_beside

    assert run_beside([(pow, (i, 2)) for i in range(7)])() == [i * i for i in range(7)]
    assert run_beside([(pow, (3, 2))], processes=4)() == [9]
    with pytest.raises(ZeroDivisionError):
        run_beside([(pow, (2, 2)), (divmod, (1, 0)), (pow, (3, 2))])()
