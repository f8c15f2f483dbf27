"""The stitch stage against ground truth: focal and rotations of views cut from a real photo by known
rotations (with and without lens distortion) and of a small generated incident's panorama set; the distractor
rejected; parallax refused; the stage's files, with a true 3D point landing where the panorama shows it."""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from workbench.core.camera import CameraIntrinsics
from workbench.core.panorama import PanoramaModel
from workbench.errors import InputError
from workbench.stitch import StitchOptions, stitch_photos
from workbench.stitch.cutviews import align_rotation, cut_views, grid_rotations, rotation_errors_deg

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
STITCHING = DATA / "stitching"
SMALL = (480, 360)  # the generated incident's 800x600 photos reduced by 0.6

needs_data = pytest.mark.skipif(not STITCHING.is_dir(), reason="../shared/data/stitching is not there")
FAST = StitchOptions(compose=False)


# ----------------------------------------------------------------------------------------------------------
# fixtures
# ----------------------------------------------------------------------------------------------------------
def _view_intrinsics(k1: float) -> CameraIntrinsics:
    w, h = SMALL
    f = w / 2 / np.tan(np.radians(15.0))  # 30 degrees horizontal field of view
    return CameraIntrinsics(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2 + 4.0, cy=(h - 1) / 2 - 3.0, k1=k1)


def _cut_set(tmp: Path, k1: float, kind: str = "grid"):
    """Views cut from a real photo (Petra, CC-BY-3.0; see ../shared/data/SOURCES.md): four in a 2 x 2 grid, or
    a single row of three (12 degrees apart: the focal is weakly constrained there)."""
    src = cv2.imread(str(STITCHING / "skimage_pano_petra" / "DFM_4210.jpg"))
    intr = _view_intrinsics(k1)
    rots = grid_rotations([-9.0, 9.0], [-6.0, 6.0], seed=1) if kind == "grid" else \
        grid_rotations([-12.0, 0.0, 12.0], [0.0], seed=2)
    views = cut_views(src, 2280.0, rots, intr)
    tmp.mkdir(parents=True, exist_ok=True)
    for v in views:
        cv2.imwrite(str(tmp / v.name), v.image, [cv2.IMWRITE_JPEG_QUALITY, 95])
    return [tmp / v.name for v in views], {v.name: v.cam_from_src for v in views}, intr


@pytest.fixture(scope="module")
def sample_small(small_incident, tmp_path_factory):
    """The panorama photos of the session's small generated incident (tests/conftest.py) reduced to 480x360,
    their true intrinsics and cam_from_world."""
    root, truth = small_incident
    out = tmp_path_factory.mktemp("sample_small")
    paths, intr, rot, photos = [], {}, {}, []
    for ph in truth["photos"]:
        if ph["set"] != "panorama":
            continue
        name = Path(ph["photo"]).name
        img = cv2.imread(str(root / ph["photo"]))
        cv2.imwrite(str(out / name), cv2.resize(img, SMALL, interpolation=cv2.INTER_AREA),
                    [cv2.IMWRITE_JPEG_QUALITY, 95])
        paths.append(out / name)
        K = CameraIntrinsics.from_dict(ph["intrinsics"])
        intr[name] = K.scaled(SMALL[0] / K.width)
        rot[name] = np.asarray(ph["cam_from_world"])[:3, :3]
        photos.append(ph)
    return {"paths": paths, "intrinsics": intr, "cam_from_world": rot, "truth": truth, "photos": photos, "root": root}


# ----------------------------------------------------------------------------------------------------------
# ground truth: focal and rotations
# ----------------------------------------------------------------------------------------------------------
@needs_data
@pytest.mark.parametrize("k1", [0.0, -0.1])
@pytest.mark.parametrize("kind, rms_band", [("grid", (0.05, 1.0)), ("row", (0.02, 0.25))])
def test_cut_views_estimated_focal_and_rotations(tmp_path, k1, kind, rms_band):
    """Focal, k1 and rotations estimated (no calibration, no EXIF): focal within 0.5 %, every rotation within
    0.05 deg. A grid, and a single row (yaw only), where focal and distortion trade off along a shallow valley,
    so the rotations need precise matches (Lucas-Kanade refined: the fit's residuals are a small fraction of a
    pixel there; SIFT's keypoints alone give about 0.3 px)."""
    paths, truth, intr = _cut_set(tmp_path, k1, kind=kind)
    r = stitch_photos(paths, options=FAST)
    assert r.intrinsics_source == "fallback"
    assert [s.name for s in r.model.sources] == [p.name for p in paths] and not r.rejected
    if kind == "row":
        assert len(r.model.sources) == 3
    for s in r.model.sources:
        err = s.intrinsics.fx / intr.fx - 1.0
        assert -0.005 < err < 0.005, (s.name, err)
        assert abs(s.intrinsics.k1 - k1) < 0.03
    errs = rotation_errors_deg({s.name: s.cam_from_pano for s in r.model.sources}, truth)
    assert all(0.0 < e < 0.05 for e in errs.values()), errs
    assert r.parallax["verdict"] == "ok"
    assert rms_band[0] < r.parallax["rms_work_px"] < rms_band[1]


@needs_data
def test_refine_matches_subpixel(tmp_path):
    """Exact matches between two cut views, perturbed by up to 0.6 px, come back to within about 0.1 px."""
    from workbench.stitch import register as reg

    paths, truth, intr = _cut_set(tmp_path, -0.1)
    a, b = paths[0].name, paths[1].name
    gray = [cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2GRAY) for p in paths[:2]]
    rng = np.random.default_rng(4)
    xa = rng.uniform([40, 40], [intr.width - 40, intr.height - 40], (400, 2))
    b_from_a = truth[b] @ truth[a].T

    def to_b(x):
        return intr.project(intr.rays(x) @ b_from_a.T)

    xb = to_b(xa)
    inside = intr.in_image(xb, margin=12.0)
    xa, xb = xa[inside], xb[inside]
    h = 0.5  # the local linear map a -> b, by central differences
    J = np.stack([(to_b(xa + [h, 0]) - to_b(xa - [h, 0])) / (2 * h), (to_b(xa + [0, h]) - to_b(xa - [0, h])) / (2 * h)],
                 axis=2)
    noisy = xb + rng.uniform(-0.6, 0.6, xb.shape)
    size = (intr.width, intr.height)
    refined, ok = reg.refine_matches(*(reg.smooth_for_refinement(g) for g in gray), xa, noisy, size, size, J)
    assert ok.sum() > 0.5 * len(ok)
    before = np.linalg.norm(noisy - xb, axis=1)
    after = np.linalg.norm(refined[ok] - xb[ok], axis=1)
    assert 0.3 < np.median(before) < 0.6
    # random points (not keypoints: some patches are poorly textured), JPEG quality 95
    assert 0.0 < np.median(after) < 0.12, np.median(after)
    assert np.percentile(after, 90) < 0.3


def _rotation_matches(reg, lens, R, rng, *, n: int, noise_px: float, one_point_id: bool = False):
    """Matches between three photos of one lens turned by ``R`` (photo k's rotation), for bundle adjustment:
    ``n`` random directions per pair (0, 1), (1, 2), (0, 2), the first photo's pixels with ``noise_px`` of noise.
    Point ids per pair (or all 0 with ``one_point_id``)."""
    a, b, xa, xb, pid = [], [], [], [], []
    for q, (i, j) in enumerate(((0, 1), (1, 2), (0, 2))):
        d = rng.normal(size=(n, 3))
        d[:, 2] = np.abs(d[:, 2]) * 3
        d = d @ R[i]
        pi, pj = lens.project(d @ R[i].T), lens.project(d @ R[j].T)
        m = lens.in_image(pi) & lens.in_image(pj)
        a.append(np.full(m.sum(), i))
        b.append(np.full(m.sum(), j))
        xa.append(pi[m] + rng.normal(0, noise_px, (m.sum(), 2)))
        xb.append(pj[m])
        pid.append(np.full(m.sum(), 0 if one_point_id else q))
    return reg.Observations(*(np.concatenate(v) for v in (a, b, xa, xb, pid)))


def test_bundle_adjust_jacobian_is_exact(monkeypatch):
    """The analytic Jacobian of the rotation-only bundle adjustment equals central differences (estimated lens
    with k1, k2 and principal point, focal only, and a fixed calibrated lens with tangential terms)."""
    from scipy.optimize._numdiff import approx_derivative
    from scipy.spatial.transform import Rotation

    from workbench.stitch import bundle as reg

    rng = np.random.default_rng(0)
    lens = CameraIntrinsics(width=640, height=480, fx=700.0, fy=700.0, cx=325.0, cy=236.0, k1=-0.1, k2=0.02,
                            p1=0.0005, p2=-0.0003)
    R = {k: Rotation.from_euler("YXZ", [15.0 * k - 15.0, 3.0 * (k % 2), 1.0 * k], degrees=True).as_matrix().T
         for k in range(3)}
    obs = _rotation_matches(reg, lens, R, rng, n=400, noise_px=0.3, one_point_id=True)
    assert len(obs.a) > 100
    R0 = {k: Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix() @ R[k] for k in range(3)}
    start = CameraIntrinsics(width=640, height=480, fx=680.0, fy=680.0, cx=319.5, cy=239.5)
    checked = []
    real = reg.least_squares

    def checking(fun, x0, jac=None, args=(), **kw):
        x = x0 + rng.normal(0, 0.02, len(x0))
        J, J_fd = jac(x, *args), approx_derivative(fun, x, args=args, method="3-point")
        checked.append(float(np.max(np.abs(J - J_fd)) / np.max(np.abs(J))))
        return real(fun, x0, jac=jac, args=args, **kw)

    monkeypatch.setattr(reg, "least_squares", checking)
    # the residuals and Jacobian as evaluated (the solver gets their compressed form, which has no Jacobian)
    monkeypatch.setattr(reg, "_compress_least_squares", lambda r, J: (r, J))
    for fixed, k1 in ((False, True), (False, False), (True, False)):
        init = {k: lens if fixed else start for k in range(3)}
        out = reg.bundle_adjust(obs, [0, 1, 2], {0: 0, 1: 0, 2: 0}, init, R0, {k: 1.0 for k in range(3)},
                                fixed_intrinsics=fixed, estimate_k1=k1, focal_prior=None if fixed else {0: 690.0})
        if fixed:  # the right model (the estimated ones have no tangential terms): the truth comes back
            errs = rotation_errors_deg(out.cam_from_pano, R)
            assert all(0.0 < e < 0.05 for e in errs.values()), errs
    assert len(checked) == 6 and all(0.0 < c < 1e-5 for c in checked), checked


def test_compressed_least_squares_takes_the_same_steps(monkeypatch):
    """Levenberg-Marquardt on the (n + 1)-row compressed residuals and Jacobian: the same linearised costs and column
    norms as on the m rows, and the same adjustment as without the compression."""
    from scipy.spatial.transform import Rotation

    from workbench.stitch import bundle as reg

    rng = np.random.default_rng(3)
    J, r = rng.normal(size=(500, 7)) * np.array([1.0, 10.0, 0.1, 1.0, 3.0, 1e3, 1e-2]), rng.normal(size=500)
    rc, Jc = reg._compress_least_squares(r, J)
    assert rc.shape == (8,) and Jc.shape == (8, 7)
    for _ in range(5):
        p = rng.normal(size=7)
        assert np.linalg.norm(Jc @ p + rc) == pytest.approx(np.linalg.norm(J @ p + r), rel=1e-9)
    assert np.allclose(np.linalg.norm(Jc, axis=0), np.linalg.norm(J, axis=0), rtol=1e-9)
    # a bundle adjustment with and without it
    lens = CameraIntrinsics(width=640, height=480, fx=700.0, fy=700.0, cx=319.5, cy=239.5, k1=-0.1)
    R = {k: Rotation.from_euler("YXZ", [12.0 * k - 12.0, 2.0 * (k % 2), 0.5 * k], degrees=True).as_matrix().T
         for k in range(3)}
    obs = _rotation_matches(reg, lens, R, rng, n=600, noise_px=0.2)
    R0 = {k: Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix() @ R[k] for k in range(3)}
    start = {k: CameraIntrinsics(width=640, height=480, fx=680.0, fy=680.0, cx=319.5, cy=239.5) for k in range(3)}

    def run():
        return reg.bundle_adjust(obs, [0, 1, 2], {0: 0, 1: 0, 2: 0}, start, R0, {k: 1.0 for k in range(3)},
                                 fixed_intrinsics=False, estimate_k1=True)

    out = run()
    monkeypatch.setattr(reg, "_compress_least_squares", lambda r, J: (r, J))
    plain = run()
    assert out.intrinsics[0].fx == pytest.approx(plain.intrinsics[0].fx, rel=1e-7)
    assert out.intrinsics[0].k1 == pytest.approx(plain.intrinsics[0].k1, abs=1e-7)
    assert max(rotation_errors_deg(out.cam_from_pano, plain.cam_from_pano).values()) < 1e-6
    assert np.array_equal(out.used, plain.used)


def test_last_adjustment_weighs_the_tail_less():
    """Restarted from an adjustment (``start``, its rotations as ``R0``), the same adjustment comes back; with
    ``final_loss_median`` (soft L1 at the scale of the median residual) a tail of mismatches (5 %, 1 to 3 px outwards,
    inside the 4 px outlier threshold) pulls the focal far less from the fit without them."""
    from scipy.spatial.transform import Rotation

    from workbench.stitch import bundle as reg

    rng = np.random.default_rng(5)
    lens = CameraIntrinsics(width=640, height=480, fx=700.0, fy=700.0, cx=319.5, cy=239.5, k1=-0.1)
    R = {k: Rotation.from_euler("Y", 12.0 * k - 12.0, degrees=True).as_matrix().T for k in range(3)}
    obs = _rotation_matches(reg, lens, R, rng, n=800, noise_px=0.05)
    bad = rng.random(len(obs.a)) < 0.05
    out = obs.xb[bad] - [lens.cx, lens.cy]  # pushed outwards: a tail that pulls the focal
    obs.xb[bad] += rng.uniform(1.0, 3.0, bad.sum())[:, None] * out / np.linalg.norm(out, axis=1, keepdims=True)
    R0 = {k: Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix() @ R[k] for k in range(3)}
    init = {k: CameraIntrinsics(width=640, height=480, fx=680.0, fy=680.0, cx=319.5, cy=239.5) for k in range(3)}
    args = ([0, 1, 2], {0: 0, 1: 0, 2: 0}, init)
    ws = {k: 1.0 for k in range(3)}
    ba = reg.bundle_adjust(obs, *args, R0, ws, fixed_intrinsics=False, estimate_k1=True)
    assert ba.used[bad].mean() > 0.9  # inside the outlier threshold
    again = reg.bundle_adjust(obs, *args, ba.cam_from_pano, ws, fixed_intrinsics=False, estimate_k1=True,
                              robust_pass=False, used=ba.used, start=ba.intrinsics)
    assert again.intrinsics[0].fx == pytest.approx(ba.intrinsics[0].fx, rel=1e-6)
    assert again.intrinsics[0].k1 == pytest.approx(ba.intrinsics[0].k1, abs=1e-6)
    last = reg.bundle_adjust(obs, *args, ba.cam_from_pano, ws, fixed_intrinsics=False, estimate_k1=True,
                             robust_pass=False, used=ba.used, start=ba.intrinsics, final_loss_median=1.0)
    clean = reg.bundle_adjust(obs, *args, ba.cam_from_pano, ws, fixed_intrinsics=False, estimate_k1=True,
                              robust_pass=False, used=ba.used & ~bad, start=ba.intrinsics)  # the tail left out
    off_ls, off_robust = (abs(b.intrinsics[0].fx / clean.intrinsics[0].fx - 1.0) for b in (ba, last))
    assert off_robust < 0.25 * off_ls, (off_ls, off_robust)


@needs_data
def test_cut_views_calibrated_keeps_the_lens(tmp_path):
    paths, truth, intr = _cut_set(tmp_path, -0.1)
    r = stitch_photos(paths, options=FAST, calibrated={p.name: intr for p in paths})
    assert r.intrinsics_source == "calibrated"
    assert all(s.intrinsics == intr for s in r.model.sources)
    errs = rotation_errors_deg({s.name: s.cam_from_pano for s in r.model.sources}, truth)
    assert all(0.0 < e < 0.03 for e in errs.values()), errs


def test_sample_panorama_calibrated(sample_small):
    """The synthetic sample's panorama set (distorted, k1 = -0.08), calibrated route: rotations to 0.05 deg."""
    d = sample_small
    r = stitch_photos(d["paths"], options=FAST, calibrated=d["intrinsics"])
    assert len(r.model.sources) == len(d["paths"])
    errs = rotation_errors_deg({s.name: s.cam_from_pano for s in r.model.sources}, d["cam_from_world"])
    assert all(0.0 < e < 0.05 for e in errs.values()), errs
    # wave correction: the panorama's y axis is (nearly) the scene's down
    A = align_rotation({s.name: s.cam_from_pano for s in r.model.sources}, d["cam_from_world"])  # pano_from_world
    down_in_pano = A @ np.array([0.0, 0.0, -1.0])
    assert np.degrees(np.arccos(np.clip(down_in_pano[1], -1, 1))) < 15.0


@needs_data
def test_same_photos_give_the_same_result(tmp_path):
    """Deterministic: FLANN's randomised forests are seeded in the thread that builds them, RANSAC per pair, and
    pairs are matched in whatever order the threads finish but sorted after; two runs give identical models
    and identical panoramas (the photos kept from registration or read again for composition)."""
    paths, _, _ = _cut_set(tmp_path, -0.1)
    runs = [stitch_photos(paths, options=StitchOptions(seam_megapix=0.05, keep_full_max_megapix=k))
            for k in (2.0, 2.0, 0.0)]
    a = runs[0]
    for b in runs[1:]:
        assert a.stats["pairs"] == b.stats["pairs"]
        for sa, sb in zip(a.model.sources, b.model.sources):
            assert sa.intrinsics == sb.intrinsics
            assert np.array_equal(sa.cam_from_pano, sb.cam_from_pano)
        assert np.array_equal(a.image, b.image)


@needs_data
def test_per_photo_focal_model_when_the_zoom_changes(tmp_path):
    """Views of one row whose focal changes by 6 % and 12 % from the first: one focal per photo is chosen (its robust
    pass is tried, its final pass runs when chosen), with each focal within 1 %."""
    src = cv2.imread(str(STITCHING / "skimage_pano_petra" / "DFM_4210.jpg"))
    rots = grid_rotations([-12.0, 0.0, 12.0], [0.0], seed=2)
    base = _view_intrinsics(0.0)
    focals = {}
    paths = []
    for n, (R, z) in enumerate(zip(rots, (1.0, 1.06, 1.12))):
        intr = replace(base, fx=base.fx * z, fy=base.fy * z)
        v = cut_views(src, 2280.0, [R], intr)[0]
        name = f"zoom_{n}.jpg"
        cv2.imwrite(str(tmp_path / name), v.image, [cv2.IMWRITE_JPEG_QUALITY, 95])
        paths.append(tmp_path / name)
        focals[name] = intr.fx
    r = stitch_photos(paths, options=FAST)
    assert r.stats["focal_model"] == "per_photo"
    for s in r.model.sources:
        assert abs(s.intrinsics.fx / focals[s.name] - 1.0) < 0.01, (s.name, s.intrinsics.fx, focals[s.name])


# ----------------------------------------------------------------------------------------------------------
# the connected set, the distractor, parallax
# ----------------------------------------------------------------------------------------------------------
@needs_data
def test_weir_distractor_rejected(tmp_path):
    names = ["weir_1.jpg", "weir_2.jpg", "weir_3.jpg", "weir_noise.jpg"]
    paths = []
    for n in names:  # reduced to about 640 px wide to keep the test fast
        img = cv2.imread(str(STITCHING / "opencv_weir" / n))
        s = 640 / 1333
        cv2.imwrite(str(tmp_path / n), cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA))
        paths.append(tmp_path / n)
    r = stitch_photos(paths, options=StitchOptions(compose=False, check_parallax=False))
    assert [s.name for s in r.model.sources] == names[:3]
    assert [x["name"] for x in r.rejected] == ["weir_noise.jpg"]
    assert "confidence" in r.rejected[0]["reason"]


@needs_data
def test_unrelated_photo_rejected_from_sample(sample_small, tmp_path):
    d = sample_small
    img = cv2.imread(str(STITCHING / "skimage_pano_arches" / "JDW_9519.jpg"))
    cv2.imwrite(str(tmp_path / "zz_other.jpg"), cv2.resize(img, SMALL))
    paths = d["paths"] + [tmp_path / "zz_other.jpg"]
    intr = dict(d["intrinsics"], **{"zz_other.jpg": d["intrinsics"][d["paths"][0].name]})
    r = stitch_photos(paths, options=FAST, calibrated=intr)
    assert [x["name"] for x in r.rejected] == ["zz_other.jpg"]
    assert len(r.model.sources) == len(d["paths"])


def test_parallax_is_refused(tmp_path):
    """Photos from different places are refused with advice to use sfm. Built here: three views of the ray-cast
    scene of workbench.intrinsics.synthetic (ground and boxes 4-6 m tall) from three places 6 m apart, 18 m
    from the boxes (the small generated incident's overlapping multi-view photos are 4-8 m apart at 50-100 m:
    too little parallax to test this; the full sample's were 30-110 m apart)."""
    from PIL import Image

    from workbench.intrinsics.synthetic import look_at, make_scene, pixel_rays, render

    w, h = SMALL
    f = w / 2 / np.tan(np.radians(27.5))
    intr = CameraIntrinsics(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2, cy=(h - 1) / 2)
    quads, rays = make_scene(0), pixel_rays(intr)
    for i, x in enumerate((-6.0, 0.0, 6.0)):
        M = look_at(np.array([x, -16.0, 2.0]), np.array([0.0, 2.0, 1.5]))
        Image.fromarray(render(quads, intr, M, rays_cam=rays)).save(tmp_path / f"view_{i}.jpg", quality=95)
    with pytest.raises(InputError, match=r"(?s)different positions \(parallax\).*camera.source = \"sfm\""):
        stitch_photos(sorted(tmp_path.glob("*.jpg")), options=FAST)


def test_too_few_photos(tmp_path):
    with pytest.raises(InputError, match="at least two"):
        stitch_photos([tmp_path / "a.jpg"])


# ----------------------------------------------------------------------------------------------------------
# the stage: files, and a true 3D point landing where the panorama image shows it
# ----------------------------------------------------------------------------------------------------------
def test_stage_writes_panorama_and_exact_model(sample_small, tmp_path):
    from workbench.pipeline import STAGES
    from workbench.project import Project
    from workbench.runner import Runner
    from workbench.pipeline import stage

    STAGE = stage("stitch")

    d = sample_small
    root = tmp_path / "inc"
    (root / "photos" / "panorama").mkdir(parents=True)
    for p in d["paths"]:
        shutil.copy(p, root / "photos" / "panorama" / p.name)
    shutil.copy(d["root"] / "project.toml", root / "project.toml")
    shutil.copy(d["root"] / "camera_profile.json", root / "camera_profile.json")  # 800x600: scaled by the stage
    project = Project(root)
    assert STAGE.applies(project)
    seen = []
    Runner(project, [STAGES[0], STAGE]).run(only=["inputs", "stitch"],
                                           progress_factory=lambda s: (lambda f, m="": seen.append((s.name, f))))
    assert any(n == "stitch" and 0 < f < 1 for n, f in seen)
    data = json.loads((root / "out" / "stitch" / "panorama.json").read_text())
    assert data["intrinsics_source"] == "calibrated" and data["rejected"] == []
    assert data["parallax"]["verdict"] == "ok"
    assert data["sources"][0]["image"] == "photos/panorama/pano_00.jpg"
    model = PanoramaModel.from_dict(data)
    pano = cv2.imread(str(root / "out" / "stitch" / "panorama.jpg"))
    assert pano.shape[:2] == (model.height, model.width)
    stats = json.loads((root / "out" / "stitch" / "stats.json").read_text())
    assert stats["n_kept"] == len(d["paths"]) and stats["peak_rss_mb"] > 0

    # true marked points of the carriages, projected with the model (scene frame aligned by the rotations)
    truth = d["truth"]
    A = align_rotation({s.name: s.cam_from_pano for s in model.sources}, d["cam_from_world"])  # pano_from_world
    centre = np.asarray(truth["panorama_center_enu"])
    n_checked = n_ncc = 0
    for ph in d["photos"]:
        name = Path(ph["photo"]).name
        i = model.source_index(name)
        for car, pts in ph["observations"].items():
            for pname, o in pts.items():
                if not o["visible"]:
                    continue
                X = np.asarray(next(c for c in truth["carriages"] if c["number"] == car)["marked_points_enu"][pname])
                uv = model.project(((X - centre) @ A.T)[None])[0]
                # the same point seen in the photo (true pixel, reduced like the photo) mapped into the panorama
                uv_true = (np.asarray(o["uv"]) + 0.5) * (SMALL[0] / ph["intrinsics"]["width"]) - 0.5
                np.testing.assert_allclose(model.from_source(i, uv_true[None])[0], uv, atol=0.6)
                n_checked += 1
                if not (20 < uv[0] < model.width - 20 and 20 < uv[1] < model.height - 20):
                    continue
                # the panorama image shows there what the photo shows at the true pixel
                g = np.arange(-8, 9, dtype=float)
                gy, gx = np.meshgrid(g, g, indexing="ij")
                grid = np.column_stack([gx.ravel() + uv[0], gy.ravel() + uv[1]])
                dirs = model.rays(grid) @ model.sources[i].cam_from_pano.T
                src_px = model.sources[i].intrinsics.project(dirs).astype(np.float32)
                if not model.sources[i].intrinsics.in_image(src_px, margin=1.0).all():
                    continue  # the patch leaves this photo
                photo = cv2.imread(str(d["paths"][i]), cv2.IMREAD_GRAYSCALE).astype(np.float32)
                a = cv2.remap(photo, src_px[:, 0].reshape(17, 17), src_px[:, 1].reshape(17, 17), cv2.INTER_LINEAR)
                b = cv2.remap(cv2.cvtColor(pano, cv2.COLOR_BGR2GRAY).astype(np.float32),
                              grid[:, 0].reshape(17, 17).astype(np.float32),
                              grid[:, 1].reshape(17, 17).astype(np.float32), cv2.INTER_LINEAR)
                if a.std() < 8:
                    continue  # flat patch: nothing to compare
                ncc = float(np.corrcoef(a.ravel(), b.ravel())[0, 1])
                assert ncc > 0.9, (name, car, pname, ncc)
                n_ncc += 1
    assert n_checked >= 10 and n_ncc >= 10


def _copy_sample(sample_small, root: Path) -> Path:
    """An incident at ``root`` with the reduced sample's panorama photos, settings and scaled camera profile."""
    (root / "photos" / "panorama").mkdir(parents=True)
    for p in sample_small["paths"]:
        shutil.copy(p, root / "photos" / "panorama" / p.name)
    shutil.copy(sample_small["root"] / "project.toml", root / "project.toml")
    shutil.copy(sample_small["root"] / "camera_profile.json", root / "camera_profile.json")
    return root


def test_cli_runs_the_stitch_stage(sample_small, tmp_path):
    """`workbench run PATH --only inputs --only stitch` on a copy of the sample (reduced photos, scaled profile): the
    photos described while the inputs stage runs."""
    import subprocess
    import sys

    root = _copy_sample(sample_small, tmp_path / "inc")
    exe = Path(sys.executable).parent / "workbench"
    r = subprocess.run([str(exe), "-v", "run", str(root), "--only", "inputs", "--only", "stitch"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "photos described ahead of the stage" in r.stderr  # the runner's prefetch, during the inputs stage
    state = json.loads((root / "out" / "state.json").read_text())
    assert state["stitch"]["status"] == "done"
    assert set(state["stitch"]["outputs"]) >= {"panorama_image", "panorama_model", "stats"}
    model = PanoramaModel.from_dict(json.loads((root / "out" / "stitch" / "panorama.json").read_text()))
    assert len(model.sources) == len(sample_small["paths"])
    # `workbench stitch`: no head start where the stitch is done (the stage is skipped); forced, the photos are
    # described from the process's start (cli._head_start), the runner's prefetch leaves them be, and the stage
    # takes them: the same panorama to the byte
    first = {f: (root / "out" / "stitch" / f).read_bytes() for f in ("panorama.jpg", "panorama.json")}
    toml = root / "project.toml"  # (no terrain: the copy does not have the sample's DEM)
    toml.write_text(re.sub(r'(?m)^dem = .*$', "", toml.read_text()))
    r = subprocess.run([str(exe), "-v", "stitch", str(root)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "stitch: up to date, skipped" in r.stderr, r.stdout + r.stderr
    assert "described" not in r.stderr, r.stderr
    r = subprocess.run([str(exe), "-v", "stitch", str(root), "--force"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "being described already (the command's head start)" in r.stderr, r.stderr
    assert "photos described ahead of the stage" in r.stderr, r.stderr
    assert {f: (root / "out" / "stitch" / f).read_bytes() for f in first} == first


def test_minpack_called_as_scipy_calls_it():
    """bundle.least_squares calls MINPACK's lmder (the extension loaded without the package scipy.optimize) as
    scipy.optimize.least_squares(method="lm") does: the same steps, the same result to the bit."""
    from scipy.optimize import least_squares as scipy_lsq

    from workbench.stitch import bundle

    assert bundle._minpack() is not None
    t = np.linspace(0.0, 3.0, 40)
    y = 2.5 * np.exp(-1.3 * t) + 0.4 * np.sin(3.0 * t) + np.random.default_rng(1).normal(0, 0.01, len(t))

    def fun(x, scale):
        return scale * (x[0] * np.exp(-x[1] * t) + x[2] * np.sin(x[3] * t) - y)

    def jac(x, scale):
        return scale * np.column_stack([np.exp(-x[1] * t), -x[0] * t * np.exp(-x[1] * t), np.sin(x[3] * t),
                                        x[2] * t * np.cos(x[3] * t)])

    x0 = np.array([1.0, 1.0, 0.1, 2.8])
    for tol, nfev in ((1e-10, 200), (1e-4, 200), (1e-10, 3)):
        ours = bundle.least_squares(fun, x0, jac, (2.0,), xtol=tol, ftol=tol, max_nfev=nfev)
        ref = scipy_lsq(fun, x0, jac=jac, args=(2.0,), method="lm", xtol=tol, ftol=tol, max_nfev=nfev)
        assert np.array_equal(ours.x, ref.x) and ours.cost == ref.cost and ours.nfev == ref.nfev


def test_exif_tags_read_once_per_unchanged_photo(tmp_path, monkeypatch):
    """The stitch's EXIF focal priors (read_focal_px) reuse the tags the inputs stage read from the same unchanged
    file (files.exif.read_exif_tags); a photo rewritten since is read again."""
    from workbench.files import exif

    p = tmp_path / "a.jpg"
    img = np.full((60, 80, 3), 128, np.uint8)
    exif.write_jpeg(p, img, focal_length_mm=20.0, sensor_width_mm=23.5)
    reads = []
    real = exif._read_exif_tags
    monkeypatch.setattr(exif, "_read_exif_tags", lambda path: reads.append(path) or real(path))
    f0 = exif.read_focal_px(p)
    assert exif.exif_focal_prior(p).focal_px == f0 and len(reads) == 1
    exif.read_exif_tags(p)[2].clear()  # (each caller gets its own copy)
    assert exif.read_focal_px(p) == f0 and len(reads) == 1
    exif.write_jpeg(p, img, focal_length_mm=40.0, sensor_width_mm=23.5)
    assert exif.read_focal_px(p) == pytest.approx(2 * f0) and len(reads) == 2


@needs_data
def test_prefetched_photos_give_the_same_panorama(sample_small, tmp_path, caplog):
    """The photos described ahead of the stage (stage.prefetch, while the inputs stage runs) give the panorama of
    the stage's own description, and are dropped when a photo changed since."""
    import logging
    import os
    import threading

    from workbench.project import Project
    from workbench.stitch import stage

    root = _copy_sample(sample_small, tmp_path / "inc")
    caplog.set_level(logging.INFO, logger="workbench.stitch.stage")
    for source in ("calibrated", "exif"):  # (the pairs are matched ahead too where the lens is not calibrated)
        toml = (root / "project.toml").read_text()
        (root / "project.toml").write_text(re.sub(r'(?m)^source = "\w+"', f'source = "{source}"', toml, count=1))
        project = Project(root)
        assert project.settings.camera.source.value == source
        plain = stage.stitch_project(project)
        runs = []
        caplog.clear()
        for touch in (False, True):
            stage.prefetch(project)
            if touch:  # a photo rewritten after it was described: described again by the stage
                p = project.photo_paths()[0]
                os.utime(p, ns=(p.stat().st_atime_ns, p.stat().st_mtime_ns + 1_000_000))
            runs.append(stage.stitch_project(project))
            assert not stage._PREFETCH
            # (no prefetch thread outlives the stage: a later stage may fork)
            assert not [t for t in threading.enumerate() if t.name.startswith("stitch prefetch")]
        n = len(project.photo_paths())
        pairs = 0 if source == "calibrated" else n * (n - 1) // 2
        assert f"{n} photos described ahead of the stage (and {pairs} pairs matched)" in caplog.text
        assert "changed since" in caplog.text
        for r in runs:
            assert r.model.to_dict() == plain.model.to_dict()
            assert np.array_equal(r.image, plain.image)


# ----------------------------------------------------------------------------------------------------------
# composition: the resampling maps and the gains
# ----------------------------------------------------------------------------------------------------------
def _compose_model(projection: str) -> PanoramaModel:
    from scipy.spatial.transform import Rotation

    from workbench.core.panorama import PanoramaSource

    intr = CameraIntrinsics(width=900, height=600, fx=800.0, fy=800.0, cx=452.0, cy=297.5, k1=-0.12, k2=0.02,
                            p1=0.0006, p2=-0.0004)
    srcs = [PanoramaSource(name=f"p{i}.jpg", image=f"p{i}.jpg", intrinsics=intr,
                           cam_from_pano=Rotation.from_euler("YXZ", [yaw, 4.0 * i, 2.0 - i], degrees=True).as_matrix().T)
            for i, yaw in enumerate((-30.0, 0.0, 30.0))]
    return PanoramaModel(projection=projection, scale=800.0, offset=(-1000.0, -400.0), width=2000, height=800,
                         sources=tuple(srcs))


@pytest.mark.parametrize("projection", ["planar", "cylindrical", "spherical"])
def test_compose_maps_are_the_model(projection):
    """The maps interpolated from every 8th pixel are within 0.02 px of the model's exact mapping (panorama pixel
    -> ray -> cam_from_pano -> lens) wherever the photo sees; the mask is the photo's footprint."""
    from workbench.stitch.compose import footprint, source_maps

    m = _compose_model(projection)
    for i, src in enumerate(m.sources):
        box = footprint(m, i, src.intrinsics)
        mx, my, mask = source_maps(m, i, src.intrinsics, box)
        assert mx.shape == my.shape == mask.shape == (box[3] - box[1], box[2] - box[0])
        v, u = np.mgrid[box[1]:box[3], box[0]:box[2]]
        uv = np.column_stack([u.ravel(), v.ravel()]).astype(float)
        exact = src.intrinsics.project(m.rays(uv) @ src.cam_from_pano.T)
        inside = src.intrinsics.in_image(exact)
        got = np.column_stack([mx.ravel(), my.ravel()])
        err = np.abs(got[inside] - exact[inside]).max()
        assert 0.0 < err < 0.02, err
        assert inside.sum() > 0.3 * inside.size
        # the mask is the photo: it differs from the exact footprint only on a few border pixels
        assert np.count_nonzero((mask.ravel() > 0) != inside) < 0.002 * inside.size
        # every pixel of the photo's border lands in the box
        w, h = src.intrinsics.width, src.intrinsics.height
        border = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5], [w / 2, -0.5]])
        p = m.from_source(i, border)
        assert np.all((p >= [box[0], box[1]]) & (p <= [box[2] - 1, box[3] - 1]))


def test_compose_source_pixels_do_not_fold_back():
    """Strong barrel distortion folds rays far outside the photo back into it (OpenCV's model is not monotone);
    the composition's projection continues it outward instead, and agrees with the model inside the photo."""
    from workbench.stitch.compose import source_pixels

    intr = CameraIntrinsics(width=800, height=600, fx=800.0, fy=800.0, cx=400.0, cy=300.0, k1=-0.25)
    ang = np.radians(np.linspace(0.0, 89.0, 400))
    cam = np.column_stack([np.sin(ang), np.zeros_like(ang), np.cos(ang)])
    folded = intr.project(cam)
    far = ang > np.radians(45.0)  # the photo spans 26.6 degrees from its axis
    assert intr.in_image(folded[far]).any()  # the plain model folds back in
    ours = source_pixels(intr, cam)
    assert np.all(np.diff(ours[:, 0]) > 0)  # monotone outward
    inside = intr.in_image(ours)
    np.testing.assert_allclose(ours[inside], folded[inside], atol=1e-9)
    assert inside[~far].any() and not inside[far].any()
    # behind the camera: finite, and far outside except the backward axis itself (source_maps masks that)
    back = source_pixels(intr, np.array([[0.3, 0.2, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]))
    assert np.all(np.isfinite(back)) and not intr.in_image(back[:2]).any()


def test_compose_maps_photo_seeing_the_pole():
    """A photo that sees the zenith spans every longitude of a spherical panorama, whose box then holds rays
    behind the photo too (the backward axis among them): the mask is still exactly the photo's footprint."""
    from workbench.core.panorama import PanoramaSource
    from workbench.stitch.compose import footprint, source_maps

    intr = CameraIntrinsics(width=400, height=300, fx=300.0, fy=300.0, cx=200.0, cy=150.0, k1=-0.05)
    up = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # cam_from_pano: the camera looks along -y
    m = PanoramaModel(projection="spherical", scale=100.0, offset=(-400.0, 0.0), width=629, height=315,
                      sources=(PanoramaSource(name="up.jpg", image="up.jpg", intrinsics=intr, cam_from_pano=up),))
    box = footprint(m, 0, intr)
    assert box[2] - box[0] >= 2 * np.pi * 100.0 and box[1] <= 0  # every longitude, from the pole's row
    box = (0, 0, m.width, m.height)  # the whole sphere: the nadir is this photo's backward axis
    mx, my, mask = source_maps(m, 0, intr, box)
    v, u = np.mgrid[box[1]:box[3], box[0]:box[2]]
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    cam = m.rays(uv) @ up.T
    assert (cam[:, 2] < -0.999).any()
    src, exact = m.to_source(uv)  # the model's own choice: the photo sees the ray (no fold-back)
    inside = src == 0
    assert 0.05 * inside.size < inside.sum() < 0.6 * inside.size
    assert np.count_nonzero((mask.ravel() > 0) != inside) < 0.002 * inside.sum()
    # near the pole the mapping curves strongly (polar coordinates): a finer grid keeps it exact
    err = np.abs(np.column_stack([mx.ravel(), my.ravel()])[inside] - exact[inside]).max()
    assert err < 0.02, err


def test_block_gains_as_opencv():
    """The block gains applied by resize and multiply are OpenCV's BlocksGainCompensator.apply, bit for bit."""
    from workbench.stitch.compose import apply_block_gains

    rng = np.random.default_rng(3)
    imgs = [cv2.GaussianBlur(rng.integers(0, 256, (120, 160, 3), dtype=np.uint8), (7, 7), 2) for _ in range(2)]
    imgs[1] = cv2.convertScaleAbs(imgs[1], alpha=1.3)
    masks = [np.full((120, 160), 255, np.uint8)] * 2
    comp = cv2.detail_BlocksGainCompensator()
    comp.feed(corners=[(0, 0), (60, 10)], images=imgs, masks=[cv2.UMat(x) for x in masks])
    gains = comp.getMatGains()
    big = rng.integers(0, 256, (517, 733, 3), dtype=np.uint8)
    for k in range(2):
        assert gains[k].ndim == 2 and np.ptp(gains[k]) >= 0
        want = comp.apply(k, (0, 0), big.copy(), np.full(big.shape[:2], 255, np.uint8))
        want = want.get() if isinstance(want, cv2.UMat) else want
        assert np.array_equal(apply_block_gains(big, np.asarray(gains[k], np.float32)), want)
    assert not np.allclose(gains[1], 1.0)  # (the second photo is brighter: the gains do something)


@needs_data
def test_composed_panorama_is_the_photos_through_the_model(tmp_path):
    """Each panorama pixel shows what the model says: the photo pixel ``to_source`` gives (up to gains and
    blending), and black where no photo sees."""
    paths, _, _ = _cut_set(tmp_path, -0.1, kind="row")
    r = stitch_photos(paths, options=StitchOptions(seam_megapix=0.05))
    m, pano = r.model, r.image
    assert pano.shape[:2] == (m.height, m.width)
    v, u = np.mgrid[0:m.height:3, 0:m.width:3]
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(float)
    src, px = m.to_source(uv)
    got = pano[v.ravel(), u.ravel()].astype(float)
    # (a pixel whose centre is within a few hundredths of a pixel of a photo's edge may go either way)
    assert np.count_nonzero(got[src < 0].max(axis=1)) <= 0.002 * np.count_nonzero(src < 0)
    photos = {s.name: cv2.imread(str(p)) for s, p in zip(m.sources, paths)}
    ok = src >= 0
    for i, s in enumerate(m.sources):
        sel = ok & (src == i) & s.intrinsics.in_image(np.nan_to_num(px), margin=3.0)
        q = px[sel].astype(np.float32)
        want = cv2.remap(photos[s.name], q[:, 0].reshape(-1, 1), q[:, 1].reshape(-1, 1), cv2.INTER_LINEAR)
        diff = np.abs(got[sel] - want.reshape(-1, 3).astype(float))
        assert sel.sum() > 1000
        assert np.median(diff) < 4.0, (s.name, np.median(diff))  # misplaced by a pixel: tens of levels


def test_statistics_without_numpy_ma_equal_numpy():
    """register.unique_sorted, median and percentile (which keep numpy.ma out of a fresh stitch) give NumPy's
    np.unique (1-D and axis=0), np.median and np.percentile to the bit, NaN included."""
    from workbench.stitch.register import median, percentile, unique_sorted

    rng = np.random.default_rng(5)
    for n in (1, 2, 3, 7, 50, 301):
        for scale in (1e-4, 1.0, 3e5):
            a = np.abs(rng.normal(size=n)) * scale
            assert median(a) == float(np.median(a))
            assert median(list(a)) == float(np.median(list(a)))
            for q in (0, 10, 50, 90, 99.5, 100):
                assert percentile(a, q) == float(np.percentile(a, q))
        pairs = rng.integers(0, 9, size=(n, 2))
        u = unique_sorted(pairs)
        assert u.dtype == np.unique(pairs, axis=0).dtype and np.array_equal(u, np.unique(pairs, axis=0))
        ids = rng.integers(0, 5, size=n)
        assert np.array_equal(unique_sorted(ids), np.unique(ids))
    assert np.isnan(median([1.0, np.nan, 2.0])) and np.isnan(percentile([1.0, np.nan, 2.0], 90))
