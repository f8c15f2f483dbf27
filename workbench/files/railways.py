"""The railway layer (``terrain.railways``): the one reader and writer. Format in ``docs/gis.md``, "Railway lines".

* **GeoJSON** (``.geojson`` / ``.json``): a FeatureCollection (or one Feature, or a bare geometry) of
  ``LineString`` / ``MultiLineString`` features, coordinates ``[x, y]`` or ``[x, y, h]`` in the file's ``crs``
  member (``{"type": "name", "properties": {"name": "EPSG:32618"}}``; any CRS pyproj knows), else WGS84
  longitude, latitude (RFC 7946). A feature with a ``railway`` property other than ``rail`` is skipped, as are
  points and polygons. Properties used: ``name`` (else ``ref``), the feature's ``id`` (else ``id`` / ``@id``
  property, else ``#<index>``), ``chainage_origin`` (the chainage in metres at the line's first vertex).
* **OpenStreetMap XML** (``.osm`` / ``.xml``): ``<way>`` elements tagged ``railway=rail``, their ``<nd ref>``
  nodes' ``lat`` / ``lon``; ``name`` (else ``ref``) tag, id ``way/<id>``; a ``chainage_origin`` tag as above.
  Ways that continue one another are joined into one line (:func:`_joined_ways`). Without a ``chainage_origin``, a
  line's chainage comes from the kilometre posts beside it (``railway=milestone`` nodes with ``railway:position``).
  OSM PBF is not read: convert it (``osmium cat in.osm.pbf -o out.osm``).

Every line comes back in the scene frame (:class:`~workbench.core.track.RailwayLine`, ENU metres, converted vertex
by vertex through :func:`~workbench.core.frames.enu_from_layer_coords`). Heights: the terrain's under each vertex
when a terrain model is given (and covers it), else the file's, else the reference point's (ENU up ~ 0).

A file with no railway line is a :class:`NoRailwayLines` warning naming the file (and no layer: None); a file
that cannot be read, or an entry that is not a valid line, is an :class:`InputError` naming the file and the entry.
"""

from __future__ import annotations

import json
import logging
import math
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core.frames import SceneFrame, enu_from_layer_coords
from ..core.io import atomic_write_text, to_json
from ..core.track import RailwayLine, TrackPosition, centre_heading_covariance, reference_line, track_position
from ..errors import InputError, WorkbenchWarning

if TYPE_CHECKING:  # pragma: no cover
    from .dem import TerrainModel
    from .solution import Solution

log = logging.getLogger(__name__)

__all__ = ["RailwayLine", "RailwayLayer", "NoRailwayLines", "read_railways", "parse_railways_geojson",
           "parse_railways_osm", "parse_milestones_osm", "write_railways_geojson", "carriage_track_positions", "RAILWAY_TAGS"]

#: The ``railway`` values read as railway lines (OpenStreetMap's tag for a main-line track).
RAILWAY_TAGS = ("rail",)
_GEOJSON_SUFFIXES = (".geojson", ".json")
_OSM_SUFFIXES = (".osm", ".xml")


class NoRailwayLines(WorkbenchWarning):
    """A railway layer holds no railway line (no LineString, or no way tagged railway=rail)."""


@dataclass(frozen=True, eq=False)
class RailwayLayer:
    """A read railway layer: its ``lines`` in the scene frame, the file, its CRS, where the heights came from
    (``"terrain"``, ``"file"``, ``"none"``: the reference point's height) and how many entries were skipped."""

    path: Path
    lines: tuple[RailwayLine, ...]
    crs: str
    heights: str
    skipped: int = 0


# ----------------------------------------------------------------------------------------------------------
# GeoJSON
# ----------------------------------------------------------------------------------------------------------
def _crs_of(doc: dict, where: str) -> str:
    crs = doc.get("crs")
    if crs is None:
        return "EPSG:4326"
    name = (crs.get("properties") or {}).get("name") if isinstance(crs, dict) else None
    if not isinstance(name, str) or not name:
        raise InputError(f"{where}: 'crs' = {crs!r} is not a named CRS; give {{\"type\": \"name\", \"properties\": "
                         f"{{\"name\": \"EPSG:32618\"}}}} or leave it out for WGS84 longitude, latitude")
    return name


def _features(doc: Any, where: str) -> list[dict]:
    if not isinstance(doc, dict):
        raise InputError(f"{where}: not a GeoJSON object (a FeatureCollection of LineStrings)")
    kind = doc.get("type")
    if kind == "FeatureCollection":
        feats = doc.get("features")
        if not isinstance(feats, list):
            raise InputError(f"{where}: a FeatureCollection without a 'features' list")
        return feats
    if kind == "Feature":
        return [doc]
    if kind in ("LineString", "MultiLineString", "Point", "MultiPoint", "Polygon", "MultiPolygon",
                "GeometryCollection"):
        return [{"type": "Feature", "properties": {}, "geometry": doc}]
    raise InputError(f"{where}: 'type' = {kind!r}; a railway layer is a GeoJSON FeatureCollection of LineStrings")


def _feature_id(feat: dict, props: dict, i: int) -> str:
    for v in (feat.get("id"), props.get("id"), props.get("@id")):
        if isinstance(v, (str, int)) and not isinstance(v, bool) and str(v):
            return str(v)
    return f"#{i}"


def _positions(coords: Any, where: str) -> np.ndarray:
    """(n, 3) positions of a LineString's coordinates (NaN height where only x, y are given)."""
    if not isinstance(coords, list) or len(coords) < 2:
        n = len(coords) if isinstance(coords, list) else coords
        raise InputError(f"{where}: a line needs at least 2 positions (got {n!r})")
    out = np.full((len(coords), 3), np.nan)
    for k, c in enumerate(coords):
        ok = isinstance(c, list) and len(c) in (2, 3) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in c)
        if not ok:
            raise InputError(f"{where}: position {k} = {c!r} is not [x, y] or [x, y, h] of finite numbers")
        out[k, :len(c)] = c
    return out


def _chainage_origin(props: dict, where: str) -> float:
    v = props.get("chainage_origin", 0.0)
    if v is None:
        return 0.0
    try:
        f = float(v)
    except (TypeError, ValueError):
        f = float("nan")
    if isinstance(v, bool) or not math.isfinite(f):
        raise InputError(f"{where}: chainage_origin = {v!r} is not a number of metres (the chainage at the line's "
                         f"first vertex)")
    return f


def parse_railways_geojson(doc: Any, where: str) -> tuple[list[tuple[str, str | None, np.ndarray, float, dict]], str,
                                                               int]:
    """The railway lines of a parsed GeoJSON document, in the file's CRS: ``([(id, name, (n, 3) coordinates with NaN
    where no height, chainage origin, properties)], crs, entries skipped)``; :class:`InputError` naming ``where``
    and the entry."""
    crs = _crs_of(doc, where) if isinstance(doc, dict) else "EPSG:4326"
    lines, skipped = [], 0
    for i, feat in enumerate(_features(doc, where)):
        w = f"{where}: features[{i}]"
        if not isinstance(feat, dict) or feat.get("type") != "Feature":
            raise InputError(f"{w}: not a GeoJSON Feature")
        props = feat.get("properties") or {}
        if not isinstance(props, dict):
            raise InputError(f"{w}: 'properties' is not an object")
        fid = _feature_id(feat, props, i)
        w = f"{where}: feature {fid}"
        geom = feat.get("geometry")
        kind = geom.get("type") if isinstance(geom, dict) else None
        tag = props.get("railway")
        if kind not in ("LineString", "MultiLineString") or (tag is not None and tag not in RAILWAY_TAGS):
            if geom is not None and not isinstance(geom, dict):
                raise InputError(f"{w}: 'geometry' is not a GeoJSON geometry")
            skipped += 1
            continue
        coords = geom.get("coordinates")
        parts = [coords] if kind == "LineString" else coords
        if not isinstance(parts, list) or not parts:
            raise InputError(f"{w}: a {kind} without coordinates")
        name = props.get("name") or props.get("ref")
        origin = _chainage_origin(props, w)
        for k, part in enumerate(parts):
            pid = fid if len(parts) == 1 else f"{fid}[{k}]"
            lines.append((pid, None if name is None else str(name), _positions(part, w if len(parts) == 1 else
                                                                              f"{w}, part {k}"), origin, props))
    return lines, crs, skipped


# ----------------------------------------------------------------------------------------------------------
# OpenStreetMap XML
# ----------------------------------------------------------------------------------------------------------
def parse_railways_osm(text: str, where: str) -> tuple[list[tuple[str, str | None, np.ndarray, float, dict]], int]:
    """The ways tagged ``railway=rail`` of an OpenStreetMap XML document, in WGS84 (lon, lat, NaN):
    ``([(id, name, (n, 3), chainage origin, tags)], ways skipped)``; :class:`InputError` naming the way or node."""
    if "<!DOCTYPE" in text[:2000] or "<!ENTITY" in text[:2000]:
        raise InputError(f"{where}: an XML document type declaration; OpenStreetMap XML has none (not read)")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise InputError(f"{where}: not well-formed XML ({exc})") from None
    if root.tag != "osm":
        raise InputError(f"{where}: the root element is <{root.tag}>, not <osm>; give OpenStreetMap XML (.osm) or "
                         f"GeoJSON")
    nodes: dict[str, tuple[float, float]] = {}
    for n in root.iter("node"):
        nid = n.get("id")
        try:
            lat, lon = float(n.get("lat", "nan")), float(n.get("lon", "nan"))
        except ValueError:
            lat = lon = float("nan")
        if nid is None or not (math.isfinite(lat) and math.isfinite(lon) and abs(lat) <= 90 and abs(lon) <= 180):
            raise InputError(f"{where}: node {nid!r} has lat = {n.get('lat')!r}, lon = {n.get('lon')!r}; give "
                             f"WGS84 degrees")
        nodes[nid] = (lon, lat)
    ways, skipped = [], 0
    for way in root.iter("way"):
        wid = way.get("id")
        tags = {t.get("k"): t.get("v") for t in way.iter("tag")}
        if tags.get("railway") not in RAILWAY_TAGS:
            skipped += 1
            continue
        w = f"{where}: way {wid}"
        refs = [nd.get("ref") for nd in way.iter("nd")]
        if len(refs) < 2:
            raise InputError(f"{w}: a railway way with {len(refs)} node(s); a line needs 2 or more")
        missing = [r for r in refs if r not in nodes]
        if missing:
            raise InputError(f"{w}: node {missing[0]} is not in the file ({len(missing)} of the way's {len(refs)} "
                             f"nodes missing); export complete ways (e.g. osmium extract --strategy complete_ways)")
        ways.append(_Way(str(wid), refs, tags, _chainage_origin(tags, w)))
    lines = []
    for chain in _joined_ways(ways):
        first = chain[0][0]
        refs = list(first.refs if not chain[0][1] else first.refs[::-1])
        for way, rev in chain[1:]:
            refs += (way.refs[::-1] if rev else way.refs)[1:]
        P = np.array([[*nodes[r], np.nan] for r in refs])
        tags = dict(first.tags)
        if len(chain) > 1:
            tags["joined_ways"] = ";".join(way.id for way, _ in chain)
        lines.append((f"way/{first.id}", first.tags.get("name") or first.tags.get("ref"), P, first.origin, tags))
    return lines, skipped


@dataclass(frozen=True)
class _Way:
    id: str
    refs: list[str]
    tags: dict
    origin: float  # the chainage_origin tag at its first node (0: none)

    @property
    def line_key(self) -> str | None:
        """What makes two pieces one line: their name, else their ref (None: unnamed)."""
        return self.tags.get("name") or self.tags.get("ref")


def _joined_ways(ways: list[_Way]) -> list[list[tuple[_Way, bool]]]:
    """OpenStreetMap splits a track into ways at every bridge, level crossing or change of a tag; the pieces that
    continue one another are joined into one line: two ways meet end to end at a node that no other railway way
    touches (a switch, where three meet, ends them), with the same name (else ref; or both none), and the piece
    joined on carries no chainage origin of its own. Each chain starts at a way that has a chainage origin, else
    at a way whose start is open (kept as drawn), else at an open end (that way reversed); the ways after it are
    reversed where they run the other way, so a line's direction, and with it its chainage, is its first way's. Returns the chains as (way, reversed)
    lists, in the order of their first ways in the file."""
    touches: dict[str, int] = {}
    for w in ways:
        for r in set(w.refs):
            touches[r] = touches.get(r, 0) + 1
    ends: dict[str, list[tuple[int, int]]] = {}  # node -> [(way index, 0 start / 1 end)]
    for i, w in enumerate(ways):
        if w.refs[0] != w.refs[-1]:  # a closed way (a loop) is a line of its own
            for side, r in ((0, w.refs[0]), (1, w.refs[-1])):
                ends.setdefault(r, []).append((i, side))
    link: dict[tuple[int, int], tuple[int, int]] = {}
    for r, at in ends.items():
        if len(at) != 2 or touches.get(r, 0) != 2:
            continue
        (i, si), (j, sj) = at
        a, b = ways[i], ways[j]
        if i == j or a.line_key != b.line_key:
            continue
        # a piece with its own chainage origin starts a line: nothing is joined before its first node
        if (si == 0 and a.tags.get("chainage_origin") is not None) or (sj == 0 and b.tags.get("chainage_origin")
                                                                       is not None):
            continue
        link[(i, si)], link[(j, sj)] = (j, sj), (i, si)
    used, chains = set(), []
    n = len(ways)
    starts = [i for i, w in enumerate(ways) if w.tags.get("chainage_origin") is not None]
    starts += [i for i in range(n) if (i, 0) not in link]  # an open start: the line begins there, as drawn
    starts += [i for i in range(n) if (i, 1) not in link]  # an open end only: the line begins there, reversed
    starts += list(range(n))  # what is left: closed chains, broken at their first way
    for s in starts:
        if s in used:
            continue
        rev = (s, 0) in link and (s, 1) not in link
        chain, i = [], s
        while i not in used:
            used.add(i)
            chain.append((ways[i], rev))
            nxt = link.get((i, 0 if rev else 1))
            if nxt is None:
                break
            i, side = nxt
            rev = side == 1  # entered at its end: it runs the other way
        chains.append(chain)
    order = {id(w): k for k, w in enumerate(ways)}
    return sorted(chains, key=lambda c: min(order[id(w)] for w, _ in c))


# ----------------------------------------------------------------------------------------------------------
# The reader
# ----------------------------------------------------------------------------------------------------------
def _enu_line(lid: str, name: str | None, coords: np.ndarray, origin: float, props: dict, crs: str,
              frame: SceneFrame, where: str) -> RailwayLine:
    has_h = bool(np.all(np.isfinite(coords[:, 2])))
    P = coords.copy()
    if not has_h:
        P[:, 2] = frame.height_m
    enu = enu_from_layer_coords(P, crs, frame, f"{where}: line {lid}")
    far = float(np.max(np.linalg.norm(enu[:, :2], axis=1)))
    if far > 50_000.0:
        raise InputError(f"{where}: line {lid} reaches {far / 1000:.0f} km from the incident's reference point; a "
                         f"wrong 'crs' or swapped coordinates? (GeoJSON positions are [longitude, latitude])")
    keep = np.concatenate([[True], np.linalg.norm(np.diff(enu[:, :2], axis=0), axis=1) > 1e-6])
    enu = enu[keep]  # repeated vertices
    if len(enu) < 2:
        raise InputError(f"{where}: line {lid} has all its vertices at one place")
    return RailwayLine(lid, name, enu, origin, {k: v for k, v in props.items() if isinstance(k, str)})


#: A kilometre post counts for a line when it stands within this distance of it (m): beside the track.
POST_MAX_OFFSET_M = 25.0
#: Posts whose chainages disagree with the line's length by more than this (m) are warned about.
POST_MAX_SPREAD_M = 50.0


def parse_milestones_osm(text: str, where: str) -> list[tuple[str, float, float, float]]:
    """The kilometre posts of an OpenStreetMap XML document: nodes tagged ``railway=milestone`` with a
    ``railway:position`` (kilometres, ``12.3``; miles with ``mi:``, ``mi:7.25``; a decimal comma read as a point),
    as ``(node id, lon, lat, position in metres)``; a post whose position does not read is skipped with a
    warning naming it."""
    root = ET.fromstring(text)  # parse_railways_osm has checked the document
    out = []
    for n in root.iter("node"):
        tags = {t.get("k"): t.get("v") for t in n.iter("tag")}
        if tags.get("railway") != "milestone" or tags.get("railway:position") is None:
            continue
        v = str(tags["railway:position"]).strip().replace(",", ".")
        unit = 1000.0
        if v.lower().startswith("mi:"):
            v, unit = v[3:].strip(), 1609.344
        try:
            pos = float(v) * unit
        except ValueError:
            log.warning("%s: node %s: railway:position = %r is not a number of kilometres (or mi:<miles>); "
                        "post not used", where, n.get("id"), tags["railway:position"])
            continue
        if math.isfinite(pos):
            out.append((str(n.get("id")), float(n.get("lon")), float(n.get("lat")), pos))
    return out


def _chainage_from_posts(line: RailwayLine, posts: list[tuple[str, float, float, float]], frame: SceneFrame,
                         where: str) -> RailwayLine:
    """The line's chainage from the kilometre posts beside it (within :data:`POST_MAX_OFFSET_M`), where the
    layer gives it no ``chainage_origin``: the origin that puts the posts at their positions (the median over the
    posts), the line reversed first when the posts count down along it (chainage grows along a line). Recorded in
    its properties as ``chainage_source``; posts that disagree by more than :data:`POST_MAX_SPREAD_M` with one
    another (a chainage jump, a misplaced post) are warned about."""
    if not posts or "chainage_origin" in line.properties:
        return line
    ll = np.array([[lon, lat, frame.height_m] for _, lon, lat, _ in posts])
    enu = enu_from_layer_coords(ll, "EPSG:4326", frame, f"{where}: kilometre posts")
    feet = [line.foot(p[:2]) for p in enu]
    near = [(pid, pos, f) for (pid, _, _, pos), f in zip(posts, feet)
            if abs(f.offset_m) <= POST_MAX_OFFSET_M and not f.beyond_end]
    if not near:
        return line
    along = np.array([f.chainage_m - line.chainage_origin_m for _, _, f in near])
    pos = np.array([p for _, p, _ in near])
    P = line.points_enu
    if len(near) >= 2 and np.polyfit(along, pos, 1)[0] < 0:  # the posts count down along the line: turn it
        total = float(np.sum(np.linalg.norm(np.diff(P[:, :2], axis=0), axis=1)))
        P, along = P[::-1].copy(), total - along
    origin = float(np.median(pos - along))
    spread = float(np.max(np.abs(pos - along - origin)))
    if spread > POST_MAX_SPREAD_M:
        log.warning("%s: line %s: its %d kilometre posts disagree with its length by up to %.0f m (a chainage jump "
                    "or a misplaced post); chainage from their median", where, line.id, len(near), spread)
    source = {"posts": [pid for pid, _, _ in near], "spread_m": round(spread, 2)}
    return RailwayLine(line.id, line.name, P, origin, {**line.properties, "chainage_source": source})


def _drape(lines: list[RailwayLine], terrain: "TerrainModel") -> tuple[list[RailwayLine], bool]:
    out, any_dem = [], False
    for ln in lines:
        z = terrain.height_at(ln.points_enu[:, :2])
        ok = np.isfinite(z)
        any_dem |= bool(ok.any())
        P = ln.points_enu.copy()
        P[ok, 2] = z[ok]
        out.append(RailwayLine(ln.id, ln.name, P, ln.chainage_origin_m, ln.properties))
    return out, any_dem


def read_railways(path: str | Path, frame: SceneFrame, *, terrain: "TerrainModel | None" = None
                  ) -> RailwayLayer | None:
    """Read a railway layer (GeoJSON or OpenStreetMap XML, by suffix, else by content) into the scene frame.

    None, with a :class:`NoRailwayLines` warning naming the file, when it holds no railway line."""
    path = Path(path)
    where = f"railway layer {path}"
    suffix = path.suffix.lower()
    if suffix == ".pbf" or path.name.lower().endswith(".osm.pbf"):
        raise InputError(f"{where}: OpenStreetMap PBF is not read; convert it to XML (osmium cat {path.name} -o "
                         f"{path.stem.removesuffix('.osm')}.osm) or GeoJSON (ogr2ogr -f GeoJSON out.geojson "
                         f"{path.name} lines)")
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{where}: does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{where}: cannot be read as UTF-8 text ({exc})") from None
    is_osm = suffix in _OSM_SUFFIXES or (suffix not in _GEOJSON_SUFFIXES and text.lstrip().startswith("<"))
    if is_osm:
        raw, skipped = parse_railways_osm(text, where)
        crs = "EPSG:4326"
    else:
        try:
            doc = json.loads(text)
        except (json.JSONDecodeError, RecursionError) as exc:
            raise InputError(f"{where}: not valid JSON ({exc}); a railway layer is GeoJSON or OpenStreetMap XML "
                             f"(.osm)") from None
        raw, crs, skipped = parse_railways_geojson(doc, where)
    if not raw:
        what = "no way tagged railway=rail" if is_osm else "no LineString or MultiLineString feature (railway=rail)"
        msg = f"{where}: {what} in it ({skipped} other entries skipped); no railway lines are drawn or reported"
        log.warning(msg)
        warnings.warn(msg, NoRailwayLines, stacklevel=2)
        return None
    lines = [_enu_line(*r, crs, frame, where) for r in raw]
    if is_osm:
        lines = [_chainage_from_posts(ln, parse_milestones_osm(text, where), frame, where) for ln in lines]
    heights = "file" if all(np.all(np.isfinite(r[2][:, 2])) for r in raw) else "none"
    if terrain is not None:
        lines, draped = _drape(lines, terrain)
        heights = "terrain" if draped else heights
    return RailwayLayer(path, tuple(lines), crs, heights, skipped)


def write_railways_geojson(path: str | Path, lines: list[dict], crs: str, *, decimals: int = 4) -> Path:
    """A railway layer as GeoJSON in ``crs`` (a ``crs`` member naming it), written atomically. ``lines``: dicts with
    ``id``, ``coords`` ((n, 2) or (n, 3) in ``crs``) and optional ``name`` and further properties."""
    feats = []
    for ln in lines:
        props = {"railway": "rail", **{k: v for k, v in ln.items() if k not in ("coords",)}}
        coords = np.round(np.asarray(ln["coords"], dtype=float), decimals).tolist()
        feats.append({"type": "Feature", "id": str(ln["id"]), "properties": props,
                      "geometry": {"type": "LineString", "coordinates": coords}})
    doc = {"type": "FeatureCollection", "name": "railways", "crs": {"type": "name", "properties": {"name": crs}},
           "features": feats}
    return atomic_write_text(Path(path), to_json(doc))


# ----------------------------------------------------------------------------------------------------------
# The carriages of a solution on the layer
# ----------------------------------------------------------------------------------------------------------
def _cov_enh(c: Any, centre: np.ndarray, q: float) -> np.ndarray | None:
    """(east, north, heading) covariance of a solved carriage: from its pose covariance, else its sigmas (or 95 %
    half widths / q) taken as independent, else None."""
    cov = c.record.get("covariance_pose")
    if cov is not None:
        try:
            C = np.asarray(cov, dtype=float)
        except (TypeError, ValueError):
            C = None
        if C is not None and C.shape == (6, 6) and np.all(np.isfinite(C)):
            return centre_heading_covariance(c.world_from_carriage, centre, C)
    sb, sh = c.floats("sigma_body_centre_m"), c.floats("sigma_hpr_deg")
    if sb is None or sh is None:
        cb, ch = c.floats("ci95_body_centre_m"), c.floats("ci95_hpr_deg")
        if cb is None or ch is None:
            return None
        sb, sh = [x / q for x in cb], [x / q for x in ch]
    return np.diag([sb[0] ** 2, sb[1] ** 2, sh[0] ** 2])


def carriage_track_positions(solution: "Solution", layer: RailwayLayer | None) -> dict[str, TrackPosition]:
    """``{car number: TrackPosition}`` of every posed carriage of a read solution on the layer's reference line
    (the line nearest the consist: :func:`~workbench.core.track.reference_line`), with the uncertainty of the
    body centre and heading propagated; {} without a layer or a posed carriage."""
    from ..core.frames import hpr_from_rotation

    if layer is None or not layer.lines or not solution.posed:
        return {}
    q = solution.doc.get("ci95_factor")
    q = float(q) if isinstance(q, (int, float)) and not isinstance(q, bool) and math.isfinite(q) and q > 0 else 1.96
    cars = []
    for c in solution.posed:
        M = c.world_from_carriage
        given = c.floats("body_centre_enu")
        centre = np.asarray(given, dtype=float) if given is not None and len(given) == 3 else M[:3, 3]
        cars.append((c, centre, hpr_from_rotation(M[:3, :3])[0]))
    line = reference_line(layer.lines, np.array([x[1][:2] for x in cars]))
    return {c.number: track_position(line, centre[:2], heading, _cov_enh(c, centre, q), ci95_factor=q)
            for c, centre, heading in cars}
