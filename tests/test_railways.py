"""The railway layer (workbench/files/railways.py) and the carriages' place on the track (workbench/core/track.py):
GeoJSON in several CRSs, OpenStreetMap XML, the warnings and errors, the geometry against circles drawn as
polylines, the uncertainty propagation, and a synthetic incident's truth, as generated and as solved."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from conftest import with_solver_lines

from workbench.core.frames import SceneFrame, rotation_from_hpr
from workbench.core.geometry import exp_so3
from workbench.core.track import RailwayLine, centre_heading_covariance, reference_line, track_position, wrap_deg
from workbench.errors import InputError
from workbench.files.railways import NoRailwayLines, carriage_track_positions, read_railways
from workbench.project import Project

FRAME = SceneFrame("EPSG:32618", 40.878, -73.9215, 4.0)


def _arc(radius: float, step: float, n: int, bearing0: float = 150.0) -> np.ndarray:
    """(n, 2) ENU points of a left-hand curve of ``radius`` through the origin, ``step`` metres of arc apart."""
    b = math.radians(bearing0)
    fwd, left = np.array([math.sin(b), math.cos(b)]), np.array([-math.cos(b), math.sin(b)])
    centre = radius * left
    phi = (np.arange(n) - n // 2) * step / radius
    u = np.cos(phi)[:, None] * -left + np.sin(phi)[:, None] * fwd
    return centre + radius * u


def _line_enu() -> np.ndarray:
    xy = _arc(400.0, 10.0, 31)
    return np.column_stack([xy, np.full(len(xy), 0.5)])


# ---------------------------------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------------------------------
def _geojson(coords: list, crs: str | None, **props) -> dict:
    doc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "id": "main", "properties": {"name": "Hudson Line", "railway": "rail", **props},
         "geometry": {"type": "LineString", "coordinates": coords}},
        {"type": "Feature", "properties": {"railway": "station"}, "geometry": {"type": "Point", "coordinates":
                                                                                 coords[0]}},
        {"type": "Feature", "properties": {"railway": "abandoned"}, "geometry": {"type": "LineString",
                                                                                  "coordinates": coords[:2]}}]}
    if crs:
        doc["crs"] = {"type": "name", "properties": {"name": crs}}
    return doc


def test_geojson_in_three_crss_gives_the_same_line(tmp_path):
    enu = _line_enu()
    utm = FRAME.crs_from_enu(enu)
    wgs = FRAME.wgs84_from_enu(enu)
    from pyproj import Transformer

    nyft = np.column_stack(Transformer.from_crs("EPSG:4326", "EPSG:2263", always_xy=True).transform(wgs[:, 0], wgs[:, 1]))
    files = {"utm.geojson": _geojson(np.round(utm, 4).tolist(), "urn:ogc:def:crs:EPSG::32618", chainage_origin=1200.5),
             "wgs84.geojson": _geojson(np.round(wgs[:, :2], 10).tolist(), None),  # RFC 7946: no crs, lon/lat
             "nyft.geojson": _geojson(np.round(nyft, 4).tolist(), "EPSG:2263")}  # NY Long Island, US survey feet
    layers = {}
    for name, doc in files.items():
        (tmp_path / name).write_text(json.dumps(doc))
        layers[name] = read_railways(tmp_path / name, FRAME)
    for name, layer in layers.items():
        assert len(layer.lines) == 1 and layer.skipped == 2, name  # the station and the abandoned line skipped
        line = layer.lines[0]
        assert line.id == "main" and line.name == "Hudson Line"
        assert np.max(np.linalg.norm(line.points_enu[:, :2] - enu[:, :2], axis=1)) < 2e-3, name
    assert layers["utm.geojson"].heights == "file" and layers["wgs84.geojson"].heights == "none"
    assert np.allclose(layers["utm.geojson"].lines[0].points_enu[:, 2], 0.5, atol=1e-3)
    assert layers["utm.geojson"].lines[0].chainage_origin_m == 1200.5
    assert layers["wgs84.geojson"].lines[0].chainage_origin_m == 0.0
    assert np.allclose(layers["wgs84.geojson"].lines[0].points_enu[:, 2], 0.0, atol=0.05)  # no height: the origin's


OSM = """<?xml version='1.0' encoding='UTF-8'?>
<osm version="0.6" generator="test">
  {nodes}
  <way id="101"><nd ref="1"/><nd ref="2"/><nd ref="3"/>
    <tag k="railway" v="rail"/><tag k="name" v="Hudson Line"/><tag k="chainage_origin" v="17300"/></way>
  <way id="102"><nd ref="3"/><nd ref="4"/><tag k="railway" v="rail"/><tag k="ref" v="Track 2"/></way>
  <way id="103"><nd ref="1"/><nd ref="4"/><tag k="highway" v="residential"/></way>
  <way id="104"><nd ref="2"/><nd ref="4"/><tag k="railway" v="platform"/></way>
</osm>"""


def _osm_nodes(lonlat: np.ndarray) -> str:
    return "\n  ".join(f'<node id="{i + 1}" lat="{p[1]:.9f}" lon="{p[0]:.9f}" version="1"/>' for i, p in enumerate(lonlat))


def test_openstreetmap_xml_ways_tagged_rail(tmp_path):
    enu = np.array([[-60.0, 80.0, 0.0], [0.0, 0.0, 0.0], [50.0, -90.0, 0.0], [80.0, -170.0, 0.0]])
    ll = FRAME.wgs84_from_enu(enu)
    p = tmp_path / "lines.osm"
    p.write_text(OSM.format(nodes=_osm_nodes(ll)))
    layer = read_railways(p, FRAME)
    assert [ln.id for ln in layer.lines] == ["way/101", "way/102"] and layer.skipped == 2
    assert [ln.name for ln in layer.lines] == ["Hudson Line", "Track 2"]
    assert layer.lines[0].chainage_origin_m == 17300.0 and layer.crs == "EPSG:4326"
    assert np.allclose(layer.lines[0].points_enu[:, :2], enu[:3, :2], atol=1e-3)
    assert np.allclose(layer.lines[1].points_enu[:, :2], enu[2:, :2], atol=1e-3)


def test_no_railway_lines_is_a_warning_naming_the_file(tmp_path):
    p = tmp_path / "stations.geojson"
    p.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"railway": "station"}, "geometry": {"type": "Point", "coordinates": [-73.9, 40.8]}},
        {"type": "Feature", "properties": {"highway": "primary", "railway": "platform"},
         "geometry": {"type": "LineString", "coordinates": [[-73.9, 40.8], [-73.91, 40.81]]}}]}))
    with pytest.warns(NoRailwayLines, match=r"stations\.geojson.*no LineString"):
        assert read_railways(p, FRAME) is None
    q = tmp_path / "roads.osm"
    q.write_text('<osm version="0.6"><node id="1" lat="40.8" lon="-73.9"/><node id="2" lat="40.81" lon="-73.9"/>'
                 '<way id="7"><nd ref="1"/><nd ref="2"/><tag k="highway" v="primary"/></way></osm>')
    with pytest.warns(NoRailwayLines, match=r"roads\.osm.*no way tagged railway=rail"):
        assert read_railways(q, FRAME) is None


@pytest.mark.parametrize("name, text, needle", [
    ("one.geojson", json.dumps({"type": "Feature", "id": "short", "properties": {},
                                "geometry": {"type": "LineString", "coordinates": [[-73.9, 40.8]]}}),
     r"one\.geojson: feature short: a line needs at least 2 positions"),
    ("bad.geojson", json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"name": "x"}, "geometry": {"type": "LineString",
                                                                      "coordinates": [[-73.9, 40.8], ["a", 40.9]]}}]}),
     r"bad\.geojson: feature #0: position 1 = \['a', 40\.9\]"),
    ("origin.geojson", json.dumps({"type": "Feature", "id": "L", "properties": {"chainage_origin": "km 12"},
                                   "geometry": {"type": "LineString", "coordinates": [[-73.9, 40.8], [-73.9, 40.81]]}}),
     r"origin\.geojson: feature L: chainage_origin = 'km 12'"),
    ("crs.geojson", json.dumps({"type": "Feature", "id": "L", "crs": {"type": "name", "properties": {"name": "EPSG:999999"}},
                                "properties": {}, "geometry": {"type": "LineString", "coordinates": [[0, 0], [1, 1]]}}),
     r"crs\.geojson: line L: crs = 'EPSG:999999'"),
    ("swapped.geojson", json.dumps({"type": "Feature", "id": "L", "properties": {},
                                    "geometry": {"type": "LineString", "coordinates": [[40.8, -73.9], [40.81, -73.9]]}}),
     r"swapped\.geojson: line L reaches \d+ km from"),
    ("notjson.geojson", "{not json", r"notjson\.geojson: not valid JSON"),
    ("missing.osm", '<osm version="0.6"><node id="1" lat="40.8" lon="-73.9"/><way id="5"><nd ref="1"/><nd ref="2"/>'
                    '<tag k="railway" v="rail"/></way></osm>', r"missing\.osm: way 5: node 2 is not in the file"),
    ("badnode.osm", '<osm version="0.6"><node id="1" lat="north" lon="-73.9"/></osm>', r"badnode\.osm: node '1' has lat"),
    ("notosm.osm", "<gpx></gpx>", r"notosm\.osm: the root element is <gpx>"),
    ("lines.osm.pbf", "", r"lines\.osm\.pbf: OpenStreetMap PBF is not read; convert it"),
])
def test_malformed_files_name_the_file_and_the_entry(tmp_path, name, text, needle):
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(InputError, match=needle):
        read_railways(p, FRAME)


# ---------------------------------------------------------------------------------------------------------------
# Geometry
# ---------------------------------------------------------------------------------------------------------------
def test_straight_line_signs_and_ends():
    line = RailwayLine("n", None, np.array([[0.0, 0.0, 0.0], [0.0, 50.0, 0.0], [0.0, 100.0, 0.0]]), 500.0)
    tp = track_position(line, np.array([3.0, 10.0]), heading_deg=80.0)
    assert tp.chainage_m == pytest.approx(510.0) and tp.offset_m == pytest.approx(-3.0)  # east of a northbound line
    assert tp.yaw_deg == pytest.approx(-80.0) and not tp.beyond_end  # front turned right (clockwise)
    tp = track_position(line, np.array([-2.0, 120.0]), heading_deg=350.0)
    assert tp.chainage_m == pytest.approx(620.0) and tp.offset_m == pytest.approx(2.0) and tp.beyond_end
    assert tp.yaw_deg == pytest.approx(10.0)
    assert track_position(line, np.array([0.0, -5.0]), 185.0).yaw_deg == pytest.approx(175.0)
    xy, bearing = line.at(560.0)  # the map's chainage ticks
    assert np.allclose(xy, [0.0, 60.0]) and bearing == pytest.approx(0.0)
    assert wrap_deg(180.0) == 180.0 and wrap_deg(-180.0) == 180.0 and wrap_deg(-190.0) == pytest.approx(170.0)


@pytest.mark.parametrize("step", [1.0, 30.0])
def test_circle_drawn_as_a_polyline(step):
    """A 300 m curve drawn with 1 m or 30 m chords: chainage as on the circle (less what the chords are shorter:
    the length is the polyline's), yaw as on the circle, the offset within the chords' sagitta (L^2 / 8R: 0.4 mm,
    0.375 m), the chainage within a tenth of it (the blended direction is not quite the circle's)."""
    R = 300.0
    xy = _arc(R, step, int(240 / step) + 1, bearing0=0.0)  # starts west of north, turns left (west)
    line = RailwayLine("c", None, np.column_stack([xy, np.zeros(len(xy))]))
    centre = np.array([-R, 0.0])
    phi0 = -(len(xy) // 2) * step / R
    sag = step ** 2 / (8 * R)
    for phi, off, head in [(0.0, 0.0, 0.0), (0.05, 10.0, 20.0), (-0.2, -14.0, -35.0), (0.31, 4.0, 180.0)]:
        u = np.array([math.cos(phi), math.sin(phi)])
        p = centre + (R - off) * u
        bearing = -math.degrees(phi)  # the tangent of this left-hand curve at phi
        tp = track_position(line, p, head)
        arc = R * (phi - phi0)
        short = arc / step * (step - 2 * R * math.sin(step / (2 * R)))  # the chords are shorter than the arc
        assert tp.chainage_m == pytest.approx(arc - short, abs=1e-3 + 0.1 * sag)  # 1 mm, 38 mm
        assert tp.offset_m == pytest.approx(off, abs=1e-4 + sag)
        assert tp.yaw_deg == pytest.approx(wrap_deg(bearing - head), abs=0.01)


def test_reference_line_is_the_nearest_to_the_consist():
    a = RailwayLine("a", None, np.array([[0.0, -100, 0], [0.0, 100, 0]]))
    b = RailwayLine("b", None, np.array([[4.4, -100, 0], [4.4, 100, 0]]))
    assert reference_line([a, b], np.array([[1.0, 0], [2.0, 10]])).id == "a"
    assert reference_line([a, b], np.array([[3.0, 0], [9.0, 10]])).id == "b"


def test_uncertainty_propagation():
    line = RailwayLine("e", None, np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0]]))  # eastbound
    C = np.diag([0.2 ** 2, 0.05 ** 2, 0.5 ** 2])  # east, north, heading
    tp = track_position(line, np.array([10.0, 2.0]), 95.0, C, ci95_factor=2.0)
    assert tp.sigma_chainage_m == pytest.approx(0.2, rel=1e-6) and tp.sigma_offset_m == pytest.approx(0.05, rel=1e-6)
    assert tp.sigma_yaw_deg == pytest.approx(0.5, rel=1e-6) and tp.ci95("offset_m") == pytest.approx(0.1, rel=1e-6)
    # the pose covariance (scene rotation vector, origin) to (east, north, heading): against finite differences
    rng = np.random.default_rng(3)
    R = rotation_from_hpr(37.0, 4.0, 81.0)
    t = np.array([5.0, -3.0, 1.0])
    c_local = np.array([0.0, 0.0, 2.1])
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 1e-4

    def enh(x):
        Rx = exp_so3(x[:3]) @ R
        c = Rx @ c_local + t + x[3:]
        return np.array([c[0], c[1], math.degrees(math.atan2(Rx[0, 0], Rx[1, 0]))])

    J = np.column_stack([(enh(e) - enh(-e)) / 2e-6 for e in np.eye(6) * 1e-6])
    assert np.allclose(centre_heading_covariance(M, R @ c_local + t, cov), J @ cov @ J.T, rtol=1e-5, atol=1e-10)


# ---------------------------------------------------------------------------------------------------------------
# A synthetic incident: the truth as generated, and as solved
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    """A 3-car Spuyten Duyvil incident (2 photos of 320x240, 200 m of terrain), known cameras, true picks with 1 px
    noise, run up to the solve (about 15 s)."""
    from workbench.pipeline import STAGES
    from workbench.runner import Runner
    from workbench.synth.generate import SynthOptions, generate_incident
    from workbench.synth.handpicks import write_known_cameras, write_true_correspondences

    root = tmp_path_factory.mktemp("railways") / "inc"
    t0 = time.perf_counter()
    generate_incident(root, SynthOptions(n_cars=3, photo_width=320, photo_height=240, n_panorama=2, n_multiview=0,
                                         terrain_size_m=200.0, supersample=1))
    write_known_cameras(root, "panorama")
    write_true_correspondences(root, "panorama", sigma_px=1.0, seed=0)
    # the hand picks only: every car has them (the automatic finder placed no point here: the same
    # correspondences.json with it, which took most of the stages' time; docs/performance.md, the thirteenth pass)
    (root / "project.toml").write_text((root / "project.toml").read_text() + '\n[correspond]\nfinder = "off"\n')
    project = Project(root)
    Runner(project, list(STAGES)).run(until="solve")
    truth = json.loads((root / "truth" / "ground_truth.json").read_text())
    return project, truth, time.perf_counter() - t0


def test_synthetic_truth_is_the_functions_figures_on_the_written_layer(solved):
    project, truth, _ = solved
    assert project.settings.terrain.railways == truth["layers"]["railways"]
    layer = project.railways()
    assert layer.heights == "terrain" and len(layer.lines) == 1
    line = layer.lines[0]
    assert line.id == "spuyten-duyvil-track" and not line.chainage_origin_m
    file_heights = project.railways(heights=False).lines[0].points_enu[:, 2]
    on_dem = np.isfinite(project.terrain_model(max_cells=160_000).height_at(line.points_enu[:, :2]))
    assert on_dem.mean() > 0.6  # the area of interest ends before the DEM: the file's heights beyond it
    assert np.allclose(file_heights[on_dem] - line.points_enu[on_dem, 2], 0.2, atol=1e-3)  # top of rail on the bed
    assert np.array_equal(file_heights[~on_dem], line.points_enu[~on_dem, 2])
    for c in truth["carriages"]:
        t = c["track"]
        tp = track_position(line, np.asarray(c["body_centre_enu"])[:2], c["heading_deg"])
        assert t["line_id"] == line.id and not tp.beyond_end
        assert tp.chainage_m == pytest.approx(t["chainage_m"], abs=1e-3)  # the polyline of 1 m chords vs the arc
        assert tp.offset_m == pytest.approx(t["offset_m"], abs=1e-3)
        assert tp.yaw_deg == pytest.approx(t["yaw_deg"], abs=5e-3)
        assert tp.track_bearing_deg == pytest.approx(t["track_bearing_deg"], abs=5e-3)


def test_solved_carriages_on_the_track_within_their_intervals(solved):
    project, truth, took = solved
    solution = project.solution()
    positions = carriage_track_positions(solution, project.railways(heights=False))
    true = {c["number"]: c["track"] for c in truth["carriages"]}
    assert set(positions) == set(true)
    for c in solution.posed:
        tp = positions[c.number]
        ci_e, ci_n, _ = c.floats("ci95_body_centre_m")
        for k in ("chainage_m", "offset_m", "yaw_deg"):
            err = abs(getattr(tp, k) - true[c.number][k])
            assert err <= tp.ci95(k), (c.number, k, err, tp.ci95(k))
            # the body centre's interval projected on a direction is no wider than its east and north together
            bound = math.hypot(ci_e, ci_n) if k != "yaw_deg" else 1.01 * c.floats("ci95_hpr_deg")[0] + 0.05
            assert 0 < tp.ci95(k) <= bound, (c.number, k, tp.ci95(k), bound)
    assert took < 40


def test_project_railways_unset_and_missing(solved, tmp_path):
    from workbench.pipeline import stage

    project, _, _ = solved
    layer_file = project.path(project.settings.terrain.railways)
    for name in ("render", "export"):  # a changed layer makes them stale (the report too, once render has run)
        assert stage(name).inputs(project)["railways"] == layer_file, name
    assert "terrain.railways" in stage("report").settings_sections
    text = project.settings_path.read_text()
    other = tmp_path / "copy"
    other.mkdir()
    (other / "project.toml").write_text("\n".join(line for line in text.splitlines() if not line.startswith("railways")))
    assert Project(other).railways() is None
    (other / "project.toml").write_text(text.replace(project.settings.terrain.railways, "nowhere.geojson"))
    with pytest.raises(InputError, match=r"terrain.railways = 'nowhere.geojson'"):
        Project(other).railways(heights=False)


def test_geojson_export_carries_the_place_on_the_track(solved):
    from workbench.export import ExportOptions
    from workbench.export.stage import export_scene

    project, truth, _ = solved
    paths, _ = export_scene(project, ExportOptions(tiles=False, terrain_max_faces=20_000))
    gj = json.loads(paths["geojson"].read_text())
    positions = carriage_track_positions(project.solution(), project.railways(heights=False))
    true = {c["number"]: c["track"] for c in truth["carriages"]}
    assert len(gj["features"]) == 2 * len(positions)
    for feat in gj["features"]:
        p, tp = feat["properties"], positions[feat["properties"]["number"]]
        assert p["track_line"] == "spuyten-duyvil-track" and p["beyond_line_end"] is False
        assert p["chainage_m"] == pytest.approx(tp.chainage_m, abs=1e-4)
        assert p["lateral_offset_m"] == pytest.approx(tp.offset_m, abs=1e-4)
        assert p["yaw_to_track_deg"] == pytest.approx(tp.yaw_deg, abs=1e-4)
        assert abs(p["lateral_offset_m"] - true[p["number"]]["offset_m"]) <= p["ci95_lateral_offset_m"]


def test_map_draws_the_line_and_records_a_layer_without_one(solved, tmp_path, monkeypatch):
    from PIL import Image

    from workbench.report import render_stage
    from workbench.report.scene import load_scene

    project, _, _ = solved
    monkeypatch.setattr(render_stage, "MAP_SIZE", (240, 240))
    stations = tmp_path / "stations.geojson"
    stations.write_text(json.dumps({"type": "Feature", "properties": {"railway": "station"},
                                    "geometry": {"type": "Point", "coordinates": [-73.92, 40.878]}}))
    sc = load_scene(project, textured=False)
    sr = render_stage.SceneRenderer(sc)
    maps = {}
    for name, layer in (("with", None), ("without", stations)):
        p = Project(project.root)
        if layer is not None:
            p.__dict__["settings"] = p.settings.model_copy(
                update={"terrain": p.settings.terrain.model_copy(update={"railways": str(layer)})})
        run = render_stage._RenderRun(p, lambda f, m="": None, tmp_path / name, sc, sr)
        run.top_down_map()
        maps[name] = np.asarray(Image.open(tmp_path / name / "map.png").convert("L"), dtype=float)
        if layer is None:
            assert run.railways == {"file": project.settings.terrain.railways, "lines": 1, "warnings": []}
        else:
            assert run.railways["lines"] == 0 and "stations.geojson" in run.railways["warnings"][0]
    assert maps["with"].shape == maps["without"].shape
    assert np.mean(np.abs(maps["with"] - maps["without"]) > 40) > 0.002  # the dashed line and its ticks


def _way(i, refs, **tags):
    return (f'<way id="{i}">' + "".join(f'<nd ref="{r}"/>' for r in refs)
            + "".join(f'<tag k="{k}" v="{v}"/>' for k, v in {"railway": "rail", **tags}.items()) + "</way>")


def test_openstreetmap_pieces_of_one_track_are_joined(tmp_path):
    """OpenStreetMap splits a track at bridges and tag changes: ways that continue one another end to end (same
    name, no other railway way at the node) are one line, in the first way's direction, the others reversed as
    needed; a switch (three ways at a node), another name, or a piece with its own chainage origin ends a line."""
    enu = np.array([[0.0, 100.0 * k, 0.0] for k in range(12)])  # nodes 1..12, 100 m apart northwards
    nodes = _osm_nodes(FRAME.wgs84_from_enu(enu))
    ways = [_way(10, [1, 2, 3]), _way(11, [5, 4, 3]), _way(12, [5, 6]),  # one track in three pieces, 11 reversed
            _way(13, [6, 7]), _way(14, [6, 8]),  # a switch at 6: the through line ends, both branches stand alone
            _way(20, [9, 10], name="Hudson Line"), _way(21, [10, 11], name="Harlem Line"),  # names differ at 10
            _way(30, [11, 12], name="Harlem Line", chainage_origin="500")]  # its own origin: nothing before it
    p = tmp_path / "split.osm"
    p.write_text(f'<osm version="0.6">{nodes}{"".join(ways)}</osm>')
    layer = read_railways(p, FRAME)
    by_id = {ln.id: ln for ln in layer.lines}
    assert sorted(by_id) == ["way/10", "way/13", "way/14", "way/20", "way/21", "way/30"]
    joined = by_id["way/10"]
    assert np.allclose(joined.points_enu[:, :2], enu[:6, :2], atol=1e-3)  # nodes 1..6 in order
    assert abs(joined.length_m - 500.0) < 0.01 and joined.chainage_origin_m == 0.0
    assert [len(by_id[k].points_enu) for k in ("way/13", "way/14", "way/20", "way/21", "way/30")] == [2, 2, 2, 2, 2]
    assert by_id["way/30"].chainage_origin_m == 500.0
    # the joined line's chainage runs on across the pieces: node 5 (in the reversed piece) at 400 m
    assert abs(joined.foot(enu[4, :2]).chainage_m - 400.0) < 0.01


@pytest.mark.parametrize("positions, expected, turned", [
    (("12.3", "12,5"), (12300.0, 12500.0), False),  # km, a decimal comma read as a point
    (("12.5", "12.3"), (12500.0, 12300.0), True),  # counting down along the line as drawn: turned
    (("mi:7.6429", "mi:7.7672"), (7.6429 * 1609.344, 7.7672 * 1609.344), False)])  # miles
def test_chainage_from_kilometre_posts(tmp_path, positions, expected, turned):
    """Without a chainage_origin, an OSM line's chainage comes from the kilometre posts beside it (railway=milestone,
    railway:position in km, or mi:<miles>): the posts read their own positions back; a line the posts count down
    along is turned; a post far from the line is not used; a chainage_origin tag wins over the posts."""
    enu = np.array([[0.0, 100.0 * k, 0.0] for k in range(5)])  # nodes 1..5, 100 m apart northwards
    posts_enu = np.array([[5.0, 100.0, 0.0], [-4.0, 300.0, 0.0], [200.0, 200.0, 0.0]])  # beside, beside, far
    ll = FRAME.wgs84_from_enu(np.vstack([enu, posts_enu]))
    nodes = [f'<node id="{i + 1}" lat="{p[1]:.9f}" lon="{p[0]:.9f}"/>' for i, p in enumerate(ll[:5])]
    for k, (p, v) in enumerate(zip(ll[5:], (*positions, "99.0"))):
        nodes.append(f'<node id="{100 + k}" lat="{p[1]:.9f}" lon="{p[0]:.9f}"><tag k="railway" v="milestone"/>'
                     f'<tag k="railway:position" v="{v}"/></node>')
    p = tmp_path / "posts.osm"
    p.write_text(f'<osm version="0.6">{"".join(nodes)}{_way(1, [1, 2, 3, 4, 5])}</osm>')
    line = read_railways(p, FRAME).lines[0]
    assert line.properties["chainage_source"]["posts"] == ["100", "101"]
    # the posts are 200 m apart along the line and 200 m (or 200 m in miles, to 0.3 m) apart in chainage
    assert line.properties["chainage_source"]["spread_m"] < 0.3
    for k in range(2):
        assert abs(line.foot(posts_enu[k, :2]).chainage_m - expected[k]) < 0.3
    assert np.allclose(line.points_enu[0, :2], enu[-1 if turned else 0, :2], atol=1e-3)
    p.write_text(p.read_text().replace('<tag k="railway" v="rail"/>',
                                       '<tag k="railway" v="rail"/><tag k="chainage_origin" v="1000"/>'))
    line = read_railways(p, FRAME).lines[0]
    assert "chainage_source" not in line.properties and line.chainage_origin_m == 1000.0


def _line_through_pivots(project, car: dict, path) -> None:
    """Write a straight railway line (GeoJSON in the project CRS, 300 m) through a carriage's true bogie pivots."""
    from workbench.rolling_stock import get_type
    from workbench.core.track import bogie_pivots

    M = np.asarray(car["world_from_carriage"], dtype=float)
    X = bogie_pivots(get_type(car["type"])) @ M[:3, :3].T + M[:3, 3]
    u = (X[0] - X[1]) / np.linalg.norm(X[0, :2] - X[1, :2])
    enu = X[1] + np.arange(-150.0, 151.0, 5.0)[:, None] * u
    crs = project.frame.crs_from_enu(enu)
    doc = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": project.settings.location.crs}},
           "features": [{"type": "Feature", "properties": {"railway": "rail", "id": "stayed", "name": "kept"},
                         "geometry": {"type": "LineString", "coordinates": crs.tolist()}}]}
    path.write_text(json.dumps(doc))


def test_a_carriage_on_the_rails_keeps_to_the_line(solved, tmp_path):
    """A carriage marked ``on_track``: its bogie pivots are drawn to the line through their true places, its
    lateral interval shrinks and still holds the truth; the railway layer becomes an input of the solve."""
    import shutil

    from workbench.errors import SettingsError
    from workbench.pipeline import stage
    from workbench.rolling_stock import get_type
    from workbench.solve.stage import run_solve
    from workbench.core.track import bogie_pivots

    project, truth, _ = solved
    root = tmp_path / "inc"
    shutil.copytree(project.root, root)
    car = truth["carriages"][1]
    _line_through_pivots(project, car, root / "kept.geojson")
    text = (root / "project.toml").read_text()
    text = text.replace(f'railways = "{project.settings.terrain.railways}"', 'railways = "kept.geojson"')
    entry = next(ln for ln in text.splitlines() if f'number = "{car["number"]}"' in ln)
    assert entry.endswith("},")
    (root / "project.toml").write_text(with_solver_lines(text.replace(entry, entry[:-2] + ', on_track = true },'),
                                                         "track_sigma_m = 0.05"))
    p = Project(root)
    assert stage("solve").inputs(p)["railways"] == root / "kept.geojson"
    line = p.railways(heights=False).lines[0]
    before = {c.number: c for c in project.solution().posed}[car["number"]]
    run_solve(p, lambda *a, **k: None)  # the stage alone (the runner would find the consist changed upstream too)
    sol = p.solution()
    rec = next(r for r in sol.doc["track_prior"] if r["number"] == car["number"])
    assert rec["applied"] and rec["line_id"] == "stayed" and rec["sigma_m"] == 0.05
    after = {c.number: c for c in sol.posed}[car["number"]]

    def lateral(c):  # the pivots' offsets from the line, the body centre's lateral 95 % half width
        M = c.world_from_carriage
        X = bogie_pivots(get_type(car["type"])) @ M[:3, :3].T + M[:3, 3]
        cov = centre_heading_covariance(M, np.asarray(c.record["body_centre_enu"]),
                                        np.asarray(c.record["covariance_pose"]))
        b = math.radians(line.foot(X[0, :2]).bearing_deg)
        n = np.array([-math.cos(b), math.sin(b)])
        return [line.foot(x[:2]).offset_m for x in X], 1.96 * math.sqrt(n @ cov[:2, :2] @ n)

    off0, ci0 = lateral(before)
    off1, ci1 = lateral(after)
    assert max(map(abs, off1)) < 0.6 * max(map(abs, off0)) and max(map(abs, off1)) < 0.1, (off0, off1)
    assert 0.01 < ci1 < 0.8 * ci0, (ci0, ci1)
    true_centre = np.asarray(car["body_centre_enu"])
    err = np.abs(np.asarray(after.record["body_centre_enu"]) - true_centre)
    assert np.all(err <= np.asarray(after.record["ci95_body_centre_m"])), (err, after.record["ci95_body_centre_m"])
    assert "track prior for 1 carriage" in next(s["note"] for s in sol.doc["steps"] if s["name"] == "4_all")
    from workbench.report.track_table import track_table

    table = track_table(p, sol)
    rails = {r["number"]: r["rails"] for r in table["rows"]}
    assert rails.pop(car["number"]) == "held †" and table["held_sigma_m"] == 0.05
    for c in truth["carriages"]:  # the others left the rails by metres
        if c["number"] in rails:
            assert abs(c["track"]["offset_m"]) > 3 and rails[c["number"]] == "no", rails
    # bad input: on the rails without a railway layer, named with the key and the remedy
    (root / "project.toml").write_text((root / "project.toml").read_text().replace('railways = "kept.geojson"', ""))
    with pytest.raises(SettingsError, match=r"consist\[1\].on_track = true .*terrain.railways"):
        Project(root).settings
