"""The typed readers of workbench/files/: what they accept, and errors that name the file and the entry."""

from __future__ import annotations

import json

import numpy as np
import pytest

from workbench.core.frames import SceneFrame
from workbench.errors import InputError
from workbench.files.cameras import parse_cameras, read_cameras, write_cameras
from workbench.files.panorama import parse_panorama
from workbench.files.solution import parse_solution

INTR = {"width": 800, "height": 600, "fx": 700.0, "fy": 700.0, "cx": 399.5, "cy": 299.5}


def _view(name="a.jpg", **kw):
    return {"name": name, "intrinsics": dict(INTR), "cam_from_world": np.eye(4).tolist(), **kw}


def test_cameras_round_trip_and_focal_known(tmp_path):
    doc = {"route": "single", "views": [_view(), _view("b.jpg", focal_known=False)]}
    path = write_cameras(tmp_path / "cameras.json", doc)
    cams = read_cameras(path)
    assert cams.names == ["a.jpg", "b.jpg"] and cams.focal_unknown == ["b.jpg"]
    assert cams["a.jpg"].focal_known and np.allclose(cams["a.jpg"].center_enu, 0)
    assert "b.jpg" in cams and "c.jpg" not in cams
    entry = cams["b.jpg"].entry()
    assert entry["focal_known"] is False and entry["center_enu"] == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("bad, needle", [
    ({"route": "single", "views": [_view(focal_known="no")]}, "views[0] ('a.jpg').focal_known = 'no'"),
    ({"route": "single", "views": [_view(), _view()]}, "views[1] ('a.jpg'): the name is used twice"),
    ({"route": "nowhere", "views": [_view()]}, "route = 'nowhere'"),
    ({"route": "single", "views": [_view(center_enu=[1, [2], 3])]}, "views[0] ('a.jpg').center_enu"),
    ({"route": "single", "views": [_view(cam_from_world=(2 * np.eye(4)).tolist())]}, "not a rotation"),
])
def test_cameras_errors_name_the_entry(bad, needle, tmp_path):
    with pytest.raises(InputError) as e:
        parse_cameras(bad, tmp_path / "cameras.json")
    assert needle in str(e.value) and "cameras.json" in str(e.value)


def test_a_bad_cameras_file_is_not_written(tmp_path):
    path = tmp_path / "cameras.json"
    path.write_text("{}")
    with pytest.raises(InputError):
        write_cameras(path, {"route": "single", "views": []})
    assert path.read_text() == "{}"


def test_panorama_model_errors_name_the_file():
    src = {"name": "p.jpg", "intrinsics": dict(INTR), "cam_from_pano": np.eye(3).tolist()}
    pano = parse_panorama({"projection": "spherical", "scale": 1, "offset": [1], "width": 2, "height": 2,
                           "sources": [src]}, "panorama.json")
    assert [v.name for v in pano.sources] == ["p.jpg"]
    with pytest.raises(InputError, match="panorama.json: cannot be read as a panorama model"):
        pano.model()


FRAME = SceneFrame("EPSG:32618", 40.8781, -73.9227, 3.0)


def _solution(**car):
    c = {"number": "6100", "status": "solved", "world_from_carriage": np.eye(4).tolist(), **car}
    return {"frame": {"lat": 40.8781, "lon": -73.9227, "height_m": 3.0}, "focal_px": {"a.jpg": 701.5},
            "carriages": [c, {"number": "6101", "status": "left_out", "reason": "no points"}]}


def test_solution_reads_poses_and_left_out():
    sol = parse_solution(_solution(ci95_body_centre_m=[0.1, 0.2, float("nan")]), "solution.json", frame=FRAME,
                         numbers=["6100", "6101"])
    assert [c.number for c in sol.posed] == ["6100"] and [c.reason for c in sol.left_out] == ["no points"]
    assert sol.focal_px == {"a.jpg": 701.5}
    assert sol.posed[0].floats("ci95_body_centre_m") is None  # not all finite: not used


@pytest.mark.parametrize("doc, kw, needle", [
    ({**_solution(), "frame": {"lat": 41.0, "lon": -73.9227, "height_m": 3.0}}, {}, "the solution is stale"),
    (_solution(number="9999"), {}, "carriages[0].number = '9999' is not in the project's consist"),
    (_solution(world_from_carriage=(2 * np.eye(4)).tolist()), {}, "carriages[0].world_from_carriage: not a rigid"),
    (_solution(status="flying"), {}, "carriages[0].status = 'flying'"),
    ({**_solution(), "focal_px": {"a.jpg": -3}}, {}, "focal_px['a.jpg'] = -3"),
    ({"carriages": "none"}, {}, "no 'carriages' list"),
])
def test_solution_errors_name_the_entry(doc, kw, needle):
    with pytest.raises(InputError) as e:
        parse_solution(json.loads(json.dumps(doc)), "out/solve/solution.json", frame=FRAME,
                       numbers=["6100", "6101"], **kw)
    assert needle in str(e.value) and "solution.json" in str(e.value)
