"""EXIF GPS of a photo: where the camera stood (a prior on its centre) and, where the phone wrote it, which way it
looked (``GPSImgDirection``, a prior on its heading); docs/gis.md, "Priors from the photos' GPS and compass".

A malformed tag (not a number, NaN or infinite, out of range, a zero denominator, an unknown reference) is
ignored with a :class:`GpsTagIgnored` warning naming the photo and the tag; it never stops the run.
"""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from PIL import Image, UnidentifiedImageError

from ..errors import WorkbenchWarning

log = logging.getLogger(__name__)

__all__ = ["GpsFix", "GpsTagIgnored", "read_gps", "read_gps_fix"]

_GPS_IFD = 0x8825
# EXIF 2.32 GPS tag numbers
_LAT_REF, _LAT, _LON_REF, _LON, _ALT_REF, _ALT = 1, 2, 3, 4, 5, 6
_DIR_REF, _DIR, _H_ERROR = 16, 17, 31


class GpsTagIgnored(WorkbenchWarning):
    """A photo's EXIF GPS tag is malformed (not a number, NaN, out of range): it is ignored."""


@dataclass(frozen=True)
class GpsFix:
    """What a photo's EXIF GPS block says. ``lon_deg``/``lat_deg`` None: no usable position; ``alt_m`` None: no
    usable altitude; ``h_error_m``: ``GPSHPositioningError`` (metres); ``direction_deg`` / ``direction_ref``:
    ``GPSImgDirection`` (degrees clockwise from north, 0-360) and its reference ``"T"`` (true north) or ``"M"``
    (magnetic north); ``ignored``: one line per malformed tag left out."""

    photo: str
    lon_deg: float | None = None
    lat_deg: float | None = None
    alt_m: float | None = None
    h_error_m: float | None = None
    direction_deg: float | None = None
    direction_ref: str | None = None
    ignored: tuple[str, ...] = field(default=())

    @property
    def has_position(self) -> bool:
        return self.lon_deg is not None and self.lat_deg is not None


def _finite(x) -> float | None:
    """A finite float from an EXIF number (rational, int, float), else None."""
    try:
        v = float(x)
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return None
    return v if math.isfinite(v) else None


def _deg(value) -> float | None:
    """Degrees from an EXIF (degrees, minutes, seconds) triple, or None when it is not one."""
    if isinstance(value, (str, bytes)):
        return None
    try:
        parts = [_finite(x) for x in value]
    except TypeError:
        return None
    if len(parts) != 3 or any(p is None for p in parts) or any(p < 0 for p in parts) or parts[1] >= 60 \
            or parts[2] >= 60:
        return None
    d, m, s = parts
    return d + m / 60.0 + s / 3600.0


def _ref(value) -> str:
    """An ASCII reference tag (``"N"``, ``b"T"``, ...) as an upper-case string ('' when unreadable)."""
    if isinstance(value, bytes):
        value = value.decode("ascii", errors="replace")
    return str(value).strip("\x00 ").upper() if value is not None else ""


class _Reader:
    """Reads one photo's GPS block, collecting a line per malformed tag."""

    def __init__(self, photo: str, gps: dict):
        self.photo, self.gps, self.ignored = photo, gps, []

    def bad(self, tag: str, value, why: str) -> None:
        self.ignored.append(f"{self.photo}: EXIF {tag} = {value!r} {why}; ignored")

    def coordinate(self, tag: str, num: int, ref_num: int, signs: tuple[str, str], limit: float) -> float | None:
        if num not in self.gps:
            return None
        v = _deg(self.gps[num])
        if v is None or v > limit:
            self.bad(tag, self.gps[num], f"is not a (degrees, minutes, seconds) triple within 0-{limit:g} degrees")
            return None
        ref = _ref(self.gps.get(ref_num, signs[0]))
        if ref not in signs:
            self.bad(f"{tag}Ref", self.gps.get(ref_num), f"is not {signs[0]!r} or {signs[1]!r}")
            return None
        return -v if ref == signs[1] else v

    def altitude(self) -> float | None:
        if _ALT not in self.gps:
            return None
        a = _finite(self.gps[_ALT])
        if a is None or a < 0 or a > 20_000:  # unsigned in EXIF: below sea level is GPSAltitudeRef = 1
            self.bad("GPSAltitude", self.gps[_ALT], "is not a finite height of 0-20000 m")
            return None
        ref = self.gps.get(_ALT_REF, 0)
        try:
            below = (ref[0] if isinstance(ref, bytes) else int(ref or 0)) == 1
        except (TypeError, ValueError, IndexError):
            self.bad("GPSAltitudeRef", ref, "is not 0 (above sea level) or 1 (below)")
            return None
        return -a if below else a

    def positive(self, tag: str, num: int) -> float | None:
        if num not in self.gps:
            return None
        v = _finite(self.gps[num])
        if v is None or v <= 0 or v > 100_000:
            self.bad(tag, self.gps[num], "is not a finite positive number of metres")
            return None
        return v

    def direction(self) -> tuple[float | None, str | None]:
        if _DIR not in self.gps:
            return None, None
        v = _finite(self.gps[_DIR])
        if v is None or not (0.0 <= v <= 360.0):
            self.bad("GPSImgDirection", self.gps[_DIR], "is not a finite direction of 0-360 degrees")
            return None, None
        ref = _ref(self.gps.get(_DIR_REF, ""))
        if ref not in ("T", "M"):
            self.bad("GPSImgDirectionRef", self.gps.get(_DIR_REF), "is not 'T' (true north) or 'M' (magnetic "
                     "north), so GPSImgDirection cannot be used")
            return None, None
        return v % 360.0, ref


def read_gps_fix(path: str | Path, *, warn: bool = True) -> GpsFix | None:
    """Everything usable in a photo's EXIF GPS block (:class:`GpsFix`), or None when it has no GPS block (or the
    file has no readable EXIF). Malformed tags are left out and, with ``warn``, each is warned about
    (:class:`GpsTagIgnored`, naming the photo and the tag)."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            gps = dict(im.getexif().get_ifd(_GPS_IFD))
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError, TypeError, KeyError, IndexError) as exc:
        log.debug("%s: EXIF not readable (%s)", path, exc)
        return None
    if not gps:
        return None
    r = _Reader(path.name, gps)
    lat = r.coordinate("GPSLatitude", _LAT, _LAT_REF, ("N", "S"), 90.0)
    lon = r.coordinate("GPSLongitude", _LON, _LON_REF, ("E", "W"), 180.0)
    if (lat is None) != (lon is None) and (_LAT in gps) != (_LON in gps):
        r.ignored.append(f"{path.name}: EXIF GPS has {'GPSLatitude' if lat is not None else 'GPSLongitude'} "
                         f"without the other; the position is ignored")
    if lat is None or lon is None:
        lat = lon = None
    alt = r.altitude() if lat is not None else None
    h_err = r.positive("GPSHPositioningError", _H_ERROR)
    direction, ref = r.direction()
    if warn:
        for line in r.ignored:
            warnings.warn(GpsTagIgnored(line), stacklevel=2)
    if lat is None and direction is None:
        return GpsFix(path.name, ignored=tuple(r.ignored)) if r.ignored else None
    return GpsFix(path.name, lon, lat, alt, h_err, direction, ref, tuple(r.ignored))


def read_gps(path: str | Path) -> tuple[float, float, float | None] | None:
    """``(lon_deg, lat_deg, altitude_m or None)`` from a photo's EXIF GPS tags, or None when it has none (malformed
    tags are warned about, :func:`read_gps_fix`)."""
    fix = read_gps_fix(path)
    if fix is None or not fix.has_position:
        return None
    return fix.lon_deg, fix.lat_deg, fix.alt_m
