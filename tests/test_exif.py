"""EXIF focal prior: crafted tags for each pitfall, and real photos from ../shared/data."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import piexif
import pytest
from PIL import Image

from workbench.errors import InputError
from workbench.files.exif import exif_focal_prior
from workbench.files.exif import read_focal_px

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


def _jpeg(path: Path, w: int = 400, h: int = 300, **tags) -> Path:
    """A JPEG of w x h with the given EXIF tags (name -> value; floats become rationals)."""
    ids = {"FocalLength": (piexif.ExifIFD.FocalLength, True), "FocalLengthIn35mmFilm": (piexif.ExifIFD.FocalLengthIn35mmFilm, False),
           "FocalPlaneXResolution": (piexif.ExifIFD.FocalPlaneXResolution, True),
           "FocalPlaneYResolution": (piexif.ExifIFD.FocalPlaneYResolution, True),
           "FocalPlaneResolutionUnit": (piexif.ExifIFD.FocalPlaneResolutionUnit, False),
           "PixelXDimension": (piexif.ExifIFD.PixelXDimension, False),
           "PixelYDimension": (piexif.ExifIFD.PixelYDimension, False),
           "DigitalZoomRatio": (piexif.ExifIFD.DigitalZoomRatio, True)}
    exif, zeroth = {}, {piexif.ImageIFD.Make: b"Test"}
    for name, value in tags.items():
        if name == "Model":
            zeroth[piexif.ImageIFD.Model] = value.encode()
            continue
        tag, rational = ids[name]
        exif[tag] = (int(round(value * 10000)), 10000) if rational else int(value)
    raw = piexif.dump({"0th": zeroth, "Exif": exif, "GPS": {}, "1st": {}, "thumbnail": None})
    Image.fromarray(np.full((h, w, 3), 90, np.uint8)).save(path, exif=raw)
    return path


# 4.25 mm lens on a 6.17 mm wide sensor, 400 px wide: f = 4.25 / 6.17 * 400 = 275.53 px
F_PX = 4.25 / 6.17 * 400
RES_CM = 400 / 0.617  # px per cm


@pytest.mark.parametrize("unit,res", [(3, RES_CM), (2, RES_CM * 2.54), (4, RES_CM / 10)])
def test_focal_plane_units(tmp_path, unit, res):
    p = _jpeg(tmp_path / "a.jpg", FocalLength=4.25, FocalPlaneXResolution=res, FocalPlaneResolutionUnit=unit)
    pr = exif_focal_prior(p)
    assert pr.source == "focal_plane"
    assert abs(pr.focal_px / F_PX - 1) < 1e-3
    assert 0.01 * F_PX < pr.sigma_px < 0.05 * F_PX
    assert pr.tags["FocalPlaneResolutionUnit"] == unit and pr.warnings == ()
    assert read_focal_px(p) == pr.focal_px  # the inputs stage's reader delegates here


def test_missing_unit_means_inches(tmp_path):
    p = _jpeg(tmp_path / "a.jpg", FocalLength=4.25, FocalPlaneXResolution=RES_CM * 2.54)
    pr = exif_focal_prior(p)
    assert abs(pr.focal_px / F_PX - 1) < 1e-3
    assert any("default (inch)" in w for w in pr.warnings)


def test_wrong_unit_is_corrected_by_the_35mm_tag(tmp_path):
    # resolution written per cm but the unit says inch: the focal-plane focal is 2.54 x too small
    f35 = round(4.25 * 36 / 6.17)
    p = _jpeg(tmp_path / "a.jpg", FocalLength=4.25, FocalPlaneXResolution=RES_CM, FocalPlaneResolutionUnit=2,
              FocalLengthIn35mmFilm=f35)
    pr = exif_focal_prior(p)
    assert abs(pr.focal_px / F_PX - 1) < 1e-3
    assert any("looks wrong" in w for w in pr.warnings)
    assert 0.04 * F_PX < pr.sigma_px < 0.08 * F_PX


def test_35mm_equivalent_uses_the_long_side(tmp_path):
    land = exif_focal_prior(_jpeg(tmp_path / "l.jpg", 400, 300, FocalLengthIn35mmFilm=28))
    port = exif_focal_prior(_jpeg(tmp_path / "p.jpg", 300, 400, FocalLengthIn35mmFilm=28))
    assert land.source == port.source == "35mm_equivalent"
    assert abs(land.focal_px - 28 / 36 * 400) < 1e-9 and abs(port.focal_px - 28 / 36 * 400) < 1e-9
    assert 0.04 * land.focal_px < land.sigma_px < 0.07 * land.focal_px


def test_resized_photo_scales_the_focal_plane_focal(tmp_path):
    # tags written for 800 x 600, photo is 400 x 300
    p = _jpeg(tmp_path / "a.jpg", FocalLength=4.25, FocalPlaneXResolution=2 * RES_CM, FocalPlaneResolutionUnit=3,
              PixelXDimension=800, PixelYDimension=600)
    pr = exif_focal_prior(p)
    assert abs(pr.focal_px / F_PX - 1) < 1e-3 and any("resized" in w for w in pr.warnings)


def test_cropped_photo_drops_the_focal_plane(tmp_path):
    p = _jpeg(tmp_path / "a.jpg", FocalLength=4.25, FocalPlaneXResolution=RES_CM, FocalPlaneResolutionUnit=3,
              PixelXDimension=400, PixelYDimension=200, FocalLengthIn35mmFilm=25)
    pr = exif_focal_prior(p)
    assert pr.source == "35mm_equivalent" and any("cropped" in w for w in pr.warnings)
    assert pr.sigma_px >= 0.15 * pr.focal_px


def test_disagreeing_tags_prefer_the_35mm_equivalent(tmp_path):
    p = _jpeg(tmp_path / "a.jpg", FocalLength=4.25, FocalPlaneXResolution=RES_CM * 1.4, FocalPlaneResolutionUnit=3,
              FocalLengthIn35mmFilm=25)
    pr = exif_focal_prior(p)
    assert pr.source == "35mm_equivalent" and abs(pr.focal_px - 25 / 36 * 400) < 1e-9
    assert any("disagrees" in w for w in pr.warnings) and set(pr.candidates) == {"focal_plane", "35mm_equivalent"}


def test_digital_zoom(tmp_path):
    p = _jpeg(tmp_path / "a.jpg", FocalLength=4.25, FocalPlaneXResolution=RES_CM, FocalPlaneResolutionUnit=3,
              DigitalZoomRatio=2.0)
    pr = exif_focal_prior(p)
    assert abs(pr.focal_px / (2 * F_PX) - 1) < 1e-3 and any("DigitalZoomRatio" in w for w in pr.warnings)


@pytest.mark.parametrize("tags,why", [
    ({"FocalLength": 0.0, "FocalPlaneXResolution": RES_CM, "FocalPlaneResolutionUnit": 3}, "0 means unknown"),
    ({"FocalLength": 4.25, "FocalPlaneXResolution": RES_CM, "FocalPlaneResolutionUnit": 7}, "not a unit"),
    ({"FocalLength": 4.25, "FocalPlaneXResolution": RES_CM / 1000, "FocalPlaneResolutionUnit": 3}, "implausible"),
    ({"FocalLengthIn35mmFilm": 1}, "field of view"),
    ({"FocalLength": 4.25}, None),  # a focal in mm with no way to convert it
    ({}, None),
])
def test_nonsense_gives_no_prior(tmp_path, tags, why, caplog):
    p = _jpeg(tmp_path / "a.jpg", **tags)
    with caplog.at_level(logging.INFO, logger="workbench.files.exif"):
        assert exif_focal_prior(p) is None
    assert read_focal_px(p) is None
    if why:
        assert why in caplog.text  # the reason is reported


def test_sensor_width_given(tmp_path):
    p = _jpeg(tmp_path / "a.jpg", FocalLength=4.25)
    pr = exif_focal_prior(p, sensor_width_mm=6.17)
    assert pr.source == "sensor_width" and abs(pr.focal_px / F_PX - 1) < 1e-9
    with pytest.raises(InputError):
        exif_focal_prior(p, sensor_width_mm=-1)


def test_no_exif_and_unreadable(tmp_path):
    p = tmp_path / "plain.png"
    Image.fromarray(np.zeros((10, 10, 3), np.uint8)).save(p)
    assert exif_focal_prior(p) is None
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"\xff\xd8 broken")
    with pytest.raises(InputError, match="bad.jpg"):
        exif_focal_prior(bad)


# -- real photos -------------------------------------------------------------------------------------------
def _real(rel: str) -> Path:
    p = DATA / rel
    if not p.is_file():
        pytest.skip(f"{p} is not here")
    return p


def test_real_lund_35mm_only():
    pr = exif_focal_prior(_real("multiview/opensfm_lund/images/01.jpg"))  # 1024x768, FocalLengthIn35mmFilm 35
    assert pr.source == "35mm_equivalent" and abs(pr.focal_px - 35 / 36 * 1024) < 1e-6
    assert pr.tags["FocalLengthIn35mmFilm"] == 35


def test_real_nikon_portrait_uses_sensor_table():
    pr = exif_focal_prior(_real("stitching/skimage_pano_arches/JDW_0302.jpg"))  # 477x720, 18 mm, 35 mm eq. 27
    assert (pr.width, pr.height) == (477, 720) and pr.source == "sensor_width"
    assert abs(pr.focal_px - 18 / 23.6 * 720) < 1e-6
    assert abs(pr.candidates["35mm_equivalent"] - 27 / 36 * 720) < 1e-6  # the two agree within 2 %
    assert abs(pr.focal_px / pr.candidates["35mm_equivalent"] - 1) < 0.03


def test_real_canon_cropped_and_resized_after_tagging():
    # Canon EOS 5D photo, 1280x660, FocalPlaneXResolution written for the full 4368 px sensor width
    pr = exif_focal_prior(_real("trains/photos_wikimedia_japan_emu/meitetsu-3500/Meitetsu_3500_series_(II)_EMU_011.JPG"))
    naive = 130.0 * (4368000 / 1415) / 25.4  # what FocalLength x FocalPlaneXResolution alone would say
    assert abs(naive - 15800) < 10
    assert pr.source == "sensor_width" and abs(pr.focal_px - 130 / 35.8 * 1280) < 1e-6
    assert any("resized or cropped" in w for w in pr.warnings) and any("cropped" in w for w in pr.warnings)
    assert pr.sigma_px >= 0.15 * pr.focal_px


def test_real_synthetic_incident_focal_plane(small_incident):
    """The EXIF a generated incident's photos carry (tests/conftest.py's small incident, never projects/)."""
    root, t = small_incident
    ph = t["photos"][0]
    pr = exif_focal_prior(root / ph["photo"])
    assert pr.source == "focal_plane" and abs(pr.focal_px / ph["intrinsics"]["fx"] - 1) < 1e-4
    assert abs(pr.candidates["35mm_equivalent"] / ph["intrinsics"]["fx"] - 1) < 0.03


# -- the route a run takes (calibrated, exif, fallback) ---------------------------------------------------
def _project(tmp_path: Path, source: str, profile: bool = False):
    from workbench.project import Project

    root = tmp_path / "inc"
    (root / "photos" / "panorama").mkdir(parents=True)
    cam = f'source = "{source}"\n' + ('profile = "camera_profile.json"\n' if profile else "")
    (root / "project.toml").write_text(
        '[incident]\nname = "t"\ndate = 2024-05-01\n[location]\nlat = 40.0\nlon = -73.0\ncrs = "EPSG:32618"\n'
        '[[consist]]\nnumber = "1"\ntype = "shoreliner"\n[camera]\n' + cam)
    return Project(root)


def test_route_calibrated_scales_the_profile(tmp_path):
    from workbench.files.intrinsics import resolve_intrinsics

    project = _project(tmp_path, "calibrated", profile=True)
    prof = {"model": "brown", "source": "test", "intrinsics": {"width": 800, "height": 600, "fx": 700.0, "fy": 700.0,
                                                               "cx": 401.0, "cy": 299.0, "k1": -0.1}}
    (project.root / "camera_profile.json").write_text(json.dumps(prof))
    _jpeg(project.root / "photos" / "panorama" / "a.jpg", 400, 300)
    choice = resolve_intrinsics(project)
    assert choice.source == "calibrated" and choice.focal_known == {"a.jpg": True}
    i = choice.per_photo["a.jpg"]
    assert (i.width, i.height, i.fx, i.k1) == (400, 300, 350.0, -0.1)
    assert abs(i.cx - ((401.0 + 0.5) / 2 - 0.5)) < 1e-12  # pixel centres kept consistent
    _jpeg(project.root / "photos" / "panorama" / "b.jpg", 300, 300)  # another aspect: refused
    with pytest.raises(InputError, match="aspect"):
        resolve_intrinsics(project)


def test_route_exif_and_fallback(tmp_path):
    from workbench.files.intrinsics import resolve_intrinsics

    project = _project(tmp_path, "exif")
    _jpeg(project.root / "photos" / "panorama" / "a.jpg", FocalLength=4.25, FocalPlaneXResolution=RES_CM,
          FocalPlaneResolutionUnit=3)
    _jpeg(project.root / "photos" / "panorama" / "b.jpg")  # no EXIF focal
    choice = resolve_intrinsics(project)
    assert choice.source == "exif" and choice.focal_known == {"a.jpg": True, "b.jpg": False}
    assert abs(choice.per_photo["a.jpg"].fx / F_PX - 1) < 1e-3
    assert choice.detail["without_exif"] == ["b.jpg"] and choice.detail["exif"]["a.jpg"]["source"] == "focal_plane"
    (project.root / "photos" / "panorama" / "a.jpg").unlink()
    assert resolve_intrinsics(project).source == "fallback"  # no photo has a prior
    unknown = _project(tmp_path / "u", "unknown")
    _jpeg(unknown.root / "photos" / "panorama" / "a.jpg", FocalLength=4.25, FocalPlaneXResolution=RES_CM,
          FocalPlaneResolutionUnit=3)
    c = resolve_intrinsics(unknown)
    assert c.source == "fallback" and c.focal_known == {"a.jpg": False}
    assert abs(np.degrees(2 * np.arctan(200 / c.per_photo["a.jpg"].fx)) - 55.0) < 1e-9
