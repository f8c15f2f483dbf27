"""The automatic finder only where it can work (issue 16): ``[correspond] finder = "off"`` scans no photo and
keeps the hand picks; in ``auto``, the cars whose type has no reference imagery are not searched and are named
for hand picks with the reason."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from workbench.correspond import search
from workbench.correspond import stage as cs
from workbench.correspond.match import MatchOptions
from workbench.pipeline import STAGES
from workbench.project import Project
from workbench.rolling_stock import get_type
from workbench.runner import Runner


def _incident(root: Path, consist: list[tuple[str, str]], finder: str | None, picks: list[dict]) -> Project:
    """A hand-made incident: two small photos (noise), the consist, the incident's hand picks."""
    root.mkdir(parents=True)
    cars = []
    for i, (number, type_id) in enumerate(consist):
        cars.append(f'[[consist]]\nnumber = "{number}"\ntype = "{type_id}"\n'
                    + ('coupling_to_next = "held"\n' if i < len(consist) - 1 else ""))
    (root / "project.toml").write_text(
        '[incident]\nname = "finder test"\ndate = 2024-05-01\n\n'
        '[location]\nlat = 40.878\nlon = -73.9215\ncrs = "EPSG:32618"\n\n'
        + "\n".join(cars)
        + ("" if finder is None else f'\n[correspond]\nfinder = "{finder}"\n'), encoding="utf-8")
    photos = root / "photos" / "panorama"
    photos.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for k in range(2):
        Image.fromarray(rng.integers(90, 160, (240, 320, 3), dtype=np.uint8)).save(photos / f"pano_0{k}.jpg")
    (root / "correspondences.json").write_text(json.dumps({"observations": picks}), encoding="utf-8")
    return Project(root)


PICKS = [{"carriage": "6100", "point": "coupler_front", "view": "pano_00.jpg", "uv": [100.0, 150.0]},
         {"carriage": "6100", "point": "coupler_rear", "view": "pano_01.jpg", "uv": [210.5, 140.25],
          "sigma_px": 2.0}]


def _no_scan(monkeypatch):
    """Every way the stage could read a photo's pixels or run the finder fails the test."""
    def refuse(*a, **k):
        raise AssertionError("the finder ran or a photo was decoded")

    for name in ("automatic", "photo_intrinsics", "_read_rgb", "_car_references"):
        monkeypatch.setattr(cs, name, refuse)


def test_finder_off_keeps_the_hand_picks_and_scans_no_photo(tmp_path, monkeypatch):
    project = _incident(tmp_path / "inc", [("6100", "shoreliner"), ("4126", "p32ac-dm")], "off", PICKS)
    stale = project.stage_dir("correspond") / "references"
    stale.mkdir(parents=True)
    (stale / "references.json").write_text("{}")  # an earlier automatic run's: not this run's
    _no_scan(monkeypatch)
    res = cs.run_correspond(project, lambda f, m="": None)
    out = json.loads(res.outputs["correspondences"].read_text())
    assert [(o["carriage"], o["point"], o["view"], o["uv"], o["source"]) for o in out["observations"]] == \
        [(p["carriage"], p["point"], p["view"], p["uv"], "manual") for p in PICKS]
    assert out["observations"][1]["sigma_px"] == 2.0
    assert [n["carriage"] for n in out["needs_manual"]] == ["4126"]  # 6100 has picks
    assert "finder = 'off'" in out["needs_manual"][0]["reason"]
    assert "references" not in res.outputs and not stale.exists()
    assert res.stats["finder"] == "off" and res.stats["photos"] == {} and res.stats["n_sift"] == 0
    assert res.stats["not_searched"] == ["6100", "4126"] and res.stats["intrinsics"] is None


def test_finder_off_through_the_runner(tmp_path, monkeypatch):
    """The runner records the stage without a references output; a bad pick still fails, naming the item."""
    project = _incident(tmp_path / "inc", [("6100", "shoreliner")], "off", PICKS)
    _no_scan(monkeypatch)
    Runner(project, STAGES).run(only=["inputs", "correspond"])
    state = json.loads((project.root / "out" / "state.json").read_text())
    assert state["correspond"]["status"] == "done"
    assert set(state["correspond"]["outputs"]) == {"stats", "correspondences"}
    out = json.loads(cs.output_path(project).read_text())
    assert len(out["observations"]) == 2 and out["needs_manual"] == []
    bad = [{**PICKS[0], "point": "no_such_point"}]
    (project.root / "correspondences.json").write_text(json.dumps({"observations": bad}))
    with pytest.raises(Exception, match="no_such_point"):
        cs.run_correspond(project, lambda f, m="": None)


def test_types_without_reference_imagery_are_not_searched(tmp_path, monkeypatch):
    """finder = auto, but no car of the consist has reference imagery: no photo is scanned either."""
    for tid in ("keikyu-n1000", "meitetsu-3500", "dot-111"):
        assert not get_type(tid).has_reference_imagery
    for tid in ("shoreliner", "p32ac-dm", "amfleet-i", "acs-64"):
        assert get_type(tid).has_reference_imagery
    picks = [{"carriage": "1001", "point": "coupler_front", "view": "pano_00.jpg", "uv": [100.0, 150.0]}]
    project = _incident(tmp_path / "inc", [("1001", "keikyu-n1000"), ("111001", "dot-111")], None, picks)
    assert project.settings.correspond.finder.value == "auto"
    _no_scan(monkeypatch)
    res = cs.run_correspond(project, lambda f, m="": None)
    out = json.loads(res.outputs["correspondences"].read_text())
    assert len(out["observations"]) == 1
    assert [n["carriage"] for n in out["needs_manual"]] == ["111001"]
    assert "'dot-111' has no reference imagery" in out["needs_manual"][0]["reason"]
    assert res.stats["finder"] == "auto" and res.stats["not_searched"] == ["1001", "111001"]


def test_a_mixed_consist_searches_only_the_cars_with_reference_imagery(tmp_path, monkeypatch):
    """A car with reference imagery beside one without: only the first gets references and is matched; the
    other is named with the reason (and the two blank photos show neither)."""
    project = _incident(tmp_path / "inc", [("6100", "shoreliner"), ("1001", "keikyu-n1000")], "auto", [])
    searched = []
    real = cs._car_references

    def spy(project, consist, types, *a, **k):
        refs, ref_cache, untextured = real(project, consist, types, *a, **k)
        searched.extend(refs)
        return refs, ref_cache, untextured

    monkeypatch.setattr(cs, "_car_references", spy)
    opts = MatchOptions(workers=1, tilts=((1.0, 1.0),), end_tilts=((1.0, 1.0),), photo_upsample=1.0)  # quick
    res = cs.run_correspond(project, lambda f, m="": None, opts)
    out = json.loads(res.outputs["correspondences"].read_text())
    assert searched == ["6100"]
    reasons = {n["carriage"]: n["reason"] for n in out["needs_manual"]}
    assert set(reasons) == {"6100", "1001"}
    assert "no face matched" in reasons["6100"] and "'keikyu-n1000' has no reference imagery" in reasons["1001"]
    assert set(res.stats["photos"]) == {"pano_00.jpg", "pano_01.jpg"}  # the photos were scanned, for 6100
    refs = json.loads(res.outputs["references"].read_text())
    assert set(refs) == {"6100"}


def test_pose_search_skips_cars_without_references(monkeypatch):
    """chain_search looks only for the cars it has references of (the others have no reference imagery)."""
    asked = []
    monkeypatch.setattr(search, "anchors_of", lambda k, consist, *a, **kw: [search.Anchor(
        end="front", world=np.zeros(3), neighbour=consist[k][0] + "-n")])
    monkeypatch.setattr(search, "search_car", lambda photo, number, *a, **k: asked.append(number) or [])
    monkeypatch.setattr(search, "face_reference_cached",
                        lambda *a, **k: pytest.fail("a reference was built for a car without reference imagery"))
    consist = [("6100", "shoreliner", "held"), ("1001", "keikyu-n1000", None)]
    types = {"6100": get_type("shoreliner"), "1001": get_type("keikyu-n1000")}
    by_number = {"6100": {f: object() for f in search.FACES}}
    search.chain_search(None, [], consist, types, by_number, np.eye(4), None, MatchOptions(), {})
    assert asked == ["6100"]
