"""Rolling-stock library: shipped types, geometry, marked points, textures, user types and errors."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import trimesh

from workbench.errors import SettingsError, UnknownModelType, WorkbenchError
from workbench.rolling_stock import TYPES_DIR, CarriageType, get_type, load_library

# the types with reference imagery (their liveries are what the synthetic photos show: the finder's references)
REFERENCE = ("shoreliner", "p32ac-dm", "amfleet-i", "acs-64")
# real rolling stock photographed or of most derailments (issue 16): colours to draw them in, no reference
REAL = ("keikyu-n1000", "meitetsu-3500", "dot-111")
SHIPPED = REFERENCE + REAL

# published values (see the comments in each type file): length over couplers, width, height (m)
PUBLISHED = {
    "shoreliner": (25.91, 3.20, 4.30),  # 85 ft, 10 ft 6 in, ~14 ft 1 in
    "p32ac-dm": (21.03, 3.05, 4.37),  # 69 ft, 10 ft, 14 ft 4 in
    "amfleet-i": (26.01, 3.20, 3.86),  # 85 ft 4 in, 10 ft 6 in, 12 ft 8 in
    "acs-64": (20.32, 2.984, 3.81),  # 20,320 mm, 2,984 mm, 3,810 mm without pantograph
    # from memory of published figures (marked so in the type files): 18,000 mm x 2,798 mm, roof ~3.62 m
    "keikyu-n1000": (18.00, 2.80, 3.62),
    "meitetsu-3500": (19.15, 2.74, 3.68),  # 19 m class leading car, 2,740 mm, roof ~3.68 m
    "dot-111": (17.30, 3.00, 4.20),  # ~17.3 m over couplers, 3.0 m tank, top of the shell ~4.2 m
}
COUPLER_HEIGHT = {"keikyu-n1000": 0.88, "meitetsu-3500": 0.88}  # Japanese standard; else AAR 0.876 m


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


def test_workbench_types_lists_them():
    import os
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "workbench.cli", "types"], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "COLUMNS": "250"})
    assert r.returncode == 0, r.stderr
    for tid in SHIPPED:
        assert f" {tid} " in r.stdout, r.stdout


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
    zc = COUPLER_HEIGHT.get(tid, 0.876)
    np.testing.assert_allclose(ct.coupler_front, [ct.length_m / 2, 0, zc], atol=1e-9)
    np.testing.assert_allclose(ct.coupler_rear, [-ct.length_m / 2, 0, zc], atol=1e-9)
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
    # a corner anchor of an end rounded in plan (corner_radius_m r) stays at the sharp corner the side and end
    # planes would make (picked from two edges): r (sqrt 2 - 1) off the rounded surface; every other point on it
    # (an end also bowed in plan, corner_setback_m, meets the side at a wider angle: cut by less, but cut)
    expected, bowed = np.zeros(len(names)), np.zeros(len(names), bool)
    for i, n in enumerate(names):
        faces = set(ct.marked_point_faces[n])
        for end in ("front", "rear"):
            e = getattr(ct.spec, end, None)
            r = float(getattr(e, "corner_radius_m", 0.0) or 0.0)
            if end in faces and faces & {"left", "right"} and r > 0:
                expected[i] = r * (np.sqrt(2.0) - 1.0)
                bowed[i] = float(getattr(e, "corner_setback_m", 0.0) or 0.0) > 0
    for textured in (False, True):
        d = _surface_distance(ct.mesh(textured=textured), pts)
        ok = np.where(bowed, (d > 0.005) & (d < expected + 1e-3), np.abs(d - expected) < 1e-3)
        assert np.all(ok), dict(zip(names, d - expected))
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
    assert a.std() > (20 if tid in REFERENCE else 5)  # a plain black tank car is plainer than a coach
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


@pytest.mark.parametrize("tid", REFERENCE)
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


# --------------------------------------------------------------------------------------------------------
# every bound stated (issue 16)
# --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("old,new,key,value,bound", [
    ("wheel_diameter_m = 0.9", "wheel_diameter_m = 0.9\ncoupler_height_m = 1.8", "dimensions.coupler_height_m", "1.8",
     "implausible coupler height: allowed above 0.3 m and below body_bottom_m + 0.5 = 1.600 m"),
    ("bogie_centres_m = 12.0", "bogie_centres_m = 15.0", "dimensions.bogie_centres_m", "15.0",
     "(bogie_centres_m at most 13.800 m)"),
    ("eave_height_m = 3.5", "eave_height_m = 3.5\nroof_edge_inset_m = 1.6", "profile.roof_edge_inset_m", "1.6",
     "less than width_m / 2 - 0.05 = 1.450 m"),
    ("wheel_diameter_m = 0.9", "wheel_diameter_m = 1.09", "dimensions.wheel_diameter_m", "1.09",
     "at most body_bottom_m - 0.02 = 1.080 m"),
    ("length_over_couplers_m = 18.0", "length_over_couplers_m = 17.25", "dimensions.body_length_m", "17.2",
     "at most length_over_couplers_m - 0.1 = 17.150 m"),
    ("x_m = 5.0", "x_m = 8.5", "doors[0].x_m", "8.5", "at most body_length_m / 2 = 8.600 m"),
    ("equipment_depth_m = 0.0", "equipment_depth_m = 0.9", "dimensions.equipment_depth_m", "0.9",
     "at most body_bottom_m - 0.25 = 0.850 m"),
])
def test_every_bound_is_stated_with_the_value(tmp_path: Path, old, new, key, value, bound):
    p = tmp_path / "bad.toml"
    text = _user_toml().replace("wheel_diameter_m = 0.9", "wheel_diameter_m = 0.9\nequipment_depth_m = 0.0")
    assert old in text
    p.write_text(text.replace(old, new, 1), encoding="utf-8")
    with pytest.raises(SettingsError) as e:
        load_library(extra_dirs=[tmp_path])
    msg = str(e.value)
    assert str(p) in msg and f"'{key}' = {value}:" in msg and bound in msg, msg


def test_rounded_end_corners(tmp_path: Path):
    """An end's corners rounded in plan (``corner_radius_m``): the sharp corner is cut by r (sqrt 2 - 1), the end
    face and the side stay where they were, the corner anchors stay at the sharp corner (picked from two edges);
    a radius too large for the body is refused with its bound."""
    p = tmp_path / "user.toml"
    p.write_text(_user_toml() + "\n[front]\ncorner_radius_m = 0.6\ncorner_segments = 8\n", encoding="utf-8")
    t = load_library(extra_dirs=[tmp_path])["test-flat"]
    m = t.mesh(textured=False)
    assert m.is_watertight and np.allclose(m.bounds, [[-9.0, -1.5, 0.0], [9.0, 1.5, m.bounds[1][2]]], atol=1e-6)
    z = 2.0
    def dist(q):
        return float(np.linalg.norm(trimesh.proximity.closest_point(m, [q])[0][0] - q))
    r = 0.6
    assert dist([8.6, 1.5, z]) == pytest.approx(r * (np.sqrt(2) - 1), abs=0.006)  # the front corners: cut
    assert dist([8.6, -1.5, z]) == pytest.approx(r * (np.sqrt(2) - 1), abs=0.006)
    assert dist([-8.6, 1.5, z]) < 1e-6  # the rear: sharp
    assert dist([8.6, 0.0, z]) < 1e-6 and dist([0.0, 1.5, z]) < 1e-6 and dist([8.0, 1.5, z]) < 1e-6
    assert np.allclose(t.marked_points["tfl"][:2], [8.6, 1.5])  # anchor body_top_front_left
    p.write_text(_user_toml() + "\n[front]\ncorner_radius_m = 1.6\n", encoding="utf-8")
    with pytest.raises(SettingsError) as e:
        load_library(extra_dirs=[tmp_path])
    assert "'front.corner_radius_m' = 1.6:" in str(e.value) and "= 1.450 m" in str(e.value), str(e.value)


def test_an_end_bowed_in_plan(tmp_path: Path):
    """An end bowed in plan (``corner_setback_m`` s, a cab front swept back to its corners): its middle stays at
    body_length_m / 2, its surface falls back as s (y / half width)^2, the corner anchors stand s behind the middle,
    the coupler stays at length_over_couplers_m / 2; a setback too long for the body, or a door it would cut, is
    refused with its bound."""
    p = tmp_path / "user.toml"
    p.write_text(_user_toml() + "\n[front]\ncorner_setback_m = 0.5\n", encoding="utf-8")
    t = load_library(extra_dirs=[tmp_path])["test-flat"]
    m = t.mesh(textured=False)
    assert m.is_watertight
    def dist(q):
        return float(np.linalg.norm(trimesh.proximity.closest_point(m, [q])[0][0] - q))
    for y in (0.0, 0.375, 0.75, 1.125, 1.35, 1.5):  # the face's samples (the body 17.2 m long): on the surface
        assert dist([8.6 - 0.5 * (y / 1.5) ** 2, y, 2.5]) < 1e-6, y
        assert dist([8.6 - 0.5 * (y / 1.5) ** 2, -y, 1.5]) < 1e-6, y
    assert dist([8.62, 0.0, 2.5]) == pytest.approx(0.02, abs=1e-6)  # nothing ahead of the middle
    assert dist([8.1, 1.5, 2.5]) < 1e-6 and dist([7.0, 1.5, 2.5]) < 1e-6  # the side up to the corner
    assert dist([-8.6, 1.5, 2.5]) < 1e-6 and dist([-8.6, 0.0, 2.5]) < 1e-6  # the rear: flat, sharp
    assert np.allclose(t.marked_points["tfl"][:2], [8.1, 1.5])  # anchor body_top_front_left
    assert np.allclose(t.coupler_front, [t.spec.dimensions.length_over_couplers_m / 2, 0.0,
                                         t.spec.dimensions.coupler_height_m])
    p.write_text(_user_toml() + "\n[front]\ncorner_setback_m = 7.0\n", encoding="utf-8")
    with pytest.raises(SettingsError) as e:
        load_library(extra_dirs=[tmp_path])
    assert "'front.corner_setback_m' = 7.0:" in str(e.value) and "= 5.600 m" in str(e.value), str(e.value)
    p.write_text(_user_toml() + "\n[front]\ncorner_setback_m = 3.2\n", encoding="utf-8")  # the door at 4.5-5.5 m
    with pytest.raises(SettingsError) as e:
        load_library(extra_dirs=[tmp_path])
    assert "'doors[0].x_m' = 5.0:" in str(e.value) and "corner_setback_m = 5.400 m" in str(e.value), str(e.value)


def test_explicit_point_error_states_the_distance_and_the_tolerance(tmp_path: Path):
    p = tmp_path / "bad.toml"
    p.write_text(_user_toml().replace("xyz = [-8.6, -1.5, 1.1]", "xyz = [-8.6, -1.6, 1.1]"), encoding="utf-8")
    with pytest.raises(SettingsError) as e:
        load_library(extra_dirs=[tmp_path])
    msg = str(e.value)
    assert "'corner'" in msg and "0.100 m from the model's surface" in msg and "5 mm" in msg, msg


def test_a_tank_car_is_a_cylinder(lib):
    """dot-111: the profile's rounded roof and rounded lower edge (8 segments each) make the tank's 3.0 m circle
    within 17 mm (the two quarter ellipses' centres sit 6 cm off the axis: the format keeps a flat strip of at
    least 10 cm on top and below)."""
    from workbench.rolling_stock.geometry import profile_yz

    ct = lib["dot-111"]
    axis = (ct.spec.profile.eave_height_m + ct.spec.profile.wall_bottom_m) / 2
    yz = profile_yz(ct.spec)
    r = np.hypot(yz[:, 0], yz[:, 1] - axis)
    assert np.all(np.abs(r - 1.5) < 0.017), r
    body = ct.parts()[0].mesh  # and between the vertices: the chords sag inwards by under 1 cm
    pts, _ = trimesh.sample.sample_surface(body, 4000, seed=0)
    mid = pts[np.abs(pts[:, 0]) < ct.body_length_m / 2 - 0.01]
    rr = np.hypot(mid[:, 1], mid[:, 2] - axis)
    assert np.all(np.abs(rr - 1.5) < 0.017), (rr.min(), rr.max())


# --------------------------------------------------------------------------------------------------------
# mesh types (a manufacturer's CAD export)
# --------------------------------------------------------------------------------------------------------
# a box car body 20 m over the "couplers" (the box's ends), 3.0 m wide, from 0.0 to 3.6 m above the rail
BOX_LO, BOX_HI = np.array([-10.0, -1.5, 0.0]), np.array([10.0, 1.5, 3.6])
BOX_POINTS = {  # corners of the box, with their faces
    "top_front_left": ([10.0, 1.5, 3.6], ["front", "left", "roof"]),
    "top_front_right": ([10.0, -1.5, 3.6], ["front", "right", "roof"]),
    "top_rear_left": ([-10.0, 1.5, 3.6], ["rear", "left", "roof"]),
    "top_rear_right": ([-10.0, -1.5, 3.6], ["rear", "right", "roof"]),
    "bottom_front_left": ([10.0, 1.5, 0.0], ["front", "left"]),
    "bottom_rear_right": ([-10.0, -1.5, 0.0], ["rear", "right"]),
    "mid_left": ([0.0, 1.5, 1.8], ["left"]),
}
# glTF's axes (+y up, +z forward, +x left) to the carriage frame's
GLTF_AXES = [[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]


def _box_file(folder: Path, suffix: str, scale: float = 1.0, gltf_axes: bool = False,
              color=(200, 30, 40, 255)) -> Path:
    """The box exported as a CAD tool would: STL / OBJ in millimetres (``scale``), GLB in glTF's axes."""
    box = trimesh.creation.box(extents=BOX_HI - BOX_LO)
    box.apply_translation((BOX_LO + BOX_HI) / 2)
    if gltf_axes:  # carriage (x, y, z) -> glTF (x_g, y_g, z_g) = (y, z, x)
        box.vertices = box.vertices[:, [1, 2, 0]]
    box.apply_scale(scale)
    box.visual.face_colors = np.tile(color, (len(box.faces), 1))
    path = folder / f"box{suffix}"
    box.export(path)
    return path


def _mesh_toml(mesh_file: str, length: float = 20.0, unit_m: float = 1.0, transform=None, points=None,
               extra: str = "") -> str:
    lines = [f'id = "cad-box"\nname = "CAD box car"\nkind = "freight_car"\n{extra}\n[mesh]\nfile = "{mesh_file}"\n'
             f"unit_m = {unit_m}"]
    if transform is not None:
        lines.append(f"carriage_from_file = {transform!r}")
    lines.append(f"\n[dimensions]\nlength_over_couplers_m = {length}\ncoupler_height_m = 0.9\n")
    for name, (xyz, faces) in (points or BOX_POINTS).items():
        lines.append(f'[[marked_points]]\nname = "{name}"\nxyz = {list(map(float, xyz))!r}\nfaces = {faces!r}\n'
                     .replace("'", '"'))
    return "\n".join(lines)


@pytest.mark.parametrize("suffix,scale,unit_m,axes", [(".stl", 1000.0, 0.001, False), (".obj", 1000.0, 0.001, False),
                                                      (".glb", 1.0, 1.0, True)])
def test_mesh_type_from_a_cad_export(tmp_path: Path, suffix, scale, unit_m, axes):
    f = _box_file(tmp_path, suffix, scale=scale, gltf_axes=axes)
    (tmp_path / "cad-box.toml").write_text(_mesh_toml(f.name, unit_m=unit_m, transform=GLTF_AXES if axes else None),
                                           encoding="utf-8")
    ct = get_type("cad-box", extra_dirs=[tmp_path])
    assert ct.is_mesh_type and not ct.has_reference_imagery and ct.kind == "freight_car"
    assert (ct.length_m, ct.body_length_m, ct.width_m, ct.height_m) == pytest.approx((20.0, 20.0, 3.0, 3.6))
    np.testing.assert_allclose(ct.bounding_box(), [BOX_LO, BOX_HI], atol=1e-9)
    np.testing.assert_allclose(ct.coupler_front, [10.0, 0.0, 0.9])
    (c, h), = ct.collision_boxes()
    np.testing.assert_allclose(c - h, BOX_LO, atol=1e-9)
    np.testing.assert_allclose(c + h, BOX_HI, atol=1e-9)
    plain = ct.mesh(textured=False)
    assert plain.is_watertight and plain.volume == pytest.approx(20 * 3 * 3.6)  # outward faces, as in the file
    pts = np.array(list(ct.marked_points.values()))
    assert np.all(_surface_distance(plain, pts) < 1e-6)  # (a GLB holds float32)
    assert ct.marked_point_faces["mid_left"] == ("left",)
    tex = ct.mesh(car_number="42")
    assert isinstance(tex.visual, trimesh.visual.TextureVisuals) and tex.metadata["car_number"] == "42"
    uv = np.asarray(tex.visual.uv)
    assert uv.shape == (len(tex.vertices), 2) and np.all((uv > 0) & (uv < 1))
    img = np.asarray(tex.visual.material.image.convert("RGB"))
    colours = {tuple(c) for c in img.reshape(-1, 3)}
    if suffix == ".stl":  # STL has no colour: the type's colour
        assert colours == {(0x8a, 0x8d, 0x90)}
    else:  # the file's colour
        assert (200, 30, 40) in colours
    s = ct.sample_surface(100, seed=0)
    assert s.shape == (100, 3) and s[:, 2].min() == pytest.approx(0.0)  # the 8 hull corners, topped up
    assert np.array_equal(s, ct.sample_surface(100, seed=0))
    assert ct.parts()[0].kind == "body"


def test_mesh_type_keeps_the_files_material_colours(tmp_path: Path):
    from trimesh.visual.material import PBRMaterial

    box = trimesh.creation.box(extents=BOX_HI - BOX_LO)
    box.apply_translation((BOX_LO + BOX_HI) / 2)
    box.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(baseColorFactor=[20, 200, 30, 255]))
    wheel = trimesh.creation.cylinder(radius=0.4, height=0.2)  # a second node, another colour
    wheel.apply_translation([5.0, 1.3, 0.4])
    wheel.visual.face_colors = [10, 10, 10, 255]
    trimesh.Scene([box, wheel]).export(tmp_path / "two.glb")
    (tmp_path / "cad-box.toml").write_text(_mesh_toml("two.glb"), encoding="utf-8")
    ct = get_type("cad-box", extra_dirs=[tmp_path])
    m = ct.mesh()
    colours = {tuple(c) for c in np.asarray(m.visual.material.image).reshape(-1, 3)}
    assert colours == {(20, 200, 30), (10, 10, 10)}
    assert len(m.faces) == len(box.faces) + len(wheel.faces)


def _write_box_type(tmp_path: Path, **kw) -> Path:
    f = _box_file(tmp_path, ".stl", scale=kw.pop("scale", 1.0))
    p = tmp_path / "cad-box.toml"
    p.write_text(_mesh_toml(f.name, **kw), encoding="utf-8")
    return p


def test_mesh_type_marked_point_off_the_mesh_names_it_and_its_distance(tmp_path: Path):
    pts = dict(BOX_POINTS)
    pts["mid_left"] = ([0.0, 1.52, 1.8], ["left"])  # 2 cm outside the side
    p = _write_box_type(tmp_path, points=pts)
    with pytest.raises(SettingsError) as e:
        load_library(extra_dirs=[tmp_path])
    msg = str(e.value)
    assert str(p) in msg and "'mid_left'" in msg and "marked_points[6]" in msg, msg
    assert "0.020 m from the model's surface" in msg and "5 mm" in msg, msg
    pts["mid_left"] = ([0.0, 1.504, 1.8], ["left"])  # 4 mm: within the tolerance
    _write_box_type(tmp_path, points=pts)
    assert get_type("cad-box", extra_dirs=[tmp_path]).marked_points["mid_left"][1] == pytest.approx(1.504)


def test_mesh_type_anchored_couplers_are_checked_too(tmp_path: Path):
    pts = dict(list(BOX_POINTS.items())[:6])
    _write_box_type(tmp_path, points=pts, extra="")
    p = tmp_path / "cad-box.toml"
    text = p.read_text() + '\n[[marked_points]]\nname = "cf"\nanchor = "coupler_front"\n'
    p.write_text(text)  # (10, 0, 0.9): on the box's front face
    assert get_type("cad-box", extra_dirs=[tmp_path]).marked_point_faces["cf"] == ("front",)
    p.write_text(text.replace("length_over_couplers_m = 20.0", "length_over_couplers_m = 20.08"))
    with pytest.raises(SettingsError, match=r"'cf', anchor 'coupler_front' at \[10.04, 0.0, 0.9\]\): the point is "
                                            r"0.040 m from"):
        load_library(extra_dirs=[tmp_path])
    p.write_text(text.replace('anchor = "coupler_front"', 'anchor = "body_top_front_left"'))
    with pytest.raises(SettingsError, match="only the anchors coupler_front and coupler_rear"):
        load_library(extra_dirs=[tmp_path])


@pytest.mark.parametrize("kw,match", [
    ({"scale": 1000.0}, r"\|x\| <= length_over_couplers_m / 2 \+ 0.05 = 10.050 m; check 'mesh.unit_m'"),
    ({"length": 50.0}, "at least half of length_over_couplers_m = 50.0 m"),
    ({"transform": [[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]]}, "must be a rotation"),
    ({"transform": [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "a mirror cannot be used"),
    ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]}, r"must be \[0, 0, 0, 1\]"),
    ({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -0.5], [0, 0, 0, 1]]},
     "lowest point must lie between -0.05 and 1.5 m"),
    ({"transform": [[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 1.5], [0, 0, 0, 1]]}, "within 2.5 m of the centre line"),
])
def test_mesh_type_in_the_wrong_frame_or_units_is_refused(tmp_path: Path, kw, match):
    _write_box_type(tmp_path, **kw)
    with pytest.raises(SettingsError, match=match):
        load_library(extra_dirs=[tmp_path])


def test_mesh_type_file_errors(tmp_path: Path):
    p = tmp_path / "cad-box.toml"
    p.write_text(_mesh_toml("missing.stl"), encoding="utf-8")
    with pytest.raises(SettingsError, match=r"'mesh.file' = 'missing.stl': not found"):
        load_library(extra_dirs=[tmp_path])
    p.write_text(_mesh_toml("box.step"), encoding="utf-8")
    with pytest.raises(SettingsError, match=r"mesh.file.*one of .gltf, .glb, .obj, .stl"):
        load_library(extra_dirs=[tmp_path])
    (tmp_path / "broken.glb").write_bytes(b"glTF not really")
    p.write_text(_mesh_toml("broken.glb"), encoding="utf-8")
    with pytest.raises(SettingsError, match=r"'mesh.file' = 'broken.glb': cannot read this mesh"):
        load_library(extra_dirs=[tmp_path])
    _box_file(tmp_path, ".stl")
    p.write_text(_mesh_toml("box.stl").replace("[mesh]", '[profile]\neave_height_m = 3.0\n[mesh]'), encoding="utf-8")
    with pytest.raises(SettingsError, match="unknown key 'profile'"):
        load_library(extra_dirs=[tmp_path])


def test_mesh_type_reloads_when_its_mesh_changes(tmp_path: Path):
    _write_box_type(tmp_path)
    a = get_type("cad-box", extra_dirs=[tmp_path])
    assert get_type("cad-box", extra_dirs=[tmp_path]) is a  # cached
    import os
    import time

    f = tmp_path / "box.stl"
    box = trimesh.load(f)
    box.apply_translation([0.0, 0.0, 0.004])  # (the marked points stay within 5 mm of it)
    box.export(f)
    t = time.time() + 5
    os.utime(f, (t, t))
    b = get_type("cad-box", extra_dirs=[tmp_path])
    assert b is not a and b.height_m == pytest.approx(3.604)


TRUCK = Path(__file__).resolve().parents[2] / "shared" / "data" / "trains" / "model_truck_openmaterial" / \
    "truck_example.gltf"


@pytest.mark.skipif(not TRUCK.is_file(), reason="../shared/data/trains is not here")
def test_a_real_gltf_as_a_mesh_type(tmp_path: Path):
    """A real glTF (a road truck exported from Blender, metric, +y up, its front towards -x, its left +z): a
    stand-in rigid vehicle, put into the carriage frame by carriage_from_file, its marked points on the mesh."""
    import shutil
    import time

    for f in (TRUCK, TRUCK.with_suffix(".bin")):
        shutil.copy(f, tmp_path / f.name)
    shutil.copytree(TRUCK.parent / "Textures", tmp_path / "Textures")
    # x_c = -x_f + 2.7664 (the middle of its length), y_c = z_f, z_c = y_f + 0.5452 (the tyres' bottom)
    transform = [[-1, 0, 0, 2.7664], [0, 0, 1, 0], [0, 1, 0, 0.5452], [0, 0, 0, 1]]
    scene = trimesh.load(TRUCK, force="scene")
    V = scene.to_geometry().vertices @ np.array(transform)[:3, :3].T + np.array(transform)[:3, 3]
    picks = {  # real vertices of the file: the extreme corners a person would pick
        "front_top_left": V[np.argmax(V @ [1, 1, 1])], "front_top_right": V[np.argmax(V @ [1, -1, 1])],
        "rear_top_left": V[np.argmax(V @ [-1, 1, 1])], "rear_top_right": V[np.argmax(V @ [-1, -1, 1])],
        "front_low_left": V[np.argmax(V @ [1, 1, -1])], "rear_low_right": V[np.argmax(V @ [-1, -1, -1])],
        "top": V[np.argmax(V[:, 2])],
    }
    faces = {"front_top_left": ["front", "left", "roof"], "front_top_right": ["front", "right", "roof"],
             "rear_top_left": ["rear", "left", "roof"], "rear_top_right": ["rear", "right", "roof"],
             "front_low_left": ["front", "left"], "rear_low_right": ["rear", "right"], "top": ["roof"]}
    points = {n: (np.round(p, 5), faces[n]) for n, p in picks.items()}
    (tmp_path / "cad-box.toml").write_text(
        _mesh_toml(TRUCK.name, length=8.44, transform=transform, points=points), encoding="utf-8")
    t0 = time.perf_counter()
    ct = get_type("cad-box", extra_dirs=[tmp_path])
    t_load = time.perf_counter() - t0
    lo, hi = ct.bounding_box()
    assert lo[2] == pytest.approx(0.0, abs=1e-3) and hi[2] == pytest.approx(3.3826, abs=1e-3)
    assert ct.width_m == pytest.approx(2.8757, abs=1e-3) and ct.body_length_m == pytest.approx(8.4393, abs=1e-3)
    cab = scene.geometry["Cabin_High"].vertices.mean(axis=0)  # (its node is at the origin)
    assert np.array(transform)[0, :3] @ cab + transform[0][3] > 2.5  # the cab is at the front (+x)
    m = ct.mesh(textured=True)
    assert len(m.faces) > 40_000
    # its materials are OpenMaterial references to physical materials, without colours: drawn in mesh.color
    assert {tuple(c) for c in np.asarray(m.visual.material.image).reshape(-1, 3)} == {(0x8a, 0x8d, 0x90)}
    print(f"truck_example.gltf as a mesh type: {len(m.faces)} triangles, loaded and checked in {t_load:.2f} s")
    assert t_load < 20
