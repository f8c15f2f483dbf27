"""Synthetic building footprints with heights, their GeoJSON form, and extruded facade meshes.

A building is a dict ``{"id": str, "footprint_crs": (k, 2) polygon in the project CRS, "height_m": float,
"base_m": ground height (project vertical datum), "kind": "house" | "apartment" | "warehouse"}``.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import shapely
import trimesh
from pyproj import CRS
from shapely.geometry import Point, Polygon
from shapely.geometry.polygon import orient

from ..core.frames import SceneFrame
from ..core.io import atomic_write_text, to_json
from ..errors import InputError
from ..files.dem import TerrainModel
from .terrain import SynthTerrain

__all__ = ["make_buildings", "write_buildings_geojson", "read_buildings_geojson", "building_meshes"]

# kind: (length range, depth range, height range) metres
_KINDS = {
    "house": ((9.0, 15.0), (7.0, 11.0), (6.0, 9.5)),
    "apartment": ((28.0, 45.0), (12.0, 16.0), (14.0, 24.0)),
    "warehouse": ((30.0, 70.0), (20.0, 38.0), (7.0, 12.0)),
}
# scenario: list of (kind, count, offset range from the train's track, along-track range)
_PLAN = {
    "embankment_river": [("house", 7, (50.0, 104.0), (-170.0, 170.0)),
                         ("apartment", 3, (122.0, 178.0), (-150.0, 150.0))],
    "cutting_curve": [("warehouse", 9, None, None)],  # inside the industrial lots
}
_MIN_R, _MAX_R = 40.0, 180.0


def _ground_height_datum(terrain: SynthTerrain, crs_xy: np.ndarray) -> np.ndarray:
    """Bilinear DEM height (datum) at project-CRS points (node-centred grid)."""
    T = terrain.transform
    z = terrain.heights
    c = (crs_xy[:, 0] - T.c) / T.a - 0.5
    r = (crs_xy[:, 1] - T.f) / T.e - 0.5
    c = np.clip(c, 0, z.shape[1] - 1.000001)
    r = np.clip(r, 0, z.shape[0] - 1.000001)
    c0, r0 = np.floor(c).astype(int), np.floor(r).astype(int)
    fc, fr = c - c0, r - r0
    return ((1 - fr) * ((1 - fc) * z[r0, c0] + fc * z[r0, c0 + 1])
            + fr * ((1 - fc) * z[r0 + 1, c0] + fc * z[r0 + 1, c0 + 1]))


def _sample_points(poly: Polygon, spacing: float) -> np.ndarray:
    minx, miny, maxx, maxy = poly.bounds
    gx, gy = np.meshgrid(np.arange(minx, maxx + spacing, spacing), np.arange(miny, maxy + spacing, spacing))
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    inside = shapely.contains_xy(poly, pts[:, 0], pts[:, 1])
    return np.vstack([np.asarray(poly.exterior.coords)[:-1], pts[inside]])


def make_buildings(scenario: str, terrain: SynthTerrain, frame: SceneFrame, *, seed: int = 0) -> list[dict]:
    """5-15 buildings 40-180 m from the origin, clear of the track bed, roads and the river."""
    if scenario not in _PLAN:
        raise ValueError(f"unknown synthetic scenario {scenario!r}; choose one of {', '.join(_PLAN)}")
    lay = terrain.layout
    if lay is None:
        raise ValueError("terrain has no curve layout; make it with workbench.synth.terrain.make_terrain")
    rng = np.random.default_rng([seed, 7919])
    f = terrain.features
    big = 1000.0
    keep_out = [Polygon(lay.band_polygon(f["bed_offset_m"] - f["bed_half_width_m"] - 6.0,
                                         f["bed_offset_m"] + f["bed_half_width_m"] + 6.0, -big, big)).buffer(0)]
    if terrain.water_polygon_enu is not None:
        keep_out.append(Polygon(terrain.water_polygon_enu).buffer(6.0))
    keep_out += [Polygon(r["polygon_enu"]).buffer(2.5) for r in f.get("roads", [])]
    dem_poly = Polygon(f["dem_polygon_enu"]).buffer(-5.0)
    placed: list[Polygon] = []
    out: list[dict] = []
    for kind, count, off_range, along_range in _PLAN[scenario]:
        (l0, l1), (d0, d1), (h0, h1) = _KINDS[kind]
        regions = [Polygon(lot).buffer(-3.0) for lot in f.get("lots", [])] if off_range is None else [None]
        n_done = 0
        for _attempt in range(400 * count):
            if n_done >= count:
                break
            L, D = rng.uniform(l0, l1), rng.uniform(d0, d1)
            if off_range is None:
                region = regions[int(rng.integers(len(regions)))]
                if region.is_empty:
                    continue
                minx, miny, maxx, maxy = region.bounds
                c = np.array([rng.uniform(minx, maxx), rng.uniform(miny, maxy)])
                off, phi = lay.offset_along(c[:1], c[1:])
                phi = float(phi[0])
            else:
                off = rng.uniform(*off_range)
                phi = rng.uniform(*along_range) / (lay.radius - off)
                c = lay.point(np.array(phi), np.array(off))
                region = None
            t = -math.sin(phi) * lay.ref + math.cos(phi) * lay.forward0
            yaw = rng.normal(0.0, math.radians(4.0))
            t = np.array([t[0] * math.cos(yaw) - t[1] * math.sin(yaw), t[0] * math.sin(yaw) + t[1] * math.cos(yaw)])
            nrm = np.array([-t[1], t[0]])
            corners = np.array([c - L / 2 * t - D / 2 * nrm, c + L / 2 * t - D / 2 * nrm,
                                c + L / 2 * t + D / 2 * nrm, c - L / 2 * t + D / 2 * nrm])
            poly = Polygon(corners)
            r = np.linalg.norm(corners, axis=1)
            if poly.distance(Point(0, 0)) < _MIN_R or r.max() > _MAX_R:
                continue
            if not dem_poly.contains(poly) or (region is not None and not region.contains(poly)):
                continue
            if any(poly.intersects(k) for k in keep_out) or any(poly.distance(q) < 6.0 for q in placed):
                continue
            placed.append(poly)
            n_done += 1
            crs_xy = frame.crs_from_enu(np.column_stack([corners, np.zeros(4)]))[:, :2]
            samples = _sample_points(poly, 1.0)
            samples_crs = frame.crs_from_enu(np.column_stack([samples, np.zeros(len(samples))]))[:, :2]
            base = float(np.min(_ground_height_datum(terrain, samples_crs)))
            out.append({"id": f"B{len(out) + 1:02d}", "kind": kind, "footprint_crs": crs_xy,
                        "height_m": round(float(rng.uniform(h0, h1)), 2), "base_m": round(base, 3)})
    return out


# ----------------------------------------------------------------------------------------------------------
# GeoJSON
# ----------------------------------------------------------------------------------------------------------
def _epsg_urn(crs: Any) -> str:
    c = CRS.from_user_input(crs)
    epsg = c.to_epsg()
    if epsg is None:
        raise ValueError(f"CRS {crs!r} has no EPSG code; the buildings GeoJSON needs one")
    return f"urn:ogc:def:crs:EPSG::{epsg}"


def write_buildings_geojson(path: str | Path, buildings: list[dict], crs: Any) -> Path:
    """GeoJSON FeatureCollection in the project CRS (a ``crs`` member with the EPSG URN), written atomically."""
    feats = []
    for b in buildings:
        ring = np.asarray(b["footprint_crs"], dtype=float)
        if not np.array_equal(ring[0], ring[-1]):
            ring = np.vstack([ring, ring[:1]])
        props = {"id": str(b["id"]), "height_m": float(b["height_m"]),
                 "base_m": None if b.get("base_m") is None else float(b["base_m"])}
        for k, v in b.items():
            if k not in ("id", "height_m", "base_m", "footprint_crs"):
                props[k] = v
        feats.append({"type": "Feature", "id": str(b["id"]), "properties": props,
                      "geometry": {"type": "Polygon", "coordinates": [np.round(ring, 4).tolist()]}})
    doc = {"type": "FeatureCollection", "name": "buildings",
           "crs": {"type": "name", "properties": {"name": _epsg_urn(crs)}}, "features": feats}
    return atomic_write_text(Path(path), to_json(doc))


def read_buildings_geojson(path: str | Path, *, expect_crs: Any = None) -> list[dict]:
    """Inverse of :func:`write_buildings_geojson`, validating every feature (InputError naming feature and file).

    ``expect_crs``: when given, the file's ``crs`` member must name the same EPSG code.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"buildings file {path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"buildings file {path} is not valid GeoJSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection" or not isinstance(doc.get("features"), list):
        raise InputError(f"buildings file {path} is not a GeoJSON FeatureCollection")
    if expect_crs is not None:
        name = ((doc.get("crs") or {}).get("properties") or {}).get("name")
        if name is None:
            raise InputError(f"buildings file {path} has no 'crs' member; it must be in {expect_crs} "
                             f"(add \"crs\": {{\"type\": \"name\", \"properties\": {{\"name\": "
                             f"\"{_epsg_urn(expect_crs)}\"}}}})")
        try:
            same = CRS.from_user_input(name).to_epsg() == CRS.from_user_input(expect_crs).to_epsg()
        except Exception:  # noqa: BLE001
            same = False
        if not same:
            raise InputError(f"buildings file {path} is in {name}, but the project CRS is {expect_crs}; "
                             f"reproject it (e.g. ogr2ogr -t_srs {expect_crs})")
    out = []
    for i, feat in enumerate(doc["features"]):
        props = (feat or {}).get("properties") or {}
        fid = str(props.get("id", (feat or {}).get("id", f"#{i}")))
        geom = (feat or {}).get("geometry") or {}
        coords = geom.get("coordinates")
        if geom.get("type") == "MultiPolygon" and coords:
            coords = coords[0]
        if geom.get("type") not in ("Polygon", "MultiPolygon") or not coords:
            raise InputError(f"buildings file {path}: feature {fid} has no polygon geometry "
                             f"(type {geom.get('type')!r})")
        try:
            ring = np.asarray(coords[0], dtype=float)[:, :2]
        except (ValueError, IndexError, TypeError):
            raise InputError(f"buildings file {path}: feature {fid} has a malformed polygon") from None
        if len(ring) > 1 and np.array_equal(ring[0], ring[-1]):
            ring = ring[:-1]
        if len(ring) < 3 or not np.all(np.isfinite(ring)) or Polygon(ring).area <= 0:
            raise InputError(f"buildings file {path}: feature {fid} has a degenerate polygon ({len(ring)} points)")
        h = props.get("height_m")
        try:
            hv = float(h)
        except (TypeError, ValueError):
            hv = float("nan")
        if not (math.isfinite(hv) and hv > 0):
            raise InputError(f"buildings file {path}: feature {fid} has height_m={h!r}; it must be a number > 0")
        base = props.get("base_m")
        if base is not None:
            try:
                base = float(base)
            except (TypeError, ValueError):
                raise InputError(f"buildings file {path}: feature {fid} has base_m={base!r}; give a number "
                                 f"or leave it out") from None
        b = {"id": fid, "footprint_crs": ring, "height_m": hv, "base_m": base}
        for k, v in props.items():
            if k not in b:
                b[k] = v
        out.append(b)
    return out


# ----------------------------------------------------------------------------------------------------------
# Meshes
# ----------------------------------------------------------------------------------------------------------
_FACADES = {
    "house": [(236, 230, 214), (190, 92, 70), (205, 200, 190), (170, 150, 120), (150, 160, 170)],
    "apartment": [(150, 90, 70), (200, 180, 150), (175, 170, 160), (130, 80, 65)],
    "warehouse": [(176, 178, 174), (200, 190, 165), (120, 135, 150), (160, 150, 140)],
}
_ROOFS = {"house": [(80, 70, 68), (120, 60, 50), (70, 72, 78)], "apartment": [(60, 60, 62), (90, 88, 85)],
          "warehouse": [(150, 152, 150), (110, 112, 115), (70, 70, 72)]}
# kind: (bay width, floor height, window u interval, window v interval)
_WINDOWS = {"house": (3.5, 2.9, (0.3, 0.7), (0.35, 0.8)), "apartment": (3.2, 3.0, (0.2, 0.8), (0.3, 0.8)),
            "warehouse": (6.0, 4.5, (0.2, 0.8), (0.62, 0.86))}
_GLASS = (52, 64, 78)
_DOOR = (72, 74, 78)


def _pick(options: list, key: str, salt: str) -> tuple:
    h = int(hashlib.sha256(f"{key}:{salt}".encode()).hexdigest()[:8], 16)
    return options[h % len(options)]


def building_meshes(buildings: list[dict], terrain_model: TerrainModel, frame: SceneFrame) -> list[trimesh.Trimesh]:
    """One mesh per building (ENU metres, vertex colours): walls from the lowest terrain under the footprint up to
    ``base_m + height_m`` (datum), with window/door bands on the facades and a flat roof."""
    out = []
    cell = float(min(abs(terrain_model.transform.a), abs(terrain_model.transform.e)))
    for b in buildings:
        ring = np.asarray(b["footprint_crs"], dtype=float)[:, :2]
        if len(ring) > 1 and np.array_equal(ring[0], ring[-1]):
            ring = ring[:-1]
        kind = str(b.get("kind", "house"))
        if kind not in _WINDOWS:
            kind = "house"
        bid = str(b["id"])
        height = float(b["height_m"])
        # Ground under the footprint (ENU up).
        enu0 = frame.enu_from_crs(np.column_stack([ring, np.zeros(len(ring))]))
        poly = orient(Polygon(enu0[:, :2]), sign=1.0)  # counter-clockwise seen from above
        samples = _sample_points(poly, max(min(cell, 2.0), 0.25))
        zg = terrain_model.height_at(samples)
        ground = float(np.nanmin(zg)) if np.any(np.isfinite(zg)) else None
        # Roof corners: exact ENU of (E, N, base + height) when base_m is known.
        if not _is_ccw(enu0[:, :2]):
            ring = ring[::-1]
        if b.get("base_m") is not None:
            top = frame.enu_from_crs(np.column_stack([ring, np.full(len(ring), float(b["base_m"]) + height)]))
            if ground is None:
                ground = float(top[:, 2].min()) - height
            if top[:, 2].min() < ground + 2.0:  # base_m far below this terrain: keep the building standing
                top[:, 2] += ground + height - top[:, 2].min()
        else:
            if ground is None:
                raise InputError(f"building {bid} lies outside the terrain and has no base_m")
            top = frame.enu_from_crs(np.column_stack([ring, np.zeros(len(ring))]))
            top[:, 2] = ground + height
        bottom_z = ground - 0.2  # sink a little so no gap shows on sloping ground
        facade = _pick(_FACADES[kind], bid, "facade")
        roof = _pick(_ROOFS[kind], bid, "roof")
        V: list[np.ndarray] = []
        C: list[tuple] = []
        bay_w, floor_h, (wu0, wu1), (wv0, wv1) = _WINDOWS[kind]
        n = len(top)
        for i in range(n):
            p0, p1 = top[i], top[(i + 1) % n]
            e = p1[:2] - p0[:2]
            length = float(np.hypot(*e))
            if length < 1e-6:
                continue
            nb = max(1, int(round(length / bay_w)))
            ub = np.unique(np.clip(np.concatenate([np.arange(nb + 1) / nb] + [(k + np.array([wu0, wu1])) / nb
                                                                               for k in range(nb)]), 0, 1))
            z_base = min(p0[2], p1[2]) - height
            nf = max(1, int((height + 1e-6) // floor_h))
            fh = height / nf
            vb = [bottom_z] + [z_base + (k + t) * fh for k in range(nf) for t in (0.0, wv0, wv1)]
            vb = np.unique(np.clip(np.array(vb + [z_base + height]), bottom_z, None))
            for a in range(len(ub) - 1):
                um = 0.5 * (ub[a] + ub[a + 1])
                bay = min(int(um * nb), nb - 1)
                in_win_u = wu0 < um * nb - bay < wu1
                xa, xb = p0[:2] + e * ub[a], p0[:2] + e * ub[a + 1]
                za_top = p0[2] + (p1[2] - p0[2]) * ub[a]
                zb_top = p0[2] + (p1[2] - p0[2]) * ub[a + 1]
                for k in range(len(vb) - 1):
                    lo, hi = vb[k], vb[k + 1]
                    vm = 0.5 * (lo + hi) - z_base
                    if lo >= z_base + height - 1e-9:
                        continue
                    floor = int(vm // fh) if vm >= 0 else -1
                    fv = vm / fh - floor
                    colour = facade
                    if floor >= 0 and in_win_u and wv0 < fv < wv1:
                        colour = _GLASS
                    if kind == "warehouse" and floor == 0 and bay % 3 == 1 and fv < 0.75 and i % 2 == 0:
                        colour = _DOOR if in_win_u else colour
                    hi_a = za_top if k == len(vb) - 2 else hi
                    hi_b = zb_top if k == len(vb) - 2 else hi
                    # counter-clockwise footprint -> outward normals with this winding
                    V.append(np.array([[xa[0], xa[1], lo], [xb[0], xb[1], lo], [xb[0], xb[1], hi_b],
                                       [xa[0], xa[1], lo], [xb[0], xb[1], hi_b], [xa[0], xa[1], hi_a]]))
                    C.extend([colour] * 6)
        # Roof (constrained triangulation of the footprint).
        tris = shapely.constrained_delaunay_triangles(Polygon(top[:, :2]))
        roof_v = []
        for tri in shapely.get_parts(tris):
            xy = np.asarray(tri.exterior.coords)[:3]
            xy = xy if _ccw(xy) else xy[::-1]
            roof_v.append(np.column_stack([xy, _roof_z(top, xy)]))
        for rv in roof_v:
            V.append(rv)
            C.extend([roof] * 3)
        verts = np.vstack(V)
        faces = np.arange(len(verts)).reshape(-1, 3)
        colours = np.column_stack([np.asarray(C, dtype=np.uint8), np.full(len(C), 255, np.uint8)])
        m = trimesh.Trimesh(vertices=verts, faces=faces, vertex_colors=colours, process=False)
        m.metadata["name"] = bid
        m.metadata["kind"] = kind
        out.append(m)
    return out


def _ccw(xy: np.ndarray) -> bool:
    a, b, c = xy[0], xy[1], xy[2]
    return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) > 0


def _is_ccw(ring: np.ndarray) -> bool:
    """Whether ``ring`` (k, 2) runs counter-clockwise (shoelace)."""
    x, y = ring[:, 0], ring[:, 1]
    return float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) > 0


def _roof_z(top: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Roof height at xy: the nearest roof corner's (corners differ by millimetres of earth curvature)."""
    d = np.linalg.norm(top[None, :, :2] - xy[:, None, :], axis=2)
    return top[np.argmin(d, axis=1), 2]
