"""The least-squares problem: the carriages' observations flattened into rows, their weights and projection.

A :class:`Problem` holds the observation rows of the carriages being solved (one row per marked point per view)
with their weights; it projects poses to pixels with exact Jacobians. :class:`Poses` and :class:`Chains` are the
state and the structure every step passes around.
"""

from __future__ import annotations

import copy
import math
import warnings
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.geometry import rotation_angle_deg
from ..errors import InputError, SettingsError
from .model import WEIGHTINGS, CarriageInput, Observation, SolveOptions, SolveWarning, View
from .projection import project_world_points_with_jacobians

SQRT5 = math.sqrt(5.0)  # slack / sigma_T: an offset uniform in the ball |T| <= s has per-axis sd s / sqrt(5)


@dataclass
class Poses:
    """The solver's state: world_from_carriage of every carriage (``R`` (N, 3, 3), ``t`` (N, 3)) and the focal
    of every view (``f`` (V,), px)."""

    R: np.ndarray
    t: np.ndarray
    f: np.ndarray

    def copy(self) -> "Poses":
        return Poses(self.R.copy(), self.t.copy(), self.f.copy())


@dataclass
class Chains:
    """The consist's chains of held couplings: carriage indices front to rear, and each link's slack (m)."""

    members: list[list[int]]
    slacks: list[list[float]]

    @classmethod
    def singletons(cls, cars: Sequence[int]) -> "Chains":
        """Every carriage of ``cars`` on its own (no couplings)."""
        return cls([[k] for k in cars], [[] for _ in cars])


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


# ----------------------------------------------------------------------------------------------------------
# Prepared carriages
# ----------------------------------------------------------------------------------------------------------
@dataclass
class Car:
    """One carriage's observations as arrays (one row per visible point per view) and its coupler geometry."""

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
    loadings: np.ndarray | None = None  # (n, 2, 8) each point's share of its face alignment's error, NaN: none
    on_track: bool = False  # marked still on the rails (CarriageInput.on_track)
    ecc: np.ndarray | None = None  # (n,) the ECC correlation of the point's face alignment (Observation.ecc), NaN: none
    carried: np.ndarray | None = None  # (n,) bool: a prediction carried from another photo (Observation.carried)


def record_warning(wlist: list, car: Car | None, kind: str, message: str) -> None:
    """Append a structured warning to ``wlist`` and issue it as a :class:`SolveWarning`."""
    rec = {"car": car.number if car is not None else None, "index": car.index if car is not None else None,
           "kind": kind, "message": message}
    wlist.append(rec)
    warnings.warn(message, SolveWarning, stacklevel=3)


@dataclass(frozen=True)
class AlignedObservation(Observation):
    """An automatic point placed by its face's homography, with its share of that alignment's error: the point's
    displacement is ``loading @ xi`` (px), ``loading`` (2, 8), with one ``xi ~ N(0, I_8)`` shared by the points of
    the same carriage, face (``group``) and view (``workbench.correspond.alignment``; docs/correspondences.md)."""

    loading: tuple | None = None


def _iter_observations(obs: Any):
    """(point name, (u, v), sigma_px or None, derived, group or None, loading or None, ECC correlation or None,
    carried) of the visible observations of one view."""
    if isinstance(obs, Mapping):
        for name, uv in obs.items():
            if uv is None:
                continue
            if isinstance(uv, Observation):
                if uv.visible:
                    yield (str(name), (uv.u, uv.v), uv.sigma_px, uv.derived, uv.group, getattr(uv, "loading", None),
                           uv.ecc, uv.carried)
                continue
            yield str(name), uv, None, False, None, None, None, False
    else:
        for o in obs:
            if isinstance(o, Observation):
                if o.visible:
                    yield (o.point, (o.u, o.v), o.sigma_px, o.derived, o.group, getattr(o, "loading", None), o.ecc,
                           o.carried)
            else:
                name, uv = o
                yield str(name), uv, None, False, None, None, None, False


def _check_views(views: Sequence[View]) -> dict[str, int]:
    if not views:
        raise InputError("solve: no views (photos) given")
    vnames = [v.name for v in views]
    if len(set(vnames)) != len(vnames):
        raise InputError(f"solve: view names repeat: {vnames}")
    for v in views:
        M = np.asarray(v.cam_from_world, dtype=float)
        if M.shape != (4, 4) or not np.all(np.isfinite(M)):
            raise InputError(f"view {v.name!r}: cam_from_world must be a finite (4, 4) matrix")
    return {n: i for i, n in enumerate(vnames)}


def _prepare_one(i: int, c: CarriageInput, views: Sequence[View], vindex: dict[str, int],
                 options: SolveOptions) -> Car:
    ct = c.carriage_type
    names, vi, P, uv, sc, der, grp, lds, eccs, carried_fl = [], [], [], [], [], [], [], [], [], []
    for vname, obs in (c.observations or {}).items():
        if vname not in vindex:
            raise InputError(f"car {c.number}: observations for view {vname!r}, which is not among the views "
                             f"{list(vindex)}")
        intr = views[vindex[vname]].intrinsics
        seen: set[str] = set()
        for name, pix, sig, derived, group, loading, ecc, carried in _iter_observations(obs):
            where = f"car {c.number}, view {vname!r}"
            if name not in ct.marked_points:
                raise InputError(f"{where}: point {name!r} is not a marked point of type "
                                 f"{ct.id!r} (it has: {', '.join(ct.marked_points)})")
            if name in seen:
                raise InputError(f"{where}: point {name!r} is given twice")
            seen.add(name)
            a = np.asarray(pix, dtype=float).reshape(-1)
            if a.size != 2 or not np.all(np.isfinite(a)):
                raise InputError(f"{where}, point {name!r}: pixel {pix!r} is not a finite (u, v)")
            if options.check_image_bounds and not intr.in_image(a[None])[0]:
                raise InputError(f"{where}, point {name!r}: pixel ({a[0]:.1f}, {a[1]:.1f}) is outside the "
                                 f"{intr.width}x{intr.height} image")
            if sig is not None and not (np.isfinite(sig) and sig > 0):
                raise InputError(f"{where}, point {name!r}: sigma_px = {sig!r} must be a positive number of pixels")
            names.append(name)
            vi.append(vindex[vname])
            P.append(ct.marked_points[name])
            uv.append(a)
            sc.append(1.0 if sig is None else float(sig) / options.pixel_sigma_px)
            der.append(bool(derived))
            grp.append(None if group is None else str(group))
            ld = np.full((2, 8), np.nan) if loading is None or derived else np.asarray(loading, dtype=float)
            if ld.shape != (2, 8):
                raise InputError(f"{where}, point {name!r}: its alignment loading has shape {ld.shape}, not (2, 8)")
            lds.append(ld)
            eccs.append(np.nan if ecc is None or derived else float(ecc))
            carried_fl.append(bool(carried) and bool(derived))
    body = np.array([0.0, 0.0, 0.5 * float(ct.height_m)])
    return Car(i, str(c.number), ct, names, np.asarray(vi, dtype=int), np.asarray(P, dtype=float).reshape(-1, 3),
               np.asarray(uv, dtype=float).reshape(-1, 2), sorted(set(names)), np.asarray(ct.coupler_front, float),
               np.asarray(ct.coupler_rear, float), body, np.asarray(sc, dtype=float), np.asarray(der, dtype=bool),
               grp, np.asarray(lds, dtype=float).reshape(-1, 2, 8), bool(c.on_track), np.asarray(eccs, dtype=float),
               np.asarray(carried_fl, dtype=bool))


def prepare_cars(carriages: Sequence[CarriageInput], views: Sequence[View], options: SolveOptions) -> list[Car]:
    """Check the input and flatten every carriage's observations (:class:`Car`); errors name the bad item."""
    vindex = _check_views(views)
    numbers = [str(c.number) for c in carriages]
    if len(set(numbers)) != len(numbers):
        dup = sorted({n for n in numbers if numbers.count(n) > 1})
        raise InputError(f"consist: car number(s) {dup} appear more than once")
    return [_prepare_one(i, c, views, vindex, options) for i, c in enumerate(carriages)]


def degeneracy(ct: Any, names: list[str]) -> str:
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


def carriage_weights(cars: Sequence[Car], active: Sequence[int], weighting: str = "per_carriage") -> dict[int, float]:
    """Row weight of each carriage of ``active``: ``"per_carriage"`` ``sqrt(n_mean / n_i)`` (n_i its measured
    rows, predictions not counted; 1 for all when the counts are equal), ``"per_point"`` 1 (maximum likelihood
    for independent pixel noise)."""
    if weighting == "per_point":
        return {k: 1.0 for k in active}
    if weighting != "per_carriage":
        raise SettingsError(f"solve options: weighting = {weighting!r}: must be one of {', '.join(WEIGHTINGS)}")

    def measured(c: Car) -> int:
        if c.derived is None or len(c.derived) != len(c.P):
            return len(c.P)
        return max(int(np.count_nonzero(~c.derived)), 1)

    counts = {k: measured(cars[k]) for k in active}
    nmean = float(np.mean(list(counts.values()))) if counts else 1.0
    return {k: math.sqrt(nmean / max(counts[k], 1)) for k in active}


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


# ----------------------------------------------------------------------------------------------------------
# The observation rows
# ----------------------------------------------------------------------------------------------------------
class Problem:
    """The observation rows of the carriages ``active``: which carriage and view, the point, the pixel, its
    weight (the carriage's normalisation times the point's own whitening), and whether it is a measurement."""

    def __init__(self, cars: list[Car], active: list[int], views: Sequence[View], weights: dict[int, float]):
        self.cars, self.views = cars, views
        self.active = active
        rows_car, rows_view, P, uv, w, wv, meas, grp, lds, blk, ecc, crr = ([] for _ in range(12))
        bcodes: dict[tuple, int] = {}
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
            ld = c.loadings if c.loadings is not None and len(c.loadings) == len(c.P) \
                else np.full((len(c.P), 2, 8), np.nan)
            has = np.all(np.isfinite(ld), axis=(1, 2)) & np.array([g is not None for g in gs], bool)
            lds.append(np.where(has[:, None, None], ld, 0.0))
            ecc.append(c.ecc if c.ecc is not None and len(c.ecc) == len(c.P) else np.full(len(c.P), np.nan))
            crr.append(c.carried if c.carried is not None and len(c.carried) == len(c.P) else np.zeros(len(c.P), bool))
            # one face alignment: the carriage's points of one face in one view
            blk.append(np.array([bcodes.setdefault((k, g, int(v)), len(bcodes)) if h else -1
                                 for g, v, h in zip(gs, c.views, has)], dtype=int))
        self.car = np.concatenate(rows_car) if rows_car else np.zeros(0, int)
        self.view = np.concatenate(rows_view) if rows_view else np.zeros(0, int)
        self.P = np.vstack(P) if P else np.zeros((0, 3))
        self.uv = np.vstack(uv) if uv else np.zeros((0, 2))
        self.w = np.concatenate(w) if w else np.zeros(0)  # row weights (normalisation x whitening)
        self.w_noise = np.concatenate(wv) if wv else np.zeros(0)  # sd of a weighted row / pixel sigma
        self.measured = np.concatenate(meas) if meas else np.zeros(0, bool)  # rows that carry information
        self.group = np.concatenate(grp) if grp else np.zeros(0, int)  # shared-misfit group per row, -1: none
        # each point's face alignment (carriage, face, view) and its loading (px per unit of the alignment's
        # shared standard normal), -1 and zeros where the finder gave none (uncertainty.alignment_term)
        self.block = np.concatenate(blk) if blk else np.zeros(0, int)
        self.loading = np.concatenate(lds) if lds else np.zeros((0, 2, 8))
        self.ecc = np.concatenate(ecc) if ecc else np.zeros(0)  # each row's face alignment's ECC correlation, NaN
        self.carried = np.concatenate(crr) if crr else np.zeros(0, bool)  # a prediction carried from another photo
        self.by_view = [np.nonzero(self.view == v)[0] for v in range(len(views))]
        self.by_car = {k: np.nonzero(self.car == k)[0] for k in active}

    def with_predictions_scaled(self, factor: float, cars: Sequence[int] | None = None) -> "Problem":
        """A copy whose prediction rows (``~measured``), of the carriages ``cars`` (None: all), have their sigma
        multiplied by ``factor``."""
        out = copy.copy(self)
        rows = ~self.measured if cars is None else ~self.measured & np.isin(self.car, list(cars))
        out.w = np.where(rows, self.w / float(factor), self.w)
        return out

    def subset(self, cars: list[int]) -> "Problem":
        """The rows of the carriages ``cars`` alone, with the weights they have here."""
        return Problem(self.cars, cars, self.views, {k: float(self.w_noise[self.by_car[k][0]]) for k in cars})

    def intrinsics(self, v: int, f: float) -> CameraIntrinsics:
        return self.views[v].intrinsics.with_focal(f)

    def rows_of_views(self, group: Sequence[int]) -> np.ndarray:
        """The rows seen in the views ``group`` (one focal group)."""
        return np.concatenate([self.by_view[v] for v in group]) if len(group) > 1 else self.by_view[group[0]]

    def project(self, R: np.ndarray, t: np.ndarray, f: np.ndarray, jac: bool = False):
        """Pixels (M, 2) of every row at the poses ``R, t`` and focals ``f``, the scene points (M, 3), and with
        ``jac`` d pixel / d scene point (M, 2, 3) and d pixel / d focal (M, 2)."""
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


def pixel_cost(prob: Problem, poses: Poses) -> float:
    """Half the sum of the squared weighted pixel residuals."""
    uv, *_ = prob.project(poses.R, poses.t, poses.f)
    e = (uv - prob.uv) * prob.w[:, None]
    return float(0.5 * np.sum(e * e))


def chain_cost(prob: Problem, poses: Poses, links: list[list[np.ndarray]], slacks: list[list[float]],
               prior_px: float) -> float:
    """The chained cost without the terrain term: weighted pixel residuals plus the couplers' offset prior."""
    c = pixel_cost(prob, poses)
    for Tl, sl in zip(links, slacks):
        for T, s in zip(Tl, sl):
            r = np.asarray(T) * (prior_px * SQRT5 / s)
            c += 0.5 * float(r @ r)
    return c


def pose_changes(cars: Sequence[Car], active: Sequence[int], before: Poses, after: Poses) -> list[dict]:
    """Per carriage of ``active``: how far a step moved it (m, vertical m) and turned it (deg)."""
    out = []
    for k in active:
        out.append({"number": cars[k].number, "moved_m": float(np.linalg.norm(after.t[k] - before.t[k])),
                    "dz_m": float(after.t[k][2] - before.t[k][2]),
                    "rotated_deg": rotation_angle_deg(after.R[k], before.R[k])})
    return out
