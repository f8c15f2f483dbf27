"""A mesh type through an incident (issue 16): the shoreliner's own model exported as a CAD tool would (GLB in
millimetres, glTF's axes, origin at the rear coupler), given as the incident's ``rolling_stock/shoreliner.toml``
with its marked points by ``xyz``: the hand-written incident (known cameras, hand picks, no photo files) solves
as with the parametric type, and the export draws the mesh."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from conftest import hand_picked_incident

from workbench.pipeline import STAGES
from workbench.project import Project
from workbench.rolling_stock import get_type
from workbench.runner import Runner


def _cad_type(folder: Path) -> None:
    """rolling_stock/shoreliner.toml: a mesh type of the shipped shoreliner's mesh, exported in mm and glTF axes."""
    ct = get_type("shoreliner")
    m = ct.mesh(textured=False)
    V = np.asarray(m.vertices).copy()
    V[:, 0] += ct.length_m / 2  # origin at the rear coupler face
    cad = trimesh.Trimesh(V[:, [1, 2, 0]] * 1000.0, m.faces, process=False)  # glTF: (x, y, z) = (left, up, forward)
    cad.visual.face_colors = np.tile([180, 185, 190, 255], (len(m.faces), 1))
    folder.mkdir()
    cad.export(folder / "shoreliner_cad.glb")
    T = [[0, 0, 1, -ct.length_m / 2], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]
    lines = ['id = "shoreliner"', 'name = "Shoreliner (CAD export)"', "[mesh]", 'file = "shoreliner_cad.glb"',
             "unit_m = 0.001", f"carriage_from_file = {T!r}", "[dimensions]",
             f"length_over_couplers_m = {ct.length_m}", f"coupler_height_m = {ct.spec.dimensions.coupler_height_m}"]
    for n, p in ct.marked_points.items():
        lines += ["[[marked_points]]", f'name = "{n}"', f"xyz = {[round(float(v), 6) for v in p]!r}",
                  "faces = " + json.dumps(list(ct.marked_point_faces[n]))]
    (folder / "shoreliner.toml").write_text("\n".join(lines) + "\n", encoding="utf-8")


@pytest.fixture(scope="module")
def incident(tmp_path_factory) -> Path:
    """The hand-written incident (conftest's hand-picked one: known cameras, true picks with 1 px of noise) without
    its photos, of the CAD type; ``gen`` beside it is the generated incident, with its photos (read-only)."""
    work = tmp_path_factory.mktemp("mesh_type")
    gen = work / "gen"
    gen.symlink_to(hand_picked_incident(tmp_path_factory), target_is_directory=True)
    root = work / "inc"
    shutil.copytree(gen, root, ignore=shutil.ignore_patterns("out", "photos", "masks"))
    _cad_type(root / "rolling_stock")
    return root


def test_a_mesh_type_solves_and_exports(incident):
    p = Project(incident)
    types = p.carriage_types()
    assert all(t.is_mesh_type for t in types.values())
    Runner(p, STAGES).run(only=["inputs", "terrain", "georef", "solve", "export"])
    sol = json.loads((incident / "out" / "solve" / "solution.json").read_text())
    truth = {c["number"]: c for c in json.loads((incident / "truth" / "ground_truth.json").read_text())["carriages"]}
    solved = [c for c in sol["carriages"] if c["status"] == "solved"]
    assert len(solved) >= 2
    for c in solved:
        err = np.asarray(c["body_centre_enu"]) - np.asarray(truth[c["number"]]["body_centre_enu"])
        ci = np.asarray(c["ci95_body_centre_m"])
        assert np.all(np.abs(err) <= 1.75 * ci + 0.02), (c["number"], err, ci)
        assert c["rms_px"] < 3.0
    scene = trimesh.load(incident / "out" / "export" / "scene.glb", force="scene")
    cars = [g for n, g in scene.geometry.items() if n.startswith("shoreliner ")]
    assert len(cars) == len(solved) and all(len(g.faces) == len(types["6100"].mesh(textured=False).faces)
                                              for g in cars)


def test_the_picker_shows_a_mesh_type(incident, tmp_path):
    """The picker's page for an incident of mesh types: each face is the model seen from outside it (no livery to
    crop), with its marked points where they project; the pixel <-> carriage-frame mapping the view states holds."""
    from workbench.picker.server import PickerState, _reference

    root = tmp_path / "with_photos"
    shutil.copytree(incident.parent / "gen", root, ignore=shutil.ignore_patterns("out", "rolling_stock"))
    shutil.copytree(incident / "rolling_stock", root / "rolling_stock")
    p = Project(root)
    doc = PickerState(p).document()
    ct = p.carriage_types()["6100"]
    for car in doc["cars"]:
        assert set(car["faces"]) >= {"left", "right", "front", "rear"}, car["faces"].keys()
        for face, f in car["faces"].items():
            ref = _reference(p, car["number"], face)
            assert ref.image.shape[:2] == (f["height"], f["width"]) and ref.image.std() > 10  # the model is drawn
            view = np.cross(ref.axis_u_m, ref.axis_v_m)
            view /= np.linalg.norm(view)
            for name, (u, v) in ref.points.items():
                xyz = ct.marked_points[name]
                back = ref.origin_m + (u + 0.5) * ref.axis_u_m + (v + 0.5) * ref.axis_v_m
                d = back - xyz
                assert np.linalg.norm(d - (d @ view) * view) < 1e-9, (face, name)  # the same point, along the view
                assert 0 <= u < f["width"] and 0 <= v < f["height"]


def test_a_changed_mesh_file_makes_the_stages_stale(incident, tmp_path):
    from workbench.pipeline import stage

    root = tmp_path / "inc"
    shutil.copytree(incident, root, ignore=shutil.ignore_patterns("out"))
    p = Project(root)
    before = stage("solve").inputs(p)
    assert any(k.endswith(":shoreliner_cad.glb") for k in before)
    glb = root / "rolling_stock" / "shoreliner_cad.glb"
    assert before[next(k for k in before if k.endswith(":shoreliner_cad.glb"))] == glb.resolve()
