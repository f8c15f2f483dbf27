"""The carriage-type file format: one small TOML file per type, validated with pydantic v2.

A type file holds the published dimensions of one kind of rail vehicle and its marked points. It is either
**parametric** (the body built from its dimensions, cross-section and end shapes, with its window and door
layout and livery) or a **mesh type** (the model is a mesh file: glTF, OBJ or STL, e.g. a manufacturer's CAD
export; see "Mesh types" below). Every length is in metres, every height is above the top of rail, every x is
along the carriage frame's x axis (forward, towards the front coupler; 0 midway between the coupler faces;
docs/conventions.md). See ``workbench/rolling_stock/types/*.toml`` for complete examples.

Layout of a parametric type file::

    id = "my-coach"                       # lower case, digits, '-' or '_'
    name = "..."                          # display name
    operator = "..."
    kind = "coach"                        # coach | cab_car | locomotive | freight_car
    default_car_number = "1234"
    sources = ["where the dimensions come from"]

    [dimensions]                          # length_over_couplers_m, body_length_m, width_m, height_m,
                                          # body_bottom_m, floor_height_m, coupler_height_m, bogie_centres_m,
                                          # bogie_wheelbase_m, wheel_diameter_m, gauge_m, equipment_depth_m
    [profile]                             # cross-section: eave_height_m, roof_edge_inset_m, roof_segments,
                                          # wall_bottom_m, bottom_inset_m, bottom_segments
    [front] / [rear]                      # shape = "flat" | "nose"; nose_base_height_m, nose_setback_m; cab
    [[windows]]                           # groups: x_first_m, pitch_m, count, width_m, z_bottom_m, z_top_m, ...
    [[doors]]                             # x_m, width_m, z_bottom_m, z_top_m, sides, leaves, window
    [[grilles]]                           # x_start_m, x_end_m, z_bottom_m, z_top_m, sides
    [livery]                              # colours (hex), stripes, texts; reference
    [[marked_points]]                     # name + anchor (derived from the dimensions) or name + xyz + faces

The cross-section (``[profile]``, symmetric about the centre line, y-z) is, from the bottom up: the body
bottom (``dimensions.body_bottom_m``), a tumblehome of ``bottom_inset_m`` up to ``wall_bottom_m`` (a straight
chamfer, or rounded with ``bottom_segments`` > 1), the vertical side wall up to ``eave_height_m``, and the
rounded roof edge, ``roof_edge_inset_m`` wide, up to ``dimensions.height_m``. A plain box body:
``eave_height_m = height_m`` and ``roof_edge_inset_m = 0``. A cylinder (a tank car): ``eave_height_m`` and
``wall_bottom_m`` 1-2 cm either side of the axis, both insets at their maximum (``width_m / 2 - 0.05``
less a little), ``roof_segments = bottom_segments = 8``.

**Bounds** (each error message names the key, its value and the bound):

* positive: every dimension, every height; ``equipment_depth_m`` and the insets may be 0;
  ``roof_segments``, ``bottom_segments``: 1..8; window ``count``: 1..60; door ``leaves``: 1..2;
  ``livery.grime``: 0..1; 7 to 10 marked points, names unique.
* ``length_over_couplers_m - 0.1 >= body_length_m`` (room for the couplers);
  ``body_bottom_m < floor_height_m < height_m``; ``wheel_diameter_m <= body_bottom_m - 0.02``;
  ``0.3 < coupler_height_m < body_bottom_m + 0.5`` (AAR: 0.876 m; Japan: 0.88 m; UIC buffers: 1.025-1.065 m);
  ``bogie_centres_m / 2 + bogie_wheelbase_m / 2 + wheel_diameter_m / 2 <= body_length_m / 2`` (the bogies under
  the body); ``gauge_m <= width_m - 0.4``; ``equipment_depth_m <= body_bottom_m - 0.25`` (when not 0).
* ``body_bottom_m <= wall_bottom_m < eave_height_m <= height_m`` (``eave_height_m < height_m`` when
  ``roof_edge_inset_m > 0``; ``wall_bottom_m > body_bottom_m`` when ``bottom_inset_m > 0``);
  ``roof_edge_inset_m`` and ``bottom_inset_m`` ``< width_m / 2 - 0.05``.
* a nose: ``wall_bottom_m <= nose_base_height_m <= eave_height_m``;
  ``nose_setback_m <= body_length_m / 2 - bogie_centres_m / 4``.
* an end bowed in plan: ``corner_setback_m`` (>= 0) ``<= body_length_m / 2 - bogie_centres_m / 4`` less the nose's
  ``nose_setback_m``; the corner anchors (``body_*``, ``nose_*``) stand that far behind the end's middle.
* windows and doors on the flat side wall: ``wall_bottom_m <= z_bottom_m < z_top_m <= eave_height_m``, and
  within the body: ``|x| + width / 2 <= body_length_m / 2`` less that end's ``corner_setback_m``; grilles:
  ``x_start_m < x_end_m``, ``z_bottom_m < z_top_m``.
* a marked point given by ``xyz`` must lie within ``POINT_TOLERANCE_M`` (5 mm) of the model's surface (the
  built mesh, or the mesh file); the message names the point and its distance.

Marked-point anchors (derived from the dimensions, so they always agree with the built mesh):

* ``coupler_front`` / ``coupler_rear``: centre of the coupler face, (+-L/2, 0, coupler height).
* ``body_top_{front|rear}_{left|right}``: top of the flat side wall at that end (for a nose end: where the
  sloped nose meets the top of the side wall).
* ``body_bottom_{front|rear}_{left|right}``: bottom corner of the body at that end.
* ``nose_{front|rear}_{left|right}``: the knee of a nose end, where the vertical lower front meets the slope.
* ``door{i}_{top|bottom}_{front|rear}_{left|right}``: a corner of door *i* (1-based, in file order).
* ``roof_{front|rear}`` / ``bottom_{front|rear}``: the top / the bottom of that end on the centre line (y = 0,
  at ``height_m`` / ``body_bottom_m``; for a nose end, the top of the slope).

**Reference imagery.** The automatic finder (the correspond stage) searches photos only for the types whose
livery is the car's real appearance: a parametric type with a ``[livery]`` table and ``livery.reference``
true (the default). A type without a ``[livery]`` table (drawn in the default grey), one with
``reference = false`` (colours to draw it in, not its real look: real trains photographed on site), and every
mesh type are not searched: their cars need hand picks (``workbench pick``).

**Mesh types.** A ``[mesh]`` table instead of ``[profile]``, the end shapes, windows, doors, grilles and
livery::

    id = "cad-coach"
    name = "..."
    kind = "coach"
    sources = ["the manufacturer's CAD export, drawing no. ..."]

    [mesh]
    file = "cad-coach.glb"                # .gltf, .glb, .obj or .stl; relative to this type file
    unit_m = 0.001                        # metres per unit of the file: 1 (glTF), 0.001 (CAD in mm), 0.0254 (in)
    carriage_from_file = [[1, 0, 0, -13.0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    color = "#8a8d90"                     # drawn in this colour where the file has none (STL, OBJ without .mtl)

    [dimensions]
    length_over_couplers_m = 26.0         # the couplers' faces at x = +-L/2 (where the consist is linked)
    coupler_height_m = 0.876

    [[marked_points]]                     # 7-10; by xyz + faces, or anchor = coupler_front | coupler_rear
    name = "roof_front_left"
    xyz = [12.9, 1.5, 3.9]
    faces = ["left", "front", "roof"]

The file's coordinates are scaled by ``unit_m`` and then moved by ``carriage_from_file`` (4x4, row-major, a
rotation and a translation in metres; no scale, no mirror) into the carriage frame: x forward, y left, z up,
origin on the centre line midway between the coupler faces at top-of-rail height. glTF's own axes (+y up,
+z forward, +x left) are ``[[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]``. The checks, each stated in
its message: the rotation orthonormal with determinant +1 (within 1e-6), the last row ``[0, 0, 0, 1]``; at
most ``MESH_MAX_TRIANGLES`` triangles; the mesh in the carriage frame within ``MESH_X_MARGIN_M`` (5 cm) of the
coupler faces (``|x| <= L/2 + 0.05``) and spanning at least half of L in x; its lowest point between
-0.05 m and 1.5 m; its top between 1.0 m and 6.5 m; ``|y| <= 2.5`` m; every marked point within 5 mm of it
(anchored couplers included). Width, height and body length are read off the mesh.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ..core.settings import describe_validation_error
from ..errors import SettingsError

FACES = ("left", "right", "front", "rear", "roof")
Face = Literal["left", "right", "front", "rear", "roof"]
Side = Literal["left", "right"]
Kind = Literal["coach", "cab_car", "locomotive", "freight_car"]
Color = Annotated[str, Field(pattern=r"^#[0-9a-fA-F]{6}$")]
Pos = Annotated[float, Field(gt=0)]
NonNeg = Annotated[float, Field(ge=0)]

POINT_TOLERANCE_M = 0.005  # a marked point given by xyz lies within this of the model's surface
MESH_SUFFIXES = (".gltf", ".glb", ".obj", ".stl")
MESH_MAX_TRIANGLES = 2_000_000
MESH_X_MARGIN_M = 0.05  # a mesh may reach this far beyond the coupler faces (x = +-L/2)
MESH_LOWEST_Z_M = (-0.05, 1.5)  # its lowest point: from just below the rail to a body without running gear
MESH_TOP_Z_M = (1.0, 6.5)  # its top: from a flat wagon to a double-stack container car
MESH_HALF_WIDTH_M = 2.5


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
    bottom_segments: Annotated[int, Field(ge=1, le=8)] = 1  # 1: a straight chamfer; more: a rounded lower edge


class End(_Model):
    shape: Literal["flat", "nose"] = "flat"
    nose_base_height_m: Pos | None = None  # height where the sloped nose leaves the vertical lower front
    nose_setback_m: Pos | None = None  # how far back the slope reaches at roof height
    cab: bool = False  # draw a driving cab (windscreen, headlights) on this end
    # the end's vertical corners rounded in plan (seen from above), radius in metres (0: sharp); the corner
    # anchors stay at the sharp corner the side and end planes would make (pick it from two edges)
    corner_radius_m: NonNeg = 0.0
    corner_segments: Annotated[int, Field(ge=1, le=8)] = 4
    # the end bowed in plan: how far its side corners stand behind its middle (a cab front swept back to its
    # corners); the end's surface at lateral offset y lies corner_setback_m * (y / (width_m / 2))^2 behind its
    # middle, and the corner anchors move back with it (body_length_m stays the length on the centre line)
    corner_setback_m: NonNeg = 0.0

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

    def centres(self) -> list[float]:
        return [self.x_m]


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
    # true: the painted livery is the car's real appearance, a reference the automatic finder searches photos
    # for; false: colours to draw the car in only (the finder leaves its cars to hand picks)
    reference: bool = True
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


MarkedPoints = Annotated[list[MarkedPoint], Field(min_length=7, max_length=10)]


def _lower_id(v):
    return v.lower() if isinstance(v, str) else v


class _TypeHeader(_Model):
    """What every type file starts with: its id, names, kind and sources."""

    id: Annotated[str, Field(pattern=r"^[a-z0-9][a-z0-9_-]*$")]
    name: str
    operator: str = ""
    kind: Kind = "coach"
    default_car_number: str = ""
    sources: list[str] = []

    @field_validator("id", mode="before")
    @classmethod
    def _lower(cls, v):
        return _lower_id(v)


class CarriageSpec(_TypeHeader):
    """A parametric type: the body built from its dimensions, profile and end shapes."""

    dimensions: Dimensions
    profile: Profile
    front: End = End()
    rear: End = End()
    windows: list[WindowGroup] = []
    doors: list[Door] = []
    grilles: list[Grille] = []
    livery: Livery = Livery()
    marked_points: MarkedPoints

    @property
    def has_livery(self) -> bool:
        """Whether the file gives a ``[livery]`` table (else the default grey one is painted)."""
        return "livery" in self.model_fields_set


class MeshDimensions(_Model):
    length_over_couplers_m: Pos
    coupler_height_m: Pos = 0.876
    gauge_m: Pos = 1.435


Matrix4 = Annotated[list[Annotated[list[float], Field(min_length=4, max_length=4)]], Field(min_length=4, max_length=4)]


class MeshSource(_Model):
    file: Annotated[str, Field(min_length=1)]  # relative to the type file
    unit_m: Pos = 1.0  # metres per unit of the file
    carriage_from_file: Matrix4 | None = None  # 4x4 row-major, on the scaled coordinates (metres); None: identity
    color: Color = "#8a8d90"

    @field_validator("file")
    @classmethod
    def _suffix(cls, v: str) -> str:
        if not v.lower().endswith(MESH_SUFFIXES):
            raise ValueError(f"a mesh file must be one of {', '.join(MESH_SUFFIXES)}")
        return v


class MeshCarriageSpec(_TypeHeader):
    """A mesh type: the model is a mesh file (a manufacturer's CAD export), its marked points given by xyz."""

    mesh: MeshSource
    dimensions: MeshDimensions
    marked_points: MarkedPoints

    @property
    def has_livery(self) -> bool:
        return False


AnySpec = Union[CarriageSpec, MeshCarriageSpec]


# --------------------------------------------------------------------------------------------------------
def _describe(exc: ValidationError, path: Path) -> str:
    return describe_validation_error(exc, str(path), hint="see workbench/rolling_stock/spec.py")


def _bad(path: Path, key: str, value, why: str) -> SettingsError:
    return SettingsError(f"{path}: '{key}' = {value!r}: {why}")


ANCHOR_RE = re.compile(
    r"^(?:coupler_(front|rear)"
    r"|body_(top|bottom)_(front|rear)_(left|right)"
    r"|nose_(front|rear)_(left|right)"
    r"|door(\d+)_(top|bottom)_(front|rear)_(left|right)"
    r"|(roof|bottom)_(front|rear))$"
)


def _check_dimensions(d: Dimensions, path: Path) -> None:
    half = d.body_length_m / 2
    if d.body_length_m > d.length_over_couplers_m - 0.1:
        raise _bad(path, "dimensions.body_length_m", d.body_length_m,
                   f"must be at most length_over_couplers_m - 0.1 = {d.length_over_couplers_m - 0.1:.3f} m "
                   "(room for the couplers)")
    if not d.body_bottom_m < d.floor_height_m < d.height_m:
        raise _bad(path, "dimensions.floor_height_m", d.floor_height_m,
                   f"must lie between body_bottom_m = {d.body_bottom_m} and height_m = {d.height_m} m")
    if d.wheel_diameter_m + 0.02 > d.body_bottom_m:
        raise _bad(path, "dimensions.wheel_diameter_m", d.wheel_diameter_m,
                   f"the wheels must fit under the body: at most body_bottom_m - 0.02 = {d.body_bottom_m - 0.02:.3f} m")
    if not 0.3 < d.coupler_height_m < d.body_bottom_m + 0.5:
        raise _bad(path, "dimensions.coupler_height_m", d.coupler_height_m,
                   f"implausible coupler height: allowed above 0.3 m and below body_bottom_m + 0.5 = "
                   f"{d.body_bottom_m + 0.5:.3f} m (AAR 0.876 m, Japan 0.88 m, UIC buffers 1.025-1.065 m)")
    reach = d.bogie_centres_m / 2 + d.bogie_wheelbase_m / 2 + d.wheel_diameter_m / 2
    if reach > half:
        raise _bad(path, "dimensions.bogie_centres_m", d.bogie_centres_m,
                   f"the bogies stick out beyond the body: bogie_centres_m / 2 + bogie_wheelbase_m / 2 + "
                   f"wheel_diameter_m / 2 = {reach:.3f} m must be at most body_length_m / 2 = {half:.3f} m "
                   f"(bogie_centres_m at most {2 * half - d.bogie_wheelbase_m - d.wheel_diameter_m:.3f} m)")
    if d.gauge_m + 0.4 > d.width_m:
        raise _bad(path, "dimensions.gauge_m", d.gauge_m,
                   f"wider than the body: at most width_m - 0.4 = {d.width_m - 0.4:.3f} m")
    if d.equipment_depth_m > 0 and d.body_bottom_m - d.equipment_depth_m < 0.25:
        raise _bad(path, "dimensions.equipment_depth_m", d.equipment_depth_m,
                   f"the underframe equipment would come closer than 0.25 m to the rail: at most body_bottom_m - "
                   f"0.25 = {d.body_bottom_m - 0.25:.3f} m (or 0: none)")


def _check_profile(spec: CarriageSpec, path: Path) -> float:
    """The cross-section's bounds; returns the bottom of the side wall."""
    d, p = spec.dimensions, spec.profile
    wall_bottom = p.wall_bottom_m if p.wall_bottom_m is not None else d.body_bottom_m
    if not d.body_bottom_m <= wall_bottom < p.eave_height_m:
        raise _bad(path, "profile.wall_bottom_m", wall_bottom,
                   f"must lie between body_bottom_m = {d.body_bottom_m} m (included) and eave_height_m = "
                   f"{p.eave_height_m} m (excluded)")
    if p.eave_height_m > d.height_m:
        raise _bad(path, "profile.eave_height_m", p.eave_height_m, f"must be at most height_m = {d.height_m} m")
    if p.roof_edge_inset_m > 0 and p.eave_height_m >= d.height_m:
        raise _bad(path, "profile.eave_height_m", p.eave_height_m,
                   f"must be below height_m = {d.height_m} m when roof_edge_inset_m > 0 (a box body: "
                   "roof_edge_inset_m = 0)")
    limit = d.width_m / 2 - 0.05
    if p.roof_edge_inset_m >= limit:
        raise _bad(path, "profile.roof_edge_inset_m", p.roof_edge_inset_m,
                   f"too wide for the body: must be less than width_m / 2 - 0.05 = {limit:.3f} m")
    if p.bottom_inset_m >= limit:
        raise _bad(path, "profile.bottom_inset_m", p.bottom_inset_m,
                   f"too wide for the body: must be less than width_m / 2 - 0.05 = {limit:.3f} m")
    if p.bottom_inset_m > 0 and wall_bottom <= d.body_bottom_m:
        raise _bad(path, "profile.wall_bottom_m", wall_bottom,
                   f"must be above body_bottom_m = {d.body_bottom_m} m when bottom_inset_m > 0")
    for end in ("front", "rear"):
        e = getattr(spec, end)
        r_max = min(d.width_m / 2 - 0.05, d.body_length_m / 4)
        if e.corner_radius_m > r_max:
            raise _bad(path, f"{end}.corner_radius_m", e.corner_radius_m,
                       f"too large: at most min(width_m / 2 - 0.05, body_length_m / 4) = {r_max:.3f} m (a flat "
                       "strip of at least 10 cm across the end)")
    return wall_bottom


def _check_layout(spec: CarriageSpec, wall_bottom: float, path: Path) -> None:
    """End shapes, windows, doors and grilles."""
    d, p = spec.dimensions, spec.profile
    half = d.body_length_m / 2
    for end_name in ("front", "rear"):
        e: End = getattr(spec, end_name)
        if e.shape == "nose":
            if not wall_bottom <= e.nose_base_height_m <= p.eave_height_m:
                raise _bad(path, f"{end_name}.nose_base_height_m", e.nose_base_height_m,
                           f"must lie on the flat side wall ({wall_bottom} .. {p.eave_height_m} m)")
            most = half - d.bogie_centres_m / 4
            if e.nose_setback_m > most:
                raise _bad(path, f"{end_name}.nose_setback_m", e.nose_setback_m,
                           f"too long for the body: at most body_length_m / 2 - bogie_centres_m / 4 = {most:.3f} m")
        most = half - d.bogie_centres_m / 4 - ((e.nose_setback_m or 0.0) if e.shape == "nose" else 0.0)
        if e.corner_setback_m > most:
            raise _bad(path, f"{end_name}.corner_setback_m", e.corner_setback_m,
                       f"too long for the body: at most body_length_m / 2 - bogie_centres_m / 4 (less the nose's "
                       f"setback) = {most:.3f} m")
    # windows and doors: on the flat side wall, and every one on the body
    openings = [(f"windows[{i}]", "window", "x_first_m", g) for i, g in enumerate(spec.windows)]
    openings += [(f"doors[{i}]", "door", "x_m", dr) for i, dr in enumerate(spec.doors)]
    for key, kind, x_key, o in openings:
        if not wall_bottom <= o.z_bottom_m < o.z_top_m <= p.eave_height_m:
            raise _bad(path, f"{key}.z_top_m", o.z_top_m,
                       f"{kind}s must lie on the flat side wall ({wall_bottom} .. {p.eave_height_m} m), bottom < top "
                       f"(z_bottom_m = {o.z_bottom_m})")
        for x in o.centres():
            end = spec.front if x >= 0 else spec.rear
            if abs(x) + o.width_m / 2 > half - end.corner_setback_m:
                what = "body_length_m / 2" + (" less the end's corner_setback_m" if end.corner_setback_m else "")
                raise _bad(path, f"{key}.{x_key}", getattr(o, x_key),
                           f"a {kind} at x = {x:.2f} m is off the body: |x| + width_m / 2 must be at most "
                           f"{what} = {half - end.corner_setback_m:.3f} m")
    for i, g in enumerate(spec.grilles):
        if g.x_end_m <= g.x_start_m or g.z_top_m <= g.z_bottom_m:
            raise _bad(path, f"grilles[{i}].x_end_m", g.x_end_m,
                       f"need x_start_m < x_end_m and z_bottom_m < z_top_m (x_start_m = {g.x_start_m}, z_bottom_m = "
                       f"{g.z_bottom_m}, z_top_m = {g.z_top_m})")


def _check_marked_points(spec: AnySpec, path: Path) -> None:
    seen: set[str] = set()
    mesh_type = isinstance(spec, MeshCarriageSpec)
    for i, mp in enumerate(spec.marked_points):
        key = f"marked_points[{i}]"
        if mp.name in seen:
            raise _bad(path, f"{key}.name", mp.name, "duplicate marked-point name")
        seen.add(mp.name)
        if mp.anchor is None:
            continue
        m = ANCHOR_RE.match(mp.anchor)
        if mesh_type and not (m and m.group(1)):
            raise _bad(path, f"{key}.anchor", mp.anchor,
                       "a mesh type has only the anchors coupler_front and coupler_rear; give the point by "
                       "'xyz' and 'faces'")
        if not m:
            raise _bad(path, f"{key}.anchor", mp.anchor,
                       "unknown anchor; use coupler_front|rear, body_top|bottom_<end>_<side>, "
                       "nose_<end>_<side>, door<i>_top|bottom_<front|rear>_<side> or roof|bottom_<end>")
        if m.group(5) and getattr(spec, m.group(5)).shape != "nose":
            raise _bad(path, f"{key}.anchor", mp.anchor, f"the {m.group(5)} end is not a nose")
        if m.group(7):
            k = int(m.group(7))
            if not 1 <= k <= len(spec.doors):
                raise _bad(path, f"{key}.anchor", mp.anchor, f"there are {len(spec.doors)} doors (1-based)")
            if m.group(10) not in spec.doors[k - 1].sides:
                raise _bad(path, f"{key}.anchor", mp.anchor, f"door {k} is not on the {m.group(10)} side")


def check_consistency(spec: AnySpec, path: Path) -> None:
    """Cross-field checks the per-field validation cannot do; raises :class:`SettingsError` naming the key, its
    value and the bound. (A mesh type's mesh and points are checked against the file when it is loaded:
    :mod:`.mesh_type`.)"""
    if isinstance(spec, CarriageSpec):
        _check_dimensions(spec.dimensions, path)
        wall_bottom = _check_profile(spec, path)
        _check_layout(spec, wall_bottom, path)
    _check_marked_points(spec, path)


def load_spec(path: Path) -> AnySpec:
    """Read and validate one type file (a mesh type when it has a ``[mesh]`` table). Every problem is a
    :class:`SettingsError` naming the file and key."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SettingsError(f"{path}: carriage type file not found") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SettingsError(f"{path}: not valid TOML ({exc}); fix the syntax at that line") from None
    model = MeshCarriageSpec if isinstance(data, dict) and "mesh" in data else CarriageSpec
    try:
        spec = model.model_validate(data)
    except ValidationError as exc:
        raise SettingsError(_describe(exc, path)) from None
    check_consistency(spec, path)
    return spec
