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
    p0, p1 = np.asarray(p0_uv, float), np.asarray(p1_uv, float)
    if gray.ndim != 2 or p0.shape != (2,) or p1.shape != (2,) or np.allclose(p0, p1):
        raise ValueError(f"{gray.shape=}, {p0_uv=}, {p1_uv=}: expected a (h, w) image and two distinct (u, v)")
    pts = edge_points(gray, p0, p1, half_width_px)
    for _ in range(3):
        if len(pts) < 8:
            raise ValueError(f"no straight edge along {p0_uv} - {p1_uv}: {len(pts)} edge points")
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
