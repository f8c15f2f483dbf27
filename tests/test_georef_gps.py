"""EXIF GPS and compass as priors on the central routes (issue 17): a synthetic phone photo with its GPS (5 m
noise, GPSHPositioningError) and 2 map points is placed with the truth inside the stated 95 % interval; the
compass direction is used when the photo has it (true north) and not when it is magnetic; malformed GPS tags are
ignored with a warning naming the photo and the tag. The incidents are written by scripts/bench_georef_gps.py,
which runs the same check over 20 seeds. About 5 s."""

from __future__ import annotations

import importlib.util
import warnings
from pathlib import Path

import numpy as np
import piexif
import pytest

from workbench.errors import InputError
from workbench.georef.gps import GpsTagIgnored, read_gps_fix
from workbench.georef.options import GeorefOptions
from workbench.georef.priors import central_priors
from workbench.project import Project

REPO = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("bench_georef_gps", REPO / "scripts" / "bench_georef_gps.py")
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)

CHI2_3_95 = 7.8147


def _photo(root: Path) -> Path:
    return root / "photos" / "single" / "phone.jpg"


def _set_gps(path: Path, **raw) -> None:
    """Overwrite GPS tags of a photo with raw piexif values (by tag name), e.g. a zero-denominator rational."""
    d = piexif.load(str(path))
    for name, value in raw.items():
        tag = next(t for t, info in piexif.TAGS["GPS"].items() if info["name"] == name)
        if value is None:
            d["GPS"].pop(tag, None)
        else:
            d["GPS"][tag] = value
    piexif.insert(piexif.dump(d), str(path))


def test_gps_tags_are_read(tmp_path):
    truth = bench.make_case(tmp_path / "inc", 1, compass=True)
    fix = read_gps_fix(_photo(tmp_path / "inc"))
    assert fix is not None and fix.has_position and fix.ignored == ()
    assert fix.h_error_m == pytest.approx(5.0 * np.sqrt(2.0), rel=1e-5)
    assert fix.direction_ref == "T" and fix.direction_deg == pytest.approx(truth["compass_deg"] % 360.0, abs=1e-4)
    project = Project(tmp_path / "inc")
    enu = project.frame.enu_from_wgs84(np.array([fix.lon_deg, fix.lat_deg, fix.alt_m]))
    assert np.allclose(enu, truth["gps_enu"], atol=0.01)
    pri = central_priors(project.frame, None, [("phone.jpg", _photo(tmp_path / "inc"))], GeorefOptions())
    assert pri.source == "exif_gps" and np.allclose(pri.sigma_m, [5.0, 5.0, 15.0])  # GPSHPositioningError / sqrt 2
    assert [h.azimuth_deg for h in pri.headings] == [pytest.approx(fix.direction_deg)]
    # no GPSHPositioningError: the phone default; no GPSAltitude: the height is free
    _set_gps(_photo(tmp_path / "inc"), GPSHPositioningError=None, GPSAltitude=None, GPSAltitudeRef=None)
    pri = central_priors(project.frame, None, [("phone.jpg", _photo(tmp_path / "inc"))], GeorefOptions())
    assert pri.sigma_m[0] == pri.sigma_m[1] == GeorefOptions().gps_h_sigma_m and np.isinf(pri.sigma_m[2])
    assert pri.record["centre"]["sigma_enu_m"][2] is None
    assert "phone default" in pri.record["centre"]["photos"][0]["sigma_h_from"]


@pytest.mark.parametrize("seed", [1001, 1003, 1004])
def test_single_photo_gps_and_two_map_points(tmp_path, seed):
    truth = bench.make_case(tmp_path / "inc", seed, n_points=2)
    doc, stats = bench.place(tmp_path / "inc")
    g = doc["georegistration"]
    assert doc["route"] == "single" and g["n_points"] == 2 and stats["prior_source"] == "exif_gps"
    c = bench.centre_check(doc, truth)
    assert c["d2"] < CHI2_3_95, (c, truth["gps_enu"] - truth["centre"])
    # the GPS sigma came from GPSHPositioningError, recorded in cameras.json and the statistics
    for rec in (g["priors"], stats["priors"]):
        assert rec["used"] == ["centre"] and rec["heading"] == []
        assert rec["centre"]["sigma_enu_m"] == pytest.approx([5.0, 5.0, 15.0])
        assert rec["centre"]["photos"][0]["sigma_h_from"] == "GPSHPositioningError / sqrt(2)"
    # the stated centre is not tighter than the points and the GPS can make it: metres, not centimetres
    assert 1.0 < np.linalg.norm(c["sigma"]) < 40.0


def test_compass_prior_is_used_and_one_point_places_the_photo(tmp_path):
    truth = bench.make_case(tmp_path / "two", 1002, n_points=2, compass=True)
    doc, stats = bench.place(tmp_path / "two")
    rec = doc["georegistration"]["priors"]
    assert rec["used"] == ["centre", "heading"] and len(rec["heading"]) == 1
    h = rec["heading"][0]
    assert h["photo"] == "phone.jpg" and h["ref"] == "T" and h["sigma_deg"] == GeorefOptions().compass_sigma_deg
    assert h["prior_deg"] == pytest.approx(truth["compass_deg"] % 360.0, abs=1e-4)
    # the fitted heading is the photo's: the azimuth of its optical axis
    axis = np.asarray(doc["views"][0]["cam_from_world"])[2, :3]
    assert h["fitted_deg"] == pytest.approx(np.degrees(np.arctan2(axis[0], axis[1])) % 360.0, abs=1e-6)
    assert abs((h["fitted_deg"] - truth["heading_deg"] + 180.0) % 360.0 - 180.0) < 3.0
    # one map point, GPS (with altitude) and the compass: 6 equations for 6 unknowns
    truth = bench.make_case(tmp_path / "one", 1003, n_points=1, compass=True)
    doc, stats = bench.place(tmp_path / "one")
    assert doc["georegistration"]["n_points"] == 1 and stats["priors"]["used"] == ["centre", "heading"]
    assert bench.centre_check(doc, truth)["d2"] < CHI2_3_95
    # one point and GPS without the compass cannot place it: the error says what else would
    bench.make_case(tmp_path / "nocompass", 1003, n_points=1)
    with pytest.raises(InputError, match="GPSImgDirection"):
        bench.place(tmp_path / "nocompass")


def test_magnetic_compass_is_not_used(tmp_path):
    bench.make_case(tmp_path / "inc", 1004, n_points=2, compass=True)
    _set_gps(_photo(tmp_path / "inc"), GPSImgDirectionRef=b"M")
    doc, stats = bench.place(tmp_path / "inc")
    rec = stats["priors"]
    assert rec["used"] == ["centre"] and rec["heading"] == []
    assert any("magnetic" in n and "phone.jpg" in n and "declination" in n for n in rec["notes"])


def test_malformed_gps_tags_are_ignored_with_a_warning(tmp_path):
    root = tmp_path / "inc"
    bench.make_case(root, 1005, n_points=2, compass=True)
    photo = _photo(root)
    # NaN positioning error (0/0) and an impossible direction: warned, the rest still used
    _set_gps(photo, GPSHPositioningError=(0, 0), GPSImgDirection=(4000, 1))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fix = read_gps_fix(photo)
    msgs = [str(w.message) for w in caught if issubclass(w.category, GpsTagIgnored)]
    assert any("phone.jpg" in m and "GPSHPositioningError" in m for m in msgs)
    assert any("phone.jpg" in m and "GPSImgDirection" in m for m in msgs)
    assert fix.has_position and fix.h_error_m is None and fix.direction_deg is None
    doc, stats = bench.place(root)
    assert stats["priors"]["used"] == ["centre"]
    assert stats["priors"]["centre"]["sigma_enu_m"][0] == GeorefOptions().gps_h_sigma_m
    assert any("GPSHPositioningError" in w for w in stats["warnings"])
    # a latitude with a zero denominator, a minute of 75, a reference 'X', text for the altitude: never a crash
    for bad in ({"GPSLatitude": ((40, 1), (52, 0), (0, 1))}, {"GPSLongitude": ((73, 1), (75, 1), (0, 1))},
                {"GPSLatitudeRef": b"X"}, {"GPSAltitude": (0, 0)}, {"GPSImgDirectionRef": b"Q"}):
        bench.make_case(tmp_path / "b", 1005, n_points=2, compass=True)
        _set_gps(_photo(tmp_path / "b"), **bad)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fix = read_gps_fix(_photo(tmp_path / "b"))
        tag = next(iter(bad))
        assert any(tag in str(w.message) and "phone.jpg" in str(w.message) for w in caught), (bad, caught)
        assert fix is not None
        if tag.startswith(("GPSLatitude", "GPSLongitude")):
            assert not fix.has_position
            # no position prior left and only 2 points: a clear error, not a crash
            with pytest.raises(InputError, match="control point"):
                bench.place(tmp_path / "b")
        else:
            bench.place(tmp_path / "b")
        import shutil
        shutil.rmtree(tmp_path / "b")


def test_panorama_heading_prior_is_on_its_own_photo():
    """In a panorama rig the compass of a photo constrains that photo's optical axis (cam_from_rig included)."""
    from scipy.spatial.transform import Rotation

    from workbench.core.camera import CameraIntrinsics
    from workbench.files.control_points import ControlPoint
    from workbench.files.panorama import RigView
    from workbench.georef.central import solve_central
    from workbench.georef.options import HeadingPrior

    rng = np.random.default_rng(3)
    R_rig, centre, heading = bench._camera(rng)  # rig = the first photo's frame
    turn = Rotation.from_euler("y", -40.0, degrees=True).as_matrix()  # the second photo turned 40 deg right
    intr = CameraIntrinsics(width=1600, height=1200, fx=1150.0, fy=1150.0, cx=799.5, cy=599.5)
    views = [RigView("a.jpg", intr, np.eye(3)), RigView("b.jpg", intr, turn)]
    cps = []
    for k, (view, u) in enumerate(((0, 500.0), (1, 1100.0))):
        R_cam = np.asarray(views[view].cam_from_rig) @ R_rig
        ray = R_cam.T @ intr.rays(np.array([[u, 700.0]]))[0]
        X = centre + 60.0 * ray / np.linalg.norm(ray)
        uv = intr.project(((X - centre) @ R_cam.T)[None])[0]
        cps.append(ControlPoint(f"p{k}", X, 0.05, {views[view].name: uv}))
    axis_b = (turn @ R_rig)[2]
    heading_b = float(np.degrees(np.arctan2(axis_b[0], axis_b[1])) % 360.0)
    assert abs((heading_b - heading - 40.0 + 180.0) % 360.0 - 180.0) < 5.0
    res = solve_central(views, cps, prior_centre=centre + [3.0, -4.0, 5.0], prior_sigma_m=np.array([5.0, 5.0, 15.0]),
                        heading_priors=[HeadingPrior(1, heading_b, 15.0, "b.jpg")], opts=GeorefOptions())
    h = res.stats["heading_priors"][0]
    assert h["photo"] == "b.jpg" and abs(h["residual_deg"]) < 8.0  # photo a looks 40 deg away
    assert np.linalg.norm(res.centre_enu - centre) < 3.0 * np.linalg.norm(res.stats["sigma_centre_m"])
    # a heading prior 60 deg off is outvoted by the two points (robust loss), not followed
    res = solve_central(views, cps, prior_centre=centre, prior_sigma_m=np.array([5.0, 5.0, 15.0]),
                        heading_priors=[HeadingPrior(1, heading_b + 60.0, 15.0, "b.jpg")], opts=GeorefOptions())
    assert abs(res.stats["heading_priors"][0]["residual_deg"] + 60.0) < 10.0
