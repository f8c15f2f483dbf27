"""Rolling-stock library: shipped types, geometry, marked points, textures, user types and errors."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import trimesh

from workbench.errors import SettingsError, UnknownModelType, WorkbenchError
from workbench.rolling_stock import TYPES_DIR, CarriageType, get_type, load_library

SHIPPED = ("shoreliner", "p32ac-dm", "amfleet-i", "acs-64")

# published values (see the comments in each type file): length over couplers, width, height (m)
PUBLISHED = {
    "shoreliner": (25.91, 3.20, 4.30),  # 85 ft, 10 ft 6 in, ~14 ft 1 in
    "p32ac-dm": (21.03, 3.05, 4.37),  # 69 ft, 10 ft, 14 ft 4 in
    "amfleet-i": (26.01, 3.20, 3.86),  # 85 ft 4 in, 10 ft 6 in, 12 ft 8 in
    "acs-64": (20.32, 2.984, 3.81),  # 20,320 mm, 2,984 mm, 3,810 mm without pantograph
}


def _surface_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Exact distance of each point to the mesh surface (brute force over all triangles; no rtree needed)."""
    tri = mesh.triangles
    out = []
    for p in np.atleast_2d(points):
        q = trimesh.triangles.closest_point(tri, np.repeat(p[None], len(tri), axis=0))
        out.append(np.min(np.linalg.norm(q - p, axis=1)))
    return np.array(out)


@pytest.fixture(scope="module")
def lib() -> dict[str, CarriageType]:
    return load_library()


def test_all_shipped_types_load(lib):
    assert set(SHIPPED) <= set(lib)
    for tid in SHIPPED:
        ct = lib[tid]
        assert ct.id == tid and ct.name and ct.source_path.is_file()
        assert ct.source_path.parent == TYPES_DIR.resolve()
    assert get_type("Shoreliner").id == "shoreliner"  # case-insensitive


@pytest.mark.parametrize("tid", SHIPPED)
def test_dimensions_match_published(lib, tid):
    ct = lib[tid]
    L, W, H = PUBLISHED[tid]
    assert ct.length_m == pytest.approx(L, abs=0.03)
    assert ct.width_m == pytest.approx(W, abs=0.03)
    assert ct.height_m == pytest.approx(H, abs=0.03)
    lo, hi = ct.bounding_box()
    assert hi - lo == pytest.approx([L, W, H], abs=0.03)
    assert lo[2] == pytest.approx(0.0, abs=1e-9)  # wheels touch the rail at z = 0
    assert lo[0] == pytest.approx(-L / 2, abs=1e-9) and hi[0] == pytest.approx(L / 2, abs=1e-9)


@pytest.mark.parametrize("tid", SHIPPED)
def test_couplers_at_half_length(lib, tid):
    ct = lib[tid]
    np.testing.assert_allclose(ct.coupler_front, [ct.length_m / 2, 0, 0.876], atol=1e-9)
    np.testing.assert_allclose(ct.coupler_rear, [-ct.length_m / 2, 0, 0.876], atol=1e-9)
    np.testing.assert_allclose(ct.marked_points["coupler_front"], ct.coupler_front)
    np.testing.assert_allclose(ct.marked_points["coupler_rear"], ct.coupler_rear)
    assert ct.marked_point_faces["coupler_front"] == ("front",)


@pytest.mark.parametrize("tid", SHIPPED)
def test_marked_points_on_surface(lib, tid):
    ct = lib[tid]
    assert 7 <= len(ct.marked_points) <= 10
    assert list(ct.marked_points) == list(ct.marked_point_faces)
    names = list(ct.marked_points)
    pts = np.array([ct.marked_points[n] for n in names])
    assert pts.shape == (len(names), 3)
    for textured in (False, True):
        d = _surface_distance(ct.mesh(textured=textured), pts)
        assert np.all(d < 1e-3), dict(zip(names, d))
    for n in names:
        assert ct.marked_point_faces[n] and set(ct.marked_point_faces[n]) <= {"left", "right", "front", "rear", "roof"}
        assert np.linalg.norm(ct.marked_point_normals[n]) == pytest.approx(1.0)


@pytest.mark.parametrize("tid", SHIPPED)
def test_marked_points_visible_per_side_and_end_not_coplanar(lib, tid):
    ct = lib[tid]
    for side, end in itertools.product(("left", "right"), ("front", "rear")):
        sel = [n for n, fs in ct.marked_point_faces.items() if set(fs) & {side, end}]
        assert len(sel) >= 6, (side, end, sel)
        P = np.array([ct.marked_points[n] for n in sel])
        sv = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
        assert sv[-1] > 0.1, (side, end, sv)  # spread out of any plane by more than 10 cm
        # each point lies on the faces it claims: a side point has y = +-w/2 (or the body's lower edge)
        for n in sel:
            p = ct.marked_points[n]
            if side in ct.marked_point_faces[n]:
                assert np.sign(p[1]) == (1 if side == "left" else -1)


@pytest.mark.parametrize("tid", SHIPPED)
def test_mesh_valid_with_outward_normals(lib, tid):
    ct = lib[tid]
    m = ct.mesh(textured=False)
    assert 200 < len(m.faces) < 5000
    assert m.is_watertight and m.volume > 0
    assert np.all(m.area_faces > 1e-9)
    # every part is closed with outward normals (positive volume)
    for part in ct.parts():
        assert part.mesh.is_watertight and part.mesh.volume > 0, part.name
    # body faces point away from the body centre
    body = ct.parts()[0].mesh
    c = body.center_mass
    assert np.all(np.einsum("ij,ij->i", body.triangles_center - c, body.face_normals) > 0)
    # textured mesh: the same triangles, same orientation
    t = ct.mesh()
    assert len(t.faces) == len(m.faces)
    assert np.all(t.area_faces > 1e-9)
    assert t.volume == pytest.approx(m.volume, rel=1e-6)


@pytest.mark.parametrize("tid", SHIPPED)
def test_texture_and_uvs(lib, tid):
    ct = lib[tid]
    m = ct.mesh(car_number="4242")
    assert isinstance(m.visual, trimesh.visual.TextureVisuals)
    img = m.visual.material.image
    assert img is not None and 1024 <= img.size[0] <= 2048
    uv = np.asarray(m.visual.uv)
    assert uv.shape == (len(m.vertices), 2)
    assert np.all(uv >= 0) and np.all(uv <= 1)
    # texture is detailed (not flat colour) and deterministic; car number changes it
    a = np.asarray(img.convert("L"), dtype=float)
    assert a.std() > 20
    b = np.asarray(ct.mesh(car_number="4242").visual.material.image.convert("L"), dtype=float)
    assert np.array_equal(a, b)
    c = np.asarray(ct.mesh(car_number="9999").visual.material.image.convert("L"), dtype=float)
    assert not np.array_equal(a, c)
    assert m.metadata["car_number"] == "4242"


def test_texture_maps_to_right_faces(lib):
    """Side faces sample the side regions, the ends the end regions, the roof the roof."""
    from workbench.rolling_stock.livery import Atlas

    ct = lib["shoreliner"]
    m = ct.mesh()
    atlas = Atlas(ct.spec)
    n_body = len(ct.parts()[0].mesh.faces)
    uv = np.asarray(m.visual.uv).reshape(-1, 3, 2)[:n_body].mean(axis=1)
    px = np.column_stack([uv[:, 0] * atlas.width, (1 - uv[:, 1]) * atlas.height])
    normals = m.face_normals[:n_body]

    def in_region(name, p):
        r = atlas.regions[name]
        return r.x0 <= p[0] <= r.x0 + r.w and r.y0 <= p[1] <= r.y0 + r.h

    for nrm, p in zip(normals, px):
        if nrm[1] > 0.9:
            assert in_region("left", p)
        elif nrm[1] < -0.9:
            assert in_region("right", p)
        elif nrm[0] > 0.9:
            assert in_region("front", p)
        elif nrm[0] < -0.9:
            assert in_region("rear", p)
        elif nrm[2] > 0.9:
            assert in_region("roof", p)


def test_mesh_cache_returns_copies(lib):
    ct = lib["acs-64"]
    a = ct.mesh("650")
    a.apply_translation([10, 0, 0])
    b = ct.mesh("650")
    assert b.bounds[0][0] == pytest.approx(-ct.length_m / 2)


@pytest.mark.parametrize("tid", SHIPPED)
def test_collision_boxes_and_samples(lib, tid):
    ct = lib[tid]
    boxes = ct.collision_boxes()
    assert len(boxes) >= 3
    c, h = boxes[0]
    assert h == pytest.approx([ct.body_length_m / 2, ct.width_m / 2, (ct.height_m - ct.spec.dimensions.body_bottom_m) / 2])
    assert c[0] == pytest.approx(0.0) and c[1] == pytest.approx(0.0)
    for c, h in boxes:
        assert np.all(np.asarray(h) > 0)
        assert np.all(np.abs(c[:2]) + h[:2] <= [ct.body_length_m / 2 + 1e-9, ct.width_m / 2 + 1e-9])
    pts = ct.sample_surface(3000, seed=0)
    m = ct.mesh(textured=False)
    assert pts.shape == (max(3000, len(np.unique(m.vertices, axis=0))), 3)
    assert np.array_equal(pts, ct.sample_surface(3000, seed=0))
    assert pts[:, 2].min() == pytest.approx(0.0, abs=1e-9)  # wheel contact points included
    lo, hi = ct.bounding_box()
    assert np.all(pts >= lo - 1e-9) and np.all(pts <= hi + 1e-9)
    d = _surface_distance(m, pts[np.linspace(0, len(pts) - 1, 40).astype(int)])
    assert np.all(d < 1e-6)


# --------------------------------------------------------------------------------------------------------
def _user_toml(tid: str = "test-flat", length: float = 18.0, extra: str = "") -> str:
    return f"""
id = "{tid}"
name = "Test flat-ended car"
operator = "Test Railway"
default_car_number = "77"
{extra}
[dimensions]
length_over_couplers_m = {length}
body_length_m = 17.2
width_m = 3.0
height_m = 4.0
body_bottom_m = 1.1
floor_height_m = 1.25
bogie_centres_m = 12.0
bogie_wheelbase_m = 2.5
wheel_diameter_m = 0.9

[profile]
eave_height_m = 3.5

[[doors]]
x_m = 5.0
width_m = 1.0
z_bottom_m = 1.25
z_top_m = 3.2

[livery]
operator_text = "TEST RAILWAY"
stripes = [{{ z_bottom_m = 1.6, z_top_m = 1.8, color = "#aa2200" }}]

[[marked_points]]
name = "cf"
anchor = "coupler_front"
[[marked_points]]
name = "cr"
anchor = "coupler_rear"
[[marked_points]]
name = "tfl"
anchor = "body_top_front_left"
[[marked_points]]
name = "tfr"
anchor = "body_top_front_right"
[[marked_points]]
name = "trl"
anchor = "body_top_rear_left"
[[marked_points]]
name = "trr"
anchor = "body_top_rear_right"
[[marked_points]]
name = "dl"
anchor = "door1_top_front_left"
[[marked_points]]
name = "corner"
xyz = [-8.6, -1.5, 1.1]
faces = ["right", "rear"]
"""


def test_user_type_loads_from_extra_dir(tmp_path: Path):
    (tmp_path / "test-flat.toml").write_text(_user_toml(), encoding="utf-8")
    lib = load_library(extra_dirs=[tmp_path])
    assert "test-flat" in lib and set(SHIPPED) <= set(lib)
    ct = get_type("test-flat", extra_dirs=[tmp_path])
    assert ct.length_m == 18.0 and ct.source_path == (tmp_path / "test-flat.toml").resolve()
    np.testing.assert_allclose(ct.marked_points["dl"], [5.5, 1.5, 3.2])
    np.testing.assert_allclose(ct.marked_points["corner"], [-8.6, -1.5, 1.1])
    assert ct.marked_point_faces["corner"] == ("right", "rear")
    m = ct.mesh()
    pts = np.array(list(ct.marked_points.values()))
    assert np.all(_surface_distance(m, pts) < 1e-3)
    with pytest.raises(UnknownModelType):
        get_type("test-flat")  # not without the extra folder


def test_bad_type_file_unknown_key(tmp_path: Path):
    p = tmp_path / "bad.toml"
    p.write_text(_user_toml(extra='colour = "red"'), encoding="utf-8")
    with pytest.raises(SettingsError) as e:
        load_library(extra_dirs=[tmp_path])
    assert str(p) in str(e.value) and "colour" in str(e.value)


def test_bad_type_file_negative_length(tmp_path: Path):
    p = tmp_path / "bad.toml"
    p.write_text(_user_toml(length=-18.0), encoding="utf-8")
    with pytest.raises(SettingsError) as e:
        load_library(extra_dirs=[tmp_path])
    msg = str(e.value)
    assert str(p) in msg and "dimensions.length_over_couplers_m" in msg and "-18.0" in msg


def test_bad_type_file_inconsistent_values(tmp_path: Path):
    p = tmp_path / "bad.toml"
    p.write_text(_user_toml(length=15.0), encoding="utf-8")  # shorter than the body
    with pytest.raises(SettingsError, match="body_length_m"):
        load_library(extra_dirs=[tmp_path])
    p.write_text(_user_toml().replace('anchor = "door1_top_front_left"', 'anchor = "door7_top_front_left"'))
    with pytest.raises(SettingsError, match=r"marked_points\[6\]\.anchor"):
        load_library(extra_dirs=[tmp_path])
    p.write_text("id = [", encoding="utf-8")
    with pytest.raises(SettingsError, match="not valid TOML"):
        load_library(extra_dirs=[tmp_path])


def test_unknown_type_lists_known_ones():
    with pytest.raises(UnknownModelType) as e:
        get_type("tgv-duplex")
    msg = str(e.value)
    assert "tgv-duplex" in msg
    for tid in SHIPPED:
        assert tid in msg
    assert isinstance(e.value, WorkbenchError)


@pytest.mark.parametrize("tid", SHIPPED)
def test_livery_has_sift_features(lib, tid):
    cv2 = pytest.importorskip("cv2")
    from workbench.rolling_stock.livery import Atlas

    ct = lib[tid]
    img = np.asarray(ct.mesh().visual.material.image.convert("L"))
    atlas = Atlas(ct.spec)
    for region, minimum in (("left", 500), ("right", 500), ("front", 60), ("rear", 60)):
        r = atlas.regions[region]
        kp = cv2.SIFT_create().detect(img[r.y0:r.y0 + r.h, r.x0:r.x0 + r.w])
        assert len(kp) >= minimum, (region, len(kp))


def test_open3d_conversion(lib):
    pytest.importorskip("open3d")
    from workbench.rolling_stock.preview import to_open3d

    m = lib["p32ac-dm"].mesh()
    om = to_open3d(m)
    assert len(om.triangles) == len(m.faces)
    assert np.asarray(om.triangle_uvs).shape == (3 * len(m.faces), 2)


def test_explicit_marked_point_off_surface_is_refused(tmp_path: Path):
    p = tmp_path / "bad.toml"
    p.write_text(_user_toml().replace("xyz = [-8.6, -1.5, 1.1]", "xyz = [-8.0, -1.0, 2.0]"), encoding="utf-8")
    with pytest.raises(SettingsError, match=r"marked_points\[7\]\.xyz"):
        load_library(extra_dirs=[tmp_path])
