"""JPEGs with the EXIF camera tags that photo-based calibration reads (focal length, focal-plane resolution).

The focal length in pixels is ``FocalLength [mm] * FocalPlaneXResolution [px / unit] / unit [mm]``; the
focal-plane resolution is written in centimetres (``FocalPlaneResolutionUnit = 3``) as
``image width [px] / sensor width [cm]``. ``FocalLengthIn35mmFilm`` is the width-based equivalent
``FocalLength * 36 mm / sensor width`` (rounded to whole millimetres, as the tag is an integer).
"""

from __future__ import annotations

import datetime as _dt
import io
import os
import tempfile
from fractions import Fraction
from pathlib import Path

import numpy as np
import piexif
from PIL import Image


def _rational(x: float, max_den: int = 1_000_000) -> tuple[int, int]:
    fr = Fraction(float(x)).limit_denominator(max_den)
    num, den = fr.numerator, fr.denominator
    while num > 0xFFFFFFFF or den > 0xFFFFFFFF:  # EXIF rationals are unsigned 32-bit
        num, den = num // 2, max(1, den // 2)
    return int(num), int(den)


def _tag_value(ifd: str, tag: int, value):
    kind = piexif.TAGS[ifd][tag]["type"]
    if isinstance(value, _dt.datetime):
        value = value.strftime("%Y:%m:%d %H:%M:%S")
    if kind in (piexif.TYPES.Rational, piexif.TYPES.SRational):
        if isinstance(value, (list, tuple)) and value and not isinstance(value[0], int):
            return tuple(_rational(v) for v in value)
        if isinstance(value, (list, tuple)):
            return tuple(value)
        return _rational(value)
    if kind == piexif.TYPES.Ascii and isinstance(value, str):
        return value.encode("ascii", errors="replace")
    return value


def _find_tag(name: str) -> tuple[str, int]:
    for ifd in ("Exif", "0th", "GPS"):
        for tag, info in piexif.TAGS[ifd].items():
            if info["name"] == name:
                return ifd, tag
    raise ValueError(f"extra EXIF tag {name!r} is not a tag name piexif knows (e.g. 'DateTimeOriginal')")


def write_jpeg(path, image: np.ndarray, *, focal_length_mm: float, sensor_width_mm: float, make: str = "Synthetic",
               model: str = "WorkbenchCam", quality: int = 92, extra: dict | None = None) -> None:
    """Write ``image`` ((h, w, 3) uint8 RGB) to ``path`` as a JPEG with EXIF camera tags, atomically.

    ``extra``: more tags by their EXIF name, e.g. ``{"DateTimeOriginal": "2024:05:01 14:03:00"}`` (a
    ``datetime`` is formatted for you); rational tags take floats.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise ValueError(f"image must be (h, w, 3) uint8 RGB, got shape {img.shape} dtype {img.dtype}")
    if not (focal_length_mm > 0 and sensor_width_mm > 0):
        raise ValueError(f"focal_length_mm={focal_length_mm} and sensor_width_mm={sensor_width_mm} must be positive")
    h, w = img.shape[:2]
    res_per_cm = w / (sensor_width_mm / 10.0)
    zeroth = {
        piexif.ImageIFD.Make: make.encode("ascii", errors="replace"),
        piexif.ImageIFD.Model: model.encode("ascii", errors="replace"),
        piexif.ImageIFD.Orientation: 1,
    }
    exif = {
        piexif.ExifIFD.FocalLength: _rational(focal_length_mm),
        piexif.ExifIFD.FocalLengthIn35mmFilm: int(round(focal_length_mm * 36.0 / sensor_width_mm)),
        piexif.ExifIFD.FocalPlaneXResolution: _rational(res_per_cm),
        piexif.ExifIFD.FocalPlaneYResolution: _rational(res_per_cm),  # square pixels
        piexif.ExifIFD.FocalPlaneResolutionUnit: 3,
        piexif.ExifIFD.PixelXDimension: int(w),
        piexif.ExifIFD.PixelYDimension: int(h),
    }
    ifds = {"0th": zeroth, "Exif": exif, "GPS": {}}
    for name, value in (extra or {}).items():
        ifd, tag = _find_tag(name)
        ifds[ifd][tag] = _tag_value(ifd, tag, value)
    exif_bytes = piexif.dump({"0th": ifds["0th"], "Exif": ifds["Exif"], "GPS": ifds["GPS"], "1st": {},
                              "thumbnail": None})

    buf = io.BytesIO()
    Image.fromarray(img, mode="RGB").save(buf, format="JPEG", quality=int(quality), exif=exif_bytes)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(buf.getvalue())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def read_focal_px(path) -> float | None:
    """The focal length in pixels of the photo at ``path`` from its EXIF tags, or None if they do not tell.

    Delegates to :func:`workbench.intrinsics.exif.exif_focal_prior`, which handles the EXIF pitfalls (missing
    or nonsense tags, focal-plane units, resized, cropped or rotated photos) and records what it used.
    """
    from ..intrinsics.exif import exif_focal_prior

    prior = exif_focal_prior(Path(path))
    return None if prior is None else prior.focal_px
