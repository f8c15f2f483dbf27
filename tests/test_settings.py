"""Settings validation: unknown keys and bad values name the file, the key and the value."""

import datetime as dt
from pathlib import Path

import pytest

from workbench.core.settings import load_settings, parse_settings
from workbench.errors import SettingsError
from workbench.project import Project


def good() -> dict:
    return {
        "incident": {"name": "test", "date": dt.date(2013, 12, 1)},
        "location": {"lat": 40.878, "lon": -73.9215, "crs": "EPSG:32618"},
        "consist": [{"number": "1", "type": "shoreliner", "coupling_to_next": "held"},
                    {"number": "2", "type": "shoreliner"}],
    }


def test_good_settings_and_defaults():
    s = parse_settings(good())
    assert s.solver.slack_held_m == 0.05 and s.camera.source.value == "exif"
    assert [c.number for c in s.consist] == ["1", "2"]


@pytest.mark.parametrize("mutate, expect", [
    (lambda d: d["solver"].update(slak_held_m=0.1) if "solver" in d else d.update(solver={"slak_held_m": 0.1}),
     "unknown key 'solver.slak_held_m'"),
    (lambda d: d["location"].update(crs="EPSG:4326"), "'location.crs' = 'EPSG:4326'"),
    (lambda d: d["location"].update(lat=123.0), "'location.lat' = 123.0"),
    (lambda d: d.update(consist=[]), "consist is empty"),
    (lambda d: d["consist"][0].pop("coupling_to_next"), "consist[0].coupling_to_next is missing"),
    (lambda d: d["consist"][1].update(coupling_to_next="held"), "the last car (2) has no next car"),
    (lambda d: d["consist"][0].update(coupling_to_next="snapped"), "'consist[0].coupling_to_next' = 'snapped'"),
    (lambda d: d["consist"][1].update(number="1"), "appears twice"),
    (lambda d: d.update(camera={"source": "calibrated"}), "needs profile"),
    (lambda d: d["incident"].pop("name"), "missing key 'incident.name'"),
    (lambda d: d.update(terrain={"dem_vertical_accuracy_m": -1}), "'terrain.dem_vertical_accuracy_m' = -1"),
])
def test_bad_settings(mutate, expect):
    d = good()
    mutate(d)
    with pytest.raises(SettingsError) as err:
        parse_settings(d, "projects/x/project.toml")
    assert expect in str(err.value)
    assert str(err.value).startswith("projects/x/project.toml: ")


def test_template_written_by_init_is_valid(tmp_path: Path):
    p = Project.create(tmp_path / "inc", lat=40.0, lon=-75.0)
    s = load_settings(p.settings_path)
    assert s.location.lat == 40.0 and s.location.crs == "EPSG:32618"
    with pytest.raises(SettingsError, match="already exists"):
        Project.create(tmp_path / "inc")


def test_toml_syntax_error_names_file(tmp_path: Path):
    f = tmp_path / "project.toml"
    f.write_text("[incident\nname = 'x'\n")
    with pytest.raises(SettingsError, match=f"{f}: not valid TOML"):
        load_settings(f)
    with pytest.raises(SettingsError, match="settings file not found"):
        load_settings(tmp_path / "nope" / "project.toml")
