"""The incident's DEM (``terrain.dem``: one GeoTIFF, a folder or a glob of tiles) as a terrain model in the scene frame.

Every later stage (settling carriages, rendering, camera placement) uses :class:`TerrainModel`:

* :meth:`TerrainModel.from_geotiff` reads a DEM (any CRS rasterio knows; reprojected into the project CRS when it
  differs), crops it to the area of interest, fills nodata holes (harmonic inpainting, reported), and converts every
  grid node (the cell centre, rasterio ``offset="center"``) exactly to ENU with :meth:`SceneFrame.enu_from_crs`.
* :meth:`TerrainModel.mesh` triangulates the ENU grid: two triangles per cell with a fixed diagonal (from the cell's
  north-east node to its south-west node).
* :meth:`TerrainModel.height_at` / :meth:`TerrainModel.normal_at` query *that* triangulation exactly. The ENU grid
  is not axis-aligned (grid convergence, scale factor, earth curvature), so a query is mapped to fractional grid
  indices with a cubic polynomial fitted once to the node positions, then the containing triangle is found by
  barycentric tests on the actual ENU vertices (looking at neighbouring cells when the guess lies on the wrong side
  of an edge). The height is the plane of that triangle, so it agrees with the mesh to rounding error.
"""

from __future__ import annotations

import logging
import math
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import rasterio
import trimesh
from pyproj import CRS
from rasterio.enums import Resampling
from rasterio.io import MemoryFile
from rasterio.transform import Affine
from rasterio.warp import reproject, transform_bounds
from rasterio.warp import transform as warp_transform
from rasterio.windows import Window
from scipy import sparse
from scipy.sparse.linalg import spsolve

from ..core.frames import SceneFrame
from ..core.io import resolve_dem_sources  # noqa: F401 - re-exported: the DEM sources of a terrain.dem value
from ..errors import InputError, WorkbenchWarning

if TYPE_CHECKING:  # pragma: no cover
    from PIL import Image

log = logging.getLogger(__name__)

__all__ = ["TerrainModel", "DemHolesFilled", "DemVerticalUnits", "resolve_dem_sources", "simplify_terrain_mesh",
           "vertical_unit_factor"]

# Neighbour cells searched (in this order) when the polynomial guess of a query's cell is off by an edge.
_NEIGHBOURS = [(0, 0), (0, -1), (0, 1), (-1, 0), (1, 0), (-1, -1), (-1, 1), (1, -1), (1, 1)]
_BARY_EPS = 1e-9


class DemHolesFilled(WorkbenchWarning):
    """Nodata cells of a DEM were filled by inpainting; heights there are interpolated, not measured."""


class DemVerticalUnits(WorkbenchWarning):
    """A DEM's heights were not in metres (its band unit or vertical CRS says feet or centimetres); converted."""


# Band / vertical-axis unit names (lower case) -> metres per unit.
_UNIT_FACTORS = {
    "": 1.0, "m": 1.0, "metre": 1.0, "meter": 1.0, "metres": 1.0, "meters": 1.0,
    "ft": 0.3048, "foot": 0.3048, "feet": 0.3048, "international foot": 0.3048,
    "us-ft": 1200.0 / 3937.0, "ftus": 1200.0 / 3937.0, "us survey foot": 1200.0 / 3937.0,
    "foot_us": 1200.0 / 3937.0, "us_survey_foot": 1200.0 / 3937.0,
    "cm": 0.01, "centimetre": 0.01, "centimeter": 0.01, "centimetres": 0.01, "centimeters": 0.01,
    "dm": 0.1, "mm": 0.001, "millimetre": 0.001, "millimeter": 0.001,
}
PLAUSIBLE_HEIGHTS_M = (-500.0, 9000.0)  # lowest and highest land surface on Earth, with margin


def vertical_unit_factor(src, where: str) -> tuple[float, str]:
    """(metres per DEM unit, unit name) from the band's unit tag or the vertical part of a compound CRS.

    An unknown unit name is an :class:`InputError` naming the file.
    """
    names = []
    units = getattr(src, "units", None) or (None,)
    if units and units[0]:
        names.append(("band unit", str(units[0]).strip()))
    crs = _pyproj_crs(src.crs)
    if crs is not None and crs.is_compound and len(crs.sub_crs_list) > 1:
        ax = crs.sub_crs_list[1].axis_info
        if ax:
            names.append(("vertical CRS unit", ax[0].unit_name))
    for what, name in names:
        f = _UNIT_FACTORS.get(name.lower())
        if f is None:
            raise InputError(f"DEM {where}: {what} {name!r} is not a length unit the workbench knows; heights must be "
                             f"in metres (or a declared foot / centimetre unit): convert it, e.g. gdal_calc.py, "
                             f"or set the unit with gdal_edit.py -units m {where}")
        if f != 1.0:
            return f, name
    return 1.0, "metre"


def _read_heights(src, win, where: str, info: dict) -> np.ndarray:
    """Band 1 in ``win`` as float metres (NaN = nodata): scale/offset tags applied, then the unit factor."""
    z = src.read(1, window=win, masked=True).astype(float).filled(np.nan)
    scale = (getattr(src, "scales", None) or (1.0,))[0] or 1.0
    offset = (getattr(src, "offsets", None) or (0.0,))[0] or 0.0
    if scale != 1.0 or offset != 0.0:
        z = z * scale + offset
        info["scale_offset"] = (float(scale), float(offset))
    f, unit = vertical_unit_factor(src, where)
    info["vertical_unit"] = unit
    if f != 1.0:
        z = z * f
        msg = f"DEM {where}: heights are in {unit!r}; converted to metres (x {f:.6g})"
        log.warning(msg)
        warnings.warn(msg, DemVerticalUnits, stacklevel=4)
    return z


def _check_plausible_heights(z: np.ndarray, where: str) -> None:
    lo, hi = float(np.nanmin(z)), float(np.nanmax(z))
    if lo < PLAUSIBLE_HEIGHTS_M[0] or hi > PLAUSIBLE_HEIGHTS_M[1]:
        raise InputError(f"DEM {where}: heights from {lo:.1f} to {hi:.1f} are not plausible metres (land lies between "
                         f"{PLAUSIBLE_HEIGHTS_M[0]:.0f} and {PLAUSIBLE_HEIGHTS_M[1]:.0f} m); the DEM may be in "
                         f"centimetres or feet, or its nodata value is not set: declare the unit "
                         f"(gdal_edit.py -units cm|ft), set -a_nodata, or convert it to metres")


def _pyproj_crs(crs: Any) -> CRS | None:
    if crs is None:
        return None
    try:
        return CRS.from_user_input(crs.to_wkt() if hasattr(crs, "to_wkt") else crs)
    except Exception:  # noqa: BLE001 - any unparsable CRS counts as missing
        return None


def _same_crs(a: CRS, b: CRS) -> bool:
    if a.equals(b, ignore_axis_order=True):
        return True
    ea, eb = a.to_epsg(), b.to_epsg()
    return ea is not None and ea == eb


def _fill_holes(z: np.ndarray, where: str) -> tuple[np.ndarray, int]:
    """Fill NaN cells by harmonic inpainting (discrete Laplace equation, known cells as boundary values)."""
    hole = ~np.isfinite(z)
    n = int(hole.sum())
    if n == 0:
        return z, 0
    if n == z.size:
        raise InputError(f"{where}: every cell in the area of interest is nodata; nothing to build a terrain from")
    R, C = z.shape
    idx = np.full(z.shape, -1, dtype=np.int64)
    idx[hole] = np.arange(n)
    hr, hc = np.nonzero(hole)
    diag = np.zeros(n)
    rhs = np.zeros(n)
    rows, cols = [], []
    zk = np.where(hole, 0.0, z)
    for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        nr, nc = hr + dr, hc + dc
        inside = (nr >= 0) & (nr < R) & (nc >= 0) & (nc < C)
        i = np.nonzero(inside)[0]
        nr, nc = nr[i], nc[i]
        diag[i] += 1.0
        nh = hole[nr, nc]
        rows.append(i[nh])
        cols.append(idx[nr[nh], nc[nh]])
        np.add.at(rhs, i[~nh], zk[nr[~nh], nc[~nh]])
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    A = sparse.coo_matrix((-np.ones(len(r)), (r, c)), shape=(n, n)) + sparse.diags(diag)
    sol = spsolve(A.tocsc(), rhs)
    out = z.copy()
    out[hole] = sol
    return out, n


def _poly_terms(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Cubic bivariate monomials (10 columns)."""
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y, x * x * x, x * x * y, x * y * y, y * y * y], axis=-1)


class TerrainModel:
    """A DEM as a regular grid of nodes in ENU metres (``grid_enu``, shape (rows, cols, 3), row 0 = north edge).

    Attributes: ``grid_enu``, ``heights`` (the DEM values, project vertical datum), ``transform`` (rasterio
    transform of the grid in the project CRS, north-up), ``crs`` (the project CRS), ``node_crs`` (rows, cols, 2)
    easting/northing of the nodes, ``texture_bounds_crs`` (left, bottom, right, top of the area a texture passed to
    :meth:`mesh` covers: by default the whole source DEM), ``vertical_accuracy_m`` and ``info`` (what was done
    while reading: reprojection, decimation, filled cells, ...).
    """

    def __init__(self, heights: np.ndarray, transform: Affine, frame: SceneFrame, *,
                 vertical_accuracy_m: float = 0.5, texture_bounds_crs: tuple[float, float, float, float] | None = None,
                 info: dict | None = None) -> None:
        z = np.asarray(heights, dtype=float)
        if z.ndim != 2 or z.shape[0] < 2 or z.shape[1] < 2:
            raise InputError(f"terrain grid has shape {z.shape}; need at least 2 x 2 nodes")
        if not np.all(np.isfinite(z)):
            raise ValueError("heights contain NaN/inf; fill nodata before building a TerrainModel")
        T = Affine(*tuple(transform)[:6])
        if T.b != 0 or T.d != 0:
            raise ValueError(f"transform {T} is rotated; only north-up grids are supported here")
        # Normalise orientation: row 0 = north, column 0 = west (the triangle winding relies on it).
        if T.e > 0:
            z = z[::-1]
            T = T @ Affine.translation(0, z.shape[0]) @ Affine.scale(1, -1)
        if T.a < 0:
            z = z[:, ::-1]
            T = T @ Affine.translation(z.shape[1], 0) @ Affine.scale(-1, 1)
        self.frame = frame
        self.crs = frame.crs
        self.heights = np.ascontiguousarray(z)
        self.transform = T
        self.vertical_accuracy_m = float(vertical_accuracy_m)
        self.info = dict(info or {})
        R, C = z.shape
        cc, rr = np.meshgrid(np.arange(C) + 0.5, np.arange(R) + 0.5)
        X = T.c + T.a * cc + T.b * rr
        Y = T.f + T.d * cc + T.e * rr
        self.node_crs = np.stack([X, Y], axis=-1)
        enu = frame.enu_from_crs(np.column_stack([X.ravel(), Y.ravel(), z.ravel()]))
        self.grid_enu = enu.reshape(R, C, 3)
        self.texture_bounds_crs = tuple(texture_bounds_crs) if texture_bounds_crs is not None else (
            T.c, T.f + T.e * R, T.c + T.a * C, T.f)
        self._fit_index_map()
        self.info.setdefault("shape", (R, C))
        self.info.setdefault("cell_size_m", (abs(T.a), abs(T.e)))

    # ------------------------------------------------------------------------------------------------------
    # Construction
    # ------------------------------------------------------------------------------------------------------
    @classmethod
    def from_geotiff(cls, path: str | Path, frame: SceneFrame, *, aoi_radius_m: float | None = None,
                     max_cells: int = 400_000, vertical_accuracy_m: float = 0.5) -> "TerrainModel":
        """Read a DEM GeoTIFF (or anything rasterio opens) into a terrain model in ``frame``.

        ``aoi_radius_m``: keep a square around the ENU origin that covers ``[-r, r]^2`` in ENU (None: all of it).
        ``max_cells``: the grid is block-averaged (same CRS) or resampled (other CRS) to at most this many nodes.
        """
        path = Path(path)
        if not path.exists():
            raise InputError(f"DEM {path} does not exist")
        try:
            src = rasterio.open(path)
        except rasterio.errors.RasterioIOError as exc:
            raise InputError(f"DEM {path} cannot be read by rasterio ({exc}); replace it with a valid GeoTIFF (check it with gdalinfo)") from None
        with src:
            return cls._from_dataset(src, frame, str(path), aoi_radius_m=aoi_radius_m, max_cells=max_cells,
                                     vertical_accuracy_m=vertical_accuracy_m)

    @classmethod
    def from_array(cls, heights: np.ndarray, transform: Affine, crs: Any, frame: SceneFrame, *,
                   nodata: float | None = None, aoi_radius_m: float | None = None, max_cells: int = 400_000,
                   vertical_accuracy_m: float = 0.5, name: str = "<array>") -> "TerrainModel":
        """Like :meth:`from_geotiff` for an in-memory DEM (e.g. :class:`workbench.synth.terrain.SynthTerrain`)."""
        z = np.asarray(heights)
        with MemoryFile() as mem:
            with mem.open(driver="GTiff", width=z.shape[1], height=z.shape[0], count=1, dtype=z.dtype,
                          crs=crs, transform=transform, nodata=nodata) as ds:
                ds.write(z, 1)
            with mem.open() as ds:
                return cls._from_dataset(ds, frame, name, aoi_radius_m=aoi_radius_m, max_cells=max_cells,
                                         vertical_accuracy_m=vertical_accuracy_m)

    @classmethod
    def from_sources(cls, paths: list[str | Path] | str | Path, frame: SceneFrame, *,
                     aoi_radius_m: float | None = None, max_cells: int = 400_000,
                     vertical_accuracy_m: float = 0.5) -> "TerrainModel":
        """One DEM file, or several tiles mosaicked (they must share one CRS; overlaps: the first tile wins).

        Only the part of the mosaic around the area of interest is read. Tiles in different CRSs are an
        :class:`InputError` naming two of them.
        """
        from rasterio.merge import merge

        paths = [Path(paths)] if isinstance(paths, (str, Path)) else [Path(x) for x in paths]
        if not paths:
            raise InputError("no DEM files given")
        if len(paths) == 1:
            return cls.from_geotiff(paths[0], frame, aoi_radius_m=aoi_radius_m, max_cells=max_cells,
                                    vertical_accuracy_m=vertical_accuracy_m)
        srcs = []
        try:
            for path in paths:
                try:
                    srcs.append(rasterio.open(path))
                except rasterio.errors.RasterioIOError as exc:
                    raise InputError(f"DEM tile {path} cannot be read by rasterio ({exc}); replace it with a valid "
                                     f"GeoTIFF") from None
            crss = [_pyproj_crs(s.crs) for s in srcs]
            for path, c in zip(paths, crss):
                if c is None:
                    raise InputError(f"DEM tile {path} has no CRS; assign one with gdal_edit.py -a_srs EPSG:XXXX "
                                     f"{path}")
            for path, c in zip(paths[1:], crss[1:]):
                if not _same_crs(c, crss[0]):
                    raise InputError(f"DEM tiles are in different CRSs: {paths[0]} is {crss[0].to_string()}, {path} is "
                                     f"{c.to_string()}; reproject them to one CRS (gdalwarp -t_srs "
                                     f"{crss[0].to_string()} ...) or build one mosaic (gdalbuildvrt)")
            units = {vertical_unit_factor(s, str(pth)) for s, pth in zip(srcs, paths)}
            if len(units) > 1:
                raise InputError(f"DEM tiles {[str(x) for x in paths]} declare different height units {sorted(units)}; "
                                 f"convert them to metres first")
            bounds = None
            if aoi_radius_m is not None:
                o = frame.origin_crs
                g = math.radians(frame.grid_convergence_deg())
                h = aoi_radius_m * (abs(math.cos(g)) + abs(math.sin(g))) * 1.01 + 1e-6
                T0 = srcs[0].transform
                b = transform_bounds(frame.crs.to_wkt(), srcs[0].crs, o[0] - h, o[1] - h, o[0] + h, o[1] + h,
                                     densify_pts=21)
                m = 3 * max(abs(T0.a), abs(T0.e))
                u = [min(s.bounds.left for s in srcs), min(s.bounds.bottom for s in srcs),
                     max(s.bounds.right for s in srcs), max(s.bounds.top for s in srcs)]
                bounds = (max(b[0] - m, u[0]), max(b[1] - m, u[1]), min(b[2] + m, u[2]), min(b[3] + m, u[3]))
                if bounds[0] >= bounds[2] or bounds[1] >= bounds[3]:
                    bounds = None  # no overlap: _from_dataset reports that the mosaic misses the origin
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                arr, T = merge(srcs, bounds=bounds, dtype="float64", nodata=np.nan, indexes=[1])
            profile = {"driver": "GTiff", "width": arr.shape[2], "height": arr.shape[1], "count": 1,
                       "dtype": "float64", "crs": srcs[0].crs, "transform": T, "nodata": np.nan}
            f, unit = vertical_unit_factor(srcs[0], str(paths[0]))
            names = ", ".join(x.name for x in paths[:4]) + (f", ... ({len(paths)} tiles)" if len(paths) > 4 else "")
        finally:
            for s_ in srcs:
                s_.close()
        if f != 1.0:  # the merge does not apply units: convert here, once, with the warning
            arr = arr * f
            msg = f"DEM tiles {names}: heights are in {unit!r}; converted to metres (x {f:.6g})"
            log.warning(msg)
            warnings.warn(msg, DemVerticalUnits, stacklevel=2)
        with MemoryFile() as mem:
            with mem.open(**profile) as ds:
                ds.write(arr[0], 1)
            with mem.open() as ds:
                tm = cls._from_dataset(ds, frame, f"mosaic of {names}", aoi_radius_m=aoi_radius_m,
                                       max_cells=max_cells, vertical_accuracy_m=vertical_accuracy_m)
        tm.info["tiles"] = [str(x) for x in paths]
        tm.info["vertical_unit"] = unit
        return tm

    @classmethod
    def _from_dataset(cls, src, frame: SceneFrame, where: str, *, aoi_radius_m: float | None, max_cells: int,
                      vertical_accuracy_m: float) -> "TerrainModel":
        src_crs = _pyproj_crs(src.crs)
        if src_crs is None or not (src_crs.is_projected or src_crs.is_geographic):
            raise InputError(f"DEM {where} has no CRS; assign one with gdal_edit.py -a_srs EPSG:XXXX {where}")
        T: Affine = src.transform
        if T.is_identity:
            raise InputError(f"DEM {where} has no geotransform; it cannot be placed in the scene")
        if aoi_radius_m is not None and not aoi_radius_m > 0:
            raise ValueError(f"aoi_radius_m={aoi_radius_m} must be positive")
        info: dict[str, Any] = {"source": where, "source_crs": src_crs.to_string(), "source_shape": src.shape}
        o = frame.origin_crs
        ox, oy = warp_transform(frame.crs.to_wkt(), src.crs, [o[0]], [o[1]])
        ox, oy = ox[0], oy[0]
        # The DEM's node extent (cell centres) must contain the origin.
        inv = ~T
        oc, orow = inv @ (ox, oy)
        if not (0.5 <= oc <= src.width - 0.5 and 0.5 <= orow <= src.height - 0.5):
            b = src.bounds
            raise InputError(
                f"DEM {where} does not cover the scene origin (lat {frame.lat_deg:.6f}, lon {frame.lon_deg:.6f}; "
                f"({ox:.2f}, {oy:.2f}) in {src_crs.to_string()}): its bounds are left={b.left:.2f}, "
                f"bottom={b.bottom:.2f}, right={b.right:.2f}, top={b.top:.2f}; use a DEM that covers the incident")
        same = _same_crs(src_crs, frame.crs) and T.b == 0 and T.d == 0
        info["reprojected"] = not same

        # Area of interest in the project CRS: a square that covers the ENU square [-r, r]^2 (grid convergence).
        if aoi_radius_m is not None:
            g = math.radians(frame.grid_convergence_deg())
            h = aoi_radius_m * (abs(math.cos(g)) + abs(math.sin(g))) * 1.002 + 1e-6
            aoi = (o[0] - h, o[1] - h, o[0] + h, o[1] + h)
        else:
            aoi = None

        if same:
            if aoi is not None:
                # Nodes whose centre lies within the AOI, plus one node of margin so the square is fully covered.
                cs, rs = inv @ (np.array([aoi[0], aoi[2], aoi[0], aoi[2]]), np.array([aoi[1], aoi[1], aoi[3], aoi[3]]))
                c0 = max(int(math.floor(cs.min() - 0.5)), 0)
                c1 = min(int(math.ceil(cs.max() + 0.5)), src.width)
                r0 = max(int(math.floor(rs.min() - 0.5)), 0)
                r1 = min(int(math.ceil(rs.max() + 0.5)), src.height)
            else:
                c0, c1, r0, r1 = 0, src.width, 0, src.height
            win = Window(c0, r0, c1 - c0, r1 - r0)
            z = _read_heights(src, win, where, info)
            Tw = src.window_transform(win)
            k = 1
            if z.size > max_cells:
                k = int(math.ceil(math.sqrt(z.size / max_cells)))
                while (z.shape[0] // k) * (z.shape[1] // k) > max_cells:
                    k += 1
                R, C = z.shape[0] // k, z.shape[1] // k
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN blocks stay NaN (filled below)
                    z = np.nanmean(z[:R * k, :C * k].reshape(R, k, C, k), axis=(1, 3))
                Tw = Tw @ Affine.scale(k, k)
            info["decimation"] = k
            texture_bounds = tuple(src.bounds)
        else:
            full = transform_bounds(src.crs, frame.crs.to_wkt(), *src.bounds, densify_pts=21)
            if aoi is not None:
                dst_b = (max(aoi[0], full[0]), max(aoi[1], full[1]), min(aoi[2], full[2]), min(aoi[3], full[3]))
                # Read only the part of the source that the AOI needs (with a margin of 2 source cells).
                sb = transform_bounds(frame.crs.to_wkt(), src.crs, *dst_b, densify_pts=21)
                cs, rs = inv @ (np.array([sb[0], sb[2], sb[0], sb[2]]), np.array([sb[1], sb[1], sb[3], sb[3]]))
                c0 = max(int(math.floor(cs.min())) - 2, 0)
                c1 = min(int(math.ceil(cs.max())) + 2, src.width)
                r0 = max(int(math.floor(rs.min())) - 2, 0)
                r1 = min(int(math.ceil(rs.max())) + 2, src.height)
            else:
                dst_b = full
                c0, c1, r0, r1 = 0, src.width, 0, src.height
            win = Window(c0, r0, c1 - c0, r1 - r0)
            zs = _read_heights(src, win, where, info)
            Ts = src.window_transform(win)
            # Destination resolution: the source cell size measured in the project CRS at the origin.
            px, py = warp_transform(src.crs, frame.crs.to_wkt(), [ox, ox + T.a, ox + T.b], [oy, oy + T.d, oy + T.e])
            res = min(math.hypot(px[1] - px[0], py[1] - py[0]), math.hypot(px[2] - px[0], py[2] - py[0]))
            W, H = dst_b[2] - dst_b[0], dst_b[3] - dst_b[1]
            res = max(res, math.sqrt(W * H / max_cells))
            C, R = max(int(math.ceil(W / res)), 2), max(int(math.ceil(H / res)), 2)
            while R * C > max_cells:
                res *= 1.01
                C, R = max(int(math.ceil(W / res)), 2), max(int(math.ceil(H / res)), 2)
            # Centre the destination grid on the requested box.
            x0 = (dst_b[0] + dst_b[2]) / 2 - C * res / 2
            y1 = (dst_b[1] + dst_b[3]) / 2 + R * res / 2
            Tw = Affine(res, 0.0, x0, 0.0, -res, y1)
            z = np.full((R, C), np.nan)
            reproject(source=zs, destination=z, src_transform=Ts, src_crs=src.crs, src_nodata=np.nan,
                      dst_transform=Tw, dst_crs=frame.crs.to_wkt(), dst_nodata=np.nan,
                      resampling=Resampling.bilinear)
            # Drop border rows/columns that fall entirely outside the source.
            ok = np.isfinite(z)
            rows = np.nonzero(ok.any(axis=1))[0]
            cols = np.nonzero(ok.any(axis=0))[0]
            if len(rows) < 2 or len(cols) < 2:
                raise InputError(f"DEM {where}: reprojecting into {frame.crs.to_string()} left no data around the "
                                 f"scene origin")
            z = z[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
            Tw = Tw @ Affine.translation(cols[0], rows[0])
            info["resolution_m"] = res
            texture_bounds = full
        if z.shape[0] < 2 or z.shape[1] < 2:
            raise InputError(f"DEM {where}: the area of interest holds only {z.shape} cells; need at least 2 x 2")
        z, n_filled = _fill_holes(z, f"DEM {where}")
        _check_plausible_heights(z, where)
        info["filled_cells"] = n_filled
        if n_filled:
            msg = (f"DEM {where}: filled {n_filled} nodata cell(s) of {z.size} by inpainting; terrain there is "
                   f"interpolated")
            log.warning(msg)
            warnings.warn(msg, DemHolesFilled, stacklevel=3)
        return cls(z, Tw, frame, vertical_accuracy_m=vertical_accuracy_m, texture_bounds_crs=texture_bounds,
                   info=info)

    # ------------------------------------------------------------------------------------------------------
    # Geometry
    # ------------------------------------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape  # type: ignore[return-value]

    @property
    def bounds_enu(self) -> np.ndarray:
        """[[east_min, north_min], [east_max, north_max]] of the grid nodes (metres)."""
        xy = self.grid_enu[..., :2].reshape(-1, 2)
        return np.array([xy.min(axis=0), xy.max(axis=0)])

    def faces(self) -> np.ndarray:
        """(2 (rows-1) (cols-1), 3) vertex indices; cell k = i (cols-1) + j has faces 2k (NW, SW, NE) and
        2k+1 (NE, SW, SE); counter-clockwise seen from above."""
        R, C = self.shape
        i, j = np.meshgrid(np.arange(R - 1), np.arange(C - 1), indexing="ij")
        a = (i * C + j).ravel()
        b, c, d = a + 1, a + C, a + C + 1
        f = np.empty((a.size * 2, 3), dtype=np.int64)
        f[0::2] = np.column_stack([a, c, b])
        f[1::2] = np.column_stack([b, c, d])
        return f

    def mesh(self, texture: "Image.Image | None" = None, *,
             texture_bounds_crs: tuple[float, float, float, float] | None = None) -> trimesh.Trimesh:
        """The terrain surface in ENU metres. With ``texture`` (an image north-up over ``texture_bounds_crs``, by
        default the whole source DEM), per-vertex UVs drape it (u east, v north; v = 1 at the image's top row)."""
        visual = None
        if texture is not None:
            left, bottom, right, top = texture_bounds_crs if texture_bounds_crs is not None else self.texture_bounds_crs
            xy = self.node_crs.reshape(-1, 2)
            uv = np.column_stack([(xy[:, 0] - left) / (right - left), (xy[:, 1] - bottom) / (top - bottom)])
            visual = trimesh.visual.TextureVisuals(uv=uv, image=texture)
        return trimesh.Trimesh(vertices=self.grid_enu.reshape(-1, 3).copy(), faces=self.faces(), visual=visual,
                               process=False)

    # ------------------------------------------------------------------------------------------------------
    # Queries
    # ------------------------------------------------------------------------------------------------------
    def _fit_index_map(self) -> None:
        """Fit (column, row) of a node as a cubic polynomial of its normalised ENU east/north."""
        R, C = self.shape
        step_r = max(1, R // 100)
        step_c = max(1, C // 100)
        ri = np.unique(np.r_[np.arange(0, R, step_r), R - 1])
        ci = np.unique(np.r_[np.arange(0, C, step_c), C - 1])
        sub = self.grid_enu[np.ix_(ri, ci)][..., :2].reshape(-1, 2)
        rr, cc = np.meshgrid(ri, ci, indexing="ij")
        self._xy_centre = sub.mean(axis=0)
        self._xy_scale = max(float(np.abs(sub - self._xy_centre).max()), 1e-9)
        A = _poly_terms(*((sub - self._xy_centre) / self._xy_scale).T)
        target = np.column_stack([cc.ravel(), rr.ravel()]).astype(float)
        self._index_coef, *_ = np.linalg.lstsq(A, target, rcond=None)
        self.info["index_fit_max_error_cells"] = float(np.abs(A @ self._index_coef - target).max())

    def _fractional_index(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = (xy - self._xy_centre) / self._xy_scale
        cr = _poly_terms(n[:, 0], n[:, 1]) @ self._index_coef
        return cr[:, 0], cr[:, 1]

    def _locate(self, xy_enu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Face index (-1 outside) and barycentric weights (n, 3) of the mesh triangle under each query point."""
        xy = np.asarray(xy_enu, dtype=float)
        if xy.ndim == 1:
            xy = xy[None, :]
        if xy.ndim != 2 or xy.shape[1] < 2:
            raise ValueError(f"xy_enu.shape={np.shape(xy_enu)} but expected (n, 2)")
        xy = xy[:, :2]
        n = len(xy)
        face = np.full(n, -1, dtype=np.int64)
        bary = np.full((n, 3), np.nan)
        if n == 0:
            return face, bary
        R, C = self.shape
        G = self.grid_enu
        u, v = self._fractional_index(xy)
        finite = np.isfinite(u) & np.isfinite(v) & np.all(np.isfinite(xy), axis=1)
        # Node k sits at fractional index k, so cell k spans [k, k + 1].
        j0 = np.floor(np.where(finite, u, -10.0)).astype(np.int64)
        i0 = np.floor(np.where(finite, v, -10.0)).astype(np.int64)
        rem = np.nonzero(finite & (j0 > -2) & (j0 < C) & (i0 > -2) & (i0 < R))[0]
        for di, dj in _NEIGHBOURS:
            if rem.size == 0:
                break
            i = i0[rem] + di
            j = j0[rem] + dj
            ok = (i >= 0) & (i < R - 1) & (j >= 0) & (j < C - 1)
            q = rem[ok]
            i, j = i[ok], j[ok]
            if q.size == 0:
                continue
            p = xy[q]
            a, b, c, d = G[i, j], G[i, j + 1], G[i + 1, j], G[i + 1, j + 1]
            found = np.zeros(q.size, dtype=bool)
            for t, (P0, P1, P2) in enumerate(((a, c, b), (b, c, d))):
                w = _barycentric(p, P0, P1, P2)
                inside = ~found & np.all(w >= -_BARY_EPS, axis=1)
                sel = q[inside]
                face[sel] = 2 * (i[inside] * (C - 1) + j[inside]) + t
                bary[sel] = w[inside]
                found |= inside
            done = np.zeros(n, dtype=bool)
            done[q[found]] = True
            rem = rem[~done[rem]]
        return face, bary

    def _face_vertices(self, face: np.ndarray) -> np.ndarray:
        """(n, 3, 3) ENU vertices of faces (as in :meth:`faces`)."""
        R, C = self.shape
        k, t = np.divmod(face, 2)
        i, j = np.divmod(k, C - 1)
        G = self.grid_enu
        a, b, c, d = G[i, j], G[i, j + 1], G[i + 1, j], G[i + 1, j + 1]
        t1 = (t == 1)[:, None]
        return np.stack([np.where(t1, b, a), c, np.where(t1, d, b)], axis=1)

    def height_at(self, xy_enu: np.ndarray) -> np.ndarray:
        """(n, 2) ENU east/north -> (n,) ENU up of the mesh surface there (NaN outside the terrain)."""
        face, bary = self._locate(xy_enu)
        out = np.full(len(face), np.nan)
        ok = face >= 0
        if ok.any():
            V = self._face_vertices(face[ok])
            out[ok] = np.einsum("nk,nk->n", bary[ok], V[:, :, 2])
        return out

    def normal_at(self, xy_enu: np.ndarray) -> np.ndarray:
        """(n, 2) ENU east/north -> (n, 3) unit, up-facing normals of the mesh triangle there (NaN outside)."""
        face, _ = self._locate(xy_enu)
        out = np.full((len(face), 3), np.nan)
        ok = face >= 0
        if ok.any():
            V = self._face_vertices(face[ok])
            nrm = np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])
            nrm *= np.sign(nrm[:, 2:3])
            out[ok] = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
        return out

    def contains(self, xy_enu: np.ndarray) -> np.ndarray:
        """(n,) bool: whether the terrain covers each ENU east/north point."""
        return self._locate(xy_enu)[0] >= 0

    def __repr__(self) -> str:
        b = self.bounds_enu
        return (f"TerrainModel({self.shape[0]}x{self.shape[1]} nodes, cell {abs(self.transform.a):.3g} m, "
                f"E [{b[0, 0]:.1f}, {b[1, 0]:.1f}] N [{b[0, 1]:.1f}, {b[1, 1]:.1f}] m)")


def _barycentric(p: np.ndarray, P0: np.ndarray, P1: np.ndarray, P2: np.ndarray) -> np.ndarray:
    """Barycentric weights (n, 3) of 2-D points p in triangles (P0, P1, P2), using east/north only."""
    v0x, v0y = P1[:, 0] - P0[:, 0], P1[:, 1] - P0[:, 1]
    v1x, v1y = P2[:, 0] - P0[:, 0], P2[:, 1] - P0[:, 1]
    v2x, v2y = p[:, 0] - P0[:, 0], p[:, 1] - P0[:, 1]
    den = v0x * v1y - v1x * v0y
    l1 = (v2x * v1y - v1x * v2y) / den
    l2 = (v0x * v2y - v2x * v0y) / den
    return np.column_stack([1.0 - l1 - l2, l1, l2])


def simplify_terrain_mesh(model: TerrainModel, max_error_m: float, *, max_iterations: int = 60
                          ) -> tuple[trimesh.Trimesh, dict]:
    """A mesh of the terrain with fewer vertices where it is flat: greedy refinement (Garland & Heckbert's
    insertion, batched): start from the grid's border nodes, Delaunay-triangulate in east/north, and add, in each
    triangle, the grid node whose height differs most from the triangle's plane, until no node differs by more
    than ``max_error_m``.

    Returns ``(mesh, info)``; ``info["max_error_m"]`` is the largest vertical difference between the simplified
    surface and the DEM at any grid node (<= ``max_error_m``), ``info["n_vertices"]``/``["n_vertices_full"]``.
    Vertices are grid nodes (exact ENU positions); the border is kept node for node, so the outline is the same.
    """
    from scipy.spatial import Delaunay

    if not max_error_m > 0:
        raise ValueError(f"max_error_m={max_error_m} must be positive")
    R, C = model.shape
    G = model.grid_enu.reshape(-1, 3)
    xy = G[:, :2] - G[:, :2].mean(axis=0)
    border = np.zeros((R, C), bool)
    border[0, :] = border[-1, :] = border[:, 0] = border[:, -1] = True
    sel = border.ravel().copy()
    err_max = np.inf
    tri = None
    for it in range(max_iterations):
        idx = np.nonzero(sel)[0]
        tri = Delaunay(xy[idx])
        simp = tri.find_simplex(xy)
        inside = simp >= 0
        err = np.zeros(len(G))
        T = tri.transform[simp[inside]]
        b2 = np.einsum("nij,nj->ni", T[:, :2, :], xy[inside] - T[:, 2, :])
        bary = np.column_stack([b2, 1.0 - b2.sum(axis=1)])
        zt = np.einsum("nk,nk->n", bary, G[idx[tri.simplices[simp[inside]]], 2])
        err[inside] = np.abs(zt - G[inside, 2])
        err[~inside & ~sel] = np.inf  # outside the hull (rounding on the border): insert
        err[sel] = 0.0
        err_max = float(err.max())
        if err_max <= max_error_m:
            break
        bad = np.nonzero(err > max_error_m)[0]
        key = np.where(simp[bad] >= 0, simp[bad], -1 - bad)  # one insertion per triangle per round
        order = np.lexsort((-err[bad], key))
        first = np.ones(len(order), bool)
        first[1:] = key[order][1:] != key[order][:-1]
        sel[bad[order][first]] = True
    faces = idx[tri.simplices]  # the last triangulation (if the loop ran out, info says the error it reached)
    V = G
    nz = np.cross(V[faces[:, 1]] - V[faces[:, 0]], V[faces[:, 2]] - V[faces[:, 0]])[:, 2]
    # the border nodes are nearly collinear in east/north (a grid row after the exact CRS -> ENU conversion), so
    # Delaunay leaves slivers of no plan area along the hull: near-vertical walls whose up/down orientation is
    # numerical noise. They cover nothing in plan; drop them.
    sliver = np.abs(nz) < 1e-4 * float(np.median(np.abs(nz)))
    faces, nz = faces[~sliver], nz[~sliver]
    faces[nz < 0] = faces[nz < 0][:, [0, 2, 1]]  # counter-clockwise seen from above
    used, inv = np.unique(faces, return_inverse=True)
    mesh = trimesh.Trimesh(vertices=V[used].copy(), faces=inv.reshape(-1, 3), process=False)
    info = {"max_error_m": err_max, "tolerance_m": float(max_error_m), "n_vertices": int(len(used)),
            "n_vertices_full": int(len(G)), "n_faces": int(len(mesh.faces)), "iterations": it + 1,
            "border_slivers_dropped": int(sliver.sum())}
    return mesh, info
