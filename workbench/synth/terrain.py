"""Synthetic DEMs with ground truth for synthetic incidents.

Two scenarios, deterministic for a seed, the DEM square and north-up in the project CRS and centred on the ENU origin
(which lies on the track the train ran on, at top-of-rail height when the frame comes from :func:`scenario_frame`):

* ``"embankment_river"`` - modelled on Spuyten Duyvil, Bronx (NY), 1 Dec 2013: a single track on a 2.5 m embankment
  (8 m crest, 1:2 side slopes) following a left-hand curve (radius 500 m, southbound) along a river bank; the river
  (hydro-flattened water surface 1.5 m below the embankment toe) on the outside of the curve, flat-ish ground rising
  gently on the inside to a hillside about 30 m high.
* ``"cutting_curve"`` - modelled on Frankford Junction, Philadelphia (PA), 12 May 2015: three tracks on a 270 m
  radius left-hand curve (north-eastbound) at the bottom of a shallow cutting (3.2 m on the outside, 1.6 m on the
  inside, 1:2 slopes) between level, gently undulating industrial ground.

Heights are in the project's vertical datum; the track bed is exactly smooth (a constant grade along the curve, no
cross-fall); natural ground carries a few centimetres to decimetres of smooth noise. The texture is an
orthophoto-like image over exactly the DEM's extent (row 0 = north edge) that :meth:`TerrainModel.mesh` drapes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import affine
import cv2
import numpy as np
import rasterio
from PIL import Image
from shapely.geometry import Polygon

from ..core.frames import SceneFrame
from ..core.io import atomic_write

__all__ = ["SynthTerrain", "make_terrain", "write_dem_geotiff", "dem_error", "scenario_frame", "SCENARIOS",
           "SCENARIO_SITES", "TOP_OF_RAIL_ABOVE_BED_M", "RAIL_HALF_GAUGE_M"]

#: Top of rail above the DEM surface of the ballast bed (rail 172 mm on sleepers flush with the ballast).
TOP_OF_RAIL_ABOVE_BED_M = 0.2
#: Half the distance between rail centres (standard gauge 1435 mm + rail head 72 mm).
RAIL_HALF_GAUGE_M = 0.7535
_RAIL_HEAD_M = 0.072
_SLEEPER_HALF_LENGTH_M = 1.3
_SLEEPER_SPACING_M = 0.6
_SLEEPER_WIDTH_M = 0.26

SCENARIOS = ("embankment_river", "cutting_curve")

#: Real-world reference points of the scenarios (the ENU origin; height = top of rail there in the synthetic DEM).
SCENARIO_SITES: dict[str, dict[str, Any]] = {
    "embankment_river": {"crs": "EPSG:32618", "lat": 40.87800, "lon": -73.92260, "height_m": 4.2,
                         "label": "Spuyten Duyvil, Bronx NY, 1 Dec 2013"},
    "cutting_curve": {"crs": "EPSG:32618", "lat": 40.00160, "lon": -75.08550, "height_m": 12.2,
                      "label": "Frankford Junction, Philadelphia PA, 12 May 2015"},
}

# Scenario parameters (ENU metres, datum heights). Offsets are signed: positive to the LEFT of the direction of
# travel (towards the centre of the left-hand curve), measured from the train's track.
_PARAMS: dict[str, dict[str, Any]] = {
    "embankment_river": {
        "radius": 500.0, "bearing": 150.0, "track_offsets": [0.0], "bed_offset": 0.0, "bed_half_width": 4.0,
        "bed_h0": 4.0, "grade": 0.002, "emb_height": 2.5, "water_h": 0.0,
        # roads: (offset of centre line, width, kind)
        "roads": [(42.0, 7.0, "road"), (112.0, 6.0, "road"), (13.5, 2.5, "path")],
    },
    "cutting_curve": {
        "radius": 270.0, "bearing": 60.0, "track_offsets": [0.0, 4.4, 8.8], "bed_offset": 4.4, "bed_half_width": 8.0,
        "bed_h0": 12.0, "grade": 0.003, "cut_out": 3.2, "cut_in": 1.6,
        "roads": [(-36.0, 9.0, "road"), (38.0, 8.0, "road")],
        # cross streets: (along-track position at the road, from offset, to offset, width)
        "cross_roads": [(60.0, -40.0, -260.0, 8.0), (-95.0, 42.0, 260.0, 8.0)],
        # industrial lots (paved yards): (offset0, offset1, along0, along1) in curvilinear metres
        "lots": [(-48.0, -190.0, -175.0, -8.0), (-48.0, -190.0, 8.0, 52.0), (-48.0, -190.0, 68.0, 175.0),
                 (48.0, 170.0, -170.0, -103.0), (48.0, 170.0, -87.0, 60.0)],
    },
}


def scenario_frame(scenario: str) -> SceneFrame:
    """The scene frame of a scenario at its real-world site (origin on the track, at top of rail)."""
    site = _site(scenario)
    return SceneFrame(site["crs"], site["lat"], site["lon"], site["height_m"])


def _site(scenario: str) -> dict[str, Any]:
    if scenario not in SCENARIO_SITES:
        raise ValueError(f"unknown synthetic terrain scenario {scenario!r}; choose one of {', '.join(SCENARIOS)}")
    return SCENARIO_SITES[scenario]


# ----------------------------------------------------------------------------------------------------------
# Geometry: a circular left-hand curve through the origin
# ----------------------------------------------------------------------------------------------------------
class CurveLayout:
    """A left-hand circular curve of ``radius`` through the ENU origin with travel bearing ``bearing_deg`` there.

    ``offset_along(x, y)`` gives (offset, phi): offset positive to the left (towards the centre), phi the angle
    travelled from the origin (radians, positive forwards). Arc length on the train's track = radius * phi; at an
    offset ``o`` the local along-track metres are ``(radius - o) * phi``.
    """

    def __init__(self, radius: float, bearing_deg: float) -> None:
        self.radius = float(radius)
        self.bearing_deg = float(bearing_deg)
        b = math.radians(bearing_deg)
        self.forward0 = np.array([math.sin(b), math.cos(b)])
        self.left0 = np.array([-math.cos(b), math.sin(b)])
        self.centre = self.radius * self.left0
        self.ref = -self.left0  # direction from the centre to the origin

    def offset_along(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x)
        dt = x.dtype.type if x.dtype in (np.float32, np.float64) else np.float64  # float32 stays float32
        rx = x - dt(self.centre[0])
        ry = np.asarray(y) - dt(self.centre[1])
        r = np.hypot(rx, ry)
        cross = dt(self.ref[0]) * ry - dt(self.ref[1]) * rx
        dot = dt(self.ref[0]) * rx + dt(self.ref[1]) * ry
        return dt(self.radius) - r, np.arctan2(cross, dot)

    def offset(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The offset of :meth:`offset_along` alone (the same arithmetic, without the angle: a texture's every
        pixel needs the offset, few the angle)."""
        x = np.asarray(x)
        dt = x.dtype.type if x.dtype in (np.float32, np.float64) else np.float64
        return dt(self.radius) - np.hypot(x - dt(self.centre[0]), np.asarray(y) - dt(self.centre[1]))

    def point(self, phi: np.ndarray, offset: np.ndarray | float = 0.0) -> np.ndarray:
        phi = np.asarray(phi, dtype=float)
        u = np.cos(phi)[..., None] * self.ref + np.sin(phi)[..., None] * self.forward0
        return self.centre + (self.radius - np.asarray(offset, dtype=float))[..., None] * u

    def band_polygon(self, off0: float, off1: float, along0: float, along1: float, step_m: float = 2.0) -> np.ndarray:
        """ENU polygon (k, 2) of the curvilinear rectangle offset in [off0, off1], local along in [along0, along1]
        (along measured on the offset-``off0`` line)."""
        r0 = self.radius - off0
        phis = np.linspace(along0 / r0, along1 / r0, max(int(abs(along1 - along0) / step_m), 2) + 1)
        a = self.point(phis, np.full_like(phis, off0))
        b = self.point(phis[::-1], np.full_like(phis, off1))
        return np.vstack([a, b])


# ----------------------------------------------------------------------------------------------------------
# Result
# ----------------------------------------------------------------------------------------------------------
@dataclass
class SynthTerrain:
    heights: np.ndarray  # (rows, cols) float32, metres (the project's vertical datum)
    transform: affine.Affine  # rasterio transform in the project CRS (north-up)
    crs: str  # e.g. "EPSG:32618"
    track_enu: np.ndarray  # (n, 3) the train's track centreline in ENU (top of rail), in the direction of travel
    water_polygon_enu: np.ndarray | None  # (m, 2) river outline in ENU if any
    texture: Image.Image  # orthophoto-like texture over the whole DEM (row 0 = north edge)
    scenario: str = ""
    tracks_enu: list[np.ndarray] = field(default_factory=list)  # every track's centreline (top of rail), ENU
    layout: CurveLayout | None = None
    features: dict[str, Any] = field(default_factory=dict)  # roads, lots, bed geometry (ENU polygons / metres)

    @property
    def bounds_crs(self) -> tuple[float, float, float, float]:
        """(left, bottom, right, top) of the DEM (cell edges) in the project CRS = the texture's extent."""
        rows, cols = self.heights.shape
        T = self.transform
        return (T.c, T.f + T.e * rows, T.c + T.a * cols, T.f)

    def track_bed_polygon_enu(self) -> np.ndarray:
        """ENU polygon of the whole track bed (all tracks with their ballast shoulders)."""
        f = self.features
        assert self.layout is not None
        o, w = f["bed_offset_m"], f["bed_half_width_m"]
        half = 0.5 * float(np.ptp(np.array(self.bounds_crs).reshape(2, 2), axis=0).max()) * 1.5
        return self.layout.band_polygon(o - w, o + w, -half, half)


# ----------------------------------------------------------------------------------------------------------
# Noise helpers
# ----------------------------------------------------------------------------------------------------------
def _value_noise(rng: np.random.Generator, shape: tuple[int, int], cell_px: float) -> np.ndarray:
    """Smooth noise with unit-ish standard deviation and feature size ``cell_px`` pixels (float32)."""
    h, w = shape
    gh = max(int(math.ceil(h / cell_px)) + 3, 4)
    gw = max(int(math.ceil(w / cell_px)) + 3, 4)
    g = rng.standard_normal((gh, gw)).astype(np.float32)
    big = cv2.resize(g, (int(round(gw * cell_px)), int(round(gh * cell_px))), interpolation=cv2.INTER_CUBIC)
    oy = int(cell_px)
    ox = int(cell_px)
    out = big[oy:oy + h, ox:ox + w]
    if out.shape != (h, w):  # tiny grids
        out = cv2.resize(g, (w, h), interpolation=cv2.INTER_CUBIC)
    s = float(out.std()) or 1.0
    return (out / s).astype(np.float32)


# feature size (m) of a DEM's vertical error in :func:`dem_error`: the generated terrain's own largest undulations
DEM_ERROR_FEATURE_M = 30.0


def dem_error(rng: np.random.Generator, shape: tuple[int, int], resolution_m: float, sd_m: float,
              feature_m: float = DEM_ERROR_FEATURE_M) -> np.ndarray:
    """A DEM's vertical error (``shape`` grid of ``resolution_m`` cells, float64 m): smooth noise with features of
    ``feature_m`` (neighbouring carriages share much of it, as they share a real DEM's), its mean over the grid
    zero and its standard deviation ``sd_m`` (the accuracy a DEM states). The generator writes the terrain it
    rendered, exact; the calibration benchmark adds this to give a contact the error it believes."""
    if not (sd_m >= 0 and resolution_m > 0 and feature_m > 0):
        raise ValueError(f"sd_m={sd_m}, resolution_m={resolution_m}, feature_m={feature_m}: need sd_m >= 0 and "
                         "positive sizes")
    e = _value_noise(rng, shape, feature_m / resolution_m).astype(np.float64)
    e -= e.mean()
    s = float(e.std())
    return e * (sd_m / s) if s > 0 else e


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _band(d: np.ndarray, half_width: float, px: float) -> np.ndarray:
    """Antialiased coverage (0..1) of a band |d| <= half_width for pixels of size px."""
    return np.clip(0.5 + (half_width - np.abs(d)) / px, 0.0, 1.0)


# ----------------------------------------------------------------------------------------------------------
# Heights
# ----------------------------------------------------------------------------------------------------------
def _bed_height(p: dict, s: np.ndarray) -> np.ndarray:
    return p["bed_h0"] + p["grade"] * s


def _heights(scenario: str, p: dict, lay: CurveLayout, x: np.ndarray, y: np.ndarray, noise: np.ndarray,
             with_noise: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Datum heights at ENU (x, y) and a boolean water mask."""
    off, phi = lay.offset_along(x, y)
    s = lay.radius * phi
    bed = _bed_height(p, s)
    sl = (lay.radius - off) * phi
    road_flat = np.zeros_like(off)
    for ro, rw, _kind in p.get("roads", []):
        road_flat = np.maximum(road_flat, _smoothstep((rw / 2 + 2.0 - np.abs(off - ro)) / 2.0))
    if scenario == "embankment_river":
        crest = p["bed_half_width"]
        toe = bed - p["emb_height"]
        emb = bed - np.maximum(np.abs(off) - crest, 0.0) / 2.0
        a = -off
        wo = 24.0 + 3.0 * np.sin(sl / 37.0) + 2.0 * np.sin(sl / 91.0 + 1.0)
        bank0 = crest + 2 * p["emb_height"] + 2.0
        river_g = toe - (toe - p["water_h"]) * _smoothstep((a - bank0) / (wo - bank0))
        hill_start = 75.0 + 15.0 * np.sin(sl / 70.0)
        land_g = toe + 0.012 * np.maximum(off - 9.0, 0.0) + 28.0 * _smoothstep((off - hill_start) / 120.0)
        land_g += 1.5 * np.sin(sl / 45.0) * _smoothstep((off - hill_start) / 60.0)
        g = np.where(off < 0, river_g, land_g)
        water = a >= wo
        mask = _smoothstep((np.abs(off) - crest - 6.0) / 8.0) * np.where(off < 0, _smoothstep((wo - a) / 4.0), 1.0)
        mask = mask * (1.0 - 0.8 * road_flat)
        if with_noise:
            g = g + noise * mask
        z = np.maximum(np.maximum(g, emb), p["water_h"] + 0.05)  # dry land stays above the water surface
        z = np.where(water, p["water_h"], z)
        return z, water
    if scenario == "cutting_curve":
        oc, w = p["bed_offset"], p["bed_half_width"]
        dist = np.abs(off - oc) - w
        cut = bed + np.maximum(dist, 0.0) / 2.0
        g = bed + p["cut_out"] - (p["cut_out"] - p["cut_in"]) * _smoothstep((off - oc + 6.0) / 12.0)
        g = g + 0.7 * np.sin(2 * np.pi * x / 310.0 + 0.5) * np.cos(2 * np.pi * y / 270.0) \
            + 0.4 * np.sin(2 * np.pi * (x + y) / 190.0)
        mask = _smoothstep((dist - 2.0) / 8.0) * (1.0 - 0.8 * road_flat)
        if with_noise:
            g = g + noise * mask
        z = np.minimum(g, cut)
        return z, np.zeros_like(z, dtype=bool)
    raise ValueError(f"unknown synthetic terrain scenario {scenario!r}; choose one of {', '.join(SCENARIOS)}")


# ----------------------------------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------------------------------
def make_terrain(scenario: str, frame: SceneFrame, *, size_m: float = 400.0, resolution_m: float = 1.0,
                 seed: int = 0, texture_px_per_m: float = 8.0) -> SynthTerrain:
    """Synthetic DEM (``size_m`` square, ``resolution_m`` cells, in ``frame.crs``, centred on the ENU origin),
    the track(s), the river and an orthophoto-like texture (``texture_px_per_m``, at most 4096 px a side)."""
    if scenario not in _PARAMS:
        raise ValueError(f"unknown synthetic terrain scenario {scenario!r}; choose one of {', '.join(SCENARIOS)}")
    if not (size_m > 0 and resolution_m > 0 and size_m / resolution_m >= 4):
        raise ValueError(f"size_m={size_m}, resolution_m={resolution_m}: need a positive size of at least 4 cells")
    p = _PARAMS[scenario]
    lay = CurveLayout(p["radius"], p["bearing"])
    rng = np.random.default_rng(seed)
    n = int(round(size_m / resolution_m))
    size = n * resolution_m
    o = frame.origin_crs
    T = affine.Affine(resolution_m, 0.0, o[0] - size / 2, 0.0, -resolution_m, o[1] + size / 2)

    # Grid nodes -> ENU (exact; the horizontal position barely depends on the height, use the origin's).
    cc, rr = np.meshgrid(np.arange(n) + 0.5, np.arange(n) + 0.5)
    E = T.c + T.a * cc
    N = T.f + T.e * rr
    enu = frame.enu_from_crs(np.column_stack([E.ravel(), N.ravel(), np.full(E.size, frame.height_m)]))
    x = enu[:, 0].reshape(n, n)
    y = enu[:, 1].reshape(n, n)
    noise = (0.12 * _value_noise(rng, (n, n), 30.0 / resolution_m)
             + 0.04 * _value_noise(rng, (n, n), 7.0 / resolution_m)
             + 0.015 * _value_noise(rng, (n, n), max(2.0 / resolution_m, 1.0)))
    z, _ = _heights(scenario, p, lay, x, y, noise)
    heights = z.astype(np.float32)

    # Tracks (top of rail), in the direction of travel, inside the DEM with a margin.
    tracks = []
    crs_bounds = (T.c, T.f - size, T.c + size, T.f)
    margin = 3.0 * resolution_m
    for toff in p["track_offsets"]:
        tracks.append(_track_line(frame, lay, p, toff, crs_bounds, margin))
    # Water.
    water_poly = None
    features: dict[str, Any] = {
        "bed_offset_m": p["bed_offset"], "bed_half_width_m": p["bed_half_width"],
        "track_offsets_m": list(p["track_offsets"]), "radius_m": p["radius"], "bearing_deg": p["bearing"],
        "roads": [], "lots": [],
    }
    corners_crs = np.array([[crs_bounds[0], crs_bounds[1]], [crs_bounds[2], crs_bounds[1]],
                            [crs_bounds[2], crs_bounds[3]], [crs_bounds[0], crs_bounds[3]]])
    dem_poly = Polygon(frame.enu_from_crs(np.column_stack([corners_crs, np.full(4, frame.height_m)]))[:, :2])
    features["dem_polygon_enu"] = np.asarray(dem_poly.exterior.coords)[:-1]
    big = size * 1.6
    if scenario == "embankment_river":
        phis = np.linspace(-big / lay.radius, big / lay.radius, 801)
        sl = (lay.radius) * phis
        wo = 24.0 + 3.0 * np.sin(sl / 37.0) + 2.0 * np.sin(sl / 91.0 + 1.0)
        # the river edge uses local along at its own offset; iterate once for consistency with _heights
        sl = (lay.radius + wo) * phis
        wo = 24.0 + 3.0 * np.sin(sl / 37.0) + 2.0 * np.sin(sl / 91.0 + 1.0)
        edge = lay.point(phis, -wo)
        far = lay.point(phis[::-1], np.full_like(phis, -(big + 50.0)))
        river = Polygon(np.vstack([edge, far])).buffer(0).intersection(dem_poly)
        if not river.is_empty:
            if river.geom_type != "Polygon":
                river = max(river.geoms, key=lambda g: g.area)
            water_poly = np.asarray(river.exterior.coords)[:-1]
    for ro, rw, kind in p.get("roads", []):
        poly = Polygon(lay.band_polygon(ro - rw / 2, ro + rw / 2, -big, big)).buffer(0).intersection(dem_poly)
        if not poly.is_empty:
            features["roads"].append({"kind": kind, "polygon_enu": _largest(poly), "offset_m": ro, "width_m": rw})
    for s0, o0, o1, rw in p.get("cross_roads", []):
        phi0 = s0 / lay.radius
        a = lay.point(np.array([phi0, phi0]), np.array([o0, o1]))
        d = (a[1] - a[0]) / np.linalg.norm(a[1] - a[0])
        nrm = np.array([-d[1], d[0]]) * rw / 2
        poly = Polygon([a[0] - nrm, a[1] - nrm, a[1] + nrm, a[0] + nrm]).intersection(dem_poly)
        if not poly.is_empty:
            features["roads"].append({"kind": "road", "polygon_enu": _largest(poly), "width_m": rw})
    for o0, o1, a0, a1 in p.get("lots", []):
        poly = Polygon(lay.band_polygon(o0, o1, a0 * (lay.radius - o0) / lay.radius,
                                        a1 * (lay.radius - o0) / lay.radius)).buffer(0)
        for r in features["roads"]:
            poly = poly.difference(Polygon(r["polygon_enu"]).buffer(3.0))
        poly = poly.intersection(dem_poly.buffer(-2.0))
        if not poly.is_empty and poly.area > 200:
            features["lots"].append(_largest(poly))

    terrain = SynthTerrain(heights=heights, transform=T, crs=_crs_string(frame), track_enu=tracks[0],
                           water_polygon_enu=water_poly, texture=Image.new("RGB", (1, 1)), scenario=scenario,
                           tracks_enu=tracks, layout=lay, features=features)
    terrain.texture = _make_texture(scenario, p, lay, frame, terrain, rng, texture_px_per_m)
    return terrain


def _largest(geom) -> np.ndarray:
    if geom.geom_type != "Polygon":
        geom = max(geom.geoms, key=lambda g: g.area)
    return np.asarray(geom.exterior.coords)[:-1]


def _crs_string(frame: SceneFrame) -> str:
    epsg = frame.crs.to_epsg()
    return f"EPSG:{epsg}" if epsg is not None else frame.crs.to_wkt()


def _track_line(frame: SceneFrame, lay: CurveLayout, p: dict, toff: float, crs_bounds, margin: float) -> np.ndarray:
    """Top-of-rail centreline of the track at offset ``toff``: 1 m samples, the contiguous run through phi = 0."""
    r = lay.radius - toff
    k = int(math.ceil(0.75 * math.pi * lay.radius))
    phis = np.arange(-k, k + 1, dtype=float) / r  # 1 m steps along this track, one exactly at phi = 0
    xy = lay.point(phis, np.full_like(phis, toff))
    h = _bed_height(p, lay.radius * phis) + TOP_OF_RAIL_ABOVE_BED_M
    approx = frame.crs_from_enu(np.column_stack([xy, h - frame.height_m]))
    inside = ((approx[:, 0] >= crs_bounds[0] + margin) & (approx[:, 0] <= crs_bounds[2] - margin)
              & (approx[:, 1] >= crs_bounds[1] + margin) & (approx[:, 1] <= crs_bounds[3] - margin))
    i0 = int(np.argmin(np.abs(phis)))
    if not inside[i0]:
        raise ValueError("the DEM is too small to hold the track through the origin")
    lo = i0
    while lo > 0 and inside[lo - 1]:
        lo -= 1
    hi = i0
    while hi < len(phis) - 1 and inside[hi + 1]:
        hi += 1
    # Exact ENU of the top of rail at the design height (datum) over the design easting/northing.
    crs_pts = np.column_stack([approx[lo:hi + 1, :2], h[lo:hi + 1]])
    return frame.enu_from_crs(crs_pts)


def write_dem_geotiff(path: str | Path, terrain: SynthTerrain, *, nodata: float = -9999.0) -> Path:
    """Write the DEM as a deflate-compressed float32 GeoTIFF with CRS, transform and nodata, atomically."""
    z = np.asarray(terrain.heights, dtype=np.float32)

    def write(tmp: Path) -> None:
        profile = {"driver": "GTiff", "width": z.shape[1], "height": z.shape[0], "count": 1, "dtype": "float32",
                   "crs": terrain.crs, "transform": terrain.transform, "nodata": nodata, "compress": "deflate",
                   "predictor": 3, "tiled": True, "blockxsize": 256, "blockysize": 256}
        if z.shape[0] < 256 or z.shape[1] < 256:
            profile.update(tiled=False)
            profile.pop("blockxsize")
            profile.pop("blockysize")
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(np.where(np.isfinite(z), z, nodata).astype(np.float32), 1)
            dst.update_tags(AREA_OR_POINT="Area", scenario=terrain.scenario or "")
            dst.set_band_description(1, "height (m)")

    return atomic_write(Path(path), write, suffix=".tif")


# ----------------------------------------------------------------------------------------------------------
# Texture
# ----------------------------------------------------------------------------------------------------------
_COL = {
    "grass": (86, 112, 56), "grass_dry": (132, 128, 82), "dirt": (122, 102, 78), "trees": (50, 76, 42),
    "scrub": (98, 104, 62), "water": (50, 72, 84), "mud": (96, 88, 70), "ballast": (128, 124, 118),
    "cess": (112, 102, 90), "sleeper": (168, 164, 156), "rail": (190, 190, 194), "asphalt": (70, 71, 74),
    "path": (150, 132, 102), "concrete": (158, 155, 147), "line": (225, 222, 210),
}


class _Canvas:
    """A flat float32 RGB image painted layer by layer on the pixels a layer can touch (fast for thin features)."""

    def __init__(self, npx: int, x: np.ndarray, y: np.ndarray, lay: CurveLayout, noise: dict[str, np.ndarray]) -> None:
        self.npx = npx
        self.x, self.y = x, y  # flat ENU coordinates of pixel centres
        self.lay = lay
        self.off = lay.offset(x, y)
        self.noise = noise
        self.img = np.empty((x.size, 3), dtype=np.float32)

    def near(self, centre_off: float, half_width: float) -> np.ndarray:
        return np.flatnonzero(np.abs(self.off - centre_off) <= half_width)

    def phi(self, idx: np.ndarray) -> np.ndarray:
        return self.lay.offset_along(self.x[idx], self.y[idx])[1]

    def paint(self, idx: np.ndarray, alpha: np.ndarray, colour, jitter: np.ndarray | None = None) -> None:
        a = np.asarray(alpha, dtype=np.float32)
        keep = a > 0
        if not keep.all():
            idx, a = idx[keep], a[keep]
            jitter = jitter[keep] if jitter is not None else None
        c = np.asarray(colour, dtype=np.float32)[None, :]
        if jitter is not None:
            c = c + jitter[:, None]
        a = a[:, None]
        self.img[idx] = self.img[idx] * (1.0 - a) + a * c

    def image(self) -> Image.Image:
        img = np.clip(self.img, 0, 255).astype(np.uint8).reshape(self.npx, self.npx, 3)
        return Image.fromarray(img, "RGB")


def _make_texture(scenario: str, p: dict, lay: CurveLayout, frame: SceneFrame, terrain: SynthTerrain,
                  rng: np.random.Generator, px_per_m: float) -> Image.Image:
    left, bottom, right, top = terrain.bounds_crs
    W = right - left
    npx = int(min(4096, max(16, round(W * px_per_m))))
    px = W / npx  # metres per pixel
    # Affine CRS -> ENU horizontal map fitted over the DEM (sub-millimetre over a few hundred metres).
    g = np.linspace(0.0, 1.0, 7)
    ge, gn = np.meshgrid(left + g * W, bottom + g * (top - bottom))
    src = np.column_stack([ge.ravel(), gn.ravel()])
    mean = src.mean(axis=0)
    dst = frame.enu_from_crs(np.column_stack([src, np.full(len(src), frame.height_m)]))[:, :2]
    A = np.column_stack([src - mean, np.ones(len(src))])
    coef, *_ = np.linalg.lstsq(A, dst, rcond=None)
    ec = ((np.arange(npx) + 0.5) * px + left - mean[0]).astype(np.float32)
    nr = (top - (np.arange(npx) + 0.5) * px - mean[1]).astype(np.float32)
    x = (coef[0, 0] * ec[None, :] + coef[1, 0] * nr[:, None] + np.float32(coef[2, 0])).astype(np.float32).ravel()
    y = (coef[0, 1] * ec[None, :] + coef[1, 1] * nr[:, None] + np.float32(coef[2, 1])).astype(np.float32).ravel()
    shape = (npx, npx)
    noise = {"big": _value_noise(rng, shape, 25.0 / px).ravel(), "mid": _value_noise(rng, shape, 5.0 / px).ravel(),
             "fine": _value_noise(rng, shape, max(0.6 / px, 1.0)).ravel()}
    cv = _Canvas(npx, x, y, lay, noise)
    nb, nm, nf = noise["big"], noise["mid"], noise["fine"]
    speck = rng.standard_normal(x.size).astype(np.float32)
    off = cv.off
    # Ground: grass with dry patches and bare dirt.
    a1 = _smoothstep((nb + 0.3) / 1.2) * 0.55
    a2 = _smoothstep((nm - 1.0) / 0.6) * 0.6
    for k in range(3):
        c = _COL["grass"][k] * (1 - a1) + _COL["grass_dry"][k] * a1
        cv.img[:, k] = c * (1 - a2) + _COL["dirt"][k] * a2 + 4.0 * nf
    if scenario == "embankment_river":
        idx = np.flatnonzero(off > 60.0)  # trees and brush on the hillside
        cv.paint(idx, _smoothstep((off[idx] - 70.0) / 30.0) * _smoothstep((nm[idx] + 0.2 * nb[idx] + 0.1) / 0.5),
                 _COL["trees"])
        idx = np.flatnonzero(off < -10.0)  # river bank, mud, water
        phi = cv.phi(idx)
        a = -off[idx]
        sl = (lay.radius + a) * phi
        wo = 24.0 + 3.0 * np.sin(sl / 37.0) + 2.0 * np.sin(sl / 91.0 + 1.0)
        cv.paint(idx, _smoothstep((a - 12.0) / 3.0) * _smoothstep((nm[idx] + 0.4) / 0.6) * 0.8, _COL["trees"])
        cv.paint(idx, _band(a - wo + 0.75, 1.5, px) * 0.9, _COL["mud"])
        cv.paint(idx, np.clip(0.5 + (a - wo) / px, 0.0, 1.0), _COL["water"], 4.0 * nm[idx] + 2.0 * nf[idx])
        crest, eh = p["bed_half_width"], p["emb_height"]
        idx = np.flatnonzero(np.abs(np.abs(off) - crest - eh) <= eh + px)  # embankment slopes
        cv.paint(idx, _band(np.abs(off[idx]) - crest - eh, eh, px) * 0.5, _COL["grass_dry"])
    else:
        for lot in terrain.features["lots"]:
            m = _polygon_mask(lot, coef, mean, left, top, px, npx).ravel()
            idx = np.flatnonzero(m > 0)
            j = 8.0 * nm[idx] + 5.0 * nf[idx] + 3.0 * speck[idx] - 25.0 * _smoothstep((nb[idx] - 1.2) / 0.6)
            cv.paint(idx, m[idx], _COL["concrete"], j)
        oc, w = p["bed_offset"], p["bed_half_width"]
        idx = np.flatnonzero(np.abs(np.abs(off - oc) - w - 4.0) <= 4.0)  # cutting slopes: scrub
        dist = np.abs(off[idx] - oc) - w
        cv.paint(idx, _smoothstep(dist / 1.5) * _smoothstep((7.0 - dist) / 3.0) * _smoothstep((nm[idx] + 0.6) / 1.2)
                 * 0.8, _COL["scrub"])
    # Roads and paths.
    for ro, rw, kind in p.get("roads", []):
        idx = cv.near(ro, rw / 2 + 2.0 + px)
        d = off[idx] - ro
        if kind == "path":
            cv.paint(idx, _band(d, rw / 2, px) * (0.85 + 0.1 * nf[idx]), _COL["path"])
        else:
            cv.paint(idx, _band(d, rw / 2 + 1.8, px) * 0.9, _COL["concrete"])  # sidewalks
            cv.paint(idx, _band(d, rw / 2, px), _COL["asphalt"], 3.0 * nf[idx] + 2.0 * speck[idx])
            sl = (lay.radius - off[idx]) * cv.phi(idx)
            dash = (np.mod(sl, 9.0) < 4.5).astype(np.float32)
            cv.paint(idx, _band(d, 0.06, px) * dash * 0.9, _COL["line"])
    for s0, o0, o1, rw in p.get("cross_roads", []):
        phi0 = s0 / lay.radius
        a = lay.point(np.array([phi0, phi0]), np.array([o0, o1]))
        length = float(np.linalg.norm(a[1] - a[0]))
        dvec = (a[1] - a[0]) / length
        along = (x - a[0][0]) * dvec[0] + (y - a[0][1]) * dvec[1]
        across = -(x - a[0][0]) * dvec[1] + (y - a[0][1]) * dvec[0]
        idx = np.flatnonzero((np.abs(across) <= rw / 2 + 2.0 + px) & (along > -px) & (along < length + px))
        inside = np.clip(0.5 + along[idx] / px, 0, 1) * np.clip(0.5 + (length - along[idx]) / px, 0, 1)
        cv.paint(idx, _band(across[idx], rw / 2 + 1.8, px) * inside * 0.9, _COL["concrete"])
        cv.paint(idx, _band(across[idx], rw / 2, px) * inside, _COL["asphalt"], 3.0 * nf[idx] + 2.0 * speck[idx])
    # Track bed: cess (formation shoulders), ballast, sleepers, rails.
    oc, w = p["bed_offset"], p["bed_half_width"]
    idx = cv.near(oc, w + px)
    cv.paint(idx, _band(off[idx] - oc, w, px), _COL["cess"], 5.0 * nm[idx] + 4.0 * speck[idx])
    for toff in p["track_offsets"]:
        idx = cv.near(toff, 2.1 + px)
        d = off[idx] - toff
        cv.paint(idx, _band(d, 2.1, px), _COL["ballast"], 14.0 * speck[idx] + 6.0 * nf[idx])
        s_t = (lay.radius - toff) * cv.phi(idx)
        ds = np.mod(s_t, _SLEEPER_SPACING_M) - _SLEEPER_SPACING_M / 2
        cv.paint(idx, _band(d, _SLEEPER_HALF_LENGTH_M, px) * _band(ds, _SLEEPER_WIDTH_M / 2, px) * 0.9,
                 _COL["sleeper"], 4.0 * speck[idx])
        for side in (-1.0, 1.0):
            cv.paint(idx, np.clip(_band(d - side * RAIL_HALF_GAUGE_M, _RAIL_HEAD_M / 2, px) * 1.6, 0, 1), _COL["rail"])
    # Subtle lighting variation.
    cv.img *= (1.0 + 0.03 * nb)[:, None]
    return cv.image()


def _polygon_mask(poly_enu: np.ndarray, coef: np.ndarray, mean_crs: np.ndarray, left: float, top: float, px: float,
                  npx: int) -> np.ndarray:
    """Antialiased mask (npx, npx), 0..1, of an ENU polygon in the texture (via the inverse of the affine fit)."""
    M = coef[:2].T  # enu = M @ (crs - mean) + t
    t = coef[2]
    crs = (np.linalg.solve(M, (poly_enu - t).T)).T + mean_crs
    pix = np.column_stack([(crs[:, 0] - left) / px, (top - crs[:, 1]) / px]) - 0.5
    mask = np.zeros((npx, npx), dtype=np.uint8)
    cv2.fillPoly(mask, [np.round(pix * 16).astype(np.int32)], 255, lineType=cv2.LINE_AA, shift=4)
    return mask.astype(np.float32) / 255.0
