"""Synthetic building footprints with heights, their GeoJSON form, and extruded facade meshes.

A building is a dict ``{"id": str, "footprint_crs": (k, 2) polygon in the project CRS, "height_m": float,
"base_m": ground height (project vertical datum), "kind": "house" | "apartment" | "warehouse"}``.
"""

from __future__ import annotations

import math

import numpy as np
from shapely.geometry import Point, Polygon

from ..core.frames import SceneFrame
from ..terrain.extrude import sample_points
from .terrain import SynthTerrain

__all__ = ["make_buildings"]

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
            samples = sample_points(poly, 1.0)
            samples_crs = frame.crs_from_enu(np.column_stack([samples, np.zeros(len(samples))]))[:, :2]
            base = float(np.min(_ground_height_datum(terrain, samples_crs)))
            out.append({"id": f"B{len(out) + 1:02d}", "kind": kind, "footprint_crs": crs_xy,
                        "height_m": round(float(rng.uniform(h0, h1)), 2), "base_m": round(base, 3)})
    return out
