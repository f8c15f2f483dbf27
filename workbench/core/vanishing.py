"""Straight edges in a photo, their vanishing points, and the turn between two cars they show.

A car's side carries straight edges parallel to its axis (the body's bottom edge, the edges of a painted band):
in a photo they meet at the vanishing point of the car's axis, whatever the car's dimensions, and the vanishing
points of two cars give the angle between their axes with no model at all (only the camera's focal and up
direction turn pixels into degrees). A train on straight track has one vanishing point; on a curve each car's
moves along the horizon. Pixel convention: docs/conventions.md (the top-left pixel's centre at (0, 0)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# An edge point is the centroid of the pixel differences within this many of the largest (5 differences: the
# whole of a step blurred over 1-2 px; more only adds noise).
CENTROID_HALF_PX = 2
# A photo's neighbouring pixels are not independent (demosaicing, JPEG's 8 x 8 blocks, the resampling to a
# web size): the line fit counts one independent point per CORRELATION_PX of edge length, so its sigmas are not
# optimistic. On tests/test_real_photo_track.py's synthetic photo (independent noise) over 20 noise draws the
# turn's error scattered by 0.41 of its sigma, about a bias of 0.09 deg (0.7 sigma): one edge of each car runs
# within 0.2 deg of the pixel rows, where the centroid's pull to the pixel grid (+-0.008 px) does not average
# out along the edge. Edges at a few degrees to the rows or columns average it out.
CORRELATION_PX = 4.0
CHANNEL = {"red": 0, "green": 1, "blue": 2}  # an edge's channel in an RGB photo


@dataclass(frozen=True)
class EdgeLine:
    """A straight image edge: ``point_uv`` (its points' centroid, px), ``direction`` (unit, u growing), and the
    1-sigma of its angle (rad) and of its offset along the normal at the centroid (px), independent there."""

    point_uv: np.ndarray
    direction: np.ndarray
    sigma_angle_rad: float
    sigma_offset_px: float
    rms_px: float
    n_points: int

    def moved(self, d_angle_rad: float, d_offset_px: float) -> "EdgeLine":
        """The same line turned about its centroid and shifted along its normal (for propagating sigmas)."""
        a = math.atan2(self.direction[1], self.direction[0]) + d_angle_rad
        d = np.array([math.cos(a), math.sin(a)])
        p = self.point_uv + d_offset_px * np.array([-self.direction[1], self.direction[0]])
        return EdgeLine(p, d, self.sigma_angle_rad, self.sigma_offset_px, self.rms_px, self.n_points)


def edge_points(gray: np.ndarray, p0_uv, p1_uv, half_width_px: float = 2.5) -> np.ndarray:
    """(n, 2) sub-pixel points (u, v) of the strongest edge along the segment p0-p1 in ``gray`` ((h, w) float),
    of the polarity most of the segment shows: one per pixel column it crosses (per row where it is steeper than
    45 deg), each the centroid of the pixel differences within CENTROID_HALF_PX of the largest one within
    ``half_width_px`` of the segment. The photo's own pixels, not interpolated ones: an interpolating spline
    pulls a sharp edge towards the pixel grid (0.1-0.3 deg on a vanishing point's direction in
    tests/test_real_photo_track.py), the centroid does not."""
    p0, p1 = np.asarray(p0_uv, float), np.asarray(p1_uv, float)
    steep = abs(p1[1] - p0[1]) > abs(p1[0] - p0[0])
    g = gray.T if steep else gray
    if steep:
        p0, p1 = p0[::-1], p1[::-1]
    if p1[0] < p0[0]:
        p0, p1 = p1, p0
    us = np.arange(math.ceil(p0[0]), math.floor(p1[0]) + 1)
    vs = p0[1] + (p1[1] - p0[1]) * (us - p0[0]) / (p1[0] - p0[0])
    rows = np.floor(vs - half_width_px - CENTROID_HALF_PX).astype(int)[:, None] \
        + np.arange(int(2 * (half_width_px + CENTROID_HALF_PX)) + 2)[None, :]
    ok = (rows.min(1) >= 0) & (rows.max(1) < g.shape[0]) & (us >= 0) & (us < g.shape[1])
    us, vs, rows = us[ok], vs[ok], rows[ok]
    diff = np.diff(g[rows, us[:, None]], axis=1)  # between rows k and k + 1: at k + 0.5
    pos = rows[:, :-1] + 0.5
    diff *= np.sign(diff.sum()) or 1.0
    floor = 1e-9 + 1e-3 * float(np.ptp(g[rows, us[:, None]])) if len(us) else 0.0  # a flat patch: no edge
    out = []
    for k in range(len(us)):
        near = np.flatnonzero(np.abs(pos[k] - vs[k]) <= half_width_px)
        j = near[np.argmax(diff[k, near])] if len(near) else -1
        if j < 0 or diff[k, j] <= floor:
            continue
        a, b = max(j - CENTROID_HALF_PX, 0), min(j + CENTROID_HALF_PX + 1, diff.shape[1])
        w = np.clip(diff[k, a:b], 0.0, None)
        out.append((us[k], float(w @ pos[k, a:b] / w.sum())))
    pts = np.array(out, float).reshape(-1, 2)
    return pts[:, ::-1] if steep else pts


def fit_image_edge(gray: np.ndarray, p0_uv, p1_uv, half_width_px: float = 2.5) -> EdgeLine:
    """Fit a straight line to the edge drawn approximately as the segment ``p0_uv``-``p1_uv`` (px) in ``gray``
    ((h, w) float): its points (:func:`edge_points`), then a total-least-squares line, points beyond 3 RMS (at
    least 0.3 px) dropped twice. Raises ValueError when fewer than 8 points remain (no edge there)."""
    return fit_image_line(gray, [(p0_uv, p1_uv)], half_width_px)


def fit_image_line(gray: np.ndarray, segments, half_width_px: float = 2.5) -> EdgeLine:
    """One straight line through the edges drawn as several segments ``[(p0_uv, p1_uv), ...]`` (px) in ``gray``
    ((h, w) float): pieces of one straight edge in space interrupted in the photo (the bottoms of a row of windows
    at one height on a car's side, an edge crossed by a pole). Each segment's points as :func:`edge_points`
    finds them (each its own polarity), pooled, then fitted as :func:`fit_image_edge` fits one segment's."""
    if gray.ndim != 2 or not len(segments):
        raise ValueError(f"{gray.shape=}, {len(segments)} segments: expected a (h, w) image and some segments")
    parts = []
    for p0_uv, p1_uv in segments:
        p0, p1 = np.asarray(p0_uv, float), np.asarray(p1_uv, float)
        if p0.shape != (2,) or p1.shape != (2,) or np.allclose(p0, p1):
            raise ValueError(f"{gray.shape=}, {p0_uv=}, {p1_uv=}: expected a (h, w) image and two distinct (u, v)")
        parts.append(edge_points(gray, p0, p1, half_width_px))
    pts = np.vstack(parts)
    where = f"{segments[0][0]} - {segments[-1][1]}" if len(segments) > 1 else f"{segments[0][0]} - {segments[0][1]}"
    for _ in range(3):
        if len(pts) < 8:
            raise ValueError(f"no straight edge along {where}: {len(pts)} edge points")
        m = pts.mean(0)
        direction = np.linalg.svd(pts - m)[2][0]
        r = (pts - m) @ np.array([-direction[1], direction[0]])
        rms = float(np.sqrt(np.mean(r ** 2)))
        keep = np.abs(r) <= max(3 * rms, 0.3)
        if keep.all():
            break
        pts = pts[keep]
    direction = direction if direction[0] >= 0 else -direction
    t = (pts - m) @ direction
    n_eff = max(len(pts) / CORRELATION_PX, 2.0)
    sig = max(rms, 1e-3)
    return EdgeLine(m, direction, sig / math.sqrt(float(np.sum(t ** 2)) * n_eff / len(pts)),
                    sig / math.sqrt(n_eff), rms, len(pts))


def _meet(a: EdgeLine, b: EdgeLine) -> np.ndarray:
    A = np.array([a.direction, -b.direction]).T
    t = np.linalg.solve(A, b.point_uv - a.point_uv)
    return a.point_uv + t[0] * a.direction


def vanishing_point(a: EdgeLine, b: EdgeLine) -> tuple[np.ndarray, np.ndarray]:
    """Where two image lines meet, (u, v) px, and its (2, 2) covariance from the lines' sigmas (first order)."""
    if abs(a.direction[0] * b.direction[1] - a.direction[1] * b.direction[0]) < 1e-6:
        raise ValueError("the two lines are parallel in the image: no finite vanishing point")
    vp = _meet(a, b)
    J, s = np.zeros((2, 4)), []
    for k, (line, which) in enumerate([(a, 0), (a, 1), (b, 0), (b, 1)]):
        h = (line.sigma_angle_rad, line.sigma_offset_px)[which]
        s.append(h)
        moved = line.moved(h if which == 0 else 0.0, h if which == 1 else 0.0)
        J[:, k] = (_meet(moved, b) if line is a else _meet(a, moved)) - vp
    return vp, J @ J.T  # the columns are already steps of one sigma each


def relative_yaw_deg(K: np.ndarray, up_cam: np.ndarray, vp_a, cov_a, vp_b, cov_b) -> tuple[float, float]:
    """The turn about the vertical from axis a to axis b, degrees, counter-clockwise seen from above positive,
    and its 1-sigma (from the vanishing points' covariances; the focal's doubt is not in it). ``K`` (3, 3) the
    camera matrix, ``up_cam`` the scene's up direction in camera coordinates (x right, y down, z forward)."""
    up = np.asarray(up_cam, float) / np.linalg.norm(up_cam)
    Kinv = np.linalg.inv(K)

    def yaw(pa, pb):
        ra, rb = Kinv @ np.append(pa, 1.0), Kinv @ np.append(pb, 1.0)
        ra, rb = ra - (ra @ up) * up, rb - (rb @ up) * up
        return math.degrees(math.atan2(up @ np.cross(ra, rb), ra @ rb))

    va, vb = np.asarray(vp_a, float), np.asarray(vp_b, float)
    y = yaw(va, vb)
    var = 0.0
    for vp, cov, first in ((va, np.asarray(cov_a), True), (vb, np.asarray(cov_b), False)):
        g = np.zeros(2)
        for i in range(2):
            e = np.zeros(2)
            e[i] = 0.5
            g[i] = ((yaw(vp + e, vb) - yaw(vp - e, vb)) if first else (yaw(va, vp + e) - yaw(va, vp - e)))
        var += float(g @ cov @ g)
    return y, math.sqrt(var)


def _part_of_segments(segments, lo: float, hi: float) -> list:
    """The stretch from fraction ``lo`` to ``hi`` of a run of segments along one edge (fractions of the run from
    the first segment's start to the last one's end, measured along that direction), as segments; pieces shorter
    than 6 px are left out."""
    segs = [(np.asarray(a, float), np.asarray(b, float)) for a, b in segments]
    start, end = segs[0][0], segs[-1][1]
    axis = (end - start) / np.linalg.norm(end - start)
    t0 = lambda p: float((p - start) @ axis)  # noqa: E731
    total = t0(end)
    out = []
    for a, b in segs:
        ta, tb = t0(a), t0(b)
        lo_t, hi_t = max(min(ta, tb), lo * total), min(max(ta, tb), hi * total)
        if hi_t - lo_t > 6.0:
            at = lambda s: a + (s - ta) / (tb - ta) * (b - a)  # noqa: E731
            out.append((at(lo_t), at(hi_t)))
    return out


def _car_vanishing_point(rgb: np.ndarray, car: str, edges: dict) -> tuple[np.ndarray, np.ndarray, dict]:
    lines = {}
    for name, e in edges.items():
        if e.get("channel") not in CHANNEL:
            raise ValueError(f"car {car} edge {name}: channel = {e.get('channel')!r}: give one of {list(CHANNEL)}")
        lines[name] = fit_image_line(rgb[..., CHANNEL[e["channel"]]], e["segments"], e.get("half_width_px", 2.5))
    if len(lines) != 2:
        raise ValueError(f"car {car}: {len(lines)} edges: give two straight edges along its side")
    vp, cov = vanishing_point(*lines.values())
    return vp, cov, lines


def screen_straight_track(rgb: np.ndarray, cars: dict) -> dict:
    """Straight track or not, from one photo alone (no camera, no carriage dimension): each car's vanishing point
    from two straight edges along its side (``cars``: car -> edge name -> {channel, half_width_px, segments}, as in
    scripts/bench_real_photo_screen.json), and for each car and the next the chi-square of their difference
    (2 dof): on straight track the cars' sides run to one vanishing point. ``rgb``: (h, w, 3) float. The turn in
    degrees needs the focal: given for assumed horizontal fields of view of 10, 20 and 30 deg with the camera
    level, for scale only.

    Each car's own check, ``halves_chi2``: the same chi-square between the vanishing points of the front and the
    rear half of its edges (one rigid body: one vanishing point). On a real photo it is how far the edges' noise
    model (CORRELATION_PX) falls short of the paint's and the panels' waviness: the car-to-car chi-squares are
    to be read against it (None where a half has too few edge points). Raises ValueError naming the car and edge
    for an unknown channel or a car without exactly two edges."""
    h, w = rgb.shape[:2]
    out, vps = {"cars": {}, "pairs": {}}, {}
    for car, edges in cars.items():
        vp, cov, lines = _car_vanishing_point(rgb, car, edges)
        vps[car] = (vp, cov)
        try:
            halves = [_car_vanishing_point(rgb, car, {n: {**e, "segments": _part_of_segments(e["segments"], lo, hi)}
                                                      for n, e in edges.items()}) for lo, hi in ((0, 0.5), (0.5, 1))]
            dh = halves[0][0] - halves[1][0]
            halves_chi2 = float(dh @ np.linalg.solve(halves[0][1] + halves[1][1], dh))
        except (ValueError, np.linalg.LinAlgError):
            halves_chi2 = None
        out["cars"][car] = {"vanishing_point_uv": vp.tolist(), "sigma_uv": np.sqrt(np.diag(cov)).tolist(),
                            "halves_chi2": halves_chi2,
                            "edges": {n: {"n_points": L.n_points, "rms_px": L.rms_px,
                                          "sigma_angle_deg": math.degrees(L.sigma_angle_rad)}
                                      for n, L in lines.items()}}
    cs = list(cars)
    for p, q in zip(cs, cs[1:]):
        d = vps[p][0] - vps[q][0]
        turn = {}
        for hfov in (10.0, 20.0, 30.0):
            f = 0.5 * w / math.tan(math.radians(hfov) / 2)
            K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
            turn[f"{hfov:.0f}"] = relative_yaw_deg(K, [0.0, -1.0, 0.0], *vps[p], *vps[q])
        out["pairs"][f"{p}-{q}"] = {"vp_difference_uv": d.tolist(),
                                    "chi2": float(d @ np.linalg.solve(vps[p][1] + vps[q][1], d)),
                                    "turn_deg_at_hfov": turn}
    return out
