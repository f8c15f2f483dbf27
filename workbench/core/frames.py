"""Frames and transforms: project CRS <-> WGS84 <-> ECEF <-> scene ENU, rigid transforms, heading/pitch/roll.

See ``docs/conventions.md``, which this module implements. In short:

* The **scene frame** ("world") is a local East-North-Up tangent frame in metres whose origin is the
  incident's reference point (``location.lat``, ``location.lon``, ``location.height_m``).
  Coordinates go project CRS -> geographic -> ECEF -> ENU, every pyproj transformer built with
  ``always_xy=True`` (longitude/easting first). Heights are in the DEM's vertical datum and are used as
  ellipsoidal heights for the ECEF step; over an incident site the geoid undulation is constant to
  centimetres, so this only shifts the frame vertically by a constant, which the origin height absorbs.
* Transforms are named ``b_from_a``: ``p_b = b_from_a.apply(p_a)``, and compose right to left:
  ``c_from_a = c_from_b @ b_from_a``.
* Carriage frame: x forward (towards the front coupler), y left, z up; origin on the carriage's centre
  line, midway between the couplers, at top-of-rail height. Heading is the compass bearing of the
  carriage's x axis (degrees clockwise from true north, [0, 360)); pitch is nose-up positive; roll is
  right-side-down positive. ``world_from_carriage = Rz(90 deg - heading) @ Ry(-pitch) @ Rx(roll)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError

from ..errors import InputError

from .crs import parse_projected_crs  # noqa: F401 - re-exported
from .geometry import rot_x, rot_y, rot_z  # rot_z also re-exported (tests/test_export.py)


def _as_points(points: np.ndarray, dim: int = 3, name: str = "points") -> tuple[np.ndarray, bool]:
    a = np.asarray(points, dtype=float)
    single = a.ndim == 1
    if single:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != dim:
        raise ValueError(f"{name}.shape={np.shape(points)} but expected ({dim},) or (n, {dim})")
    return a, single


# ----------------------------------------------------------------------------------------------------------
# Rotations
# ----------------------------------------------------------------------------------------------------------
def rotation_from_hpr(heading_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """``world_from_carriage`` rotation (3, 3) from heading (compass, deg), pitch (nose up, deg), roll (right down, deg)."""
    yaw = np.deg2rad(90.0 - heading_deg)
    return rot_z(yaw) @ rot_y(-np.deg2rad(pitch_deg)) @ rot_x(np.deg2rad(roll_deg))


def hpr_from_rotation(world_from_carriage: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_from_hpr`: (heading in [0, 360), pitch in [-90, 90], roll in (-180, 180]) degrees."""
    R = np.asarray(world_from_carriage, dtype=float)
    if R.shape != (3, 3):
        raise ValueError(f"{R.shape=} but expected (3, 3)")
    # R = Rz(yaw) Ry(b) Rx(roll) with b = -pitch:  R[2,0] = -sin(b) = sin(pitch)
    pitch = np.arcsin(np.clip(R[2, 0], -1.0, 1.0))
    yaw = np.arctan2(R[1, 0], R[0, 0])
    roll = np.arctan2(R[2, 1], R[2, 2])
    heading = (90.0 - np.rad2deg(yaw)) % 360.0
    return float(heading), float(np.rad2deg(pitch)), float(np.rad2deg(roll))


def is_rotation(R: np.ndarray, tol: float = 1e-9) -> bool:
    R = np.asarray(R, dtype=float)
    return R.shape == (3, 3) and np.allclose(R @ R.T, np.eye(3), atol=tol) and abs(np.linalg.det(R) - 1.0) < tol


# ----------------------------------------------------------------------------------------------------------
# Rigid transforms with named frames
# ----------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Rigid:
    """A rigid transform ``to_frame_from_from_frame``: ``p_to = R @ p_from + t``.

    Composition checks the frame names, so ``cam_from_world @ carriage_from_world`` is refused.
    """

    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,) metres
    to_frame: str
    from_frame: str

    def __post_init__(self) -> None:
        R = np.asarray(self.rotation, dtype=float)
        t = np.asarray(self.translation, dtype=float).reshape(-1)
        if R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"rotation.shape={R.shape}, translation.shape={t.shape}; expected (3, 3) and (3,)")
        if not is_rotation(R, tol=1e-6):
            raise ValueError(f"{self.to_frame}_from_{self.from_frame}: rotation is not orthonormal with det +1")
        object.__setattr__(self, "rotation", R)
        object.__setattr__(self, "translation", t)

    @property
    def name(self) -> str:
        return f"{self.to_frame}_from_{self.from_frame}"

    @classmethod
    def from_matrix(cls, matrix: np.ndarray, to_frame: str, from_frame: str) -> "Rigid":
        M = np.asarray(matrix, dtype=float)
        if M.shape != (4, 4):
            raise ValueError(f"{M.shape=} but expected (4, 4)")
        return cls(M[:3, :3], M[:3, 3], to_frame, from_frame)

    @property
    def matrix(self) -> np.ndarray:
        M = np.eye(4)
        M[:3, :3] = self.rotation
        M[:3, 3] = self.translation
        return M

    def inverse(self) -> "Rigid":
        Rt = self.rotation.T
        return Rigid(Rt, -Rt @ self.translation, self.from_frame, self.to_frame)

    def __matmul__(self, other: "Rigid") -> "Rigid":
        if not isinstance(other, Rigid):
            return NotImplemented
        if self.from_frame != other.to_frame:
            raise ValueError(f"cannot compose {self.name} @ {other.name}: frames {self.from_frame!r} and "
                             f"{other.to_frame!r} differ")
        return Rigid(self.rotation @ other.rotation, self.rotation @ other.translation + self.translation,
                     self.to_frame, other.from_frame)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points (n, 3) or (3,) from ``from_frame`` to ``to_frame``."""
        P, single = _as_points(points)
        out = P @ self.rotation.T + self.translation
        return out[0] if single else out


# ----------------------------------------------------------------------------------------------------------
# Scene frame: project CRS <-> WGS84 <-> ENU
# ----------------------------------------------------------------------------------------------------------
class SceneFrame:
    """The incident's local ENU scene frame and its links to the project CRS and to WGS84.

    ``lat_deg``, ``lon_deg``: the reference point (WGS84 degrees). ``height_m``: its height in the DEM's
    vertical datum; the ENU origin sits there.
    """

    def __init__(self, crs: str | int | CRS, lat_deg: float, lon_deg: float, height_m: float = 0.0) -> None:
        self.crs = crs if isinstance(crs, CRS) else parse_projected_crs(crs)
        if not (-90.0 <= lat_deg <= 90.0 and -180.0 <= lon_deg <= 180.0):
            raise ValueError(f"reference point lat={lat_deg}, lon={lon_deg} is outside WGS84 bounds")
        self.lat_deg = float(lat_deg)
        self.lon_deg = float(lon_deg)
        self.height_m = float(height_m)
        lat, lon = np.deg2rad(self.lat_deg), np.deg2rad(self.lon_deg)
        # Rows: east, north, up unit vectors in ECEF.
        self._enu_from_ecef_R = np.array([
            [-np.sin(lon), np.cos(lon), 0.0],
            [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)],
            [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)],
        ])
        self._origin_ecef = self._ecef_from_geodetic(np.array([[self.lon_deg, self.lat_deg, self.height_m]]))[0]

    # -- transformers (always_xy: lon/easting first) --
    @cached_property
    def _geo_from_crs(self) -> Transformer:
        return Transformer.from_crs(self.crs, "EPSG:4326", always_xy=True)

    @cached_property
    def _crs_from_geo(self) -> Transformer:
        return Transformer.from_crs("EPSG:4326", self.crs, always_xy=True)

    @cached_property
    def _ecef_from_geo(self) -> Transformer:
        return Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)

    def _ecef_from_geodetic(self, lon_lat_h: np.ndarray) -> np.ndarray:
        x, y, z = self._ecef_from_geo.transform(lon_lat_h[:, 0], lon_lat_h[:, 1], lon_lat_h[:, 2])
        return np.column_stack([x, y, z])

    def _geodetic_from_ecef(self, ecef: np.ndarray) -> np.ndarray:
        lon, lat, h = self._ecef_from_geo.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2], direction="INVERSE")
        return np.column_stack([lon, lat, h])

    # -- public API --
    @property
    def origin_crs(self) -> np.ndarray:
        """The scene origin in the project CRS: (easting, northing, height) metres."""
        return self.crs_from_wgs84(np.array([self.lon_deg, self.lat_deg, self.height_m]))

    def enu_from_wgs84(self, lon_lat_h: np.ndarray) -> np.ndarray:
        """(n, 3) longitude deg, latitude deg, height m -> (n, 3) ENU metres."""
        P, single = _as_points(lon_lat_h, name="lon_lat_h")
        enu = (self._ecef_from_geodetic(P) - self._origin_ecef) @ self._enu_from_ecef_R.T
        return enu[0] if single else enu

    def wgs84_from_enu(self, enu: np.ndarray) -> np.ndarray:
        """(n, 3) ENU metres -> (n, 3) longitude deg, latitude deg, height m."""
        P, single = _as_points(enu, name="enu")
        geo = self._geodetic_from_ecef(P @ self._enu_from_ecef_R + self._origin_ecef)
        return geo[0] if single else geo

    def wgs84_from_crs(self, xyh: np.ndarray) -> np.ndarray:
        """(n, 3) easting, northing, height in the project CRS -> (n, 3) lon, lat, height."""
        P, single = _as_points(xyh, name="xyh")
        lon, lat = self._geo_from_crs.transform(P[:, 0], P[:, 1])
        out = np.column_stack([lon, lat, P[:, 2]])
        return out[0] if single else out

    def crs_from_wgs84(self, lon_lat_h: np.ndarray) -> np.ndarray:
        P, single = _as_points(lon_lat_h, name="lon_lat_h")
        x, y = self._crs_from_geo.transform(P[:, 0], P[:, 1])
        out = np.column_stack([x, y, P[:, 2]])
        return out[0] if single else out

    def enu_from_crs(self, xyh: np.ndarray) -> np.ndarray:
        """(n, 3) easting, northing, height (project CRS, metres) -> (n, 3) ENU metres."""
        P, single = _as_points(xyh, name="xyh")
        out = self.enu_from_wgs84(self.wgs84_from_crs(P))
        return out[0] if single else out

    def crs_from_enu(self, enu: np.ndarray) -> np.ndarray:
        P, single = _as_points(enu, name="enu")
        out = self.crs_from_wgs84(self.wgs84_from_enu(P))
        return out[0] if single else out

    def grid_convergence_deg(self) -> float:
        """Angle from true north to the CRS's grid north at the origin (degrees, positive clockwise)."""
        o = self.origin_crs
        p = self.enu_from_crs(np.array([[o[0], o[1], o[2]], [o[0], o[1] + 100.0, o[2]]]))
        d = p[1] - p[0]
        return float(np.rad2deg(np.arctan2(d[0], d[1])))


def horizontal_crs(crs: CRS) -> CRS:
    """The horizontal part of a compound CRS (e.g. EPSG:7415 = RD New + NAP height), else ``crs``."""
    if crs.is_compound and crs.sub_crs_list:
        return crs.sub_crs_list[0]
    return crs


def enu_from_layer_coords(coords: np.ndarray, crs_value: Any, frame: SceneFrame, where: str) -> np.ndarray:
    """(n, 3) coordinates of a GIS layer in ``crs_value`` (x/lon first, height in the DEM datum) -> (n, 3) ENU.

    The project CRS goes through :meth:`SceneFrame.enu_from_crs`; any other projected CRS and geographic CRSs
    through WGS84 (horizontal only; heights are kept). ``where`` names the file in error messages.
    """
    try:
        crs = CRS.from_user_input(crs_value)
    except CRSError as exc:
        raise InputError(f"{where}: crs = {crs_value!r} is not a CRS pyproj knows ({exc}); give an EPSG code such "
                         f"as 'EPSG:4326' (lon, lat, h) or the project CRS {frame.crs.to_string()}") from None
    P = np.asarray(coords, dtype=float).reshape(-1, 3)
    h = horizontal_crs(crs)
    if h.equals(frame.crs, ignore_axis_order=True) or (h.to_epsg() is not None and h.to_epsg() == frame.crs.to_epsg()):
        return frame.enu_from_crs(P)
    if h.is_geographic:
        if np.any(np.abs(P[:, 1]) > 90.0):
            raise InputError(f"{where}: latitude {P[np.argmax(np.abs(P[:, 1])), 1]!r} is beyond +-90 in a "
                             f"geographic CRS ({crs_value}); coordinates are [longitude, latitude, height], "
                             f"longitude first")
        lon, lat = Transformer.from_crs(h, "EPSG:4326", always_xy=True).transform(P[:, 0], P[:, 1])
    elif h.is_projected:
        lon, lat = Transformer.from_crs(h, "EPSG:4326", always_xy=True).transform(P[:, 0], P[:, 1])
    else:
        raise InputError(f"{where}: crs = {crs_value!r} ({crs.name}) is neither projected nor geographic; give an "
                         f"EPSG code")
    return frame.enu_from_wgs84(np.column_stack([lon, lat, P[:, 2]]))
