"""The carriage-type file format: one small TOML file per type, validated with pydantic v2.

A type file holds the published dimensions of one kind of rail vehicle, the shape of its ends, its window
and door layout, its livery and its marked points. Every length is in metres, every height is above the
top of rail, every x is along the carriage frame's x axis (forward, towards the front coupler; 0 midway
between the coupler faces). See ``workbench/rolling_stock/types/*.toml`` for complete examples.

Layout of a type file::

    id = "my-coach"                       # lower case, digits, '-' or '_'
    name = "..."                          # display name
    operator = "..."
    kind = "coach"                        # coach | cab_car | locomotive
    default_car_number = "1234"
    sources = ["where the dimensions come from"]

    [dimensions]                          # length_over_couplers_m, body_length_m, width_m, height_m,
                                          # body_bottom_m, floor_height_m, coupler_height_m, bogie_centres_m,
                                          # bogie_wheelbase_m, wheel_diameter_m, gauge_m, equipment_depth_m
    [profile]                             # cross-section: eave_height_m, roof_edge_inset_m, roof_segments,
                                          # wall_bottom_m, bottom_inset_m
    [front] / [rear]                      # shape = "flat" | "nose"; nose_base_height_m, nose_setback_m; cab
    [[windows]]                           # groups: x_first_m, pitch_m, count, width_m, z_bottom_m, z_top_m, ...
    [[doors]]                             # x_m, width_m, z_bottom_m, z_top_m, sides, leaves, window
    [[grilles]]                           # x_start_m, x_end_m, z_bottom_m, z_top_m, sides
    [livery]                              # colours (hex), stripes, texts
    [[marked_points]]                     # name + anchor (derived from the dimensions) or name + xyz + faces

Marked-point anchors (derived from the dimensions, so they always agree with the built mesh):

* ``coupler_front`` / ``coupler_rear``: centre of the coupler face, (+-L/2, 0, coupler height).
* ``body_top_{front|rear}_{left|right}``: top of the flat side wall at that end (for a nose end: where the
  sloped nose meets the top of the side wall).
* ``body_bottom_{front|rear}_{left|right}``: bottom corner of the body at that end.
* ``nose_{front|rear}_{left|right}``: the knee of a nose end, where the vertical lower front meets the slope.
* ``door{i}_{top|bottom}_{front|rear}_{left|right}``: a corner of door *i* (1-based, in file order).
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ..core.settings import describe_validation_error
from ..errors import SettingsError

FACES = ("left", "right", "front", "rear", "roof")
Face = Literal["left", "right", "front", "rear", "roof"]
Side = Literal["left", "right"]
Color = Annotated[str, Field(pattern=r"^#[0-9a-fA-F]{6}$")]
Pos = Annotated[float, Field(gt=0)]
NonNeg = Annotated[float, Field(ge=0)]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Dimensions(_Model):
    length_over_couplers_m: Pos
    body_length_m: Pos  # over the body ends (end sheets / anticlimbers), without couplers
    width_m: Pos
    height_m: Pos  # top of roof above top of rail (without pantograph)
    body_bottom_m: Pos  # underside of the body / underframe above top of rail
    floor_height_m: Pos
    coupler_height_m: Pos = 0.876  # AAR: 34.5 in above top of rail
    bogie_centres_m: Pos  # distance between the bogie (truck) centres
    bogie_wheelbase_m: Pos
    wheel_diameter_m: Pos
    gauge_m: Pos = 1.435
    equipment_depth_m: NonNeg = 0.45  # underframe equipment boxes between the bogies (0: none)


class Profile(_Model):
    """Cross-section of the body (y-z), symmetric about the centre line."""

    eave_height_m: Pos  # top of the flat, vertical part of the side wall
    roof_edge_inset_m: NonNeg = 0.3  # horizontal extent of the rounded roof edge
    roof_segments: Annotated[int, Field(ge=1, le=8)] = 3
    wall_bottom_m: Pos | None = None  # bottom of the vertical side wall (default: body bottom)
    bottom_inset_m: NonNeg = 0.0  # tumblehome: how far the body bottom edge is inset from the side wall


class End(_Model):
    shape: Literal["flat", "nose"] = "flat"
    nose_base_height_m: Pos | None = None  # height where the sloped nose leaves the vertical lower front
    nose_setback_m: Pos | None = None  # how far back the slope reaches at roof height
    cab: bool = False  # draw a driving cab (windscreen, headlights) on this end

    @model_validator(mode="after")
    def _nose_params(self) -> "End":
        if self.shape == "nose" and (self.nose_base_height_m is None or self.nose_setback_m is None):
            raise ValueError("shape = 'nose' needs nose_base_height_m and nose_setback_m")
        return self


class WindowGroup(_Model):
    x_first_m: float  # centre of the first window
    pitch_m: NonNeg = 0.0
    count: Annotated[int, Field(ge=1, le=60)] = 1
    width_m: Pos
    z_bottom_m: Pos
    z_top_m: Pos
    corner_radius_m: NonNeg = 0.06
    sides: list[Side] = ["left", "right"]

    def centres(self) -> list[float]:
        return [self.x_first_m + k * self.pitch_m for k in range(self.count)]


class Door(_Model):
    x_m: float  # centre
    width_m: Pos
    z_bottom_m: Pos
    z_top_m: Pos
    sides: list[Side] = ["left", "right"]
    leaves: Annotated[int, Field(ge=1, le=2)] = 2
    window: bool = True


class Grille(_Model):
    x_start_m: float
    x_end_m: float
    z_bottom_m: Pos
    z_top_m: Pos
    sides: list[Side] = ["left", "right"]


class Stripe(_Model):
    z_bottom_m: NonNeg
    z_top_m: Pos
    color: Color
    on_ends: bool = True


class Livery(_Model):
    body_color: Color = "#c8ccd0"
    roof_color: Color = "#8a8d90"
    end_color: Color | None = None  # default: body colour
    nose_color: Color | None = None  # lower front of a cab end (default: end colour)
    underframe_color: Color = "#2a2a2a"
    window_color: Color = "#1d2630"
    frame_color: Color = "#3a3a3a"
    door_color: Color | None = None  # default: body colour
    text_color: Color = "#1a1a1a"
    number_color: Color = "#111111"
    logo_color: Color = "#0b3d91"
    stripes: list[Stripe] = []
    fluting: bool = False  # corrugated stainless lower side (thin horizontal lines)
    fluting_z_m: tuple[NonNeg, NonNeg] = (1.1, 1.9)
    operator_text: str = ""
    operator_text_x_m: float = 0.0  # centre of the operator lettering on the sides
    operator_text_z_m: Pos = 3.3  # centre height of the operator lettering on the sides
    operator_text_height_m: Pos = 0.35
    logo_text: str = ""
    logo_x_m: float = 0.0  # centre of the logo on the sides
    logo_z_m: Pos = 1.7
    logo_size_m: Pos = 0.7
    number_z_m: Pos = 1.65  # centre height of the large car number on the sides
    number_height_m: Pos = 0.35
    grime: Annotated[float, Field(ge=0, le=1)] = 0.35


class MarkedPoint(_Model):
    name: Annotated[str, Field(pattern=r"^[A-Za-z0-9_.-]+$")]
    anchor: str | None = None
    xyz: tuple[float, float, float] | None = None
    faces: list[Face] | None = None

    @model_validator(mode="after")
    def _one_source(self) -> "MarkedPoint":
        if (self.anchor is None) == (self.xyz is None):
            raise ValueError("give exactly one of 'anchor' or 'xyz'")
        if self.xyz is not None and not self.faces:
            raise ValueError("an explicit 'xyz' needs 'faces' (the faces the point lies on)")
        return self


class CarriageSpec(_Model):
    id: Annotated[str, Field(pattern=r"^[a-z0-9][a-z0-9_-]*$")]
    name: str
    operator: str = ""
    kind: Literal["coach", "cab_car", "locomotive"] = "coach"
    default_car_number: str = ""
    sources: list[str] = []
    dimensions: Dimensions
    profile: Profile
    front: End = End()
    rear: End = End()
    windows: list[WindowGroup] = []
    doors: list[Door] = []
    grilles: list[Grille] = []
    livery: Livery = Livery()
    marked_points: Annotated[list[MarkedPoint], Field(min_length=7, max_length=10)]

    @field_validator("id", mode="before")
    @classmethod
    def _lower(cls, v):
        return v.lower() if isinstance(v, str) else v


# --------------------------------------------------------------------------------------------------------
def _describe(exc: ValidationError, path: Path) -> str:
    return describe_validation_error(exc, str(path), hint="see workbench/rolling_stock/spec.py")


def _bad(path: Path, key: str, value, why: str) -> SettingsError:
    return SettingsError(f"{path}: '{key}' = {value!r}: {why}")


ANCHOR_RE = re.compile(
    r"^(?:coupler_(front|rear)"
    r"|body_(top|bottom)_(front|rear)_(left|right)"
    r"|nose_(front|rear)_(left|right)"
    r"|door(\d+)_(top|bottom)_(front|rear)_(left|right))$"
)


def check_consistency(spec: CarriageSpec, path: Path) -> None:
    """Cross-field checks the per-field validation cannot do; raises :class:`SettingsError` naming the key."""
    d, p = spec.dimensions, spec.profile
    half = d.body_length_m / 2
    if d.body_length_m > d.length_over_couplers_m:
        raise _bad(path, "dimensions.body_length_m", d.body_length_m,
                   f"longer than length_over_couplers_m = {d.length_over_couplers_m}")
    if d.length_over_couplers_m - d.body_length_m < 0.1:
        raise _bad(path, "dimensions.body_length_m", d.body_length_m,
                   "must be at least 0.1 m shorter than length_over_couplers_m (room for the couplers)")
    if not d.body_bottom_m < d.floor_height_m < d.height_m:
        raise _bad(path, "dimensions.floor_height_m", d.floor_height_m,
                   f"must lie between body_bottom_m = {d.body_bottom_m} and height_m = {d.height_m}")
    if d.wheel_diameter_m + 0.02 > d.body_bottom_m:
        raise _bad(path, "dimensions.wheel_diameter_m", d.wheel_diameter_m,
                   f"wheels must fit under the body (body_bottom_m = {d.body_bottom_m})")
    if not 0.3 < d.coupler_height_m < d.body_bottom_m + 0.5:
        raise _bad(path, "dimensions.coupler_height_m", d.coupler_height_m, "implausible coupler height")
    if d.bogie_centres_m / 2 + d.bogie_wheelbase_m / 2 + d.wheel_diameter_m / 2 > half:
        raise _bad(path, "dimensions.bogie_centres_m", d.bogie_centres_m, "the bogies stick out beyond the body")
    if d.gauge_m + 0.4 > d.width_m:
        raise _bad(path, "dimensions.gauge_m", d.gauge_m, "wider than the body")
    if d.equipment_depth_m > 0 and d.body_bottom_m - d.equipment_depth_m < 0.25:
        raise _bad(path, "dimensions.equipment_depth_m", d.equipment_depth_m,
                   "the underframe equipment would come closer than 0.25 m to the rail")
    wall_bottom = p.wall_bottom_m if p.wall_bottom_m is not None else d.body_bottom_m
    if not d.body_bottom_m <= wall_bottom < p.eave_height_m:
        raise _bad(path, "profile.wall_bottom_m", wall_bottom,
                   f"must lie between body_bottom_m = {d.body_bottom_m} and eave_height_m = {p.eave_height_m}")
    if p.eave_height_m > d.height_m:
        raise _bad(path, "profile.eave_height_m", p.eave_height_m, f"above height_m = {d.height_m}")
    if p.roof_edge_inset_m > 0 and p.eave_height_m >= d.height_m:
        raise _bad(path, "profile.eave_height_m", p.eave_height_m,
                   "must be below height_m when roof_edge_inset_m > 0")
    if p.roof_edge_inset_m >= d.width_m / 2 - 0.05:
        raise _bad(path, "profile.roof_edge_inset_m", p.roof_edge_inset_m, "too wide for the body")
    if p.bottom_inset_m >= d.width_m / 2 - 0.05:
        raise _bad(path, "profile.bottom_inset_m", p.bottom_inset_m, "too wide for the body")
    if p.bottom_inset_m > 0 and wall_bottom <= d.body_bottom_m:
        raise _bad(path, "profile.wall_bottom_m", wall_bottom,
                   "must be above body_bottom_m when bottom_inset_m > 0")
    for end_name in ("front", "rear"):
        e: End = getattr(spec, end_name)
        if e.shape == "nose":
            if not wall_bottom <= e.nose_base_height_m <= p.eave_height_m:
                raise _bad(path, f"{end_name}.nose_base_height_m", e.nose_base_height_m,
                           f"must lie on the flat side wall ({wall_bottom} .. {p.eave_height_m} m)")
            if e.nose_setback_m > half - d.bogie_centres_m / 4:
                raise _bad(path, f"{end_name}.nose_setback_m", e.nose_setback_m, "too long for the body")
    for i, g in enumerate(spec.windows):
        key = f"windows[{i}]"
        if not wall_bottom <= g.z_bottom_m < g.z_top_m <= p.eave_height_m:
            raise _bad(path, f"{key}.z_top_m", g.z_top_m,
                       f"windows must lie on the flat side wall ({wall_bottom} .. {p.eave_height_m} m), bottom < top")
        for x in g.centres():
            if abs(x) + g.width_m / 2 > half:
                raise _bad(path, f"{key}.x_first_m", g.x_first_m, f"a window at x = {x:.2f} m is off the body")
    for i, dr in enumerate(spec.doors):
        key = f"doors[{i}]"
        if not wall_bottom <= dr.z_bottom_m < dr.z_top_m <= p.eave_height_m:
            raise _bad(path, f"{key}.z_top_m", dr.z_top_m,
                       f"doors must lie on the flat side wall ({wall_bottom} .. {p.eave_height_m} m), bottom < top")
        if abs(dr.x_m) + dr.width_m / 2 > half:
            raise _bad(path, f"{key}.x_m", dr.x_m, "the door is off the body")
    for i, g in enumerate(spec.grilles):
        if g.x_end_m <= g.x_start_m or g.z_top_m <= g.z_bottom_m:
            raise _bad(path, f"grilles[{i}].x_end_m", g.x_end_m, "need x_start_m < x_end_m and z_bottom_m < z_top_m")
    seen: set[str] = set()
    for i, mp in enumerate(spec.marked_points):
        key = f"marked_points[{i}]"
        if mp.name in seen:
            raise _bad(path, f"{key}.name", mp.name, "duplicate marked-point name")
        seen.add(mp.name)
        if mp.anchor is not None:
            m = ANCHOR_RE.match(mp.anchor)
            if not m:
                raise _bad(path, f"{key}.anchor", mp.anchor,
                           "unknown anchor; use coupler_front|rear, body_top|bottom_<end>_<side>, "
                           "nose_<end>_<side> or door<i>_top|bottom_<front|rear>_<side>")
            if m.group(5) and getattr(spec, m.group(5)).shape != "nose":
                raise _bad(path, f"{key}.anchor", mp.anchor, f"the {m.group(5)} end is not a nose")
            if m.group(7):
                k = int(m.group(7))
                if not 1 <= k <= len(spec.doors):
                    raise _bad(path, f"{key}.anchor", mp.anchor, f"there are {len(spec.doors)} doors (1-based)")
                if m.group(10) not in spec.doors[k - 1].sides:
                    raise _bad(path, f"{key}.anchor", mp.anchor, f"door {k} is not on the {m.group(10)} side")


def load_spec(path: Path) -> CarriageSpec:
    """Read and validate one type file. Every problem is a :class:`SettingsError` naming the file and key."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SettingsError(f"{path}: carriage type file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SettingsError(f"{path}: not valid TOML ({exc}); fix the syntax at that line") from None
    try:
        spec = CarriageSpec.model_validate(data)
    except ValidationError as exc:
        raise SettingsError(_describe(exc, path)) from None
    check_consistency(spec, path)
    return spec
