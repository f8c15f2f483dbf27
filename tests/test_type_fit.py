"""``workbench type-fit``: a type's estimated dimensions measured from hand picks on photos of intact cars
(workbench/solve/type_fit.py), against the truth of simulated photos."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from workbench.cli import main
from workbench.core.camera import look_at
from workbench.errors import InputError, SettingsError
from workbench.rolling_stock import get_type
from workbench.solve.type_fit import PhotoPicks, fit_type_dimensions, type_points, photo_intrinsics

TRUTH = {"profile.eave_height_m": 3.15, "front.nose_base_height_m": 1.90}  # the type file: 3.36, 2.00
VIEWS = [(20.0, 60.0, 12.0), (-35.0, 40.0, 25.0)]  # azimuth (deg), distance (m), horizontal field of view (deg)


def _picks(ctype, rng, noise_px: float = 0.5) -> list[PhotoPicks]:
    """Two telephoto 3/4 views of one car, one from each side, its visible marked points at ``noise_px``."""
    P = type_points(ctype, TRUTH)
    out = []
    for k, (az, dist, hf) in enumerate(VIEWS):
        w, h = 1024, 683
        intr = photo_intrinsics((w, h), 0.5 * w / math.tan(math.radians(hf / 2)))
        a = math.radians(az)
        M = look_at(np.array([dist * math.cos(a) + 5.0, dist * math.sin(a), 3.0]), np.array([0.0, 0.0, 2.0]))
        names = [n for n in P if P[n][1] * math.sin(a) > 0 or "coupler" in n]
        uv = intr.project(np.array([P[n] for n in names]) @ M[:3, :3].T + M[:3, 3])
        uv = uv + rng.normal(0.0, noise_px, uv.shape)
        out.append(PhotoPicks(f"photo{k}.jpg", (w, h), "1", {n: (float(u), float(v)) for n, (u, v) in zip(names, uv)}))
    return out


def test_dimensions_recovered_with_honest_sigmas():
    """30 draws at 0.5 px, started from the type file's 3.36 m eave and 2.00 m nose base: the fitted values land
    on the truth (3.15 m, 1.90 m) within a few centimetres, and their errors over their stated sigmas have an RMS near
    1 (two-sided); the focal of each photo comes back to its field of view."""
    t = get_type("keikyu-n1000")
    rng = np.random.default_rng(3)
    z, err = [], []
    for _ in range(30):
        fit = fit_type_dimensions(t, _picks(t, rng), list(TRUTH))
        z.append([(fit.values[k] - TRUTH[k]) / fit.sigmas[k] for k in TRUTH])
        err.append([fit.values[k] - TRUTH[k] for k in TRUTH])
        assert fit.before == {"profile.eave_height_m": t.spec.profile.eave_height_m,
                              "front.nose_base_height_m": t.spec.front.nose_base_height_m}
        for k, (_, _, hf) in enumerate(VIEWS):
            assert abs(fit.hfov_deg[f"photo{k}.jpg"] - hf) < 0.1 * hf
    rms_z = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((0.6 < rms_z) & (rms_z < 1.5)), rms_z
    assert np.max(np.abs(err)) < 0.08, np.max(np.abs(err), axis=0)
    assert 0.3 < fit.sigma_px < 0.8 and fit.rms_px < 1.2


def test_a_cab_front_bowed_in_plan_is_measured():
    """``front.corner_setback_m`` (the cab's corners behind its middle, where the coupler stands) comes back from
    the two views: 5 draws at 0.5 px, the truth 0.20 m, started from the type file's value."""
    t = get_type("keikyu-n1000")
    truth = {"front.corner_setback_m": 0.20}
    rng = np.random.default_rng(5)
    for _ in range(5):
        P = type_points(t, truth)
        picks = []
        for k, (az, dist, hf) in enumerate(VIEWS):
            intr = photo_intrinsics((1024, 683), 512 / math.tan(math.radians(hf / 2)))
            a = math.radians(az)
            M = look_at(np.array([dist * math.cos(a) + 5.0, dist * math.sin(a), 3.0]), np.array([0.0, 0.0, 2.0]))
            names = [n for n in P if P[n][1] * math.sin(a) > 0 or "coupler" in n]
            uv = intr.project(np.array([P[n] for n in names]) @ M[:3, :3].T + M[:3, 3])
            uv = uv + rng.normal(0, 0.5, uv.shape)
            pts = {n: (float(a), float(b)) for n, (a, b) in zip(names, uv)}
            picks.append(PhotoPicks(f"p{k}.jpg", (1024, 683), "1", pts))
        fit = fit_type_dimensions(t, picks, list(truth))
        s = fit.sigmas["front.corner_setback_m"]
        assert abs(fit.values["front.corner_setback_m"] - 0.20) < max(4 * s, 0.02) and 0.001 < s < 0.1, fit.values


def test_bad_requests_are_refused_with_what_to_do():
    t = get_type("keikyu-n1000")
    picks = _picks(t, np.random.default_rng(0))
    with pytest.raises(SettingsError, match="profile.eave_height_m"):  # the valid keys are listed
        fit_type_dimensions(t, picks, ["dimensions.length_over_couplers_m"])
    with pytest.raises(SettingsError, match="at least one"):
        fit_type_dimensions(t, picks, [])
    bad = [PhotoPicks("p.jpg", (800, 600), "1", {"roof_apex": (1.0, 2.0), **picks[0].points})]
    with pytest.raises(InputError, match="roof_apex"):
        fit_type_dimensions(t, bad, ["profile.eave_height_m"])
    few = [PhotoPicks("p.jpg", (800, 600), "1", dict(list(picks[0].points.items())[:3]))]
    with pytest.raises(InputError, match="at least 4"):
        fit_type_dimensions(t, few, ["profile.eave_height_m"])


def _run(argv, capsys) -> tuple[int, str]:
    try:
        main(argv)
        code = 0
    except SystemExit as e:
        code = int(e.code or 0)
    cap = capsys.readouterr()
    return code, cap.out + cap.err


def test_command_fits_an_incident_folders_picks(tmp_path, capsys):
    """``workbench type-fit`` on a folder (project.toml, photos, correspondences.json) prints the fitted values
    and writes them as JSON; a dimension that cannot be fitted exits 2 naming it."""
    from PIL import Image

    t = get_type("keikyu-n1000")
    picks = _picks(t, np.random.default_rng(1))
    (tmp_path / "photos").mkdir()
    for p in picks:
        Image.new("RGB", p.size).save(tmp_path / "photos" / p.view)
    (tmp_path / "project.toml").write_text(
        '[incident]\nname = "type photos"\ndate = 2020-01-01\n[location]\nlat = 35.5\nlon = 139.7\ncrs = "EPSG:32654"\n'
        '[[consist]]\nnumber = "1"\ntype = "keikyu-n1000"\n[camera]\nsource = "unknown"\nphotos = "photos"\n')
    obs = [{"carriage": p.car, "point": n, "view": p.view, "uv": list(uv)} for p in picks for n, uv in p.points.items()]
    (tmp_path / "correspondences.json").write_text(json.dumps({"observations": obs}))
    out = tmp_path / "fit.json"
    code, text = _run(["type-fit", str(tmp_path), "--free", ",".join(TRUTH), "--out", str(out)], capsys)
    assert code == 0, text
    assert "profile.eave_height_m" in text and "photo1.jpg" in text
    doc = json.loads(out.read_text())
    assert abs(doc["dimensions"]["profile.eave_height_m"]["value_m"] - TRUTH["profile.eave_height_m"]) < 0.08
    code, text = _run(["type-fit", str(tmp_path), "--free", "profile.roof_colour"], capsys)
    assert code == 2 and "profile.roof_colour" in text
