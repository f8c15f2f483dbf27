"""EXIF GPS of a photo (a prior on where the camera stood)."""

from __future__ import annotations

import logging
from pathlib import Path

from PIL import Image, UnidentifiedImageError

log = logging.getLogger(__name__)

_GPS_IFD = 0x8825


def _deg(value) -> float | None:
    try:
        d, m, s = (float(x) for x in value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return d + m / 60.0 + s / 3600.0


def read_gps(path: str | Path) -> tuple[float, float, float | None] | None:
    """``(lon_deg, lat_deg, altitude_m or None)`` from a photo's EXIF GPS tags, or None when it has none."""
    try:
        with Image.open(path) as im:
            gps = im.getexif().get_ifd(_GPS_IFD)
    except (OSError, UnidentifiedImageError, ValueError):
        return None
    if not gps or 2 not in gps or 4 not in gps:
        return None
    lat, lon = _deg(gps[2]), _deg(gps[4])
    if lat is None or lon is None:
        return None
    if str(gps.get(1, "N")).upper().startswith("S"):
        lat = -lat
    if str(gps.get(3, "E")).upper().startswith("W"):
        lon = -lon
    alt = None
    if 6 in gps:
        try:
            alt = float(gps[6])
            ref = gps.get(5, 0)
            if (ref[0] if isinstance(ref, bytes) else int(ref or 0)) == 1:
                alt = -alt
        except (TypeError, ValueError, ZeroDivisionError, IndexError):
            alt = None
    if not (-90 <= lat <= 90 and -180 <= lon <= 180):
        return None
    return lon, lat, alt
