"""A carriage's place relative to the track: chainage, lateral offset and yaw (the figures a rail operator reports a
derailment in). Pure geometry, no file is read here (the railway layer is read by ``workbench/files/railways.py``).

Definitions (``docs/gis.md``, "Railway lines"); every figure is horizontal (scene east/north), heights are ignored:

* A **line** is a polyline in the scene frame (:class:`RailwayLine`); its direction is the order of its vertices.
  Its **chainage** at the first vertex is ``chainage_origin_m`` (0 unless the layer gives a ``chainage_origin``) and
  grows by the horizontal length along the line.
* The **track direction** along the line is the vertex tangents (at an inner vertex the mean of its two segments'
  directions; at an end the next vertex's tangent mirrored about the end segment) blended linearly along each
  segment, so it turns smoothly round a curve drawn as a polyline.
* A point's **foot** on the line is the nearest place of the line where the track direction is perpendicular to
  the line from it to the point (beyond either end, on the straight line on from the end vertex along its
  tangent: the position is then flagged ``beyond_end``). **Chainage** = the chainage at the foot; **lateral offset** = the horizontal distance from the
  foot, positive to the LEFT of the direction of increasing chainage. (With the plain nearest point of a polyline
  the chainage of a point 10 m off a curve drawn with 30 m chords of a 300 m radius would be up to 0.5 m off, and
  stand still over a wedge outside each vertex.)
  **Yaw relative to the track** = track bearing minus the carriage's heading, wrapped to (-180, 180]: positive when
  the carriage's front (its x axis) points to the LEFT of the direction of increasing chainage (counter-clockwise
  seen from above), about ±180 for a carriage facing against it.
* For a consist, one **reference line** is used for every carriage: the line with the smallest mean distance to
  the carriages' body centres (so all chainages are on the same line).

Uncertainty: the carriage's (east, north, heading) covariance is propagated to first order through the
numerical Jacobian of (chainage, offset, yaw); the line itself is taken as exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from typing import Sequence

import numpy as np

from .geometry import skew

__all__ = ["RailwayLine", "TrackPosition", "Foot", "reference_line", "track_position", "centre_heading_covariance",
           "wrap_deg", "bogie_pivots", "RailsCheck", "rails_check"]

_MIN_SEGMENT_M = 1e-6


def wrap_deg(a: float) -> float:
    """An angle in degrees wrapped to (-180, 180]."""
    w = math.fmod(float(a), 360.0)
    if w <= -180.0:
        w += 360.0
    elif w > 180.0:
        w -= 360.0
    return w


@dataclass(frozen=True, eq=False)
class RailwayLine:
    """One railway line in the scene frame: ``points_enu`` (n, 3) metres, n >= 2, consecutive vertices apart
    horizontally; ``id`` and ``name`` as the layer gives them; ``chainage_origin_m``: the chainage at the first
    vertex (metres; a named origin such as a kilometre post, else 0)."""

    id: str
    name: str | None
    points_enu: np.ndarray
    chainage_origin_m: float = 0.0
    properties: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        P = np.asarray(self.points_enu, dtype=float)
        if P.ndim != 2 or P.shape[1] != 3 or len(P) < 2:
            raise ValueError(f"line {self.id}: points_enu.shape={P.shape}; expected (n >= 2, 3)")
        if not np.all(np.isfinite(P)):
            raise ValueError(f"line {self.id}: a vertex is not finite")
        if np.any(np.linalg.norm(np.diff(P[:, :2], axis=0), axis=1) < _MIN_SEGMENT_M):
            raise ValueError(f"line {self.id}: two consecutive vertices at the same place")
        if not math.isfinite(float(self.chainage_origin_m)):
            raise ValueError(f"line {self.id}: chainage_origin_m is not finite")
        object.__setattr__(self, "points_enu", P)
        object.__setattr__(self, "chainage_origin_m", float(self.chainage_origin_m))

    @property
    def label(self) -> str:
        return f"{self.name} ({self.id})" if self.name else self.id

    @cached_property
    def _segments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(a (m, 2) segment starts, d (m, 2) segment vectors, length (m,), cumulative length at each vertex (m+1,))."""
        xy = self.points_enu[:, :2]
        d = np.diff(xy, axis=0)
        L = np.linalg.norm(d, axis=1)
        return xy[:-1], d, L, np.concatenate([[0.0], np.cumsum(L)])

    @cached_property
    def _vertex_tangents(self) -> np.ndarray:
        """(n, 2) unit tangents at the vertices: at an inner vertex the mean of its two segments' directions; at an
        end the next vertex's tangent mirrored about the end segment (so a curve keeps turning to its end; the end
        segment's direction on a line of two vertices)."""
        _, d, L, _ = self._segments
        u = d / L[:, None]
        inner = u[:-1] + u[1:]
        n = np.linalg.norm(inner, axis=1)
        inner = np.where(n[:, None] > 1e-9, inner / np.maximum(n, 1e-300)[:, None], u[:-1])  # a hairpin: incoming
        if len(inner) == 0:
            return np.vstack([u[:1], u[-1:]])

        def mirrored(t: np.ndarray, axis: np.ndarray) -> np.ndarray:
            return 2.0 * float(t @ axis) * axis - t

        return np.vstack([mirrored(inner[0], u[0]), inner, mirrored(inner[-1], u[-1])])

    @property
    def length_m(self) -> float:
        return float(self._segments[3][-1])

    def rail_polyline(self, offset_m: float = 0.0, step_m: float = 0.5) -> np.ndarray:
        """(k, 3) the line offset horizontally by ``offset_m`` (positive to the LEFT of the direction of increasing
        chainage: a rail at half the gauge), each vertex moved along the left normal of its track direction (the
        blended vertex tangent), heights kept; densified to at most ``step_m`` between consecutive points (linear
        between vertices: a chord of the curve as drawn)."""
        T = self._vertex_tangents
        left = np.column_stack([-T[:, 1], T[:, 0]])
        P = self.points_enu.copy()
        P[:, :2] += float(offset_m) * left
        out = [P[:1]]
        for a, b in zip(P[:-1], P[1:]):
            n = max(1, int(math.ceil(float(np.linalg.norm(b[:2] - a[:2])) / float(step_m))))
            t = (np.arange(1, n + 1) / n)[:, None]
            out.append(a + t * (b - a))
        return np.vstack(out)

    def at(self, chainage_m: float) -> tuple[np.ndarray, float]:
        """(east/north (2,), compass bearing of the track direction) at ``chainage_m`` (clamped to the line)."""
        a, d, L, cum = self._segments
        s = float(np.clip(chainage_m - self.chainage_origin_m, 0.0, cum[-1]))
        i = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(L) - 1))
        t = (s - cum[i]) / L[i]
        T = self._vertex_tangents
        tan = (1.0 - t) * T[i] + t * T[i + 1]
        return a[i] + t * d[i], math.degrees(math.atan2(tan[0], tan[1])) % 360.0

    def _candidates(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every place on the line where the track direction is perpendicular to the line to ``p``: on segment i,
        ``(p - a_i - t d_i) . ((1 - t) T_i + t T_i+1) = 0`` (a quadratic in t), t in [0, 1]; and beyond either end,
        on the straight line from the end vertex along its tangent. Returns (foot (k, 2), length along the line
        from its first vertex (k,), unit direction there (k, 2), beyond an end (k,) bool)."""
        a, d, L, cum = self._segments
        T = self._vertex_tangents
        r = p - a
        dT = T[1:] - T[:-1]
        A = -np.einsum("ij,ij->i", d, dT)
        B = np.einsum("ij,ij->i", r, dT) - np.einsum("ij,ij->i", d, T[:-1])
        C = np.einsum("ij,ij->i", r, T[:-1])
        seg, ts = [], []
        with np.errstate(divide="ignore", invalid="ignore"):
            disc = B * B - 4.0 * A * C
            sq = np.sqrt(np.maximum(disc, 0.0))
            qq = -0.5 * (B + np.where(B >= 0.0, sq, -sq))
            lin = np.abs(A) <= 1e-12 * np.maximum(np.abs(B), 1e-300)
            roots = [np.where(lin, -C / B, qq / A), np.where(lin, np.nan, C / qq)]
        for root in roots:
            ok = (disc >= 0.0) & np.isfinite(root) & (root >= -1e-12) & (root <= 1.0 + 1e-12)
            seg.append(np.nonzero(ok)[0])
            ts.append(np.clip(root[ok], 0.0, 1.0))
        i = np.concatenate(seg).astype(int)
        t = np.concatenate(ts)
        tan = (1.0 - t)[:, None] * T[i] + t[:, None] * T[i + 1]
        tan /= np.maximum(np.linalg.norm(tan, axis=1), 1e-300)[:, None]
        feet, along, dirs, beyond = [a[i] + t[:, None] * d[i]], [cum[i] + t * L[i]], [tan], [np.zeros(len(i), bool)]
        xy = self.points_enu[:, :2]
        for k, sign, base in ((0, -1.0, 0.0), (len(xy) - 1, 1.0, float(cum[-1]))):
            s = float((p - xy[k]) @ T[k])
            if sign * s > 0.0:
                feet.append((xy[k] + s * T[k])[None])
                along.append(np.array([base + s]))
                dirs.append(T[k][None])
                beyond.append(np.array([True]))
        return np.vstack(feet), np.concatenate(along), np.vstack(dirs), np.concatenate(beyond)

    def offset_and_normal(self, xy: np.ndarray) -> tuple[float, np.ndarray]:
        """The point ``xy`` (2,)'s signed offset from the line (m, left positive) and the line's left unit normal at
        its foot (2,): the offset's derivative with respect to the point."""
        f = self.foot(xy)
        b = math.radians(f.bearing_deg)
        return f.offset_m, np.array([-math.cos(b), math.sin(b)])  # left of the direction (sin b, cos b)

    def foot(self, xy: np.ndarray) -> "Foot":
        """Where the point ``xy`` (2,) meets the line (see :class:`Foot`): the nearest of the places where the track
        direction (the vertex tangents blended along each segment) is perpendicular to the line to the point, so
        that chainage runs on smoothly round a curve drawn as a polyline; the nearest point of the polyline when
        there is no such place."""
        p = np.asarray(xy, dtype=float).reshape(2)
        q, along, tan, beyond = self._candidates(p)
        if len(q) == 0:  # e.g. the point at a curve's centre: the nearest point of the polyline
            a, d, L, cum = self._segments
            t = np.clip(np.einsum("ij,ij->i", p - a, d) / (L * L), 0.0, 1.0)
            q, along, tan, beyond = a + t[:, None] * d, cum[:-1] + t * L, d / L[:, None], np.zeros(len(L), bool)
        dist = np.linalg.norm(p - q, axis=1)
        k = int(np.argmin(dist))
        r = p - q[k]
        side = tan[k, 0] * r[1] - tan[k, 1] * r[0]  # > 0: left of the direction of the line
        offset = float(dist[k]) if side >= 0.0 else -float(dist[k])
        return Foot(chainage_m=self.chainage_origin_m + float(along[k]), offset_m=offset,
                    bearing_deg=math.degrees(math.atan2(tan[k, 0], tan[k, 1])) % 360.0, xy=q[k].copy(),
                    beyond_end=bool(beyond[k]))


@dataclass(frozen=True)
class Foot:
    """Where a point meets a line: ``chainage_m`` there, the point's signed ``offset_m`` (left positive), the
    track's compass ``bearing_deg`` there, the foot ``xy`` (2,) and whether it lies beyond an end of the line
    (``beyond_end``)."""

    chainage_m: float
    offset_m: float
    bearing_deg: float
    xy: np.ndarray
    beyond_end: bool


@dataclass(frozen=True)
class TrackPosition:
    """A carriage's place relative to a line (definitions in the module docstring). ``sigma_*``: 1-sigma,
    ``ci95_*``: 95 % half widths (``ci95_factor`` sigmas), None where no uncertainty was given."""

    line_id: str
    line_name: str | None
    chainage_m: float
    offset_m: float
    yaw_deg: float
    track_bearing_deg: float
    beyond_end: bool
    sigma_chainage_m: float | None = None
    sigma_offset_m: float | None = None
    sigma_yaw_deg: float | None = None
    ci95_factor: float = 1.96

    def ci95(self, name: str) -> float | None:
        """The 95 % half width of ``chainage_m``, ``offset_m`` or ``yaw_deg``."""
        s = getattr(self, "sigma_" + name)
        return None if s is None else self.ci95_factor * s

    def to_dict(self, decimals: int = 4) -> dict:
        """JSON-ready: the figures, their 1-sigma and 95 % half widths, the line."""
        def r(x):
            return None if x is None else round(float(x), decimals)

        return {"line_id": self.line_id, "line_name": self.line_name, "chainage_m": r(self.chainage_m),
                "offset_m": r(self.offset_m), "yaw_deg": r(self.yaw_deg), "track_bearing_deg": r(self.track_bearing_deg),
                "beyond_end": self.beyond_end, "sigma_chainage_m": r(self.sigma_chainage_m),
                "sigma_offset_m": r(self.sigma_offset_m), "sigma_yaw_deg": r(self.sigma_yaw_deg),
                "ci95_chainage_m": r(self.ci95("chainage_m")),
                "ci95_offset_m": r(self.ci95("offset_m")), "ci95_yaw_deg": r(self.ci95("yaw_deg"))}


def reference_line(lines: Sequence[RailwayLine], centres_xy: np.ndarray) -> RailwayLine:
    """The line with the smallest mean horizontal distance to the points ``centres_xy`` (k, 2) (the first such)."""
    if not lines:
        raise ValueError("no railway lines")
    C = np.asarray(centres_xy, dtype=float).reshape(-1, 2)
    if len(C) == 0:
        return lines[0]
    best, best_d = lines[0], math.inf
    for line in lines:
        d = float(np.mean([abs(line.foot(c).offset_m) for c in C]))
        if d < best_d - 1e-9:
            best, best_d = line, d
    return best


def _figures(line: RailwayLine, x: np.ndarray) -> np.ndarray:
    """(chainage m, offset m, yaw deg) of (east, north, heading deg)."""
    f = line.foot(x[:2])
    return np.array([f.chainage_m, f.offset_m, wrap_deg(f.bearing_deg - x[2])])


def track_position(line: RailwayLine, centre_xy: np.ndarray, heading_deg: float, cov_enh: np.ndarray | None = None,
                   *, ci95_factor: float = 1.96, step_m: float = 0.01) -> TrackPosition:
    """The place of a carriage (body centre ``centre_xy`` (2,), compass ``heading_deg``) relative to ``line``.

    ``cov_enh`` (3, 3): covariance of (east m, north m, heading deg); propagated through the numerical Jacobian
    (central differences, ``step_m`` and ``step_m`` degrees) to the 1-sigma of chainage, offset and yaw."""
    x = np.array([float(centre_xy[0]), float(centre_xy[1]), float(heading_deg)])
    f = line.foot(x[:2])
    yaw = wrap_deg(f.bearing_deg - x[2])
    s = [None, None, None]
    if cov_enh is not None:
        C = np.asarray(cov_enh, dtype=float)
        if C.shape == (3, 3) and np.all(np.isfinite(C)):
            J = np.zeros((3, 3))
            for k in range(3):
                e = np.zeros(3)
                e[k] = step_m
                diff = _figures(line, x + e) - _figures(line, x - e)
                diff[2] = wrap_deg(diff[2])
                J[:, k] = diff / (2.0 * step_m)
            var = np.diag(J @ C @ J.T)
            s = [float(math.sqrt(max(v, 0.0))) for v in var]
    return TrackPosition(line_id=line.id, line_name=line.name, chainage_m=f.chainage_m, offset_m=f.offset_m,
                         yaw_deg=yaw, track_bearing_deg=f.bearing_deg, beyond_end=f.beyond_end,
                         sigma_chainage_m=s[0], sigma_offset_m=s[1], sigma_yaw_deg=s[2], ci95_factor=float(ci95_factor))


def centre_heading_covariance(world_from_carriage: np.ndarray, body_centre_enu: np.ndarray,
                              covariance_pose: np.ndarray) -> np.ndarray:
    """(3, 3) covariance of (east m, north m, heading deg) of a carriage's body centre and heading, from its pose
    covariance ``covariance_pose`` (6, 6: the scene rotation vector in rad, then the origin in m, as the solve
    writes it: ``R' = exp(omega) R``, ``t' = t + dt``)."""
    M = np.asarray(world_from_carriage, dtype=float)
    R, t = M[:3, :3], M[:3, 3]
    lever = np.asarray(body_centre_enu, dtype=float) - t
    Jc = np.hstack([-skew(lever), np.eye(3)])[:2]  # d(body centre east, north) / d(omega, t)
    a = R[:, 0]  # the carriage's x axis; heading = atan2(a_e, a_n); da = omega x a = -skew(a) omega
    da = -skew(a)
    h2 = a[0] ** 2 + a[1] ** 2
    if h2 < 1e-12:  # standing on its end: the heading is undefined
        dh = np.full(3, np.nan)
    else:
        dh = (a[1] * da[0] - a[0] * da[1]) / h2
    Jh = np.concatenate([np.degrees(dh), np.zeros(3)])
    J = np.vstack([Jc, Jh])
    return J @ np.asarray(covariance_pose, dtype=float) @ J.T


def bogie_pivots(ctype) -> np.ndarray:
    """(2, 3) the front and rear bogie pivots of a carriage type (``rolling_stock.CarriageType``) in its frame:
    ``(+-bogie_centres_m / 2, 0, 0)``, metres, top of rail (a type without bogie centres: a third of its length)."""
    d = getattr(getattr(ctype, "spec", None), "dimensions", None)
    c = getattr(d, "bogie_centres_m", None)
    half = 0.5 * float(c) if c else float(ctype.length_m) / 3.0
    return np.array([[half, 0.0, 0.0], [-half, 0.0, 0.0]])


@dataclass(frozen=True)
class RailsCheck:
    """Whether a solved carriage may stand on the rails of ``line_id``: its bogie pivots' lateral offsets (m, left
    positive, front then rear), their 1-sigma from the pose's covariance and the line's own, the chi-square of both
    offsets being 0 (2 degrees of freedom), ``consistent`` when that chi-square is under its 95 % point (5.99), and
    ``decided``: off the rails (not consistent), or on them with each offset's 95 % half width under
    ``resolution_m`` (a consistent but wide interval settles nothing)."""

    line_id: str
    offsets_m: tuple[float, float]
    sigma_m: tuple[float, float]
    chi2: float
    consistent: bool
    decided: bool

    def to_dict(self) -> dict:
        return {"line_id": self.line_id, "offsets_m": [round(x, 4) for x in self.offsets_m],
                "sigma_m": [round(x, 4) for x in self.sigma_m], "chi2": round(self.chi2, 3),
                "consistent": self.consistent, "decided": self.decided, "verdict": self.verdict}

    @property
    def verdict(self) -> str:
        """``"no"`` (the offsets reject the rails), ``"yes"`` (on them, to ``resolution_m``) or ``"cannot tell"``."""
        return "no" if not self.consistent else ("yes" if self.decided else "cannot tell")


def rails_check(line: RailwayLine, world_from_carriage: np.ndarray, pivots: np.ndarray,
                covariance_pose: np.ndarray | None, line_sigma_m: float, resolution_m: float = 0.5,
                common_cov_en: np.ndarray | None = None) -> RailsCheck:
    """Test a solved carriage (``world_from_carriage`` (4, 4), its bogie ``pivots`` (2, 3) in the carriage frame,
    ``covariance_pose`` (6, 6) rotation vector then origin, or None) against standing on ``line`` (accurate to
    ``line_sigma_m`` at each pivot). ``common_cov_en`` (2, 2): a horizontal error shared by the whole carriage
    (the camera's georeference), m^2."""
    M = np.asarray(world_from_carriage, dtype=float)
    R, t = M[:3, :3], M[:3, 3]
    q = np.asarray(pivots, dtype=float) @ R.T
    off, J, Nh = np.zeros(2), np.zeros((2, 6)), np.zeros((2, 2))
    for i in range(2):
        off[i], Nh[i] = line.offset_and_normal((q[i] + t)[:2])
        n = np.append(Nh[i], 0.0)
        J[i] = np.concatenate([np.cross(q[i], n), n])  # d offset / d (omega, t): R' = exp(omega) R
    C = np.eye(2) * float(line_sigma_m) ** 2
    if covariance_pose is not None:
        C = C + J @ np.asarray(covariance_pose, dtype=float) @ J.T
    if common_cov_en is not None:
        C = C + Nh @ np.asarray(common_cov_en, dtype=float) @ Nh.T
    sd = np.sqrt(np.diag(C))
    chi2 = float(off @ np.linalg.solve(C, off))
    consistent = chi2 <= 5.991
    decided = bool(not consistent or np.all(1.96 * sd <= resolution_m))
    return RailsCheck(line.id, (float(off[0]), float(off[1])), (float(sd[0]), float(sd[1])), chi2, bool(consistent),
                      decided)
