"""Ground control points: landmarks with known coordinates, picked in the photos (``control_points.json``).

Format (docs/gis.md)::

    {"crs": "EPSG:32618",                       # any CRS pyproj knows: the project CRS, another projected
                                                 # CRS (E, N, h) or a geographic one (lon, lat, h; longitude first)
     "description": "optional free text",
     "points": [
        {"name": "roof_b12_ne", "coords": [E, N, h], "sigma_m": 0.05,
         "kind": "roof_corner",                  # optional free text: what the landmark is
         "pixels": {"pano_01.jpg": [812.4, 433.0], "pano_02.jpg": [120.0, 410.5]}}
     ],
     "track_picks": [                            # optional: points picked on a railway line in a photo
        {"photo": "pano_01.jpg", "line": "hudson-line-1",  # the line's id in terrain.railways ("": its only line)
         "rail": "left",                         # "centre" (default), "left" or "right" of increasing chainage
         "gauge_m": 1.435,                       # rails: at (gauge + rail head) / 2 from the centre line
         "pixels": [[412.0, 700.5], [520.3, 655.0]]}  # anywhere on that rail: not matched to places on the line
     ]}

Heights are in the DEM's vertical datum (like ``location.height_m``). Pixels follow docs/conventions.md
(pixel (0, 0) is the centre of the top-left pixel) in the photo as it is on disk (distorted). ``pixels`` may
name photos of several photo sets; a route uses the ones it has.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..core.frames import SceneFrame, enu_from_layer_coords
from ..core.io import atomic_write_bytes, atomic_write_text, read_json, to_json
from ..core.layout import CONTROL_POINTS_FILE
from ..core.settings import describe_validation_error
from ..errors import InputError

log = logging.getLogger(__name__)

MAX_DISTANCE_M = 20_000.0  # a control point farther than this from the scene origin is a CRS or axis-order mistake

__all__ = ["CONTROL_POINTS_FILE", "ControlPoint", "ControlPointsDoc", "load_control_points", "parse_control_points",
           "save_control_points", "BACKUP_SUFFIX", "TrackPick", "parse_track_picks", "load_track_picks", "RAILS",
           "STANDARD_GAUGE_M", "RAIL_HEAD_WIDTH_M"]

RAILS = ("centre", "left", "right")  # which line of a track a pick is on: its centre line, or a rail
STANDARD_GAUGE_M = 1.435  # between the rails' running edges
RAIL_HEAD_WIDTH_M = 0.07  # a rail's pick is taken at its head's middle: (gauge + head) / 2 from the centre line

BACKUP_SUFFIX = ".bak"  # the file as it was before the last save that changed it


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ControlPointSpec(_Strict):
    name: Annotated[str, Field(min_length=1)]
    coords: Annotated[list[float], Field(min_length=3, max_length=3)]
    sigma_m: Annotated[float, Field(gt=0.0)] = 0.05
    kind: str = ""
    pixels: dict[str, Annotated[list[float], Field(min_length=2, max_length=2)]] = {}


class TrackPickSpec(_Strict):
    photo: Annotated[str, Field(min_length=1)]
    line: str = ""
    rail: Literal["centre", "left", "right"] = "centre"
    gauge_m: Annotated[float, Field(gt=0.5, le=2.0)] = STANDARD_GAUGE_M
    pixels: Annotated[list[Annotated[list[float], Field(min_length=2, max_length=2)]], Field(min_length=1)]


class ControlPointsDoc(_Strict):
    crs: Annotated[str, Field(min_length=1)]
    description: str = ""
    points: list[ControlPointSpec] = []
    track_picks: list[TrackPickSpec] = []

    @model_validator(mode="after")
    def _points_or_track_picks(self) -> "ControlPointsDoc":
        if not self.points and not self.track_picks:
            raise ValueError("neither 'points' nor 'track_picks' has an entry; give landmarks with coordinates "
                             "picked in the photos, or points picked on the railway line")
        return self


@dataclass(frozen=True)
class ControlPoint:
    """One control point in the scene frame: ``enu`` (3,) metres, 1-sigma ``sigma_m``, pixels per photo name."""

    name: str
    enu: np.ndarray
    sigma_m: float
    pixels: dict[str, np.ndarray] = field(default_factory=dict)
    kind: str = ""
    coords: tuple[float, float, float] = (0.0, 0.0, 0.0)  # as written in the file, in its CRS


@dataclass(frozen=True)
class TrackPick:
    """Points picked on one line of a railway track in one photo (``track_picks[]``): ``pixels`` (n, 2) anywhere on
    the line (not matched to places on it), the railway line's ``line`` id ("" = the layer's only line), which
    ``rail`` (``centre``, ``left`` or ``right`` of the direction of increasing chainage), the track's ``gauge_m``."""

    photo: str
    line: str
    rail: str
    gauge_m: float
    pixels: np.ndarray

    @property
    def offset_m(self) -> float:
        """The picked line's horizontal offset from the track's centre line, positive to the left: 0 for the centre,
        +-(gauge + rail head) / 2 for a rail (the middle of its head)."""
        half = 0.5 * (self.gauge_m + RAIL_HEAD_WIDTH_M)
        return {"centre": 0.0, "left": half, "right": -half}[self.rail]


def _validated(data: Any, where: str) -> ControlPointsDoc:
    try:
        return ControlPointsDoc.model_validate(data)
    except ValidationError as exc:
        raise InputError(describe_validation_error(exc, where, "see docs/gis.md (control_points.json)")) from None


def parse_track_picks(data: Any, where: str = CONTROL_POINTS_FILE) -> list[TrackPick]:
    """The ``track_picks`` of a ``control_points.json`` document (validated as :func:`parse_control_points` does)."""
    doc = _validated(data, where)
    out = []
    for i, t in enumerate(doc.track_picks):
        uv = np.asarray(t.pixels, dtype=float)
        if not np.all(np.isfinite(uv)):
            raise InputError(f"{where}: track_picks[{i}] (photo {t.photo!r}): a pixel is not a finite number; fix or "
                             f"remove it")
        out.append(TrackPick(photo=t.photo, line=t.line, rail=t.rail, gauge_m=float(t.gauge_m), pixels=uv))
    return out


def load_track_picks(path: str | Path) -> list[TrackPick]:
    """The track picks of ``control_points.json`` (none when the file has no ``track_picks``)."""
    path = Path(path)
    return parse_track_picks(read_json(path), str(path))


def parse_control_points(data: Any, frame: SceneFrame, where: str = CONTROL_POINTS_FILE) -> list[ControlPoint]:
    """Validate a ``control_points.json`` document and convert every point into the scene frame (its track picks:
    :func:`parse_track_picks`)."""
    doc = _validated(data, where)
    parse_track_picks(data, where)
    if not doc.points:
        return []
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
    log.info("wrote %d control points and %d track picks to %s", len(doc.points), len(doc.track_picks), path)
    return path, backup
