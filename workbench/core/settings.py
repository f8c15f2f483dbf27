"""Incident settings (``project.toml``): validated pydantic models that reject unknown keys.

The file format is documented in ``docs/formats.md``; ``TEMPLATE`` below is what ``workbench init``
writes. Every error names the file, the key (dotted path) and the bad value.
"""

from __future__ import annotations

import datetime as _dt
import tomllib
from enum import Enum
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ..errors import SettingsError
from .crs import check_projected_crs
from .layout import SETTINGS_FILE


class _Strict(BaseModel):
    """Unknown keys are errors; types are strict (``"1.5"`` is not a number, ``"yes"`` not a boolean; an integer
    is a number); NaN and infinity are refused. Enum choices, dates and coordinate lists are parsed from their TOML
    forms by the fields that say so."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True, strict=True, allow_inf_nan=False)


_LAX = Field(strict=False)  # an enum from its string, a date from a quoted 'YYYY-MM-DD', a tuple from a TOML array


def _numbers_only(v: Any, what: str) -> Any:
    """A lax tuple field still takes numbers only: ``["1.5", 2]`` is refused, not converted."""
    if isinstance(v, (list, tuple)) and any(isinstance(x, (str, bool)) for x in v):
        raise ValueError(f"give {what}, not strings or booleans")
    return v


class Incident(_Strict):
    name: Annotated[str, Field(min_length=1)]
    date: Annotated[_dt.date, _LAX]
    description: str = ""
    synthetic: bool = False  # true for incidents made by `workbench synth` (their photos are renders)


class Location(_Strict):
    lat: Annotated[float, Field(ge=-90.0, le=90.0)]
    lon: Annotated[float, Field(ge=-180.0, le=180.0)]
    height_m: float = 0.0
    crs: str

    @field_validator("crs")
    @classmethod
    def _projected(cls, v: str) -> str:
        try:
            check_projected_crs(v)
        except SettingsError as exc:
            raise ValueError(str(exc).split(" = ", 1)[-1]) from None
        return v


class Terrain(_Strict):
    dem: str | None = None  # GeoTIFF, a folder of tiles, or a glob (`dem/*.tif`), relative to the project folder
    buildings: str | None = None  # GeoJSON footprints with heights, or CityJSON, relative path
    dem_vertical_accuracy_m: Annotated[float, Field(gt=0.0)] = 0.5
    aoi_radius_m: Annotated[float, Field(gt=0.0, le=20_000.0)] = 250.0
    simplify_max_error_m: Annotated[float, Field(ge=0.0, le=10.0)] = 0.05  # 0: no mesh simplification
    ortho: str | None = None  # orthophoto (JPEG/PNG) covering the DEM's extent, row 0 north; drapes the terrain
    # railway lines (GeoJSON lines, or OpenStreetMap XML ways tagged railway=rail), any CRS, relative path
    railways: str | None = None


class Coupling(str, Enum):
    held = "held"
    broken = "broken"


class Car(_Strict):
    number: Annotated[str, Field(min_length=1, pattern=r"^[A-Za-z0-9._-]+$")]
    type: Annotated[str, Field(min_length=1)]
    coupling_to_next: Annotated[Coupling | None, _LAX] = None  # required for every car but the last; absent on the last
    on_track: bool = False  # still on the rails: the railway line (terrain.railways) is a prior on its place


class CameraSource(str, Enum):
    calibrated = "calibrated"  # a camera profile from `workbench calibrate` (or a known synthetic camera)
    exif = "exif"  # focal prior from the photos' EXIF
    sfm = "sfm"  # multi-view structure from motion (pycolmap)
    unknown = "unknown"  # simplified pinhole, focal estimated in the solver


class Camera(_Strict):
    source: Annotated[CameraSource, _LAX] = CameraSource.exif
    photos: str = "photos/panorama"  # folder of the photos to use, relative to the project folder
    profile: str | None = None  # camera profile JSON (required when source = "calibrated")
    position_enu: Annotated[tuple[float, float, float] | None, _LAX] = None  # known camera centre until georef

    @field_validator("position_enu", mode="before")
    @classmethod
    def _numbers(cls, v: Any) -> Any:
        return _numbers_only(v, "three numbers (metres east, north, up)")

    @model_validator(mode="after")
    def _profile_needed(self) -> "Camera":
        if self.source == CameraSource.calibrated and not self.profile:
            raise ValueError("source = 'calibrated' needs profile = '<camera profile JSON>'")
        return self


class RobustLoss(str, Enum):
    linear = "linear"
    huber = "huber"
    soft_l1 = "soft_l1"
    cauchy = "cauchy"




class Solver(_Strict):
    pixel_sigma_px: Annotated[float, Field(gt=0.0)] = 1.0
    robust_loss: Annotated[RobustLoss, _LAX] = RobustLoss.linear
    loss_scale_px: Annotated[float, Field(gt=0.0)] = 3.0
    slack_held_m: Annotated[float, Field(gt=0.0, le=1.0)] = 0.05
    slack_broken_m: Annotated[float, Field(gt=0.0)] | None = None  # None: a broken coupling gives no link
    estimate_focal: bool = False
    max_iterations: Annotated[int, Field(ge=1, le=10_000)] = 200
    # a marked point whose residual exceeds this many pixel sigmas is dropped and the solve repeated (worst
    # point of each carriage per round, at most `max_rejection_rounds`); 0 turns the rejection off
    reject_outliers_sigma: Annotated[float, Field(ge=0.0)] = 5.0
    max_rejection_rounds: Annotated[int, Field(ge=0, le=50)] = 5
    # pixels of misfit shared by the points one homography placed on one face (automatic points): modelled in
    # the covariance as a common affine displacement of each face's points (docs/solver.md); 0: none;
    # "estimate": it and the points' own noise estimated from the residuals (sharper, more gross misses: see
    # docs/calibration.md, "Automatic points: the noise estimated")
    face_sigma_px: Annotated[float, Field(ge=0.0, le=10.0)] | Literal["estimate"] = 0.15
    # subtract the second-order bias of the least-squares estimate (workbench/solve/bias.py, docs/solver.md): only
    # with a known focal and no robust loss, and only for carriages whose predicted bias is under one standard
    # deviation (the step "5_bias_correction" of solution.json says what was corrected and what was not)
    bias_correction: bool = True
    # predicted points (projected from a face's pose, carried from another photo) steer the solve into its
    # basin; step "4b_predictions_checked" fits again with their sigmas multiplied by this (the measured points'
    # fit, which the intervals describe) and releases them on every car they pulled further than its covariance
    # allows (docs/correspondences.md); 1: no check, they keep their weight
    prediction_release: Annotated[float, Field(ge=1.0)] = 30.0
    # the horizontal field of view (degrees, [narrowest, widest]) an unknown focal is searched in: telephoto
    # railway photos reach 3-8 deg, phones' wide cameras 120 (a warning names this key when the focal reaches an end)
    hfov_range_deg: Annotated[tuple[float, float], _LAX] = (3.0, 120.0)
    # a relative scene (no survey) is levelled from the carriages standing on their wheels: each car's own tilt
    # (suspension, ballast; independent car to car) and the track's grade and cant (common to all, not averaged
    # away), 1-sigma degrees (docs/solver.md, "Relative scenes")
    level_sigma_car_deg: Annotated[float, Field(ge=0.0, le=20.0)] = 0.5
    level_sigma_common_deg: Annotated[float, Field(ge=0.0, le=20.0)] = 0.5
    # a carriage still on the rails (consist `on_track = true`): horizontal 1-sigma of each bogie pivot about the
    # railway line, metres: the line's own accuracy (a public map traced from aerial images: 1-2 m; a surveyed
    # or generated line: 0.05-0.1 m) with the wheelsets' play (a centimetre) (docs/solver.md, "On the rails")
    track_sigma_m: Annotated[float, Field(gt=0.0, le=50.0)] = 1.0

    @field_validator("hfov_range_deg", mode="before")
    @classmethod
    def _hfov_numbers(cls, v: Any) -> Any:
        return _numbers_only(v, "two numbers (degrees), e.g. [3.0, 120.0]")

    @field_validator("hfov_range_deg")
    @classmethod
    def _hfov_order(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not (0.5 <= v[0] < v[1] <= 170.0):
            raise ValueError("must be [narrowest, widest] field of view in degrees, 0.5 <= narrowest < widest <= 170")
        return v


class FinderMode(str, Enum):
    AUTO = "auto"  # search every photo for the library's liveries (SIFT against each car's reference faces)
    OFF = "off"  # no automatic points: the incident's hand picks only (real rolling stock not in the library)


class Correspond(_Strict):
    finder: Annotated[FinderMode, _LAX] = FinderMode.AUTO


class Georef(_Strict):
    # 1-sigma of a control point's pick in a photo (px): a survey target's centre 0.5-1 px, a landmark's corner
    # picked by hand on a phone photo 2-3 px; with each point's sigma_m it weights the picks, sets the camera's
    # covariance and the inlier limit (docs/gis.md)
    pick_sigma_px: Annotated[float, Field(gt=0.0, le=50.0)] = 1.0
    # 1-sigma of a track pick (a point picked on a rail or the track centre, control_points.json track_picks)
    # across the line, px: a rail is a thin line, but a hand pick on a phone photo is 1-3 px off it (docs/gis.md)
    track_sigma_px: Annotated[float, Field(gt=0.0, le=50.0)] = 2.0


class ExportFormat(str, Enum):
    GLB = "glb"  # glTF 2.0 binary (the only one a relative scene gets: it needs no place on the Earth)
    GEOJSON = "geojson"
    KMZ = "kmz"
    CITYJSON = "cityjson"
    TILES = "tiles"


GIS_FORMATS = ("geojson", "kmz", "cityjson", "tiles")  # they place the scene on the Earth: georeference needed


class Export(_Strict):
    # the formats the export stage writes; absent: every one the scene allows (a relative scene: glb only)
    formats: Annotated[list[Annotated[ExportFormat, _LAX]], Field(min_length=1)] | None = None


class ProjectSettings(_Strict):
    incident: Incident
    location: Location
    terrain: Terrain = Terrain()
    consist: Annotated[list[Car], Field(min_length=1)]
    camera: Camera = Camera()
    # optional [sfm] table: pycolmap options for the multi-view route (keys of workbench.intrinsics.sfm.SfmOptions,
    # plus preset = "forward_motion"); checked by the sfm stage, which rejects unknown keys
    sfm: dict[str, Any] | None = None
    solver: Solver = Solver()
    correspond: Correspond = Correspond()
    georef: Georef = Georef()
    export: Export = Export()

    @model_validator(mode="after")
    def _consist_rules(self) -> "ProjectSettings":
        seen: set[str] = set()
        for i, car in enumerate(self.consist):
            if car.number in seen:
                raise ValueError(f"consist[{i}].number = {car.number!r} appears twice; car numbers must be unique")
            seen.add(car.number)
            last = i == len(self.consist) - 1
            if last and car.coupling_to_next is not None:
                raise ValueError(f"consist[{i}].coupling_to_next = {car.coupling_to_next.value!r}: the last car "
                                 f"({car.number}) has no next car; remove the key")
            if not last and car.coupling_to_next is None:
                raise ValueError(f"consist[{i}].coupling_to_next is missing for car {car.number}: say 'held' or "
                                 f"'broken'")
            if car.on_track and not self.terrain.railways:
                raise ValueError(f"consist[{i}].on_track = true (car {car.number}) needs the railway line: set "
                                 f"terrain.railways to the railway layer (GeoJSON or OpenStreetMap XML), or remove "
                                 f"on_track")
        return self


def _format_loc(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def short_repr(value: Any, limit: int = 40) -> str:
    """``repr(value)`` cut to ``limit`` characters (a message never echoes a whole bad file back)."""
    r = repr(value)
    return r if len(r) <= limit else r[:limit] + f"... ({len(r)} characters)"


def describe_validation_error(exc: ValidationError, source: str, hint: str = "see docs/formats.md") -> str:
    """One line naming ``source`` (a file), then each bad key with its value and what is wrong."""
    msgs = []
    for err in exc.errors():
        key = _format_loc(err["loc"])
        typ = err["type"]
        if typ == "extra_forbidden":
            msgs.append(f"unknown key '{key}' (check the spelling; {hint})")
        elif typ == "missing":
            msgs.append(f"missing key '{key}'")
        else:
            msg = err["msg"].removeprefix("Value error, ")
            if key:
                msgs.append(f"'{key}' = {short_repr(err.get('input'))}: {msg}")
            else:
                msgs.append(msg)
    return f"{source}: " + "; ".join(msgs)


def parse_settings(data: dict, source: str = SETTINGS_FILE) -> ProjectSettings:
    if "consist" in data and data["consist"] == []:
        raise SettingsError(f"{source}: the consist is empty; add one [[consist]] table per carriage")
    try:
        return ProjectSettings.model_validate(data)
    except ValidationError as exc:
        raise SettingsError(describe_validation_error(exc, source)) from None


def load_settings(path: Path) -> ProjectSettings:
    """Read and validate ``project.toml``; every problem is a :class:`SettingsError` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise SettingsError(f"{path}: settings file not found; create one with `workbench init {path.parent}`")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SettingsError(f"{path}: not valid TOML ({exc}); fix the syntax at that line") from None
    return parse_settings(data, str(path))


TEMPLATE = """\
# Incident settings. Every key is documented in docs/formats.md.
# Paths are relative to this folder. Unknown keys are an error.

[incident]
name = "{name}"
date = {date}                 # TOML date: YYYY-MM-DD
description = ""

[location]
lat = {lat}                   # reference point (scene origin), WGS84 degrees
lon = {lon}
height_m = 0.0                # origin height in the DEM's vertical datum, metres
crs = "{crs}"                 # projected CRS of the project (metres), e.g. the UTM zone

[terrain]
# dem = "../../terrain/<region>/dem.tif"            # GeoTIFF with a CRS
# buildings = "../../terrain/<region>/buildings.geojson"
# railways = "../../terrain/<region>/railways.geojson"  # track centre lines (GeoJSON or OSM XML)
dem_vertical_accuracy_m = 0.5
aoi_radius_m = 250.0

# The consist, front to rear. coupling_to_next: "held" or "broken" (absent on the last car).
[[consist]]
number = "1"
type = "shoreliner"           # a rolling-stock type id (`workbench types` lists them)

[camera]
source = "exif"               # calibrated | exif | sfm | unknown
photos = "photos/panorama"
# profile = "camera_profile.json"   # needed when source = "calibrated"
# position_enu = [0.0, 0.0, 0.0]    # known camera centre (scene frame), until georegistration

[correspond]
finder = "auto"               # auto: find the carriages' liveries in the photos | off: hand picks only

[georef]
pick_sigma_px = 1.0           # 1-sigma of a control point's pick in a photo, px (hand picks on a phone photo: 2-3)
track_sigma_px = 2.0          # 1-sigma of a track pick (a point picked on a rail) across the rail, px

[solver]
pixel_sigma_px = 1.0
robust_loss = "linear"        # linear | huber | soft_l1 | cauchy
loss_scale_px = 3.0
slack_held_m = 0.05           # coupler slack of a coupling that held, metres
# slack_broken_m = 2.0        # absent: a broken coupling gives no link
estimate_focal = false
max_iterations = 200
reject_outliers_sigma = 5.0    # drop a marked point farther than this many pixel sigmas from the fit (0: off)
face_sigma_px = 0.15          # misfit shared by one face's automatic points, pixels (covariance only; 0: none; "estimate")
bias_correction = true        # remove the estimate's second-order bias (known focal only; docs/solver.md)
prediction_release = 30.0     # predictions that pull a car off its measured points' fit: sigma x this (1: no check)
hfov_range_deg = [3.0, 120.0]  # field of view (deg) an unknown focal is searched in: telephoto to wide angle
level_sigma_car_deg = 0.5     # no survey: each upright car's own tilt, deg (levels the relative scene)
level_sigma_common_deg = 0.5  # no survey: the track's grade and cant under all the cars, deg
track_sigma_m = 1.0           # a car marked on_track: its bogies' 1-sigma about the railway line, m (map: 1-2; survey: 0.05)
"""


def options_from_dict(cls: type, d: dict, what: str):
    """An options dataclass ``cls`` from a plain dict; :class:`SettingsError` naming ``what`` and the keys it knows
    when ``d`` has others."""
    known = set(cls.__dataclass_fields__)
    unknown = sorted(set(d) - known)
    if unknown:
        raise SettingsError(f"{what}: unknown key(s) {unknown}; known: {sorted(known)}")
    return cls(**d)
