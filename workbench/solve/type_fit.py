"""A carriage type's uncertain dimensions measured from photos of intact cars of the class (docs/rolling_stock.md,
"Measuring a type from photos").

A type written for a real incident has published figures (length, width, bogie centres) and others estimated
(a cab's window line, the eave, the body's bottom edge). Photos of undamaged cars of the same class, with their
marked points picked by hand, measure the estimated ones: every photo gets its own focal (unknown, no EXIF
needed) and every car its own pose; the chosen dimensions are shared by all of them and fitted with the rest by
least squares. The published dimensions fix the scale, so a dimension is measured against them (through the
photos' perspective, which a telephoto photo has little of: only ratios are well determined).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Sequence

import cv2
import numpy as np
from scipy.optimize import least_squares

from ..core.camera import CameraIntrinsics
from ..core.geometry import exp_so3
from ..errors import InputError, SettingsError
from ..rolling_stock.geometry import anchor_point

log = logging.getLogger(__name__)

__all__ = ["PhotoPicks", "TypeFit", "FITTABLE", "fit_type_dimensions", "photo_intrinsics", "project_picks",
           "type_points"]

# the dimensions a fit may free: section of the type file -> keys (metres)
FITTABLE = {
    "dimensions": ("body_length_m", "width_m", "height_m", "body_bottom_m", "floor_height_m", "coupler_height_m"),
    "profile": ("eave_height_m", "roof_edge_inset_m", "bottom_inset_m"),
    "front": ("nose_base_height_m", "nose_setback_m", "corner_setback_m"),
    "rear": ("nose_base_height_m", "nose_setback_m", "corner_setback_m"),
}


@dataclass(frozen=True)
class PhotoPicks:
    """One car's picks in one photo: ``view`` the photo's name, ``size`` (width, height) px, ``car`` its number,
    ``points`` marked-point name -> (u, v) px."""

    view: str
    size: tuple[int, int]
    car: str
    points: dict[str, tuple[float, float]]


@dataclass
class TypeFit:
    """The fitted dimensions ``values`` (key -> m) with ``sigmas`` (1-sigma, m) and the type's ``before``; each
    photo's ``focal_px`` and horizontal field of view ``hfov_deg``; the residuals ``residuals_px`` (photo ->
    car -> point -> (du, dv), observed minus model) and their ``rms_px`` (per point, the norm); ``sigma_px`` the
    pixel sigma the residuals give (``dof`` degrees of freedom)."""

    type_id: str
    values: dict[str, float]
    sigmas: dict[str, float]
    before: dict[str, float]
    focal_px: dict[str, float]
    hfov_deg: dict[str, float]
    rms_px: float
    sigma_px: float
    dof: int
    n_picks: int
    residuals_px: dict[str, dict[str, dict[str, tuple[float, float]]]] = field(default_factory=dict)
    correlation: list[list[float]] = field(default_factory=list)

    def to_json(self) -> dict:
        return {"type": self.type_id, "dimensions": {k: {"value_m": self.values[k], "sigma_m": self.sigmas[k],
                                                         "before_m": self.before[k]} for k in self.values},
                "correlation": self.correlation, "focal_px": self.focal_px, "hfov_deg": self.hfov_deg,
                "rms_px": self.rms_px, "sigma_px": self.sigma_px, "dof": self.dof, "n_picks": self.n_picks,
                "residuals_px": self.residuals_px,
                "note": "principal point at the photo's centre, no distortion, square pixels; each photo its own "
                        "focal, each car its own pose; the other dimensions as the type file gives them"}


def _split(key: str) -> tuple[str, str]:
    sec, _, name = key.partition(".")
    if sec not in FITTABLE or name not in FITTABLE[sec]:
        valid = ", ".join(f"{s}.{k}" for s, ks in FITTABLE.items() for k in ks)
        raise SettingsError(f"type fit: {key!r} is not a dimension that can be fitted; give one of {valid}")
    return sec, name


def _spec_with(spec, values: dict[str, float]):
    upd: dict[str, dict] = {}
    for key, v in values.items():
        sec, name = _split(key)
        upd.setdefault(sec, {})[name] = float(v)
    return spec.model_copy(update={sec: getattr(spec, sec).model_copy(update=kv) for sec, kv in upd.items()})


def type_points(ctype, values: dict[str, float]) -> dict[str, np.ndarray]:
    """The type's marked points (carriage frame, m) with the dimensions ``values`` (``section.key`` -> m)."""
    spec = _spec_with(ctype.spec, values)
    out = {}
    for mp in spec.marked_points:
        out[mp.name] = anchor_point(spec, mp.anchor)[0] if mp.anchor is not None else np.asarray(mp.xyz, float)
    return out


def photo_intrinsics(size: tuple[int, int], f: float) -> CameraIntrinsics:
    """A photo of ``size`` (width, height) px with focal ``f`` px, the principal point at its centre."""
    w, h = size
    return CameraIntrinsics(width=int(w), height=int(h), fx=f, fy=f, cx=(w - 1) / 2.0, cy=(h - 1) / 2.0)


def _pnp(P: np.ndarray, uv: np.ndarray, intr: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray, float]:
    flag = cv2.SOLVEPNP_SQPNP if len(P) >= 3 else cv2.SOLVEPNP_ITERATIVE
    ok, rvec, tvec = cv2.solvePnP(P.astype(np.float64), uv.astype(np.float64), intr.K, None, flags=flag)
    if not ok:
        return np.zeros(3), np.array([0.0, 0.0, 100.0]), math.inf
    proj, _ = cv2.projectPoints(P, rvec, tvec, intr.K, None)
    err = float(np.sum((proj.reshape(-1, 2) - uv) ** 2))
    return rvec.ravel(), tvec.ravel(), err


def _start(picks: Sequence[PhotoPicks], pts: dict[str, np.ndarray], views: list[str],
           hfov_range_deg: tuple[float, float]) -> tuple[np.ndarray, list[np.ndarray]]:
    """Each photo's focal (the best of a sweep over the field of view) and each car's PnP pose at it."""
    f0, poses = np.zeros(len(views)), [None] * len(picks)
    lo, hi = (math.radians(x) for x in hfov_range_deg)
    grid = np.exp(np.linspace(math.log(lo), math.log(hi), 60))
    for j, v in enumerate(views):
        idx = [i for i, p in enumerate(picks) if p.view == v]
        w = picks[idx[0]].size[0]
        best = (math.inf, None, None)
        for hf in grid:
            f = 0.5 * w / math.tan(0.5 * hf)
            intr = photo_intrinsics(picks[idx[0]].size, f)
            sols = [_pnp(np.array([pts[n] for n in picks[i].points]), np.array(list(picks[i].points.values())),
                         intr) for i in idx]
            err = sum(s[2] for s in sols)
            if err < best[0]:
                best = (err, f, sols)
        f0[j] = best[1]
        for i, s in zip(idx, best[2]):
            poses[i] = np.concatenate([s[0], s[1]])
    return f0, poses


def fit_type_dimensions(ctype, picks: Sequence[PhotoPicks], free: Sequence[str],
                        hfov_range_deg: tuple[float, float] = (3.0, 120.0)) -> TypeFit:
    """Fit the type's dimensions ``free`` (``section.key``, see :data:`FITTABLE`) to hand picks of its marked
    points on photos of intact cars (:class:`PhotoPicks`, at least 4 points a car), every photo's focal and every
    car's pose with them. Raises :class:`InputError` when the picks cannot determine them."""
    free = list(dict.fromkeys(free))
    if not free:
        raise SettingsError("type fit: name at least one dimension to fit (e.g. profile.eave_height_m)")
    for k in free:
        _split(k)
    before = {k: float(getattr(getattr(ctype.spec, _split(k)[0]), _split(k)[1])) for k in free}
    for p in picks:
        unknown = sorted(set(p.points) - set(ctype.marked_points))
        if unknown:
            raise InputError(f"type fit: car {p.car} in {p.view}: {', '.join(unknown)} not marked points of "
                             f"{ctype.id} (it has {', '.join(sorted(ctype.marked_points))})")
        if len(p.points) < 4:
            raise InputError(f"type fit: car {p.car} in {p.view} has {len(p.points)} picks; a pose needs at least 4")
    views = list(dict.fromkeys(p.view for p in picks))
    n_obs = sum(len(p.points) for p in picks)
    n_par = len(views) + 6 * len(picks) + len(free)
    if 2 * n_obs <= n_par:
        raise InputError(f"type fit: {n_obs} picks give {2 * n_obs} numbers for {n_par} unknowns (a focal per "
                         f"photo, a pose per car, {len(free)} dimensions): pick more points or free fewer dimensions")
    f0, poses0 = _start(picks, type_points(ctype, before), views, hfov_range_deg)
    x0 = np.concatenate([np.log(f0), *poses0, [before[k] for k in free]])
    uv_obs = [np.array(list(p.points.values()), float) for p in picks]
    vix = [views.index(p.view) for p in picks]

    def model(x: np.ndarray) -> list[np.ndarray]:
        pts = type_points(ctype, dict(zip(free, x[len(views) + 6 * len(picks):])))
        out = []
        for i, p in enumerate(picks):
            q = x[len(views) + 6 * i: len(views) + 6 * i + 6]
            P = np.array([pts[n] for n in p.points]) @ exp_so3(q[:3]).T + q[3:]
            out.append(photo_intrinsics(p.size, float(np.exp(x[vix[i]]))).project(P))
        return out

    def resid(x: np.ndarray) -> np.ndarray:
        return np.concatenate([(m - o).ravel() for m, o in zip(model(x), uv_obs)])

    sol = least_squares(resid, x0, x_scale="jac", method="trf")
    r = sol.fun
    dof = 2 * n_obs - n_par
    s2 = float(r @ r) / dof
    J = sol.jac
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        raise InputError("type fit: the picks do not determine the dimensions (a singular fit): pick points that "
                         "the dimensions move (e.g. the top and the bottom of a side) on more photos") from None
    k0 = len(views) + 6 * len(picks)
    C = cov[k0:, k0:]
    sd = np.sqrt(np.clip(np.diag(C), 0.0, None))
    corr = (C / np.outer(sd, sd)).round(3).tolist() if np.all(sd > 0) else []
    resid_map: dict[str, dict[str, dict[str, tuple[float, float]]]] = {}
    for p, m, o in zip(picks, model(sol.x), uv_obs):
        d = o - m
        resid_map.setdefault(p.view, {})[p.car] = {n: (float(a), float(b)) for n, (a, b) in zip(p.points, d)}
    focal = {v: float(np.exp(sol.x[j])) for j, v in enumerate(views)}
    width = {p.view: p.size[0] for p in picks}
    pts_r = r.reshape(-1, 2)
    return TypeFit(ctype.id, {k: float(v) for k, v in zip(free, sol.x[k0:])}, {k: float(s) for k, s in zip(free, sd)},
                   before, focal, {v: math.degrees(2 * math.atan(0.5 * width[v] / f)) for v, f in focal.items()},
                   float(np.sqrt(np.mean(np.sum(pts_r**2, axis=1)))), math.sqrt(s2), dof, n_obs, resid_map, corr)


def project_picks(project, type_id: str | None = None) -> tuple[object, list[PhotoPicks]]:
    """The hand picks of an incident folder whose cars are all of one type (``type_id``, or the consist's only
    type): its ``correspondences.json`` (manual points) and its photos' sizes."""
    from ..files.correspondences import load
    from ..files.intrinsics import photo_size

    types = project.carriage_types()
    by_type = {t.id for t in types.values()}
    if type_id is None:
        if len(by_type) != 1:
            raise InputError(f"{project.settings_path}: the consist has the types {', '.join(sorted(by_type))}; "
                             "name the one to fit (--type)")
        type_id = next(iter(by_type))
    cars = [n for n, t in types.items() if t.id == type_id]
    if not cars:
        raise InputError(f"{project.settings_path}: no car of type {type_id!r} in the consist")
    ctype = types[cars[0]]
    photos = {p.name: p for p in project.photo_paths_if_any()}
    path = project.manual_picks_path
    if not path.is_file():
        raise InputError(f"{path}: not found; pick the cars' marked points first (workbench pick "
                         f"{project.root})")
    sizes = {n: photo_size(p) for n, p in photos.items()}
    cf = load(path, points={n: list(t.marked_points) for n, t in types.items()}, image_sizes=sizes)
    groups: dict[tuple[str, str], dict[str, tuple[float, float]]] = {}
    for o in cf.observations:
        if o.source == "manual" and o.carriage in cars:
            if o.view not in sizes:
                raise InputError(f"{path}: {o.view!r} is not a photo of the incident ({project.root / 'photos'})")
            groups.setdefault((o.view, o.carriage), {})[o.point] = (float(o.uv[0]), float(o.uv[1]))
    picks = [PhotoPicks(v, sizes[v], c, pts) for (v, c), pts in sorted(groups.items())]
    if not picks:
        raise InputError(f"{path}: no hand pick of a {type_id} car")
    return ctype, picks
