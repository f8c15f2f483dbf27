"""A relative incident (issue 16): photos and hand picks, no control points, no known cameras, no GPS.

The scene is solved in a local frame anchored at the camera and levelled from the carriages standing on their
wheels. Checked against a simulated truth (a level track, a camera held well off level): the poses in the
levelled frame, the intervals (which carry the levelling's uncertainty), and that nothing claims a place on the
Earth (no CRS or WGS84 figure; the GIS exports refused, naming the missing georeference).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from workbench.core.frames import hpr_from_rotation
from workbench.pipeline import STAGES
from workbench.project import Project
from workbench.runner import Runner
from workbench.solve.level import UprightCar, level_from_carriages
from workbench.synth.relative import levelled_truth, relative_sim, write_relative_incident



def _incident(root: Path, sim, *, focal_known: bool) -> Project:
    return Project(write_relative_incident(root, sim, focal_known=focal_known))


_sim = relative_sim
_truth_levelled = levelled_truth


@pytest.mark.parametrize("focal_known", [True, False])
def test_relative_incident_is_levelled_and_says_so(tmp_path, focal_known):
    sim = _sim(3)
    project = _incident(tmp_path / "inc", sim, focal_known=focal_known)
    assert project.georef_route() == "relative"
    Runner(project, STAGES).run(only=["inputs", "georef", "correspond", "solve"])
    cams = project.cameras()
    assert cams.relative and cams.doc["georegistration"] is None
    sol = project.solution("test")
    assert sol.relative and sol.doc["frame"]["crs"] is None
    lev = sol.doc["frame"]["levelling"]
    assert lev["method"] == "carriages" and lev["cars_used"] == [c.number for c in sim.carriages]
    L = _truth_levelled(sim)
    for car, M_true in zip(sol.carriages, sim.truth):
        rec = car.record
        assert rec["body_centre_crs"] is None and rec["body_centre_wgs84"] is None
        T = L @ M_true
        err = np.asarray(car.world_from_carriage)[:3, 3] - T[:3, 3]
        ci_pos = np.asarray(rec["ci95_position_m"])
        assert np.all(np.abs(err) <= ci_pos), (car.number, err, ci_pos)
        # scaled by the cars' dimensions: a known focal places them to a few decimetres across, an unknown one
        # leaves the range to the focal's uncertainty (metres along the line of sight, and said so)
        assert np.all(ci_pos[:2] < (1.0 if focal_known else 15.0))
        assert np.linalg.norm(err) < (0.6 if focal_known else 3.0)
        # heading, pitch and roll in the levelled frame against the truth's, inside the 95 % intervals
        h, p, r = hpr_from_rotation(np.asarray(car.world_from_carriage)[:3, :3])
        ht, pt, rt = hpr_from_rotation(T[:3, :3])
        dh = (h - ht + 180.0) % 360.0 - 180.0
        ci = rec["ci95_hpr_deg"]
        assert abs(dh) <= ci[0] and abs(p - pt) <= ci[1] and abs(r - rt) <= ci[2], (car.number, dh, p - pt, r - rt, ci)
        # the intervals hold the levelling's tilt: pitch and roll no narrower than the common track tilt's
        assert ci[1] >= 1.96 * 0.5 * 0.99 and ci[2] >= 1.96 * 0.5 * 0.99
        assert ci[1] < 3.0 and ci[2] < 3.0  # and no wider than the data allow
        # the camera was tilted about 15 deg: the provisional frame was not level, the levelled one is
    assert lev["camera_tilt_deg"] > 5.0


def test_levelling_leaves_out_a_car_on_its_side():
    tilt = np.array([[1, 0, 0], [0, math.cos(0.2), -math.sin(0.2)], [0, math.sin(0.2), math.cos(0.2)]])
    on_side = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # rolled 90 deg
    cars = [UprightCar(str(i), tilt) for i in range(3)] + [UprightCar("9", tilt @ on_side)]
    lev = level_from_carriages(cars, tilt[:, 2], tilt[:, 1], sigma_car_deg=0.5, sigma_common_deg=0.5)
    assert lev.used == ["0", "1", "2"] and lev.left_out == ["9"]
    R = lev.world_from_provisional[:3, :3]
    assert np.allclose(R @ tilt[:, 2], [0, 0, 1], atol=1e-9)
    # three cars' own tilts average: sqrt(0.5^2 / 3 + 0.5^2) deg per axis
    assert np.allclose(lev.sigma_tilt_deg, math.sqrt(0.25 / 3 + 0.25), rtol=1e-6)


def test_levelling_with_no_upright_car_falls_back_to_the_camera():
    on_side = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    lev = level_from_carriages([UprightCar("1", on_side)], np.array([0, 0, 1.0]), np.array([0, 1.0, 0]))
    assert lev.method == "camera" and lev.used == [] and "held level" in lev.note
    assert lev.sigma_tilt_deg[0] == pytest.approx(5.0)


def test_relative_incident_outputs_say_so_and_refuse_gis(tmp_path):
    """The whole run: the glTF in the local frame, the GIS exports left out with the reason, the report's first
    page saying the scene is relative; asking for GeoJSON in project.toml is refused (exit 2 from the CLI) with
    nothing written."""
    from workbench.cli import main

    project = _incident(tmp_path / "inc", _sim(3), focal_known=True)
    Runner(project, STAGES).run()
    ex = project.stage_dir("export")
    assert (ex / "scene.glb").is_file()
    assert not any((ex / n).exists() for n in ("carriages.geojson", "scene.kmz", "scene.city.json", "tiles"))
    stats = json.loads((ex / "stats.json").read_text())
    assert stats["georeference"]["frame"] == "relative" and stats["georeference"]["crs"] is None
    assert set(stats["refused"]) == {"geojson", "kmz", "cityjson", "tiles"}
    html = (project.stage_dir("report") / "report.html").read_text()
    first = html[:html.index("<h2")]
    assert "Relative reconstruction, not georeferenced" in first and "Reference point" not in first
    assert "Latitude" not in html and "Easting" not in html
    glb_before = (ex / "scene.glb").read_bytes()
    toml = project.settings_path.read_text() + '\n[export]\nformats = ["glb", "geojson"]\n'
    project.settings_path.write_text(toml)
    with pytest.raises(SystemExit) as exc:
        main(["export", str(project.root), "--force"])
    assert exc.value.code == 2
    assert not (ex / "carriages.geojson").exists() and (ex / "scene.glb").read_bytes() == glb_before


@pytest.mark.parametrize("f35_mm, warned", [(29, False), (22, True)])
def test_an_exif_focal_the_picks_contradict_is_warned(tmp_path, f35_mm, warned):
    """A photo whose EXIF focal disagrees with the picks (a cropped photo: its EXIF still describes the whole
    frame) is named in a warning with both focals; a right EXIF focal (29 mm equivalent: 1289 px on 1600 px, the
    truth 1324 px) is not."""
    import piexif

    sim = _sim(3)
    project = _incident(tmp_path / "inc", sim, focal_known=False)
    toml = project.settings_path.read_text().replace('source = "unknown"', 'source = "exif"')
    project.settings_path.write_text(toml)
    photo = project.root / "photos" / "p" / "photo.jpg"
    exif = piexif.dump({"0th": {}, "Exif": {piexif.ExifIFD.FocalLengthIn35mmFilm: f35_mm}, "GPS": {}, "1st": {}})
    Image.open(photo).save(photo, exif=exif)
    project = Project(project.root)
    Runner(project, STAGES).run(only=["inputs", "georef", "correspond", "solve"])
    doc = project.solution("test").doc
    (check,) = doc["exif_focal_check"]
    assert check["view"] == "photo.jpg" and check["sigma_focal_picks_px"] > 0
    assert abs(check["focal_picks_px"] - sim.views[0].intrinsics.fx) < 3 * check["sigma_focal_picks_px"]
    msgs = [w["message"] for w in doc["warnings"] if w.get("kind") == "exif_focal"]
    print(f"\nEXIF {f35_mm} mm: {check['focal_exif_px']:.0f} px; picks {check['focal_picks_px']:.0f} ± "
          f"{check['sigma_focal_picks_px']:.0f} px; truth {sim.views[0].intrinsics.fx:.0f} px; warned {bool(msgs)}")
    assert bool(msgs) == warned
    if warned:
        assert "photo.jpg" in msgs[0] and f"{check['focal_exif_px']:.0f} px" in msgs[0]
        assert f"{check['focal_picks_px']:.0f} ±" in msgs[0]


def test_the_pickers_overlay_draws_a_relative_scene_in_its_levelled_frame(tmp_path):
    """The picker's outlines and residuals over the photo use the solution's (levelled) frame: every residual is
    the solve's own."""
    from workbench.picker.overlay import solution_overlay

    project = _incident(tmp_path / "inc", _sim(3), focal_known=False)
    Runner(project, STAGES).run(only=["inputs", "georef", "correspond", "solve"])
    sol = project.solution("test")
    ov = solution_overlay(project, "photo.jpg")
    assert ov["available"]
    res = {(c.number, p): e for c in sol.carriages for p, e in c.record["residuals_px"]["photo.jpg"].items()}
    got = {(r["carriage"], r["point"]): r for r in ov["residuals"] if r["view"] == "photo.jpg"}
    assert set(got) == set(res)
    for k, e in res.items():
        assert np.allclose(got[k]["residual_px"], e, atol=0.01), (k, got[k], e)


def test_a_photos_gps_and_compass_place_the_levelled_scene(tmp_path):
    """A relative incident whose photo carries a phone's EXIF GPS (position, altitude, GPSHPositioningError) and a
    true-north compass direction: the levelled scene is placed on the Earth with them (frame kind ``gps``), and the
    carriages' ENU positions and headings fall inside intervals that carry the GPS's and the compass's error
    (8 incidents, 24 carriages, 6 components each: at least 90 % inside, and not all of them at a tenth of their
    width). Without the direction the scene stays relative."""
    from workbench.synth.relative import truth_gps, write_gps_exif

    inside, small, n = 0, 0, 0
    for seed in range(8):
        try:
            sim = _sim(seed)
        except RuntimeError:
            continue
        project = _incident(tmp_path / f"inc{seed}", sim, focal_known=True)
        rng = np.random.default_rng(seed)
        lon, lat, alt, az = truth_gps(sim, project.frame, rng, 5.0 / math.sqrt(2.0), 15.0, 15.0)
        write_gps_exif(project.root / "photos" / "p" / "photo.jpg", lon, lat, alt, az, h_error_m=5.0)
        Runner(project, STAGES).run(only=["inputs", "georef", "correspond", "solve"])
        sol = project.solution("test")
        fr = sol.doc["frame"]
        assert fr["kind"] == "gps" and not sol.relative and fr["placement"]["sigma_azimuth_deg"] == 15.0
        assert fr["placement"]["sigma_enu_m"][:2] == pytest.approx([5.0 / math.sqrt(2.0)] * 2)
        for car, M in zip(sol.carriages, sim.truth):
            rec = car.record
            assert rec["body_centre_wgs84"] is not None
            e = np.asarray(car.world_from_carriage)[:3, 3] - M[:3, 3]
            d = np.subtract(hpr_from_rotation(np.asarray(car.world_from_carriage)[:3, :3]), hpr_from_rotation(M[:3, :3]))
            d[0] = (d[0] + 180.0) % 360.0 - 180.0
            z = np.abs(np.concatenate([e / np.asarray(rec["ci95_position_m"]), d / np.asarray(rec["ci95_hpr_deg"])]))
            inside += int(np.sum(z <= 1.0))
            small += int(np.sum(z <= 0.1))
            n += 6
    print(f"\nGPS + compass: {inside} of {n} components inside their 95 % intervals, {small} inside a tenth")
    assert n >= 36 and inside >= 0.9 * n and small < 0.5 * n
    # a photo with a position and no direction: the scene stays relative (a heading cannot be guessed)
    sim = _sim(3)
    project = _incident(tmp_path / "nodir", sim, focal_known=True)
    lon, lat, alt, _ = truth_gps(sim, project.frame, np.random.default_rng(0), 3.5, 15.0, 15.0)
    write_gps_exif(project.root / "photos" / "p" / "photo.jpg", lon, lat, alt, None, h_error_m=5.0)
    Runner(project, STAGES).run(only=["inputs", "georef", "correspond", "solve"])
    assert project.solution("test").relative
