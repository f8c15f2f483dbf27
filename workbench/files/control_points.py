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

from ..core.frames import SceneFrame, enu_from_layer_coords
from ..core.io import atomic_write_bytes, atomic_write_text, read_json, to_json
from ..core.layout import CONTROL_POINTS_FILE
from ..core.settings import describe_validation_error
from ..errors import InputError

log = logging.getLogger(__name__)

MAX_DISTANCE_M = 20_000.0  # a control point farther than this from the scene origin is a CRS or axis-order mistake

__all__ = ["CONTROL_POINTS_FILE", "ControlPoint", "ControlPointsDoc", "load_control_points", "parse_control_points",
           "save_control_points", "BACKUP_SUFFIX"]

BACKUP_SUFFIX = ".bak"  # the file as it was before the last save that changed it


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


def save_control_points(path: str | Path, data: Any, frame: SceneFrame) -> tuple[Path, Path | None]:
    """Check ``data`` completely as :func:`parse_control_points` reads it (an :class:`InputError` naming the point
    and the value; nothing written), then write it to ``path`` atomically (temp file, rename), first keeping the
    previous file, when it differs, as ``control_points.json.bak`` beside it. Returns (path, backup or None)."""
    path = Path(path)
    parse_control_points(data, frame, str(path))  # every check the georef stage makes, in the scene frame
    doc = ControlPointsDoc.model_validate(data)  # valid: parse_control_points has checked it
    text = to_json(doc.model_dump(exclude_defaults=True))
    backup = None
    old = path.read_bytes() if path.is_file() else None
    if old is not None and old != text.encode("utf-8"):
        backup = atomic_write_bytes(path.with_name(path.name + BACKUP_SUFFIX), old)
    atomic_write_text(path, text)
    log.info("wrote %d control points to %s", len(doc.points), path)
    return path, backup
