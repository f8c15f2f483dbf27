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


def test_utm_codes_known_without_pyproj_are_what_pyproj_says():
    """Every EPSG code the settings accept without pyproj (``core.crs.UTM_EPSG_RANGES``) is, in pyproj's database, a
    projected CRS in metres, as :func:`parse_projected_crs` requires; the neighbours of each range are not taken
    on trust; other spellings and CRSs still go to pyproj (and are refused where pyproj refuses them)."""
    from pyproj import CRS

    from workbench.core.crs import UTM_EPSG_RANGES, check_projected_crs, is_utm_epsg, parse_projected_crs

    for lo, hi in UTM_EPSG_RANGES:
        for code in range(lo, hi + 1):
            assert is_utm_epsg(f"EPSG:{code}") and is_utm_epsg(f"epsg:{code}")
            crs = parse_projected_crs(f"EPSG:{code}")  # (raises unless projected, in metres)
            assert "UTM zone" in crs.name and crs.to_epsg() == code
        assert not is_utm_epsg(f"EPSG:{lo - 1}") and not is_utm_epsg(f"EPSG:{hi + 1}")
    for other in ("EPSG:4326", "EPSG:3857", "EPSG:27700", " EPSG:32618", "EPSG::32618", "EPSG:32618x", 32618,
                  "urn:ogc:def:crs:EPSG::32618", CRS.from_epsg(32618).to_wkt()):
        assert not is_utm_epsg(other)
    check_projected_crs("EPSG:27700")  # British National Grid: projected, metres (through pyproj)
    check_projected_crs(" EPSG:32618")  # (pyproj's spelling rules)
    for bad in ("EPSG:4326", "EPSG::32618", "EPSG:99999999", "not a crs"):
        with pytest.raises(SettingsError, match="location.crs"):
            check_projected_crs(bad)


def test_settings_with_a_utm_zone_load_without_pyproj(tmp_path: Path):
    """Loading an incident's settings whose CRS is a UTM zone's EPSG code does not import pyproj (about 45 ms of
    every command's start: docs/performance.md); another CRS is checked by pyproj."""
    import subprocess
    import sys

    p = Project.create(tmp_path / "inc", lat=40.0, lon=-75.0)
    code = ("import sys; from workbench.core.settings import load_settings; "
            "s = load_settings(sys.argv[1]); print(s.location.crs, 'pyproj' in sys.modules)")
    run = subprocess.run([sys.executable, "-c", code, str(p.settings_path)], capture_output=True, text=True,
                         check=True)
    assert run.stdout.split() == ["EPSG:32618", "False"]
    text = p.settings_path.read_text()
    assert 'crs = "EPSG:32618"' in text
    p.settings_path.write_text(text.replace('crs = "EPSG:32618"', 'crs = "EPSG:27700"'))
    run = subprocess.run([sys.executable, "-c", code, str(p.settings_path)], capture_output=True, text=True,
                         check=True)
    assert run.stdout.split() == ["EPSG:27700", "True"]
