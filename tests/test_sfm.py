"""SfM with pycolmap on a small rendered multi-view set with exact cameras; COLMAP <-> Brown conversions.

The set (workbench.intrinsics.synthetic): 8 photos of 480x360 of a textured ground and three boxes, from an
arc of 140 degrees about 26 m from the centre, through a camera with k1 = -0.08, k2 = 0.012.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from PIL import Image

from workbench.core.camera import CameraIntrinsics
from workbench.errors import SettingsError, StageError
from workbench.intrinsics.sfm import (CAMERA_MODELS, SfmOptions, colmap_params_from_intrinsics,
                                      intrinsics_from_colmap, run_sfm, similarity_align)
from workbench.intrinsics.synthetic import write_multiview_set

pycolmap = pytest.importorskip("pycolmap")


@pytest.fixture(scope="module")
def mv_set(tmp_path_factory):
    folder = tmp_path_factory.mktemp("mv") / "photos"
    truth = write_multiview_set(folder, 8, seed=0)
    return folder, truth


@pytest.fixture(scope="module")
def sfm_result(mv_set):
    folder, truth = mv_set
    return run_sfm(sorted(folder.glob("*.jpg")), options=SfmOptions(seed=0, num_threads=2))


def _aligned(result, truth):
    tp = {p["name"]: p for p in truth["photos"]}
    src = np.array([v.center_model for v in result.views])
    dst = np.array([tp[v.name]["center"] for v in result.views])
    s, R, t, res = similarity_align(src, dst)
    return tp, s, R, t, res


def test_focal_distortion_and_positions(sfm_result, mv_set):
    _, truth = mv_set
    true = CameraIntrinsics.from_dict(truth["intrinsics"])
    assert len(sfm_result.views) == 8 and sfm_result.unregistered == []
    intr = sfm_result.views[0].intrinsics
    assert all(v.intrinsics == intr for v in sfm_result.views)  # one camera
    focal_err = abs(intr.fx / true.fx - 1)
    assert 0.0 < focal_err < 0.03, intr.fx
    # principal point is not refined: it stays at the image centre in our convention
    assert abs(intr.cx - (480 - 1) / 2) < 1e-9 and abs(intr.cy - (360 - 1) / 2) < 1e-9
    # distortion: same sign and size as the truth, and the radial profile agrees at the image corner
    assert -0.15 < intr.k1 < -0.02
    r = np.hypot(240, 180) / true.fx
    d_true = true.k1 * r**2 + true.k2 * r**4
    d_est = intr.k1 * r**2 + intr.k2 * r**4
    assert abs(d_est - d_true) < 0.02
    tp, s, R, t, res = _aligned(sfm_result, truth)
    rms = float(np.sqrt(np.mean(res**2)))
    assert 0.0 < rms < 0.4, rms  # metres, cameras ~26 m from the scene
    assert 0.02 < sfm_result.stats["mean_reprojection_error_px"] < 1.0


def test_poses_are_cam_from_model(sfm_result, mv_set):
    """cam_from_model composed with the alignment is the true cam_from_world (rotation within 1 degree)."""
    _, truth = mv_set
    tp, s, R, t, _ = _aligned(sfm_result, truth)
    for v in sfm_result.views:
        M = v.cam_from_model
        Rm = M[:3, :3]
        assert np.allclose(Rm @ Rm.T, np.eye(3), atol=1e-9) and abs(np.linalg.det(Rm) - 1) < 1e-9
        R_cam_from_world = Rm @ R.T  # world = s R model + t
        R_true = np.asarray(tp[v.name]["cam_from_world"])[:3, :3]
        ang = np.degrees(np.arccos(np.clip((np.trace(R_cam_from_world @ R_true.T) - 1) / 2, -1, 1)))
        assert ang < 1.0, (v.name, ang)
    # the 3-D points reproject into the photos that see them, in our pixel convention
    xyz = sfm_result.points_xyz
    assert len(xyz) == sfm_result.n_points_total > 100
    v = sfm_result.views[0]
    cam = xyz @ v.cam_from_model[:3, :3].T + v.cam_from_model[:3, 3]
    uv = v.intrinsics.project(cam[cam[:, 2] > 0])
    inside = v.intrinsics.in_image(uv)
    assert inside.sum() > 30


@pytest.mark.parametrize("model", CAMERA_MODELS)
def test_colmap_camera_conversion_is_exact(model):
    """Our projection of a converted COLMAP camera equals COLMAP's own, minus half a pixel."""
    ours_in = CameraIntrinsics(width=640, height=480, fx=500.0, fy=500.0 if "SIMPLE" in model or model == "RADIAL"
                               else 505.0, cx=321.3, cy=238.9,
                               k1=0.0 if "PINHOLE" in model else -0.1,
                               k2=0.02 if model in ("RADIAL", "OPENCV") else 0.0,
                               p1=0.001 if model == "OPENCV" else 0.0, p2=-0.0007 if model == "OPENCV" else 0.0)
    params, dropped = colmap_params_from_intrinsics(model, ours_in)
    assert dropped == []
    cam = pycolmap.Camera.create_from_model_name(1, model, 500.0, 640, 480)
    cam.params = params
    back = intrinsics_from_colmap(model, 640, 480, cam.params)
    assert back == ours_in
    rng = np.random.default_rng(1)
    P = np.column_stack([rng.uniform(-0.5, 0.5, 50), rng.uniform(-0.4, 0.4, 50), rng.uniform(1, 3, 50)])
    theirs = np.asarray(cam.img_from_cam(P))
    assert np.max(np.abs(back.project(P) - (theirs - 0.5))) < 1e-9


def test_conversion_reports_dropped_terms_and_refuses_unknown_models():
    intr = CameraIntrinsics(width=10, height=10, fx=5, fy=5, cx=4.5, cy=4.5, k1=0.1, p1=0.01, k3=0.2)
    _, dropped = colmap_params_from_intrinsics("RADIAL", intr)
    assert dropped == ["k3", "p1"]
    with pytest.raises(ValueError, match="FULL_OPENCV"):
        intrinsics_from_colmap("FULL_OPENCV", 10, 10, [1] * 12)


def test_options_are_validated():
    with pytest.raises(SettingsError, match="unknown key"):
        SfmOptions.from_dict({"camera_modle": "RADIAL"})
    with pytest.raises(SettingsError, match="camera_model"):
        SfmOptions(camera_model="FISHEYE")
    with pytest.raises(SettingsError, match="matcher"):
        SfmOptions(matcher="vocab")
    with pytest.raises(SettingsError, match="init_max_forward_motion"):
        SfmOptions(init_max_forward_motion=0)
    with pytest.raises(SettingsError, match="sift_peak_threshold"):
        SfmOptions(sift_peak_threshold=0.0)
    # the features that keep wide-baseline photos matched (issue 4): low contrast threshold, affine SIFT, DSP
    d = SfmOptions()
    assert d.sift_peak_threshold < 0.0067 and d.sift_affine_shape and d.sift_domain_size_pooling
    fm = SfmOptions.forward_motion()
    assert fm.init_max_forward_motion == 1.0 and fm.init_min_tri_angle_deg == 4 and not fm.refine_distortion


def test_similarity_align_recovers_a_known_similarity():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(10, 3))
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([0.3, -0.2, 1.1]).as_matrix()
    dst = 2.5 * src @ R.T + [1, 2, 3]
    s, R2, t, res = similarity_align(src, dst)
    assert abs(s - 2.5) < 1e-9 and np.allclose(R2, R, atol=1e-9) and np.allclose(t, [1, 2, 3], atol=1e-9)
    assert res.max() < 1e-9


def test_no_model_is_a_clear_error(tmp_path):
    for i in range(3):
        Image.fromarray(np.full((120, 160, 3), 100 + i, np.uint8)).save(tmp_path / f"blank_{i}.jpg")
    with pytest.raises(StageError, match="no model"):
        run_sfm(sorted(tmp_path.glob("*.jpg")), options=SfmOptions(forward_motion_retry=False))


# -- the stage --------------------------------------------------------------------------------------------
PROJECT_TOML = """
[incident]
name = "sfm test"
date = 2024-05-01

[location]
lat = 40.878
lon = -73.9215
crs = "EPSG:32618"

[[consist]]
number = "1"
type = "shoreliner"

[camera]
source = "sfm"
photos = "photos/multiview"
"""


def test_sfm_stage_writes_reconstruction(tmp_path, mv_set):
    from workbench.files.intrinsics import resolve_intrinsics
    from workbench.pipeline import stage
    from workbench.project import Project
    from workbench.runner import Runner, StageResult, StageSpec

    folder, truth = mv_set
    root = tmp_path / "inc"
    (root / "photos").mkdir(parents=True)
    shutil.copytree(folder, root / "photos" / "multiview")
    # a photo nothing can be matched in: reported as unregistered, with the reason
    Image.fromarray(np.full((360, 480, 3), 128, np.uint8)).save(root / "photos" / "multiview" / "zz_blank.jpg")
    (root / "project.toml").write_text(PROJECT_TOML)
    project = Project(root)
    # a stand-in for the `inputs` stage the sfm stage depends on (keeps this test independent of the others)
    inputs = StageSpec("inputs", "stand-in", lambda project, progress: StageResult(outputs={}))
    runner = Runner(project, [inputs, stage("sfm")])
    runner.run()
    rec = json.loads((root / "out" / "sfm" / "reconstruction.json").read_text())
    assert set(rec) >= {"images", "unregistered", "points", "intrinsics_source", "stats"}
    assert rec["intrinsics_source"] == "sfm"
    assert [im["name"] for im in rec["images"]] == [f"mv_{i:02d}.jpg" for i in range(8)]
    assert rec["images"][0]["image"] == "photos/multiview/mv_00.jpg"
    assert rec["unregistered"][0]["name"] == "zz_blank.jpg" and "no features" in rec["unregistered"][0]["reason"]
    assert rec["points"]["n"] == len(rec["points"]["xyz"]) == len(rec["points"]["rgb"]) > 100
    assert np.asarray(rec["images"][0]["cam_from_model"]).shape == (4, 4)
    # the EXIF focal (exact for these renders) was the initial camera
    assert rec["prior"]["source"] == "exif" and rec["prior"]["used"] is True
    true_f = truth["intrinsics"]["fx"]
    assert abs(rec["prior"]["focal_px"] / true_f - 1) < 1e-3
    f = rec["images"][0]["intrinsics"]["fx"]
    assert 0.0 < abs(f / true_f - 1) < 0.03
    stats = json.loads((root / "out" / "sfm" / "stats.json").read_text())
    assert stats["route"] == "multiview" and stats["intrinsics_source"] == "sfm" and stats["n_registered"] == 8
    # idempotent: a second run skips the stage
    st = {s.name: s.status for s in runner.run()}
    assert st["sfm"] == "done"
    assert json.loads(project.state_path.read_text())["sfm"]["status"] == "done"
    # the route and intrinsics a later stage sees
    choice = resolve_intrinsics(project)
    assert choice.source == "sfm" and choice.focal_known["mv_00.jpg"] and not choice.focal_known["zz_blank.jpg"]


def test_separate_models_are_kept(tmp_path, mv_set):
    """Two scenes that share nothing, photographed in one folder: the larger set is the main model, the other
    is kept as a separate model in its own frame (its cameras right up to a similarity), its photos listed as
    unregistered in the main model with the index of their model. (Plain SIFT to keep the test fast.)"""
    folder, truth = mv_set
    both = tmp_path / "both"
    shutil.copytree(folder, both)
    other = tmp_path / "other"
    truth_b = write_multiview_set(other, 6, seed=3)
    for p in sorted(other.glob("*.jpg")):
        shutil.copy(p, both / p.name.replace("mv_", "zz_"))
    res = run_sfm(sorted(both.glob("*.jpg")),
                  options=SfmOptions(seed=0, sift_affine_shape=False, sift_domain_size_pooling=False))
    assert [v.name for v in res.views] == [f"mv_{i:02d}.jpg" for i in range(8)]
    # COLMAP also built a model overlapping the main one: dropped, it adds no photo
    assert len(res.models) == 1, [[v.name for v in m.views] for m in res.models]
    sub = res.models[0]
    names = [v.name for v in sub.views]
    assert len(names) >= 3 and all(n.startswith("zz_") for n in names), names
    assert sorted(u["name"] for u in res.unregistered) == [f"zz_{i:02d}.jpg" for i in range(6)]
    for u in res.unregistered:
        if u["name"] in names:
            assert u["model"] == 0 and f"separate model of {len(names)} photos" in u["reason"]
        else:
            assert "model" not in u and "too few verified matches" in u["reason"]
    assert res.stats["n_models"] == 2 and res.stats["separate_models"] == [len(names)]
    assert res.stats["n_in_separate_models"] == len(names)
    tp = {p["name"].replace("mv_", "zz_"): p for p in truth_b["photos"]}
    src = np.array([v.center_model for v in sub.views])
    dst = np.array([tp[v.name]["center"] for v in sub.views])
    s, R, t, err = similarity_align(src, dst)
    assert 0.0 < float(np.sqrt(np.mean(err ** 2))) < 0.5, err
    for v in sub.views:
        Rt = np.asarray(tp[v.name]["cam_from_world"])[:3, :3]
        ang = np.degrees(np.arccos(np.clip((np.trace(v.cam_from_model[:3, :3] @ R.T @ Rt.T) - 1) / 2, -1, 1)))
        assert ang < 1.5, (v.name, ang)
    assert sub.n_points_total > 50 and len(sub.points_xyz) == sub.n_points_total
    doc = res.to_json()
    assert [im["name"] for im in doc["models"][0]["images"]] == names
    assert doc["models"][0]["points"]["n"] == sub.n_points_total
    assert doc["models"][0]["stats"]["n_registered"] == len(names)
    json.dumps(doc)  # serialisable
