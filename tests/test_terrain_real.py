"""Real DEMs (../shared/data/dem): urban 1 m DSM (EPSG:25832), SRTM 30 m (EPSG:32611), EPSG:4326 tiles that must
mosaic, a DEM with no CRS; plus the terrain stage, simplification, vertical units and bad input."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from workbench.core.frames import SceneFrame
from workbench.errors import InputError
from workbench.project import Project
from workbench.files.dem import DemVerticalUnits, TerrainModel, resolve_dem_sources, simplify_terrain_mesh
from workbench.pipeline import stage
from workbench.terrain.stage import run_terrain

STAGE = stage("terrain")

DEM = Path(__file__).resolve().parents[2] / "shared" / "data" / "dem"
NRW = DEM / "nrw_dom1_32_356_5699_1_nw_2020.tif"
SRTM = DEM / "srtm30_bigtujunga_utm11n.tif"
SF = [DEM / "osmnx_sf_elevation1_epsg4326.tif", DEM / "osmnx_sf_elevation2_epsg4326.tif"]
NO_CRS = DEM / "whitebox_DEM_no_crs.tif"


def _need(*paths: Path):
    return pytest.mark.skipif(not all(p.exists() for p in paths), reason="shared DEM data missing")


def _frame_at(path: Path, crs: str, fx: float = 0.5, fy: float = 0.5, height_m: float = 0.0) -> SceneFrame:
    """A scene frame whose origin is at fraction (fx, fy) of the DEM's extent (from the west / south)."""
    with rasterio.open(path) as ds:
        b = ds.bounds
        x, y = b.left + fx * (b.right - b.left), b.bottom + fy * (b.top - b.bottom)
        src_crs = ds.crs.to_string()
    from pyproj import Transformer

    lon, lat = Transformer.from_crs(src_crs, "EPSG:4326", always_xy=True).transform(x, y)
    return SceneFrame(crs, lat, lon, height_m)


def _write(path: Path, z: np.ndarray, transform, crs, nodata=None, units: str | None = None) -> Path:
    with rasterio.open(path, "w", driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype=z.dtype,
                       crs=crs, transform=transform, nodata=nodata) as dst:
        dst.write(z, 1)
        if units:
            dst.units = (units,)
    return path


# ----------------------------------------------------------------------------------------------------------
# Urban 1 m surface model, EPSG:25832 (same CRS as the project: no resampling)
# ----------------------------------------------------------------------------------------------------------
@_need(NRW)
def test_urban_dsm_crop_nodes_and_simplification():
    frame = _frame_at(NRW, "EPSG:25832", height_m=140.0)
    tm = TerrainModel.from_sources([NRW], frame, aoi_radius_m=60.0)
    assert not tm.info["reprojected"] and tm.info["decimation"] == 1
    R, C = tm.shape
    assert 120 <= R <= 126 and 120 <= C <= 126  # 2 x 60 m at 1 m, plus grid convergence and one node of margin
    # every node carries the DEM value at that cell centre (read independently with rasterio)
    with rasterio.open(NRW) as ds:
        ij = [(5, 7), (R // 2, C // 2), (R - 3, C - 9)]
        xy = [tm.node_crs[i, j] for i, j in ij]
        vals = np.array([v[0] for v in ds.sample(xy)])
    assert np.allclose([tm.heights[i, j] for i, j in ij], vals, atol=1e-4)
    # height queries reproduce the nodes (ENU up = DEM height - origin height, less < 2 mm of curvature)
    nodes = np.array([tm.grid_enu[i, j] for i, j in ij])
    assert np.allclose(tm.height_at(nodes[:, :2]), nodes[:, 2], atol=1e-9)
    assert np.all(np.abs(nodes[:, 2] - (vals - 140.0)) < 0.003)
    # a surface model of roofs and trees is rough: simplification keeps the error bound, removes fewer nodes
    mesh, info = simplify_terrain_mesh(tm, 0.25)
    assert 0.2 < info["max_error_m"] <= 0.25
    assert 0.1 * R * C < info["n_vertices"] < 0.95 * R * C
    # the outline is kept node for node: both meshes cover the same ground area, without holes or overlaps
    def plan_area(m):
        t = m.triangles[:, :, :2]
        return 0.5 * np.abs(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])).sum()

    assert abs(plan_area(mesh) / plan_area(tm.mesh()) - 1.0) < 1e-5  # the ENU border bows by millimetres


# ----------------------------------------------------------------------------------------------------------
# SRTM 30 m, EPSG:32611: simplification error checked against the full-resolution surface
# ----------------------------------------------------------------------------------------------------------
@_need(SRTM)
def test_srtm_simplification_error_bound():
    frame = _frame_at(SRTM, "EPSG:32611", height_m=1000.0)
    tm = TerrainModel.from_sources(SRTM, frame, aoi_radius_m=1500.0)
    mesh, info = simplify_terrain_mesh(tm, 2.0)
    assert 1.0 < info["max_error_m"] <= 2.0
    assert info["n_vertices"] < 0.8 * info["n_vertices_full"]
    # at every DEM node, the simplified surface is within the bound (vertical ray casts into the simplified mesh)
    import trimesh

    pts = tm.grid_enu.reshape(-1, 3)[::7]
    ray = trimesh.ray.ray_triangle.RayMeshIntersector(mesh)
    origins = np.column_stack([pts[:, :2], np.full(len(pts), pts[:, 2].max() + 100.0)])
    loc, idx, _ = ray.intersects_location(origins, np.tile([0.0, 0.0, -1.0], (len(pts), 1)), multiple_hits=False)
    dz = np.abs(loc[:, 2] - pts[idx, 2])
    assert len(idx) > 0.95 * len(pts)
    assert 0.5 < dz.max() <= 2.0 + 1e-6


# ----------------------------------------------------------------------------------------------------------
# EPSG:4326 tiles: a mosaic, reprojected into UTM
# ----------------------------------------------------------------------------------------------------------
@_need(*SF)
def test_geographic_tiles_mosaic(tmp_path):
    with rasterio.open(SF[0]) as a:
        seam_lon = a.bounds.right
        lat = (a.bounds.bottom + a.bounds.top) / 2
    frame = SceneFrame("EPSG:32610", lat, seam_lon - 0.0003, 20.0)  # ~25 m west of tile 1's east edge
    with pytest.raises(InputError, match="does not cover"):  # tile 2 alone misses the origin
        TerrainModel.from_sources([SF[1]], frame, aoi_radius_m=200.0)
    one = TerrainModel.from_sources([SF[0]], frame, aoi_radius_m=200.0)
    both = TerrainModel.from_sources(resolve_dem_sources(str(DEM / "osmnx_sf_elevation*_epsg4326.tif"), tmp_path),
                                     frame, aoi_radius_m=200.0)
    assert both.info["reprojected"] and len(both.info["tiles"]) == 2
    q = np.random.default_rng(0).uniform(-190, 190, (300, 2))
    inside_one = one.contains(q)
    assert 0.2 < inside_one.mean() < 0.8  # tile 1 alone covers only the western part of the area
    assert both.contains(q).all()  # the mosaic covers all of it
    a, b = one.height_at(q[inside_one]), both.height_at(q[inside_one])
    # away from the seam both are bilinear resamplings of the same cells (on grids centred differently)
    far = q[inside_one][:, 0] < -60
    assert np.median(np.abs(a - b)[far]) < 3.0  # 25 m cells on hills, sampled on two different grids
    # a folder works too, and tiles in different CRSs are refused
    d = tmp_path / "tiles"
    d.mkdir()
    for p in SF:
        shutil.copy(p, d / p.name)
    assert resolve_dem_sources("tiles", tmp_path) == sorted(d.glob("*.tif"))
    with rasterio.open(SF[1]) as src:
        z = src.read(1)
        T = src.transform
    from rasterio.crs import CRS

    _write(d / "z_other.tif", z, T, CRS.from_epsg(4269), nodata=-32768)  # NAD83 lon/lat: another CRS
    with pytest.raises(InputError, match="different CRSs.*gdalwarp"):
        TerrainModel.from_sources(resolve_dem_sources(str(d), tmp_path), frame, aoi_radius_m=200.0)


@_need(NO_CRS)
def test_dem_without_crs_is_refused():
    frame = SceneFrame("EPSG:32618", 40.878, -73.9215)
    with pytest.raises(InputError, match=r"whitebox_DEM_no_crs.tif has no CRS; assign one with gdal_edit.py"):
        TerrainModel.from_sources([NO_CRS], frame, aoi_radius_m=100.0)


def test_resolve_dem_sources_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        resolve_dem_sources("missing.tif", tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="matches no GeoTIFF"):
        resolve_dem_sources("empty", tmp_path)
    with pytest.raises(InputError, match="matches no GeoTIFF"):
        resolve_dem_sources("tiles/*.tif", tmp_path)


# ----------------------------------------------------------------------------------------------------------
# Vertical units
# ----------------------------------------------------------------------------------------------------------
def _slope(frame: SceneFrame, scale: float = 1.0) -> tuple[np.ndarray, object]:
    o = frame.origin_crs
    x = np.arange(120)
    z = (30.0 + 0.05 * x[None, :] + 0.02 * x[:, None]).astype(np.float32) * scale
    return z, from_origin(o[0] - 60, o[1] + 60, 1.0, 1.0)


def test_dem_in_feet_is_converted_with_a_warning(tmp_path):
    frame = SceneFrame("EPSG:32618", 40.878, -73.9215, 0.0)
    z, T = _slope(frame)
    m = TerrainModel.from_geotiff(_write(tmp_path / "m.tif", z, T, "EPSG:32618"), frame)
    with pytest.warns(DemVerticalUnits, match=r"ft\.tif: heights are in 'ft'"):
        f = TerrainModel.from_geotiff(_write(tmp_path / "ft.tif", z / 0.3048, T, "EPSG:32618", units="ft"), frame)
    assert np.allclose(f.heights, m.heights, atol=1e-4)
    with pytest.raises(InputError, match="furlong"):
        TerrainModel.from_geotiff(_write(tmp_path / "fl.tif", z, T, "EPSG:32618", units="furlong"), frame)


def test_dem_implausible_heights_are_refused(tmp_path):
    frame = SceneFrame("EPSG:32618", 40.878, -73.9215, 0.0)
    z, T = _slope(frame, scale=1000.0)  # 30 km high: millimetres, not metres
    with pytest.raises(InputError, match=r"mm\.tif: heights from .* not plausible metres.*-units"):
        TerrainModel.from_geotiff(_write(tmp_path / "mm.tif", z, T, "EPSG:32618"), frame)


# ----------------------------------------------------------------------------------------------------------
# The terrain stage
# ----------------------------------------------------------------------------------------------------------
def _project(tmp_path: Path, dem: str, height_m: float, buildings: str | None = None) -> Project:
    toml = f"""
[incident]
name = "terrain test"
date = 2024-01-01

[location]
lat = 40.878
lon = -73.9215
height_m = {height_m}
crs = "EPSG:32618"

[terrain]
dem = "{dem}"
aoi_radius_m = 50.0
{f'buildings = "{buildings}"' if buildings else ''}

[[consist]]
number = "1"
type = "shoreliner"
"""
    (tmp_path / "project.toml").write_text(toml)
    return Project(tmp_path)


def test_stage_writes_meshes_and_stats(tmp_path):
    frame = SceneFrame("EPSG:32618", 40.878, -73.9215, 0.0)
    z, T = _slope(frame)
    _write(tmp_path / "dem.tif", z, T, "EPSG:32618")
    project = _project(tmp_path, "dem.tif", 30.0 + 0.05 * 60 + 0.02 * 60)
    res = run_terrain(project, lambda f, m="": None)
    s = res.stats
    assert res.outputs["terrain_mesh"].is_file()
    # a plane needs only its outline: the simplified mesh keeps the border nodes and almost nothing else
    assert s["simplification"]["max_error_m"] < 1e-3 and s["n_vertices"] < 0.1 * s["simplification"]["n_vertices_full"]
    assert abs(s["dem_height_at_origin_m"] - s["location_height_m"]) < 0.6
    assert s["coverage_short_m"] == {} and s["warnings"] == []
    # a larger area of interest than the DEM: a warning that says by how much, on which sides
    (tmp_path / "project.toml").write_text((tmp_path / "project.toml").read_text().replace("aoi_radius_m = 50.0",
                                                                                          "aoi_radius_m = 80.0"))
    s = run_terrain(Project(tmp_path), lambda f, m="": None).stats
    assert set(s["coverage_short_m"]) == {"west", "south", "east", "north"}
    assert all(18.0 < v < 22.0 for v in s["coverage_short_m"].values())
    assert any("covers only part of the area of interest" in w for w in s["warnings"])
    assert STAGE.name == "terrain" and STAGE.settings_sections == ("location", "terrain")


def test_stage_detects_centimetres_by_the_reference_height(tmp_path):
    frame = SceneFrame("EPSG:32618", 40.878, -73.9215, 0.0)
    z, T = _slope(frame)
    _write(tmp_path / "dem_cm.tif", (z * 100).astype(np.float32), T, "EPSG:32618")  # 3000-4000 "m": plausible
    project = _project(tmp_path, "dem_cm.tif", 34.2)
    with pytest.raises(InputError, match=r"dem_cm.tif.*looks like it is in centimetres"):
        run_terrain(project, lambda f, m="": None)


def test_stage_dem_not_covering_the_incident(tmp_path):
    frame = SceneFrame("EPSG:32618", 40.878, -73.9215, 0.0)
    z, T = _slope(frame)
    o = frame.origin_crs
    _write(tmp_path / "far.tif", z, from_origin(o[0] + 5000, o[1], 1.0, 1.0), "EPSG:32618")
    project = _project(tmp_path, "far.tif", 30.0)
    with pytest.raises(InputError, match=r"far.tif does not cover the scene origin.*use a DEM that covers"):
        run_terrain(project, lambda f, m="": None)
