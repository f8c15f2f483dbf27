"""Property-based fuzz of every incident-file reader (issue 20): a valid document with one part replaced by
arbitrary JSON (or a key dropped, or an unknown key added), or arbitrary JSON alone, is either read or refused
with a WorkbenchError whose message is one line naming the file, never another exception; and refusing changes
no file. The documents come from the session's small generated incident (tests/conftest.py)."""

from __future__ import annotations

import json
import math
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from workbench.errors import WorkbenchError

# JSON values, including what strict JSON has not (NaN, infinities) and what breaks naive readers (deep nesting,
# huge numbers, long strings, booleans where numbers go)
SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=30),
                    st.sampled_from(["", "1.5", "yes", "NaN", "[red]x[/red]", "../../etc/passwd", "x" * 300]))
JSON = st.recursive(SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                                     st.dictionaries(st.text(max_size=12), inner, max_size=5)),
                    max_leaves=20)
FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                      HealthCheck.too_slow], derandomize=True)


def _paths(doc, prefix=()):
    """Every path (tuple of keys / indices) into a JSON document."""
    yield prefix
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _paths(v, prefix + (i,))


def _mutated(doc, data) -> object:
    """``doc`` with one part replaced, removed, or a key added, as hypothesis chooses."""
    doc = json.loads(json.dumps(doc, default=str))  # (a TOML date becomes its string)
    paths = list(_paths(doc))
    path = data.draw(st.sampled_from(paths), label="path")
    action = data.draw(st.sampled_from(["replace", "drop", "add"]), label="action")
    if not path:
        return data.draw(JSON, label="document") if action == "replace" else doc
    parent = doc
    for p in path[:-1]:
        parent = parent[p]
    last = path[-1]
    if action == "replace":
        parent[last] = data.draw(JSON, label="value")
    elif action == "drop":
        del parent[last]
    else:
        target = parent[last]
        if isinstance(target, dict):
            target[data.draw(st.text(min_size=1, max_size=10), label="key")] = data.draw(JSON, label="value")
        elif isinstance(target, list):
            target.append(data.draw(JSON, label="value"))
    return doc


def _dump(doc) -> str:
    """JSON as a careless writer makes it (NaN and Infinity allowed, as Python writes them)."""
    return json.dumps(doc, allow_nan=True)


def _nonfinite(doc) -> bool:
    """Whether a document holds a NaN or an infinity anywhere."""
    if isinstance(doc, float):
        return not math.isfinite(doc)
    if isinstance(doc, dict):
        return any(_nonfinite(v) for v in doc.values())
    if isinstance(doc, list):
        return any(_nonfinite(v) for v in doc)
    return False


def _refused_cleanly(call, path: Path, doc) -> None:
    """``call`` reads ``path`` (holding ``doc``): it returns (and then ``doc`` held no NaN or infinity: no reader
    accepts them) or raises a one-line WorkbenchError naming the file; the file is unchanged either way."""
    before = path.read_bytes()
    try:
        call()
    except WorkbenchError as exc:
        msg = str(exc)
        assert "\n" not in msg.strip(), msg
        assert str(path.name) in msg or str(path) in msg, msg
        assert len(msg) < 3000, len(msg)
    else:
        assert not _nonfinite(doc), before[:2000]
    assert path.read_bytes() == before


@pytest.fixture(scope="module")
def docs(small_incident, tmp_path_factory):
    """A copy of the small incident with a valid document of every kind written into it."""
    from workbench.synth.control_points import true_panorama_model, true_reconstruction
    from workbench.synth.handpicks import true_correspondences, write_known_cameras

    src, _truth = small_incident
    base = tmp_path_factory.mktemp("fuzz")
    shutil.copytree(src.parent.parent, base, dirs_exist_ok=True, symlinks=True)
    root = base / "projects" / src.name
    cams = write_known_cameras(root, "panorama")
    S = np.eye(4)
    S[:3, :3] *= 0.5
    return {
        "root": root,
        "cameras": json.loads(cams.read_text()),
        "correspondences": true_correspondences(root, "panorama", sigma_px=1.0, seed=0),
        "control_points": json.loads((root / "control_points.json").read_text()),
        "camera_profile": json.loads((root / "camera_profile.json").read_text()),
        "panorama": true_panorama_model(root),
        "reconstruction": true_reconstruction(root, S),
        "settings": tomllib.loads((root / "project.toml").read_text()),
    }


def _project(root):
    from workbench.project import Project

    return Project(root)


def _read_cameras(project, path):
    from workbench.files.cameras import read_cameras
    from workbench.solve.stage import read_views

    read_views(project, path)
    read_cameras(path)


def _read_correspondences(project, path):
    from workbench.files import correspondences as manual

    points = {n: list(t.marked_points) for n, t in project.carriage_types().items()}
    manual.load(path, points=points, image_sizes={p.name: (800, 600) for p in project.photo_paths()})


def _read_control_points(project, path):
    from workbench.files.control_points import load_control_points

    load_control_points(path, project.frame)


def _read_camera_profile(project, path):
    from workbench.files.profile import read_profile

    read_profile(path)


def _read_panorama_model(project, path):
    from workbench.files.panorama import read_panorama

    read_panorama(path).model()


def _read_reconstruction(project, path):
    from workbench.files.reconstruction import read_reconstruction

    read_reconstruction(path)


JSON_READERS = {"cameras": _read_cameras, "correspondences": _read_correspondences,
                "control_points": _read_control_points, "camera_profile": _read_camera_profile,
                "panorama": _read_panorama_model, "reconstruction": _read_reconstruction}


@pytest.mark.parametrize("kind", list(JSON_READERS))
@FUZZ
@given(data=st.data())
def test_json_reader(docs, kind, data):
    project = _project(docs["root"])
    path = docs["root"] / f"fuzz_{kind}.json"
    doc = _mutated(docs[kind], data)
    path.write_text(_dump(doc))
    _refused_cleanly(lambda: JSON_READERS[kind](project, path), path, doc)


def _toml_value(v):
    """A TOML literal for a JSON-ish value (None has no TOML form: a string stands in)."""
    if v is None:
        return '"null"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, int):
        return str(v) if abs(v) < 2**63 else f'"{v}"'
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(str(k))} = {_toml_value(x)}" for k, x in v.items()) + "}"


@FUZZ
@given(data=st.data())
def test_project_toml(docs, data):
    from workbench.core.settings import load_settings

    doc = _mutated(docs["settings"], data)
    lines = []
    if isinstance(doc, dict):
        for k, v in doc.items():
            lines.append(f"{json.dumps(str(k))} = {_toml_value(v)}")
    else:
        lines.append(f"x = {_toml_value(doc)}")
    path = docs["root"] / "fuzz_project.toml"
    path.write_text("\n".join(lines) + "\n")
    _refused_cleanly(lambda: load_settings(path), path, doc)


def test_settings_refuse_strings_nan_and_infinity(docs):
    """Silently accepted before: strings for numbers and booleans, NaN and infinity (issue 20)."""
    from workbench.core.settings import load_settings

    from conftest import with_solver_lines

    text = (docs["root"] / "project.toml").read_text()
    path = docs["root"] / "strict_project.toml"
    for line, needle in [('pixel_sigma_px = "1.5"', "solver.pixel_sigma_px"),
                         ('estimate_focal = "yes"', "solver.estimate_focal"),
                         ("pixel_sigma_px = nan", "solver.pixel_sigma_px"),
                         ("slack_held_m = inf", "solver.slack_held_m"),
                         ("max_iterations = 20.5", "solver.max_iterations")]:
        path.write_text(with_solver_lines(text, line))
        with pytest.raises(WorkbenchError, match=needle.replace(".", r"\.")) as err:
            load_settings(path)
        assert str(path) in str(err.value)
    path.write_text(with_solver_lines(text, "pixel_sigma_px = 2"))  # an integer is a number
    assert load_settings(path).solver.pixel_sigma_px == 2.0


def test_json_readers_refuse_nan_and_deep_nesting(tmp_path):
    from workbench.core.io import read_json

    for text, needle in [('{"a": NaN}', "NaN"), ('{"a": -Infinity}', "Infinity"), ("[" * 100_000 + "]" * 100_000,
                                                                                       "nested too deeply"),
                         ("{" * 3 + "x" * 10_000, "not valid JSON")]:
        p = tmp_path / "f.json"
        p.write_text(text)
        with pytest.raises(WorkbenchError, match=needle) as err:
            read_json(p)
        assert len(str(err.value)) < 500


def test_a_100_megapixel_photo_is_read_and_a_larger_one_refused(tmp_path):
    """PIL's own decompression-bomb limit (89 MP) refused 100 MP phone photos; the stated limit is 120 MP."""
    from PIL import Image

    from workbench.pipeline import MAX_PIXELS, read_photo_info

    ok = tmp_path / "phone_100mp.jpg"
    Image.new("RGB", (10_000, 10_000), (90, 120, 150)).save(ok, quality=70)
    info = read_photo_info(ok)
    assert (info["width"], info["height"]) == (10_000, 10_000)
    big = tmp_path / "too_big.png"
    Image.new("L", (11_000, 11_000)).save(big)  # 121 MP
    assert 11_000 ** 2 > MAX_PIXELS
    with pytest.raises(WorkbenchError, match="120 MP limit"):
        read_photo_info(big)
