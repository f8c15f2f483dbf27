"""The marked-point picker: its HTTP API, and the page driven in a headless Chromium as a person would."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageDraw

from workbench.correspond import manual as mf
from workbench.picker import PickerServer

W, H = 480, 360
SMOKE = Path(__file__).resolve().parents[1] / "workbench" / "picker" / "smoke.py"


@pytest.fixture
def incident(tmp_path):
    """A hand-made incident: two identical coaches, one photo with a drawn 'carriage', an automatic result."""
    root = tmp_path / "inc"
    (root / "photos" / "panorama").mkdir(parents=True)
    (root / "project.toml").write_text(
        '[incident]\nname = "picker test"\ndate = 2024-01-01\n\n[location]\nlat = 40.0\nlon = -74.0\n'
        'crs = "EPSG:32618"\n\n[[consist]]\nnumber = "6100"\ntype = "shoreliner"\ncoupling_to_next = "held"\n\n'
        '[[consist]]\nnumber = "6223"\ntype = "shoreliner"\n\n[camera]\nsource = "unknown"\n')
    img = Image.new("RGB", (W, H), (120, 160, 110))
    d = ImageDraw.Draw(img)
    d.rectangle((60, 150, 420, 200), fill=(200, 200, 205), outline=(20, 20, 20))
    for x in range(80, 400, 30):
        d.rectangle((x, 160, x + 18, 180), fill=(30, 40, 60))
    img.save(root / "photos" / "panorama" / "p0.jpg", quality=95)
    auto = {"observations": [{"carriage": "6100", "point": "body_top_front_left", "view": "p0.jpg",
                              "uv": [60.0, 150.0], "source": "sift", "confidence": 0.8, "sigma_px": 0.5}],
            "needs_manual": []}
    (root / "out" / "correspond").mkdir(parents=True)
    (root / "out" / "correspond" / mf.FILE_NAME).write_text(json.dumps(auto))
    return root


def _get(url):
    with urllib.request.urlopen(url, timeout=30) as r:
        return r.status, r.headers.get("Content-Type"), r.read()


def _post(url, data):
    req = urllib.request.Request(url, data=json.dumps(data).encode(), method="POST",
                                 headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def test_state_photo_and_references(incident):
    with PickerServer(incident) as srv:
        status, ctype, body = _get(srv.url + "api/state")
        doc = json.loads(body)
        assert status == 200 and ctype == "application/json"
        assert [c["number"] for c in doc["cars"]] == ["6100", "6223"]
        assert doc["photos"] == [{"name": "p0.jpg", "width": W, "height": H, "url": "/photo/p0.jpg"}]
        assert doc["automatic"][0]["point"] == "body_top_front_left" and doc["manual"] == []
        left = doc["cars"][0]["faces"]["left"]
        assert "front_door_top_front_left" in left["points"] and "coupler_front" not in left["points"]
        status, ctype, body = _get(srv.url + "reference/6100/left.png")
        assert status == 200 and ctype == "image/png"
        from io import BytesIO

        ref = Image.open(BytesIO(body))
        assert ref.size == (left["width"], left["height"])
        status, ctype, body = _get(srv.url + "photo/p0.jpg")
        assert status == 200 and Image.open(BytesIO(body)).size == (W, H)
        _, _, page = _get(srv.url)
        assert b"photo-canvas" in page and b"picker.js" in page
        with pytest.raises(urllib.error.HTTPError):
            _get(srv.url + "photo/../project.toml")


def test_save_validates_and_writes_atomically(incident):
    path = incident / mf.FILE_NAME
    good = {"carriage": "6223", "point": "coupler_rear", "view": "p0.jpg", "uv": [100.5, 170.25]}
    with PickerServer(incident) as srv:
        status, res = _post(srv.url + "api/save", {"observations": [good]})
        assert status == 200 and res["n"] == 1
        saved = json.loads(path.read_text())
        assert saved["observations"] == [{**good, "source": "manual", "confidence": 1.0}]
        for bad, msg in [({"point": "roof_hatch"}, "no marked point 'roof_hatch'"),
                         ({"carriage": "9999"}, "unknown carriage '9999'"),
                         ({"uv": [W + 3.0, 10.0]}, "outside view 'p0.jpg'")]:
            status, res = _post(srv.url + "api/save", {"observations": [good, {**good, "point": "coupler_front",
                                                                               **bad}]})
            assert status == 400 and msg in res["error"], res
            assert json.loads(path.read_text()) == saved  # a refused save leaves the file as it was
        # what the picker saved is what the stage reads
        from workbench.correspond.stage import load_manual
        from workbench.project import Project

        cf = load_manual(Project(incident))
        assert [o.key for o in cf.observations] == [("6223", "coupler_rear", "p0.jpg")]
    assert not list(incident.glob(".correspondences*"))  # no temp files left behind


def test_rejected_automatic_point_is_dropped_by_the_stage(incident):
    """A rejection saved by the picker is validated (a point picked and rejected at once is refused) and the
    stage's merge drops the automatic point."""
    rej = {"carriage": "6100", "point": "body_top_front_left", "view": "p0.jpg"}
    with PickerServer(incident) as srv:
        status, res = _post(srv.url + "api/save", {"observations": [], "rejected": [rej]})
        assert status == 200 and res["n_rejected"] == 1
        doc = json.loads(_get(srv.url + "api/state")[2])
        assert doc["rejected"] == [rej] and doc["automatic"][0]["point"] == "body_top_front_left"
        both = {"observations": [{**rej, "uv": [61.0, 151.0]}], "rejected": [rej]}
        status, res = _post(srv.url + "api/save", both)
        assert status == 400 and "picked or rejected, not both" in res["error"], res
        status, res = _post(srv.url + "api/save", {"rejected": [{**rej, "point": "no_such_point"}]})
        assert status == 400 and "no marked point 'no_such_point'" in res["error"], res
    from workbench.correspond.stage import load_manual
    from workbench.project import Project

    cf = load_manual(Project(incident))
    assert [r.key for r in cf.rejected] == [("6100", "body_top_front_left", "p0.jpg")]
    auto = mf.parse(json.loads((incident / "out" / "correspond" / mf.FILE_NAME).read_text()), "auto").observations
    assert len(auto) == 1 and mf.merge(auto, cf.observations, cf.rejected) == []
    assert mf.merge(auto, cf.observations) == auto  # without the rejection the point stays


def _playwright_python() -> str | None:
    """An interpreter with Playwright: this one, or $WORKBENCH_PLAYWRIGHT_PYTHON."""
    try:
        import playwright  # noqa: F401

        return sys.executable
    except ImportError:
        exe = os.environ.get("WORKBENCH_PLAYWRIGHT_PYTHON")
        return exe if exe and Path(exe).is_file() else None


@pytest.mark.slow
def test_driven_in_a_browser_like_a_person(incident, tmp_path):
    """Pick a point on the model, pick it roughly in the photo, zoom, pick it carefully, undo, pick again,
    save; the file holds the careful pick and the screenshot shows the photo, the model and the marker."""
    py = _playwright_python()
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if py is None or chromium is None:
        pytest.skip("needs Playwright (pip install playwright, or WORKBENCH_PLAYWRIGHT_PYTHON) and chromium")
    uv = [87.3, 161.6]  # a place inside the first drawn window
    plan = {"car": "6100", "point": "front_door_top_front_left", "face": "left", "view": "p0.jpg",
            "first_uv": [uv[0] + 7, uv[1] + 5], "uv": uv, "reject_point": "body_top_front_left"}
    (tmp_path / "plan.json").write_text(json.dumps(plan))
    shot = tmp_path / "picker.png"
    with PickerServer(incident) as srv:
        out = subprocess.run([py, str(SMOKE), srv.url, str(tmp_path / "plan.json"), str(shot), "--chromium", chromium],
                             capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    log = json.loads(out.stdout.strip().splitlines()[-1])
    assert log["point_selected"] == "front_door_top_front_left"
    assert log["scale"] > 4  # zoomed in
    assert np.allclose(log["after_undo"]["uv"], plan["first_uv"], atol=1.5)  # undo went back to the rough pick
    doc = json.loads((incident / mf.FILE_NAME).read_text())
    # the automatic point the person found wrong is rejected, and the stage will drop it
    assert "rejected" in log["rejected"], log
    assert doc["rejected"] == [{"carriage": "6100", "point": "body_top_front_left", "view": "p0.jpg",
                                "reason": "rejected in the picker"}]
    saved = doc["observations"]
    assert len(saved) == 1 and saved[0]["point"] == "front_door_top_front_left" and saved[0]["carriage"] == "6100"
    err = np.hypot(saved[0]["uv"][0] - uv[0], saved[0]["uv"][1] - uv[1])
    assert 0.0 <= err < 0.3, saved  # the careful pick at high zoom
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    assert img.shape[0] >= 700 and img.shape[1] >= 1300
    left, right = img[:, : img.shape[1] * 3 // 5], img[:, img.shape[1] * 3 // 5:]
    red = (left[..., 0] > 200) & (left[..., 1] < 60) & (left[..., 2] < 100)
    yellow = (left[..., 0] > 230) & (left[..., 1] > 190) & (left[..., 1] < 230) & (left[..., 2] < 120)
    assert (red | yellow).sum() > 20  # the manual marker (a cross; yellow while its point is selected)
    assert left.std() > 20 and right.std() > 20  # the photo and the model's faces are shown, not blank
