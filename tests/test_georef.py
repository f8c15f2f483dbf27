"""Camera georegistration from ground control points: synthetic truth (panorama, multiview, single photo),
the real Berlin GCPs (OpenSfM), and bad input."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from workbench.core.camera import CameraIntrinsics
from workbench.core.frames import SceneFrame
from workbench.core.io import atomic_write_json
from workbench.errors import InputError, StageError
from workbench.files.control_points import load_control_points, parse_control_points
from workbench.georef.fitting import umeyama
from workbench.files.cameras import parse_cameras
from workbench.files.reconstruction import SfmView
from workbench.georef.options import GeorefOptions, GeorefResidualsLarge
from workbench.georef.picks import misfit_doubt
from workbench.georef.similarity import solve_similarity
from workbench.georef.stage import run_georef
from workbench.pipeline import stage
from workbench.project import Project
from workbench.synth.control_points import (similarity, split_reconstruction, true_panorama_model,
                                            true_reconstruction, wrong_camera_reconstruction, write_control_points)

REPO = Path(__file__).resolve().parents[1]
BERLIN = REPO.parent / "shared" / "data" / "multiview" / "opensfm_berlin"
WORLD_FROM_PANO = Rotation.from_euler("zyx", [30.0, -5.0, 3.0], degrees=True).as_matrix()


def _no_progress(f: float, m: str = "") -> None:
    pass


def _rot_err_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(np.asarray(A)[:3, :3] @ np.asarray(B)[:3, :3].T).magnitude()))


@pytest.fixture(scope="module")
def sample(small_incident, tmp_path_factory):
    """A copy of the session's small generated Spuyten Duyvil incident (tests/conftest.py: 4 cars, 800x600
    photos, 4 panorama and 8 multi-view photos) and its layers, with synthetic control points. Never the sample
    in projects/ (whether the demo generated it must not change what the tests see); the full sample's figures
    are checked by scripts/bench_georef_multiview.py."""
    src, truth = small_incident
    base = tmp_path_factory.mktemp("georef")
    shutil.copytree(src.parent.parent, base, dirs_exist_ok=True)
    root = base / "projects" / src.name
    return root, truth


def _fresh(sample, tmp_path, name: str, toml_edit=None) -> Path:
    root, truth = sample
    dst = root.parent / name
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(root, dst, ignore=shutil.ignore_patterns("photos", "out"))
    (dst / "photos").mkdir()
    for sub in ("panorama", "multiview"):
        if (root / "photos" / sub).is_dir():
            (dst / "photos" / sub).symlink_to(root / "photos" / sub)
    if toml_edit:
        p = dst / "project.toml"
        p.write_text(toml_edit(p.read_text()))
    return dst


# ----------------------------------------------------------------------------------------------------------
# Synthetic control points
# ----------------------------------------------------------------------------------------------------------
def test_synthetic_control_points_are_true_pixels(sample):
    root, truth = sample
    doc = json.loads((root / "control_points.json").read_text())
    frame = SceneFrame(truth["frame"]["crs"], truth["frame"]["lat"], truth["frame"]["lon"], truth["frame"]["height_m"])
    cps = load_control_points(root / "control_points.json", frame)
    assert len(cps) >= 12
    kinds = {p["kind"] for p in doc["points"]}
    assert "ground_mark" in kinds and kinds <= {"roof_corner", "wall_base_corner", "ground_mark"}
    per_photo = {Path(ph["photo"]).name: 0 for ph in truth["photos"]}
    errs = []
    for cp in cps:
        for name, uv in cp.pixels.items():
            per_photo[name] += 1
            ph = next(p for p in truth["photos"] if Path(p["photo"]).name == name)
            intr = CameraIntrinsics.from_dict(ph["intrinsics"])
            M = np.asarray(ph["cam_from_world"])
            q = M[:3, :3] @ cp.enu + M[:3, 3]
            errs.append(np.hypot(*(intr.project(q[None])[0] - uv)))
    errs = np.array(errs)
    # 0.5 px noise per axis: the pixel error is Rayleigh with mean 0.63 px (coords rounded to 1 mm, pixels to 0.01)
    assert 0.45 < errs.mean() < 0.8 and errs.max() < 3.0
    pano = [n for n in per_photo if n.startswith("pano")]
    assert all(per_photo[n] >= 6 for n in pano)
    # deterministic: a second run gives the same file
    before = (root / "control_points.json").read_text()
    write_control_points(root, force=True)
    assert (root / "control_points.json").read_text() == before


# ----------------------------------------------------------------------------------------------------------
# Panorama route
# ----------------------------------------------------------------------------------------------------------
def _check_panorama(dst: Path, truth: dict, *, centre_band=(0.001, 0.10), rot_band=(0.0005, 0.10)) -> dict:
    atomic_write_json(dst / "out" / "stitch" / "panorama.json", true_panorama_model(dst, WORLD_FROM_PANO))
    project = Project(dst)
    assert project.georef_route() == "panorama"
    res = run_georef(project, _no_progress)
    doc = json.loads(res.outputs["cameras"].read_text())
    assert doc["route"] == "panorama" and doc["intrinsics_source"] == "calibrated"
    W = np.asarray(doc["panorama"]["world_from_pano"])
    centre_err = float(np.linalg.norm(W[:3, 3] - np.asarray(truth["panorama_center_enu"])))
    rot_err = _rot_err_deg(W, WORLD_FROM_PANO)
    assert centre_band[0] < centre_err < centre_band[1], centre_err
    assert rot_band[0] < rot_err < rot_band[1], rot_err
    truth_by = {Path(p["photo"]).name: p for p in truth["photos"]}
    for v in doc["views"]:
        T = np.asarray(truth_by[v["name"]]["cam_from_world"])
        assert _rot_err_deg(v["cam_from_world"], T) < rot_band[1]
        M = np.asarray(v["cam_from_world"])
        assert np.allclose(-M[:3, :3].T @ M[:3, 3], v["center_enu"], atol=1e-9)
    g = doc["georegistration"]
    assert 0.2 < g["rms_px"] < 1.5 and g["rms_m"] < 0.2
    return doc


def test_panorama_with_position_prior(sample, tmp_path):
    root, truth = sample
    dst = _fresh(sample, tmp_path, "pano_prior")
    doc = _check_panorama(dst, truth)
    assert doc["georegistration"]["prior_source"] == "camera.position_enu"


def test_panorama_without_prior_uses_p3p(sample, tmp_path):
    root, truth = sample

    def drop_position(text: str) -> str:
        lines, out, skip = text.splitlines(), [], False
        for ln in lines:
            if ln.startswith("position_enu"):
                skip = not ln.rstrip().endswith("]")
                continue
            if skip:
                skip = not ln.strip().startswith("]")
                continue
            out.append(ln)
        return "\n".join(out) + "\n"

    dst = _fresh(sample, tmp_path, "pano_noprior", drop_position)
    assert Project(dst).settings.camera.position_enu is None
    doc = _check_panorama(dst, truth)
    assert doc["georegistration"]["prior"] == "no"


def test_panorama_outlier_is_rejected_and_warned(sample, tmp_path):
    root, truth = sample
    dst = _fresh(sample, tmp_path, "pano_outlier")
    cp = json.loads((dst / "control_points.json").read_text())
    victim = next(p for p in cp["points"] if any(k.startswith("pano") for k in p["pixels"]))
    name = next(k for k in victim["pixels"] if k.startswith("pano"))
    victim["pixels"][name][0] += 80.0
    (dst / "control_points.json").write_text(json.dumps(cp))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        doc = _check_panorama(dst, truth)
    bad = [r for r in doc["georegistration"]["residuals"] if r["point"] == victim["name"] and r["view"] == name]
    assert bad and not bad[0]["inlier"] and 60 < bad[0]["error_px"] < 100
    assert any(victim["name"] in w for w in doc["georegistration"]["warnings"])


def test_panorama_picks_made_in_the_stitched_image(sample, tmp_path):
    """Control points picked in the panorama image (key "panorama") are mapped into their source photos."""
    from workbench.core.panorama import PanoramaModel
    from workbench.synth.control_points import true_world_from_pano

    root, truth = sample
    dst = _fresh(sample, tmp_path, "pano_picks")
    pdoc = true_panorama_model(dst)
    atomic_write_json(dst / "out" / "stitch" / "panorama.json", pdoc)
    model = PanoramaModel.from_dict(pdoc)
    cp = json.loads((dst / "control_points.json").read_text())
    n = 0
    for p in cp["points"]:
        pano = sorted(k for k in p["pixels"] if k.startswith("pano"))
        if pano:
            uv = model.from_source(model.source_index(pano[0]), np.asarray([p["pixels"][pano[0]]]))[0]
            for k in pano:
                del p["pixels"][k]
            p["pixels"]["panorama"] = uv.tolist()
            n += 1
    (dst / "control_points.json").write_text(json.dumps(cp))
    assert n >= 8
    doc = json.loads(run_georef(Project(dst), _no_progress).outputs["cameras"].read_text())
    W = np.asarray(doc["panorama"]["world_from_pano"])
    assert 0.001 < np.linalg.norm(W[:3, 3] - truth["panorama_center_enu"]) < 0.2
    assert 0.0005 < _rot_err_deg(W, true_world_from_pano(dst)) < 0.1
    assert doc["georegistration"]["n_observations"] == n
    cp["points"][0]["pixels"] = {"panorama": [-500.0, -500.0]}
    (dst / "control_points.json").write_text(json.dumps(cp))
    with pytest.raises(InputError, match="outside every source photo"):
        run_georef(Project(dst), _no_progress)


# ----------------------------------------------------------------------------------------------------------
# Multiview (SfM similarity) and single photo
# ----------------------------------------------------------------------------------------------------------
def test_multiviewsimilarity(sample, tmp_path):
    root, truth = sample
    dst = _fresh(sample, tmp_path, "multiview", lambda t: t.replace('source = "calibrated"', 'source = "sfm"')
                 .replace('photos = "photos/panorama"', 'photos = "photos/multiview"'))
    S = np.eye(4)
    Rs = Rotation.from_euler("zyx", [120.0, 10.0, -20.0], degrees=True).as_matrix()
    S[:3, :3] = 0.37 * Rs
    S[:3, 3] = [40.0, -20.0, 5.0]
    atomic_write_json(dst / "out" / "sfm" / "reconstruction.json", true_reconstruction(dst, S))
    project = Project(dst)
    assert project.georef_route() == "multiview"
    res = run_georef(project, _no_progress)
    doc = json.loads(res.outputs["cameras"].read_text())
    assert doc["route"] == "multiview" and doc["panorama"] is None
    Wm = np.asarray(doc["georegistration"]["world_from_model"])
    assert abs(np.cbrt(np.linalg.det(Wm[:3, :3])) - 0.37) < 0.37 * 1e-3
    truth_by = {Path(p["photo"]).name: p for p in truth["photos"]}
    c_err = [np.linalg.norm(np.asarray(v["center_enu"]) - truth_by[v["name"]]["center_enu"]) for v in doc["views"]]
    r_err = [_rot_err_deg(v["cam_from_world"], truth_by[v["name"]]["cam_from_world"]) for v in doc["views"]]
    assert len(doc["views"]) == sum(1 for p in truth["photos"] if p["set"] == "multiview")
    assert 0.001 < max(c_err) < 0.10, c_err
    assert 0.0005 < max(r_err) < 0.10, r_err
    assert doc["georegistration"]["n_triangulated"] >= 6
    # SfM's cameras exact: the shared-camera adjustment keeps them. "sfm" is scored on the poses it keeps (the
    # model's, by the similarity), which fit the held-out picks better than any set refitted per photo; the
    # photos keep exactly the poses they have with the adjustment off. (Scored on poses refitted to each photo's
    # own picks, "sfm" lost to a refined focal on the full sample, 0.973 against 0.953 px, and a 5-pick photo
    # took a pose from its own picks 0.14 m and 0.25 deg off.)
    (adj,) = doc["georegistration"]["camera_adjustment"]
    ho = adj["held_out_rms_px"]
    assert adj["chosen"] == "sfm", adj
    assert 0.3 < ho["sfm"] < 0.9 * min(ho[k] for k in ("sfm_poses_refit", "f", "f_pp", "f_pp_k1")), ho
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        off = json.loads(run_georef(project, _no_progress, GeorefOptions(adjust_camera=False))
                         .outputs["cameras"].read_text())
    assert [v["cam_from_world"] for v in off["views"]] == [v["cam_from_world"] for v in doc["views"]]


def test_single_photo_pnp(sample, tmp_path):
    root, truth = sample
    dst = _fresh(sample, tmp_path, "single", lambda t: t.replace('photos = "photos/panorama"',
                                                                 'photos = "photos/single"'))
    ph = next(p for p in truth["photos"] if p["photo"].endswith("pano_02.jpg"))
    (dst / "photos" / "single").mkdir()
    shutil.copy(root / ph["photo"], dst / "photos" / "single" / "pano_02.jpg")
    project = Project(dst)
    assert project.georef_route() == "single"
    doc = json.loads(run_georef(project, _no_progress).outputs["cameras"].read_text())
    v = doc["views"][0]
    assert doc["route"] == "single" and v["name"] == "pano_02.jpg"
    assert 0.001 < np.linalg.norm(np.asarray(v["center_enu"]) - ph["center_enu"]) < 0.25
    assert 0.0005 < _rot_err_deg(v["cam_from_world"], ph["cam_from_world"]) < 0.1
    # without a camera profile: the EXIF focal, no distortion model (k1 = -0.08 unmodelled: metres, not cm)
    toml = (dst / "project.toml").read_text()
    (dst / "project.toml").write_text(toml.replace('source = "calibrated"', 'source = "exif"')
                                      .replace('profile = "camera_profile.json"\n', ""))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        doc = json.loads(run_georef(Project(dst), _no_progress).outputs["cameras"].read_text())
    v = doc["views"][0]
    assert doc["intrinsics_source"] == "exif" and not v["focal_known"]
    assert abs(v["intrinsics"]["fx"] / ph["intrinsics"]["fx"] - 1.0) < 0.01
    err = np.linalg.norm(np.asarray(v["center_enu"]) - ph["center_enu"])
    assert 0.05 < err < 5.0


def test_known_cameras_are_validated_and_checked(sample, tmp_path):
    from workbench.synth.handpicks import write_known_cameras

    root, truth = sample
    dst = _fresh(sample, tmp_path, "known")
    write_known_cameras(dst, "panorama")
    project = Project(dst)
    assert project.georef_route() == "known"
    res = run_georef(project, _no_progress)
    assert json.loads(res.outputs["cameras"].read_text()) == json.loads((dst / "cameras.json").read_text())
    assert 0.2 < res.stats["control_point_check"]["rms_px"] < 1.5
    doc = json.loads((dst / "cameras.json").read_text())
    doc["views"][0]["center_enu"] = [0.0, 0.0, 0.0]
    (dst / "cameras.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"center_enu .* disagrees with cam_from_world"):
        run_georef(Project(dst), _no_progress)


def test_stage_spec():
    assert stage("georef").name == "georef" and set(stage("georef").depends_on) == {"stitch", "sfm"}


# ----------------------------------------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------------------------------------
def test_bad_control_points(sample, tmp_path):
    root, truth = sample
    dst = _fresh(sample, tmp_path, "bad")
    atomic_write_json(dst / "out" / "stitch" / "panorama.json", true_panorama_model(dst, WORLD_FROM_PANO))
    good = json.loads((dst / "control_points.json").read_text())

    def run_with(doc):
        (dst / "control_points.json").write_text(json.dumps(doc))
        return run_georef(Project(dst), _no_progress)

    doc = json.loads(json.dumps(good))
    p = next(p for p in doc["points"] if "pano_00.jpg" in p["pixels"])
    w, h = (next(ph for ph in truth["photos"] if ph["photo"].endswith("pano_00.jpg"))["intrinsics"][k]
            for k in ("width", "height"))
    p["pixels"]["pano_00.jpg"] = [w + 100.0, 300.0]
    with pytest.raises(InputError, match=rf"{p['name']}.*pano_00.jpg.*outside the {w}x{h} image"):
        run_with(doc)
    doc = json.loads(json.dumps(good))
    doc["points"][0]["coords"] = doc["points"][0]["coords"][::-1][1:] + [0.0]  # northing first: lands far away
    with pytest.raises(InputError, match="km from the incident"):
        run_with(doc)
    doc = json.loads(json.dumps(good))
    doc["points"][0]["sigma"] = 0.1
    with pytest.raises(InputError, match="unknown key 'points\\[0\\].sigma'"):
        run_with(doc)
    doc = {"crs": "EPSG:4326", "points": [{"name": "a", "coords": [40.878, -73.92, 5.0]}]}  # lat, lon swapped
    with pytest.raises(InputError, match="km from the incident|longitude first"):
        run_with(doc)
    doc = json.loads(json.dumps(good))
    keep = [p for p in doc["points"] if any(k.startswith("pano") for k in p["pixels"])][:1]
    doc["points"] = keep
    with pytest.raises(InputError, match="at least 3"):
        run_with(doc)
    (dst / "control_points.json").write_text(json.dumps(good))
    (dst / "out" / "stitch" / "panorama.json").unlink()
    with pytest.raises(StageError, match="stitch"):
        run_georef(Project(dst), _no_progress)


def test_umeyama_round_trip():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(10, 3))
    R = Rotation.random(random_state=2).as_matrix()
    dst = 2.5 * src @ R.T + [1.0, 2.0, 3.0]
    s, R2, t = umeyama(src, dst)
    assert abs(s - 2.5) < 1e-12 and np.allclose(R2, R) and np.allclose(t, [1, 2, 3])


# ----------------------------------------------------------------------------------------------------------
# Real data: OpenSfM Berlin, 3 photos, 2 GCPs with lat/lon/alt, EXIF GPS
# ----------------------------------------------------------------------------------------------------------
def _berlin():
    from workbench.georef.gps import read_gps

    rec = json.loads((BERLIN / "reconstruction_example.json").read_text())[0]
    cam = next(iter(rec["cameras"].values()))
    w, h = cam["width"], cam["height"]
    size = max(w, h)
    # OpenSfM: normalised = (pixel + 0.5 - w/2) / max(w, h) with pixel centres at integers -> cx = w/2 - 0.5
    intr = CameraIntrinsics(width=w, height=h, fx=cam["focal"] * size, fy=cam["focal"] * size, cx=w / 2 - 0.5,
                            cy=h / 2 - 0.5, k1=cam["k1"], k2=cam["k2"])
    ref = rec["reference_lla"]
    frame = SceneFrame("EPSG:25833", ref["latitude"], ref["longitude"], ref["altitude"])
    views = []
    for name, s in sorted(rec["shots"].items()):
        M = np.eye(4)
        M[:3, :3] = Rotation.from_rotvec(s["rotation"]).as_matrix()
        M[:3, 3] = s["translation"]
        views.append(SfmView(name, intr, M))
    g = json.loads((BERLIN / "ground_control_points.json").read_text())
    pts = [{"name": f"gcp_{p['id']}", "sigma_m": 0.1,
            "coords": [p["position"]["longitude"], p["position"]["latitude"], p["position"]["altitude"]],
            "pixels": {o["shot_id"]: [o["projection"][0] * size + w / 2 - 0.5, o["projection"][1] * size + h / 2 - 0.5]
                       for o in p["observations"]}}
           for p in g["points"] if "position" in p]
    cps = parse_control_points({"crs": "EPSG:4326", "points": pts}, frame, "ground_control_points.json")
    gps = {}
    for v in views:
        lon, lat, alt = read_gps(BERLIN / "images" / v.name)
        gps[v.name] = frame.enu_from_wgs84(np.array([lon, lat, alt]))
    return views, cps, gps, rec


@pytest.mark.skipif(not (BERLIN / "ground_control_points.json").is_file(), reason="shared Berlin data missing")
def test_berlin_gcps_real_data(capsys):
    views, cps, gps, rec = _berlin()
    assert len(cps) == 2 and sum(len(c.pixels) for c in cps) == 3
    # the EXIF GPS read here is what OpenSfM stored (its topocentric frame = our ENU at reference_lla)
    for v in views:
        assert np.allclose(gps[v.name], rec["shots"][v.name]["gps_position"], atol=0.05)
    # GCP 0 is picked in two photos: its rays meet in the OpenSfM model (pixel conventions agree)
    from workbench.georef.fitting import triangulate_rays

    cp0 = next(c for c in cps if c.name == "gcp_0")
    by = {v.name: v for v in views}
    cs, ds = [], []
    for name, uv in cp0.pixels.items():
        M = by[name].cam_from_model
        cs.append(-M[:3, :3].T @ M[:3, 3])
        ds.append(M[:3, :3].T @ by[name].intrinsics.rays(uv[None])[0])
    X, angle = triangulate_rays(np.array(cs), np.array(ds))
    for name, uv in cp0.pixels.items():
        M = by[name].cam_from_model
        e = np.hypot(*(by[name].intrinsics.project((M[:3, :3] @ X + M[:3, 3])[None])[0] - uv))
        assert 0.01 < e < 8.0, (name, e)
    # similarity from the 2 GCPs + 3 GPS centres; the residuals are reported (and warned about when large)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = solve_similarity(views, cps, gps_centres=gps, opts=GeorefOptions(), where="berlin")
    s = res.stats
    with capsys.disabled():
        print(f"\nBerlin: scale {s['scale']:.3f}, GCP rms {s['rms_px']:.2f} px / {s['rms_m']:.3f} m, "
              f"GPS centre rms {s['gps_rms_m']:.1f} m; per pick: "
              + ", ".join(f"{r['point']}@{r['view']} {r['error_px']:.1f} px {r['error_m']:.3f} m"
                          for r in res.residuals))
    assert 0.5 < s["rms_px"] < 10.0 and 0.001 < s["rms_m"] < 0.5
    assert 1.0 < s["gps_rms_m"] < 40.0  # phone GPS: metres horizontally, tens of metres in altitude
    assert 0.5 < s["scale"] < 2.0
    warned = [w for w in caught if issubclass(w.category, GeorefResidualsLarge)]
    # over 3 px and more than the picks' stated errors explain (misfit_doubt: with 3 picks and 7 parameters no
    # degree of freedom is left to tell, so the 3 px decides)
    doubt = misfit_doubt(res.residuals, s["rms_px"], GeorefOptions(), 7)
    assert (doubt is not None) == (s["rms_px"] > GeorefOptions().warn_rms_px)
    assert (doubt is not None) == any("RMS" in str(w.message) for w in warned)


# ----------------------------------------------------------------------------------------------------------
# Multiview with separate SfM models (issue 4): each model placed by its own control points
# ----------------------------------------------------------------------------------------------------------
def _mv_project(sample, tmp_path, name: str) -> tuple[Path, dict, list[str]]:
    root, truth = sample
    dst = _fresh(sample, tmp_path, name, lambda t: t.replace('source = "calibrated"', 'source = "sfm"')
                 .replace('photos = "photos/panorama"', 'photos = "photos/multiview"'))
    names = sorted(Path(p["photo"]).name for p in truth["photos"] if p["set"] == "multiview")
    return dst, truth, names


def _picks_per_photo(dst: Path) -> dict[str, int]:
    cp = json.loads((dst / "control_points.json").read_text())
    n: dict[str, int] = {}
    for p in cp["points"]:
        for k in p["pixels"]:
            n[k] = n.get(k, 0) + 1
    return n


def test_multiview_separate_models_are_placed(sample, tmp_path):
    dst, truth, names = _mv_project(sample, tmp_path, "mv_two_models")
    half = len(names) // 2
    groups = [names[:half], names[half:]]
    frames = [similarity(0.37, [120.0, 10.0, -20.0], [40.0, -20.0, 5.0]),
              similarity(2.9, [-70.0, 35.0, 160.0], [-300.0, 80.0, 12.0])]
    atomic_write_json(dst / "out" / "sfm" / "reconstruction.json", split_reconstruction(dst, groups, frames))
    doc = json.loads(run_georef(Project(dst), _no_progress).outputs["cameras"].read_text())
    parse_cameras(doc, "cameras.json")
    g = doc["georegistration"]
    assert [m["model"] for m in g["models"]] == ["main", "models[0]"]
    assert [m["status"] for m in g["models"]] == ["georegistered", "georegistered"], g["models"]
    assert sorted(v["name"] for v in doc["views"]) == names and g["unregistered"] == []
    # each model's own similarity is recovered (the main one stays in world_from_model)
    for m, S in zip(g["models"], frames):
        W = np.asarray(m["world_from_model"])
        s = np.cbrt(np.linalg.det(W[:3, :3]))
        assert 0.0 < abs(s / np.cbrt(np.linalg.det(S[:3, :3])) - 1) < 2e-3, (m["model"], s)
    assert np.allclose(g["world_from_model"], g["models"][0]["world_from_model"])
    truth_by = {Path(p["photo"]).name: p for p in truth["photos"]}
    for v in doc["views"]:
        c_err = np.linalg.norm(np.asarray(v["center_enu"]) - truth_by[v["name"]]["center_enu"])
        r_err = _rot_err_deg(v["cam_from_world"], truth_by[v["name"]]["cam_from_world"])
        assert 0.0005 < c_err < 0.15, (v["name"], c_err)
        assert 0.0002 < r_err < 0.15, (v["name"], r_err)
    sub = g["models"][1]
    assert sub["n_fitting_triangulated"] >= 3 and sub["spread_m"] > 1.0 and 0.0 < sub["sigma_centre_max_m"] < 0.5
    assert sorted(sub["placed"]) == groups[1]


def test_multiview_separate_model_without_control_points_stays_unregistered(sample, tmp_path):
    dst, truth, names = _mv_project(sample, tmp_path, "mv_sub_no_cps")
    picks = _picks_per_photo(dst)
    # the separate model: the two photos with the fewest picks; their picks removed but one point's
    lone = sorted(names, key=lambda n: (picks.get(n, 0), n))[:2]
    cp = json.loads((dst / "control_points.json").read_text())
    kept = 0
    for p in cp["points"]:
        if all(k in p["pixels"] for k in lone) and kept == 0:
            kept += 1
            continue
        for k in lone:
            p["pixels"].pop(k, None)
    cp["points"] = [p for p in cp["points"] if p["pixels"]]
    (dst / "control_points.json").write_text(json.dumps(cp))
    groups = [[n for n in names if n not in lone], lone]
    frames = [similarity(0.37, [120.0, 10.0, -20.0], [40.0, -20.0, 5.0]),
              similarity(1.7, [10.0, -5.0, 90.0], [3.0, 4.0, 5.0])]
    atomic_write_json(dst / "out" / "sfm" / "reconstruction.json", split_reconstruction(dst, groups, frames))
    doc = json.loads(run_georef(Project(dst), _no_progress).outputs["cameras"].read_text())
    g = doc["georegistration"]
    assert [m["status"] for m in g["models"]] == ["georegistered", "unregistered"]
    assert "control point" in g["models"][1]["reason"] and "needs at least 3" in g["models"][1]["reason"] \
        or "are needed" in g["models"][1]["reason"], g["models"][1]["reason"]
    assert sorted(v["name"] for v in doc["views"]) == groups[0]
    assert sorted(u["name"] for u in g["unregistered"]) == sorted(lone)
    assert all("could not be placed" in u["reason"] for u in g["unregistered"])


def test_multiview_wrong_separate_model_is_rejected(sample, tmp_path):
    """A separate model whose shape disagrees with its control points (a photo placed wrongly by look-alike
    matches) is refused by the residual check, not placed."""
    dst, truth, names = _mv_project(sample, tmp_path, "mv_sub_wrong")
    half = len(names) // 2
    groups = [names[:half], names[half:]]
    frames = [similarity(0.37, [120.0, 10.0, -20.0], [40.0, -20.0, 5.0]),
              similarity(2.9, [-70.0, 35.0, 160.0], [-300.0, 80.0, 12.0])]
    rec = split_reconstruction(dst, groups, frames)
    # turn the separate model's photo with the most picks by 20 degrees about its own centre: its rays go elsewhere
    picks = _picks_per_photo(dst)
    im = max(rec["models"][0]["images"], key=lambda i: (picks.get(i["name"], 0), i["name"]))
    M = np.asarray(im["cam_from_model"])
    c = -M[:3, :3].T @ M[:3, 3]
    R = Rotation.from_euler("y", 20.0, degrees=True).as_matrix() @ M[:3, :3]
    M[:3, :3], M[:3, 3] = R, -R @ c
    im["cam_from_model"] = M.tolist()
    atomic_write_json(dst / "out" / "sfm" / "reconstruction.json", rec)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        doc = json.loads(run_georef(Project(dst), _no_progress).outputs["cameras"].read_text())
    g = doc["georegistration"]
    assert g["models"][0]["status"] == "georegistered"
    sub = g["models"][1]
    # either the whole model is refused, or the turned photo is left out of it; its wrong pose never reaches
    # cameras.json (placed, it was placed on its own, by resection, within centimetres)
    assert sub["status"] == "unregistered" or im["name"] in sub.get("rejected_views", {}), sub
    truth_by = {Path(p["photo"]).name: p for p in truth["photos"]}
    for v in doc["views"]:
        assert np.linalg.norm(np.asarray(v["center_enu"]) - truth_by[v["name"]]["center_enu"]) < 0.3, v["name"]
        assert _rot_err_deg(v["cam_from_world"], truth_by[v["name"]]["cam_from_world"]) < 0.3, v["name"]
    assert set(groups[0]) <= {v["name"] for v in doc["views"]}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        doc = json.loads(run_georef(Project(dst), _no_progress, GeorefOptions(resect_unplaced=False))
                         .outputs["cameras"].read_text())
    assert im["name"] not in {v["name"] for v in doc["views"]}
    assert im["name"] in {u["name"] for u in doc["georegistration"]["unregistered"]}


def test_multiview_photo_left_out_by_sfm_is_resected(sample, tmp_path):
    """A photo SfM did not register, with picks of enough control points, is placed on its own (resection) with
    the main model's shared camera; with resection off it stays unregistered."""
    dst, truth, names = _mv_project(sample, tmp_path, "mv_resect")
    picks = _picks_per_photo(dst)
    lone = max(names, key=lambda n: (picks.get(n, 0), n))
    assert picks[lone] >= 4
    rec = split_reconstruction(dst, [[n for n in names if n != lone]],
                                [similarity(0.37, [120.0, 10.0, -20.0], [40.0, -20.0, 5.0])])
    rec["unregistered"] = [{"name": lone, "reason": "too few verified matches with the registered photos"}]
    atomic_write_json(dst / "out" / "sfm" / "reconstruction.json", rec)
    doc = json.loads(run_georef(Project(dst), _no_progress).outputs["cameras"].read_text())
    g = doc["georegistration"]
    assert sorted(v["name"] for v in doc["views"]) == names and g["unregistered"] == []
    (r,) = g["resected"]
    assert r["name"] == lone and r["intrinsics_from"].startswith("main model") and r["rms_px"] < 3.0
    truth_by = {Path(p["photo"]).name: p for p in truth["photos"]}
    v = next(v for v in doc["views"] if v["name"] == lone)
    assert 0.001 < np.linalg.norm(np.asarray(v["center_enu"]) - truth_by[lone]["center_enu"]) < 0.3
    assert 0.0005 < _rot_err_deg(v["cam_from_world"], truth_by[lone]["cam_from_world"]) < 0.2
    # its pose error is stated (the resection's covariance), so the solve carries it: the truth inside the stated
    # 99.9 % ellipsoid of the centre, which is neither absurdly sharp nor vague
    pu = g["pose_uncertainty"]["views"][lone]
    assert pu["source"] == "resection" and pu["model"] is None
    Cc = np.asarray(pu["covariance_rotation_centre"])[3:, 3:]
    e = np.asarray(v["center_enu"]) - truth_by[lone]["center_enu"]
    assert e @ np.linalg.solve(Cc, e) < 16.27 and 0.002 < np.sqrt(np.linalg.eigvalsh(Cc).max()) < 1.0
    doc = json.loads(run_georef(Project(dst), _no_progress, GeorefOptions(resect_unplaced=False))
                     .outputs["cameras"].read_text())
    assert lone not in [v["name"] for v in doc["views"]]
    assert [u["name"] for u in doc["georegistration"]["unregistered"]] == [lone]


def test_multiview_resection_checks_a_wrong_sfm_focal(sample, tmp_path):
    """SfM's focal 8 % off (a weak model): a photo resected with it lands metres off with small residuals; its
    control points disagree with that focal, so the resection refines the focal, and the photo is placed only
    if they then fix its position (else it stays unplaced, with the reason): never metres off."""
    dst, truth, names = _mv_project(sample, tmp_path, "mv_resect_focal")
    picks = _picks_per_photo(dst)
    lone = max(names, key=lambda n: (picks.get(n, 0), n))
    rec = split_reconstruction(dst, [[n for n in names if n != lone]],
                                [similarity(0.37, [120.0, 10.0, -20.0], [40.0, -20.0, 5.0])])
    for im in rec["images"]:
        im["intrinsics"] = {**im["intrinsics"], "fx": im["intrinsics"]["fx"] * 0.92,
                            "fy": im["intrinsics"]["fy"] * 0.92}
    rec["unregistered"] = [{"name": lone, "reason": "too few verified matches with the registered photos"}]
    atomic_write_json(dst / "out" / "sfm" / "reconstruction.json", rec)
    truth_by = {Path(p["photo"]).name: p for p in truth["photos"]}

    def run(opts):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return json.loads(run_georef(Project(dst), _no_progress, opts).outputs["cameras"].read_text())

    # without the focal check (never refined) and without the shared camera's adjustment: placed, but metres off
    doc = run(GeorefOptions(resect_focal_disagree_sigma=1e9, adjust_camera=False))
    v = next(v for v in doc["views"] if v["name"] == lone)
    err_fixed = np.linalg.norm(np.asarray(v["center_enu"]) - truth_by[lone]["center_enu"])
    assert 0.5 < err_fixed < 20.0, err_fixed
    # with it: the refined focal is near the truth, and the photo is within 0.5 m or not placed
    doc = run(GeorefOptions(adjust_camera=False))
    placed = [v for v in doc["views"] if v["name"] == lone]
    if placed:
        r = next(r for r in doc["georegistration"]["resected"] if r["name"] == lone)
        true_f = truth_by[lone]["intrinsics"]["fx"]
        assert 0.0 < abs(r["focal_check"]["refined_focal_px"] / true_f - 1) < 0.03, r["focal_check"]
        assert "focal refined" in r["intrinsics_from"]
        assert 0.001 < np.linalg.norm(np.asarray(placed[0]["center_enu"]) - truth_by[lone]["center_enu"]) < 0.5
        # what the solve carries: its pose and the refined focal on one factor (a group of one photo), the
        # focal's row of it the focal's stated sigma
        pv = doc["georegistration"]["pose_uncertainty"]["views"][lone]
        assert pv["source"] == "resection" and pv["model"] == f"resection[{lone}]", pv
        K = np.asarray(pv["sfm_intrinsics_factor"]["factor"])
        assert pv["sfm_intrinsics_factor"]["params"] == ["f"]
        assert np.isclose(float(np.sqrt(K @ K.T)[0, 0]), r["focal_check"]["sigma_focal_px"], rtol=1e-6)
    else:
        (u,) = [u for u in doc["georegistration"]["unregistered"] if u["name"] == lone]
        assert "fix it only to" in u["reason"], u


# ----------------------------------------------------------------------------------------------------------
# The shared camera adjusted from the control points; honest stated uncertainty; the main model checked
# ----------------------------------------------------------------------------------------------------------
def _wrong_camera_reconstruction(dst: Path, names: list[str], lone: str, *, f_scale: float, dcx: float,
                                 dcy: float) -> dict:
    return wrong_camera_reconstruction(dst, names, lone, similarity(0.37, [120.0, 10.0, -20.0], [40.0, -20.0, 5.0]),
                                       f_scale=f_scale, dcx=dcx, dcy=dcy)


def _errors(doc: dict, truth: dict) -> dict[str, tuple[float, float, float | None, float | None]]:
    """photo -> (centre error m, rotation error deg, |error| / stated sigma, squared Mahalanobis distance)."""
    truth_by = {Path(p["photo"]).name: p for p in truth["photos"]}
    unc = doc["georegistration"].get("view_uncertainty", {})
    out = {}
    for v in doc["views"]:
        d = np.asarray(v["center_enu"]) - truth_by[v["name"]]["center_enu"]
        u = unc.get(v["name"], {})
        ratio = float(np.linalg.norm(d) / u["sigma_centre_m"]) if u.get("sigma_centre_m") else None
        m2 = (float(d @ np.linalg.solve(np.asarray(u["cov_centre_enu_m2"]), d))
              if u.get("cov_centre_enu_m2") is not None else None)
        out[v["name"]] = (float(np.linalg.norm(d)), _rot_err_deg(v["cam_from_world"],
                                                                truth_by[v["name"]]["cam_from_world"]), ratio, m2)
    return out


def test_multiview_shared_camera_adjusted_and_uncertainty_honest(sample, tmp_path):
    """SfM's shared camera 3 % short in focal with its principal point 20 px off (what pycolmap gave on the
    synthetic incidents): the photos' own picks refine focal and principal point jointly with the poses (kept:
    the held-out residual drops), the photos land centimetres from the truth, and every stated covariance
    covers the error (the truth inside the 95 % ellipsoid), without being wildly pessimistic. The picks are stated
    at 1 px (a hand pick's default), not the generator's 0.5 px: at 0.5 px the fit with SfM's wrong camera already
    states a centre sigma near its error (1.45 sigmas for the worst photo, not beyond 3), which is not what this
    test is about."""
    dst, truth, names = _mv_project(sample, tmp_path, "mv_adjust")
    toml = dst / "project.toml"
    assert "pick_sigma_px = 0.5" in toml.read_text()
    toml.write_text(toml.read_text().replace("pick_sigma_px = 0.5", "pick_sigma_px = 1.0"))
    picks = _picks_per_photo(dst)
    lone = max(names, key=lambda n: (picks.get(n, 0), n))
    rec = _wrong_camera_reconstruction(dst, names, lone, f_scale=0.97, dcx=-20.0, dcy=13.0)
    atomic_write_json(dst / "out" / "sfm" / "reconstruction.json", rec)
    true_intr = next(p for p in truth["photos"] if p["set"] == "multiview")["intrinsics"]

    def run(opts):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return json.loads(run_georef(Project(dst), _no_progress, opts).outputs["cameras"].read_text())

    off = _errors(run(GeorefOptions(adjust_camera=False)), truth)
    doc = run(GeorefOptions())
    on = _errors(doc, truth)
    (adj,) = doc["georegistration"]["camera_adjustment"]
    assert adj["chosen"] != "sfm", adj
    ho = adj["held_out_rms_px"]
    assert ho[adj["chosen"]] < 0.7 * ho["sfm"], ho
    it = doc["views"][0]["intrinsics"]
    sg = adj["sigma_refined"]
    assert 0.0 < abs(it["fx"] / true_intr["fx"] - 1) < 0.01, (it["fx"], true_intr["fx"])
    # the principal point within 3 of its stated sigmas (cy, with the cameras' pitch, is the weak one)
    for k in ("cx", "cy"):
        assert 0.0 < abs(it[k] - true_intr[k]) < 3.0 * sg[k] and sg[k] < 15.0, (k, it[k], true_intr[k], sg)
    assert 1.0 < adj["condition"] < 1e4 and 0.0 < adj["sigma_intrinsics"]["f"] < 0.01 * true_intr["fx"], adj
    # positions: worse than 0.3 m somewhere with SfM's camera; within 0.25 m everywhere with the adjusted one
    assert max(e[0] for e in off.values()) > 0.3, off
    assert 0.001 < max(e[0] for e in on.values()) < 0.25, on
    assert 0.0005 < max(e[1] for e in on.values()) < min(1.2, max(e[1] for e in off.values())), (on, off)
    unc = doc["georegistration"]["view_uncertainty"]
    for name, e in on.items():  # rotation errors within 3 stated sigmas too
        assert e[1] < 3.0 * unc[name]["sigma_rotation_deg"], (name, e, unc[name]["sigma_rotation_deg"])
    # honesty: every photo has a covariance; the truth inside its 95 % ellipsoid (chi-square 3 dof: 7.81) for
    # at least 85 % of the photos, and the mean squared Mahalanobis distance neither tiny nor large (3 expected)
    m2 = [e[3] for e in on.values()]
    assert all(x is not None for x in m2), on
    assert sum(x < 7.81 for x in m2) >= 0.85 * len(m2), m2
    assert 0.2 < float(np.mean(m2)) < 6.0, m2
    # with the adjustment off the stated sigmas do not cover the error: that is what it fixes
    worst = max((e for e in off.values() if e[2] is not None), key=lambda e: e[0])
    assert worst[2] > 3.0, off
    # what the solve carries: the adjusted photos as one group sharing the adjustment's error, their poses and the
    # refined intrinsics on one factor; each photo's marginal from it covers its centre error as well
    pu = doc["georegistration"]["pose_uncertainty"]
    adjusted = {n: v for n, v in pu["views"].items() if v["source"] == "camera_adjustment"}
    assert adjusted and {v["model"] for v in adjusted.values()} == {"camera_adjustment[0]"}, pu["views"]
    assert pu["models"]["camera_adjustment[0]"]["kind"] == "camera_adjustment"
    from workbench.georef.shared_camera import INTRINSIC_SETS

    truth_by = {Path(p["photo"]).name: p for p in truth["photos"]}
    m2 = []
    for n, v in adjusted.items():
        assert v["sfm_intrinsics_factor"]["params"] == list(INTRINSIC_SETS[adj["chosen"]])
        F = np.asarray(v["sfm_factor"])
        d = np.asarray(next(w for w in doc["views"] if w["name"] == n)["center_enu"]) - truth_by[n]["center_enu"]
        m2.append(float(d @ np.linalg.solve((F @ F.T)[3:, 3:], d)))
    print("adjusted photos' centre Mahalanobis^2 (3 dof):", np.round(m2, 2))
    assert sum(x < 7.81 for x in m2) >= 0.85 * len(m2) and 0.2 < float(np.mean(m2)) < 6.0, m2
    # the photo SfM left out, resected with SfM's camera and then re-posed by the adjustment, carries the
    # adjustment's error with the others, not the replaced resection's (until session 19 it did: on draw 992002
    # of the calibration benchmark four such photos stated a Mahalanobis^2 / 6 of 124-388)
    assert lone in adjusted, (lone, pu["views"].get(lone))


def test_multiview_main_model_is_checked(sample, tmp_path):
    """A main model that fails the separate-model checks (SfM's focal 15 % off: picks far from the fit) is not
    kept, and its photos are tried on their own; when none of them passes either, the stage errors, naming the
    main model's failed check and every photo's reason (never a model metres off, silently kept)."""
    dst, truth, names = _mv_project(sample, tmp_path, "mv_main_checked")
    picks = _picks_per_photo(dst)
    lone = max(names, key=lambda n: (picks.get(n, 0), n))
    rec = _wrong_camera_reconstruction(dst, names, lone, f_scale=0.85, dcx=0.0, dcy=0.0)
    atomic_write_json(dst / "out" / "sfm" / "reconstruction.json", rec)

    def run(opts):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return json.loads(run_georef(Project(dst), _no_progress, opts).outputs["cameras"].read_text())

    for opts in (GeorefOptions(), GeorefOptions(resect_unplaced=False)):
        with pytest.raises(InputError, match=r"main.*control-point RMS residual") as ei:
            run(opts)
        if opts.resect_unplaced:
            assert "no photo could be placed on its own" in str(ei.value) and lone in str(ei.value)
    # the same model with SfM's focal right is placed, and checked: its figures are reported
    rec = _wrong_camera_reconstruction(dst, names, lone, f_scale=1.0, dcx=0.0, dcy=0.0)
    atomic_write_json(dst / "out" / "sfm" / "reconstruction.json", rec)
    doc = run(GeorefOptions())
    g = doc["georegistration"]
    main = g["models"][0]
    assert main["status"] == "georegistered" and main["n_fitting_triangulated"] >= 3, main
    assert 0.0 < main["rms_px"] < 3.0 and 0.0 < main["sigma_centre_max_m"] < 0.5, main
    # with SfM's camera right, the adjustment (whichever set the held-out picks choose) does not make it worse
    on = _errors(doc, truth)
    off = _errors(run(GeorefOptions(adjust_camera=False)), truth)
    assert sorted(on) == sorted(off) == sorted(names)
    assert 0.0005 < max(e[0] for e in on.values()) < max(0.15, 1.5 * max(e[0] for e in off.values())), (on, off)
    assert sum(e[3] < 7.81 for e in on.values() if e[3] is not None) >= 0.85 * len(on), on


def test_multiview_unchecked_camera_needs_picks_to_check_its_focal(sample, tmp_path):
    """A photo resected with SfM's camera when no placed model checked that camera (the main model refused: its
    focal 15 % off) and with too few picks (5) to check the focal itself is left out, with the reason; on the
    full sample such a photo (focal 8 % off) was placed 2.5 m off with a 0.41 m 1-sigma. With the model placed
    (its camera right, so checked by its control points) the same 5-pick photo is placed, within 0.5 m."""
    dst, truth, names = _mv_project(sample, tmp_path, "mv_unchecked")
    picks = _picks_per_photo(dst)
    few = max(names, key=lambda n: (picks.get(n, 0), n))
    cp = json.loads((dst / "control_points.json").read_text())
    keep = sorted(p["name"] for p in cp["points"] if few in p["pixels"])[:5]
    for p in cp["points"]:
        if p["name"] not in keep:
            p["pixels"].pop(few, None)
    cp["points"] = [p for p in cp["points"] if p["pixels"]]
    (dst / "control_points.json").write_text(json.dumps(cp))
    opts = GeorefOptions(adjust_camera=False)

    def run():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return json.loads(run_georef(Project(dst), _no_progress, opts).outputs["cameras"].read_text())

    atomic_write_json(dst / "out" / "sfm" / "reconstruction.json",
                      _wrong_camera_reconstruction(dst, names, few, f_scale=0.85, dcx=0.0, dcy=0.0))
    try:
        doc = run()
        reasons = {u["name"]: u["reason"] for u in doc["georegistration"]["unregistered"]}
        assert doc["georegistration"]["models"][0]["status"] == "unregistered"
        assert few in reasons, [v["name"] for v in doc["views"]]
        why = reasons[few]
    except InputError as exc:
        why = str(exc).split(f"{few}: ", 1)[1]
    assert "checked by no placed SfM model" in why and "of its 5 picks fit with it: too few to check the focal" \
        in why, why
    atomic_write_json(dst / "out" / "sfm" / "reconstruction.json",
                      _wrong_camera_reconstruction(dst, names, few, f_scale=1.0, dcx=0.0, dcy=0.0))
    doc = run()
    (v,) = [v for v in doc["views"] if v["name"] == few]
    truth_by = {Path(p["photo"]).name: p for p in truth["photos"]}
    assert 0.001 < np.linalg.norm(np.asarray(v["center_enu"]) - truth_by[few]["center_enu"]) < 0.5
    assert [r["name"] for r in doc["georegistration"]["resected"]] == [few]


def test_names_of_photos_that_do_not_exist_are_blamed_on_their_file(sample, tmp_path):
    """A cameras.json view or a control point's pixels keyed by a photo the incident does not have were accepted
    (the error came later, blaming correspondences.json, or the point was silently left out) (issue 20)."""
    from workbench.synth.handpicks import write_known_cameras

    dst = _fresh(sample, tmp_path, "unknown_names")
    write_known_cameras(dst, "panorama")
    doc = json.loads((dst / "cameras.json").read_text())
    good = doc["views"][1]["name"]
    doc["views"][1]["name"] = "renamed.jpg"
    (dst / "cameras.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"cameras\.json: views\[1\]\.name: view 'renamed\.jpg' is not a photo"):
        run_georef(Project(dst), _no_progress)
    doc["views"][1]["name"] = good
    (dst / "cameras.json").write_text(json.dumps(doc))
    cps = json.loads((dst / "control_points.json").read_text())
    point = cps["points"][0]
    point["pixels"]["no_such_photo.jpg"] = [10.0, 10.0]
    (dst / "control_points.json").write_text(json.dumps(cps))
    with pytest.raises(InputError, match=rf"control_points\.json: point '{point['name']}': pixels of photo "
                                         r"'no_such_photo\.jpg' is not a photo"):
        run_georef(Project(dst), _no_progress)


@pytest.mark.slow
def test_bench_georef_multiview_script(small_incident, tmp_path):
    """scripts/bench_georef_multiview.py, which checks the full sample's figures (the suite never reads
    projects/), runs and meets its bands on the small generated incident: its two scenarios that this file's tests
    do not already solve as it sets them (SfM's camera off with the picks at the generator's 0.5 px; a focal 8 %
    off). Its other three are this file's situations on the same incident, with the same or tighter bands:
    ``exact`` is test_multiviewsimilarity's (the similarity, the SfM camera chosen, centres within 0.10 m),
    ``two_models`` test_multiview_separate_models_are_placed's, ``main_bad`` test_multiview_main_model_is_checked's
    (the main model refused); `--scenarios` unknown is refused."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_georef_multiview",
                                                  REPO / "scripts" / "bench_georef_multiview.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert set(bench.SCENARIOS) == {"exact", "two_models", "shared_cam", "wrong_focal", "main_bad"}
    out = tmp_path / "bench.json"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = bench.main(["--incident", str(small_incident[0]), "--out", str(out),
                         "--scenarios", "shared_cam,wrong_focal"])
    doc = json.loads(out.read_text())
    assert rc == 0 and doc["failed"] == [], doc["failed"]
    rows = doc["rows"]
    assert {k for k, r in rows.items() if isinstance(r, dict)} == {"shared_cam", "wrong_focal"}
    assert all(c["ok"] for r in ("shared_cam", "wrong_focal") for c in rows[r]["checks"]) and \
        len(rows["shared_cam"]["checks"]) == 2 and len(rows["wrong_focal"]["checks"]) == 2
    assert 0.001 < rows["shared_cam"]["max_centre_m"] < 0.25 and rows["shared_cam"]["placed"] == 8
    with pytest.raises(SystemExit):
        bench.main(["--incident", str(small_incident[0]), "--out", str(out), "--scenarios", "exact,nope"])
