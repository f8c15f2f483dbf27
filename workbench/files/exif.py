"""Photos' EXIF: a focal-length prior (pixels, with a 1-sigma) from the tags, robust to the known pitfalls, and
JPEGs written with the camera tags (:func:`write_jpeg`, for synthetic photos).

Three ways to turn EXIF into a focal length in pixels, tried in this order:

1. ``focal_plane``: ``FocalLength [mm] * FocalPlaneXResolution [px/unit] / unit [mm]``, where
   ``FocalPlaneResolutionUnit`` is 2 = inch (also the EXIF default when the tag is missing), 3 = cm,
   4 = mm, 5 = micrometre; scaled by ``image width / PixelXDimension`` when the photo was resized after the
   tags were written.
2. ``sensor_width``: ``FocalLength / sensor long side [mm] * image long side [px]``, with the sensor size
   given by the caller (a camera profile's ``sensor_width_mm``) or found in a small built-in table by
   ``Model`` (:data:`SENSOR_SIZES_MM`).
3. ``35mm_equivalent``: ``FocalLengthIn35mmFilm / 36 mm * image long side [px]`` (36 mm is the long side of
   a 35 mm frame; the tag is an integer, and cameras differ in whether they scale by the diagonal or the
   width, hence the wider sigma).

Pitfalls handled, each reported in ``FocalPrior.warnings`` (and candidates that fail a check are dropped):
missing tags; zero, negative, NaN or absurd values (``FocalLength`` 0 means "unknown"); focal-plane unit
missing or wrong (a result that matches the 35 mm equivalent after a 2.54, 10 or 25.4 unit change is
corrected); photos resized or rotated after the tags were written (``PixelXDimension`` differs); photos
cropped (aspect ratio changed) or whose implied sensor size contradicts the camera model; a digital zoom;
fields of view outside [1, 150] degrees; candidates that disagree (the 35 mm equivalent is then preferred).

Pixel sizes refer to the photo as stored (its pixel grid, before any EXIF ``Orientation`` rotation), which is
how OpenCV (with ``IMREAD_IGNORE_ORIENTATION``) and COLMAP read it.
"""

from __future__ import annotations

import datetime as _dt
import io
import logging
import math
import os
import tempfile
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np
import piexif
from PIL import Image

from ..errors import InputError

log = logging.getLogger(__name__)

# EXIF tag ids (EXIF 2.32): base IFD and Exif sub-IFD
_MAKE, _MODEL, _ORIENTATION, _EXIF_IFD = 0x010F, 0x0110, 0x0112, 0x8769
_FOCAL, _F35, _FPXR, _FPYR, _FPUNIT = 0x920A, 0xA405, 0xA20E, 0xA20F, 0xA210
_PXDIM, _PYDIM, _DZOOM = 0xA002, 0xA003, 0xA404

UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # FocalPlaneResolutionUnit -> millimetres per unit
UNIT_NAMES = {2: "inch", 3: "cm", 4: "mm", 5: "um"}

#: Sensor sizes (long side, short side) in mm of a few cameras, by EXIF ``Model`` (case-insensitive).
#: Only a sample (cameras whose photos are in the test data); give ``sensor_width_mm`` for others.
SENSOR_SIZES_MM: dict[str, tuple[float, float]] = {
    "canon eos 5d": (35.8, 23.9),
    "canon eos 5d mark ii": (36.0, 24.0),
    "nikon d7000": (23.6, 15.6),
    "nikon d800": (35.9, 24.0),
    "iphone 4s": (4.54, 3.42),
}

HFOV_RANGE_DEG = (1.0, 150.0)  # plausible field of view along the long side; outside it a candidate is dropped
SENSOR_RANGE_MM = (1.0, 100.0)  # plausible sensor long side
REL_SIGMA = {"focal_plane": 0.02, "sensor_width": 0.03, "35mm_equivalent": 0.05}
AGREE_TOL = 0.10  # candidates within 10 % agree


@dataclass(frozen=True)
class FocalPrior:
    """A focal length prior of one photo: ``focal_px`` (fx = fy, px) with 1-sigma ``sigma_px``.

    ``source``: ``focal_plane``, ``sensor_width`` or ``35mm_equivalent``; ``tags``: the EXIF values read
    (name -> value); ``warnings``: each pitfall met; ``width``, ``height``: the photo's stored size (px).
    """

    focal_px: float
    sigma_px: float
    source: str
    width: int
    height: int
    tags: dict[str, Any] = field(default_factory=dict)
    candidates: dict[str, float] = field(default_factory=dict)  # every usable estimate, px
    warnings: tuple[str, ...] = ()

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view (along the image width), degrees."""
        return math.degrees(2.0 * math.atan(self.width / 2.0 / self.focal_px))

    def to_dict(self) -> dict:
        return {"focal_px": self.focal_px, "sigma_px": self.sigma_px, "source": self.source,
                "width": self.width, "height": self.height, "hfov_deg": self.hfov_deg, "tags": dict(self.tags),
                "candidates": dict(self.candidates), "warnings": list(self.warnings)}


def _num(v) -> float | None:
    """An EXIF number (int, IFDRational, (num, den) tuple) as a float; None if absent or not finite."""
    if v is None:
        return None
    try:
        if isinstance(v, tuple) and len(v) == 2:
            x = float(v[0]) / float(v[1]) if v[1] else float("nan")
        elif isinstance(v, (tuple, list)) and len(v) == 1:
            x = float(v[0])
        else:
            x = float(v)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) else None


def _text(v) -> str | None:
    if v is None:
        return None
    if isinstance(v, bytes):
        v = v.decode("ascii", errors="replace")
    s = str(v).replace("\x00", "").strip()
    return s or None


_TAGS_READ: dict[tuple, tuple[int, int, dict[str, Any]]] = {}  # read_exif_tags' results, by the file's stamp
_TAGS_KEPT = 256


def read_exif_tags(path: Path) -> tuple[int, int, dict[str, Any]]:
    """(width, height, {tag name: value}) of the photo at ``path`` (stored pixel grid); tags absent are left out.

    Read once per process for a file that has not changed since (same path, inode, size, modification and change
    times; the runner's hashes use the same stamp): the inputs stage and the stitch read the same photos' tags."""
    path = Path(path)
    try:
        st = path.stat()
        key = (str(path.resolve()), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)
    except OSError:
        key = None
    if key is not None and key in _TAGS_READ:
        w, h, tags = _TAGS_READ[key]
        return w, h, dict(tags)
    w, h, tags = _read_exif_tags(path)
    if key is not None:
        if len(_TAGS_READ) >= _TAGS_KEPT:
            _TAGS_READ.clear()
        _TAGS_READ[key] = (w, h, dict(tags))
    return w, h, tags


def _read_exif_tags(path: Path) -> tuple[int, int, dict[str, Any]]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            w, h = im.size
            exif = im.getexif()
            sub = dict(exif.get_ifd(_EXIF_IFD)) if exif else {}
            base = dict(exif) if exif else {}
    except (OSError, ValueError, UnidentifiedImageError, SyntaxError) as exc:
        raise InputError(f"{path}: cannot read the image ({exc}); replace it with an intact copy") from None
    except Exception as exc:  # noqa: BLE001 - broken EXIF blocks raise assorted errors inside Pillow
        log.warning("%s: unreadable EXIF (%s); no EXIF prior", path, exc)
        return w, h, {}

    def get(tag):  # some writers put Exif tags in the base IFD
        return sub.get(tag, base.get(tag))

    raw = {"Make": _text(base.get(_MAKE)), "Model": _text(base.get(_MODEL)), "Orientation": _num(base.get(_ORIENTATION)),
           "FocalLength": _num(get(_FOCAL)), "FocalLengthIn35mmFilm": _num(get(_F35)),
           "FocalPlaneXResolution": _num(get(_FPXR)), "FocalPlaneYResolution": _num(get(_FPYR)),
           "FocalPlaneResolutionUnit": _num(get(_FPUNIT)), "PixelXDimension": _num(get(_PXDIM)),
           "PixelYDimension": _num(get(_PYDIM)), "DigitalZoomRatio": _num(get(_DZOOM))}
    return w, h, {k: v for k, v in raw.items() if v is not None}


def _hfov_long_deg(f_px: float, long_px: int) -> float:
    return math.degrees(2.0 * math.atan(long_px / 2.0 / f_px))


class _FocalCandidates:
    """The focal candidates (pixels) of one photo from its EXIF tags, by the three ways of the module
    docstring, with what was found on the way: the warnings, in the order found, and the tags used."""

    def __init__(self, width: int, height: int, tags: dict[str, Any], sensor_width_mm: float | None):
        self.width, self.height, self.tags = width, height, tags
        self.long_px = max(width, height)
        self.warnings: list[str] = []
        self.used: dict[str, Any] = {}
        self.cands: dict[str, float] = {}
        self.fp_sensor_mm: float | None = None  # the sensor's long side implied by the focal-plane resolution
        self.fp_tags: dict[str, Any] = {}
        self.sensor: float | None = None  # the sensor's long side, mm, given or from the table
        self.sensor_from: str | None = None
        self._focal_tags()
        self._size_change()
        self._focal_plane()
        self._sensor_width(sensor_width_mm)
        self._equivalent_35mm()
        self._drop_absurd()

    def _focal_tags(self) -> None:
        """FocalLength, FocalLengthIn35mmFilm (None where absent or absurd), DigitalZoomRatio, Orientation."""
        tags, warnings = self.tags, self.warnings
        f_mm = tags.get("FocalLength")
        if f_mm is not None and not (0 < f_mm <= 5000):
            warnings.append(f"FocalLength = {f_mm:g} mm is not a focal length (0 means unknown); ignored")
            f_mm = None
        f35 = tags.get("FocalLengthIn35mmFilm")
        if f35 is not None and not (0 < f35 <= 10000):
            warnings.append(f"FocalLengthIn35mmFilm = {f35:g} mm is not a focal length (0 means unknown); ignored")
            f35 = None
        zoom = tags.get("DigitalZoomRatio")
        zoom = zoom if zoom is not None and 1.0 < zoom <= 100.0 else 1.0
        if zoom > 1.0:
            warnings.append(f"DigitalZoomRatio = {zoom:g}: the optical focal is multiplied by it")
            self.used["DigitalZoomRatio"] = zoom
        orient = tags.get("Orientation")
        if orient in (5, 6, 7, 8):
            warnings.append(f"Orientation = {orient:g}: the photo is stored rotated; the prior is for the stored "
                            f"pixel grid")
        self.f_mm, self.f35, self.zoom = f_mm, f35, zoom

    def _size_change(self) -> None:
        """How the photo's size relates to the size the tags were written for: ``scale`` (resized or rotated)
        and ``cropped`` (another aspect ratio)."""
        width, height = self.width, self.height
        self.scale, self.cropped = 1.0, False
        px, py = self.tags.get("PixelXDimension"), self.tags.get("PixelYDimension")
        if px and py and px > 0 and py > 0:
            if (round(px), round(py)) != (width, height):
                if abs(px / py - width / height) < 0.01 * width / height:
                    self.scale = width / px
                    self.warnings.append(f"resized: PixelXDimension x PixelYDimension = {px:g}x{py:g} but the photo "
                                         f"is {width}x{height}; focal-plane focal scaled by {self.scale:.4g}")
                elif abs(py / px - width / height) < 0.01 * width / height:
                    self.scale = width / py
                    self.warnings.append(f"rotated: the tags describe a {px:g}x{py:g} image but the photo is "
                                         f"{width}x{height}")
                else:
                    self.cropped = True
                    self.warnings.append(f"cropped: the tags describe a {px:g}x{py:g} image but the photo is "
                                         f"{width}x{height} (another aspect ratio); the focal-plane resolution "
                                         f"does not apply")

    def _focal_plane(self) -> None:
        """1. ``FocalLength`` times the focal-plane resolution."""
        tags, warnings, f_mm = self.tags, self.warnings, self.f_mm
        res, unit = tags.get("FocalPlaneXResolution"), tags.get("FocalPlaneResolutionUnit")
        if f_mm is None or res is None or self.cropped:
            return
        if unit is None:
            unit = 2
            warnings.append("FocalPlaneResolutionUnit missing: the EXIF default (inch) is assumed")
        if res <= 0:
            warnings.append(f"FocalPlaneXResolution = {res:g} is not positive; ignored")
        elif unit not in UNIT_MM:
            warnings.append(f"FocalPlaneResolutionUnit = {unit:g} is not a unit EXIF defines (2 inch, 3 cm, 4 mm, "
                            f"5 um); focal-plane resolution ignored")
        else:
            unit_mm = UNIT_MM[int(unit)]
            f_px = f_mm * res / unit_mm * self.scale * self.zoom
            px, py = tags.get("PixelXDimension"), tags.get("PixelYDimension")
            tagged_long = max(px, py) if (px and py and px > 0 and py > 0) else self.long_px
            self.fp_sensor_mm = tagged_long / res * unit_mm  # sensor long side, mm (square pixels)
            if not (SENSOR_RANGE_MM[0] <= self.fp_sensor_mm <= SENSOR_RANGE_MM[1]):
                warnings.append(f"FocalPlaneXResolution = {res:g} per {UNIT_NAMES[int(unit)]} implies a "
                                f"{self.fp_sensor_mm:.3g} mm sensor; implausible, ignored")
            else:
                self.cands["focal_plane"] = f_px
                self.fp_tags = {"FocalPlaneXResolution": res, "FocalPlaneResolutionUnit": int(unit)}

    def _sensor_width(self, sensor_width_mm: float | None) -> None:
        """2. ``FocalLength`` over the sensor's size (given, or from the table by ``Model``)."""
        tags, long_px, f_mm = self.tags, self.long_px, self.f_mm
        model = (tags.get("Model") or "").strip().lower()
        if sensor_width_mm is not None:
            if not sensor_width_mm > 0:
                raise InputError(f"sensor_width_mm = {sensor_width_mm!r}: must be a positive width in mm")
            self.sensor, self.sensor_from = float(sensor_width_mm), "given"
        elif model in SENSOR_SIZES_MM:
            self.sensor, self.sensor_from = SENSOR_SIZES_MM[model][0], f"table ({tags.get('Model')})"
            ss = SENSOR_SIZES_MM[model]
            short_px = min(self.width, self.height)
            if abs(long_px / short_px - ss[0] / ss[1]) > 0.03 * ss[0] / ss[1]:
                self.cropped = True
                self.warnings.append(f"cropped: the photo's aspect {long_px / short_px:.3f} differs from the "
                                     f"{tags.get('Model')} sensor's {ss[0] / ss[1]:.3f}; the focal in pixels is "
                                     f"uncertain")
        sensor = self.sensor
        if f_mm is not None and sensor is not None:
            self.cands["sensor_width"] = f_mm / sensor * long_px * self.zoom
            if self.fp_sensor_mm is not None and abs(self.fp_sensor_mm / sensor - 1) > AGREE_TOL:
                self.warnings.append(f"the focal-plane resolution implies a {self.fp_sensor_mm:.3g} mm sensor but "
                                     f"the sensor is {sensor:.3g} mm ({self.sensor_from}): the photo was resized or "
                                     f"cropped after the tags were written; focal-plane resolution ignored")
                self.cands.pop("focal_plane", None)

    def _equivalent_35mm(self) -> None:
        """3. ``FocalLengthIn35mmFilm`` over the 36 mm long side of a 35 mm frame."""
        f35, f_mm = self.f35, self.f_mm
        if f35 is not None:
            self.cands["35mm_equivalent"] = f35 / 36.0 * self.long_px
            if f_mm is not None and not (0.3 <= f35 / f_mm <= 15.0):
                self.warnings.append(f"FocalLengthIn35mmFilm / FocalLength = {f35 / f_mm:.3g} is not a plausible "
                                     f"crop factor")

    def _drop_absurd(self) -> None:
        """Drop the candidates whose field of view is outside ``HFOV_RANGE_DEG``."""
        for name in list(self.cands):
            hfov = _hfov_long_deg(self.cands[name], self.long_px)
            if not (HFOV_RANGE_DEG[0] <= hfov <= HFOV_RANGE_DEG[1]):
                self.warnings.append(f"{name}: focal {self.cands[name]:.4g} px gives a {hfov:.3g} deg field of view; "
                                     f"ignored")
                del self.cands[name]

    def choose(self) -> tuple[str, float, float]:
        """(source, focal px, relative sigma): the first candidate in the module docstring's order, unless the
        35 mm equivalent disagrees (then a wrong focal-plane unit is corrected, or the 35 mm equivalent used)."""
        cands = self.cands
        order = [n for n in ("focal_plane", "sensor_width", "35mm_equivalent") if n in cands]
        source = order[0]
        f_px = cands[source]
        rel_sigma = REL_SIGMA[source]
        if "35mm_equivalent" in cands and source != "35mm_equivalent":
            ref = cands["35mm_equivalent"]
            ratio = f_px / ref
            if abs(ratio - 1) > AGREE_TOL:
                fixed = None
                if source == "focal_plane":
                    for factor in (2.54, 1 / 2.54, 10.0, 0.1, 25.4, 1 / 25.4):
                        if abs(ratio * factor - 1) <= AGREE_TOL:
                            fixed = factor
                            break
                if fixed is not None:
                    f_px *= fixed
                    rel_sigma = REL_SIGMA["35mm_equivalent"]
                    self.warnings.append(f"FocalPlaneResolutionUnit = {self.fp_tags.get('FocalPlaneResolutionUnit')} "
                                         f"looks wrong: the focal-plane focal times {fixed:.4g} matches the 35 mm "
                                         f"equivalent; corrected")
                else:
                    self.warnings.append(f"{source} focal {f_px:.4g} px disagrees with the 35 mm-equivalent "
                                         f"{ref:.4g} px ({100 * (ratio - 1):+.0f} %); the 35 mm equivalent is used")
                    source, f_px, rel_sigma = "35mm_equivalent", ref, REL_SIGMA["35mm_equivalent"]
        if source == "35mm_equivalent":
            rel_sigma = math.hypot(rel_sigma, 0.5 / self.f35)  # integer tag
        if self.cropped:
            rel_sigma = max(rel_sigma, 0.15)
        return source, f_px, rel_sigma

    def used_tags(self, source: str) -> dict[str, Any]:
        """The tags the focal from ``source`` rests on (and the camera's name and the tagged size)."""
        used, tags = self.used, self.tags
        if source != "35mm_equivalent" and self.f_mm is not None:
            used["FocalLength"] = self.f_mm
        if source == "focal_plane":
            used.update(self.fp_tags)
        if source == "sensor_width":
            used.update(sensor_long_side_mm=self.sensor, sensor_from=self.sensor_from)
        if source == "35mm_equivalent":
            used["FocalLengthIn35mmFilm"] = self.f35
        for k in ("Make", "Model", "PixelXDimension", "PixelYDimension"):
            if k in tags:
                used[k] = tags[k]
        return used


def focal_prior_from_tags(width: int, height: int, tags: dict[str, Any], *,
                          sensor_width_mm: float | None = None) -> FocalPrior | None:
    """The focal prior of a ``width`` x ``height`` photo from its EXIF ``tags`` (see :func:`read_exif_tags`).

    ``sensor_width_mm``: the sensor's long side, mm, when known (overrides the built-in table).
    Returns None when the tags do not give a usable focal length (the warnings are logged).
    """
    c = _FocalCandidates(width, height, tags, sensor_width_mm)
    if not c.cands:
        if tags:
            log.info("no EXIF focal prior: %s", "; ".join(c.warnings) or "no focal tags")
        return None
    source, f_px, rel_sigma = c.choose()
    used = c.used_tags(source)
    return FocalPrior(focal_px=float(f_px), sigma_px=float(rel_sigma * f_px), source=source, width=int(width),
                      height=int(height), tags=used, candidates={k: float(v) for k, v in c.cands.items()},
                      warnings=tuple(c.warnings))


def exif_focal_prior(path: Path, *, sensor_width_mm: float | None = None) -> FocalPrior | None:
    """The EXIF focal prior of the photo at ``path``, or None when its tags do not give one.

    :class:`InputError` if the file is not a readable image. See the module docstring for the rules.
    """
    width, height, tags = read_exif_tags(Path(path))
    prior = focal_prior_from_tags(width, height, tags, sensor_width_mm=sensor_width_mm)
    if prior is not None:
        for w in prior.warnings:
            log.info("%s: EXIF: %s", Path(path).name, w)
    return prior


# ---------------------------------------------------------------------------------------------------------
# Writing (synthetic photos with the tags a real camera writes)
# ---------------------------------------------------------------------------------------------------------
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

    Uses :func:`exif_focal_prior`, which handles the EXIF pitfalls (missing
    or nonsense tags, focal-plane units, resized, cropped or rotated photos) and records what it used.
    """
    prior = exif_focal_prior(Path(path))
    return None if prior is None else prior.focal_px
