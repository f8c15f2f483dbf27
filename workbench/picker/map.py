"""The picker's map pane: the incident's orthophoto (or a hillshade of its DEM) as one north-up image in the
project CRS, the buildings and railway lines to draw over it, and heights from the DEM (docs/picker.md).

The image's georeference is ``crs_from_pixel`` (2, 3): ``[E, N] = crs_from_pixel @ [u, v, 1]`` with pixel
(0, 0) the centre of the top-left pixel (docs/conventions.md); rows run south, so ``crs_from_pixel[1][1] < 0``.

Where the orthophoto's georeference comes from, in this order:

1. the file's own CRS and geotransform (a GeoTIFF in any CRS: warped into the project CRS, bilinear);
2. a world file beside it (``.jgw``/``.pgw``/``.tfw``/``.wld``, read by GDAL), in the CRS of a ``.prj`` beside it,
   else the project CRS;
3. the orthophoto convention of ``terrain.ortho`` (docs/formats.md): the image covers the DEM's extent, row 0 at
   the north edge (the synthetic samples' ``*_ortho.jpg``); used only where the image's aspect ratio is the DEM's
   (within 2 %);

otherwise an :class:`InputError` names the file and says what to add. Only the part of the orthophoto around the
incident (``terrain.aoi_radius_m``, widened by 20 %) is read and shown, so a large sheet keeps its resolution.

Heights: bilinear between the DEM's nodes (cell centres) as the terrain stage reads the DEM (tiles mosaicked,
vertical units converted, holes filled, cropped to ``terrain.aoi_radius_m``); a point outside is refused with
that extent.
"""

from __future__ import annotations

import io
import logging
import math
import threading
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..project import Project

log = logging.getLogger(__name__)

__all__ = ["MapImage", "MapService", "hillshade", "ortho_source", "warp_to_crs", "bilinear_height"]

MAX_MAP_PX = 2048  # the map image's longest side
ASPECT_TOLERANCE = 0.02  # the DEM-extent convention: the orthophoto's aspect ratio within 2 % of the DEM's
WORLD_FILE_SUFFIXES = (".jgw", ".jpgw", ".pgw", ".pngw", ".tfw", ".tifw", ".wld")


@dataclass
class MapImage:
    """``rgba`` (h, w, 4) uint8, north-up in ``crs``; ``crs_from_pixel`` (2, 3) (module docstring); ``source``:
    what it shows and where its georeference came from."""

    rgba: np.ndarray
    crs_from_pixel: np.ndarray
    crs: str
    source: str
    notes: list[str] = field(default_factory=list)

    @property
    def pixel_size_m(self) -> float:
        return float(abs(self.crs_from_pixel[0, 0]))

    def pixel_from_crs(self, en: np.ndarray) -> np.ndarray:
        """(n, 2) map pixels of (n, 2) easting/northing."""
        A = self.crs_from_pixel
        en = np.atleast_2d(np.asarray(en, float))
        return np.column_stack([(en[:, 0] - A[0, 2]) / A[0, 0], (en[:, 1] - A[1, 2]) / A[1, 1]])


def hillshade(z: np.ndarray, cell_x_m: float, cell_y_m: float, azimuth_deg: float = 315.0,
              altitude_deg: float = 45.0) -> np.ndarray:
    """Shading (rows, cols) in [0, 1] of a north-up height grid ``z`` (row 0 north), lit from ``azimuth_deg``
    (clockwise from grid north) at ``altitude_deg`` above the horizon."""
    z = np.asarray(z, float)
    dz_de = np.gradient(z, axis=1) / cell_x_m
    dz_dn = -np.gradient(z, axis=0) / cell_y_m  # rows run south
    n = np.stack([-dz_de, -dz_dn, np.ones_like(z)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    az, alt = math.radians(azimuth_deg), math.radians(altitude_deg)
    light = np.array([math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt)])
    return np.clip(n @ light, 0.0, 1.0)


def bilinear_height(heights: np.ndarray, transform, e: float, n: float) -> float | None:
    """The height at (``e``, ``n``) interpolated bilinearly between the nodes (cell centres) of a north-up grid
    with rasterio ``transform``; None outside the nodes' extent."""
    R, C = heights.shape
    fc = (e - transform.c) / transform.a - 0.5
    fr = (n - transform.f) / transform.e - 0.5
    if not (0.0 <= fc <= C - 1 and 0.0 <= fr <= R - 1):
        return None
    c0, r0 = min(int(fc), C - 2), min(int(fr), R - 2)
    tc, tr = fc - c0, fr - r0
    z = heights[r0:r0 + 2, c0:c0 + 2]
    return float((1 - tr) * ((1 - tc) * z[0, 0] + tc * z[0, 1]) + tr * ((1 - tc) * z[1, 0] + tc * z[1, 1]))


AOI_MARGIN = 1.2  # the map covers terrain.aoi_radius_m around the incident, widened by this factor


def _georeference(src, path: Path, project: Project) -> tuple[object, str, str]:
    """(rasterio transform of the whole image, its CRS (WKT or user string), where they came from): the module
    docstring's order; :class:`InputError` naming the file and what to add when there is none."""
    import rasterio
    from rasterio.transform import from_bounds

    if not src.transform.is_identity and src.crs:
        return src.transform, src.crs.to_wkt(), "the file's own CRS and geotransform"
    if not src.transform.is_identity:
        prj = next((p for p in (path.with_suffix(".prj"), Path(str(path) + ".prj")) if p.is_file()), None)
        if prj is not None:
            return src.transform, prj.read_text(encoding="utf-8", errors="replace"), \
                f"its world file, CRS from {prj.name}"
        return src.transform, project.frame.crs.to_wkt(), "its world file, in the project CRS (no .prj beside it)"
    dems = project.dem_paths() if project.settings.terrain.dem else []
    if len(dems) == 1:
        with rasterio.open(dems[0]) as d:
            dem_aspect = d.width * abs(d.transform.a) / (d.height * abs(d.transform.e))
            b, dem_crs = d.bounds, (d.crs.to_wkt() if d.crs else None)
        if dem_crs and abs(src.width / src.height / dem_aspect - 1.0) <= ASPECT_TOLERANCE:
            return from_bounds(b.left, b.bottom, b.right, b.top, src.width, src.height), dem_crs, \
                f"the DEM's extent ({dems[0].name}; the terrain.ortho convention)"
    names = ", ".join(path.with_suffix(s).name for s in (".jgw", ".pgw", ".wld"))
    raise InputError(f"{path}: the orthophoto has no georeference: no CRS or geotransform in the file, no world "
                     f"file beside it ({names}), and it does not cover the DEM's extent as terrain.ortho "
                     f"otherwise must. Add a world file (6 lines: pixel width, 0, 0, -pixel height, easting and "
                     f"northing of the top-left pixel's centre, in the project CRS or the CRS of a .prj beside it), "
                     f"or save it as a GeoTIFF with its CRS (gdal_translate -a_srs EPSG:XXXX -a_ullr ...)")


def _aoi_window(T, crs: str, width: int, height: int, project: Project):
    """The window of an image (transform ``T`` in ``crs``) that covers the incident's area (``terrain.aoi_radius_m``
    around the reference point, widened by AOI_MARGIN); the whole image where it is rotated or misses the area."""
    from rasterio.warp import transform_bounds
    from rasterio.windows import Window, from_bounds

    whole = Window(0, 0, width, height)
    if T.b != 0 or T.d != 0:
        return whole
    o, r = project.frame.origin_crs, project.settings.terrain.aoi_radius_m * AOI_MARGIN
    b = transform_bounds(project.frame.crs.to_wkt(), crs, o[0] - r, o[1] - r, o[0] + r, o[1] + r, densify_pts=21)
    from rasterio.errors import WindowError

    w = from_bounds(*b, transform=T)
    c0, r0 = max(0, math.floor(w.col_off)), max(0, math.floor(w.row_off))
    c1, r1 = min(width, math.ceil(w.col_off + w.width)), min(height, math.ceil(w.row_off + w.height))
    try:
        win = Window(c0, r0, c1 - c0, r1 - r0).intersection(whole)
    except WindowError:  # no overlap
        return whole
    return win if win.width >= 2 and win.height >= 2 else whole


def ortho_source(path: Path, project: Project) -> tuple[np.ndarray, object, str, str]:
    """(rgb (3, h, w) uint8 of the part covering the incident, read at most ~2x the map size; the rasterio
    transform of that array; its CRS as WKT or user string; where the georeference came from) of an orthophoto
    (module docstring)."""
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.errors import NotGeoreferencedWarning
    from rasterio.windows import transform as window_transform
    from affine import Affine

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            src = rasterio.open(path)
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(f"{path}: the orthophoto (terrain.ortho) cannot be read ({exc}); give a GeoTIFF, or a "
                         f"JPEG/PNG with its world file") from None
    with src:
        T, crs, how = _georeference(src, path, project)
        win = _aoi_window(T, crs, src.width, src.height, project)
        ww, wh = int(win.width), int(win.height)
        f = max(1, math.ceil(max(ww, wh) / (2 * MAX_MAP_PX)))
        h, w = math.ceil(wh / f), math.ceil(ww / f)
        bands = [1, 2, 3] if src.count >= 3 else [1, 1, 1]
        arr = src.read(bands, window=win, out_shape=(3, h, w), resampling=Resampling.average)
        Tw = window_transform(win, T) @ Affine.scale(ww / w, wh / h)
        dtype = src.dtypes[0]
    if arr.dtype != np.uint8:  # 16-bit or float imagery: stretched to 8 bits (2nd-98th percentile)
        lo, hi = np.nanpercentile(arr, [2, 98])
        arr = np.clip((arr - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
        log.info("%s: %s orthophoto stretched to 8 bits", path, dtype)
    return arr, Tw, crs, how


def warp_to_crs(rgb: np.ndarray, src_transform, src_crs: str, dst_crs: str,
                max_px: int = MAX_MAP_PX) -> tuple[np.ndarray, object]:
    """(rgba (h, w, 4) uint8, north-up rasterio transform) of ``rgb`` (3, h, w) in ``dst_crs``, longest side at
    most ``max_px``; alpha 0 where the source does not cover. Bilinear."""
    from pyproj import CRS
    from rasterio.enums import Resampling
    from rasterio.transform import array_bounds
    from rasterio.warp import calculate_default_transform, reproject
    from affine import Affine

    _, h, w = rgb.shape
    same = CRS.from_user_input(src_crs) == CRS.from_user_input(dst_crs)
    north_up = src_transform.b == 0 and src_transform.d == 0 and src_transform.a > 0 and src_transform.e < 0
    if same and north_up and max(h, w) <= max_px:
        alpha = np.full((h, w, 1), 255, np.uint8)
        return np.concatenate([np.moveaxis(rgb, 0, -1), alpha], axis=-1), src_transform
    west, south, east, north = array_bounds(h, w, src_transform)
    T, dw, dh = calculate_default_transform(src_crs, dst_crs, w, h, west, south, east, north)
    s = max(dw, dh) / max_px
    if s > 1.0:
        dw, dh = max(2, round(dw / s)), max(2, round(dh / s))
        T = T @ Affine.scale(s)
    out = np.zeros((4, dh, dw), np.uint8)
    src4 = np.concatenate([rgb, np.full((1, h, w), 255, np.uint8)], axis=0)
    for b in range(4):
        reproject(src4[b], out[b], src_transform=src_transform, src_crs=src_crs, dst_transform=T, dst_crs=dst_crs,
                  resampling=Resampling.bilinear, src_nodata=None, dst_nodata=0)
    return np.moveaxis(out, 0, -1), T


def _crs_from_pixel(T) -> np.ndarray:
    """rasterio transform (pixel corners) -> (2, 3) ``crs_from_pixel`` at pixel centres (module docstring)."""
    return np.array([[T.a, 0.0, T.c + 0.5 * T.a], [0.0, T.e, T.f + 0.5 * T.e]])


class MapService:
    """The map of one incident, built on first use and kept (the DEM is read once): ``image()``, ``layers()``,
    ``height_at(e, n)``. Thread-safe."""

    def __init__(self, project: Project) -> None:
        self.project = project
        self._lock = threading.Lock()
        self._image: MapImage | None = None
        self._terrain = None
        self._png: bytes | None = None

    def terrain(self):
        """The terrain model (None without a DEM), read once."""
        with self._lock:
            if self._terrain is None and self.project.settings.terrain.dem:
                self._terrain = self.project.terrain_model()
            return self._terrain

    def image(self) -> MapImage:
        with self._lock:
            if self._image is None:
                self._image = self._build()
            return self._image

    def _build(self) -> MapImage:
        project = self.project
        crs = project.frame.crs.to_wkt()
        ortho = project.orthophoto_path()
        if ortho is not None:
            rgb, T, src_crs, how = ortho_source(ortho, project)
            rgba, T2 = warp_to_crs(rgb, T, src_crs, crs)
            log.info("picker map: orthophoto %s (georeference: %s), %dx%d px of %.2f m", ortho, how, rgba.shape[1],
                     rgba.shape[0], abs(T2.a))
            return MapImage(rgba, _crs_from_pixel(T2), project.settings.location.crs,
                            f"orthophoto {ortho.name} (georeference: {how})")
        if not project.settings.terrain.dem:
            raise InputError(f"{project.settings_path}: the map needs terrain.ortho (an orthophoto) or terrain.dem "
                             f"(a DEM, shown as a hillshade); set one under [terrain]")
        tm = self._terrain if self._terrain is not None else project.terrain_model()
        self._terrain = tm
        z, T = tm.heights, tm.transform
        shade = hillshade(z, abs(T.a), abs(T.e))
        t = (z - z.min()) / max(float(np.ptp(z)), 1e-6)
        tint = np.stack([0.55 + 0.35 * t, 0.65 + 0.2 * t, 0.5 + 0.1 * t], axis=-1)  # green lowland to tan hills
        rgb = np.clip(255 * tint * (0.25 + 0.75 * shade[..., None]), 0, 255).astype(np.uint8)
        rgba, T2 = warp_to_crs(np.moveaxis(rgb, -1, 0), T, crs, crs)
        return MapImage(rgba, _crs_from_pixel(T2), project.settings.location.crs,
                        f"hillshade of the DEM {', '.join(p.name for p in project.dem_paths()[:2])} (no orthophoto: "
                        f"set terrain.ortho to show one)")

    def png(self) -> bytes:
        """The map image as PNG (encoded once)."""
        from PIL import Image

        im = self.image()
        with self._lock:
            if self._png is None:
                buf = io.BytesIO()
                Image.fromarray(im.rgba).save(buf, "PNG", compress_level=3)
                self._png = buf.getvalue()
            return self._png

    def layers(self) -> dict:
        """Buildings (footprint rings, base and roof heights) and railway lines in map pixels and project CRS;
        ``notes`` says what could not be drawn."""
        project, im = self.project, self.image()
        t = project.settings.terrain
        out: dict = {"buildings": [], "railways": [], "notes": []}
        if t.buildings:
            try:
                out["buildings"] = self._buildings(project.path(t.buildings))
            except InputError as exc:  # the map is still useful without them: say why they are missing
                out["notes"].append(f"buildings not drawn: {exc}")
        if t.railways:
            layer = None
            try:
                layer = project.railways(heights=False)
                if layer is None:  # the reader has warned, naming the file
                    out["notes"].append(f"railways: {t.railways} holds no railway=rail line")
            except InputError as exc:
                out["notes"].append(f"railways not drawn: {exc}")
            for line in (layer.lines if layer is not None else ()):
                en = project.frame.crs_from_enu(np.asarray(line.points_enu, float))[:, :2]
                out["railways"].append({"id": line.id, "name": line.name, "line": _round(im.pixel_from_crs(en), 2)})
        return out

    def _buildings(self, path: Path) -> list[dict]:
        """The footprints of a buildings GeoJSON in map pixels and the project CRS, with base and height."""
        from ..terrain.buildings import is_cityjson

        if is_cityjson(path):
            raise InputError(f"{path.name} is a CityJSON model (the map draws GeoJSON footprints)")
        from ..files.buildings import read_buildings_geojson

        im, out = self.image(), []
        for b in read_buildings_geojson(path, expect_crs=self.project.frame.crs.to_string()):
            ring = np.asarray(b["footprint_crs"], float)[:, :2]
            base = b.get("base_m")
            out.append({"id": str(b.get("id", "")), "ring": _round(im.pixel_from_crs(ring), 2),
                        "ring_crs": _round(ring, 3), "base_m": None if base is None else float(base),
                        "height_m": float(b["height_m"])})
        return out

    def height_at(self, e: float, n: float) -> float:
        """The DEM's height at project-CRS (``e``, ``n``), bilinear; :class:`InputError` with the DEM's extent
        outside it, or without a DEM."""
        tm = self.terrain()
        if tm is None:
            raise InputError(f"{self.project.settings_path}: no terrain.dem, so no height from the DEM: type the "
                             f"height")
        h = bilinear_height(tm.heights, tm.transform, e, n)
        if h is None:
            lo, hi = tm.node_crs[-1, 0], tm.node_crs[0, -1]
            raise InputError(f"({e:.2f}, {n:.2f}) is outside the DEM: its extent here (terrain.dem cropped to "
                             f"terrain.aoi_radius_m) is E {lo[0]:.1f} to {hi[0]:.1f}, N {lo[1]:.1f} to {hi[1]:.1f} "
                             f"({self.project.settings.location.crs}); pick inside it or type the height")
        return h

    def dem_extent(self) -> list[float] | None:
        """[e_min, n_min, e_max, n_max] of the DEM's nodes (project CRS), or None without a DEM."""
        tm = self.terrain()
        if tm is None:
            return None
        lo, hi = tm.node_crs[-1, 0], tm.node_crs[0, -1]
        return [float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])]

    def document(self) -> dict:
        """What the page needs to show the map: the image's URL, size and georeference, the layers, the scale
        and the direction of true north."""
        im = self.image()
        h, w = im.rgba.shape[:2]
        return {"available": True, "url": "/map.png", "width": int(w), "height": int(h), "crs": im.crs,
                "crs_from_pixel": im.crs_from_pixel.tolist(), "pixel_size_m": im.pixel_size_m, "source": im.source,
                "grid_convergence_deg": self.project.frame.grid_convergence_deg(),
                "dem_extent": self.dem_extent(), **self.layers()}


def _round(a: np.ndarray, d: int) -> list:
    return np.round(np.asarray(a, float), d).tolist()
