"""The solver's public data: what goes in (carriages, views, links, options) and what comes out (results).

Conventions: ``docs/conventions.md``. The method is described in ``docs/solver.md``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Mapping

import numpy as np

from ..core.camera import CameraIntrinsics
from ..errors import SettingsError, WorkbenchWarning

LOSSES = ("linear", "huber", "soft_l1", "cauchy")
WEIGHTINGS = ("per_carriage", "per_point")


class SolveWarning(WorkbenchWarning):
    """A carriage could not be solved as asked (too few / degenerate points, left out or carried by its chain),
    or the solve did not converge. Also recorded, structured, in ``SolveResult.warnings``."""


@dataclass(frozen=True)
class Observation:
    """One marked point seen in one view: name, pixel (u, v), visibility indicator."""

    point: str
    u: float
    v: float
    visible: bool = True
    sigma_px: float | None = None  # this point's pixel sigma (None: the solve's pixel_sigma_px)
    # a prediction from other observations (a point projected from a face's pose, or carried from another
    # photo): it guides the fit but adds no information, so the covariance and the pixel sigma leave it out
    derived: bool = False
    # points sharing one systematic misfit (one face of a carriage, in every view): see face_sigma_px
    group: str | None = None
    # the ECC correlation of the face alignment that placed the point (automatic points; None: none): a face
    # without matches of its own takes its shared misfit from it (uncertainty.face_misfit_px)
    ecc: float | None = None
    # a prediction carried from another photo of the panorama (correspond's method "carried"): that photo's point
    # seen again along the same ray; the covariance counts it with its source's alignment error (pose_covariance)
    carried: bool = False


@dataclass(frozen=True, kw_only=True)
class View:
    """One photo: name, intrinsics, ``cam_from_world`` (4, 4); ``focal_known`` False when its focal is only a
    starting value (with ``SolveOptions.estimate_focal``, those views' focal is estimated, and every view's when
    none is marked)."""

    name: str
    intrinsics: CameraIntrinsics
    cam_from_world: np.ndarray
    focal_known: bool = True

    @property
    def camera_centre(self) -> np.ndarray:
        M = np.asarray(self.cam_from_world, dtype=float)
        return -M[:3, :3].T @ M[:3, 3]


@dataclass(kw_only=True)
class CarriageInput:
    """One carriage of the consist (in consist order, front first).

    ``observations``: view name -> either a mapping point name -> (u, v) (present = visible; ``None`` = not
    visible) or a sequence of :class:`Observation`.
    """

    number: str
    carriage_type: Any  # workbench.rolling_stock.CarriageType
    observations: Mapping[str, Any] = field(default_factory=dict)
    on_track: bool = False  # still on the rails: the railway line is a prior (see .track_prior)


@dataclass(frozen=True)
class ChainLink:
    """Coupling between consist indices ``front`` and ``rear`` (= front + 1); ``slack_m=None``: no link."""

    front: int
    rear: int
    slack_m: float | None = 0.05


@dataclass(frozen=True, kw_only=True)
class SolveOptions:
    """How to solve; every field is explained in ``docs/solver.md`` (section "Options")."""

    pixel_sigma_px: float = 1.0
    robust_loss: str = "linear"  # one of LOSSES (scipy's names and formulas)
    loss_scale_px: float = 3.0
    estimate_focal: bool = False
    max_iterations: int = 200
    use_terrain_contact: bool = True
    terrain_sigma_m: float = 0.10
    terrain_samples: int = 400
    # the horizontal field of view an unknown focal is searched in, log-spaced with this ratio between focals
    hfov_range_deg: tuple[float, float] = (3.0, 120.0)
    hfov_step_ratio: float = 1.06
    tolerance: float = 1e-10
    check_image_bounds: bool = True
    compute_covariance: bool = True
    prior_dof: float = 5.0
    # shared misfit of a group of points, in the covariance only (see .uncertainty); None: estimated from the
    # residuals with the points' own noise (.variance_components), where the problem has groups
    face_sigma_px: float | None = 0.0
    weighting: str = "per_carriage"  # one of WEIGHTINGS
    bias_correction: bool = True  # subtract the second-order bias (see .bias)
    bias_max_over_sd: float = 1.0  # a carriage whose bias exceeds this many sd is left uncorrected
    prediction_release: float = 30.0  # step 4b's factor on the predictions' sigmas (1: no check)
    track_sigma_m: float = 1.0  # horizontal 1-sigma of an on-track carriage's bogie pivot about the railway line
    track_gate_m: float = 5.0  # a pivot farther than this from the line at step 4's start: no prior (warned)
    # the multi-view photos' stated errors (.camera_residual.ViewCameraErrors): the residual directions they fill
    # are set aside when the pixel sigma is estimated (the camera term adds their error to the intervals)
    camera_errors: Any = None

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> None:
            raise SettingsError(f"solve options: {name} = {getattr(self, name)!r}: {why}")

        if not (np.isfinite(self.pixel_sigma_px) and self.pixel_sigma_px > 0):
            bad("pixel_sigma_px", "must be a positive number of pixels")
        if self.robust_loss not in LOSSES:
            bad("robust_loss", f"must be one of {', '.join(LOSSES)}")
        if not (np.isfinite(self.loss_scale_px) and self.loss_scale_px > 0):
            bad("loss_scale_px", "must be positive (pixels)")
        if int(self.max_iterations) < 1:
            bad("max_iterations", "must be at least 1")
        if not (np.isfinite(self.terrain_sigma_m) and self.terrain_sigma_m > 0):
            bad("terrain_sigma_m", "must be positive (metres)")
        lo, hi = self.hfov_range_deg
        if not (0 < lo < hi < 180):
            bad("hfov_range_deg", "must be (low, high) with 0 < low < high < 180 degrees")
        if not (1.001 <= self.hfov_step_ratio <= 2.0):
            bad("hfov_step_ratio", "must be between 1.001 and 2 (the ratio of neighbouring focals in the sweep)")
        if self.terrain_samples < 8:
            bad("terrain_samples", "must be at least 8")
        if not (self.tolerance > 0):
            bad("tolerance", "must be positive")
        if self.face_sigma_px is not None and not (np.isfinite(self.face_sigma_px) and self.face_sigma_px >= 0):
            bad("face_sigma_px", "must be a non-negative number of pixels, or None (estimated)")
        for name in ("track_sigma_m", "track_gate_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.floating)) and np.isfinite(v) and v > 0):
                bad(name, "must be a positive number of metres")
        if self.weighting not in WEIGHTINGS:
            bad("weighting", f"must be one of {', '.join(WEIGHTINGS)}")
        if not isinstance(self.bias_correction, (bool, np.bool_)):
            bad("bias_correction", "must be true or false")
        if not (isinstance(self.bias_max_over_sd, (int, float, np.floating)) and np.isfinite(self.bias_max_over_sd)
                and self.bias_max_over_sd > 0):
            bad("bias_max_over_sd", "must be a positive number of standard deviations")
        if not (isinstance(self.prediction_release, (int, float, np.floating)) and np.isfinite(self.prediction_release)
                and self.prediction_release >= 1):
            bad("prediction_release", "must be a number >= 1 (the factor on the predictions' sigmas in the last fit)")


@dataclass
class CarriageResult:
    index: int
    number: str
    type_id: str
    status: str  # "solved" | "carried" | "left_out"
    n_points: int
    world_from_carriage: np.ndarray | None = None
    hpr_deg: tuple[float, float, float] | None = None
    body_centre_m: np.ndarray | None = None
    covariance_pose: np.ndarray | None = None  # (6, 6): scene rotation vector (rad), origin (m)
    sigma_position_m: np.ndarray | None = None  # origin, ENU 1-sigma
    ci95_position_m: np.ndarray | None = None  # origin, ENU 95 % half width
    sigma_body_centre_m: np.ndarray | None = None
    ci95_body_centre_m: np.ndarray | None = None
    sigma_hpr_deg: np.ndarray | None = None
    ci95_hpr_deg: np.ndarray | None = None
    # a carried carriage: its body centre less the point its held coupling(s) hold it at (scene frame, m), and
    # (3, 3) ENU m^2 its swing about that point to second order (the arc the first-order covariance draws
    # straight), in the body centre's sigmas (camera_term.swing_second_moment); None: not carried
    swing_lever_m: np.ndarray | None = None
    centre_curvature_m2: np.ndarray | None = None
    residuals_px: dict[str, dict[str, tuple[float, float]]] = field(default_factory=dict)
    rms_px: float | None = None
    clearance_m: float | None = None


@dataclass
class StepStats:
    name: str
    ran: bool
    note: str = ""
    cost_before: float | None = None
    cost_after: float | None = None
    iterations: int = 0
    status: str = ""
    time_s: float = 0.0
    per_carriage: list[dict] = field(default_factory=list)
    facts: dict = field(default_factory=dict)  # what ``note`` says, as values a program (or a test) can read


@dataclass
class SolveResult:
    carriages: list[CarriageResult]
    status: str  # "converged" | "not_converged" | "failed"
    message: str
    warnings: list[dict]
    steps: list[StepStats]
    iterations: int
    time_s: float
    final_cost: float
    focal_px: dict[str, float]
    sigma_focal_px: dict[str, float]
    sigma_px: float = float("nan")  # pixel sigma used for the covariance
    sigma_px_estimated: float = float("nan")  # the residuals' own (multi-view: where the cameras' errors do not act)
    sigma_px_camera: float = float("nan")  # the residuals' RMS (px) along the directions the cameras' errors fill
    face_sigma_px: float = 0.0  # the shared face misfit in the covariance (px)
    face_misfit_max_px: float | None = None  # the largest face misfit taken from a face's ECC correlation (px)
    aligned_misfit_max_px: float | None = None  # the largest misfit added to an aligned face's alignment error (px)
    noise_estimated: bool = False  # sigma_px and face_sigma_px both estimated from the residuals
    dof: float = 0.0
    ci95_factor: float = 1.96
    neighbour_correlation: list[dict] = field(default_factory=list)
    links: list[dict] = field(default_factory=list)
    covariance: np.ndarray | None = None  # full (6 n_solved [+ n_focal]) in the order of `covariance_order`
    covariance_order: list[str] = field(default_factory=list)
    # the cost at the least-squares minimum (= final_cost unless the bias correction moved the poses off it)
    cost_at_minimum: float = float("nan")
    # what the bias correction did (BiasCorrection.summary(), or {"applied": False, "note"}); empty when off
    bias_correction: dict = field(default_factory=dict)
    # the railway line's prior for the carriages marked on the rails (TrackPriorRecord.to_dict() each)
    track_prior: list[dict] = field(default_factory=list)

    @property
    def converged(self) -> bool:
        return self.status == "converged"

    def carriage(self, number: str) -> CarriageResult:
        for c in self.carriages:
            if c.number == number:
                return c
        raise KeyError(number)

    def to_dict(self) -> dict:
        def conv(o: Any) -> Any:
            if isinstance(o, np.ndarray):
                return conv(o.tolist())
            if isinstance(o, (np.floating, float)):
                f = float(o)
                return f if math.isfinite(f) else None
            if isinstance(o, (np.integer,)):
                return int(o)
            if isinstance(o, dict):
                return {str(k): conv(v) for k, v in o.items()}
            if isinstance(o, (list, tuple)):
                return [conv(v) for v in o]
            return o

        d = {k: v for k, v in self.__dict__.items() if k not in ("carriages", "steps", "covariance")}
        d["carriages"] = [asdict(c) for c in self.carriages]
        d["steps"] = [asdict(s) for s in self.steps]
        return conv(d)
