"""Points picked on the railway track in the photos as a georeferencing feature (``track_picks`` in
``control_points.json``; docs/gis.md, "Track picks").

A track pick is a pixel anywhere on one line of the track (its centre line, or the left or right rail at
``(gauge + rail head) / 2`` from it), not matched to a place on the line. Its residual is its **signed distance to
the line projected into the photo**: the line (``RailwayLine.rail_polyline``, densified to
:data:`STEP_M`) is put in the camera frame, cut where it passes behind the camera (depth under :data:`NEAR_M`),
projected by the pinhole (no distortion: the pick is undistorted instead, so a chord of the line stays straight),
and the pick's distance to the nearest projected segment, in the undistorted normalised plane, is multiplied by
the focal (px; within a few per cent of the distance in the photo as it is, the lens's local scale). The sign is
the side of the line (the segment's direction crossed with the pick's), so the residual is smooth across the line.

Why this residual: it is what a pick measures (the direction across the line in the photo; along the line a pick
says nothing), in pixels, so it takes the pick's noise ``sigma_px`` directly and sits in the same weighted least
squares as the control points' reprojection errors. The line's own error (its map position, ``line_sigma_m``
horizontally and ``height_sigma_m`` vertically) is seen at the depth of the nearest line point and added to the
pick's sigma as for a control point (:func:`~workbench.georef.picks.pick_sigma`); it is one error shared by every
pick of that line (a whole line shifted), which the camera's covariance counts once (``central.py``).

What track picks fix: a straight line seen in a photo is an image line (2 numbers); two rails at a known gauge
add the scale (4 numbers); a horizontal curve adds its bend (5 of the camera's 6 unknowns). They never fix the
camera's place along a track that is straight, or circular with a constant grade (a helix is the same seen from
anywhere along it): that needs something else (control points, the photos' GPS, ``camera.position_enu``).
:func:`track_observability` measures it at the solution.
"""

from __future__ import annotations

import logging
import math
import warnings
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from ..core.track import RailwayLine
from ..errors import InputError
from ..files.control_points import TrackPick
from .options import GeorefOptions, GeorefResidualsLarge

log = logging.getLogger(__name__)

__all__ = ["TrackObservation", "TrackTerm", "build_track_term", "track_rotation_candidates", "track_observability",
           "track_inliers", "track_fit_stats", "STEP_M", "NEAR_M"]

STEP_M = 0.5  # the line is densified to this before projection (a 1 m chord of a 300 m curve is 0.4 mm off)
NEAR_M = 0.5  # line points nearer than this in depth are cut (the line passing behind the camera)
MAX_RANGE_M = 1500.0  # line points farther than this from the scene origin are not used
_NO_LINE_PX = 200.0  # the residual of a pick when its line projects nowhere in front of the camera


@dataclass(frozen=True)
class TrackObservation:
    """The picks ``uv`` (n, 2) of one line of the track in view ``view``; ``xy`` (n, 2): their undistorted
    normalised coordinates; ``line_enu`` (m, 3): that line (rail or centre) in the scene frame, densified."""

    view: int
    photo: str
    line_id: str
    rail: str
    uv: np.ndarray
    xy: np.ndarray
    line_enu: np.ndarray


@dataclass(frozen=True)
class TrackTerm:
    """The track picks of a central rig, their noise and their lines' error (1-sigma, metres)."""

    obs: tuple[TrackObservation, ...]
    sigma_px: float
    line_sigma_m: tuple[float, ...]  # per observation: the horizontal 1-sigma of its line's position
    height_sigma_m: tuple[float, ...]  # per observation: the vertical 1-sigma of its line's heights

    @property
    def n(self) -> int:
        return int(sum(len(o.uv) for o in self.obs))

    def pick_index(self) -> np.ndarray:
        """(n,) the observation each pick belongs to."""
        return np.concatenate([np.full(len(o.uv), k) for k, o in enumerate(self.obs)]) if self.obs \
            else np.zeros(0, int)

    def line_groups(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """[(pick indices, (3,) 1-sigma east/north/up of the line's shift)] per railway line: one shared error."""
        k = self.pick_index()
        out = []
        for lid in sorted({o.line_id for o in self.obs}):
            ks = [i for i, o in enumerate(self.obs) if o.line_id == lid]
            s = np.array([self.line_sigma_m[ks[0]]] * 2 + [self.height_sigma_m[ks[0]]], float)
            out.append((np.nonzero(np.isin(k, ks))[0], s))
        return out

    def errors(self, R: np.ndarray, c: np.ndarray, views: Sequence,
               segments: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(signed residual px (n,), depth m of the nearest line point (n,)) at ``rig_from_world`` R and centre c;
        ``nan`` where the line projects nowhere in front of the camera. ``segments`` (from :meth:`nearest`): each
        pick measured to that segment of its line, not to the nearest one (the Jacobian's differences)."""
        res, depth = [], []
        for k, o in enumerate(self.obs):
            v = views[o.view]
            cam_from_world = np.asarray(v.cam_from_rig, float) @ R
            if segments is None:
                q = (o.line_enu - c) @ cam_from_world.T
                r, d, _ = _signed_distances(o.xy, q)
            else:
                s = segments[k]
                ends = np.concatenate([s, s + 1])
                q = (o.line_enu[ends] - c) @ cam_from_world.T
                r, d = _fixed_distances(o.xy, q[:len(s)], q[len(s):])
            f = 0.5 * (v.intrinsics.fx + v.intrinsics.fy)
            res.append(f * r)
            depth.append(d)
        if not res:
            return np.zeros(0), np.zeros(0)
        return np.concatenate(res), np.concatenate(depth)

    def nearest(self, R: np.ndarray, c: np.ndarray, views: Sequence) -> list[np.ndarray]:
        """Per observation, the index of the segment of its line nearest to each pick (0 where none)."""
        out = []
        for o in self.obs:
            cam_from_world = np.asarray(views[o.view].cam_from_rig, float) @ R
            out.append(_signed_distances(o.xy, (o.line_enu - c) @ cam_from_world.T)[2])
        return out

    def sigmas(self, depth: np.ndarray, views: Sequence) -> np.ndarray:
        """(n,) each pick's 1-sigma (px): its noise and its line's position error (the larger of the horizontal
        and vertical one) seen at ``depth``."""
        out = []
        for o, hs, vs in zip(self.obs, self.line_sigma_m, self.height_sigma_m):
            intr = views[o.view].intrinsics
            out.append(np.full(len(o.uv), 0.5 * (intr.fx + intr.fy) * max(hs, vs)))
        f_sig = np.concatenate(out) if out else np.zeros(0)
        d = np.where(np.isfinite(depth), np.maximum(depth, 1e-3), np.inf)
        return np.sqrt(self.sigma_px ** 2 + (f_sig / d) ** 2)

    def whitened(self, R: np.ndarray, c: np.ndarray, views: Sequence, use: np.ndarray, sig: np.ndarray,
                 segments: list[np.ndarray] | None = None) -> np.ndarray:
        """The residual rows of the picks ``use`` divided by their ``sig`` (``segments``: as :meth:`errors`)."""
        r, _ = self.errors(R, c, views, segments)
        r = np.where(np.isfinite(r), r, _NO_LINE_PX)
        return r[use] / sig[use]

    def perturbed(self, rng: np.random.Generator, sig_px: np.ndarray, views: Sequence) -> "TrackTerm":
        """The same picks each moved by Gaussian noise of ``sig_px`` (n,) (the re-solves of the sampled
        covariance)."""
        out, k = [], 0
        for o in self.obs:
            m = len(o.uv)
            uv = o.uv + rng.normal(0.0, 1.0, (m, 2)) * sig_px[k:k + m, None]
            out.append(replace(o, uv=uv, xy=_normalised(views[o.view].intrinsics, uv)))
            k += m
        return replace(self, obs=tuple(out))

    def tangent_at(self, c: np.ndarray) -> np.ndarray:
        """(2,) the horizontal direction of the (first) picked line where it passes nearest to ``c``."""
        P = self.obs[0].line_enu
        k = int(np.argmin(np.linalg.norm(P[:, :2] - np.asarray(c, float)[:2], axis=1)))
        a, b = P[max(k - 1, 0), :2], P[min(k + 1, len(P) - 1), :2]
        d = b - a
        return d / max(float(np.linalg.norm(d)), 1e-12)

    def coarse(self, max_picks: int = 16, step: int = 4) -> "TrackTerm":
        """A cheaper copy for scoring many starts: at most ``max_picks`` picks per observation, every ``step``-th
        line point."""
        obs = []
        for o in self.obs:
            k = np.linspace(0, len(o.uv) - 1, min(len(o.uv), max_picks)).round().astype(int)
            obs.append(replace(o, uv=o.uv[k], xy=o.xy[k], line_enu=o.line_enu[::step]))
        return replace(self, obs=tuple(obs), line_sigma_m=tuple(self.line_sigma_m),
                       height_sigma_m=tuple(self.height_sigma_m))


def _normalised(intr, uv: np.ndarray) -> np.ndarray:
    r = intr.rays(np.asarray(uv, float).reshape(-1, 2))
    return r[:, :2] / r[:, 2:3]


def _fixed_distances(xy: np.ndarray, qa: np.ndarray, qb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point ``xy`` (n, 2)'s signed distance (normalised plane) to its own segment, ends ``qa``, ``qb`` (n, 3)
    in the camera frame (NaN where an end is nearer than :data:`NEAR_M`), and the depth there."""
    ok = (qa[:, 2] > NEAR_M) & (qb[:, 2] > NEAR_M)
    a = qa[:, :2] / np.where(ok, qa[:, 2], 1.0)[:, None]
    b = qb[:, :2] / np.where(ok, qb[:, 2], 1.0)[:, None]
    d = b - a
    w = xy - a
    t = np.clip((w * d).sum(axis=1) / np.maximum((d * d).sum(axis=1), 1e-18), 0.0, 1.0)
    e = w - t[:, None] * d
    cross = d[:, 0] * w[:, 1] - d[:, 1] * w[:, 0]
    r = np.hypot(e[:, 0], e[:, 1]) * np.where(cross >= 0.0, 1.0, -1.0)
    z = qa[:, 2] + t * (qb[:, 2] - qa[:, 2])
    return np.where(ok, r, np.nan), np.where(ok, z, np.nan)


def _signed_distances(xy: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point ``xy`` (n, 2)'s signed distance (normalised plane) to the pinhole projection of the polyline
    ``q`` (m, 3) in the camera frame, cut where its depth is under :data:`NEAR_M`, the depth there and the index
    of that segment (0 and NaN where none): the nearer of the two segments at the projected vertex nearest to the
    point (the line is densified, so that is the nearest segment)."""
    n = len(xy)
    none = (np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, int))
    front = q[:, 2] > NEAR_M
    if n == 0 or np.count_nonzero(front[:-1] & front[1:]) == 0:
        return none
    p = q[:, :2] / np.where(front, q[:, 2], 1.0)[:, None]
    vert = np.nonzero(front)[0]
    d2 = ((xy[:, None, 0] - p[None, vert, 0]) ** 2 + (xy[:, None, 1] - p[None, vert, 1]) ** 2)
    j = vert[np.argmin(d2, axis=1)]
    best_r, best_z, best_s = np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, int)
    for s in (j - 1, j):
        ok = (s >= 0) & (s < len(q) - 1)
        s = np.clip(s, 0, len(q) - 2)
        ok &= front[s] & front[s + 1]
        r, z = _fixed_distances(xy, q[s], q[s + 1])
        better = ok & np.isfinite(r) & ~(np.abs(best_r) <= np.abs(r))
        best_r, best_z, best_s = np.where(better, r, best_r), np.where(better, z, best_z), np.where(better, s, best_s)
    return best_r, best_z, best_s


def _pick_line(lines: Sequence[RailwayLine], name: str, where: str) -> RailwayLine:
    if not lines:
        raise InputError(f"{where}: the railway layer (terrain.railways) has no line; track picks need one")
    if not name:
        if len(lines) == 1:
            return lines[0]
        raise InputError(f"{where}: 'line' is not given and the railway layer has {len(lines)} lines "
                         f"({', '.join(ln.id for ln in lines[:8])}); name the line the picks are on by its id")
    for ln in lines:
        if ln.id == name:
            return ln
    raise InputError(f"{where}: line {name!r} is not in the railway layer (its lines: "
                     f"{', '.join(ln.id for ln in lines[:8])}); give one of those ids")


def build_track_term(picks: Sequence[TrackPick], lines: Sequence[RailwayLine], views: Sequence, *, sigma_px: float,
                     line_sigma_m: float, height_sigma_m: float, where: str) -> TrackTerm | None:
    """The track picks in ``views`` (by photo name; picks in other photos are not this route's) on the railway
    ``lines`` (scene frame, heights as the caller chose); None when there are none. A line's ``accuracy_m``
    property, where the layer gives it, is its horizontal 1-sigma in place of ``line_sigma_m``. A pick outside its
    photo, or naming a line the layer does not have, is an :class:`InputError` naming the entry."""
    by_name = {v.name: i for i, v in enumerate(views)}
    obs, hs, vs = [], [], []
    for i, tp in enumerate(picks):
        w = f"{where}: track_picks[{i}] (photo {tp.photo!r})"
        vi = by_name.get(tp.photo)
        if vi is None:
            continue
        intr = views[vi].intrinsics
        bad = ~intr.in_image(tp.pixels)
        if bad.any():
            uv = tp.pixels[int(np.argmax(bad))]
            raise InputError(f"{w}: pixel {uv.tolist()} is outside the {intr.width}x{intr.height} image (u in [-0.5, "
                             f"{intr.width - 0.5}], v in [-0.5, {intr.height - 0.5}]); fix or remove the pick")
        line = _pick_line(lines, tp.line, w)
        P = line.rail_polyline(tp.offset_m, STEP_M)
        P = P[np.linalg.norm(P[:, :2], axis=1) <= MAX_RANGE_M]
        if len(P) < 2:
            raise InputError(f"{w}: line {line.id!r} has no part within {MAX_RANGE_M:.0f} m of the incident")
        obs.append(TrackObservation(vi, tp.photo, line.id, tp.rail, tp.pixels.copy(), _normalised(intr, tp.pixels),
                                    P))
        acc = line.properties.get("accuracy_m")
        ok = isinstance(acc, (int, float)) and not isinstance(acc, bool) and math.isfinite(acc) and acc >= 0
        hs.append(float(acc) if ok else float(line_sigma_m))
        vs.append(float(height_sigma_m))
    if not obs:
        return None
    return TrackTerm(tuple(obs), float(sigma_px), tuple(hs), tuple(vs))


def _look_rotation(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """``cam_from_world`` of a level camera (no roll) looking at ``azimuth_deg`` (clockwise from north) and
    ``elevation_deg`` up."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    fwd = np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    return np.vstack([right, np.cross(fwd, right), fwd])


def track_rotation_candidates(track: TrackTerm, views: Sequence, centres: Sequence[np.ndarray], *, keep: int = 4,
                              step_deg: float = 5.0, chunk: int = 128) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(rig_from_world, centre)`` starts from the track picks alone at each of ``centres``: the photo with the
    most picks turned over a grid of azimuths (all round) and elevations (-45 to 20 deg), no roll (the other
    photos turned with it), scored by the picks' truncated squared angles (at 0.05 rad) to the nearest point of
    their line as seen from the centre (a coarse copy of the term: 8 picks per line and photo, 2 m between line
    points); the ``keep`` best over all centres."""
    counts = np.bincount([o.view for o in track.obs for _ in range(len(o.uv))], minlength=len(views))
    vi = int(np.argmax(counts))
    coarse = track.coarse(max_picks=8)
    cam_from_rig = np.asarray(views[vi].cam_from_rig, float)
    bear = []  # each pick's bearing in the rig frame
    for o in coarse.obs:
        ray = np.column_stack([o.xy, np.ones(len(o.xy))])
        bear.append((ray / np.linalg.norm(ray, axis=1, keepdims=True)) @ np.asarray(views[o.view].cam_from_rig, float))
    grid = [cam_from_rig.T @ _look_rotation(float(az), float(el)) for az in np.arange(0.0, 360.0, step_deg)
            for el in np.arange(-45.0, 20.0 + 1e-9, step_deg)]
    Rs = np.array(grid)  # (K, 3, 3) rig_from_world
    T2 = 0.05 ** 2
    scored = []
    for c0 in centres:
        c0 = np.asarray(c0, float)
        cost = np.zeros(len(Rs))
        for o, b in zip(coarse.obs, bear):
            U = o.line_enu - c0
            U /= np.maximum(np.linalg.norm(U, axis=1, keepdims=True), 1e-9)
            for k0 in range(0, len(Rs), chunk):
                W = b @ Rs[k0:k0 + chunk]  # (k, n, 3): the picks' directions in the scene
                cosmax = np.max(W @ U.T, axis=2)
                ang2 = 2.0 * (1.0 - np.clip(cosmax, -1.0, 1.0))  # ~ angle^2
                cost[k0:k0 + chunk] += np.sum(np.minimum(ang2, T2), axis=1)
        scored.extend((float(cst), R, c0) for cst, R in zip(cost, Rs))
    scored.sort(key=lambda s: s[0])
    return [(R, c0) for _, R, c0 in scored[:keep]]


def track_observability(J_track: np.ndarray, cov_centre: np.ndarray | None, tangent_en: np.ndarray) -> dict:
    """What the track picks alone fix: the rank of their whitened Jacobian ``J_track`` (k, 6: rotation vector,
    centre), its condition number (columns scaled to unit norm), the 1-sigma of the camera's position along the
    track (``tangent_en``: the track direction at the camera's foot) from the track picks alone (None when they do
    not fix it: more than 1 km) and, with ``cov_centre`` (3, 3) of the whole fit, from everything."""
    t = np.array([tangent_en[0], tangent_en[1], 0.0], float)
    t /= max(np.linalg.norm(t), 1e-12)
    out: dict = {"n_rows": int(J_track.shape[0])}
    if J_track.shape[0] == 0:
        return out
    norms = np.linalg.norm(J_track, axis=0)
    Js = J_track / np.where(norms > 0, norms, 1.0)
    s = np.linalg.svd(Js, compute_uv=False)
    out["rank"] = int(np.sum(s > 1e-6 * s[0])) if s[0] > 0 else 0
    out["condition_number"] = float(s[0] / s[-1]) if s[-1] > 0 else None
    H = J_track.T @ J_track
    try:
        C = np.linalg.inv(H + 1e-12 * np.trace(H) * np.eye(6))
        sa = float(math.sqrt(max(float(t @ C[3:6, 3:6] @ t), 0.0)))
        out["sigma_along_track_from_track_m"] = sa if sa < 1000.0 else None
    except np.linalg.LinAlgError:
        out["sigma_along_track_from_track_m"] = None
    if cov_centre is not None:
        out["sigma_along_track_m"] = float(math.sqrt(max(float(t @ np.asarray(cov_centre) @ t), 0.0)))
    return out


def track_inliers(track: TrackTerm, R: np.ndarray, c: np.ndarray, views: Sequence, opts: GeorefOptions) -> np.ndarray:
    """(n,) the track picks within ``opts.ransac_threshold_px`` of their line, or 4 times their sigma where that is
    larger (as the control points' :func:`~workbench.georef.central.inlier_limits`)."""
    r, depth = track.errors(R, c, views)
    lim = np.maximum(float(opts.ransac_threshold_px), 4.0 * track.sigmas(depth, views))
    return np.isfinite(r) & (np.abs(np.nan_to_num(r, nan=np.inf)) < lim)


def track_fit_stats(track: TrackTerm, R: np.ndarray, c: np.ndarray, views: Sequence, opts: GeorefOptions,
                    inliers: np.ndarray | None, J_track: np.ndarray, cov_centre: np.ndarray | None, where: str,
                    warns: list[str]) -> dict:
    """The track picks' residuals (per pick: photo, line, rail, pixel, signed residual px, inlier), their RMS and
    outliers, and :func:`track_observability`; a large RMS or an outlier is warned about
    (:class:`GeorefResidualsLarge`, appended to ``warns``)."""
    r, depth = track.errors(R, c, views)
    inl = np.ones(track.n, bool) if inliers is None else inliers
    k = track.pick_index()
    picks = [{"photo": track.obs[j].photo, "line": track.obs[j].line_id, "rail": track.obs[j].rail,
              "uv": track.obs[j].uv[i - int(np.sum(k < j))].tolist(),
              "residual_px": float(r[i]) if np.isfinite(r[i]) else None, "inlier": bool(inl[i])}
             for i, j in enumerate(k)]
    good = np.isfinite(r) & inl
    rms = float(np.sqrt(np.mean(r[good] ** 2))) if good.any() else None
    out = {"n_picks": track.n, "n_outliers": int(np.sum(~inl)), "rms_px": rms,
           "max_px": float(np.max(np.abs(r[good]))) if good.any() else None,
           "sigma_px": track.sigma_px, "line_sigma_m": list(track.line_sigma_m),
           "height_sigma_m": list(track.height_sigma_m), "picks": picks,
           "observability": track_observability(J_track, cov_centre, track.tangent_at(c))}
    msgs = []
    if rms is not None and rms > max(opts.warn_rms_px, 2.0 * track.sigma_px):
        msgs.append(f"{where}: track picks' RMS distance to their line {rms:.2f} px (sigma {track.sigma_px} px); "
                    f"check the line and rail named, and the picks")
    for p in picks:
        if not p["inlier"]:
            e = "no line in front of the camera" if p["residual_px"] is None else f"{abs(p['residual_px']):.1f} px"
            msgs.append(f"{where}: track pick {p['uv']} in {p['photo']} ({p['rail']} of line {p['line']}): {e} from "
                        f"its line (rejected as an outlier); check which rail it is on")
    sa = out["observability"].get("sigma_along_track_m")
    if sa is not None and sa > 25.0:
        msgs.append(f"{where}: the camera's place along the track is known to {sa:.0f} m only (1-sigma): the track "
                    f"picks do not fix it; add control points or a GPS position")
    for m in msgs:
        log.warning(m)
        warnings.warn(m, GeorefResidualsLarge, stacklevel=3)
    warns.extend(msgs)
    return out
