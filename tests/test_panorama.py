"""The panorama camera model (workbench/core/panorama.py): formulas against OpenCV's warpers, exact
Jacobians against finite differences, round trips pixel <-> ray <-> source photo, the file format."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from workbench.core.camera import CameraIntrinsics
from workbench.core.panorama import PROJECTIONS, PanoramaModel, PanoramaSource

CV2_NAME = {"planar": "plane", "cylindrical": "cylindrical", "spherical": "spherical"}


def _model(projection: str, distortion: bool = True) -> PanoramaModel:
    k = dict(k1=-0.1, k2=0.01, p1=0.0005, p2=-0.0004) if distortion else {}
    intr = CameraIntrinsics(width=640, height=480, fx=600.0, fy=600.0, cx=322.0, cy=236.5, **k)
    srcs = []
    for i, yaw in enumerate((-25.0, 0.0, 25.0)):
        pano_from_cam = Rotation.from_euler("YXZ", [yaw, 3.0 * (i - 1), 1.0 - i], degrees=True).as_matrix()
        srcs.append(PanoramaSource(name=f"p{i}.jpg", image=f"photos/p{i}.jpg", intrinsics=intr,
                                   cam_from_pano=pano_from_cam.T))
    return PanoramaModel(projection=projection, scale=610.0, offset=(-700.0, -300.0), width=1400, height=600,
                         sources=tuple(srcs))


def _dirs(n: int = 200, seed: int = 0, max_deg: float = 60.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yaw = np.radians(rng.uniform(-max_deg, max_deg, n))
    pitch = np.radians(rng.uniform(-max_deg * 0.7, max_deg * 0.7, n))
    d = np.column_stack([np.cos(pitch) * np.sin(yaw), np.sin(pitch), np.cos(pitch) * np.cos(yaw)])
    return d * rng.uniform(0.5, 3.0, (n, 1))  # any length


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_project_rays_round_trip(projection):
    m = _model(projection)
    d = _dirs()
    uv = m.project(d)
    assert np.all(np.isfinite(uv))
    back = m.rays(uv)
    np.testing.assert_allclose(back, d / np.linalg.norm(d, axis=1, keepdims=True), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-12)


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_matches_opencv_warpers(projection):
    """model.from_source on an undistorted photo == cv2.PyRotationWarper.warpPoint - offset (float32 precision)."""
    m = _model(projection, distortion=False)
    warper = cv2.PyRotationWarper(CV2_NAME[projection], m.scale)
    rng = np.random.default_rng(1)
    for i, src in enumerate(m.sources):
        K = src.intrinsics.K.astype(np.float32)
        R = src.cam_from_pano.T.astype(np.float32)  # OpenCV's camera R is pano_from_cam
        pts = rng.uniform([0, 0], [639, 479], (20, 2))
        ours = m.from_source(i, pts)
        theirs = np.array([warper.warpPoint((float(u), float(v)), K, R) for u, v in pts]) - np.array(m.offset)
        err = np.abs(ours - theirs).max()
        assert err < 0.05, err
        # and OpenCV's backward maps (what cv2.remap samples for each warped pixel) agree with our rays
        tl, xmap, ymap = warper.buildMaps((640, 480), K, R)
        ys, xs = rng.integers(0, xmap.shape[0], 30), rng.integers(0, xmap.shape[1], 30)
        uv_pano = np.column_stack([xs + tl[0], ys + tl[1]]) - np.array(m.offset)
        theirs = np.column_stack([xmap[ys, xs], ymap[ys, xs]])
        ours = src.intrinsics.project(m.rays(uv_pano) @ src.cam_from_pano.T)
        ok = (theirs[:, 0] > 0) & (theirs[:, 0] < 639) & (theirs[:, 1] > 0) & (theirs[:, 1] < 479)
        assert ok.sum() > 5
        assert np.abs(ours[ok] - theirs[ok]).max() < 0.05


def test_planar_is_a_pinhole():
    m = _model("planar")
    K = np.array([[m.scale, 0, -m.offset[0]], [0, m.scale, -m.offset[1]], [0, 0, 1.0]])
    d = _dirs(max_deg=40)
    p = d @ K.T
    np.testing.assert_allclose(m.project(d), p[:, :2] / p[:, 2:], atol=1e-9)
    assert np.all(np.isnan(m.project(np.array([[0.0, 0.0, -1.0]]))))  # behind: undefined


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_jacobian_matches_finite_differences(projection):
    m = _model(projection)
    d = _dirs(50, seed=2)
    uv, J = m.project_with_jacobian(d)
    assert J.shape == (50, 2, 3)
    eps = 1e-6
    num = np.zeros_like(J)
    for k in range(3):
        e = np.zeros(3)
        e[k] = eps
        num[:, :, k] = (m.project(d + e) - m.project(d - e)) / (2 * eps)
    np.testing.assert_allclose(J, num, rtol=1e-6, atol=1e-5)
    # scaling a direction does not move its pixel: J d = 0
    np.testing.assert_allclose(np.einsum("nij,nj->ni", J, d), 0.0, atol=1e-8)


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_source_round_trip_with_distortion(projection):
    m = _model(projection)
    rng = np.random.default_rng(3)
    for i, src in enumerate(m.sources):
        pts = rng.uniform([5, 5], [634, 474], (40, 2))
        uv = m.from_source(i, pts)
        assert np.all(np.isfinite(uv))
        idx, uv_src = m.to_source(uv)
        assert np.all(idx >= 0)
        # the same ray, whichever photo was chosen: map it back and compare panorama pixels
        np.testing.assert_allclose(m.from_source(idx, uv_src), uv, atol=1e-7)
        same = idx == i
        np.testing.assert_allclose(uv_src[same], pts[same], atol=1e-7)
        # chosen photo: the one whose axis is closest to the ray
        d = m.rays(uv)
        cos = np.stack([d @ s.cam_from_pano[2] for s in m.sources], axis=1)
        inside = np.stack([s.intrinsics.in_image(s.intrinsics.project(d @ s.cam_from_pano.T)) for s in m.sources], 1)
        cos[~inside] = -np.inf
        np.testing.assert_array_equal(idx, np.argmax(cos, axis=1))


def test_to_source_outside_every_photo():
    m = _model("cylindrical")
    idx, uv = m.to_source(np.array([[m.width / 2, -5000.0]]))  # straight up: no photo sees it
    assert idx[0] == -1 and np.all(np.isnan(uv[0]))


def test_dict_round_trip_and_strict_keys():
    m = _model("spherical")
    d = json.loads(json.dumps(m.to_dict()))
    m2 = PanoramaModel.from_dict({**d, "rejected": [], "intrinsics_source": "calibrated", "parallax": {}})
    assert m2.projection == m.projection and m2.offset == m.offset and (m2.width, m2.height) == (m.width, m.height)
    for a, b in zip(m.sources, m2.sources):
        assert a.intrinsics == b.intrinsics and a.name == b.name
        np.testing.assert_array_equal(a.cam_from_pano, b.cam_from_pano)
    uv = np.array([[700.0, 300.0], [100.0, 250.0]])
    np.testing.assert_array_equal(m.rays(uv), m2.rays(uv))
    with pytest.raises(ValueError, match="unknown key"):
        PanoramaModel.from_dict({**d, "scael": 1.0})
    with pytest.raises(ValueError, match="missing"):
        PanoramaModel.from_dict({k: v for k, v in d.items() if k != "offset"})


def test_bad_values_are_refused():
    m = _model("planar")
    with pytest.raises(ValueError, match="projection"):
        PanoramaModel(projection="fisheye", scale=1.0, offset=(0, 0), width=1, height=1, sources=())
    with pytest.raises(ValueError, match="rotation"):
        PanoramaSource(name="x", image="x", intrinsics=m.sources[0].intrinsics, cam_from_pano=np.eye(3) * 2)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        m.project(np.zeros((4, 2)))
