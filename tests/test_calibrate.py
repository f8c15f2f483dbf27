"""Chessboard calibration against OpenCV's reference calibration of its stereo sample (../shared/data)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from workbench.core.camera import CameraIntrinsics
from workbench.errors import InputError, SettingsError
from workbench.intrinsics.calibrate import (CalibrationOptions, calibrate_chessboard, load_camera_profile,
                                            parse_pattern, run_calibrate, validate_profile)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
BOARD = DATA / "calibration" / "opencv_stereo_chessboard"
# OpenCV's left_intrinsics.yml (13 views, 9x6, flags = CALIB_FIX_ASPECT_RATIO), see SOURCES.md
REF = dict(fx=535.9157, cx=342.2832, cy=235.5708, k1=-0.26637, k2=-0.03859, p1=0.001783, p2=-0.000281, k3=0.23839,
           rms=0.3926)

needs_data = pytest.mark.skipif(not BOARD.is_dir(), reason="../shared/data/calibration is not here")


@pytest.fixture(scope="module")
def left_images():
    if not BOARD.is_dir():
        pytest.skip("../shared/data/calibration is not here")
    return sorted(BOARD.glob("left*.jpg"))


@pytest.fixture(scope="module")
def calibrated(left_images):
    return calibrate_chessboard(left_images, (9, 6), 25.0)


@needs_data
def test_agrees_with_opencv_reference(calibrated, left_images):
    profile, stats = calibrated
    k = profile["intrinsics"]
    assert len(left_images) == 13 and stats["n_used"] == 13 and stats["rejected"] == []
    assert (k["width"], k["height"]) == (640, 480)
    # two-sided bands around the reference (a different OpenCV version moves them by ~0.2 px)
    assert abs(k["fx"] - REF["fx"]) < 1.0
    assert k["fy"] == k["fx"]  # fixed aspect ratio, as the reference
    assert abs(k["cx"] - REF["cx"]) < 1.0
    assert abs(k["cy"] - REF["cy"]) < 1.0
    assert abs(k["k1"] - REF["k1"]) < 0.01
    assert abs(k["k2"] - REF["k2"]) < 0.05
    assert abs(k["k3"] - REF["k3"]) < 0.08
    assert abs(k["p1"] - REF["p1"]) < 3e-4 and abs(k["p2"] - REF["p2"]) < 3e-4
    assert 0.8 * REF["rms"] < stats["rms_px"] < 1.2 * REF["rms"]
    # the one poor view of the reference (left02, 1.18 px) is the poor one here too
    per_view = {v["image"]: v["rms_px"] for v in stats["views"]}
    assert 1.0 < per_view["left02.jpg"] < 1.4
    assert all(0.1 < e < 0.6 for n, e in per_view.items() if n != "left02.jpg")
    # the 1-sigma of the focal is sub-pixel and honest (the reference differs by less than 3 sigma)
    assert 0.1 < stats["sigma"]["fx"] < 3.0
    assert 55 < stats["hfov_deg"] < 65


@needs_data
def test_profile_is_our_brown_model(calibrated):
    """Our projection with the profile equals OpenCV's projectPoints with the same numbers."""
    import cv2

    profile, _ = calibrated
    intr = validate_profile(profile)
    rng = np.random.default_rng(0)
    P = np.column_stack([rng.uniform(-0.4, 0.4, 200), rng.uniform(-0.3, 0.3, 200), rng.uniform(0.8, 3.0, 200)])
    ours = intr.project(P)
    theirs, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), intr.K, intr.dist_coeffs)
    assert np.max(np.abs(ours - theirs.reshape(-1, 2))) < 1e-8


@needs_data
def test_cli_function_writes_profile_and_rejects_boardless_photos(tmp_path, left_images):
    src = tmp_path / "boards"
    src.mkdir()
    for p in left_images[:6]:
        shutil.copy(p, src / p.name)
    import cv2

    cv2.imwrite(str(src / "zz_blank.png"), np.full((480, 640), 128, np.uint8))  # no board in it
    out = tmp_path / "profile.json"
    stats = run_calibrate(src, out, pattern="9x6", square_mm=25)
    assert stats["n_images"] == 7 and stats["n_used"] == 6
    assert stats["rejected"] == [{"image": "zz_blank.png", "reason": "no 9x6 chessboard found"}]
    data = json.loads(out.read_text())
    assert set(data) == {"model", "source", "intrinsics"} and data["model"] == "brown"
    assert set(data["intrinsics"]) == {"width", "height", "fx", "fy", "cx", "cy", "skew", "k1", "k2", "k3", "p1", "p2"}
    intr, _ = load_camera_profile(out)
    assert isinstance(intr, CameraIntrinsics) and abs(intr.fx - REF["fx"]) < 10.0
    assert (tmp_path / "profile.stats.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["boards", "profile.json", "profile.stats.json"]
    # --glob picks the photos of one camera
    stats2 = run_calibrate(src, tmp_path / "p2.json", pattern="9x6", square_mm=25, glob="left0[1-4]*")
    assert stats2["n_images"] == 4 and stats2["rejected"] == []
    with pytest.raises(InputError, match="matching"):
        run_calibrate(src, tmp_path / "p3.json", glob="right*")


@needs_data
def test_view_rejection_by_rms(left_images):
    opts = CalibrationOptions(pattern=(9, 6), square_mm=25.0, max_view_rms_px=0.8)
    profile, stats = calibrate_chessboard(left_images, options=opts)
    assert stats["n_used"] == 12
    assert [r["image"] for r in stats["rejected"]] == ["left02.jpg"]
    assert 0.15 < stats["rms_px"] < 0.35  # better without the poor view
    assert abs(profile["intrinsics"]["fx"] - REF["fx"]) < 3.0


@needs_data
def test_wrong_pattern_and_bad_inputs(tmp_path, left_images):
    with pytest.raises(InputError, match="found in 0 of 3"):
        calibrate_chessboard(left_images[:3], (8, 5), 25.0)
    import cv2

    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((240, 320), np.uint8))
    with pytest.raises(InputError, match="same camera"):
        calibrate_chessboard([left_images[0], small], (9, 6), 25.0)
    bad = tmp_path / "broken.jpg"
    bad.write_bytes(b"not a jpeg")
    with pytest.raises(InputError, match="cannot read"):
        calibrate_chessboard([bad], (9, 6), 25.0)


def test_options_and_pattern_parsing():
    assert parse_pattern("9x6") == (9, 6) and parse_pattern(" 7 X 5 ") == (7, 5)
    for bad in ("9", "9x", "axb", "9x6x2"):
        with pytest.raises(SettingsError):
            parse_pattern(bad)
    with pytest.raises(SettingsError, match="square_mm"):
        CalibrationOptions(square_mm=0)
    with pytest.raises(SettingsError, match="pattern"):
        CalibrationOptions(pattern=(1, 6))
    with pytest.raises(SettingsError, match="unknown key"):
        CalibrationOptions.from_dict({"pattern": (9, 6), "squares_mm": 25})
    with pytest.raises(InputError, match="unknown key"):
        validate_profile({"model": "brown", "intrinsics": {"width": 10, "height": 10, "fx": 1, "fy": 1, "cx": 0,
                                                           "cy": 0}, "extra": 1})
    with pytest.raises(InputError, match="invalid"):
        validate_profile({"intrinsics": {"width": 10, "height": 10, "fx": -1, "fy": 1, "cx": 0, "cy": 0}})
