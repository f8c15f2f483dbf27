"""Terrain model (DEM -> ENU mesh, exact surface queries), synthetic scenarios and synthetic buildings."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio
import trimesh
from PIL import Image
from rasterio.transform import from_origin
from shapely.geometry import Point, Polygon

from workbench.core.frames import SceneFrame
from workbench.errors import InputError
from workbench.files.buildings import read_buildings_geojson, write_buildings_geojson
from workbench.synth.buildings import make_buildings
from workbench.terrain.extrude import building_meshes
from workbench.synth.terrain import (RAIL_HALF_GAUGE_M, TOP_OF_RAIL_ABOVE_BED_M, make_terrain, scenario_frame,
                                     write_dem_geotiff)
from workbench.files.dem import DemHolesFilled, TerrainModel

SHARED_DEM = Path(__file__).resolve().parents[2] / "shared" / "data" / "dem"  # ../shared beside the repository
SCENARIOS = ["embankment_river", "cutting_curve"]


# ----------------------------------------------------------------------------------------------------------
# Fixtures
# ----------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small():
    """A 200 m embankment scenario, its GeoTIFF and terrain model (fast)."""
    frame = scenario_frame("embankment_river")
    terrain = make_terrain("embankment_river", frame, size_m=200.0, resolution_m=1.0, seed=3, texture_px_per_m=2.0)
    return frame, terrain


@pytest.fixture(scope="module")
def small_model(small, tmp_path_factory):
    frame, terrain = small
    path = write_dem_geotiff(tmp_path_factory.mktemp("dem") / "small.tif", terrain)
    return path, TerrainModel.from_geotiff(path, frame)


@pytest.fixture(scope="module", params=SCENARIOS)
def full(request):
    """Full-size scenario (400 m, 1 m cells, 4 px/m texture) with its terrain model and buildings."""
    sc = request.param
    frame = scenario_frame(sc)
    terrain = make_terrain(sc, frame, seed=0, texture_px_per_m=4.0)
    model = TerrainModel.from_array(terrain.heights, terrain.transform, terrain.crs, frame)
    buildings = make_buildings(sc, terrain, frame, seed=0)
    return sc, frame, terrain, model, buildings


def _write_tif(path: Path, z: np.ndarray, transform, crs, nodata=None) -> Path:
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype=z.dtype,
                       crs=crs, transform=transform, nodata=nodata) as dst:
        dst.write(z, 1)
    return path


class _BruteTree:
    """Stand-in for trimesh's r-tree (rtree is not installed): the triangles whose boxes overlap a query box."""

    def __init__(self, triangles: np.ndarray) -> None:
        self.lo = triangles.min(axis=1)
        self.hi = triangles.max(axis=1)
        self.bounds = np.concatenate([self.lo.min(axis=0), self.hi.max(axis=0)])

    def intersection(self, b):
        b = np.asarray(b, dtype=float)
        return np.flatnonzero(np.all(self.lo <= b[3:] + 1e-9, axis=1) & np.all(self.hi >= b[:3] - 1e-9, axis=1))


def _raycast_down(mesh: trimesh.Trimesh, xy: np.ndarray):
    tris = mesh.triangles
    origins = np.column_stack([xy, np.full(len(xy), tris[:, :, 2].max() + 10.0)])
    dirs = np.tile([0.0, 0.0, -1.0], (len(xy), 1))
    idx_tri, idx_ray, loc = trimesh.ray.ray_triangle.ray_triangle_id(
        tris, origins, dirs, tree=_BruteTree(tris), multiple_hits=False)
    z = np.full(len(xy), np.nan)
    tri = np.full(len(xy), -1)
    z[idx_ray] = loc[:, 2]
    tri[idx_ray] = idx_tri
    return z, tri


# ----------------------------------------------------------------------------------------------------------
# GeoTIFF and TerrainModel
# ----------------------------------------------------------------------------------------------------------
def test_geotiff_round_trip(small, small_model):
    frame, terrain = small
    path, _ = small_model
    with rasterio.open(path) as ds:
        assert ds.crs.to_epsg() == 32618
        assert ds.transform.almost_equals(terrain.transform, precision=1e-9)
        assert ds.dtypes[0] == "float32" and ds.nodata is not None
        assert ds.profile.get("compress", "").lower() == "deflate"
        np.testing.assert_array_equal(ds.read(1), terrain.heights)
    assert not list(path.parent.glob(".*"))  # no temp file left behind


def test_height_at_agrees_with_mesh_raycast(small_model):
    _, model = small_model
    mesh = model.mesh()
    assert len(mesh.faces) == 2 * (model.shape[0] - 1) * (model.shape[1] - 1)
    rng = np.random.default_rng(1)
    b = model.bounds_enu
    xy = rng.uniform(b[0] + 2.0, b[1] - 2.0, size=(300, 2))
    z_ray, tri = _raycast_down(mesh, xy)
    z = model.height_at(xy)
    assert np.all(np.isfinite(z_ray)) and np.all(np.isfinite(z))
    assert np.max(np.abs(z - z_ray)) < 1e-3
    # Normals: unit, up-facing, the normal of the triangle the ray hit.
    n = model.normal_at(xy)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    assert np.all(n[:, 2] > 0)
    same = np.einsum("ij,ij->i", n, mesh.face_normals[tri]) > 1 - 1e-9
    assert same.mean() > 0.98


def test_height_at_grid_nodes_and_speed(small, small_model):
    frame, terrain = small
    _, model = small_model
    T = terrain.transform
    rows, cols = np.meshgrid(np.arange(0, 200, 7), np.arange(0, 200, 11), indexing="ij")
    E, N = T @ (cols.ravel() + 0.5, rows.ravel() + 0.5)
    enu = frame.enu_from_crs(np.column_stack([E, N, terrain.heights[rows.ravel(), cols.ravel()]]))
    np.testing.assert_allclose(model.height_at(enu[:, :2]), enu[:, 2], atol=1e-6)
    # Outside: NaN.
    assert np.isnan(model.height_at(np.array([[1000.0, 0.0], [0.0, -5000.0]]))).all()
    assert np.isnan(model.normal_at(np.array([[1000.0, 0.0]]))).all()
    # Speed: 100k queries well under a second.
    q = np.random.default_rng(2).uniform(-95, 95, size=(100_000, 2))
    model.height_at(q[:100])
    t0 = time.perf_counter()
    h = model.height_at(q)
    dt = time.perf_counter() - t0
    assert np.isfinite(h).all()
    assert dt < 0.5, f"100k height queries took {dt:.3f} s"


def test_mesh_texture_uvs_drape_track(full):
    """Track pixels of the texture fall on the track line when the mesh drapes it."""
    sc, frame, terrain, model, _ = full
    mesh = model.mesh(terrain.texture)
    uv = mesh.visual.uv
    tex = np.asarray(terrain.texture, dtype=float)
    h, w = tex.shape[:2]

    def colours(xy):
        face, bary = model._locate(xy)
        assert (face >= 0).all()
        fuv = np.einsum("nk,nkj->nj", bary, uv[mesh.faces[face]])
        col = np.clip((fuv[:, 0] * w).astype(int), 0, w - 1)
        row = np.clip(((1.0 - fuv[:, 1]) * h).astype(int), 0, h - 1)
        return tex[row, col]

    track = terrain.track_enu[::3]
    on = colours(track[:, :2])
    tangent = np.gradient(terrain.track_enu[:, :2], axis=0)[::3]
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    left = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    # The outer side of the bed (right of the train's track) is ground in both scenarios.
    beside = colours(track[:, :2] - left * (terrain.features["bed_half_width_m"] + 6.0))

    def greyish(c):
        return (np.ptp(c, axis=1) < 30) & (c.mean(axis=1) > 90)

    assert greyish(on).mean() > 0.95
    assert greyish(beside).mean() < 0.2
    # The rails (bright) sit at +-RAIL_HALF_GAUGE_M: brighter on average than the ballast between them.
    rails = np.vstack([colours(track[:, :2] + s * left * RAIL_HALF_GAUGE_M) for s in (-1, 1)])
    ballast = colours(track[:, :2] + left * 1.8)
    assert rails.mean() > ballast.mean() + 10


def test_no_crs_raises(tmp_path):
    path = _write_tif(tmp_path / "nocrs.tif", np.zeros((20, 20), np.float32), from_origin(0, 20, 1, 1), None)
    frame = scenario_frame("cutting_curve")
    with pytest.raises(InputError, match=r"nocrs\.tif.*has no CRS.*gdal_edit\.py -a_srs"):
        TerrainModel.from_geotiff(path, frame)
    real = SHARED_DEM / "whitebox_DEM_no_crs.tif"
    if real.exists():  # a LOCAL_CS ("unnamed", unknown units) counts as no CRS
        with pytest.raises(InputError, match=r"whitebox_DEM_no_crs\.tif.*has no CRS"):
            TerrainModel.from_geotiff(real, frame)


def test_dem_not_covering_origin_raises(tmp_path):
    frame = scenario_frame("cutting_curve")
    o = frame.origin_crs
    path = _write_tif(tmp_path / "far.tif", np.zeros((50, 50), np.float32),
                      from_origin(o[0] + 5000, o[1] + 25, 1, 1), "EPSG:32618")
    with pytest.raises(InputError, match=r"far\.tif does not cover the scene origin.*bounds are left="):
        TerrainModel.from_geotiff(path, frame)


def test_nodata_holes_filled(tmp_path):
    frame = scenario_frame("cutting_curve")
    o = frame.origin_crs
    n = 120
    rr, cc = np.mgrid[0:n, 0:n]
    z = (10.0 + 0.05 * cc - 0.02 * rr).astype(np.float32)  # a plane: harmonic inpainting reproduces it
    hole = ((rr - 60) ** 2 + (cc - 55) ** 2 < 15 ** 2) | ((rr > 90) & (rr < 110) & (cc > 10) & (cc < 20))
    zh = np.where(hole, -9999.0, z).astype(np.float32)
    path = _write_tif(tmp_path / "holes.tif", zh, from_origin(o[0] - 60, o[1] + 60, 1, 1), "EPSG:32618", -9999.0)
    with pytest.warns(DemHolesFilled, match=r"holes\.tif: filled \d+ nodata"):
        model = TerrainModel.from_geotiff(path, frame)
    assert model.info["filled_cells"] == int(hole.sum())
    np.testing.assert_allclose(model.heights, z, atol=1e-4)


def test_aoi_crop_and_decimation(small_model):
    path, full_model = small_model
    frame = full_model.frame
    m = TerrainModel.from_geotiff(path, frame, aoi_radius_m=50.0)
    b = m.bounds_enu
    assert np.all(b[0] <= -50.0) and np.all(b[1] >= 50.0)
    assert np.all(b[0] > -55.0) and np.all(b[1] < 55.0)
    q = np.random.default_rng(5).uniform(-50, 50, (500, 2))
    np.testing.assert_allclose(m.height_at(q), full_model.height_at(q), atol=1e-6)
    d = TerrainModel.from_geotiff(path, frame, max_cells=5000)
    assert d.heights.size <= 5000 and d.info["decimation"] >= 2
    # Block averages of a smooth-ish surface: close to the full model away from the embankment edges.
    assert np.nanmedian(np.abs(d.height_at(q) - full_model.height_at(q))) < 0.3


def test_dem_in_geographic_crs_is_reprojected(tmp_path):
    frame = scenario_frame("cutting_curve")
    # A smooth analytic surface in lon/lat over ~600 m around the origin.
    dlon, dlat = 0.00001, 0.00001  # ~0.85 m x 1.1 m cells
    n = 600
    lon0, lat0 = frame.lon_deg - n / 2 * dlon, frame.lat_deg + n / 2 * dlat
    rr, cc = np.mgrid[0:n, 0:n]
    lon = lon0 + (cc + 0.5) * dlon
    lat = lat0 - (rr + 0.5) * dlat

    def f(lo, la):
        return 20.0 + 3000.0 * (lo - frame.lon_deg) + 2.0 * np.sin((la - frame.lat_deg) * 2000.0)

    path = _write_tif(tmp_path / "geo.tif", f(lon, lat).astype(np.float32),
                      from_origin(lon0, lat0, dlon, dlat), "EPSG:4326")
    m = TerrainModel.from_geotiff(path, frame, aoi_radius_m=150.0)
    assert m.info["reprojected"]
    q = np.random.default_rng(3).uniform(-140, 140, (200, 2))
    z = m.height_at(q)
    geo = frame.wgs84_from_enu(np.column_stack([q, z]))
    truth = f(geo[:, 0], geo[:, 1])
    # The surface is ENU z at DEM height: compare in heights (datum) via the geodetic height of the point.
    assert np.max(np.abs(geo[:, 2] - truth)) < 0.05


@pytest.mark.skipif(not (SHARED_DEM / "srtm30_bigtujunga_utm11n.tif").exists(), reason="shared DEM missing")
def test_real_srtm_same_and_other_crs():
    path = SHARED_DEM / "srtm30_bigtujunga_utm11n.tif"
    with rasterio.open(path) as ds:
        cx, cy = (ds.bounds.left + ds.bounds.right) / 2, (ds.bounds.bottom + ds.bounds.top) / 2
    probe = SceneFrame("EPSG:32611", 34.0, -118.0)
    lon, lat, _ = probe.wgs84_from_crs(np.array([cx, cy, 0.0]))
    same = TerrainModel.from_geotiff(path, SceneFrame("EPSG:32611", lat, lon, 1000.0), aoi_radius_m=3000.0)
    other = TerrainModel.from_geotiff(path, SceneFrame("EPSG:3310", lat, lon, 1000.0), aoi_radius_m=3000.0)
    assert not same.info["reprojected"] and other.info["reprojected"]
    q = np.random.default_rng(4).uniform(-2500, 2500, (400, 2))
    a, b = same.height_at(q), other.height_at(q)
    assert np.isfinite(a).all() and np.isfinite(b).all()
    # Rugged 30 m terrain resampled bilinearly: the two agree to a few metres.
    assert np.median(np.abs(a - b)) < 3.0
    assert np.all(same.normal_at(q)[:, 2] > 0)


# ----------------------------------------------------------------------------------------------------------
# Synthetic scenarios
# ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sc", SCENARIOS)
def test_scenario_deterministic(sc):
    frame = scenario_frame(sc)
    kw = dict(size_m=160.0, resolution_m=2.0, texture_px_per_m=1.0)
    a = make_terrain(sc, frame, seed=7, **kw)
    b = make_terrain(sc, frame, seed=7, **kw)
    c = make_terrain(sc, frame, seed=8, **kw)
    np.testing.assert_array_equal(a.heights, b.heights)
    np.testing.assert_array_equal(a.track_enu, b.track_enu)
    assert a.texture.tobytes() == b.texture.tobytes()
    assert not np.array_equal(a.heights, c.heights)
    assert a.heights.dtype == np.float32 and a.heights.shape == (80, 80)
    assert a.texture.size[0] <= 4096


def test_track_bed_smooth_and_on_terrain(full):
    sc, frame, terrain, model, _ = full
    track = terrain.track_enu
    i0 = int(np.argmin(np.linalg.norm(track[:, :2], axis=1)))
    assert np.linalg.norm(track[i0, :2]) < 0.01  # passes through the origin ...
    assert abs(track[i0, 2]) < 0.01  # ... at top-of-rail height (scenario_frame's origin height)
    step = np.linalg.norm(np.diff(track[:, :2], axis=0), axis=1)
    np.testing.assert_allclose(step, 1.0, atol=0.05)
    # Top of rail sits TOP_OF_RAIL_ABOVE_BED_M above the mesh surface (exact design, cm tolerance).
    ground = model.height_at(track[:, :2])
    np.testing.assert_allclose(track[:, 2] - ground, TOP_OF_RAIL_ABOVE_BED_M, atol=0.01)
    # Smooth along: second differences of the bed at 1 m spacing are tiny.
    assert np.max(np.abs(np.diff(ground, 2))) < 0.005
    # Smooth and level across the bed: the whole bed width has the centreline's height.
    lay = terrain.layout
    f = terrain.features
    for off in np.linspace(f["bed_offset_m"] - f["bed_half_width_m"] + 1.5,
                           f["bed_offset_m"] + f["bed_half_width_m"] - 1.5, 7):  # 1.5: a cell diagonal
        off_xy, phi = lay.offset_along(track[:, 0], track[:, 1])
        pts = lay.point(phi, np.full(len(phi), off))
        np.testing.assert_allclose(model.height_at(pts), ground, atol=0.01)
    for t in terrain.tracks_enu:
        np.testing.assert_allclose(t[:, 2] - model.height_at(t[:, :2]), TOP_OF_RAIL_ABOVE_BED_M, atol=0.01)


def test_scenario_shapes(full):
    sc, frame, terrain, model, _ = full
    lay = terrain.layout
    track = terrain.track_enu
    mid = track[len(track) // 2 - 40: len(track) // 2 + 40]
    _, phi = lay.offset_along(mid[:, 0], mid[:, 1])
    bed = model.height_at(mid[:, :2])

    def at(off):
        return model.height_at(lay.point(phi, np.full(len(phi), off)))

    # Slopes are realistic everywhere (no cliffs): max gradient < 1:1 except nothing.
    gy, gx = np.gradient(terrain.heights.astype(float), 1.0)
    assert np.max(np.hypot(gx, gy)) < 0.75
    rough = model.height_at(np.random.default_rng(0).uniform(-150, 150, (2000, 2)))
    assert np.isfinite(rough).all()
    if sc == "embankment_river":
        # 2-3 m embankment, 8 m crest, 1:2 slopes, river on the outside (right), rising ground on the inside.
        assert np.all(np.abs(at(-2.5) - bed) < 0.01) and np.all(np.abs(at(2.5) - bed) < 0.01)
        np.testing.assert_allclose(bed - at(-6.0), 1.0, atol=0.05)  # 2 m down the 1:2 slope
        assert 2.0 <= np.median(bed - at(10.0)) <= 3.0
        assert terrain.water_polygon_enu is not None
        water = Polygon(terrain.water_polygon_enu)
        assert water.distance(Point(0, 0)) > 15.0
        wpts = np.array(water.representative_point().coords)
        toe = np.median(at(-10.0))
        assert 1.0 <= toe - model.height_at(wpts)[0] <= 2.0
        assert terrain.heights.max() - np.median(bed) > 20.0  # a hillside a camera can stand on
    else:
        assert len(terrain.tracks_enu) == 3
        assert 200.0 <= lay.radius <= 300.0
        assert np.all(at(-25.0) - bed > 1.5) and np.all(at(30.0) - bed > 0.5)  # in a shallow cutting


# ----------------------------------------------------------------------------------------------------------
# Buildings
# ----------------------------------------------------------------------------------------------------------
def test_buildings_clear_of_track_and_water(full):
    sc, frame, terrain, model, buildings = full
    assert 5 <= len(buildings) <= 15
    f = terrain.features
    bed = Polygon(terrain.track_bed_polygon_enu())
    water = Polygon(terrain.water_polygon_enu) if terrain.water_polygon_enu is not None else None
    ids = set()
    for b in buildings:
        ids.add(b["id"])
        enu = frame.enu_from_crs(np.column_stack([b["footprint_crs"], np.full(len(b["footprint_crs"]), b["base_m"])]))
        poly = Polygon(enu[:, :2])
        assert poly.is_valid and poly.area > 40
        assert not poly.intersects(bed) and poly.distance(bed) > 3.0
        if water is not None:
            assert not poly.intersects(water)
        r = np.linalg.norm(enu[:, :2], axis=1)
        assert poly.distance(Point(0, 0)) >= 40.0 and r.max() <= 180.0
        assert b["height_m"] > 0
        ground = model.height_at(enu[:, :2])
        assert np.all(enu[:, 2] <= ground + 0.05)  # base = lowest ground under the footprint
    assert len(ids) == len(buildings)
    assert f["bed_half_width_m"] > 0


def test_buildings_geojson_round_trip_and_validation(full, tmp_path):
    sc, frame, terrain, model, buildings = full
    path = write_buildings_geojson(tmp_path / "b.geojson", buildings, terrain.crs)
    doc = json.loads(path.read_text())
    assert doc["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::32618"
    back = read_buildings_geojson(path, expect_crs="EPSG:32618")
    assert [b["id"] for b in back] == [b["id"] for b in buildings]
    for a, b in zip(buildings, back):
        np.testing.assert_allclose(b["footprint_crs"], a["footprint_crs"], atol=1e-3)
        assert b["height_m"] == pytest.approx(a["height_m"]) and b["base_m"] == pytest.approx(a["base_m"])
        assert b["kind"] == a["kind"]
    with pytest.raises(InputError, match="project CRS is EPSG:32611"):
        read_buildings_geojson(path, expect_crs="EPSG:32611")
    bad = json.loads(path.read_text())
    bad["features"][1]["properties"]["height_m"] = 0
    (tmp_path / "bad.geojson").write_text(json.dumps(bad))
    with pytest.raises(InputError, match=rf"bad\.geojson: feature {buildings[1]['id']} has height_m=0"):
        read_buildings_geojson(tmp_path / "bad.geojson")
    bad = json.loads(path.read_text())
    bad["features"][0]["geometry"] = None
    (tmp_path / "nogeom.geojson").write_text(json.dumps(bad))
    with pytest.raises(InputError, match=rf"nogeom\.geojson: feature {buildings[0]['id']} has no polygon"):
        read_buildings_geojson(tmp_path / "nogeom.geojson")


def test_building_meshes(full):
    sc, frame, terrain, model, buildings = full
    meshes = building_meshes(buildings, model, frame)
    assert len(meshes) == len(buildings)
    for b, m in zip(buildings, meshes):
        enu = frame.enu_from_crs(np.column_stack([b["footprint_crs"], np.full(len(b["footprint_crs"]),
                                                                               b["base_m"] + b["height_m"])]))
        assert m.bounds[1, 2] == pytest.approx(enu[:, 2].max(), abs=0.01)  # roof at base + height
        ground = model.height_at(enu[:, :2])
        assert m.bounds[0, 2] <= np.nanmin(ground)  # walls reach the lowest ground under the footprint
        colours = m.visual.vertex_colors[:, :3]
        assert len(np.unique(colours, axis=0)) >= 3  # facade, glass, roof
        # Walls face outwards: face normals of wall faces point away from the footprint centroid.
        walls = np.abs(m.face_normals[:, 2]) < 1e-6
        centres = m.triangles_center[walls][:, :2] - enu[:, :2].mean(axis=0)
        assert np.mean(np.einsum("ij,ij->i", centres, m.face_normals[walls][:, :2]) > 0) > 0.99
        assert np.all(m.face_normals[~walls][:, 2] > 0.99)  # the roof faces up


def test_look(full):
    """Save a hillshade + texture + footprints view of each scenario (inspected by eye)."""
    sc, frame, terrain, model, buildings = full
    z = terrain.heights.astype(float)
    gy, gx = np.gradient(z, abs(terrain.transform.a))
    slope = np.arctan(np.hypot(gx, gy))
    aspect = np.arctan2(-gx, gy)
    az, alt = np.radians(315.0), np.radians(45.0)
    hs = np.clip(np.sin(alt) * np.cos(slope) + np.cos(alt) * np.sin(slope) * np.cos(az - aspect), 0, 1)
    zn = (z - z.min()) / max(np.ptp(z), 1e-6)
    rgb = np.stack([0.35 + 0.65 * zn, 0.55 + 0.3 * zn, 0.95 - 0.6 * zn], -1) * (0.3 + 0.7 * hs[..., None])
    size = 800
    left = Image.fromarray((np.clip(rgb, 0, 1) * 255).astype(np.uint8)).resize((size, size), Image.BILINEAR)
    right = terrain.texture.resize((size, size), Image.LANCZOS)
    from PIL import ImageDraw

    lb, bb, rb, tb = terrain.bounds_crs
    for img in (left, right):
        d = ImageDraw.Draw(img)
        for b in buildings:
            pts = [((x - lb) / (rb - lb) * size, (tb - y) / (tb - bb) * size) for x, y in b["footprint_crs"]]
            d.polygon(pts, outline=(255, 40, 40))
        tr = frame.crs_from_enu(terrain.track_enu)
        d.line([((x - lb) / (rb - lb) * size, (tb - y) / (tb - bb) * size) for x, y, _ in tr[::10]],
               fill=(255, 255, 0), width=1)
    out = Image.new("RGB", (2 * size, size))
    out.paste(left, (0, 0))
    out.paste(right, (size, 0))
    out.save(f"/tmp/terrain_look_{sc}.png")
    assert Path(f"/tmp/terrain_look_{sc}.png").stat().st_size > 10_000
