"""The correspondence file (``correspondences.json``, docs/pipeline.md): validation, merging, writing.

The incident's hand-written file and the ``correspond`` stage's output share one format::

    {"observations": [{"carriage": "6100", "point": "front_left_cant", "view": "pano_01.jpg",
                       "uv": [812.4, 433.0], "source": "manual", "confidence": 1.0, "sigma_px": 1.0}],
     "needs_manual": [{"carriage": "6227", "reason": "..."}],
     "rejected": [{"carriage": "6234", "point": "coupler_rear", "view": "pano_02.jpg", "reason": "..."}]}

``rejected`` (hand-written file only): automatic points a person reviewed and found wrong; the stage drops
them. A (carriage, point, view) may be picked or rejected, not both.

``construction`` (optional, manual points): how a pick was made when it is not a click on the point itself.
``{"method": "edges", "segments": [[[u, v], [u, v]], [[u, v], [u, v]]]}``: the point is where the lines through
two segments drawn along the two edges that meet there cross (a rounded or hidden corner); ``uv`` must be that
intersection (within :data:`CONSTRUCTION_TOLERANCE_PX`), the segments at least :data:`MIN_SEGMENT_PX` long and
at least :data:`MIN_EDGE_ANGLE_DEG` apart. The stages read ``uv`` only; the construction is the record.

Pixels follow docs/conventions.md: (0, 0) is the centre of the top-left pixel, so an image of width w spans
u in [-0.5, w - 0.5]. ``view`` is a photo name of the photo set, or ``"panorama"``.
"""

from __future__ import annotations

import math
import reprlib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, StrictFloat, StrictInt, ValidationError, field_validator, model_validator

from ..core.io import read_json
from ..core.layout import CORRESPONDENCES_FILE
from ..errors import InputError

FILE_NAME = CORRESPONDENCES_FILE  # the picks file's name (core/layout.py names every incident file)
PANORAMA = "panorama"
CONSTRUCTION_TOLERANCE_PX = 0.05  # uv against its construction's intersection (both written to 0.001 px)
MIN_SEGMENT_PX = 2.0
MIN_EDGE_ANGLE_DEG = 5.0

Pixel = tuple[StrictFloat, StrictFloat]


def lines_intersection(a: tuple, b: tuple) -> tuple[tuple[float, float] | None, float]:
    """Where the lines through segments ``a`` and ``b`` (each ``((u, v), (u, v))``) cross, and the angle between
    them in degrees (0 to 90); ``(None, 0.0)`` for parallel lines or a segment of no length."""
    (p, q), (r, s) = ((tuple(map(float, a[0])), tuple(map(float, a[1]))),
                      (tuple(map(float, b[0])), tuple(map(float, b[1]))))
    d1, d2 = (q[0] - p[0], q[1] - p[1]), (s[0] - r[0], s[1] - r[1])
    n1, n2 = math.hypot(*d1), math.hypot(*d2)
    cross = d1[0] * d2[1] - d1[1] * d2[0]
    if n1 == 0.0 or n2 == 0.0 or cross == 0.0:
        return None, 0.0
    angle = math.degrees(math.asin(min(1.0, abs(cross) / (n1 * n2))))
    k = ((r[0] - p[0]) * d2[1] - (r[1] - p[1]) * d2[0]) / cross
    return (p[0] + k * d1[0], p[1] + k * d1[1]), angle


class Construction(BaseModel):
    """How a manual point was made (module docstring): ``method = "edges"``, two drawn ``segments``."""

    model_config = ConfigDict(extra="forbid")

    method: Literal["edges"]
    segments: tuple[tuple[Pixel, Pixel], tuple[Pixel, Pixel]]

    @field_validator("segments")
    @classmethod
    def _drawn(cls, v):
        for i, (p, q) in enumerate(v):
            if not all(math.isfinite(x) for x in (*p, *q)):
                raise ValueError(f"segment {i} = {[list(p), list(q)]} is not finite")
            if math.hypot(q[0] - p[0], q[1] - p[1]) < MIN_SEGMENT_PX:
                raise ValueError(f"segment {i} is shorter than {MIN_SEGMENT_PX:g} px (draw it along the edge)")
        _, angle = lines_intersection(*v)
        if angle < MIN_EDGE_ANGLE_DEG:
            raise ValueError(f"the two edges are {angle:.1f} deg apart, less than {MIN_EDGE_ANGLE_DEG:g} deg: their "
                             f"intersection is not defined well enough")
        return v

    def point(self) -> tuple[float, float]:
        return lines_intersection(*self.segments)[0]

    def to_json(self) -> dict:
        return {"method": self.method,
                "segments": [[[round(float(x), 3) for x in pt] for pt in seg] for seg in self.segments]}


class Alignment(BaseModel):
    """A homography point's share of its face alignment's error (docs/correspondences.md, "What a face's
    alignment measures"): the point's displacement is ``loading_px @ xi`` (px of the photo on disk) with one
    ``xi ~ N(0, I_8)`` shared by the points of the same carriage, face and view."""

    model_config = ConfigDict(extra="forbid")

    loading_px: tuple[tuple[StrictFloat, StrictFloat, StrictFloat, StrictFloat, StrictFloat, StrictFloat,
                            StrictFloat, StrictFloat],
                      tuple[StrictFloat, StrictFloat, StrictFloat, StrictFloat, StrictFloat, StrictFloat,
                            StrictFloat, StrictFloat]]
    n_matches: StrictInt = Field(ge=8)  # the matches the face's homography was fitted to

    @field_validator("loading_px")
    @classmethod
    def _finite(cls, v):
        if not all(math.isfinite(x) for row in v for x in row):
            raise ValueError("loading_px is not finite")
        return v

    def to_json(self) -> dict:
        return {"loading_px": [[round(float(x), 5) for x in row] for row in self.loading_px],
                "n_matches": int(self.n_matches)}


class Observation(BaseModel):
    # numbers must be JSON numbers (a string "1.5" or a boolean is refused) and finite (NaN, Infinity and 1e400,
    # which reads as infinity, are refused)
    model_config = ConfigDict(extra="forbid")

    carriage: str
    point: str
    view: str
    uv: tuple[StrictFloat, StrictFloat]
    source: Literal["manual", "sift"] = "manual"
    confidence: StrictFloat = Field(1.0, ge=0.0, le=1.0, allow_inf_nan=False)
    sigma_px: StrictFloat | None = Field(None, gt=0.0, allow_inf_nan=False)
    # how a "sift" point was placed: on its face's plane by the face's homography; projected from the car's pose
    # (off the plane); or carried from another photo of a panorama set. The last two are predictions: the
    # solve lets them guide the fit but counts no information from them (docs/pipeline.md)
    method: Literal["homography", "pose", "carried"] | None = None
    # the carriage face whose homography or pose placed a "sift" point (left, right, front, rear, roof): the
    # points of one face share its small misfit, which the solve's covariance models (solver.face_sigma_px)
    face: str | None = None
    # how a manual point was made, when not by a click on it (module docstring): the stages read uv only
    construction: Construction | None = None
    # a "homography" point's share of its face alignment's error, when the face had matches of its own
    alignment: Alignment | None = None
    # a "homography" point's face alignment's ECC correlation coefficient (the dense alignment of the face's
    # reference to the photo): how well the face's painted reference matches what the photo shows there
    ecc: StrictFloat | None = Field(None, ge=-1.0, le=1.0, allow_inf_nan=False)

    @field_validator("uv")
    @classmethod
    def _finite(cls, v):
        if not all(math.isfinite(x) for x in v):
            raise ValueError(f"uv = {list(v)} is not finite")
        return v

    @model_validator(mode="after")
    def _aligned(self):
        if self.alignment is not None and self.method != "homography":
            raise ValueError(f"an alignment is recorded for method 'homography' points only (method = {self.method!r})")
        if self.ecc is not None and self.method != "homography":
            raise ValueError(f"an ECC correlation is recorded for method 'homography' points only (method = "
                             f"{self.method!r})")
        return self

    @model_validator(mode="after")
    def _constructed(self):
        if self.construction is None:
            return self
        if self.source != "manual":
            raise ValueError("a construction is recorded for manual points only")
        x = self.construction.point()
        if math.hypot(self.uv[0] - x[0], self.uv[1] - x[1]) > CONSTRUCTION_TOLERANCE_PX:
            raise ValueError(f"uv = {list(self.uv)} is not where the construction's edges cross "
                             f"([{x[0]:.3f}, {x[1]:.3f}])")
        return self

    @property
    def key(self) -> tuple[str, str, str]:
        return (self.carriage, self.point, self.view)

    def to_json(self) -> dict:
        d = {"carriage": self.carriage, "point": self.point, "view": self.view,
             "uv": [round(float(self.uv[0]), 3), round(float(self.uv[1]), 3)], "source": self.source,
             "confidence": round(float(self.confidence), 3)}
        if self.sigma_px is not None:
            d["sigma_px"] = round(float(self.sigma_px), 3)
        if self.method is not None:
            d["method"] = self.method
        if self.face is not None:
            d["face"] = self.face
        if self.construction is not None:
            d["construction"] = self.construction.to_json()
        if self.alignment is not None:
            d["alignment"] = self.alignment.to_json()
        if self.ecc is not None:
            d["ecc"] = round(float(self.ecc), 4)
        return d


class NeedsManual(BaseModel):
    model_config = ConfigDict(extra="forbid")

    carriage: str
    reason: str = ""


class Rejection(BaseModel):
    """An automatic point a person found wrong (in the picker): the stage drops it."""

    model_config = ConfigDict(extra="forbid")

    carriage: str
    point: str
    view: str
    reason: str = ""

    @property
    def key(self) -> tuple[str, str, str]:
        return (self.carriage, self.point, self.view)


class CorrespondenceFile(BaseModel):
    model_config = ConfigDict(extra="forbid")

    observations: list[Observation] = Field(default_factory=list)
    needs_manual: list[NeedsManual] = Field(default_factory=list)
    rejected: list[Rejection] = Field(default_factory=list)
    note: str | None = None  # free text (who picked, how)

    def to_json(self) -> dict:
        d = {"observations": [o.to_json() for o in self.observations],
             "needs_manual": [n.model_dump() for n in self.needs_manual]}
        if self.rejected:
            d["rejected"] = [r.model_dump(exclude_defaults=True) for r in self.rejected]
        if self.note:
            d["note"] = self.note
        return d


def _where(loc: tuple) -> str:
    return ".".join(cut_for_message(x, 40, quote=False) if not isinstance(x, int) else f"[{x}]" for x in loc).replace(".[", "[")


_repr = reprlib.Repr()
_repr.maxlevel, _repr.maxstring, _repr.maxother, _repr.maxlist, _repr.maxdict = 2, 40, 40, 4, 3


def cut_for_message(value: object, n: int = 40, *, quote: bool = True) -> str:
    """``value`` for a message: its repr (or the string itself, ``quote=False``), cut to about ``n`` characters
    (a bad value may be megabytes long)."""
    s = _repr.repr(value) if quote or not isinstance(value, str) else value
    return s if len(s) <= n else s[: n - 3] + "..."


def parse(data: object, path: Path | str) -> CorrespondenceFile:
    """Structure check (keys, types, finite numbers, ranges); :class:`InputError` naming the entry."""
    try:
        return CorrespondenceFile.model_validate(data)
    except ValidationError as exc:
        errs = "; ".join(f"{_where(e['loc'])}: {e['msg']} (got {cut_for_message(e.get('input'))})" for e in exc.errors()[:5])
        raise InputError(f"{path}: invalid correspondence file: {errs}. See docs/pipeline.md "
                         f"(correspondences.json)") from None


def validate(cf: CorrespondenceFile, path: Path | str, *, points: dict[str, list[str]],
             image_sizes: dict[str, tuple[int, int]]) -> CorrespondenceFile:
    """Names and coordinates against the incident: unknown carriages, points or views, coordinates outside
    the image and duplicate (carriage, point, view) entries are an :class:`InputError` naming them.

    ``points``: car number -> marked point names of its type; ``image_sizes``: view name -> (width, height)
    (``"panorama"`` may be absent when no panorama is stitched yet: its coordinates are then only checked to
    be finite and non-negative).
    """
    problems: list[str] = []
    seen: dict[tuple[str, str, str], int] = {}
    for i, o in enumerate(cf.observations):
        where = f"observations[{i}]"
        if o.carriage not in points:
            problems.append(f"{where}: unknown carriage {cut_for_message(o.carriage)} (the consist has {', '.join(points)})")
            continue
        if o.point not in points[o.carriage]:
            problems.append(f"{where}: carriage {cut_for_message(o.carriage)} has no marked point {cut_for_message(o.point)} (its points: "
                            f"{', '.join(points[o.carriage])})")
        if o.view in image_sizes:
            w, h = image_sizes[o.view]
            u, v = o.uv
            if not (-0.5 <= u <= w - 0.5 and -0.5 <= v <= h - 0.5):
                problems.append(f"{where}: uv = [{u}, {v}] is outside view {cut_for_message(o.view)} ({w} x {h} px; pixel centres "
                                f"span [-0.5, {w - 0.5}] x [-0.5, {h - 0.5}])")
        elif o.view == PANORAMA:
            if min(o.uv) < -0.5:
                problems.append(f"{where}: uv = {list(o.uv)} is outside the panorama")
        else:
            problems.append(f"{where}: unknown view {cut_for_message(o.view)} (the photos are {', '.join(sorted(image_sizes))}"
                            f", or 'panorama')")
        if o.key in seen:
            problems.append(f"{where}: duplicate of observations[{seen[o.key]}] (carriage {cut_for_message(o.carriage)}, point "
                            f"{cut_for_message(o.point)}, view {cut_for_message(o.view)}); keep one")
        else:
            seen[o.key] = i
    for i, n in enumerate(cf.needs_manual):
        if n.carriage not in points:
            problems.append(f"needs_manual[{i}]: unknown carriage {cut_for_message(n.carriage)}")
    rejected: dict[tuple[str, str, str], int] = {}
    for i, r in enumerate(cf.rejected):
        where = f"rejected[{i}]"
        if r.carriage not in points:
            problems.append(f"{where}: unknown carriage {cut_for_message(r.carriage)} (the consist has {', '.join(points)})")
        elif r.point not in points[r.carriage]:
            problems.append(f"{where}: carriage {cut_for_message(r.carriage)} has no marked point {cut_for_message(r.point)}")
        if r.view not in image_sizes and r.view != PANORAMA:
            problems.append(f"{where}: unknown view {cut_for_message(r.view)} (the photos are {', '.join(sorted(image_sizes))})")
        if r.key in rejected:
            problems.append(f"{where}: duplicate of rejected[{rejected[r.key]}]; keep one")
        rejected.setdefault(r.key, i)
        if r.key in seen:
            problems.append(f"{where}: (carriage {cut_for_message(r.carriage)}, point {cut_for_message(r.point)}, view {cut_for_message(r.view)}) is "
                            f"also picked in observations[{seen[r.key]}]; a point is picked or rejected, not both")
    if problems:
        more = f" (and {len(problems) - 8} more)" if len(problems) > 8 else ""
        raise InputError(f"{path}: " + "; ".join(problems[:8]) + more)
    return cf


def load(path: Path, *, points: dict[str, list[str]], image_sizes: dict[str, tuple[int, int]]) -> CorrespondenceFile:
    """Read and validate a correspondence file."""
    path = Path(path)
    data = read_json(path)
    return validate(parse(data, path), path, points=points, image_sizes=image_sizes)


def merge(automatic: list[Observation], manual: list[Observation],
          rejected: list[Rejection] = ()) -> list[Observation]:
    """Automatic and manual observations; a manual one replaces the automatic one of the same
    (carriage, point, view), and a rejected automatic one is dropped. Ordered by carriage, view, point."""
    drop = {r.key for r in rejected}
    out = {o.key: o for o in automatic if o.key not in drop}
    for o in manual:
        out[o.key] = o
    return sorted(out.values(), key=lambda o: (o.carriage, o.view, o.point))
