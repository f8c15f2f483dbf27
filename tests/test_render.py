"""Off-screen rendering: pixel convention, textures, depth, instance masks, lens distortion, EXIF."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh
from PIL import Image

from workbench.core.camera import CameraIntrinsics, look_at, project_world
from workbench.errors import RenderError
from workbench.render import OffscreenScene, SceneMesh
from workbench.render import offscreen as offscreen_mod
from workbench.files.exif import read_focal_px, write_jpeg
from workbench.render.lens import render_photo

BLACK = (0.0, 0.0, 0.0)


def _world_from_cam(M: np.ndarray) -> np.ndarray:
    R, t = M[:3, :3], M[:3, 3]
    W = np.eye(4)
    W[:3, :3] = R.T
    W[:3, 3] = -R.T @ t
    return W


def _disk_facing_camera(center_cam, radius: float, M: np.ndarray, rgb=(255, 255, 255), n: int = 96) -> trimesh.Trimesh:
    """A flat disk parallel to the image plane (its image is a circle centred on the centre's projection)."""
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    c = np.asarray(center_cam, float)
    ring = c + np.column_stack([radius * np.cos(a), radius * np.sin(a), np.zeros(n)])
    V = np.vstack([c, ring])
    F = np.array([[0, 1 + (i + 1) % n, 1 + i] for i in range(n)])  # normal towards the camera (-z)
    Wc = _world_from_cam(M)
    Vw = V @ Wc[:3, :3].T + Wc[:3, 3]
    m = trimesh.Trimesh(Vw, F, process=False)
    m.visual.face_colors = [*rgb, 255]
    return m


def _centroid(gray: np.ndarray, uv: np.ndarray, half: int, floor: float = 10.0) -> np.ndarray:
    u0, v0 = int(round(uv[0])), int(round(uv[1]))
    win = gray[v0 - half:v0 + half + 1, u0 - half:u0 + half + 1].astype(float)
    w = np.clip(win - floor, 0.0, None)
    ys, xs = np.mgrid[v0 - half:v0 + half + 1, u0 - half:u0 + half + 1]
    return np.array([(w * xs).sum() / w.sum(), (w * ys).sum() / w.sum()])


@pytest.fixture(scope="module")
def camera():
    # non-square image, principal point well off-centre
    intr = CameraIntrinsics(width=400, height=260, fx=310.0, fy=290.0, cx=151.3, cy=97.8)
    M = look_at(np.array([3.0, -8.0, 2.0]), np.array([0.5, 1.0, 1.2]))
    return intr, M


def test_pixel_centre_convention_subpixel(camera):
    intr, M = camera
    scene = OffscreenScene(intr.width, intr.height, background_rgb=BLACK)
    centres = [np.array([0.0, 0.0, 6.0]), np.array([0.9, 0.55, 7.0]), np.array([-1.6, -0.8, 8.0]),
               np.array([2.7, 1.3, 6.5]), np.array([-0.93, 1.1, 5.5])]
    for i, c in enumerate(centres):
        scene.add(SceneMesh(f"disk{i}", _disk_facing_camera(c, 0.3, M), instance_id=i))
    Wc = _world_from_cam(M)
    scene.set_sun(Wc[:3, :3] @ np.array([0.0, 0.0, 1.0]), shadows=False)  # light along the view
    res = scene.render(intr.K, M)
    assert res.color.shape == (260, 400, 3) and res.color.dtype == np.uint8
    assert res.depth.shape == (260, 400) and res.depth.dtype == np.float32
    assert res.instance.shape == (260, 400) and res.instance.dtype == np.int32
    gray = res.color.astype(float).mean(axis=2)
    for i, c in enumerate(centres):
        uv = intr.project(c[None])[0]
        got = _centroid(gray, uv, half=int(0.3 * intr.fx / c[2]) + 4)
        assert np.all(np.abs(got - uv) < 0.3), (i, got, uv)
        # the instance mask (ray cast at pixel centres) has the same convention
        mask = res.instance == i
        ys, xs = np.nonzero(mask)
        assert np.all(np.abs(np.array([xs.mean(), ys.mean()]) - uv) < 0.3), (i, xs.mean(), ys.mean(), uv)
        # and depth is the disk's camera z
        assert abs(res.depth[int(round(uv[1])), int(round(uv[0]))] - c[2]) < 1e-3
    # colour and instance masks agree pixel for pixel except along anti-aliased edges
    lit = gray > 60
    objs = res.instance >= 0
    assert (lit ^ objs).sum() < 0.08 * objs.sum()


def _asymmetric_texture() -> np.ndarray:
    tex = np.zeros((64, 64, 3), np.uint8)
    tex[:32, :32] = [220, 30, 30]  # top-left red
    tex[:32, 32:] = [30, 200, 30]  # top-right green
    tex[32:, :32] = [30, 30, 220]  # bottom-left blue
    tex[32:, 32:] = [230, 230, 230]  # bottom-right white
    return tex


def _textured_wall(x0, x1, y, z0, z1) -> trimesh.Trimesh:
    """A vertical quad in the plane y = const, facing -y, image upright (trimesh UV: v = 1 at the image top)."""
    V = np.array([[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]], float)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    F = np.array([[0, 1, 2], [0, 2, 3]])
    vis = trimesh.visual.TextureVisuals(uv=uv, image=Image.fromarray(_asymmetric_texture()))
    return trimesh.Trimesh(V, F, visual=vis, process=False)


def test_texture_not_flipped():
    intr = CameraIntrinsics(width=240, height=180, fx=200.0, fy=200.0, cx=119.5, cy=89.5)
    M = look_at(np.array([0.0, -5.0, 1.0]), np.array([0.0, 0.0, 1.0]))
    scene = OffscreenScene(intr.width, intr.height)
    scene.add(SceneMesh("wall", _textured_wall(-1.0, 1.0, 0.0, 0.0, 2.0)))
    scene.set_sun([0.0, 1.0, -0.3], shadows=False)
    res = scene.render(intr.K, M)
    probes = {"red": [-0.5, 0.0, 1.5], "green": [0.5, 0.0, 1.5], "blue": [-0.5, 0.0, 0.5], "white": [0.5, 0.0, 0.5]}
    for name, X in probes.items():
        uv, _ = project_world(intr, M, np.array([X]))
        r, g, b = res.color[int(round(uv[0, 1])), int(round(uv[0, 0]))].astype(int)
        if name == "red":
            assert r > 100 and r > 2 * g and r > 2 * b, (name, r, g, b)
        elif name == "green":
            assert g > 100 and g > 2 * r and g > 2 * b, (name, r, g, b)
        elif name == "blue":
            assert b > 100 and b > 2 * r and b > 2 * g, (name, r, g, b)
        else:
            assert min(r, g, b) > 150, (name, r, g, b)


def test_depth_is_metres_along_optical_axis():
    intr = CameraIntrinsics(width=320, height=240, fx=160.0, fy=160.0, cx=150.0, cy=130.0)  # wide view
    M = look_at(np.array([0.0, 0.0, 2.0]), np.array([0.0, 10.0, 2.0]))
    scene = OffscreenScene(intr.width, intr.height)
    wall = trimesh.Trimesh(np.array([[-50, 7.5, -50], [50, 7.5, -50], [50, 7.5, 50], [-50, 7.5, 50]], float),
                           np.array([[0, 1, 2], [0, 2, 3]]), process=False)
    scene.add(SceneMesh("wall", wall))
    res = scene.render(intr.K, M)
    # camera z, not distance along the ray: the same 7.5 m at the centre and in the corners
    assert np.allclose(res.depth, 7.5, atol=1e-4)
    assert np.all(res.instance == -1)


def test_instance_mask_and_occlusion():
    intr = CameraIntrinsics(width=320, height=200, fx=260.0, fy=260.0, cx=170.0, cy=95.0)
    M = look_at(np.array([0.0, -12.0, 3.0]), np.array([0.0, 0.0, 1.0]))
    scene = OffscreenScene(intr.width, intr.height)
    ground = trimesh.creation.box(extents=[80, 80, 0.2])
    ground.apply_translation([0, 0, -0.1])
    ground.visual.face_colors = [110, 140, 80, 255]
    a = trimesh.creation.box(extents=[2, 2, 2])
    a.apply_translation([-2.0, 0.0, 1.0])
    b = trimesh.creation.box(extents=[2, 2, 2])
    b.apply_translation([1.5, 3.0, 1.0])  # partly behind nothing, further away
    c = trimesh.creation.box(extents=[1, 1, 1])
    c.apply_translation([1.0, -2.0, 0.5])  # in front of b
    scene.add(SceneMesh("ground", ground))
    scene.add(SceneMesh("a", a, instance_id=3))
    scene.add(SceneMesh("b", b, instance_id=7))
    scene.add(SceneMesh("c", c, instance_id=0))
    res = scene.render(intr.K, M)
    R, t = M[:3, :3], M[:3, 3]
    eye = -R.T @ t
    # (point on a face, the face's plane as (axis, value), expected instance)
    for X, (axis, value), want in [([-2.0, -1.0, 1.0], (1, -1.0), 3), ([1.5, 2.0, 1.5], (1, 2.0), 7),
                                   ([1.0, -2.5, 0.5], (1, -2.5), 0), ([0.0, -5.0, 0.0], (2, 0.0), -1)]:
        uv, _ = project_world(intr, M, np.array([X], float))
        u, v = int(round(uv[0, 0])), int(round(uv[0, 1]))
        assert res.instance[v, u] == want, (X, res.instance[v, u], want)
        # exact depth of the face plane along this pixel centre's ray (camera z)
        d = R.T @ np.append(intr.normalized_from_pixels(np.array([[u, v]], float))[0], 1.0)
        z = (value - eye[axis]) / d[axis]
        assert abs(res.depth[v, u] - z) < 1e-3, (X, res.depth[v, u], z)
    assert set(np.unique(res.instance)) == {-1, 0, 3, 7}
    assert np.all(np.isinf(res.depth[0]))  # top row: sky
    assert np.all(res.instance[0] == -1)



def test_depth_and_ids_cast_when_read_against_the_scene_as_rendered():
    """Depth and ids are cast when first read (most renders are pictures nobody reads them of), against the
    triangles the scene had at the render: the same arrays as cast at once, whatever the scene became since."""
    intr = CameraIntrinsics(width=160, height=100, fx=130.0, fy=130.0, cx=85.0, cy=47.5)
    M = look_at(np.array([0.0, -12.0, 3.0]), np.array([0.0, 0.0, 1.0]))
    scene = OffscreenScene(intr.width, intr.height)
    ground = trimesh.creation.box(extents=[80, 80, 0.2])
    ground.apply_translation([0, 0, -0.1])
    box = trimesh.creation.box(extents=[2, 2, 2])
    box.apply_translation([0.0, 0.0, 1.0])
    scene.add(SceneMesh("ground", ground))
    scene.add(SceneMesh("box", box, instance_id=4))
    u, v = np.meshgrid(np.arange(intr.width, dtype=float), np.arange(intr.height, dtype=float))
    xy = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy], axis=-1)
    depth, instance = scene.trace(M, xy)
    res = scene.render(intr.K, M)
    photo = render_photo(scene, CameraIntrinsics(width=160, height=100, fx=130.0, fy=130.0, cx=85.0, cy=47.5,
                                                 k1=-0.05), M, supersample=1)
    scene.remove("box")  # after the renders: what they cast is the scene they rendered
    assert np.array_equal(res.depth, depth) and np.array_equal(res.instance, instance)
    assert np.count_nonzero(photo.instance == 4) > 100
    assert not np.any(scene.render(intr.K, M).instance == 4)


def test_empty_scene_gives_background():
    scene = OffscreenScene(64, 48, background_rgb=(0.2, 0.4, 0.6))
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    res = scene.render(K, np.eye(4))
    assert np.all(np.isinf(res.depth)) and res.depth.dtype == np.float32
    assert np.all(res.instance == -1)
    assert res.color.shape == (48, 64, 3)
    assert np.ptp(res.color.reshape(-1, 3), axis=0).max() <= 3  # uniform background


def test_render_rejects_skew():
    scene = OffscreenScene(32, 32)
    with pytest.raises(ValueError, match="render_photo"):
        scene.render(np.array([[30.0, 2.0, 16], [0, 30.0, 16], [0, 0, 1]]), np.eye(4))


def test_scenes_share_the_renderer():
    K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    M = look_at(np.array([0.0, -5.0, 0.0]), np.zeros(3))
    red, blue = trimesh.creation.box(extents=[3, 0.1, 3]), trimesh.creation.box(extents=[3, 0.1, 3])
    red.visual.face_colors = [220, 20, 20, 255]
    blue.visual.face_colors = [20, 20, 220, 255]
    s1, s2 = OffscreenScene(64, 48), OffscreenScene(64, 48)
    s1.add(SceneMesh("x", red, 1))
    s2.add(SceneMesh("x", blue, 2))
    for _ in range(2):
        c1, c2 = s1.render(K, M), s2.render(K, M)
        assert c1.color[24, 32, 0] > c1.color[24, 32, 2] and c2.color[24, 32, 2] > c2.color[24, 32, 0]
        assert c1.instance[24, 32] == 1 and c2.instance[24, 32] == 2


def test_missing_vulkan_is_a_render_error(monkeypatch):
    monkeypatch.delenv("WORKBENCH_SKIP_VULKAN_CHECK", raising=False)
    monkeypatch.setattr(offscreen_mod.ctypes.util, "find_library", lambda name: None)
    with pytest.raises(RenderError, match="libvulkan1 mesa-vulkan-drivers libegl1 libgl1"):
        offscreen_mod._check_vulkan()


@pytest.mark.parametrize("skew", [0.0, 3.0])
def test_distorted_photo_markers(skew):
    intr = CameraIntrinsics(width=480, height=360, fx=420.0, fy=415.0, cx=247.0, cy=171.0, skew=skew,
                            k1=-0.1, k2=0.02, p1=0.001, p2=-0.0015)
    M = look_at(np.array([10.0, -20.0, 5.0]), np.array([11.0, -10.0, 4.0]))
    scene = OffscreenScene(intr.width, intr.height, background_rgb=BLACK)
    targets = []
    for u in (12.0, 120.0, 240.0, 380.0, 466.0):
        for v in (10.0, 100.0, 180.0, 350.0):
            z = 6.0 + 0.1 * len(targets)
            xy = intr.undistort(intr.normalized_from_pixels(np.array([[u, v]])))[0]
            c = np.array([xy[0] * z, xy[1] * z, z])
            targets.append(c)
            scene.add(SceneMesh(f"m{len(targets)}", _disk_facing_camera(c, 0.045 * z / 6.0, M), instance_id=len(targets) - 1))
    scene.set_sun(_world_from_cam(M)[:3, :3] @ np.array([0.0, 0.0, 1.0]), shadows=False)
    res = render_photo(scene, intr, M)
    assert res.color.shape == (360, 480, 3)
    gray = res.color.astype(float).mean(axis=2)
    for i, c in enumerate(targets):
        uv = intr.project(c[None])[0]
        got = _centroid(gray, uv, half=6)
        assert np.all(np.abs(got - uv) < 0.3), (i, got, uv)
        u, v = int(round(uv[0])), int(round(uv[1]))
        assert abs(res.depth[v, u] - c[2]) < 0.02, (i, res.depth[v, u], c[2])
        assert res.instance[v, u] == i


def test_undistorted_photo_is_plain_render(camera):
    intr, M = camera
    scene = OffscreenScene(intr.width, intr.height)
    scene.add(SceneMesh("d", _disk_facing_camera([0, 0, 5], 0.5, M), 0))
    res = render_photo(scene, intr, M)
    assert res.instance[int(round(intr.cy)), int(round(intr.cx))] == 0


def test_look_textured_lit_scene():
    """A daylight scene, saved to /tmp/render_look.png for eyes; shaded sides must not be black."""
    intr = CameraIntrinsics(width=480, height=360, fx=420.0, fy=420.0, cx=239.5, cy=179.5)
    M = look_at(np.array([1.5, -2.0, 2.5]), np.array([0.0, 9.0, 1.5]))
    ground = trimesh.creation.box(extents=[60, 60, 0.2])
    ground.apply_translation([0, 10, -0.1])
    ground.visual.face_colors = [110, 140, 80, 255]
    box = trimesh.creation.box(extents=[3, 2, 2.5])
    box.apply_translation([4, 8, 1.25])
    box.visual.face_colors = [200, 120, 40, 255]
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.2)
    sphere.apply_translation([-4, 7, 1.2])
    sphere.visual.vertex_colors = [180, 180, 200, 255]
    scene = OffscreenScene(intr.width, intr.height)
    scene.add(SceneMesh("ground", ground))
    scene.add(SceneMesh("wall", _textured_wall(-2.0, 2.0, 10.0, 0.0, 4.0), 0))
    scene.add(SceneMesh("box", box, 1))
    scene.add(SceneMesh("sphere", sphere, 2))
    scene.set_sun([0.5, 0.6, -0.6])
    res = render_photo(scene, intr, M)
    Image.fromarray(res.color).save("/tmp/render_look.png")
    # the box's side facing away from the sun (+x) is in its own shadow but lit by the sky
    uv, _ = project_world(intr, M, np.array([[2.6, 8.0, 1.25], [2.5, 7.0, 1.25]]))
    side_lit = res.color[int(uv[1, 1]), int(uv[1, 0])].astype(int)  # front face (-y), sunlit
    assert side_lit.sum() > 250
    sphere_px = res.color[res.instance == 2].astype(float).mean(axis=1)
    assert sphere_px.min() > 40, "shadowed side of the sphere is black"
    assert (res.instance == 0).sum() > 1000


def test_exif_round_trip(tmp_path):
    img = (np.random.default_rng(0).random((300, 400, 3)) * 255).astype(np.uint8)
    p = tmp_path / "sub" / "photo.jpg"
    write_jpeg(p, img, focal_length_mm=4.25, sensor_width_mm=6.17, make="Acme", model="X1",
               extra={"DateTimeOriginal": "2024:05:01 14:03:00"})
    assert sorted(os.listdir(p.parent)) == ["photo.jpg"]  # no temporary left behind
    want_px = 4.25 / 6.17 * 400
    got = read_focal_px(p)
    assert got is not None and abs(got - want_px) / want_px < 1e-3
    import piexif

    ex = piexif.load(str(p))
    assert ex["0th"][piexif.ImageIFD.Make] == b"Acme" and ex["0th"][piexif.ImageIFD.Model] == b"X1"
    assert ex["Exif"][piexif.ExifIFD.DateTimeOriginal] == b"2024:05:01 14:03:00"
    assert ex["Exif"][piexif.ExifIFD.FocalLengthIn35mmFilm] == round(4.25 * 36 / 6.17)
    assert ex["Exif"][piexif.ExifIFD.FocalPlaneResolutionUnit] == 3
    assert ex["Exif"][piexif.ExifIFD.PixelXDimension] == 400 and ex["Exif"][piexif.ExifIFD.PixelYDimension] == 300
    back = np.asarray(Image.open(p))
    assert back.shape == img.shape
    # a resized copy that kept the tags still gives the right focal for its own size
    Image.fromarray(back).resize((200, 150)).save(tmp_path / "small.jpg", exif=Image.open(p).info["exif"])
    assert abs(read_focal_px(tmp_path / "small.jpg") - want_px / 2) / want_px < 1e-3


def test_exif_missing_gives_none(tmp_path):
    p = tmp_path / "plain.jpg"
    Image.fromarray(np.zeros((10, 10, 3), np.uint8)).save(p)
    assert read_focal_px(p) is None


def test_track_mesh_lays_two_rails_along_the_line():
    """The railway layer drawn in the 3-D scene: two rails at the gauge plus a head's width apart, centre to centre,
    along the line, at its heights (top of rail) or 0.2 m over the ground it was draped on."""
    from workbench.core.track import RailwayLine
    from workbench.report.scene import RAIL_ABOVE_GROUND_M, track_mesh

    s = np.linspace(0.0, 1.0, 30)
    P = np.column_stack([100.0 * np.sin(s), 100.0 * (1.0 - np.cos(s)), 5.0 + s])  # a 100 m radius curve, rising
    line = RailwayLine("l1", None, P)
    for top, dz in ((True, 0.0), (False, RAIL_ABOVE_GROUND_M)):
        m = track_mesh([line], top_of_rail=top)
        V = np.asarray(m.vertices)
        assert len(m.faces) == 2 * 2 * (len(P) - 1)  # two rails, two triangles a segment
        r = np.hypot(V[:, 0], V[:, 1] - 100.0)  # distance from the curve's centre
        half = (1.435 + 0.07) / 2
        assert np.all(np.abs(np.abs(r - 100.0) - half) <= 0.0701)  # each rail's band is 0.14 m wide about its line
        assert np.allclose(np.sort(np.unique(np.round(np.abs(r - 100.0) - half, 6))), [-0.07, 0.07], atol=2e-3)
        feet = np.array([line.foot(v[:2]).chainage_m for v in V])
        z_line = np.interp(feet, 100.0 * s, P[:, 2])
        assert np.abs(V[:, 2] - (z_line + dz)).max() < 0.01
        assert np.all(m.face_normals[:, 2] > 0.99)  # faces up
    assert track_mesh([], top_of_rail=True) is None
