"""Buildings to meshes in the scene frame: CityJSON as cities publish it (Delft LoD1, Zurich LoD2, in
../shared/data/buildings), GeoJSON footprints, and bad input."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from pyproj import Transformer
from rasterio.transform import from_origin

from workbench.core.frames import SceneFrame
from workbench.errors import InputError
from workbench.terrain.buildings import BuildingsDatumMismatch, cityjson_meshes, read_buildings
from workbench.files.dem import TerrainModel

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "buildings"
DELFT = DATA / "delft_3dfier" / "delft_lod1.city.json"
ZURICH = DATA / "zurich_lod2" / "zurich_subset_lod2.city.json"


def _need(p: Path):
    return pytest.mark.skipif(not p.exists(), reason="shared buildings data missing")


def _doc(p: Path) -> dict:
    return json.loads(p.read_text(encoding="utf-8"))


def _centre_frame(doc: dict, layer_crs: str, project_crs: str, height_m: float = 0.0) -> SceneFrame:
    V = np.asarray(doc["vertices"], float) * doc["transform"]["scale"] + doc["transform"]["translate"]
    lon, lat = Transformer.from_crs(layer_crs, "EPSG:4326", always_xy=True).transform(np.median(V[:, 0]),
                                                                                     np.median(V[:, 1]))
    return SceneFrame(project_crs, lat, lon, height_m)


def _flat_terrain(frame: SceneFrame, z: float, half: float = 600.0, cell: float = 5.0) -> TerrainModel:
    o = frame.origin_crs
    n = int(2 * half / cell)
    return TerrainModel.from_array(np.full((n, n), z), from_origin(o[0] - half, o[1] + half, cell, cell),
                                   frame.crs.to_string(), frame)


@_need(DELFT)
def test_delft_lod1_heights_match_measured_height():
    doc = _doc(DELFT)
    frame = _centre_frame(doc, "EPSG:28992", "EPSG:28992")
    res = read_buildings(DELFT, frame)  # no terrain: heights as in the file (NAP), ENU up = NAP - 0
    assert res.info["crs"] == "EPSG:7415" and res.info["lods"] == ["1"]
    assert res.info["n_buildings"] == sum(o["type"] == "Building" for o in doc["CityObjects"].values()) == 160
    top, bottom = [], []
    for m in res.meshes:
        a = doc["CityObjects"][m.metadata["name"]]["attributes"]
        top.append(m.vertices[:, 2].max() - a["measuredHeight"])
        bottom.append(m.vertices[:, 2].min() - a["min-height-surface"])
    # exact to the file's millimetre scale, less the Earth's curvature over ~150 m (< 2 mm)
    assert np.all(np.abs(top) < 0.003) and np.all(np.abs(bottom) < 0.003)
    assert np.ptp(top) > 1e-4  # curvature shows: the values really went through ECEF -> ENU


@_need(DELFT)
def test_delft_stands_on_terrain_and_any_project_crs():
    doc = _doc(DELFT)
    rd = _centre_frame(doc, "EPSG:28992", "EPSG:28992")
    utm = SceneFrame("EPSG:32631", rd.lat_deg, rd.lon_deg, 0.0)  # same origin, another project CRS
    with warnings.catch_warnings():
        warnings.simplefilter("error", BuildingsDatumMismatch)  # 0.4-1.3 m shifts: no datum warning
        tm = _flat_terrain(rd, 1.0)
        a = read_buildings(DELFT, rd, tm)
    b = read_buildings(DELFT, utm, _flat_terrain(utm, 1.0))
    va = np.vstack([m.vertices for m in a.meshes])
    vb = np.vstack([m.vertices for m in b.meshes])
    assert va.shape == vb.shape and np.abs(va - vb).max() < 0.01  # the scene frame does not depend on the CRS
    for m in a.meshes[:40]:
        ground = tm.height_at(m.vertices[:, :2])
        assert abs(m.vertices[:, 2].min() - np.nanmin(ground)) < 1e-9
    sh = a.info["vertical_shift_m"]
    assert 0.3 < sh["min"] <= sh["median"] <= sh["max"] < 1.5  # the file's ground is 0-0.6 m NAP; the terrain 1 m


@_need(ZURICH)
def test_zurich_lod2_roofs_and_surface_areas():
    doc = _doc(ZURICH)
    frame = _centre_frame(doc, "EPSG:2056", "EPSG:2056", height_m=400.0)
    res = cityjson_meshes(ZURICH, frame)
    assert res.info["lods"] == ["2"] and res.info["n_buildings"] == 161  # BuildingParts carry the geometry
    merged = res.merged()
    n = merged.face_normals
    sloped = (np.abs(n[:, 2]) > 0.2) & (np.abs(n[:, 2]) < 0.98)
    assert 0.05 < sloped.mean() < 0.9  # real roof shapes
    # heights 396-621 m absolute, here relative to 400 m (curvature within ~3 km: < 1 m)
    z = merged.vertices[:, 2] + 400.0
    assert 390.0 < z.min() < 405.0 and 600.0 < z.max() < 625.0
    # triangulation preserves every surface's area (holes included): Newell areas in LV95 vs mesh area
    V = np.asarray(doc["vertices"], float) * doc["transform"]["scale"]
    total = 0.0
    for o in doc["CityObjects"].values():
        for g in o.get("geometry", []):
            for surf in g["boundaries"]:
                for k, ring in enumerate(surf):
                    P = V[ring]
                    nrm = 0.5 * np.sum(np.cross(P, np.roll(P, -1, axis=0)), axis=0)
                    total += np.linalg.norm(nrm) * (1 if k == 0 else -1)
    assert abs(merged.area / total - 1.0) < 2e-3  # LV95 scale factor and rounding


def _write(p: Path, doc: dict) -> Path:
    p.write_text(json.dumps(doc))
    return p


def _tiny_cityjson(frame: SceneFrame, **extra) -> dict:
    o = frame.origin_crs
    ring = [[0, 1, 2, 3]]
    doc = {"type": "CityJSON", "version": "2.0",
           "transform": {"scale": [0.01, 0.01, 0.01], "translate": [o[0], o[1], 0]},
           "metadata": {"referenceSystem": f"https://www.opengis.net/def/crs/EPSG/0/{frame.crs.to_epsg()}"},
           "vertices": [[0, 0, 0], [1000, 0, 0], [1000, 1000, 0], [0, 1000, 0]],
           "CityObjects": {"b1": {"type": "Building", "attributes": {},
                                  "geometry": [{"type": "MultiSurface", "lod": "0", "boundaries": [ring]}]}}}
    doc.update(extra)
    return doc


def test_cityjson_lod0_extruded_by_measured_height(tmp_path):
    frame = SceneFrame("EPSG:32618", 40.878, -73.9215, 0.0)
    doc = _tiny_cityjson(frame)
    doc["CityObjects"]["b1"]["attributes"]["measuredHeight"] = 7.5
    res = read_buildings(_write(tmp_path / "b.city.json", doc), frame, _flat_terrain(frame, 2.0, half=50.0))
    m = res.meshes[0]
    assert abs(np.ptp(m.vertices[:, 2]) - 7.5) < 1e-4 and abs(m.vertices[:, 2].min() - 2.0) < 0.01
    assert abs(m.area - (2 * 100 + 4 * 10 * 7.5)) < 0.5  # a 10 x 10 x 7.5 m box


def test_cityjson_bad_input(tmp_path):
    frame = SceneFrame("EPSG:32618", 40.878, -73.9215, 0.0)
    with pytest.raises(InputError, match=r"1 building\(s\) have no height.*measuredHeight"):
        read_buildings(_write(tmp_path / "a.city.json", _tiny_cityjson(frame)), frame)
    doc = _tiny_cityjson(frame)
    doc["metadata"] = {}
    with pytest.raises(InputError, match="no metadata.referenceSystem"):
        read_buildings(_write(tmp_path / "b.city.json", doc), frame)
    doc = _tiny_cityjson(frame)
    doc["metadata"]["referenceSystem"] = "https://www.opengis.net/def/crs/EPSG/0/2056"  # wrong CRS: Switzerland
    doc["CityObjects"]["b1"]["attributes"]["measuredHeight"] = 5.0
    with pytest.raises(InputError, match=r"km from the incident.*referenceSystem is wrong"):
        read_buildings(_write(tmp_path / "c.city.json", doc), frame)


def test_geojson_footprints(tmp_path):
    from workbench.files.buildings import write_buildings_geojson

    frame = SceneFrame("EPSG:32618", 40.878, -73.9215, 0.0)
    o = frame.origin_crs
    ring = np.array([[o[0] + 10, o[1] + 10], [o[0] + 30, o[1] + 10], [o[0] + 30, o[1] + 25], [o[0] + 10, o[1] + 25]])
    blds = [{"id": "h1", "footprint_crs": ring, "height_m": 9.0, "base_m": None, "kind": "house"}]
    path = write_buildings_geojson(tmp_path / "b.geojson", blds, "EPSG:32618")
    tm = _flat_terrain(frame, 3.0, half=100.0)
    res = read_buildings(path, frame, tm)
    m = res.meshes[0]
    assert res.info["format"] == "geojson"
    assert abs(m.vertices[:, 2].max() - (tm.height_at(np.array([[20.0, 17.0]]))[0] + 9.0)) < 0.01
    # no height: a clear message with what to do
    doc = json.loads(path.read_text())
    del doc["features"][0]["properties"]["height_m"]
    with pytest.raises(InputError, match=r"feature h1 has no height_m; give every building its height"):
        read_buildings(_write(tmp_path / "nh.geojson", doc), frame, tm)
    # another CRS than the project's
    doc = json.loads(path.read_text())
    doc["crs"]["properties"]["name"] = "urn:ogc:def:crs:EPSG::32617"
    with pytest.raises(InputError, match=r"reproject it \(e.g. ogr2ogr -t_srs EPSG:32618\)"):
        read_buildings(_write(tmp_path / "crs.geojson", doc), frame, tm)
