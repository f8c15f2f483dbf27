"""Simplified carriage geometry in the carriage frame, and the marked-point anchors derived from it.

The body is the convex hull of its cross-section (``profile``) swept along x and, for a nose end, cut by
the sloped nose plane; so it is closed, convex and has outward normals by construction. The running gear
(wheels, axles, bogie frames, bolsters), the underframe equipment and the couplers are separate closed
convex parts. Windows, doors and grilles live in the texture (see :mod:`.livery`), not in the geometry.
"""

from __future__ import annotations

from dataclasses import dataclass

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # trimesh takes seconds to import: loaded when a mesh is built, not to list or check types
    import trimesh

from .spec import CarriageSpec, ANCHOR_RE

FACE_NORMALS = {
    "left": np.array([0.0, 1.0, 0.0]),
    "right": np.array([0.0, -1.0, 0.0]),
    "front": np.array([1.0, 0.0, 0.0]),
    "rear": np.array([-1.0, 0.0, 0.0]),
    "roof": np.array([0.0, 0.0, 1.0]),
}

COUPLER_HALF = np.array([0.0, 0.14, 0.13])  # coupler head half-size in y and z (x comes from the overhang)


@dataclass(frozen=True)
class Part:
    mesh: trimesh.Trimesh
    kind: str  # "body" or "gear"
    name: str


def wall_bottom(spec: CarriageSpec) -> float:
    p = spec.profile
    return p.wall_bottom_m if p.wall_bottom_m is not None else spec.dimensions.body_bottom_m


def profile_yz(spec: CarriageSpec) -> np.ndarray:
    """Body cross-section, (k, 2) array of (y, z), counter-clockwise seen from the front (+x)."""
    d, p = spec.dimensions, spec.profile
    hw, h, bb = d.width_m / 2, d.height_m, d.body_bottom_m
    wb = wall_bottom(spec)
    right_half: list[tuple[float, float]] = []  # from bottom centre-ish up the right side (y < 0)
    if p.bottom_inset_m > 0:
        right_half.append((-(hw - p.bottom_inset_m), bb))
        n = p.bottom_segments  # 1: a straight chamfer; more: a quarter ellipse from the bottom to the wall
        for k in range(1, n):
            t = 0.5 * np.pi * k / n
            right_half.append((-(hw - p.bottom_inset_m + p.bottom_inset_m * np.sin(t)), wb - (wb - bb) * np.cos(t)))
        right_half.append((-hw, wb))
    else:
        right_half.append((-hw, bb))
    right_half.append((-hw, p.eave_height_m))
    if p.roof_edge_inset_m > 0:
        n = p.roof_segments
        for k in range(1, n + 1):
            t = 0.5 * np.pi * k / n
            y = -(hw - p.roof_edge_inset_m + p.roof_edge_inset_m * np.cos(t))
            z = p.eave_height_m + (h - p.eave_height_m) * np.sin(t)
            right_half.append((y, z))
    elif p.eave_height_m < h:
        right_half.append((-hw, h))
    pts = right_half + [(-y, z) for (y, z) in reversed(right_half)]
    return np.array(pts, dtype=float)


def nose_x(spec: CarriageSpec, end: str, z: np.ndarray | float) -> np.ndarray | float:
    """x of the body end surface at height z (flat: the end face; nose: vertical below the base, sloped above)."""
    d = spec.dimensions
    sign = 1.0 if end == "front" else -1.0
    xe = sign * d.body_length_m / 2
    e = getattr(spec, end)
    zz = np.asarray(z, dtype=float)
    if e.shape != "nose":
        out = np.full(zz.shape, xe)
    else:
        frac = np.clip((zz - e.nose_base_height_m) / (d.height_m - e.nose_base_height_m), 0.0, None)
        out = xe - sign * e.nose_setback_m * frac
    return out if zz.ndim else float(out)


def end_x(spec: CarriageSpec, end: str, z: np.ndarray | float, y: np.ndarray | float) -> np.ndarray | float:
    """x of the body end surface at height z and lateral offset y: :func:`nose_x` on the centre line, and an end
    bowed in plan (``corner_setback_m``) falling back towards its corners as (y / half width)^2."""
    e = getattr(spec, end)
    x = nose_x(spec, end, z)
    if not e.corner_setback_m:
        return x
    sign = 1.0 if end == "front" else -1.0
    f = np.clip(np.abs(np.asarray(y, dtype=float)) / (spec.dimensions.width_m / 2), 0.0, 1.0)
    out = x - sign * e.corner_setback_m * f ** 2
    return out if np.ndim(out) else float(out)


def body_points(spec: CarriageSpec) -> np.ndarray:
    """Vertices of the body hull: the cross-section at each end (following the nose's rake), and, where an end's
    corners are rounded in plan (``corner_radius_m``), that section drawn in along quarter circles."""
    prof = profile_yz(spec)
    hw = spec.dimensions.width_m / 2
    pts = []
    for end in ("front", "rear"):
        sign = 1.0 if end == "front" else -1.0
        e = getattr(spec, end)
        xs = end_x(spec, end, prof[:, 1], hw)  # the end's x at its corners (at every height of the section)
        r = float(e.corner_radius_m)
        n = int(e.corner_segments) if r > 0 else 0
        pts.append(np.column_stack([xs - sign * r, prof[:, 0], prof[:, 1]]))  # where the side leaves the wall
        for k in range(n + 1 if n else 0):  # the quarter circle from the side (phi = 90 deg) to the end face (phi = 0)
            phi = 0.5 * np.pi * k / n
            half = hw - r + r * np.sin(phi)
            y = np.clip(prof[:, 0], -half, half)
            pts.append(np.column_stack([end_x(spec, end, prof[:, 1], y) - sign * r * (1.0 - np.cos(phi)), y,
                                        prof[:, 1]]))
        if e.corner_setback_m:  # a bowed end: its face sampled across the width
            for f in (0.0, 0.25, 0.5, 0.75, 0.9):
                y = f * np.clip(prof[:, 0], -(hw - r), hw - r)
                pts.append(np.column_stack([end_x(spec, end, prof[:, 1], y), y, prof[:, 1]]))
        if e.shape == "nose":  # the vertical lower front up to the nose's base, its corners rounded as below
            zb = e.nose_base_height_m
            for phi in (0.5 * np.pi * np.arange(n + 1) / n if n else [0.5 * np.pi]):
                y = hw - r + r * np.sin(phi)
                x = end_x(spec, end, 0.0, min(y, hw - r) if n else y) - sign * r * (1.0 - np.cos(phi))
                pts.append(np.array([[x, y, zb], [x, -y, zb]]))
            if e.corner_setback_m:
                for f in (0.0, 0.25, 0.5, 0.75, 0.9):
                    y = f * (hw - r)
                    x = end_x(spec, end, 0.0, y)
                    pts.append(np.array([[x, y, zb], [x, -y, zb]]))
    return np.vstack(pts)


def _hull(points: np.ndarray) -> trimesh.Trimesh:
    import trimesh

    m = trimesh.convex.convex_hull(np.asarray(points, dtype=float))
    keep = m.area_faces > 1e-10
    if not np.all(keep):
        m.update_faces(keep)
        m.remove_unreferenced_vertices()
    m.fix_normals()
    return m


def _box(lo, hi) -> trimesh.Trimesh:
    import trimesh

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


def _wheel(x: float, y: float, radius: float, half_width: float, sections: int = 16) -> trimesh.Trimesh:
    """A wheel (cylinder, axis along y) with one rim vertex exactly at its lowest point (the rail contact)."""
    a = -0.5 * np.pi + 2 * np.pi * np.arange(sections) / sections
    ring = np.column_stack([x + radius * np.cos(a), np.zeros(sections), radius + radius * np.sin(a)])
    left, right = ring.copy(), ring.copy()
    left[:, 1] = y + half_width
    right[:, 1] = y - half_width
    return _hull(np.vstack([left, right]))


def bogie_boxes(spec: CarriageSpec) -> list[tuple[np.ndarray, np.ndarray]]:
    """(lo, hi) of the axis-aligned box around each bogie (wheels, frames, bolster), front bogie first."""
    d = spec.dimensions
    out = []
    for sign in (1.0, -1.0):
        xb = sign * d.bogie_centres_m / 2
        lx = d.bogie_wheelbase_m / 2 + d.wheel_diameter_m / 2 + 0.1
        ly = d.gauge_m / 2 + 0.35
        out.append((np.array([xb - lx, -ly, 0.0]), np.array([xb + lx, ly, d.body_bottom_m])))
    return out


def equipment_box(spec: CarriageSpec) -> tuple[np.ndarray, np.ndarray] | None:
    d = spec.dimensions
    if d.equipment_depth_m <= 0:
        return None
    inner = d.bogie_centres_m / 2 - d.bogie_wheelbase_m / 2 - d.wheel_diameter_m / 2 - 0.5
    if inner < 1.0:
        return None
    hy = d.width_m / 2 - 0.35
    return (np.array([-inner, -hy, d.body_bottom_m - d.equipment_depth_m]), np.array([inner, hy, d.body_bottom_m]))


def build_parts(spec: CarriageSpec) -> list[Part]:
    d = spec.dimensions
    parts = [Part(_hull(body_points(spec)), "body", "body")]
    r = d.wheel_diameter_m / 2
    hg = d.gauge_m / 2
    for bi, sign in enumerate((1.0, -1.0)):
        xb = sign * d.bogie_centres_m / 2
        tag = "front" if sign > 0 else "rear"
        for xa in (xb + d.bogie_wheelbase_m / 2, xb - d.bogie_wheelbase_m / 2):
            for ys in (1.0, -1.0):
                parts.append(Part(_wheel(xa, ys * (hg + 0.035), r, 0.07), "gear", f"wheel_{tag}"))
            parts.append(Part(_box([xa - 0.09, -hg, r - 0.09], [xa + 0.09, hg, r + 0.09]), "gear", f"axle_{tag}"))
        lx = d.bogie_wheelbase_m / 2 + r * 0.8
        for ys in (1.0, -1.0):
            yc = ys * (hg + 0.22)
            parts.append(Part(_box([xb - lx, yc - 0.11, r - 0.15], [xb + lx, yc + 0.11, r + 0.25]), "gear",
                              f"sideframe_{tag}"))
        # bolster up to the underside of the body
        parts.append(Part(_box([xb - 0.35, -(hg + 0.3), r + 0.1], [xb + 0.35, hg + 0.3, d.body_bottom_m]), "gear",
                          f"bolster_{tag}"))
    eq = equipment_box(spec)
    if eq is not None:
        parts.append(Part(_box(*eq), "gear", "equipment"))
    for sign, tag in ((1.0, "front"), (-1.0, "rear")):
        xe = sign * d.body_length_m / 2
        xc = sign * d.length_over_couplers_m / 2
        reach = 1.2  # the draft gear starts this far inside the body end
        xs = sorted([xe - sign * reach, xc])
        zc = d.coupler_height_m
        parts.append(Part(_box([xs[0], -COUPLER_HALF[1], zc - COUPLER_HALF[2]], [xs[1], COUPLER_HALF[1], zc + COUPLER_HALF[2]]),
                          "gear", f"coupler_{tag}"))
        if d.body_bottom_m > zc:  # carrier from the coupler up into the body
            xs2 = sorted([xe - sign * reach, xe - sign * 0.05])
            parts.append(Part(_box([xs2[0], -0.2, zc], [xs2[1], 0.2, d.body_bottom_m + 0.05]), "gear", f"carrier_{tag}"))
    return parts


# --------------------------------------------------------------------------------------------------------
def anchor_point(spec: CarriageSpec, anchor: str) -> tuple[np.ndarray, tuple[str, ...]]:
    """Carriage-frame position and faces of a named anchor (see :mod:`.spec`)."""
    m = ANCHOR_RE.match(anchor)
    if not m:
        raise ValueError(f"unknown anchor {anchor!r}")
    if m.group(1):  # the couplers: a mesh type's too (its dimensions hold the length and the coupler height)
        end, d = m.group(1), spec.dimensions
        sign = 1.0 if end == "front" else -1.0
        return np.array([sign * d.length_over_couplers_m / 2, 0.0, d.coupler_height_m]), (end,)
    d, p = spec.dimensions, spec.profile
    hw = d.width_m / 2
    if m.group(2):
        which, end, side = m.group(2), m.group(3), m.group(4)
        ys = 1.0 if side == "left" else -1.0
        if which == "top":
            z = p.eave_height_m
            return np.array([end_x(spec, end, z, hw), ys * hw, z]), (side, end)
        z = d.body_bottom_m
        return np.array([end_x(spec, end, z, hw - p.bottom_inset_m), ys * (hw - p.bottom_inset_m), z]), (side, end)
    if m.group(5):
        end, side = m.group(5), m.group(6)
        ys = 1.0 if side == "left" else -1.0
        z = getattr(spec, end).nose_base_height_m
        return np.array([end_x(spec, end, z, hw), ys * hw, z]), (side, end)
    if m.group(11):  # the top or the bottom of an end, on the centre line
        which, end = m.group(11), m.group(12)
        z = d.height_m if which == "roof" else d.body_bottom_m
        return np.array([nose_x(spec, end, z), 0.0, z]), ((end, "roof") if which == "roof" else (end,))
    k, which, xend, side = int(m.group(7)), m.group(8), m.group(9), m.group(10)
    door = spec.doors[k - 1]
    ys = 1.0 if side == "left" else -1.0
    x = door.x_m + (door.width_m / 2 if xend == "front" else -door.width_m / 2)
    z = door.z_top_m if which == "top" else door.z_bottom_m
    return np.array([x, ys * hw, z]), (side,)
