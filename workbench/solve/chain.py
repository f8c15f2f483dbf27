"""Simultaneous pose of all carriages of a consist from a few 2D-3D marked points each, chained at the couplers.

Conventions: ``docs/conventions.md`` (scene ENU frame, camera x right / y down / z forward, carriage frame x
forward / y left / z up, origin midway between the coupler faces at top-of-rail height).

Unknowns
    every carriage's ``world_from_carriage`` (rotation, translation) and, optionally, one focal length per
    view (fx = fy moved together; principal point and distortion held at the given intrinsics).
Observations
    per view (known ``cam_from_world`` and intrinsics), per carriage, per marked point: a pixel (u, v); the
    point's presence (or ``Observation.visible``) is the visibility indicator I_ij.
Residuals
    reprojection errors (px) of the visible points. ``SolveOptions.weighting``: ``"per_carriage"`` (the
    default, as the issue states it) gives carriage i's rows the weight ``w_i = sqrt(n_mean / n_i)`` (``n_i``
    its visible points, ``n_mean`` the mean over the solved carriages): the seed's per-carriage normalisation
    1/sqrt(n_i), rescaled by a constant so that with equal counts the weights are 1 and the cost is the plain
    sum of squares; ``"per_point"`` weights every point alike (1 / sigma^2): the maximum-likelihood estimate
    for independent pixel noise, whose covariance is the Cramér-Rao bound's (the per-carriage weighting
    discounts the points of well-observed carriages; with unequal counts its error is larger, see
    docs/solver.md). Equal counts: the same estimator. The covariance accounts for the weighting with the
    sandwich form (see :mod:`.uncertainty`). An optional robust loss (scipy's ``huber``, ``soft_l1``,
    ``cauchy``) with a scale in px.
Chain
    carriage i+1's front coupler sits at carriage i's rear coupler plus an offset T, |T| <= slack. A link with
    ``slack_m=None`` is no link: the consist falls into independent chains.

Why this parametrisation
    The ball constraint |T| <= s is honoured **exactly** at every iterate: the translation of every carriage
    after the first one of its chain is *eliminated* through the chain,
    ``t_{i+1} = t_i + R_i c_rear_i + T_i - R_{i+1} c_front_{i+1}``, so the parameters ``x`` of a chain are the
    first carriage's translation, every carriage's rotation increment (``R = Exp(delta) R_ref``, scene-frame
    rotation vector) and every link's offset: the offset T itself while it is inside the ball ("free"), or,
    when it reaches the sphere, 2 parameters of the exponential chart of the sphere |T| = s (an active set,
    :func:`_solve_chained`: a free link whose offset leaves the ball is moved onto the sphere and the step
    re-solved; a link on the sphere is released when its multiplier changes sign). Held couplings also carry
    the offset prior N(0, (s/sqrt 5)^2) per axis (the spread of an offset uniform in the ball), which keeps
    the problem well conditioned and is the same model the covariance and the Cramér-Rao bound use.

Method (one for every step and every size)
    Levenberg-Marquardt with Marquardt scaling (the exact diagonal of the Gauss-Newton matrix in ``x``) and
    Nielsen's damping update, :func:`_lm_struct` — a trust-region method in the sense of Moré (1978): each
    step minimises the Gauss-Newton model in the scaled ellipsoid whose radius the damping is the multiplier
    of, and the radius follows the ratio of actual to predicted reduction. The step is taken in ``x`` (so the
    constraint stays exact) but *computed* in expanded variables ``z`` (every carriage's own rotation and
    translation increments, the link parameters, the focal) subject to the linearised coupling equations
    ``C z = 0``: there the Gauss-Newton matrix is block diagonal (plus the focal's rows) and ``C`` couples only
    neighbours, so the KKT system is sparse and is factored by SuperLU (``scipy.sparse.linalg.splu``) in
    O(N) per iteration for a chain of N carriages (the elimination in ``x`` would make the normal equations
    dense, O(N^3)); a small system (up to :data:`DENSE_KKT_MAX` rows, ~17 carriages with free rotations) is
    solved dense by LAPACK, where SuperLU's per-call overhead would dominate. The step is identical to the
    dense one in ``x``. A link on the sphere adds the sphere's curvature times its multiplier to its block of
    the Gauss-Newton matrix (the constraint's term of the Lagrangian's Hessian), so that an offset held at the
    slack converges quadratically, not linearly. Exact analytic Jacobians (projection
    derivatives from :mod:`.projection`, the SO(3) left Jacobian, the chain rule of the couplings). Robust
    losses (scipy's ``huber``, ``soft_l1``, ``cauchy``) enter as in scipy's ``least_squares`` (rows rescaled
    by the loss' derivatives).

The four steps (as the seed, plus an optional contact term)
    1. each carriage alone, constraints off (PnP start: SQPnP on undistorted normalised points, then one joint
       refinement of all the independent poses (a block-diagonal problem) and, when estimated, the focal; with an
       unknown focal first a sweep over the horizontal field of view picks the focal of least total PnP
       reprojection error, and on a chained consist a profile of the *chained* cost over the focal
       (:func:`_chained_focal_profile`) replaces it and the focal is held in this step: one carriage seen
       from afar shows too little perspective for its PnP error to tell the focal, and its error falls towards
       the affine limit (the longest focal), while the couplers tell it well);
    2. each carriage lowered (or raised) along gravity (scene -z) until its surface samples rest on the
       terrain without penetrating it (skipped, and recorded so, without a terrain);
    3. constraints on, rotations held from step 1, translations (and focal) optimised;
    4. everything optimised together; with a terrain and ``use_terrain_contact`` a soft contact residual
       per carriage, ``min clearance / terrain_sigma_m`` (in units of the pixel sigma), joins the cost. After a
       focal profile, a check: the solution (focal free) can cost no more than the profile's best fixed-focal
       chained solve; if it does, step 4 ended in another basin and is restarted from that solve (kept if
       cheaper; the step's note says so). Then a check of every chained carriage's fit
       (:func:`_retry_branches`): one whose pixel residuals are far beyond their chi-square (and the other
       carriages') may sit on the wrong branch of its own PnP (an end face seen alone, or 4 points, fit two
       poses ~90 degrees apart, and SQPnP may pick the wrong one); steps 3 and 4 are re-run from its other
       branches (:func:`_pnp_branches`) and the cheapest solution kept (the step's note says so). A carriage
       with at most :data:`FEW_POINTS` (5) points cannot show a wrong branch in its own chi-square (4 points fit
       P3P's other poses with 2 degrees of freedom left), so every such chained carriage is tried on its other
       PnP branches and on a pose carried from each chain neighbour over the held coupling, the chained cost
       judging. The focal profile makes the misfit check at each focal (not the few-point one).

Step 5 (``SolveOptions.bias_correction``, on by default; not with a robust loss or an estimated focal)
    the second-order bias of the least-squares estimate (Box 1971; Cook, Tsai & Wei 1986) is estimated at the
    solution and subtracted (:mod:`.bias`): sigma-point differences of the residuals give each row's curvature
    along the covariance, no analytic Hessian; the corrected poses are put back on the chain (offsets clipped to
    the slack); the covariance is the minimum's, centred on the corrected poses; ``SolveResult.cost_at_minimum``
    keeps the minimum's cost and ``SolveResult.bias_correction`` / the step's stats what moved. A carriage whose
    predicted bias exceeds ``SolveOptions.bias_max_over_sd`` (1) standard deviations in any pose component is
    left uncorrected (the expansion does not hold there; the step's note names it).

:func:`refine_from` (step 4 alone, from given poses) is a diagnostic for benchmarks: started at the truth it
finds the minimum in the truth's basin, which tells a solver failure from the estimator's own spread.
"""

from __future__ import annotations

import copy
import logging
import math
import time
import warnings
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Mapping, Sequence

import numpy as np
import scipy.sparse as sp

from ..core.camera import CameraIntrinsics
from ..core.frames import hpr_from_rotation
from ..errors import InputError, SettingsError, WorkbenchWarning
from .projection import exp_so3, left_jacobian_so3, project_world_points_with_jacobians, skew

log = logging.getLogger(__name__)


SQRT5 = math.sqrt(5.0)  # slack / sigma_T: an offset uniform in the ball |T| <= s has per-axis sd s / sqrt(5)


class SolveWarning(WorkbenchWarning):
    """A carriage could not be solved as asked (too few / degenerate points, left out or carried by its chain),
    or the solve did not converge. Also recorded, structured, in ``SolveResult.warnings``."""


# ----------------------------------------------------------------------------------------------------------
# Public data
# ----------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Observation:
    """One marked point seen in one view: name, pixel (u, v), visibility indicator."""

    point: str
    u: float
    v: float
    visible: bool = True
    sigma_px: float | None = None  # this point's pixel sigma (None: the solve's pixel_sigma_px)
    # a prediction from other observations (a point projected from a face's pose, or carried from another
    # photo): it guides the fit, but adds no information, so the covariance and the pixel sigma leave it out
    derived: bool = False
    # points that share one systematic misfit (those the homographies placed on one face of the carriage, in
    # every view): their covariance adds ``SolveOptions.face_sigma_px`` of a common affine displacement
    group: str | None = None


@dataclass(frozen=True, kw_only=True)
class View:
    """One photo: name, intrinsics, ``cam_from_world`` (4, 4)."""

    name: str
    intrinsics: CameraIntrinsics
    cam_from_world: np.ndarray

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


@dataclass(frozen=True)
class ChainLink:
    """Coupling between consist indices ``front`` and ``rear`` (= front + 1); ``slack_m=None``: no link."""

    front: int
    rear: int
    slack_m: float | None = 0.05


_LOSSES = ("linear", "huber", "soft_l1", "cauchy")
_WEIGHTINGS = ("per_carriage", "per_point")


@dataclass(frozen=True, kw_only=True)
class SolveOptions:
    pixel_sigma_px: float = 1.0
    robust_loss: str = "linear"
    loss_scale_px: float = 3.0
    estimate_focal: bool = False
    max_iterations: int = 200
    use_terrain_contact: bool = True
    terrain_sigma_m: float = 0.10
    terrain_samples: int = 400
    # the horizontal field of view an unknown focal is searched in: railway photos are often telephoto (8-20 deg),
    # phones' wide cameras reach 100-120 deg. The sweep is log-spaced in focal, a step 6 % (72 steps)
    hfov_range_deg: tuple[float, float] = (3.0, 120.0)
    hfov_step_ratio: float = 1.06
    tolerance: float = 1e-10
    check_image_bounds: bool = True
    compute_covariance: bool = True
    prior_dof: float = 5.0
    # pixels of a systematic misfit shared by the points of one group (one face of a carriage, all views): a
    # common affine displacement of that size, modelled in the covariance only (see .uncertainty); 0: none
    face_sigma_px: float = 0.0
    # residual weighting (see the module doc, "Residuals"): "per_carriage", carriage i's term normalised by its
    # n_i visible points (w_i = sqrt(n_mean / n_i)); or "per_point", every point weighted 1 / sigma^2 — the
    # maximum-likelihood estimate for independent pixel noise, the estimator whose Cramér-Rao bound is the ML
    # information. The two are identical when every carriage shows the same number of points.
    weighting: str = "per_carriage"
    # subtract the second-order bias of the least-squares estimate (Box 1971; see .bias) from the solution: the
    # reported poses are the corrected ones, the intervals are centred on them, and the step
    # "5_bias_correction" records what moved. On by default; not applied with a robust loss or an estimated focal
    # (there the step says so), nor to a carriage whose predicted bias is not small against its own spread
    # (below). See docs/solver.md for what it changes.
    bias_correction: bool = True
    # the second-order expansion holds only where the bias is small against the estimate's spread: a carriage
    # whose predicted bias exceeds this many standard deviations in any of its six pose components is left
    # uncorrected (the step's note names it), so that a poorly observed carriage is never moved by an expansion
    # that does not hold there
    bias_max_over_sd: float = 1.0
    # predictions (points projected from a face's pose, points carried from another photo: Observation.derived)
    # steer steps 1-4 at their own sigma, which keeps a carriage seen by one face in the right basin. Step
    # "4b_predictions_checked" then fits again with their sigmas multiplied by this factor (the fit of the measured
    # points, which the covariance describes) and checks each carriage: where its predictions moved it further
    # from that fit than its own covariance allows (chi-square, 6 dof, 95 %), they were off (a far corner
    # projected from a face whose pose fits the face but not the car) and stay released; elsewhere they agree
    # with the measurements and keep their weight. 1: no check, the predictions keep their weight
    prediction_release: float = 30.0

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> None:
            raise SettingsError(f"solve options: {name} = {getattr(self, name)!r}: {why}")

        if not (np.isfinite(self.pixel_sigma_px) and self.pixel_sigma_px > 0):
            bad("pixel_sigma_px", "must be a positive number of pixels")
        if self.robust_loss not in _LOSSES:
            bad("robust_loss", f"must be one of {', '.join(_LOSSES)}")
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
        if not (np.isfinite(self.face_sigma_px) and self.face_sigma_px >= 0):
            bad("face_sigma_px", "must be a non-negative number of pixels")
        if self.weighting not in _WEIGHTINGS:
            bad("weighting", f"must be one of {', '.join(_WEIGHTINGS)}")
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
    sigma_px_estimated: float = float("nan")
    dof: float = 0.0
    ci95_factor: float = 1.96
    neighbour_correlation: list[dict] = field(default_factory=list)
    links: list[dict] = field(default_factory=list)
    covariance: np.ndarray | None = None  # full (6 n_solved [+ n_focal]) in the order of `covariance_order`
    covariance_order: list[str] = field(default_factory=list)
    # the cost at the least-squares minimum (= final_cost unless the bias correction moved the poses off it)
    cost_at_minimum: float = float("nan")
    # SolveOptions.bias_correction: what it did ({"applied", "note", "max_shift_m", "max_rotation_deg",
    # "focal_shift_px", "links_clipped", "max_bias_over_sd", "skipped"}, or {"applied": False, "note"});
    # empty when off
    bias_correction: dict = field(default_factory=dict)

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


# ----------------------------------------------------------------------------------------------------------
# Input checking and flattening
# ----------------------------------------------------------------------------------------------------------
def _iter_observations(car: CarriageInput, view_name: str, obs: Any):
    """(point name, (u, v), sigma_px or None, derived, group or None) of the visible observations of one view."""
    if isinstance(obs, Mapping):
        for name, uv in obs.items():
            if uv is None:
                continue
            if isinstance(uv, Observation):
                if uv.visible:
                    yield str(name), (uv.u, uv.v), uv.sigma_px, uv.derived, uv.group
                continue
            yield str(name), uv, None, False, None
    else:
        for o in obs:
            if isinstance(o, Observation):
                if o.visible:
                    yield o.point, (o.u, o.v), o.sigma_px, o.derived, o.group
            else:
                name, uv = o
                yield str(name), uv, None, False, None


@dataclass
class _Car:
    index: int
    number: str
    ctype: Any
    names: list[str]  # per observation row
    views: np.ndarray  # (n,) int
    P: np.ndarray  # (n, 3)
    uv: np.ndarray  # (n, 2)
    distinct: list[str]
    c_front: np.ndarray
    c_rear: np.ndarray
    c_body: np.ndarray
    scale: np.ndarray | None = None  # (n,) each point's sigma / the solve's pixel sigma (None: all 1)
    derived: np.ndarray | None = None  # (n,) bool: a prediction, not a measurement (see Observation.derived)
    groups: list | None = None  # (n,) the observation's group (see Observation.group) or None


def _prepare(carriages: Sequence[CarriageInput], views: Sequence[View], options: SolveOptions) -> list[_Car]:
    if not views:
        raise InputError("solve: no views (photos) given")
    vnames = [v.name for v in views]
    if len(set(vnames)) != len(vnames):
        raise InputError(f"solve: view names repeat: {vnames}")
    vindex = {n: i for i, n in enumerate(vnames)}
    for v in views:
        M = np.asarray(v.cam_from_world, dtype=float)
        if M.shape != (4, 4) or not np.all(np.isfinite(M)):
            raise InputError(f"view {v.name!r}: cam_from_world must be a finite (4, 4) matrix")
    numbers = [str(c.number) for c in carriages]
    if len(set(numbers)) != len(numbers):
        dup = sorted({n for n in numbers if numbers.count(n) > 1})
        raise InputError(f"consist: car number(s) {dup} appear more than once")
    out = []
    for i, c in enumerate(carriages):
        ct = c.carriage_type
        names, vi, P, uv, sc, der, grp = [], [], [], [], [], [], []
        for vname, obs in (c.observations or {}).items():
            if vname not in vindex:
                raise InputError(f"car {c.number}: observations for view {vname!r}, which is not among the views "
                                 f"{vnames}")
            intr = views[vindex[vname]].intrinsics
            seen: set[str] = set()
            for name, pix, sig, derived, group in _iter_observations(c, vname, obs):
                if name not in ct.marked_points:
                    raise InputError(f"car {c.number}, view {vname!r}: point {name!r} is not a marked point of type "
                                     f"{ct.id!r} (it has: {', '.join(ct.marked_points)})")
                if name in seen:
                    raise InputError(f"car {c.number}, view {vname!r}: point {name!r} is given twice")
                seen.add(name)
                a = np.asarray(pix, dtype=float).reshape(-1)
                if a.size != 2 or not np.all(np.isfinite(a)):
                    raise InputError(f"car {c.number}, view {vname!r}, point {name!r}: pixel {pix!r} is not a "
                                     f"finite (u, v)")
                if options.check_image_bounds and not intr.in_image(a[None])[0]:
                    raise InputError(f"car {c.number}, view {vname!r}, point {name!r}: pixel ({a[0]:.1f}, "
                                     f"{a[1]:.1f}) is outside the {intr.width}x{intr.height} image")
                if sig is not None and not (np.isfinite(sig) and sig > 0):
                    raise InputError(f"car {c.number}, view {vname!r}, point {name!r}: sigma_px = {sig!r} must be a "
                                     f"positive number of pixels")
                names.append(name)
                vi.append(vindex[vname])
                P.append(ct.marked_points[name])
                uv.append(a)
                sc.append(1.0 if sig is None else float(sig) / options.pixel_sigma_px)
                der.append(bool(derived))
                grp.append(None if group is None else str(group))
        distinct = sorted(set(names))
        body = np.array([0.0, 0.0, 0.5 * float(ct.height_m)])
        out.append(_Car(i, str(c.number), ct, names, np.asarray(vi, dtype=int),
                        np.asarray(P, dtype=float).reshape(-1, 3), np.asarray(uv, dtype=float).reshape(-1, 2),
                        distinct, np.asarray(ct.coupler_front, float), np.asarray(ct.coupler_rear, float), body,
                        np.asarray(sc, dtype=float), np.asarray(der, dtype=bool), grp))
    return out


def _degeneracy(ct: Any, names: list[str]) -> str:
    """'' or 'collinear' / 'coplanar' for the distinct marked points ``names``."""
    if len(names) < 3:
        return "collinear"
    X = np.array([ct.marked_points[n] for n in names], dtype=float)
    s = np.linalg.svd(X - X.mean(0), compute_uv=False)
    if s[0] <= 0 or s[1] / s[0] < 1e-3:
        return "collinear"
    if len(names) < 4 or s[2] / s[0] < 1e-3:
        return "coplanar"
    return ""


# ----------------------------------------------------------------------------------------------------------
# Parametrisation of one optimisation step
# ----------------------------------------------------------------------------------------------------------
_EYE3 = np.eye(3)
_EYE3.flags.writeable = False
# the trust-region system of a step is solved dense up to this many unknowns and constraints (a 10-carriage
# step with free rotations has 114): dense LU costs O(n^3), SuperLU O(n) plus a fixed per-call overhead; on
# the benchmark's consists the two break even between 20 (n = 234) and 30 carriages (n = 354)
DENSE_KKT_MAX = 200


def _sphere_basis(d: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis of the plane orthogonal to the unit vector d."""
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b1 = np.cross(d, a)
    b1 /= np.linalg.norm(b1)
    return np.column_stack([b1, np.cross(d, b1)])


class _Layout:
    """Maps the parameter vector of a step to poses (and focal) with d t / d params per carriage.

    Per chain: the first carriage's translation (3), the rotation increments (3 per carriage, when free),
    and per link either ``"free"`` (the offset T itself, 3 parameters; the active-set driver keeps it inside
    the ball) or ``"sphere"`` (the constraint active: ``T = s (d0 + B a) / |d0 + B a|``, 2 parameters, exactly
    on the sphere |T| = s).
    """

    def __init__(self, chains: list[list[int]], slacks: list[list[float]], rot_free: bool, focal_views: list[int],
                 cars: list[_Car], R_ref: np.ndarray, t_ref: np.ndarray, f_ref: np.ndarray,
                 modes: list[list[str]] | None = None, prior_px: float = 1.0):
        self.chains, self.slacks, self.rot_free = chains, slacks, rot_free
        self.prior_px = float(prior_px)  # the configured pixel sigma: coupler prior rows are T * prior_px / sigma_T
        self.focal_views = list(focal_views)
        self.cars = cars
        self.R_ref, self.f_ref = R_ref.copy(), f_ref.copy()
        self.modes = modes if modes is not None else [["free"] * (len(ch) - 1) for ch in chains]
        self.off, self.size, self.link_off, self.sphere = [], [], [], []
        n = 0
        x0 = []
        for c, (ch, sl) in enumerate(zip(chains, slacks)):
            self.off.append(n)
            m = 3 + (3 * len(ch) if rot_free else 0)
            x0.append(t_ref[ch[0]])
            if rot_free:
                x0.append(np.zeros(3 * len(ch)))
            lo, sph = [], []
            for j in range(len(ch) - 1):
                a, b = cars[ch[j]], cars[ch[j + 1]]
                T = (t_ref[ch[j + 1]] + R_ref[ch[j + 1]] @ b.c_front) - (t_ref[ch[j]] + R_ref[ch[j]] @ a.c_rear)
                lo.append(m)
                if self.modes[c][j] == "sphere":
                    nT = float(np.linalg.norm(T))
                    d0 = T / nT if nT > 0 else np.array([1.0, 0.0, 0.0])
                    sph.append((d0, _sphere_basis(d0)))
                    x0.append(np.zeros(2))
                    m += 2
                else:
                    sph.append(None)
                    x0.append(T)
                    m += 3
            self.link_off.append(lo)
            self.sphere.append(sph)
            self.size.append(m)
            n += m
        self.f_off = n
        n += len(self.focal_views)
        x0.append(np.zeros(len(self.focal_views)))
        self.n = n
        self.x0 = np.concatenate([np.asarray(v, float).reshape(-1) for v in x0]) if x0 else np.zeros(0)
        self.chain_of = {}
        for c, ch in enumerate(chains):
            for j, k in enumerate(ch):
                self.chain_of[k] = (c, j)
        self.rot_cars = [k for ch in chains for k in ch] if rot_free else []
        self.rot_idx = np.array([self.off[c] + 3 + 3 * j + i for c, ch in enumerate(chains) for j in range(len(ch))
                                 for i in range(3)], dtype=int) if rot_free else np.zeros(0, int)
        # every link of every chain, in chain order, as arrays (unpack works on all links at once)
        links = [(c, j) for c, ch in enumerate(chains) for j in range(len(ch) - 1)]
        self._link_a = np.array([chains[c][j] for c, j in links], dtype=int)  # front carriage of the link
        self._link_b = np.array([chains[c][j + 1] for c, j in links], dtype=int)  # rear carriage
        self._c_rear = np.array([cars[chains[c][j]].c_rear for c, j in links], dtype=float).reshape(-1, 3)
        self._c_front = np.array([cars[chains[c][j + 1]].c_front for c, j in links], dtype=float).reshape(-1, 3)
        self._link_col = [self.off[c] + self.link_off[c][j] for c, j in links]  # first column of its parameters
        is_sph = np.array([self.sphere[c][j] is not None for c, j in links], dtype=bool)
        self._free = np.nonzero(~is_sph)[0]
        self._free_cols = np.array([self._link_col[i] for i in self._free], dtype=int).reshape(-1, 1) + np.arange(3)
        self._sph = np.nonzero(is_sph)[0]
        self._sph_cols = np.array([self._link_col[i] for i in self._sph], dtype=int).reshape(-1, 1) + np.arange(2)
        self._sph_d0 = np.array([self.sphere[c][j][0] for c, j in (links[i] for i in self._sph)]).reshape(-1, 3)
        self._sph_B = np.array([self.sphere[c][j][1] for c, j in (links[i] for i in self._sph)]).reshape(-1, 3, 2)
        self._sph_s = np.array([slacks[c][j] for c, j in (links[i] for i in self._sph)], dtype=float)
        self.link_sph = is_sph
        self.link_w = np.where(is_sph, 2, 3)  # parameters per link
        # coupler prior rows: T * prior_px / sigma_T, sigma_T = slack / sqrt 5
        self.link_scale = np.array([self.prior_px * SQRT5 / slacks[c][j] for c, j in links], dtype=float)
        self._chain_links = np.cumsum([0] + [len(ch) - 1 for ch in chains])  # chain c: links [c_, c_ + 1)

    def unpack(self, x: np.ndarray, with_derivs: bool | str = True):
        """Poses, focal, offsets at ``x``. ``with_derivs``: True also the dense chain derivatives ``D`` (d t / d
        chain params, O(N^2) for a long chain) and the left Jacobians; ``"local"`` only the left Jacobians
        (what the structured solver needs); False neither. The left Jacobians are an (N, 3, 3) array (the
        identity for a carriage whose rotation is held), None without derivatives. Sets, per link,
        ``self.GT[c][j] = (column, d T / d link params (3, 3 or 2))``, and for all links in chain order ``self.T``
        (L, 3) and ``self.GT_pad`` (L, 3, 3) (a sphere link's third column zero)."""
        R = self.R_ref.copy()
        t = np.zeros((len(self.cars), 3))
        D: dict[int, np.ndarray] = {}  # car -> (3, size_c): d t / d chain params
        Jl = np.tile(_EYE3, (len(self.cars), 1, 1)) if with_derivs else None
        if self.rot_free and self.rot_cars:  # all rotations at once
            dl = x[self.rot_idx].reshape(-1, 3)
            R[self.rot_cars] = exp_so3(dl) @ self.R_ref[self.rot_cars]
            if with_derivs:
                Jl[self.rot_cars] = left_jacobian_so3(dl)
        nl = len(self._link_a)
        T = np.empty((nl, 3))
        GT: list[np.ndarray] = [_EYE3] * nl
        GT_pad = np.zeros((nl, 3, 3))
        GT_pad[self._free] = _EYE3
        T[self._free] = x[self._free_cols]
        if len(self._sph):
            # exponential chart of the sphere at d0 (covers every direction): T = s (cos|v| d0 + sinc|v| v), v = B a
            d0, B, s = self._sph_d0, self._sph_B, self._sph_s
            v = np.einsum("nij,nj->ni", B, x[self._sph_cols])
            th = np.linalg.norm(v, axis=1)
            small = th < 1e-6
            ths = np.where(small, 1.0, th)
            c1 = np.where(small, 1.0 - th * th / 6.0, np.sin(ths) / ths)
            c2 = np.where(small, -1.0 / 3.0 + th * th / 30.0, (ths * np.cos(ths) - np.sin(ths)) / ths**3)
            T[self._sph] = s[:, None] * (np.cos(th)[:, None] * d0 + c1[:, None] * v)
            G = (c1[:, None, None] * (_EYE3 - d0[:, :, None] * v[:, None, :]) + c2[:, None, None] * v[:, :, None]
                 * v[:, None, :]) @ B * s[:, None, None]
            GT_pad[self._sph, :, :2] = G
            for i, g in zip(self._sph, G):
                GT[i] = g
        self.T, self.GT_pad = T, GT_pad
        ra = np.einsum("nij,nj->ni", R[self._link_a], self._c_rear)
        rb = np.einsum("nij,nj->ni", R[self._link_b], self._c_front)
        step = ra + T - rb  # t_b - t_a of every link
        T_links: list[list[np.ndarray]] = []
        self.GT = []
        for c, ch in enumerate(self.chains):
            o = self.off[c]
            l0, l1 = self._chain_links[c], self._chain_links[c + 1]
            t[ch[0]] = x[o:o + 3]
            if l1 > l0:
                t[ch[1:]] = x[o:o + 3] + np.cumsum(step[l0:l1], axis=0)
            T_links.append(list(T[l0:l1]))
            self.GT.append([(self._link_col[i], GT[i]) for i in range(l0, l1)])
            if with_derivs is True:
                Dk = np.zeros((3, self.size[c]))
                Dk[:, 0:3] = _EYE3
                D[ch[0]] = Dk
                for j in range(len(ch) - 1):
                    i = l0 + j
                    lo = self.link_off[c][j]
                    Dk = Dk.copy()
                    Dk[:, lo:lo + GT[i].shape[1]] += GT[i]
                    if self.rot_free:
                        ja = 3 + 3 * j
                        Dk[:, ja:ja + 3] += -skew(ra[i]) @ Jl[ch[j]]
                        Dk[:, ja + 3:ja + 6] += skew(rb[i]) @ Jl[ch[j + 1]]
                    D[ch[j + 1]] = Dk
        f = self.f_ref.copy()
        for i, grp in enumerate(self.focal_views):
            for v_ in grp:
                f[v_] = self.f_ref[v_] * math.exp(x[self.f_off + i])
        return R, t, f, D, Jl, T_links


# ----------------------------------------------------------------------------------------------------------
# Residuals
# ----------------------------------------------------------------------------------------------------------
def carriage_weights(cars: Sequence[_Car], active: Sequence[int], weighting: str = "per_carriage") -> dict[int, float]:
    """Row weight of each carriage of ``active`` (see :class:`SolveOptions.weighting`): ``"per_carriage"``
    ``sqrt(n_mean / n_i)`` (n_i its measured observation rows, predictions not counted; n_mean their mean over
    ``active``: 1 for all when the counts are equal), ``"per_point"`` 1 (maximum likelihood for independent
    pixel noise)."""
    if weighting == "per_point":
        return {k: 1.0 for k in active}
    if weighting != "per_carriage":
        raise SettingsError(f"solve options: weighting = {weighting!r}: must be one of {', '.join(_WEIGHTINGS)}")

    def measured(c: _Car) -> int:
        if c.derived is None or len(c.derived) != len(c.P):
            return len(c.P)
        return max(int(np.count_nonzero(~c.derived)), 1)

    counts = {k: measured(cars[k]) for k in active}
    nmean = float(np.mean(list(counts.values()))) if counts else 1.0
    return {k: math.sqrt(nmean / max(counts[k], 1)) for k in active}


class _Problem:
    def __init__(self, cars: list[_Car], active: list[int], views: Sequence[View], weights: dict[int, float]):
        self.cars, self.views = cars, views
        self.active = active
        rows_car, rows_view, P, uv, w, wv, meas, grp = [], [], [], [], [], [], [], []
        codes: dict[tuple, int] = {}
        for k in active:
            c = cars[k]
            rows_car.append(np.full(len(c.P), k))
            rows_view.append(c.views)
            P.append(c.P)
            uv.append(c.uv)
            sc = c.scale if c.scale is not None and len(c.scale) == len(c.P) else np.ones(len(c.P))
            # a point with its own sigma s_j is whitened by pixel_sigma / s_j; the carriage's normalisation
            # weight multiplies it (and is what the weighted rows' noise variance keeps: see .uncertainty)
            w.append(weights[k] / sc)
            wv.append(np.full(len(c.P), weights[k]))
            der = c.derived if c.derived is not None and len(c.derived) == len(c.P) else np.zeros(len(c.P), bool)
            meas.append(~der)
            gs = c.groups if c.groups is not None and len(c.groups) == len(c.P) else [None] * len(c.P)
            grp.append(np.array([-1 if g is None else codes.setdefault((k, g), len(codes)) for g in gs], dtype=int))
        self.car = np.concatenate(rows_car) if rows_car else np.zeros(0, int)
        self.view = np.concatenate(rows_view) if rows_view else np.zeros(0, int)
        self.P = np.vstack(P) if P else np.zeros((0, 3))
        self.uv = np.vstack(uv) if uv else np.zeros((0, 2))
        self.w = np.concatenate(w) if w else np.zeros(0)  # row weights (normalisation x whitening)
        self.w_noise = np.concatenate(wv) if wv else np.zeros(0)  # sd of a weighted row / pixel sigma
        self.measured = np.concatenate(meas) if meas else np.zeros(0, bool)  # rows that carry information
        self.group = np.concatenate(grp) if grp else np.zeros(0, int)  # shared-misfit group per row, -1: none
        self.by_view = [np.nonzero(self.view == v)[0] for v in range(len(views))]
        self.by_car = {k: np.nonzero(self.car == k)[0] for k in active}

    def with_predictions_scaled(self, factor: float, cars: Sequence[int] | None = None) -> "_Problem":
        """A copy whose prediction rows (``~measured``), of the carriages ``cars`` (None: all), have their sigma
        multiplied by ``factor``."""
        out = copy.copy(self)
        rows = ~self.measured if cars is None else ~self.measured & np.isin(self.car, list(cars))
        out.w = np.where(rows, self.w / float(factor), self.w)
        return out

    def intrinsics(self, v: int, f: float) -> CameraIntrinsics:
        return self.views[v].intrinsics.with_focal(f)

    def project(self, R: np.ndarray, t: np.ndarray, f: np.ndarray, jac: bool = False):
        M = len(self.P)
        uv = np.empty((M, 2))
        JX = np.empty((M, 2, 3)) if jac else None
        Jf = np.empty((M, 2)) if jac else None
        Xw = np.einsum("nij,nj->ni", R[self.car], self.P) + t[self.car]
        for v, idx in enumerate(self.by_view):
            if len(idx) == 0:
                continue
            intr = self.intrinsics(v, f[v])
            u_, jx, jf = project_world_points_with_jacobians(Xw[idx], self.views[v].cam_from_world, intr, ("f",))
            uv[idx] = u_
            if jac:
                JX[idx] = jx
                ratio = intr.fy / intr.fx
                Jf[idx] = jf[:, :, 0] * np.array([1.0, ratio])
        return uv, Xw, JX, Jf


class _Contact:
    """Soft terrain contact per carriage: residual ``scale * min_s (z_s - h(xy_s))`` (scale = px_sigma / sigma_z).

    ``samples``: carriage index -> its surface samples (m, 3), carriage frame, metres; ``self.cars`` keeps their
    order, which is the order of the batched :meth:`clearances` and of the contact rows."""

    def __init__(self, terrain: Any, samples: dict[int, np.ndarray], scale: float, step: float = 0.05):
        self.terrain, self.samples, self.scale, self.step = terrain, samples, scale, step
        self.cars = list(samples)
        self._row = {k: i for i, k in enumerate(self.cars)}
        m = max((len(S) for S in samples.values()), default=0)
        self._S = np.zeros((len(self.cars), m, 3))  # padded to the longest set; _valid marks the real samples
        self._valid = np.zeros((len(self.cars), m), dtype=bool)
        for i, k in enumerate(self.cars):
            S = np.asarray(samples[k], dtype=float).reshape(-1, 3)
            self._S[i, :len(S)] = S
            self._valid[i, :len(S)] = True

    def clearances(self, R_c: np.ndarray, t_c: np.ndarray, cars: Sequence[int] | None = None):
        """The clearance of several carriages at once: poses ``R_c`` (n, 3, 3), ``t_c`` (n, 3) of the carriages
        ``cars`` (consist indices; None: ``self.cars``). Returns the clearance (n,) (m; NaN for a carriage off
        the terrain), its lowest sample in the scene X (n, 3) and that sample rotated, R s (n, 3)."""
        rows = slice(None) if cars is None else np.array([self._row[k] for k in cars], dtype=int)
        S, valid = self._S[rows], self._valid[rows]
        X = S @ np.swapaxes(R_c, 1, 2) + t_c[:, None, :]  # (n, m, 3)
        if valid.all():
            h = np.asarray(self.terrain.height_at(X[:, :, :2].reshape(-1, 2)), dtype=float).reshape(valid.shape)
        else:
            h = np.full(valid.shape, np.nan)
            h[valid] = np.asarray(self.terrain.height_at(X[valid][:, :2]), dtype=float)
        dz = X[:, :, 2] - h
        dz = np.where(np.isfinite(dz), dz, np.inf)
        n = np.arange(len(S))
        i = np.argmin(dz, axis=1) if S.shape[1] else np.zeros(len(S), dtype=int)
        d = dz[n, i] if S.shape[1] else np.full(len(S), np.inf)
        d = np.where(np.isfinite(d), d, np.nan)
        return d, X[n, i], np.einsum("nij,nj->ni", R_c, S[n, i])

    def clearance(self, R: np.ndarray, t: np.ndarray, k: int):
        """Carriage ``k`` (scene poses ``R`` (N, 3, 3), ``t`` (N, 3)): (clearance m, lowest sample X (3,), R s
        (3,)), or None off the terrain."""
        d, X, q = self.clearances(R[[k]], t[[k]], [k])
        return None if not np.isfinite(d[0]) else (float(d[0]), X[0], q[0])

    def gradients(self, xy: np.ndarray) -> np.ndarray:
        """Terrain slopes (n, 2) (dh/dx, dh/dy; 0 where undefined) at ``xy`` (n, 2), central differences."""
        e = self.step
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        q = np.repeat(xy, 4, axis=0) + np.tile([[e, 0.0], [-e, 0.0], [0.0, e], [0.0, -e]], (len(xy), 1))
        h = np.asarray(self.terrain.height_at(q), dtype=float).reshape(-1, 4)
        g = np.column_stack([(h[:, 0] - h[:, 1]) / (2 * e), (h[:, 2] - h[:, 3]) / (2 * e)])
        return np.where(np.isfinite(g), g, 0.0)

    def rows(self, R_c: np.ndarray, t_c: np.ndarray):
        """Contact residuals and their derivatives for every carriage (poses as :meth:`clearances`): residual
        (n,) (0 off the terrain), ``a`` (n, 3) d residual / d X (0 off the terrain), R s (n, 3), on-terrain mask."""
        d, X, q = self.clearances(R_c, t_c)
        on = np.isfinite(d)
        gh = self.gradients(X[:, :2])
        a = np.column_stack([-gh, np.ones(len(d))]) * self.scale
        a[~on] = 0.0
        return np.where(on, self.scale * np.nan_to_num(d), 0.0), a, q, on


def focal_groups(views: Sequence[View], used: Sequence[int]) -> list[list[int]]:
    """Views (indices, among ``used``) that share one focal parameter: those with identical intrinsics, i.e.
    photos from one camera (the source photos of a panorama, a multi-view set of one camera)."""
    groups: list[list[int]] = []
    keys: list[CameraIntrinsics] = []
    for v in used:
        intr = views[v].intrinsics
        for g, key in zip(groups, keys):
            if intr == key:
                g.append(v)
                break
        else:
            groups.append([v])
            keys.append(intr)
    return groups


def _group_rows(prob: "_Problem", group: Sequence[int]) -> np.ndarray:
    return np.concatenate([prob.by_view[v] for v in group]) if len(group) > 1 else prob.by_view[group[0]]


def _residuals_and_jac(prob: _Problem, lay: _Layout, x: np.ndarray, contact: _Contact | None, jac: bool):
    R, t, f, D, Jl, T_links = lay.unpack(x, with_derivs=True)
    uv, Xw, JX, Jf = prob.project(R, t, f, jac=jac)
    w = prob.w
    r = ((uv - prob.uv) * w[:, None]).reshape(-1)
    cars_c = contact.cars if contact is not None else []
    rc = np.zeros(len(cars_c))
    if cars_c:
        rc, a_c, q_c, on_c = contact.rows(R[cars_c], t[cars_c])
    T_all = [(c, j, T) for c, Tl in enumerate(T_links) for j, T in enumerate(Tl)]
    rp = np.concatenate([T * (lay.prior_px * SQRT5 / lay.slacks[c][j]) for c, j, T in T_all]) if T_all else np.zeros(0)
    res = np.concatenate([r, rc, rp])
    if not jac:
        return res, None
    M = len(prob.P)
    J = np.zeros((2 * M + len(cars_c) + len(rp), lay.n))
    row0 = 2 * M + len(cars_c)
    for i, (c, j, T) in enumerate(T_all):
        col, GT = lay.GT[c][j]
        J[row0 + 3 * i:row0 + 3 * i + 3, col:col + GT.shape[1]] = GT * (lay.prior_px * SQRT5 / lay.slacks[c][j])
    JXw = JX * w[:, None, None]
    for k in prob.active:
        c, j = lay.chain_of[k]
        o, m = lay.off[c], lay.size[c]
        idx = prob.by_car[k]
        rows = np.concatenate([2 * idx, 2 * idx + 1])
        Jk = np.concatenate([JXw[idx, 0, :], JXw[idx, 1, :]], axis=0)  # (2n, 3)
        J[rows, o:o + m] = Jk @ D[k]
        if lay.rot_free:
            q = prob.P[idx] @ R[k].T  # R p
            Jr = -np.einsum("nab,nbc->nac", JXw[idx], skew(q)) @ Jl[k]  # (n, 2, 3)
            ro = o + 3 + 3 * j
            J[rows, ro:ro + 3] += np.concatenate([Jr[:, 0, :], Jr[:, 1, :]], axis=0)
    for i, grp in enumerate(lay.focal_views):
        idx = _group_rows(prob, grp)
        col = lay.f_off + i
        J[2 * idx, col] = Jf[idx, 0] * w[idx] * f[prob.view[idx]]
        J[2 * idx + 1, col] = Jf[idx, 1] * w[idx] * f[prob.view[idx]]
    for i, k in enumerate(cars_c):
        if not on_c[i]:
            continue
        a, q = a_c[i], q_c[i]  # d residual / d X, R s
        c, j = lay.chain_of[k]
        o, m = lay.off[c], lay.size[c]
        row = 2 * M + i
        J[row, o:o + m] = a @ D[k]
        if lay.rot_free:
            ro = o + 3 + 3 * j
            J[row, ro:ro + 3] += -(a @ skew(q)) @ Jl[k]
    return res, J


_TRACE: list | None = None  # debugging: per evaluation of :func:`_lm_struct` (nfev, cost, new cost, predicted, lambda, |dx|, scaled grad)


def _run_lsq(prob: _Problem, lay: _Layout, contact: _Contact | None, options: SolveOptions):
    return _lm_struct(prob, lay, contact, options)


# ----------------------------------------------------------------------------------------------------------
# Structured (sparse) trust-region solver
# ----------------------------------------------------------------------------------------------------------
class _ZLayout:
    """Index map of the *expanded* variables ``z`` of a chained step: per carriage its rotation increment (3, when
    free) and its translation increment (3), per link its offset parameters (3 free / 2 on the sphere), then the
    log-focal of each estimated view. The chain parameters ``x`` of :class:`_Layout` are a subset of ``z`` (the
    first carriage's translation, the rotations, the links, the focal); the other translations are tied to
    them by the linearised coupling equations ``C z = 0`` (3 per link). In ``z`` the Gauss-Newton matrix is
    block diagonal (a carriage's pixels see only its own pose) plus the focal's rows, and ``C`` couples only
    neighbours: the LM/trust-region system is a sparse KKT system, O(N) to factor for a chain of N carriages."""

    def __init__(self, lay: _Layout):
        self.nr = 3 if lay.rot_free else 0
        self.bs = self.nr + 3
        self.zc: dict[int, int] = {}
        n = 0
        for ch in lay.chains:
            for k in ch:
                self.zc[k] = n
                n += self.bs
        self.zl: list[list[tuple[int, int]]] = []
        for c, ch in enumerate(lay.chains):
            row = []
            for j in range(len(ch) - 1):
                w = 2 if lay.sphere[c][j] is not None else 3
                row.append((n, w))
                n += w
            self.zl.append(row)
        self.zf = n
        self.nf = len(lay.focal_views)
        n += self.nf
        self.nz = n
        xz = np.empty(lay.n, dtype=int)
        for c, ch in enumerate(lay.chains):
            o = lay.off[c]
            xz[o:o + 3] = self.zc[ch[0]] + self.nr + np.arange(3)
            if lay.rot_free:
                for j, k in enumerate(ch):
                    xz[o + 3 + 3 * j:o + 6 + 3 * j] = self.zc[k] + np.arange(3)
            for j in range(len(ch) - 1):
                z0, w = self.zl[c][j]
                lo = o + lay.link_off[c][j]
                xz[lo:lo + w] = z0 + np.arange(w)
        xz[lay.f_off:lay.f_off + self.nf] = self.zf + np.arange(self.nf)
        self.xz = xz
        self.n_links = sum(len(ch) - 1 for ch in lay.chains)
        # fixed sparsity pattern of Hz and C (values are filled per iteration)
        bs, nf = self.bs, self.nf
        self.cars = [k for ch in lay.chains for k in ch]
        self.chain_end = np.concatenate([np.full(len(ch), sum(len(h) for h in lay.chains[:c + 1]))
                                         for c, ch in enumerate(lay.chains)]).astype(int)
        starts = np.cumsum([0] + [len(ch) for ch in lay.chains])[:-1]
        self.first_pos = starts.astype(int)
        self.is_first = np.zeros(len(self.cars), bool)
        self.is_first[self.first_pos] = True
        self.tfirst_x = np.array([lay.off[c] + i for c in range(len(lay.chains)) for i in range(3)], dtype=int)
        self.rot_x = lay.rot_idx
        self.link_rear_pos = np.array([starts[c] + j + 1 for c, ch in enumerate(lay.chains)
                                       for j in range(len(ch) - 1)], dtype=int)
        z0 = np.array([self.zc[k] for k in self.cars], dtype=int)
        ar = np.arange(bs)
        self.h_rows = [np.repeat(z0[:, None] + ar, bs, axis=1).ravel(), ]
        self.h_cols = [np.tile(z0[:, None] + ar, (1, bs)).ravel()]
        if nf:
            fr = self.zf + np.arange(nf)
            a = np.repeat(z0[:, None] + ar, nf, axis=1).ravel()
            b = np.tile(fr, len(z0) * bs)
            self.h_rows += [a, b, np.repeat(fr, nf)]
            self.h_cols += [b, a, np.tile(fr, nf)]
        self.link_list = [(c, j) for c, ch in enumerate(lay.chains) for j in range(len(ch) - 1)]
        for c, j in self.link_list:
            l0, w = self.zl[c][j]
            self.h_rows.append(np.repeat(l0 + np.arange(w), w))
            self.h_cols.append(np.tile(l0 + np.arange(w), w))
        self.h_rows = np.concatenate(self.h_rows)
        self.h_cols = np.concatenate(self.h_cols)
        crow, ccol = [], []
        nr = self.nr
        for li, (c, j) in enumerate(self.link_list):
            ka, kb = lay.chains[c][j], lay.chains[c][j + 1]
            l0, w = self.zl[c][j]
            r3 = 3 * li + np.arange(3)
            cols = [self.zc[kb] + nr + np.arange(3), self.zc[ka] + nr + np.arange(3), l0 + np.arange(w)]
            if lay.rot_free:
                cols += [self.zc[ka] + np.arange(3), self.zc[kb] + np.arange(3)]
            for cc in cols:
                crow.append(np.repeat(r3, len(cc)))
                ccol.append(np.tile(cc, 3))
        self.c_rows = np.concatenate(crow) if crow else np.zeros(0, int)
        self.c_cols = np.concatenate(ccol) if ccol else np.zeros(0, int)
        # per link (chain order): its parameters' indices in x and in z, padded to 3 (link_mask: the real ones)
        self.link_mask = np.arange(3) < lay.link_w[:, None]  # (L, 3)
        self.link_mask2 = self.link_mask[:, :, None] & self.link_mask[:, None, :]  # (L, 3, 3)
        self.link_x = np.array(lay._link_col, dtype=int).reshape(-1, 1) + np.arange(3)
        self.link_z = np.array([self.zl[c][j][0] for c, j in self.link_list], dtype=int).reshape(-1, 1) + np.arange(3)
        # the C entries of a link, in the order of c_rows / c_cols: I, -I, -GT (3 x w), then -A, -B (rotations)
        nblk = 5 if lay.rot_free else 3
        self.c_mask = np.ones((self.n_links, nblk, 9), dtype=bool)
        self.c_mask[:, 2, :] = np.repeat(self.link_mask, 3, axis=0).reshape(-1, 9)
        self.car_pos = np.full(len(lay.cars), -1, dtype=int)  # consist index -> position in self.cars
        self.car_pos[self.cars] = np.arange(len(self.cars))
        # the KKT matrix [[Hz + diag(damping), C^T], [C, 0]]: its entries (Hz, C, C^T, the diagonal) in one list
        nz, nk = self.nz, self.nz + 3 * self.n_links
        self.nk = nk
        k_rows = np.concatenate([self.h_rows, self.c_rows + nz, self.c_cols, np.arange(nz)])
        k_cols = np.concatenate([self.h_cols, self.c_cols, self.c_rows + nz, np.arange(nz)])
        self.dense = nk <= DENSE_KKT_MAX
        if self.dense:
            self.k_flat = k_rows * nk + k_cols
        else:  # compressed-column structure, computed once: each entry's slot in the CSC data (duplicates summed)
            uniq, self.k_slot = np.unique(k_cols * nk + k_rows, return_inverse=True)
            self.k_indices = (uniq % nk).astype(np.int32)
            self.k_indptr = np.searchsorted(uniq // nk, np.arange(nk + 1)).astype(np.int32)

    def kkt(self, h_vals: np.ndarray, c_vals: np.ndarray, damping: np.ndarray) -> np.ndarray | sp.csc_matrix:
        """The KKT matrix (nk, nk) ``[[Hz + diag(damping), C^T], [C, 0]]`` from the values of Hz and C on their
        patterns (:func:`_struct_system`) and the damping (nz,): dense when small (``self.dense``), else CSC."""
        vals = np.concatenate([h_vals, c_vals, c_vals, damping])
        nk = self.nk
        if self.dense:
            return np.bincount(self.k_flat, weights=vals, minlength=nk * nk).reshape(nk, nk)
        data = np.bincount(self.k_slot, weights=vals, minlength=len(self.k_indices))
        return sp.csc_matrix((data, self.k_indices, self.k_indptr), shape=(nk, nk))


def _struct_eval(prob: _Problem, lay: _Layout, zl: _ZLayout, x: np.ndarray, contact: _Contact | None, loss_fn):
    """Residuals, cost and the Gauss-Newton blocks in ``z`` (see :class:`_ZLayout`) at ``x``; a robust loss
    enters as scipy's ``least_squares`` does (rows rescaled by sqrt(rho' + 2 rho'' r^2), residuals by
    rho' / that)."""
    R, t, f, _, Jl, T_links = lay.unpack(x, with_derivs="local")
    uv, Xw, JX, Jf = prob.project(R, t, f, jac=True)
    w = prob.w
    M = len(prob.P)
    rpix = ((uv - prob.uv) * w[:, None]).reshape(-1)
    JXw = JX * w[:, None, None]
    if lay.rot_free:
        q = Xw - t[prob.car]
        Jr = -np.einsum("nab,nbc,ncd->nad", JXw, skew(q), Jl[prob.car])
        Jpt = np.concatenate([Jr, JXw], axis=2)
    else:
        Jpt = JXw
    nf = zl.nf
    Jfp = np.zeros((M, 2, nf))
    for i, grp in enumerate(lay.focal_views):
        idx = _group_rows(prob, grp)
        Jfp[idx, :, i] = Jf[idx] * (w[idx] * f[prob.view[idx]])[:, None]
    cars_c = contact.cars if contact is not None else []
    rc = np.zeros(len(cars_c))
    Jc = np.zeros((len(cars_c), zl.bs))
    if cars_c:
        rc, a, qk, _ = contact.rows(R[cars_c], t[cars_c])
        Jc[:, zl.nr:] = a
        if lay.rot_free:  # -(a x-matrix(R s)) J_l, i.e. (R s x a)^T J_l
            Jc[:, :3] = np.einsum("ni,nij->nj", np.cross(qk, a), Jl[cars_c])
    s_l = lay.link_scale
    rp = (lay.T * s_l[:, None]).reshape(-1)
    r = np.concatenate([rpix, rc, rp])
    if loss_fn is None:
        cost = 0.5 * float(r @ r)
        sc = None
    else:
        rho = loss_fn(r)
        cost = 0.5 * float(np.sum(rho[0]))
        js = rho[1] + 2 * rho[2] * r**2
        js = np.sqrt(np.maximum(js, np.finfo(float).eps))
        r = r * rho[1] / js
        sc = js
    rpm = r[:2 * M].reshape(M, 2)
    rcm = r[2 * M:2 * M + len(cars_c)]
    rpr = r[2 * M + len(cars_c):]
    if sc is not None:
        sp_ = sc[:2 * M].reshape(M, 2)
        Jpt = Jpt * sp_[:, :, None]
        Jfp = Jfp * sp_[:, :, None]
        Jc = Jc * sc[2 * M:2 * M + len(cars_c), None]
        scp = sc[2 * M + len(cars_c):]
    ncar = len(zl.cars)
    cpos = zl.car_pos[prob.car]
    Hcar = np.zeros((ncar, zl.bs, zl.bs))
    gcar = np.zeros((ncar, zl.bs))
    np.add.at(Hcar, cpos, np.einsum("nai,naj->nij", Jpt, Jpt))
    np.add.at(gcar, cpos, np.einsum("nai,na->ni", Jpt, rpm))
    Hcf = np.zeros((ncar, zl.bs, nf))
    if nf:
        np.add.at(Hcf, cpos, np.einsum("nai,naj->nij", Jpt, Jfp))
    Hff = np.einsum("nai,naj->ij", Jfp, Jfp)
    gf = np.einsum("nai,na->i", Jfp, rpm)
    if cars_c:
        kpos = zl.car_pos[cars_c]
        np.add.at(Hcar, kpos, Jc[:, :, None] * Jc[:, None, :])
        np.add.at(gcar, kpos, Jc * rcm[:, None])
    # the coupler prior rows, all links at once (padded to 3 parameters, see _Layout.GT_pad)
    Jp = lay.GT_pad * s_l[:, None, None]  # (L, 3, 3): d rows / d link params
    rpr3 = rpr.reshape(-1, 3)
    gT = rpr3 * s_l[:, None]  # d cost / d T of each link's prior rows
    if sc is not None:
        scp3 = scp.reshape(-1, 3)
        Jp = Jp * scp3[:, :, None]
        gT = gT * scp3
    Hl = np.einsum("nji,njk->nik", Jp, Jp)
    gl = np.einsum("nji,nj->ni", Jp, rpr3)
    return {"x": x, "cost": cost, "R": R, "Jl": Jl, "Hcar": Hcar, "gcar": gcar, "Hcf": Hcf, "Hff": Hff, "gf": gf,
            "Hl": Hl, "gl": gl, "T": lay.T, "gTp": gT}


def _struct_chain_grad_diag(lay: _Layout, zl: _ZLayout, E: dict, cars: list[_Car]):
    """Gradient (n,) and the diagonal (n,) of the Gauss-Newton matrix in the chain parameters ``x`` (exact, by
    suffix sums along each chain: a link or rotation moves every carriage behind it), the coupling blocks
    ``(A, B)`` (each (ncar, 3, 3) in the order of ``zl.cars``: A = d(R c_rear)/d rot, B = -d(R c_front)/d rot;
    None with rotations held) and the link blocks (L, 3, 3) of the Gauss-Newton matrix, a sphere link's with
    the sphere's curvature added (padded as ``_Layout.GT_pad``)."""
    g = np.zeros(lay.n)
    d = np.zeros(lay.n)
    nr = zl.nr
    H, gc = E["Hcar"], E["gcar"]
    n = len(zl.cars)
    Htt, gt = H[:, nr:, nr:], gc[:, nr:]
    # suffix sums within each chain: S[i] = sum over the carriages from i to the end of its chain
    Sg = np.cumsum(Htt[::-1], axis=0)[::-1]
    Gg = np.cumsum(gt[::-1], axis=0)[::-1]
    Sg = np.concatenate([Sg, np.zeros((1, 3, 3))])
    Gg = np.concatenate([Gg, np.zeros((1, 3))])
    end = zl.chain_end  # per carriage: index (in zl.cars) one past its chain's last carriage
    S = Sg[:n] - Sg[end]
    G = Gg[:n] - Gg[end]
    nxt = np.minimum(np.arange(n) + 1, n)
    last = (np.arange(n) + 1) == end
    Sn = np.where(last[:, None, None], 0.0, Sg[nxt] - Sg[end])
    Gn = np.where(last[:, None], 0.0, Gg[nxt] - Gg[end])
    fi = zl.first_pos
    g[zl.tfirst_x] = G[fi].ravel()
    d[zl.tfirst_x] = np.diagonal(S[fi], axis1=1, axis2=2).ravel()
    AB = None
    if lay.rot_free:
        Rk = E["R"][zl.cars]
        JL = E["Jl"][zl.cars]
        cr = np.array([cars[k].c_rear for k in zl.cars])
        cf = np.array([cars[k].c_front for k in zl.cars])
        A = -skew(np.einsum("nij,nj->ni", Rk, cr)) @ JL
        B = skew(np.einsum("nij,nj->ni", Rk, cf)) @ JL
        F = np.where(zl.is_first[:, None, None], 0.0, B)
        Ft = np.swapaxes(F, 1, 2)
        Ho = H[:, :3, :3] + Ft @ H[:, 3:, :3] + H[:, :3, 3:] @ F + Ft @ Htt @ F
        go = gc[:, :3] + np.einsum("nji,nj->ni", F, gt)
        cc = F + A
        cct = np.swapaxes(cc, 1, 2)
        Ho = Ho + cct @ Sn @ cc
        go = go + np.einsum("nji,nj->ni", cc, Gn)
        g[zl.rot_x] = go.ravel()
        d[zl.rot_x] = np.diagonal(Ho, axis1=1, axis2=2).ravel()
        AB = (A, B)
    Hl = E["Hl"]
    if zl.n_links:
        ib = zl.link_rear_pos
        GT = lay.GT_pad
        if lay.link_sph.any():
            # the sphere's curvature (the constraint's term of the Lagrangian's Hessian): along any direction e of
            # the chart, d2T = -(|GT e|^2 / s) u normal to the sphere, so the cost's second derivative gains
            # mu GT^T GT, mu = -(dcost/dT . u) / s >= 0 while the constraint binds. Without it Gauss-Newton
            # converges only linearly on an offset held at the slack by a large multiplier
            gT = G[ib] + E["gTp"]
            T = E["T"]
            mu = -np.einsum("ni,ni->n", gT, T) / np.einsum("ni,ni->n", T, T)
            mu = np.where(lay.link_sph & (mu > 0.0), mu, 0.0)
            Hl = Hl + mu[:, None, None] * np.einsum("nji,njk->nik", GT, GT)
        m = zl.link_mask
        g[zl.link_x[m]] = (np.einsum("nji,nj->ni", GT, G[ib]) + E["gl"])[m]
        d[zl.link_x[m]] = (np.einsum("nji,njk,nki->ni", GT, S[ib], GT) + np.diagonal(Hl, axis1=1, axis2=2))[m]
    nf = zl.nf
    if nf:
        g[lay.f_off:lay.f_off + nf] = E["gf"]
        d[lay.f_off:lay.f_off + nf] = np.diag(E["Hff"])
    return g, d, AB, Hl


def _struct_system(lay: _Layout, zl: _ZLayout, E: dict, AB, Hl: np.ndarray):
    """The values of the Gauss-Newton matrix Hz (in z) and of the coupling constraint matrix C on their fixed
    patterns (``zl.h_rows, zl.h_cols`` and ``zl.c_rows, zl.c_cols``, see :meth:`_ZLayout.kkt`), and the
    gradient gz (nz,). ``AB``: the coupling blocks (A, B) (n, 3, 3) per carriage of ``zl.cars`` (rotations
    free); ``Hl`` (L, 3, 3): the link blocks (with the sphere's curvature, :func:`_struct_chain_grad_diag`)."""
    vals = [E["Hcar"].ravel()]
    gz = np.zeros(zl.nz)
    z0 = np.array([zl.zc[k] for k in zl.cars], dtype=int)
    gz[(z0[:, None] + np.arange(zl.bs)).ravel()] = E["gcar"].ravel()
    if zl.nf:
        Hcf = E["Hcf"].ravel()
        vals += [Hcf, Hcf, E["Hff"].ravel()]
        gz[zl.zf:] = E["gf"]
    if not zl.n_links:
        return np.concatenate(vals), np.zeros(0), gz
    vals.append(Hl[zl.link_mask2])
    gz[zl.link_z[zl.link_mask]] = E["gl"][zl.link_mask]
    nl = zl.n_links
    blocks = [np.broadcast_to(_EYE3.ravel(), (nl, 9)), np.broadcast_to(-_EYE3.ravel(), (nl, 9)),
              -lay.GT_pad.reshape(nl, 9)]
    if lay.rot_free:
        A, B = AB
        ib = zl.link_rear_pos
        blocks += [-A[ib - 1].reshape(nl, 9), -B[ib].reshape(nl, 9)]
    return np.concatenate(vals), np.stack(blocks, axis=1)[zl.c_mask], gz


def _solve_kkt(K: np.ndarray | sp.csc_matrix, rhs: np.ndarray) -> np.ndarray | None:
    """Solve the KKT system ``K`` (from :meth:`_ZLayout.kkt`): dense LU (LAPACK) for a small system, SuperLU
    for a large one. None when it is singular or the solution is not finite."""
    try:
        if isinstance(K, np.ndarray):
            sol = np.linalg.solve(K, rhs)
        else:
            from scipy.sparse.linalg import splu

            sol = splu(K, permc_spec="MMD_AT_PLUS_A").solve(rhs)
    except (RuntimeError, np.linalg.LinAlgError):  # exactly singular
        return None
    return sol if np.all(np.isfinite(sol)) else None


def _lm_struct(prob: _Problem, lay: _Layout, contact: _Contact | None, options: SolveOptions):
    """Levenberg-Marquardt with Marquardt scaling and Nielsen's damping update — a trust-region method in the
    sense of Moré (1978): each step minimises the Gauss-Newton model over the ellipsoid ||diag(d)^1/2 dx|| <=
    Delta, the damping lambda being that radius' multiplier, and the radius grows or shrinks with the ratio of
    actual to predicted reduction. The step is computed in the chain parameters ``x`` (so the coupling
    constraint |T| <= s stays exact, see :class:`_Layout`) but solved through the sparse KKT system of the
    expanded variables ``z`` (:class:`_ZLayout`) with a sparse LU (SuperLU), O(N) per iteration for a chain of
    N carriages instead of the dense O(N^3) normal equations of ``x`` (a small system, up to
    :data:`DENSE_KKT_MAX` unknowns and constraints, is solved dense: the same system, without the sparse
    overhead). ``d`` is the exact diagonal of the Gauss-Newton matrix in ``x``; a link on the sphere adds the
    sphere's curvature to its block (see :func:`_struct_chain_grad_diag`)."""
    if lay.n == 0:
        return lay.x0, 0, "nothing to optimise", True
    zl = _ZLayout(lay)
    tol = options.tolerance
    max_ev = int(options.max_iterations)
    loss_fn = None
    if options.robust_loss != "linear":
        from scipy.optimize._lsq.least_squares import construct_loss_function

        m = 2 * len(prob.P) + (len(contact.cars) if contact is not None else 0) + 3 * zl.n_links
        loss_fn = construct_loss_function(m, options.robust_loss, options.loss_scale_px)
    x = lay.x0.copy()
    # the focal is kept inside the field-of-view range of the sweep (guards against runaway along the
    # depth / focal ambiguity): log(f / f_ref) within [log f(hfov_hi), log f(hfov_lo)]
    flo = np.zeros(zl.nf)
    fhi = np.zeros(zl.nf)
    for i, grp in enumerate(lay.focal_views):
        v = grp[0]
        half_w = 0.5 * prob.views[v].intrinsics.width
        lo_deg, hi_deg = options.hfov_range_deg
        flo[i] = math.log(half_w / math.tan(math.radians(hi_deg) / 2) / lay.f_ref[v])
        fhi[i] = math.log(half_w / math.tan(math.radians(lo_deg) / 2) / lay.f_ref[v])
    if zl.nf:
        x[lay.f_off:] = np.clip(x[lay.f_off:], flo, fhi)
    E = _struct_eval(prob, lay, zl, x, contact, loss_fn)
    nfev = 1
    lam, nu = 1e-3, 2.0
    nc = 3 * zl.n_links
    while True:
        g, d, AB, Hl = _struct_chain_grad_diag(lay, zl, E, prob.cars)
        dmax = float(np.max(d)) if len(d) else 1.0
        d = np.maximum(d, 1e-12 * max(1.0, dmax))
        cost = E["cost"]
        if float(np.max(np.abs(g) / np.sqrt(d))) < tol * max(1.0, math.sqrt(2 * cost)):
            return x, nfev, "gradient small", True
        hv, cv, gz = _struct_system(lay, zl, E, AB, Hl)
        K0 = zl.kkt(hv, cv, np.zeros(zl.nz))
        dz = np.zeros(zl.nz)
        dz[zl.xz] = d
        rhs = np.concatenate([-gz, np.zeros(nc)])
        while True:
            sol = _solve_kkt(zl.kkt(hv, cv, lam * dz), rhs)
            if sol is None:
                lam *= 10.0
                if lam > 1e16:
                    return x, nfev, "trust region collapsed", False
                continue
            z = sol[:zl.nz]
            dx = z[zl.xz]
            pred = -float(gz @ z) - 0.5 * float(z @ (K0 @ np.concatenate([z, np.zeros(nc)]))[:zl.nz])
            if 0.0 <= pred <= tol * cost:
                # the model predicts no reduction worth taking (MINPACK's ftol test on the predicted
                # reduction): a minimum to the tolerance, also at the kink of the contact term, where
                # rejected steps would otherwise shrink the region without end
                return x, nfev, "converged (predicted reduction below tolerance)", True
            xn = x + dx
            if zl.nf and not np.all((xn[lay.f_off:] >= flo) & (xn[lay.f_off:] <= fhi)):
                # the focal would leave the sweep's field-of-view range: a failed step (radius shrinks)
                lam *= nu
                nu *= 2.0
                if lam > 1e16:
                    return x, nfev, "trust region collapsed", False
                continue
            En = _struct_eval(prob, lay, zl, xn, contact, loss_fn)
            nfev += 1
            cn = En["cost"]
            rho = (cost - cn) / pred if pred > 0 else -1.0
            if _TRACE is not None:
                _TRACE.append((nfev, cost, cn, pred, lam, float(np.linalg.norm(dx)), float(np.max(np.abs(g) / np.sqrt(d)))))
            if rho > 0 and np.isfinite(cn):
                small = abs(cost - cn) < tol * cost or float(np.linalg.norm(dx)) < tol * (
                    tol + float(np.linalg.norm(x)))
                x, E = xn, En
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                if small:
                    return x, nfev, "converged (cost / step change below tolerance)", True
                break
            lam *= nu
            nu *= 2.0
            if lam > 1e16:
                return x, nfev, "trust region collapsed", False
            if nfev >= max_ev:
                return x, nfev, "maximum evaluations reached", False
        if nfev >= max_ev:
            return x, nfev, "maximum evaluations reached", False


def _solve_chained(prob: _Problem, cars: list[_Car], chains, slacks, rot_free: bool, focal_views, R, t, f,
                   contact: _Contact | None, options: SolveOptions):
    """Active-set trust-region solve of a chained step: links start free (T itself the parameter); a link whose
    offset leaves the ball is moved onto the sphere |T| = s (2 parameters); a link on the sphere whose cost
    gradient points inwards (multiplier of the wrong sign) is freed again. Every returned offset satisfies
    |T| <= s (to rounding)."""
    modes = [["free"] * (len(ch) - 1) for ch in chains]
    nfev_tot, msgs, ok_all, rounds = 0, [], True, 0
    finalize = False
    for rounds in range(1, 40):
        lay = _Layout(chains, slacks, rot_free, focal_views, cars, R, t, f, modes, options.pixel_sigma_px)
        x, nfev, msg, ok = _run_lsq(prob, lay, contact, options)
        nfev_tot += nfev
        R, t, f, _, _, T_links = lay.unpack(x, with_derivs=False)
        last_ok, last_msg = ok, msg
        changed = False
        for c, ch in enumerate(chains):
            for j in range(len(ch) - 1):
                if modes[c][j] == "free" and np.linalg.norm(T_links[c][j]) > slacks[c][j] * (1 + 1e-12):
                    modes[c][j] = "sphere"
                    changed = True
        if changed:
            continue
        if finalize or rounds >= 12:
            break
        # release links whose constraint is not binding
        lay_free = _Layout(chains, slacks, rot_free, focal_views, cars, R, t, f, None, options.pixel_sigma_px)
        r, J = _residuals_and_jac(prob, lay_free, lay_free.x0, contact, True)
        g = J.T @ r
        for c, ch in enumerate(chains):
            for j in range(len(ch) - 1):
                if modes[c][j] != "sphere":
                    continue
                T = T_links[c][j]
                o = lay_free.off[c] + lay_free.link_off[c][j]
                if float(g[o:o + 3] @ (T / np.linalg.norm(T))) > 1e-9 * max(1.0, float(np.abs(g).max())):
                    modes[c][j] = "free"
                    changed = True
        if not changed:
            break
    n_active = sum(m == "sphere" for ms in modes for m in ms)
    return R, t, f, T_links, nfev_tot, last_msg, last_ok, rounds, n_active


def _pixel_cost(prob: _Problem, R, t, f) -> float:
    uv, *_ = prob.project(R, t, f)
    e = (uv - prob.uv) * prob.w[:, None]
    return float(0.5 * np.sum(e * e))


def _rot_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra @ Rb.T) - 1.0) / 2.0
    return float(np.rad2deg(np.arccos(np.clip(c, -1.0, 1.0))))


_CHI2_6_95 = 12.5916  # 95 % point of the chi-square distribution with 6 degrees of freedom


def _prediction_shift(released: _Problem, R, t, f, R_kept, t_kept, focal_views, chains, slacks, contact,
                      options: SolveOptions, model: dict | None = None) -> dict[int, float]:
    """Per carriage with predicted points: the squared Mahalanobis length of the shift from the fit with the
    predictions released (``R, t, f``: the measured points' fit) to the fit with them kept (``R_kept, t_kept``),
    in the released fit's pose covariance (scene rotation vector, origin). Under the solve's noise model it is
    about chi-square with 6 degrees of freedom or less (the kept fit uses the same measurements); a larger value
    says that the predictions pulled the car where its measured points do not put it."""
    from scipy.spatial.transform import Rotation

    from .uncertainty import solution_model

    if model is None:
        model = solution_model(released, R, t, f, focal_views, chains, slacks, contact, options)
    cov, col = model["cov"], model["col"]
    out = {}
    for k in released.active:
        if released.measured[released.by_car[k]].all():
            continue
        d = np.concatenate([Rotation.from_matrix(R_kept[k] @ R[k].T).as_rotvec(), t_kept[k] - t[k]])
        C = cov[col[k]:col[k] + 6, col[k]:col[k] + 6]
        out[k] = float(d @ np.linalg.pinv(C, rcond=1e-12) @ d) if np.all(np.isfinite(C)) else float("inf")
    return out


def _changes(cars, active, R0, t0, R1, t1) -> list[dict]:
    out = []
    for k in active:
        out.append({"number": cars[k].number, "moved_m": float(np.linalg.norm(t1[k] - t0[k])),
                    "dz_m": float(t1[k][2] - t0[k][2]), "rotated_deg": _rot_angle_deg(R1[k], R0[k])})
    return out


# ----------------------------------------------------------------------------------------------------------
# Start: PnP and the focal sweep
# ----------------------------------------------------------------------------------------------------------
def _pnp(P: np.ndarray, uv: np.ndarray, intr: CameraIntrinsics, cam_from_world: np.ndarray,
         xy: np.ndarray | None = None):
    """world_from_carriage (R, t) from SQPnP on undistorted normalised points; None on failure. Also the
    reprojection sum of squares (px^2). ``xy``: the pixels ``uv`` already undistorted and normalised."""
    import cv2

    if xy is None:
        xy = intr.undistort(intr.normalized_from_pixels(uv))
    try:
        ok, rvec, tvec = cv2.solvePnP(P.astype(np.float64), xy.astype(np.float64).reshape(-1, 1, 2), np.eye(3),
                                      None, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return None
    if not ok:
        return None
    Rcc = cv2.Rodrigues(rvec)[0]
    tcc = tvec.reshape(3)
    Pc = P @ Rcc.T + tcc
    if np.any(Pc[:, 2] <= 0):
        return None
    e = intr.project(Pc) - uv
    sse = float(np.sum(e * e))
    M = np.asarray(cam_from_world, float)
    Rw, tw = M[:3, :3].T, -M[:3, :3].T @ M[:3, 3]
    return Rw @ Rcc, Rw @ tcc + tw, sse


def _focal_grid(width_px: int, hfov_range_deg: tuple[float, float], step_ratio: float) -> np.ndarray:
    """Focals (px) from the widest field of view to the narrowest, log-spaced, neighbours ``step_ratio`` apart."""
    lo, hi = hfov_range_deg
    half_w = 0.5 * width_px
    f_short, f_long = half_w / math.tan(math.radians(hi) / 2.0), half_w / math.tan(math.radians(lo) / 2.0)
    n = max(3, int(math.ceil(math.log(f_long / f_short) / math.log(step_ratio))) + 1)
    return np.geomspace(f_short, f_long, n)


def _focal_sweep(prob: _Problem, cars: list[_Car], solo: list[int], group: list[int],
                 options: SolveOptions) -> float | None:
    """The focal (px) of least total PnP reprojection error over the views of ``group`` (one camera), swept
    over the horizontal field-of-view range; None when no carriage has 4 points in one of its views."""
    intr0 = prob.views[group[0]].intrinsics
    fs = _focal_grid(intr0.width, options.hfov_range_deg, options.hfov_step_ratio)
    members = [(k, v) for v in group for k in solo if np.sum(cars[k].views == v) >= 4]
    if not members:
        return None
    best = (np.inf, None)
    for fv in fs:
        tot = 0.0
        xy = _undistorted(prob, cars, members, np.full(len(prob.views), fv))
        for k, v in members:
            sel = cars[k].views == v
            r = _pnp(cars[k].P[sel], cars[k].uv[sel], prob.intrinsics(v, fv), prob.views[v].cam_from_world,
                     xy[(k, v)])
            tot += r[2] if r is not None else 1e12
        if tot < best[0]:
            best = (tot, fv)
    return best[1]


def _undistorted(prob: _Problem, cars: list[_Car], members, f: np.ndarray) -> dict:
    """(car, view) -> its pixels in that view undistorted and normalised at the focal ``f[view]``, computed one
    view at a time (the iterative undistortion is vectorised; per carriage it would cost ~10x more)."""
    out = {}
    for v in sorted({v for _, v in members}):
        mv = [(k, cars[k].views == v) for k, w in members if w == v]
        uv = np.concatenate([cars[k].uv[sel] for k, sel in mv])
        intr = prob.intrinsics(v, f[v])
        xy = intr.undistort(intr.normalized_from_pixels(uv))
        o = 0
        for k, sel in mv:
            n = int(sel.sum())
            out[(k, v)] = xy[o:o + n]
            o += n
    return out


def _pnp_start(prob: _Problem, cars: list[_Car], solo: list[int], f: np.ndarray, R: np.ndarray,
               t: np.ndarray) -> None:
    """Step 1's start (in place): every carriage of ``solo`` from SQPnP in the view where it has most points (at
    the focal ``f``); one with no view of 4 points starts 30 m in front of its first camera."""
    views = prob.views
    members = [(k, v) for k in solo for v in range(len(views)) if np.sum(cars[k].views == v) >= 4]
    xy = _undistorted(prob, cars, members, f) if members else {}
    for k in solo:
        c = cars[k]
        best = None
        for v in range(len(views)):
            sel = c.views == v
            if sel.sum() < 4:
                continue
            r = _pnp(c.P[sel], c.uv[sel], prob.intrinsics(v, f[v]), views[v].cam_from_world, xy[(k, v)])
            if r is not None and (best is None or sel.sum() > best[3]):
                best = (r[0], r[1], r[2], sel.sum())
        if best is None:  # no single view with 4 points: start in front of the first camera
            v = int(c.views[0])
            cc = views[v].camera_centre
            M = np.asarray(views[v].cam_from_world)
            R[k] = np.eye(3)
            t[k] = cc + M[2, :3] * 30.0
        else:
            R[k], t[k] = best[0], best[1]


def _car_chi2(prob: _Problem, R, t, f, sigma: float) -> dict[int, tuple[float, int]]:
    """Per carriage of ``prob``: (sum of its whitened squared pixel residuals at sigma, its number of rows)."""
    uv, *_ = prob.project(R, t, f)
    e = (uv - prob.uv) * (prob.w / np.where(prob.w_noise > 0, prob.w_noise, 1.0))[:, None] / sigma
    e2 = np.sum(e * e, axis=1)
    return {k: (float(np.sum(e2[idx])), 2 * len(idx)) for k, idx in prob.by_car.items()}


def _misfit_cars(prob: _Problem, R, t, f, sigma: float, cands: Sequence[int], p_value: float = 1e-4,
                 relative: float = 4.0) -> list[int]:
    """The carriages of ``cands`` whose pixels the solution does not fit: chi-square of their residuals beyond its
    (1 - ``p_value``) quantile with 2 n - 6 degrees of freedom, *and* more than ``relative`` times the median
    carriage's per-row misfit (so that a wrongly configured pixel sigma does not flag every carriage); worst
    first."""
    from scipy.special import gammaincinv  # the chi-square quantile as scipy.stats computes it, without its import

    c2 = _car_chi2(prob, R, t, f, sigma)
    per = [c2[k][0] / max(c2[k][1], 1) for k in c2]
    med = float(np.median(per)) if per else 0.0
    out = []
    for k in cands:
        x, m = c2[k]
        if x > 2.0 * float(gammaincinv(max(m - 6, 1) / 2, 1.0 - p_value)) and x / m > relative * med:
            out.append(k)
    return sorted(out, key=lambda k: -c2[k][0] / c2[k][1])


def _pnp_branches(prob: _Problem, cars: list[_Car], k: int, f: np.ndarray, R: np.ndarray, t: np.ndarray,
                  options: SolveOptions, max_iterations: int = 30) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Other poses of carriage ``k`` that fit its own pixels (its PnP's other branches): from its view with most
    points, OpenCV's EPnP and iterative PnP, IPPE on the best-fit plane of its points (the two poses of a
    near-planar set: an end face seen alone), and the pose ``R[k]`` mirrored in the line of sight (the normal
    of that plane reflected about the viewing ray: the weak-perspective ambiguity). Each is refined alone (as
    in step 1) and kept when it fits about as well as the best of them (chi-square) and differs from the others
    and from ``R[k]`` by more than 5 degrees. Returns ``[(R, t, sum of squared weighted residuals)]``."""
    import cv2

    c = cars[k]
    vs = [v for v in range(len(prob.views)) if np.sum(c.views == v) >= 4]
    if not vs:
        return []
    v = max(vs, key=lambda v: int(np.sum(c.views == v)))
    sel = c.views == v
    P, uv = c.P[sel].astype(np.float64), c.uv[sel]
    intr = prob.intrinsics(v, f[v])
    xy = intr.undistort(intr.normalized_from_pixels(uv)).astype(np.float64).reshape(-1, 1, 2)
    Mv = np.asarray(prob.views[v].cam_from_world, float)
    Rcw, tcw = Mv[:3, :3], Mv[:3, 3]
    starts: list[tuple[np.ndarray, np.ndarray]] = []  # camera-frame (R, t) of the carriage

    def add(rvec, tvec):
        Rc = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
        tc = np.asarray(tvec, np.float64).reshape(3)
        if np.all((P @ Rc.T + tc)[:, 2] > 0):
            starts.append((Rc, tc))

    for flag in (cv2.SOLVEPNP_EPNP, cv2.SOLVEPNP_ITERATIVE):
        try:
            n, rv, tv, _ = cv2.solvePnPGeneric(P, xy, np.eye(3), None, flags=flag)
            for r_, t_ in zip(rv, tv):
                add(r_, t_)
        except cv2.error as exc:  # that solver gives no branch here; the others may
            log.debug("car %s: PnP flag %d failed: %s", c.number, flag, exc)
    mu = P.mean(0)
    _, sv, Vt = np.linalg.svd(P - mu)
    if np.linalg.det(Vt) < 0:
        Vt[2] *= -1
    if sv[0] > 0 and sv[2] / sv[0] < 0.3:  # near planar: the two poses of the plane
        Q = (P - mu) @ Vt.T
        Q[:, 2] = 0.0
        try:
            n, rv, tv, _ = cv2.solvePnPGeneric(Q, xy, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
            for r_, t_ in zip(rv, tv):
                Rp = cv2.Rodrigues(r_)[0]
                Rc = Rp @ Vt
                tc = t_.reshape(3) - Rc @ mu
                add(cv2.Rodrigues(Rc)[0], tc)
        except cv2.error as exc:  # no planar branches here; the others may still be tried
            log.debug("car %s: IPPE on its best-fit plane failed: %s", c.number, exc)
    # the current pose mirrored in the line of sight: the best-fit plane's normal reflected about the viewing ray
    Rc0 = Rcw @ R[k]
    tc0 = Rcw @ t[k] + tcw
    cen = Rc0 @ mu + tc0
    ray = cen / np.linalg.norm(cen)
    nrm = Rc0 @ Vt[2]
    nm = 2.0 * float(nrm @ ray) * ray - nrm
    ax = np.cross(nrm, nm)
    sa, ca = float(np.linalg.norm(ax)), float(nrm @ nm)
    if sa > 1e-9:
        Rm = exp_so3(ax / sa * math.atan2(sa, ca))
        Rc = Rm @ Rc0
        add(cv2.Rodrigues(Rc)[0], cen - Rc @ mu)
    if not starts:
        return []
    Rw, tw = Rcw.T, -Rcw.T @ tcw
    w = float(prob.w_noise[prob.by_car[k][0]]) if len(prob.by_car.get(k, [])) else 1.0
    one = _Problem(cars, [k], prob.views, {k: w})
    opt = replace(options, max_iterations=max_iterations, robust_loss="linear")
    out: list[tuple[np.ndarray, np.ndarray, float]] = []
    for Rc, tc in starts:
        R2, t2 = R.copy(), t.copy()
        R2[k], t2[k] = Rw @ Rc, Rw @ tc + tw
        lay = _Layout([[k]], [[]], True, [], cars, R2, t2, f)
        x, *_ = _run_lsq(one, lay, None, opt)
        R2, t2, *_ = lay.unpack(x, with_derivs=False)
        out.append((R2[k].copy(), t2[k].copy(), _pixel_cost(one, R2, t2, f)))
    best = min(c_ for _, _, c_ in out)
    # about as good as the best: within its chi-square spread (sse / sigma^2 within 3 sqrt(2 dof) + 9)
    sig2 = options.pixel_sigma_px ** 2
    dof = max(2 * int(np.sum(sel)) - 6, 1)
    keep: list[tuple[np.ndarray, np.ndarray, float]] = []
    for Rk, tk, c_ in sorted(out, key=lambda e: e[2]):
        if 2.0 * (c_ - best) / sig2 > 3.0 * math.sqrt(2.0 * dof) + 9.0:
            continue
        if _rot_angle_deg(Rk, R[k]) < 5.0 or any(_rot_angle_deg(Rk, o[0]) < 5.0 for o in keep):
            continue
        keep.append((Rk, tk, c_))
    return keep


# A carriage with at most this many distinct points cannot show a wrong PnP branch in its own pixels: 4 or 5
# points fit the other branches of the pose (P3P's up to four, the weak-perspective mirror) with a chi-square of
# 2 to 4 degrees of freedom, so the chi-square check of :func:`_misfit_cars` does not flag it; the chained cost
# judges its branches instead (:func:`_retry_branches`). Benchmark: 12 cars showing 4, 10, 6, 10, 5, 8 points at
# 2 px: every wrong basin was a 4- or 5-point carriage (docs/solver.md).
FEW_POINTS = 5


def _neighbour_poses(cars: list[_Car], chains, k: int, R: np.ndarray, t: np.ndarray):
    """Poses of carriage ``k`` carried from each chain neighbour over the held coupling: the neighbour's rotation
    (heading from the neighbour; the jack-knife angle is what is lost) and the coupler on the neighbour's."""
    out = []
    for ch in chains:
        if k not in ch or len(ch) < 2:
            continue
        j = ch.index(k)
        if j > 0:
            a = ch[j - 1]
            out.append((R[a].copy(), t[a] + R[a] @ cars[a].c_rear - R[a] @ cars[k].c_front))
        if j < len(ch) - 1:
            b = ch[j + 1]
            out.append((R[b].copy(), t[b] + R[b] @ cars[b].c_front - R[b] @ cars[k].c_rear))
    return out


def _retry_branches(prob: _Problem, cars: list[_Car], chains, slacks, solo: Sequence[int], R1, t1, f1, R, t, f,
                    focal_views, contact: _Contact | None, options: SolveOptions, terrain: Any = None,
                    max_cars: int = 3, max_nfev: int = 10**9, few_points: bool = True):
    """After a chained solve (poses ``R, t``, focal ``f``) started from the poses ``R1, t1`` and focal ``f1``
    (step 3's start), two kinds of carriage are restarted on other poses, and the cheapest chained solution kept:

    * every carriage whose pixels the solution does not fit (:func:`_misfit_cars`; worst first, at most
      ``max_cars``), from its other PnP branches (:func:`_pnp_branches`, from ``R1, t1, f1``);
    * with ``few_points``, every chained carriage with at most :data:`FEW_POINTS` distinct points (fewest
      first), whose own pixels cannot tell a wrong branch: from its other PnP branches and from a pose
      carried from each chain neighbour (:func:`_neighbour_poses`, from the solution).

    For each start, step 4 is re-run from the solution ``R, t, f`` with that carriage's pose replaced (rested on
    the ``terrain`` when given, as step 2 does); each is ranked by a step 4 capped at 40 evaluations, the
    cheapest (if cheaper than the solution) then converged: the chained cost is the judge. No new start is
    tried once ``max_nfev`` evaluations are spent.
    Returns ``(result, nfev, notes)``: ``result`` None when nothing was cheaper, else ``(R, t, f, T_links, msg,
    ok, rounds, n_active)`` as :func:`_solve_chained`."""
    solo_set = set(solo)
    chained = [k for ch in chains if len(ch) > 1 for k in ch if k in solo_set]
    sig = options.pixel_sigma_px
    flagged = _misfit_cars(prob, R, t, f, sig, chained)
    few = sorted((k for k in chained if len(cars[k].distinct) <= FEW_POINTS),
                 key=lambda k: len(cars[k].distinct)) if few_points else []
    if not flagged and not few:
        return None, 0, []
    cost = _full_cost(prob, cars, chains, slacks, R, t, f, contact, options)
    nfev, notes, best, tried = 0, [], None, set()
    n_flag_tried = 0
    opt3 = replace(options, max_iterations=min(int(options.max_iterations), 40))
    R1, t1 = R1.copy(), t1.copy()
    while nfev < max_nfev:
        k = next((i for i in flagged if i not in tried), None) if n_flag_tried < max_cars else None
        if k is not None:
            n_flag_tried += 1
        else:
            k = next((i for i in few if i not in tried), None)
        if k is None:
            break
        tried.add(k)
        alts = [(Rk, tk, "another PnP branch") for Rk, tk, _ in _pnp_branches(prob, cars, k, f1, R1, t1, options)]
        if k in few:
            alts += [(Rk, tk, "a pose carried from its neighbour")
                     for Rk, tk in _neighbour_poses(cars, chains, k, R, t) if _rot_angle_deg(Rk, R[k]) >= 5.0]
        best_k, best_cost, best_sol = None, cost, None
        for Rk, tk, how in alts:
            # from the solution: the others' poses (and the focal) as found, this carriage on its branch
            R2, t2, f2 = R.copy(), t.copy(), f.copy()
            R2[k], t2[k] = Rk, tk
            if terrain is not None:
                M = np.eye(4)
                M[:3, :3], M[:3, 3] = Rk, tk
                M, dz = rest_on_terrain(M, cars[k].ctype, terrain, options.terrain_samples)
                if np.isfinite(dz):
                    t2[k] = M[:3, 3]
            # a ranking: a capped step 4 per branch; the cheapest, if cheaper than the solution, is then converged
            sol = _solve_chained(prob, cars, chains, slacks, True, focal_views, R2, t2, f2, contact, opt3)
            nfev += sol[4]
            c2 = _full_cost(prob, cars, chains, slacks, sol[0], sol[1], sol[2], contact, options)
            if c2 < best_cost * (1.0 - 1e-9):
                best_cost = c2
                best_sol = (sol[0], sol[1], sol[2], sol[3], sol[5], sol[6], sol[7], sol[8])
                best_k = (Rk, t2[k].copy(), how)
            if nfev >= max_nfev:
                break
        if best_k is not None:
            if not best_sol[5] or opt3.max_iterations < options.max_iterations:
                sol = _solve_chained(prob, cars, chains, slacks, True, focal_views, best_sol[0], best_sol[1],
                                     best_sol[2], contact, options)
                nfev += sol[4]
                c2 = _full_cost(prob, cars, chains, slacks, sol[0], sol[1], sol[2], contact, options)
                if c2 <= best_cost:
                    best_cost = c2
                    best_sol = (sol[0], sol[1], sol[2], sol[3], sol[5], sol[6], sol[7], sol[8])
            notes.append(f"car {cars[k].number} restarted from {best_k[2]} "
                         f"({_rot_angle_deg(best_k[0], R[k]):.0f} deg from the solution's): cost {cost:.1f} -> "
                         f"{best_cost:.1f}")
            cost, best = best_cost, best_sol
            R, t, f = best[0], best[1], best[2]
            R1[k], t1[k] = best_k[0], best_k[1]
            flagged = _misfit_cars(prob, R, t, f, sig, chained)
    left = [i for i in (flagged[:max_cars] + few) if i not in tried]
    if nfev >= max_nfev and left:
        notes.append(f"branch check stopped after {nfev} evaluations (its cap): car(s) "
                     f"{', '.join(cars[i].number for i in dict.fromkeys(left))} not tried on other poses")
    return best, nfev, notes


def _chain_cost(prob: _Problem, R, t, f, T_links, slacks, prior_px: float) -> float:
    """The chained cost without the terrain term: weighted pixel residuals plus the couplers' offset prior."""
    c = _pixel_cost(prob, R, t, f)
    for Tl, sl in zip(T_links, slacks):
        for T, s in zip(Tl, sl):
            r = np.asarray(T) * (prior_px * SQRT5 / s)
            c += 0.5 * float(r @ r)
    return c


def _full_cost(prob: _Problem, cars: list[_Car], chains, slacks, R, t, f, contact: _Contact | None,
               options: SolveOptions) -> float:
    """The cost step 4 minimises (pixels, coupler prior, terrain contact, robust loss) at the poses ``R, t``."""
    lay = _Layout(chains, slacks, True, [], cars, R, t, f, None, options.pixel_sigma_px)
    r, _ = _residuals_and_jac(prob, lay, lay.x0, contact, False)
    if options.robust_loss == "linear":
        return float(0.5 * np.sum(r**2))
    from scipy.optimize._lsq.least_squares import construct_loss_function

    lf = construct_loss_function(len(r), options.robust_loss, options.loss_scale_px)
    return float(0.5 * np.sum(lf(r, cost_only=True)))


def _chained_focal_profile(prob: _Problem, cars: list[_Car], chains, slacks, solo: list[int], focal_views,
                           f0: np.ndarray, options: SolveOptions, n_grid: int = 9,
                           max_evaluations: int = 10) -> dict:
    """Start for an unknown focal on a chained consist: the chained cost (every pose optimised, couplers on, no
    terrain) profiled over the focal of each focal group in turn.

    The per-carriage sweep (:func:`_focal_sweep`) sums independent PnP errors; when each carriage spans a small
    angle (a long consist photographed from ~1 train length) a carriage's PnP error barely depends on the focal
    and falls towards the affine limit, so that sweep runs to the longest focal of the range. The couplers
    carry the information: at a wrong focal every carriage's depth scales along its ray and the couplers
    part by about (focal error) x (carriage length). For each group, ``n_grid`` focals log-spaced over the
    field-of-view range plus the per-carriage sweep's, then the two log-midpoints beside the best: at each, PnP
    poses refined carriage by carriage (as step 1 at a known focal), then ``max_evaluations`` evaluations of the chained solve with the focal held (a fixed-focal step 4
    without terrain), a ranking; the best is then solved to convergence. Returns it: ``{"f", "R", "t", "cost",
    "evaluations"}`` (cost as :func:`_chain_cost`)."""
    f = f0.copy()
    N = len(cars)
    # a ranking, not a solve: a few LM evaluations per focal (near the right focal the cost is then within a few
    # per cent of its fixed-focal minimum; far off it is an upper bound, far above)
    opt = replace(options, max_iterations=min(int(options.max_iterations), max_evaluations))
    best: dict | None = None
    n_eval = 0

    solo_prob = _Problem(cars, solo, prob.views, {k: float(prob.w_noise[prob.by_car[k][0]]) for k in solo})

    def evaluate(fv: np.ndarray) -> dict:
        R = np.tile(np.eye(3), (N, 1, 1))
        t = np.zeros((N, 3))
        _pnp_start(prob, cars, solo, fv, R, t)
        # step 1's unchained refinement (as at a known focal): SQPnP's algebraic fit alone can leave a distant
        # carriage in the mirrored-tilt basin, from which the chained solve does not return
        lay = _Layout([[k] for k in solo], [[] for _ in solo], True, [], cars, R, t, fv)
        x, *_ = _run_lsq(solo_prob, lay, None, opt)
        R, t, *_ = lay.unpack(x, with_derivs=False)
        _place_carried(R, t, cars, chains, solo)
        R1, t1 = R.copy(), t.copy()
        R, t, fo, T_links, *_ = _solve_chained(prob, cars, chains, slacks, True, [], R, t, fv, None, opt)
        # a carriage on the wrong branch of its PnP would spoil this focal's cost: its other branches are tried
        # (the few-point carriages' check is left to the final solve's: here it would multiply the profile's cost)
        sol, *_ = _retry_branches(prob, cars, chains, slacks, solo, R1, t1, fv, R, t, fo, [], None, opt,
                                  max_cars=1, few_points=False)
        if sol is not None:
            R, t, fo, T_links = sol[:4]
        return {"f": fo.copy(), "R": R, "t": t, "cost": _chain_cost(prob, R, t, fo, T_links, slacks,
                                                                      options.pixel_sigma_px)}

    lo_deg, hi_deg = options.hfov_range_deg
    for grp in focal_views:
        half_w = 0.5 * prob.views[grp[0]].intrinsics.width
        lf = np.log(half_w / np.tan(np.deg2rad(np.array([hi_deg, lo_deg])) / 2.0))
        grid = list(np.linspace(lf[0], lf[1], n_grid))
        ls = math.log(f[grp[0]])
        if min(abs(ls - g) for g in grid) > 0.01:
            grid.append(ls)
        tried: dict[float, dict] = {}
        for lg in grid:
            fv = f.copy()
            fv[grp] = math.exp(lg)
            tried[lg] = evaluate(fv)
            n_eval += 1
        srt = sorted(tried)
        lb = min(tried, key=lambda k: tried[k]["cost"])
        i = srt.index(lb)
        for j in (i - 1, i + 1):
            if 0 <= j < len(srt):
                lm = 0.5 * (lb + srt[j])
                fv = f.copy()
                fv[grp] = math.exp(lm)
                tried[lm] = evaluate(fv)
                n_eval += 1
        gbest = min(tried.values(), key=lambda e: e["cost"])
        f = gbest["f"].copy()
        best = gbest
    assert best is not None
    # the best focal's chained solve run to convergence: the reference of step 4's basin check
    R, t, fo, T_links, *_ = _solve_chained(prob, cars, chains, slacks, True, [], best["R"], best["t"], best["f"],
                                           None, options)
    return {"f": fo.copy(), "R": R, "t": t, "cost": _chain_cost(prob, R, t, fo, T_links, slacks,
                                                                  options.pixel_sigma_px),
            "evaluations": n_eval + 1}


# ----------------------------------------------------------------------------------------------------------
# The solver
# ----------------------------------------------------------------------------------------------------------
def _warn(wlist: list, car: _Car | None, kind: str, message: str) -> None:
    rec = {"car": car.number if car is not None else None, "index": car.index if car is not None else None,
           "kind": kind, "message": message}
    wlist.append(rec)
    warnings.warn(message, SolveWarning, stacklevel=3)


_SAMPLE_CACHE: dict[tuple[str, int], np.ndarray] = {}


def _samples(ct: Any, n: int) -> np.ndarray:
    key = (f"{ct.id}:{ct.source_path}", int(n))
    s = _SAMPLE_CACHE.get(key)
    if s is None:
        s = np.asarray(ct.sample_surface(n), dtype=float)
        _SAMPLE_CACHE[key] = s
    return s


def rest_on_terrain(world_from_carriage: np.ndarray, carriage_type: Any, terrain: Any,
                    n_samples: int = 400) -> tuple[np.ndarray, float]:
    """Step 2 for one carriage: move it along gravity (scene z only) until its lowest surface sample touches the
    terrain without penetrating it. Returns (new world_from_carriage (4, 4), dz applied in metres). A carriage
    outside the terrain (heights NaN) is returned unchanged with dz = NaN."""
    M = np.array(world_from_carriage, dtype=float)
    X = _samples(carriage_type, n_samples) @ M[:3, :3].T + M[:3, 3]
    d = X[:, 2] - np.asarray(terrain.height_at(X[:, :2]), dtype=float)
    if not np.any(np.isfinite(d)):
        return M, float("nan")
    dz = -float(np.nanmin(d))
    M[2, 3] += dz
    return M, dz


def _place_carried(R: np.ndarray, t: np.ndarray, cars, chains, solved) -> None:
    """Pose every carriage not in ``solved`` from its chain neighbours (in place): same rotation, front coupler
    on the neighbour's rear coupler; forwards then backwards along each chain."""
    placed = set(solved)
    for ch in chains:
        for _ in range(2):
            for j in range(1, len(ch)):
                a, b = ch[j - 1], ch[j]
                if a in placed and b not in placed:
                    R[b] = R[a]
                    t[b] = t[a] + R[a] @ cars[a].c_rear - R[b] @ cars[b].c_front
                    placed.add(b)
            for j in range(len(ch) - 2, -1, -1):
                a, b = ch[j], ch[j + 1]
                if b in placed and a not in placed:
                    R[a] = R[b]
                    t[a] = t[b] + R[b] @ cars[b].c_front - R[a] @ cars[a].c_rear
                    placed.add(a)


def solve_consist(carriages: Sequence[CarriageInput], links: Sequence[ChainLink], views: Sequence[View],
                  options: SolveOptions | None = None, terrain: Any = None) -> SolveResult:
    """Solve the poses of all carriages (and optionally the focal) from marked-point pixels. See the module doc."""
    t_start = time.perf_counter()
    options = options or SolveOptions()
    views = list(views)
    cars = _prepare(carriages, views, options)
    N = len(cars)
    wl: list[dict] = []

    # -- links ----------------------------------------------------------------------------------------
    link_slack: dict[int, float] = {}  # front index -> slack (held/broken-with-slack link to front+1)
    seen_pairs = set()
    for L in links:
        for idx in (L.front, L.rear):
            if not (0 <= int(idx) < N):
                raise InputError(f"chain link {L.front}->{L.rear}: carriage index {idx} is not in the consist "
                                 f"(0..{N - 1})")
        if int(L.rear) != int(L.front) + 1:
            raise InputError(f"chain link {L.front}->{L.rear}: a link joins consecutive carriages (rear = front + 1)")
        if L.front in seen_pairs:
            raise InputError(f"chain link {L.front}->{L.rear} is given twice")
        seen_pairs.add(L.front)
        if L.slack_m is None:
            continue
        if not (np.isfinite(L.slack_m) and L.slack_m > 0):
            raise InputError(f"chain link {L.front}->{L.rear}: slack_m = {L.slack_m!r} must be positive (or None for "
                             f"no link)")
        link_slack[int(L.front)] = float(L.slack_m)

    # -- observability ----------------------------------------------------------------------------------
    n_pts = [len(c.distinct) for c in cars]
    degenerate = []
    for c in cars:
        d = _degeneracy(c.ctype, c.distinct) if len(c.distinct) >= 2 else "too few"
        if d == "coplanar" and not options.estimate_focal and len(c.distinct) >= 4:
            d = ""
        degenerate.append(d)
    alone_ok = [n_pts[k] >= 4 and degenerate[k] == "" for k in range(N)]
    candidate = [n_pts[k] >= 2 for k in range(N)]
    for k in range(N):
        if not candidate[k]:
            lk = (k in link_slack) or (k - 1 in link_slack)
            _warn(wl, cars[k], "left_out",
                  f"car {cars[k].number}: {n_pts[k]} visible marked point(s) — at least 2 are needed even when "
                  f"carried by its chain{' (its links are dropped)' if lk else ''}; left out")
    # chains over candidates
    chains: list[list[int]] = []
    k = 0
    while k < N:
        if not candidate[k]:
            k += 1
            continue
        ch = [k]
        while k in link_slack and k + 1 < N and candidate[k + 1]:
            ch.append(k + 1)
            k += 1
        chains.append(ch)
        k += 1
    status_car = ["left_out"] * N
    final_chains: list[list[int]] = []
    for ch in chains:
        if len(ch) == 1:
            k = ch[0]
            if alone_ok[k]:
                status_car[k] = "solved"
                final_chains.append(ch)
            else:
                why = (f"{n_pts[k]} visible point(s), 4 needed for an unlinked carriage" if n_pts[k] < 4
                       else f"its points are {degenerate[k]}" + (" and the focal is unknown"
                                                                 if degenerate[k] == "coplanar" else ""))
                _warn(wl, cars[k], "left_out", f"car {cars[k].number}: not observable alone ({why}) and not linked "
                                               f"to a neighbour; left out")
            continue
        if not any(alone_ok[k] for k in ch):
            for k in ch:
                _warn(wl, cars[k], "left_out", f"car {cars[k].number}: no carriage of its chain "
                                               f"({', '.join(cars[i].number for i in ch)}) is observable alone; left out")
            continue
        for k in ch:
            if alone_ok[k]:
                status_car[k] = "solved"
            else:
                status_car[k] = "carried"
                if n_pts[k] < 3 or degenerate[k] not in ("", "coplanar") or (
                        degenerate[k] == "coplanar" and options.estimate_focal):
                    why = (f"{n_pts[k]} visible point(s), 3 needed" if n_pts[k] < 3
                           else f"its points are {degenerate[k]}")
                    _warn(wl, cars[k], "carried", f"car {cars[k].number}: not observable alone ({why}); carried by "
                                                  f"its chain")
        final_chains.append(ch)
    active = [k for ch in final_chains for k in ch]
    chain_slacks = [[link_slack[ch[j]] for j in range(len(ch) - 1)] for ch in final_chains]

    # -- weights -----------------------------------------------------------------------------------------
    weights = carriage_weights(cars, active, options.weighting)
    prob = _Problem(cars, active, views, weights)
    V = len(views)
    f = np.array([v.intrinsics.fx for v in views], dtype=float)
    R = np.tile(np.eye(3), (N, 1, 1))
    t = np.zeros((N, 3))
    steps: list[StepStats] = []
    focal_views = focal_groups(views, [v for v in range(V) if len(prob.by_view[v]) > 0]) \
        if options.estimate_focal else []
    total_nfev = 0
    all_ok = True
    messages = []

    # -- step 1: each carriage alone ----------------------------------------------------------------------
    t1 = time.perf_counter()
    solo = [k for k in active if alone_ok[k]]
    note = ""
    if options.estimate_focal:
        for grp in focal_views:
            fb = _focal_sweep(prob, cars, solo, grp, options)
            names = ", ".join(views[v].name for v in grp)
            if fb is not None:
                f[grp] = fb
            else:
                _warn(wl, None, "focal", f"view(s) {names}: no carriage with 4 points in one photo; the focal "
                                         f"sweep kept the given focal {f[grp[0]]:.1f} px")
        note = "focal sweep: " + ", ".join(f"{'+'.join(views[v].name for v in grp)}={f[grp[0]]:.1f}px"
                                           for grp in focal_views)
    profile = None
    if focal_views and any(len(ch) > 1 for ch in final_chains):
        # the per-carriage sweep cannot tell the focal when each carriage shows little perspective (its PnP
        # error falls towards the affine limit, the largest focal); the couplers can: profile the chained cost
        profile = _chained_focal_profile(prob, cars, final_chains, chain_slacks, solo, focal_views, f, options)
        f = profile["f"].copy()
        note += "; chained focal profile: " + ", ".join(
            f"{'+'.join(views[v].name for v in grp)}={f[grp[0]]:.1f}px" for grp in focal_views) + \
            f" ({profile['evaluations']} fixed-focal chained solves)"
    _pnp_start(prob, cars, solo, f, R, t)
    # carried: from the neighbours, forwards then backwards
    _place_carried(R, t, cars, final_chains, solo)
    R_init, t_init = R.copy(), t.copy()
    cost0 = _pixel_cost(prob, R, t, f)
    # one joint refinement of every independent pose (a block-diagonal problem, one loop in the sparse solver);
    # with an unknown focal the focal ties the carriages together
    solo_prob = _Problem(cars, solo, views, weights)
    # after a chained focal profile the focal is held here: unchained, the cost would pull it to the affine limit
    lay = _Layout([[k] for k in solo], [[] for _ in solo], True, focal_views if profile is None else [], cars, R, t,
                  f)
    x, nfev, msg, ok = _run_lsq(solo_prob, lay, None, options)
    total_nfev += nfev
    R, t, f, *_ = lay.unpack(x, with_derivs=False)
    # carried ones follow their (refined) neighbours again
    _place_carried(R, t, cars, final_chains, solo)
    steps.append(StepStats("1_alone", True, (note + "; " if note else "") + "PnP (SQPnP) then joint refinement, "
                           "constraints off" + ("; carried cars placed from their neighbours"
                                                if len(solo) < len(active) else ""),
                           cost0, _pixel_cost(prob, R, t, f), nfev, msg, time.perf_counter() - t1,
                           _changes(cars, active, R_init, t_init, R, t)))

    # -- step 2: onto the terrain -------------------------------------------------------------------------
    t2 = time.perf_counter()
    samples = {k: _samples(cars[k].ctype, options.terrain_samples) for k in active} if terrain is not None else {}
    if terrain is None:
        steps.append(StepStats("2_terrain", False, "skipped: no terrain given"))
    else:
        R0, tt0 = R.copy(), t.copy()
        c0 = _pixel_cost(prob, R, t, f)
        for k in active:
            M = np.eye(4)
            M[:3, :3], M[:3, 3] = R[k], t[k]
            M, dz = rest_on_terrain(M, cars[k].ctype, terrain, options.terrain_samples)
            if not np.isfinite(dz):
                _warn(wl, cars[k], "terrain", f"car {cars[k].number}: outside the terrain; not moved in step 2")
                continue
            t[k] = M[:3, 3]
        steps.append(StepStats("2_terrain", True, "lowered/raised along gravity (-z) onto the terrain", c0,
                               _pixel_cost(prob, R, t, f), 0, "done", time.perf_counter() - t2,
                               _changes(cars, active, R0, tt0, R, t)))

    # -- step 3: constraints on, rotations held --------------------------------------------------------------
    t3 = time.perf_counter()
    R0, tt0 = R.copy(), t.copy()
    R_s3, t_s3, f_s3 = R.copy(), t.copy(), f.copy()  # step 3's start: the branch check below restarts from it
    c0 = _pixel_cost(prob, R, t, f)
    # step 3 only starts step 4: with rotations held (noisy), offsets often sit on the sphere with large
    # multipliers where Gauss-Newton converges slowly, so its iterations are capped (not an overall failure)
    opt3 = replace(options, max_iterations=min(int(options.max_iterations), 40))
    R, t, f, T_links, nfev, msg, ok, rounds, n_act = _solve_chained(prob, cars, final_chains, chain_slacks, False,
                                                                    focal_views, R, t, f, None, opt3)
    total_nfev += nfev
    nfev_3 = nfev
    steps.append(StepStats("3_chain_translations", True, "couplers on, rotations held, translations"
                           + (" and focal" if focal_views else "") + f" optimised ({rounds} active-set round(s), "
                           f"{n_act} coupler(s) at the slack)", c0, _pixel_cost(prob, R, t, f),
                           nfev, msg, time.perf_counter() - t3, _changes(cars, active, R0, tt0, R, t)))

    # -- step 4: everything ---------------------------------------------------------------------------------
    t4 = time.perf_counter()
    R0, tt0 = R.copy(), t.copy()
    c0 = _pixel_cost(prob, R, t, f)
    contact = None
    if terrain is not None and options.use_terrain_contact:
        contact = _Contact(terrain, samples, options.pixel_sigma_px / options.terrain_sigma_m)
    R, t, f, T_links, nfev, msg, ok, rounds, n_act = _solve_chained(prob, cars, final_chains, chain_slacks, True,
                                                                    focal_views, R, t, f, contact, options)
    total_nfev += nfev
    nfev_34 = nfev_3 + nfev
    restart_note = ""
    if profile is not None:
        # a proper check of the basin: the solution (focal free) can be no worse than the best fixed-focal chained
        # solve of the profile; if it is, step 4 ended in another basin: restart it from the profile's best
        c_sol = _chain_cost(prob, R, t, f, T_links, chain_slacks, options.pixel_sigma_px)
        if c_sol > profile["cost"] * (1.0 + 1e-6) + 1e-9:
            R2, t2, f2, T2, nfev2, msg2, ok2, rounds2, n_act2 = _solve_chained(
                prob, cars, final_chains, chain_slacks, True, focal_views, profile["R"], profile["t"], profile["f"],
                contact, options)
            total_nfev += nfev2
            c_old = _full_cost(prob, cars, final_chains, chain_slacks, R, t, f, contact, options)
            c2 = _full_cost(prob, cars, final_chains, chain_slacks, R2, t2, f2, contact, options)
            restart_note = (f"; ended at cost {c_sol:.1f} above the focal profile's best {profile['cost']:.1f}: "
                            f"restarted from it, cost {c2:.1f} (was {c_old:.1f})")
            if c2 < c_old:
                R, t, f, T_links, msg, ok, rounds, n_act = R2, t2, f2, T2, msg2, ok2, rounds2, n_act2
    # a carriage whose pixels the chained solution does not fit (chi-square) may sit on the wrong branch of its
    # own PnP (an end face seen alone fits two poses ~90 deg apart): steps 3 and 4 are re-run from its other
    # branches and the cheapest solution kept
    sol_b, nfev_b, notes_b = _retry_branches(prob, cars, final_chains, chain_slacks, solo, R_s3, t_s3, f_s3, R, t,
                                             f, focal_views, contact, options, terrain,
                                             max_nfev=max(200, nfev_34))
    total_nfev += nfev_b
    nfev += nfev_b
    if sol_b is not None:
        R, t, f, T_links, msg, ok, rounds, n_act = sol_b
    if notes_b:
        restart_note += "; " + "; ".join(notes_b)
    steps.append(StepStats("4_all", True, f"everything optimised ({rounds} active-set round(s), {n_act} coupler(s) "
                           f"at the slack)" + restart_note + (
        f"; soft terrain contact (sigma_z = {options.terrain_sigma_m} m)" if contact is not None else
        ("; no terrain contact term (no terrain)" if terrain is None else "; terrain contact term off")),
        c0, _pixel_cost(prob, R, t, f), nfev, msg, time.perf_counter() - t4,
        _changes(cars, active, R0, tt0, R, t)))
    if not ok:
        all_ok = False
        messages.append(f"step 4: {msg}")

    # -- step 4b: the predictions checked against the measured points ----------------------------------------
    n_pred = int((~prob.measured).sum())
    if n_pred == 0 or options.prediction_release <= 1.0:
        steps.append(StepStats("4b_predictions_checked", False, "skipped: no predicted points" if n_pred == 0
                               else "skipped: solver.prediction_release = 1 (predictions keep their weight)"))
    else:
        t4b = time.perf_counter()
        kept = (R.copy(), t.copy(), f.copy(), T_links, msg, ok, rounds, n_act)
        released = prob.with_predictions_scaled(options.prediction_release)
        R, t, f, T_links, nfev, msg, ok, rounds, n_act = _solve_chained(released, cars, final_chains, chain_slacks,
                                                                        True, focal_views, R, t, f, contact, options)
        total_nfev += nfev
        rel_sol = (R.copy(), t.copy(), f.copy(), T_links, msg, ok, rounds, n_act)
        from .uncertainty import solution_model

        rel_model = solution_model(released, R, t, f, focal_views, final_chains, chain_slacks, contact, options)

        def shift(R_k, t_k):
            return _prediction_shift(released, rel_sol[0], rel_sol[1], rel_sol[2], R_k, t_k, focal_views,
                                     final_chains, chain_slacks, contact, options, model=rel_model)

        d2 = shift(kept[0], kept[1])
        off = sorted(k for k, v in d2.items() if not v <= _CHI2_6_95)
        listed = ", ".join(f"{cars[k].number} {d2[k]:.1f}" for k in sorted(d2))
        # with some cars' predictions released and the others' kept, the kept ones can pull further (a
        # neighbour's opposite pull gone, a chained car no longer held by its own): the mixed fit is checked in
        # turn, and a car it moves beyond the limit is released too, until the fit is consistent
        rounds_note = []
        while off and len(off) < len(d2):
            prob_m = prob.with_predictions_scaled(options.prediction_release, off)
            sol_m = _solve_chained(prob_m, cars, final_chains, chain_slacks, True, focal_views, kept[0], kept[1],
                                   kept[2], contact, options)
            nfev += sol_m[4]
            total_nfev += sol_m[4]
            d2m = shift(sol_m[0], sol_m[1])
            more = sorted(k for k, v in d2m.items() if k not in off and not v <= _CHI2_6_95)
            if not more:
                break
            rounds_note.append(", ".join(f"{cars[k].number} {d2m[k]:.1f}" for k in more))
            off = sorted(set(off) | set(more))
        extra = (f"; then, with those released, the remaining predictions moved car(s) beyond the limit too "
                 f"(chi-square {'; '.join(rounds_note)}): released") if rounds_note else ""
        if not off:  # every car's predictions agree with its measured points: step 4's fit stands
            R, t, f, T_links, msg, ok, rounds, n_act = kept
            note = f"predictions agree with the measured points on every car (shift chi-square {listed}): kept"
        elif len(off) == len(d2):
            prob = released
            R, t, f, T_links, msg, ok, rounds, n_act = rel_sol
            note = (f"predictions released on every car with some (shift chi-square {listed}, 95 % limit "
                    f"{_CHI2_6_95:.1f}){extra}")
        else:
            prob = prob_m
            R, t, f, T_links, _, msg, ok, rounds, n_act = sol_m
            note = (f"predictions released on car(s) {', '.join(cars[k].number for k in off)}, kept on the others "
                    f"(shift chi-square {listed}, 95 % limit {_CHI2_6_95:.1f}){extra}")
        steps.append(StepStats("4b_predictions_checked", True, f"{n_pred} predicted point(s) checked: fitted again "
                               f"with their sigmas x {options.prediction_release:g}; " + note,
                               _pixel_cost(prob, *kept[:3]), _pixel_cost(prob, R, t, f), nfev, msg,
                               time.perf_counter() - t4b, _changes(cars, active, kept[0], kept[1], R, t)))
        if not ok:
            all_ok = False
            messages.append(f"step 4b: {msg}")
    final_cost = _full_cost(prob, cars, final_chains, chain_slacks, R, t, f, contact, options)
    cost_at_minimum = final_cost

    # -- optional: the second-order bias removed ------------------------------------------------------------
    model = None
    bc_summary: dict = {}
    if options.bias_correction and active:
        t5 = time.perf_counter()
        skip = _bias_skip_reason(options, focal_views)
        if skip:
            bc_summary = {"applied": False, "note": skip}
            steps.append(StepStats("5_bias_correction", False, skip))
        else:
            from .bias import correct
            from .uncertainty import solution_model

            model = solution_model(prob, R, t, f, focal_views, final_chains, chain_slacks, contact, options)
            bc = correct(prob, cars, R, t, f, focal_views, final_chains, chain_slacks, contact, model,
                         options.pixel_sigma_px, views, max_over_sd=options.bias_max_over_sd)
            bc_summary = bc.summary()
            if bc.applied:
                R, t, f = bc.R, bc.t, bc.f
                T_links = [[t[b] + R[b] @ cars[b].c_front - t[a] - R[a] @ cars[a].c_rear
                            for a, b in zip(ch[:-1], ch[1:])] for ch in final_chains]
                final_cost = _full_cost(prob, cars, final_chains, chain_slacks, R, t, f, contact, options)
            steps.append(StepStats("5_bias_correction", bc.applied, bc.note, cost_at_minimum, final_cost, 0,
                                   "done" if bc.applied else "skipped", time.perf_counter() - t5, bc.per_carriage))

    # -- results -------------------------------------------------------------------------------------------
    uv_all, *_ = prob.project(R, t, f)
    results = []
    for k in range(N):
        c = cars[k]
        cr = CarriageResult(index=k, number=c.number, type_id=str(c.ctype.id), status=status_car[k],
                            n_points=n_pts[k])
        if status_car[k] != "left_out":
            M = np.eye(4)
            M[:3, :3], M[:3, 3] = R[k], t[k]
            cr.world_from_carriage = M
            cr.hpr_deg = hpr_from_rotation(R[k])
            cr.body_centre_m = R[k] @ c.c_body + t[k]
            idx = prob.by_car[k]
            e = uv_all[idx] - prob.uv[idx]
            for i, row in enumerate(idx):
                vn = views[prob.view[row]].name
                cr.residuals_px.setdefault(vn, {})[c.names[i]] = (float(e[i, 0]), float(e[i, 1]))
            cr.rms_px = float(np.sqrt(np.mean(np.sum(e * e, axis=1)))) if len(idx) else None
            if contact is not None:
                cl = contact.clearance(R, t, k)
                cr.clearance_m = cl[0] if cl is not None else None
        results.append(cr)
    link_info = []
    for c_, ch in enumerate(final_chains):
        for j in range(len(ch) - 1):
            T = T_links[c_][j]
            link_info.append({"front": ch[j], "rear": ch[j + 1], "slack_m": chain_slacks[c_][j],
                              "offset_m": T.tolist(), "offset_norm_m": float(np.linalg.norm(T))})
    lo_deg, hi_deg = options.hfov_range_deg
    for grp in focal_views:
        intr = views[grp[0]].intrinsics
        hfov = math.degrees(2.0 * math.atan(0.5 * intr.width / f[grp[0]]))
        if hfov < lo_deg * 1.02 or hfov > hi_deg * 0.98:
            _warn(wl, None, "focal_at_limit",
                  f"view(s) {', '.join(views[v].name for v in grp)}: the estimated focal ({f[grp[0]]:.0f} px, "
                  f"{hfov:.1f} deg field of view) ran to the edge of the search range {lo_deg:g}-{hi_deg:g} deg "
                  f"(solver.hfov_range_deg in project.toml): if the photo's field of view lies outside it, widen "
                  f"it; else the photo shows too little perspective to tell the focal from the distance, and the "
                  f"positions along the viewing direction are not determined: give the focal (a camera profile or "
                  f"EXIF)")
    status = "converged" if all_ok else "not_converged"
    if not all_ok:
        _warn(wl, None, "not_converged", "solve did not converge: " + "; ".join(messages))
    res = SolveResult(carriages=results, status=status, message="; ".join(messages) or "converged", warnings=wl,
                      steps=steps, iterations=total_nfev, time_s=0.0, final_cost=final_cost,
                      focal_px={views[v].name: float(f[v]) for v in range(V)}, sigma_focal_px={}, links=link_info,
                      cost_at_minimum=cost_at_minimum, bias_correction=bc_summary)
    if options.compute_covariance and active:
        from .uncertainty import attach_covariance

        # with the bias correction: the covariance (and the pixel sigma) of the minimum, centred on the corrected
        # poses
        attach_covariance(res, prob, R, t, f, focal_views, final_chains, chain_slacks, contact, options, model=model)
    res.time_s = time.perf_counter() - t_start
    return res


def _bias_skip_reason(options: SolveOptions, focal_views) -> str:
    """Why the bias correction is not applied ("" when it is): a robust loss (its IRLS weights are not a fixed
    noise model); an estimated focal (the benchmark shows the second-order expansion failing there: on 12 cars
    at 2 px the correction made 86 of 150 trials worse and moved one solution 98 m, docs/solver.md)."""
    if options.robust_loss != "linear":
        return "not applied: a robust loss is not a fixed noise model"
    if focal_views:
        return ("not applied: with the focal estimated the second-order expansion does not hold (positions along "
                "the line of sight scale with the focal; see docs/solver.md)")
    return ""


def held_chains(n: int, links) -> tuple[list[list[int]], list[list[float]]]:
    """The consist's carriages 0..n-1 split into chains at every link without a slack (a broken coupling, or
    none), and each chain's link slacks (metres), front to rear: a simplification for synthetic consists."""
    slack = {int(L.front): float(L.slack_m) for L in links if L.slack_m is not None}
    chains, k = [], 0
    while k < n:
        ch = [k]
        while k in slack and k + 1 < n:
            ch.append(k + 1)
            k += 1
        chains.append(ch)
        k += 1
    return chains, [[slack[ch[j]] for j in range(len(ch) - 1)] for ch in chains]


def refine_from(carriages: Sequence[CarriageInput], links: Sequence[ChainLink], views: Sequence[View],
                world_from_carriage: Sequence[np.ndarray], options: SolveOptions | None = None) -> dict:
    """Diagnostic, not a solve: step 4 alone (every pose, and the focal when ``options.estimate_focal``, couplers
    on, no terrain) started from the given poses (4, 4) and the views' focal — for a benchmark, the truth.

    Started at the truth, it finds the minimum of the solver's cost in the truth's basin: if
    :func:`solve_consist` (which starts without help) ends at a higher cost, the solver failed (a wrong basin,
    an early stop); if it ends at the same point, any excess error over the Cramér-Rao bound is the estimator's
    own. Every carriage must be observable alone and every link held (``slack_m`` set) or absent: a
    simplification for synthetic consists. Returns ``{"world_from_carriage": [(4, 4)], "focal_px": {view:
    f}, "cost": chained cost (pixels + coupler prior) at the minimum, "converged": bool}``; with
    ``options.bias_correction`` the poses and focal are the bias-corrected ones (as :func:`solve_consist` reports
    them), and ``"world_from_carriage_minimum"`` / ``"focal_px_minimum"`` those of the minimum."""
    options = options or SolveOptions()
    views = list(views)
    cars = _prepare(carriages, views, options)
    N = len(cars)
    chains, slacks = held_chains(N, links)
    active = list(range(N))
    prob = _Problem(cars, active, views, carriage_weights(cars, active, options.weighting))
    R = np.array([np.asarray(M, float)[:3, :3] for M in world_from_carriage])
    t = np.array([np.asarray(M, float)[:3, 3] for M in world_from_carriage])
    f = np.array([v.intrinsics.fx for v in views], dtype=float)
    fv = focal_groups(views, [v for v in range(len(views)) if len(prob.by_view[v]) > 0]) \
        if options.estimate_focal else []
    R, t, f, T_links, _, _, ok, _, _ = _solve_chained(prob, cars, chains, slacks, True, fv, R, t, f, None, options)

    def poses(R, t):
        out = []
        for k in range(N):
            M = np.eye(4)
            M[:3, :3], M[:3, 3] = R[k], t[k]
            out.append(M)
        return out

    res = {"world_from_carriage": poses(R, t), "focal_px": {v.name: float(f[i]) for i, v in enumerate(views)},
           "cost": _chain_cost(prob, R, t, f, T_links, slacks, options.pixel_sigma_px), "converged": bool(ok)}
    skip = _bias_skip_reason(options, fv) if options.bias_correction else "off"
    if options.bias_correction and skip:
        res["bias_correction"] = {"applied": False, "note": skip}
    elif options.bias_correction:
        from .bias import correct
        from .uncertainty import solution_model

        model = solution_model(prob, R, t, f, fv, chains, slacks, None, options)
        bc = correct(prob, cars, R, t, f, fv, chains, slacks, None, model, options.pixel_sigma_px, views,
                     max_over_sd=options.bias_max_over_sd)
        if bc.applied:
            res["world_from_carriage_minimum"], res["focal_px_minimum"] = res["world_from_carriage"], res["focal_px"]
            res["world_from_carriage"] = poses(bc.R, bc.t)
            res["focal_px"] = {v.name: float(bc.f[i]) for i, v in enumerate(views)}
        res["bias_correction"] = bc.summary()
    return res
