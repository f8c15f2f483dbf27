"""Tests of the georeferenced exports (workbench.export): round trips against the synthetic ground truth and
real clients (Khronos glTF validator, GDAL's ogrinfo, Blender), each skipped with the reason when absent.

One small synthetic incident (3 cars, 2 photos of 320x240, 200 m of terrain) is generated once; the real
pipeline (known cameras + true marked points with 1 px noise -> solve -> export) runs on it, then the export
runs again on a solution made from the truth (with the terrain simplified, to test that path too).
"""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import time
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

import numpy as np
import pygltflib
import pytest
from pyproj import Transformer
from scipy.spatial.transform import Rotation

from workbench.core.frames import SceneFrame, rot_z
from workbench.core.io import atomic_write_json
from workbench.errors import SettingsError
from workbench.export import GLTF_FROM_ENU, ExportOptions
from workbench.export.stage import export_scene
from workbench.pipeline import stage
from workbench.project import Project
from workbench.rolling_stock import get_type

EXPORT_STAGE = stage("export")

G = GLTF_FROM_ENU
KML = "{http://www.opengis.net/kml/2.2}"


# ---------------------------------------------------------------------------------------------------------
# An independent ENU -> WGS84 (ECEF formula written here, pyproj only for ECEF -> geodetic), so a frame or axis
# mistake in the workbench's own conversions cannot cancel out in the round trip.
# ---------------------------------------------------------------------------------------------------------
def _enu_to_wgs84(enu: np.ndarray, lon0: float, lat0: float, h0: float) -> np.ndarray:
    to_ecef = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    x0, y0, z0 = to_ecef.transform(lon0, lat0, h0)
    lo, la = np.deg2rad(lon0), np.deg2rad(lat0)
    east = np.array([-np.sin(lo), np.cos(lo), 0.0])
    north = np.array([-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)])
    up = np.array([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])
    e = np.atleast_2d(enu)
    ecef = np.array([x0, y0, z0]) + e[:, :1] * east + e[:, 1:2] * north + e[:, 2:3] * up
    lon, lat, h = to_ecef.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2], direction="INVERSE")
    return np.column_stack([lon, lat, h])


def _metres(a_lonlath: np.ndarray, b_lonlath: np.ndarray, frame: SceneFrame) -> np.ndarray:
    """Distances (n,) in metres between two sets of WGS84 points (through the scene frame)."""
    return np.linalg.norm(frame.enu_from_wgs84(np.atleast_2d(a_lonlath)) - frame.enu_from_wgs84(
        np.atleast_2d(b_lonlath)), axis=1)


def _truth_solution(truth: dict, frame: SceneFrame) -> dict:
    cars = []
    for c in truth["carriages"]:
        centre = np.asarray(c["body_centre_enu"])
        cars.append({"index": c["index"], "number": c["number"], "type": c["type"], "status": "solved",
                     "world_from_carriage": c["world_from_carriage"], "body_centre_enu": centre.tolist(),
                     "body_centre_crs": frame.crs_from_enu(centre[None])[0].tolist(),
                     "body_centre_wgs84": frame.wgs84_from_enu(centre[None])[0].tolist(),
                     "heading_deg": c["heading_deg"], "pitch_deg": c["pitch_deg"], "roll_deg": c["roll_deg"],
                     "ci95_body_centre_m": [0.01, 0.01, 0.01], "ci95_hpr_deg": [0.01, 0.01, 0.01]})
    return {"status": "converged", "message": "ground truth", "frame": truth["frame"], "carriages": cars,
            "links": [], "steps": [], "warnings": []}


@pytest.fixture(scope="module")
def incident(tmp_path_factory):
    from workbench.pipeline import STAGES
    from workbench.runner import Runner
    from workbench.synth.generate import SynthOptions, generate_incident
    from workbench.synth.handpicks import write_known_cameras, write_true_correspondences

    root = tmp_path_factory.mktemp("export") / "inc"
    t0 = time.perf_counter()
    # = `workbench synth ROOT --cars 3 --width 320 --height 240 --panorama 2 --multiview 0` on 200 m of terrain
    generate_incident(root, SynthOptions(n_cars=3, photo_width=320, photo_height=240, n_panorama=2, n_multiview=0,
                                         terrain_size_m=200.0))
    t_synth = time.perf_counter() - t0
    write_known_cameras(root, "panorama")
    write_true_correspondences(root, "panorama", sigma_px=1.0, seed=0)
    # the hand picks only: every car has them (the automatic finder placed no point here: the same
    # correspondences.json with it, which took most of the stages' time; docs/performance.md, the thirteenth pass)
    (root / "project.toml").write_text((root / "project.toml").read_text() + '\n[correspond]\nfinder = "off"\n')
    project = Project(root)
    Runner(project, list(STAGES)).run(until="export")  # not the render and report stages: no test here reads them
    out = project.stage_dir("export")
    solved = {
        "solution": json.loads((project.stage_dir("solve") / "solution.json").read_text()),
        "geojson": json.loads((out / "carriages.geojson").read_text()),
        "stats": json.loads((out / "stats.json").read_text()),
        "glb": (out / "scene.glb").read_bytes(),
    }
    truth = json.loads((root / "truth" / "ground_truth.json").read_text())
    # the same export from the true poses, terrain simplified (the full-resolution band kept under the cars)
    atomic_write_json(project.stage_dir("solve") / "solution.json", _truth_solution(truth, project.frame))
    paths, stats = export_scene(project, ExportOptions(terrain_max_faces=20_000, full_resolution_margin_m=10.0))
    return {"root": root, "project": project, "truth": truth, "paths": paths, "stats": stats, "solved": solved,
            "t_synth": t_synth}


def _truth_cars(incident) -> dict:
    return {c["number"]: c for c in incident["truth"]["carriages"]}


def _terrain_tolerance(incident) -> float:
    """The terrain stage's stated vertical simplification error (0 when it keeps every DEM triangle), metres."""
    tstats = json.loads((incident["root"] / "out" / "terrain" / "stats.json").read_text())
    simp = tstats.get("simplification") or {}
    return float(simp.get("max_error_m", 0.0)) if isinstance(simp, dict) else 0.0


# ---------------------------------------------------------------------------------------------------------
def test_options_reject_bad_values():
    with pytest.raises(SettingsError, match="terrain_max_faces"):
        ExportOptions(terrain_max_faces=10)
    with pytest.raises(SettingsError, match="texture_max_px"):
        ExportOptions(texture_max_px=10)
    with pytest.raises(TypeError):
        ExportOptions(unknown_key=1)  # keyword-only dataclass: unknown options are an error


def test_real_pipeline_centres_agree_with_truth_to_the_solve_accuracy(incident):
    """Exported centres (GeoJSON, WGS84) of the real solve: at the solution's centres to < 1 mm, and at the
    truth within the solve's 95% half widths (plus 5 cm), but not at the truth exactly (it is a real solve)."""
    sol = {c["number"]: c for c in incident["solved"]["solution"]["carriages"]}
    frame = incident["project"].frame
    truth = _truth_cars(incident)
    errs = []
    for ft in incident["solved"]["geojson"]["features"]:
        if ft["geometry"]["type"] != "Point":
            continue
        n = ft["properties"]["number"]
        got = np.asarray(ft["geometry"]["coordinates"])
        assert _metres(got, np.asarray(sol[n]["body_centre_wgs84"]), frame)[0] < 1e-3
        true_wgs = _enu_to_wgs84(np.asarray(truth[n]["body_centre_enu"]), frame.lon_deg, frame.lat_deg,
                                 frame.height_m)[0]
        err = frame.enu_from_wgs84(got) - frame.enu_from_wgs84(true_wgs)
        ci = np.asarray(sol[n]["ci95_body_centre_m"])
        assert np.all(np.abs(err) <= ci + 0.05), (n, err, ci)
        errs.append(np.linalg.norm(err))
    assert len(errs) == 3
    assert 1e-4 < max(errs) < 1.5
    assert incident["solved"]["stats"]["centre_vs_solution_m"] < 1e-3


def test_real_pipeline_carriages_clear_the_exported_terrain_as_in_the_scene(incident, tmp_path):
    """Each carriage's clearance over the terrain in the GLB (lowest vertex height above the exported terrain)
    is the solve's own ``clearance_m`` in the scene: a car resting on the ground rests on it in the export. (The
    solve measures it over the DEM; the terrain stage may simplify its mesh within a stated vertical error.)"""
    tol = 0.01 + _terrain_tolerance(incident)
    path = tmp_path / "solved.glb"
    path.write_bytes(incident["solved"]["glb"])
    g, acc = _glb_arrays(path)
    nodes = {n.name: n for n in g.nodes}
    prim = g.meshes[nodes["terrain"].mesh].primitives[0]
    TV = acc(prim.attributes.POSITION).astype(float) @ G
    TF = acc(prim.indices).reshape(-1, 3).astype(np.int64)
    checked = 0
    for c in incident["solved"]["solution"]["carriages"]:
        if c.get("clearance_m") is None:
            continue
        node = nodes[f"car {c['number']}"]
        R_n = Rotation.from_quat(node.rotation).as_matrix()
        mp = g.meshes[node.mesh].primitives[0]
        CV = (acc(mp.attributes.POSITION).astype(float) @ R_n.T + node.translation) @ G
        clearance = np.nanmin(CV[:, 2] - _terrain_height(TV, TF, CV[:, :2]))
        assert abs(clearance - c["clearance_m"]) < tol, (c["number"], clearance, c["clearance_m"], tol)
        checked += 1
    assert checked == 3


def test_geojson_round_trip_and_right_hand_rule(incident):
    from shapely.geometry import Point, Polygon

    doc = json.loads(incident["paths"]["geojson"].read_text())
    assert doc["type"] == "FeatureCollection" and "crs" not in doc  # RFC 7946: WGS84 only
    frame = incident["project"].frame
    truth = _truth_cars(incident)
    points = {f["properties"]["number"]: f for f in doc["features"] if f["geometry"]["type"] == "Point"}
    polys = {f["properties"]["number"]: f for f in doc["features"] if f["geometry"]["type"] == "Polygon"}
    assert set(points) == set(polys) == set(truth)
    for n, t in truth.items():
        got = np.asarray(points[n]["geometry"]["coordinates"])
        want = _enu_to_wgs84(np.asarray(t["body_centre_enu"]), frame.lon_deg, frame.lat_deg, frame.height_m)[0]
        assert _metres(got, want, frame)[0] < 0.01
        props = points[n]["properties"]
        assert props["type"] == t["type"] and props["status"] == "solved"
        assert abs((props["heading_deg"] - t["heading_deg"] + 180) % 360 - 180) < 1e-3
        assert abs(props["pitch_deg"] - t["pitch_deg"]) < 1e-3 and abs(props["roll_deg"] - t["roll_deg"]) < 1e-3
        assert props["ci95_east_m"] == pytest.approx(0.01)
        ring = np.asarray(polys[n]["geometry"]["coordinates"][0])
        assert np.allclose(ring[0], ring[-1])
        poly = Polygon(ring[:, :2])
        assert poly.is_valid and poly.exterior.is_ccw  # right-hand rule: exterior counter-clockwise
        # the footprint (in ENU) contains the body centre's ground point, and has the body's size
        enu = frame.enu_from_wgs84(ring)
        fp = Polygon(enu[:, :2])
        assert fp.contains(Point(*t["body_centre_enu"][:2]))
        ct = get_type(t["type"])
        lo = ct.collision_boxes()[0][1] * 2  # body length, width, height
        if t["state"] == "on_side":
            expect = lo[0] * lo[2]
        else:
            expect = lo[0] * lo[1]
        assert 0.8 * expect < fp.area < 1.25 * expect, (n, fp.area, expect)


def _glb_arrays(path: Path):
    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()

    def acc(i):
        a = g.accessors[i]
        bv = g.bufferViews[a.bufferView]
        dtype = {pygltflib.FLOAT: np.float32, pygltflib.UNSIGNED_INT: np.uint32}[a.componentType]
        ncomp = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[a.type]
        off = bv.byteOffset + (a.byteOffset or 0)
        return np.frombuffer(blob, dtype=dtype, count=a.count * ncomp, offset=off).reshape(a.count, ncomp)

    return g, acc


def _terrain_height(V: np.ndarray, F: np.ndarray, xy: np.ndarray) -> np.ndarray:
    import trimesh

    m = trimesh.Trimesh(V, F, process=False)
    origins = np.column_stack([xy, np.full(len(xy), V[:, 2].max() + 10.0)])
    locs, rays, _ = m.ray.intersects_location(origins, np.tile([0.0, 0.0, -1.0], (len(xy), 1)),
                                              multiple_hits=False)
    out = np.full(len(xy), np.nan)
    out[rays] = locs[:, 2]
    return out


def test_glb_round_trip_and_carriages_rest_on_the_terrain(incident):
    g, acc = _glb_arrays(incident["paths"]["glb"])
    geo = g.asset.extras["georeference"]
    assert np.allclose(geo["gltf_from_enu"], G)
    assert geo["units"] == "metres"
    # rebuild the frame from what the file records (not from the project)
    lon0, lat0, h0 = geo["origin_wgs84"]
    frame = SceneFrame(geo["crs"], lat0, lon0, h0)
    assert np.allclose(frame.origin_crs, geo["origin_crs"], atol=1e-3)
    nodes = {n.name: n for n in g.nodes}
    terrain_node = nodes["terrain"]
    prim = g.meshes[terrain_node.mesh].primitives[0]
    TV = acc(prim.attributes.POSITION).astype(float) @ G  # glTF -> ENU (G is a rotation: G.T = inverse)
    TF = acc(prim.indices).reshape(-1, 3).astype(np.int64)
    # simplified by the terrain stage (flat areas) and, beyond the face budget, by the export itself
    assert isinstance(incident["stats"]["terrain"]["simplified"], bool)
    assert len(TF) <= 20_500
    # terrain normals up: faces counter-clockwise seen from above
    n = np.cross(TV[TF[:, 1]] - TV[TF[:, 0]], TV[TF[:, 2]] - TV[TF[:, 0]])
    assert np.mean(n[:, 2] > 0) > 0.999
    truth = _truth_cars(incident)
    for num, t in truth.items():
        node = nodes[f"car {num}"]
        R_n = Rotation.from_quat(node.rotation).as_matrix()  # glTF quaternions are x, y, z, w
        t_enu = G.T @ np.asarray(node.translation)
        R_enu = G.T @ R_n @ G
        W = np.asarray(t["world_from_carriage"])
        assert np.linalg.norm(t_enu - W[:3, 3]) < 0.005
        assert np.degrees(Rotation.from_matrix(R_enu @ W[:3, :3].T).magnitude()) < 0.01
        # the body centre, from the node and the type (not from the file's extras), to WGS84 via the recorded frame
        ct = get_type(t["type"])
        centre = R_enu @ ct.bounding_box().mean(axis=0) + t_enu
        got = frame.wgs84_from_enu(centre[None])[0]
        want = _enu_to_wgs84(np.asarray(t["body_centre_enu"]), lon0, lat0, h0)[0]
        assert _metres(got, want, frame)[0] < 0.01
        # resting: the car's vertices clear the exported terrain by ~0 (the truth's contact may be a terrain node
        # touching a body face between vertices, so the vertices may float by a few cm, never sink)
        mp = g.meshes[node.mesh].primitives[0]
        CV = (acc(mp.attributes.POSITION).astype(float) @ R_n.T + node.translation) @ G
        gap = CV[:, 2] - _terrain_height(TV, TF, CV[:, :2])
        assert np.isfinite(gap).mean() > 0.99
        clearance = np.nanmin(gap)
        tol = _terrain_tolerance(incident)
        if t["min_terrain_clearance_m"] < 0.005:
            assert -0.01 - tol < clearance < 0.05 + tol, (num, clearance)


def test_kmz_places_the_models_where_the_carriages_are(incident):
    """Read the KML as Google Earth does (model axes east, north, up at <Location>; heading clockwise from
    north about up) and check every model vertex lands on the true carriage's vertex."""
    import collada

    z = zipfile.ZipFile(incident["paths"]["kmz"])
    assert z.namelist()[0] == "doc.kml"
    kml = ET.fromstring(z.read("doc.kml"))
    frame = incident["project"].frame
    truth = _truth_cars(incident)
    models = kml.findall(f".//{KML}Model")
    assert len(models) == 3
    for m in models:
        num = m.get("id").removeprefix("car-")
        t = truth[num]
        assert m.find(f"{KML}altitudeMode").text == "absolute"
        loc = m.find(f"{KML}Location")
        lon, lat, alt = (float(loc.find(f"{KML}{k}").text) for k in ("longitude", "latitude", "altitude"))
        ori = m.find(f"{KML}Orientation")
        heading = float(ori.find(f"{KML}heading").text)
        assert float(ori.find(f"{KML}tilt").text) == 0.0 and float(ori.find(f"{KML}roll").text) == 0.0
        assert _metres(np.array([lon, lat, alt]), np.asarray(t["position_wgs84"]), frame)[0] < 0.01
        href = m.find(f"{KML}Link/{KML}href").text
        dae = collada.Collada(io.BytesIO(z.read(href)))
        assert dae.assetInfo.upaxis == "Z_UP"
        image = dae.images[0].path
        assert f"{Path(href).parent.as_posix()}/{image}" in z.namelist()
        prim = dae.geometries[0].primitives[0]
        model = np.asarray(prim.vertex)[np.asarray(prim.vertex_index).reshape(-1)]
        local = model @ rot_z(np.deg2rad(-heading)).T  # clockwise heading: local_from_model = Rz(-heading)
        here = SceneFrame(frame.crs, lat, lon, alt)
        enu = frame.enu_from_wgs84(here.wgs84_from_enu(local))
        ct = get_type(t["type"])
        mesh = ct.mesh(car_number=num, textured=True)
        want = np.asarray(mesh.vertices) @ np.asarray(t["world_from_carriage"])[:3, :3].T + \
            np.asarray(t["world_from_carriage"])[:3, 3]
        assert np.max(np.linalg.norm(enu - want, axis=1)) < 0.01
        assert abs((heading - t["heading_deg"] + 180) % 360 - 180) < 0.01  # ~ the scene heading (100 m away)


def test_cityjson_structure_and_vertices_in_the_project_crs(incident):
    doc = json.loads(incident["paths"]["cityjson"].read_text())
    assert doc["type"] == "CityJSON" and doc["version"] == "2.0"
    assert doc["metadata"]["referenceSystem"] == "https://www.opengis.net/def/crs/EPSG/0/32618"
    scale, translate = np.asarray(doc["transform"]["scale"]), np.asarray(doc["transform"]["translate"])
    V = np.asarray(doc["vertices"], dtype=np.int64)
    assert V.ndim == 2 and V.shape[1] == 3
    XYZ = V * scale + translate
    types = {}
    for oid, obj in doc["CityObjects"].items():
        types.setdefault(obj["type"], []).append(oid)
        for geom in obj["geometry"]:
            assert geom["type"] in ("CompositeSurface", "MultiSurface") and isinstance(geom["lod"], str)
            for surface in geom["boundaries"]:
                assert len(surface) >= 1
                for ring in surface:
                    assert len(ring) >= 3 and len(set(ring)) == len(ring)
                    assert all(isinstance(i, int) and 0 <= i < len(V) for i in ring)
    assert types["TINRelief"] == ["terrain"]
    assert len(types["GenericCityObject"]) == 3 and len(types.get("Building", [])) >= 1
    assert doc["CityObjects"]["terrain"]["geometry"][0]["type"] == "CompositeSurface"
    frame = incident["project"].frame
    for num, t in _truth_cars(incident).items():
        obj = doc["CityObjects"][f"car-{num}"]
        idx = sorted({i for s in obj["geometry"][0]["boundaries"] for r in s for i in r})
        enu = frame.enu_from_crs(XYZ[idx])
        ct = get_type(t["type"])
        W = np.asarray(t["world_from_carriage"])
        want = np.asarray(ct.mesh(textured=False).vertices) @ W[:3, :3].T + W[:3, 3]
        # every exported vertex is a posed model vertex (to the file's millimetre)
        d = np.min(np.linalg.norm(enu[:, None, :] - want[None, :, :], axis=2), axis=1)
        assert d.max() < 0.003
        assert obj["attributes"]["number"] == num


def test_cityjson_lib_reads_the_cityjson(incident):
    """A real CityJSON 2.0 reader (3DGI's cityjson-lib, Rust) parses the file and rejects a corrupted copy."""
    cjl = pytest.importorskip("cityjson_lib", reason="cityjson-lib is absent: `uv sync --extra test`")
    data = incident["paths"]["cityjson"].read_bytes()
    doc = json.loads(data)
    summary = cjl.CityModel.parse_document_bytes(data).summary()
    assert summary.cityobject_count == len(doc["CityObjects"])
    assert summary.vertex_count == len(doc["vertices"]) and summary.has_transform
    with pytest.raises(Exception, match="GenericThing"):
        cjl.CityModel.parse_document_bytes(data.replace(b'"GenericCityObject"', b'"GenericThing"'))


def test_tileset_transform_is_ecef_from_enu(incident):
    doc = json.loads((incident["paths"]["tileset"]).read_text())
    assert doc["asset"]["version"] == "1.1" and doc["root"]["content"]["uri"] == "scene.glb"
    assert (incident["paths"]["tileset"].parent / "scene.glb").is_file()
    M = np.asarray(doc["root"]["transform"]).reshape(4, 4).T  # stored column-major
    frame = incident["project"].frame
    to_ecef = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)
    # a point 100 m north and 10 m up of the origin, through the tileset transform and through the frame
    p = np.array([0.0, 100.0, 10.0])
    got = M[:3, :3] @ p + M[:3, 3]
    geo = frame.wgs84_from_enu(p[None])[0]
    want = np.array(to_ecef.transform(geo[0], geo[1], geo[2]))
    assert np.linalg.norm(got - want) < 1e-3
    # glTF content is y-up; 3D Tiles turns it z-up: (x, y, z) -> (x, -z, y); with our axes that is ENU again
    y_up_to_z_up = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    assert np.allclose(y_up_to_z_up @ G, np.eye(3))


# ---------------------------------------------------------------------------------------------------------
# Real clients
# ---------------------------------------------------------------------------------------------------------
def _npm_root() -> str | None:
    if shutil.which("npm") is None:
        return None
    r = subprocess.run(["npm", "root", "-g"], capture_output=True, text=True, timeout=60)
    return r.stdout.strip() or None


VALIDATE_JS = """
const fs = require('fs');
const validator = require('gltf-validator');
validator.validateBytes(new Uint8Array(fs.readFileSync(process.argv[1])), {maxIssues: 200})
  .then(r => console.log(JSON.stringify(r.issues)))
  .catch(e => { console.error(String(e)); process.exit(2); });
"""


def test_khronos_gltf_validator_reports_no_errors(incident, tmp_path):
    """The exported GLB, and a variant with the terrain coloured by height (no orthophoto), validate cleanly."""
    from workbench.export.gltf import glb_bytes
    from workbench.export.scene import _height_colors, build_scene

    root = _npm_root()
    if shutil.which("node") is None or root is None or not (Path(root) / "gltf-validator").is_dir():
        pytest.skip("the Khronos glTF validator is absent: `npm install -g gltf-validator` (needs node)")
    scene = build_scene(incident["project"], ExportOptions(terrain_max_faces=5000, full_resolution_margin_m=0.0))
    scene.terrain.texture, scene.terrain.uv = None, None
    scene.terrain.colors = _height_colors(scene.terrain.vertices[:, 2])
    coloured = tmp_path / "coloured.glb"
    coloured.write_bytes(glb_bytes(scene, ExportOptions())[0])
    for glb in (incident["paths"]["glb"], coloured):
        r = subprocess.run(["node", "-e", VALIDATE_JS, str(glb)], capture_output=True, text=True, timeout=120,
                           env={**os.environ, "NODE_PATH": root})
        assert r.returncode == 0, r.stderr
        issues = json.loads(r.stdout)
        errors = [m for m in issues["messages"] if m["severity"] == 0]
        assert issues["numErrors"] == 0, (glb.name, errors)
        assert issues["numWarnings"] == 0, (glb.name, issues["messages"])
    g = pygltflib.GLTF2().load(str(coloured))
    assert g.meshes[g.nodes[[n.name for n in g.nodes].index("terrain")].mesh].primitives[0].attributes.COLOR_0 \
        is not None


def _ogrinfo(*args: str) -> str:
    r = subprocess.run(["ogrinfo", "-ro", *args], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_ogrinfo_opens_the_geojson_and_the_kml(incident):
    if shutil.which("ogrinfo") is None:
        pytest.skip("GDAL's ogrinfo is absent: `apt-get install -y gdal-bin`")
    out = _ogrinfo("-al", "-so", str(incident["paths"]["geojson"]))
    assert "Feature Count: 6" in out and "EPSG\",4326" in out.replace(" ", "")
    assert "heading_deg: Real" in out and "number: String" in out
    kmz = incident["paths"]["kmz"]
    out = _ogrinfo("-al", f"/vsizip/{kmz}/doc.kml")
    assert out.count("OGRFeature(") == 9  # 3 models + 3 numbers + 3 footprints
    for layer in ("Carriage models", "Car numbers", "Footprints"):
        assert f"Layer name: {layer}" in out


BLENDER_SCRIPT = r"""
import json, sys
import numpy
if not hasattr(numpy, "bool"):  # Debian's Blender 3.4 glTF importer uses np.bool, gone from numpy >= 1.24
    numpy.bool = numpy.bool_
import bpy
from mathutils import Vector
glb, out = sys.argv[sys.argv.index("--") + 1:][:2]
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.import_scene.gltf(filepath=glb)
terrain = bpy.data.objects.get("terrain")
res = {}
for ob in bpy.data.objects:
    rec = {"type": ob.type, "location": list(ob.matrix_world.translation)}
    if ob.type == "MESH":
        ws = [ob.matrix_world @ v.co for v in ob.data.vertices]
        rec["min"] = [min(p[i] for p in ws) for i in range(3)]
        rec["max"] = [max(p[i] for p in ws) for i in range(3)]
        if ob.name.startswith("car ") and terrain is not None:
            low = min(ws, key=lambda p: p.z)
            inv = terrain.matrix_world.inverted()
            hit, loc, _, _ = terrain.ray_cast(inv @ Vector((low.x, low.y, low.z + 50.0)),
                                              (inv.to_3x3() @ Vector((0, 0, -1))).normalized())
            rec["lowest"] = list(low)
            rec["terrain_below"] = list(terrain.matrix_world @ loc) if hit else None
    res[ob.name] = rec
json.dump(res, open(out, "w"))
"""


def test_blender_imports_the_glb_in_enu(incident, tmp_path):
    if shutil.which("blender") is None:
        pytest.skip("Blender is absent: `apt-get install -y blender`")
    script = tmp_path / "check.py"
    script.write_text(BLENDER_SCRIPT)
    out = tmp_path / "blender.json"
    r = subprocess.run(["blender", "-b", "--factory-startup", "--python", str(script), "--",
                        str(incident["paths"]["glb"]), str(out)], capture_output=True, text=True, timeout=180)
    assert out.is_file(), r.stdout[-3000:] + r.stderr[-3000:]
    objs = json.loads(out.read_text())
    assert {"terrain", "buildings", "carriages", "car 6100", "car 6223", "car 6227"} <= set(objs)
    # Blender turns glTF's y-up into z-up: its world axes are then exactly the scene's east, north, up
    truth = _truth_cars(incident)
    for num, t in truth.items():
        ob = objs[f"car {num}"]
        assert np.linalg.norm(np.asarray(ob["location"]) - np.asarray(t["position_enu"])) < 0.005
        if t["min_terrain_clearance_m"] < 0.005 and ob.get("terrain_below"):
            gap = ob["lowest"][2] - ob["terrain_below"][2]
            assert abs(gap) < 0.05 + _terrain_tolerance(incident), (num, ob["lowest"], ob["terrain_below"])
    tb = objs["terrain"]
    assert tb["min"][0] < -80 and tb["max"][0] > 80 and tb["min"][1] < -80 and tb["max"][1] > 80


def test_export_stage_is_recorded_by_the_runner(incident):
    state = json.loads((incident["root"] / "out" / "state.json").read_text())
    rec = state["export"]
    assert rec["status"] == "done"
    assert {"glb", "geojson", "kmz", "cityjson", "tileset", "stats"} <= set(rec["outputs"])
    assert set(rec["inputs"]) >= {"solution", "terrain_mesh", "orthophoto"}
    sizes = incident["stats"]["bytes"]
    assert 100_000 < sizes["glb"] < 20_000_000


PROJECT_TOML = """
[incident]
name = "export test"
date = 2013-12-01

[location]
lat = 40.878
lon = -73.9215
height_m = 4.0
crs = "EPSG:32618"

[[consist]]
number = "A1"
type = "shoreliner"
coupling_to_next = "broken"

[[consist]]
number = "A2"
type = "shoreliner"

[camera]
source = "exif"
"""


def test_export_without_terrain_and_with_a_left_out_car(tmp_path):
    """No DEM (no terrain stage): the carriages alone; a left-out car is listed, not exported."""
    from workbench.core.frames import rotation_from_hpr
    from workbench.export.cityjson import cityjson_document
    from workbench.export.geojson import carriages_geojson
    from workbench.export.gltf import glb_bytes
    from workbench.export.scene import build_scene

    (tmp_path / "project.toml").write_text(PROJECT_TOML)
    project = Project(tmp_path)
    W = np.eye(4)
    W[:3, :3] = rotation_from_hpr(30.0, 0.0, 0.0)
    W[:3, 3] = [5.0, 10.0, 0.5]
    ct = get_type("shoreliner")
    centre = W[:3, :3] @ ct.bounding_box().mean(axis=0) + W[:3, 3]
    sol = {"status": "converged", "frame": {"crs": "EPSG:32618", "lat": 40.878, "lon": -73.9215, "height_m": 4.0},
           "carriages": [{"index": 0, "number": "A1", "type": "shoreliner", "status": "solved",
                          "world_from_carriage": W.tolist(), "body_centre_enu": centre.tolist()},
                         {"index": 1, "number": "A2", "type": "shoreliner", "status": "left_out",
                          "world_from_carriage": None}]}
    atomic_write_json(project.stage_dir("solve") / "solution.json", sol)
    # the solution, and the consist's type files (the models exported); no terrain
    assert set(EXPORT_STAGE.inputs(project)) == {"solution"} | {f"library:{c.type}.toml" for c in project.settings.consist}
    scene = build_scene(project)
    assert scene.terrain is None and [c.number for c in scene.carriages] == ["A1"]
    assert scene.left_out[0]["number"] == "A2"
    gj = carriages_geojson(scene)
    assert len(gj["features"]) == 2
    pt = next(f for f in gj["features"] if f["geometry"]["type"] == "Point")
    want = _enu_to_wgs84(centre, -73.9215, 40.878, 4.0)[0]
    assert _metres(np.asarray(pt["geometry"]["coordinates"]), want, project.frame)[0] < 0.005
    assert pt["properties"]["heading_deg"] == pytest.approx(30.0, abs=1e-6)
    assert pt["properties"]["ci95_east_m"] is None
    from shapely.geometry import Polygon

    poly = next(f for f in gj["features"] if f["geometry"]["type"] == "Polygon")
    ring = project.frame.enu_from_wgs84(np.asarray(poly["geometry"]["coordinates"][0]))
    body = ct.collision_boxes()[0][1] * 2
    assert Polygon(ring[:, :2]).area == pytest.approx(body[0] * body[1], rel=1e-4)
    # the footprint's long side points along the heading (30 deg east of north)
    d = ring[1:, :2] - ring[:-1, :2]
    longest = d[np.argmax(np.linalg.norm(d, axis=1))]
    bearing = np.degrees(np.arctan2(longest[0], longest[1])) % 180.0
    assert bearing == pytest.approx(30.0, abs=0.01)
    data, stats = glb_bytes(scene, ExportOptions())
    g = pygltflib.GLTF2.load_from_bytes(data)
    assert {n.name for n in g.nodes} == {"scene", "carriages", "car A1"}
    cj = cityjson_document(scene)
    assert [o["type"] for o in cj["CityObjects"].values()] == ["GenericCityObject"]


def test_decimate_terrain_keeps_the_band_exactly_and_leaves_no_crack():
    from workbench.export.scene import decimate_terrain

    n = 81  # an 80 x 80 m grid of 1 m cells, two triangles each, gently rolling
    x, y = np.meshgrid(np.arange(n, dtype=float) - 40, np.arange(n, dtype=float) - 40)
    z = 2.0 * np.sin(x / 9.0) * np.cos(y / 13.0) + 0.02 * x
    V = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    F = np.vstack([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
    keep = np.abs(V[F].mean(axis=1)[:, 0]) < 6.0  # a 12 m band down the middle
    V2, F2, kept, info = decimate_terrain(V, F, keep, max_faces=3000)
    assert info["simplified"] and 2000 < len(F2) <= 3100 and kept.sum() == keep.sum()
    # the band's triangles come through unchanged (same corner positions)
    np.testing.assert_array_equal(np.sort(V2[F2[kept]].reshape(-1, 9), axis=0),
                                  np.sort(V[F[keep]].reshape(-1, 9), axis=0))

    def boundary_length(VV, FF):
        e = np.sort(np.vstack([FF[:, [0, 1]], FF[:, [1, 2]], FF[:, [2, 0]]]), axis=1)
        u, cnt = np.unique(e, axis=0, return_counts=True)
        b = u[cnt == 1]
        return float(np.linalg.norm(VV[b[:, 0], :2] - VV[b[:, 1], :2], axis=1).sum())

    # no crack: the only open edges are the grid's outer border (4 x 80 m)
    assert boundary_length(V2, F2) == pytest.approx(320.0, abs=1e-6)
    # the simplified surface stays close to the original heights
    gap = np.abs(_terrain_height(V2, F2, V[::7, :2]) - V[::7, 2])
    assert 0.001 < np.nanmax(gap) < 0.08 and np.isfinite(gap).mean() > 0.99
