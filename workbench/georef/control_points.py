"""Ground control points: landmarks with known coordinates, picked in the photos (``control_points.json``).

Format (docs/gis.md)::

    {"crs": "EPSG:32618",                       # any CRS pyproj knows: the project CRS, another projected
                                                 # CRS (E, N, h) or a geographic one (lon, lat, h; longitude first)
     "description": "optional free text",
     "points": [
        {"name": "roof_b12_ne", "coords": [E, N, h], "sigma_m": 0.05,
         "kind": "roof_corner",                  # optional free text: what the landmark is
         "pixels": {"pano_01.jpg": [812.4, 433.0], "pano_02.jpg": [120.0, 410.5]}}
     ]}

Heights are in the DEM's vertical datum (like ``location.height_m``). Pixels follow docs/conventions.md
(pixel (0, 0) is the centre of the top-left pixel) in the photo as it is on disk (distorted). ``pixels`` may
name photos of several photo sets; a route uses the ones it has.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError

from ..core.frames import SceneFrame
from ..core.io import read_json
from ..core.layout import CONTROL_POINTS_FILE
from ..core.settings import describe_validation_error
from ..errors import InputError

log = logging.getLogger(__name__)

MAX_DISTANCE_M = 20_000.0  # a control point farther than this from the scene origin is a CRS or axis-order mistake

__all__ = ["CONTROL_POINTS_FILE", "ControlPoint", "ControlPointsDoc", "load_control_points", "parse_control_points",
           "enu_from_layer_coords"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ControlPointSpec(_Strict):
    name: Annotated[str, Field(min_length=1)]
    coords: Annotated[list[float], Field(min_length=3, max_length=3)]
    sigma_m: Annotated[float, Field(gt=0.0)] = 0.05
    kind: str = ""
    pixels: dict[str, Annotated[list[float], Field(min_length=2, max_length=2)]] = {}


class ControlPointsDoc(_Strict):
    crs: Annotated[str, Field(min_length=1)]
    description: str = ""
    points: Annotated[list[ControlPointSpec], Field(min_length=1)]


@dataclass(frozen=True)
class ControlPoint:
    """One control point in the scene frame: ``enu`` (3,) metres, 1-sigma ``sigma_m``, pixels per photo name."""

    name: str
    enu: np.ndarray
    sigma_m: float
    pixels: dict[str, np.ndarray] = field(default_factory=dict)
    kind: str = ""
    coords: tuple[float, float, float] = (0.0, 0.0, 0.0)  # as written in the file, in its CRS


def _horizontal(crs: CRS) -> CRS:
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
    h = _horizontal(crs)
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


def parse_control_points(data: Any, frame: SceneFrame, where: str = CONTROL_POINTS_FILE) -> list[ControlPoint]:
    """Validate a ``control_points.json`` document and convert every point into the scene frame."""
    try:
        doc = ControlPointsDoc.model_validate(data)
    except ValidationError as exc:
        raise InputError(describe_validation_error(exc, where, "see docs/gis.md (control_points.json)")) from None
    names = [p.name for p in doc.points]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"{where}: control point name(s) {dup} appear more than once; names must be unique")
    coords = np.array([p.coords for p in doc.points], dtype=float)
    if not np.all(np.isfinite(coords)):
        raise InputError(f"{where}: coordinates must be finite numbers")
    enu = enu_from_layer_coords(coords, doc.crs, frame, where)
    dist = np.linalg.norm(enu[:, :2], axis=1)
    far = np.nonzero(dist > MAX_DISTANCE_M)[0]
    if far.size:
        i = int(far[0])
        raise InputError(f"{where}: control point {names[i]!r} at {list(coords[i])} ({doc.crs}) lies "
                         f"{dist[i] / 1000:.1f} km from the incident's reference point; check 'crs' and the "
                         f"axis order ([E, N, h] or [lon, lat, h], longitude first)")
    out = []
    for p, e in zip(doc.points, enu):
        pix = {}
        for photo, uv in p.pixels.items():
            a = np.asarray(uv, dtype=float)
            if not np.all(np.isfinite(a)):
                raise InputError(f"{where}: point {p.name!r}, photo {photo!r}: pixel {uv} is not finite")
            pix[photo] = a
        out.append(ControlPoint(name=p.name, enu=np.asarray(e, float), sigma_m=float(p.sigma_m), pixels=pix,
                                kind=p.kind, coords=tuple(float(c) for c in p.coords)))
    return out


def load_control_points(path: str | Path, frame: SceneFrame) -> list[ControlPoint]:
    """Read ``control_points.json``; :class:`InputError` naming the file, the point and the value on bad input."""
    path = Path(path)
    return parse_control_points(read_json(path), frame, str(path))
