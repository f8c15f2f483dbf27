"""Livery texture atlas: one PIL image per car, painted in metres, and the UV mapping onto the mesh.

Atlas layout (one image, 2048 px wide): the left side, the right side, the roof, the underside and the
two ends, each a rectangle painted as seen from outside the car (text reads correctly). Each mesh face is
mapped by projecting it onto the plane of its region: sides use (x, z), ends (y, z), roof and underside
(x, y). A sloped nose face projects onto its end region, so the windscreen painted there lands on the slope.
Everything is deterministic: the only randomness (grime, seat silhouettes) comes from a generator seeded
with the type id and car number.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw, ImageFilter, ImageFont

from .geometry import nose_x, bogie_boxes, equipment_box, wall_bottom
from .spec import CarriageSpec

ATLAS_WIDTH = 2048
PAD = 8  # px between regions (painted with the region's edge colours against bleeding)
END_SCALE = 150.0  # px per metre on the end regions
UNDER_HEIGHT = 96  # px


@lru_cache(maxsize=64)
def _font(size_px: int) -> ImageFont.FreeTypeFont:
    return ImageFont.load_default(size=max(6, int(size_px)))


def _rgb(hex_color: str) -> tuple[int, int, int]:
    h = hex_color.lstrip("#")
    return int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16)


def _shade(c: tuple[int, int, int], f: float) -> tuple[int, int, int]:
    if f >= 1:
        return tuple(int(round(v + (255 - v) * (f - 1))) for v in c)  # type: ignore[return-value]
    return tuple(int(round(v * f)) for v in c)  # type: ignore[return-value]


@dataclass(frozen=True)
class Region:
    name: str
    x0: int
    y0: int
    w: int
    h: int
    # metres -> px: px = x0 + (a * ua + ub) * su ; py = y0 + (va * b + vb) * sv, where (a, b) are the
    # region's two carriage-frame coordinates (see Atlas.coords)
    ua: float
    ub: float
    su: float
    va: float
    vb: float
    sv: float

    def px(self, a):
        return self.x0 + (self.ua * np.asarray(a, float) + self.ub) * self.su

    def py(self, b):
        return self.y0 + (self.va * np.asarray(b, float) + self.vb) * self.sv


# which carriage-frame coordinates each region uses: (index of a, index of b)
_COORDS = {"left": (0, 2), "right": (0, 2), "front": (1, 2), "rear": (1, 2), "roof": (0, 1), "under": (0, 1)}


class Atlas:
    """Layout of one car's texture atlas."""

    def __init__(self, spec: CarriageSpec) -> None:
        d = spec.dimensions
        self.spec = spec
        L = d.length_over_couplers_m
        self.half_l = L / 2
        self.top = d.height_m + 0.05
        self.half_b = d.width_m / 2 + 0.05
        W = ATLAS_WIDTH
        s = (W - 2 * PAD) / L
        side_h = int(np.ceil(self.top * s))
        roof_h = int(np.ceil(2 * self.half_b * s))
        end_w = int(np.ceil(2 * self.half_b * END_SCALE))
        end_h = int(np.ceil(self.top * END_SCALE))
        y = PAD
        regions = {}
        # sides: seen from outside; left side seen from +y has the front (+x) on the viewer's left
        regions["left"] = Region("left", PAD, y, W - 2 * PAD, side_h, -1, self.half_l, s, -1, self.top, s)
        y += side_h + PAD
        regions["right"] = Region("right", PAD, y, W - 2 * PAD, side_h, 1, self.half_l, s, -1, self.top, s)
        y += side_h + PAD
        regions["roof"] = Region("roof", PAD, y, W - 2 * PAD, roof_h, 1, self.half_l, s, -1, self.half_b, s)
        y += roof_h + PAD
        su = UNDER_HEIGHT / (2 * self.half_b)
        regions["under"] = Region("under", PAD, y, W - 2 * PAD, UNDER_HEIGHT, 1, self.half_l, s, -1, self.half_b, su)
        y += UNDER_HEIGHT + PAD
        # ends: the front seen from +x has +y on the viewer's right; the rear seen from -x has -y on the right
        regions["front"] = Region("front", PAD, y, end_w, end_h, 1, self.half_b, END_SCALE, -1, self.top, END_SCALE)
        regions["rear"] = Region("rear", 2 * PAD + end_w, y, end_w, end_h, -1, self.half_b, END_SCALE, -1, self.top,
                                 END_SCALE)
        y += end_h + PAD
        self.regions = regions
        self.width = W
        self.height = int(np.ceil(y / 16) * 16)

    def uv(self, region: str, points: np.ndarray) -> np.ndarray:
        """UV (n, 2) in [0, 1] of carriage-frame points projected into ``region`` (origin bottom-left)."""
        r = self.regions[region]
        ia, ib = _COORDS[region]
        px = np.clip(r.px(points[:, ia]), r.x0 + 0.5, r.x0 + r.w - 0.5)
        py = np.clip(r.py(points[:, ib]), r.y0 + 0.5, r.y0 + r.h - 0.5)
        return np.column_stack([px / self.width, 1.0 - py / self.height])


# --------------------------------------------------------------------------------------------------------
class _Pen:
    """Draws on one region in carriage-frame metres."""

    def __init__(self, draw: ImageDraw.ImageDraw, region: Region) -> None:
        self.d = draw
        self.r = region

    @property
    def scale(self) -> float:
        return self.r.su

    def pt(self, a: float, b: float) -> tuple[float, float]:
        return float(self.r.px(a)), float(self.r.py(b))

    def box(self, a0, a1, b0, b1) -> list[float]:
        x0, x1 = sorted([float(self.r.px(a0)), float(self.r.px(a1))])
        y0, y1 = sorted([float(self.r.py(b0)), float(self.r.py(b1))])
        return [x0, y0, x1, y1]

    def rect(self, a0, a1, b0, b1, fill=None, outline=None, width_m: float = 0.0, radius_m: float = 0.0):
        w = max(1, int(round(width_m * self.scale))) if outline is not None else 0
        rad = int(round(radius_m * self.scale))
        bx = self.box(a0, a1, b0, b1)
        if rad > 0:
            self.d.rounded_rectangle(bx, radius=min(rad, int((bx[2] - bx[0]) / 2), int((bx[3] - bx[1]) / 2)),
                                     fill=fill, outline=outline, width=w)
        else:
            self.d.rectangle(bx, fill=fill, outline=outline, width=w)

    def line(self, pts, fill, width_m: float):
        self.d.line([self.pt(a, b) for a, b in pts], fill=fill, width=max(1, int(round(width_m * self.scale))))

    def circle(self, a, b, r_m, fill=None, outline=None, width_m: float = 0.0):
        cx, cy = self.pt(a, b)
        rp = r_m * self.scale
        self.d.ellipse([cx - rp, cy - rp, cx + rp, cy + rp], fill=fill, outline=outline,
                       width=max(1, int(round(width_m * self.scale))) if outline is not None else 0)

    def polygon(self, pts, fill=None, outline=None):
        self.d.polygon([self.pt(a, b) for a, b in pts], fill=fill, outline=outline)

    def text(self, a, b, s: str, height_m: float, fill, anchor: str = "mm", stroke=None):
        if not s:
            return
        f = _font(int(round(height_m * self.scale / 0.72)))  # cap height is ~0.72 of the font size
        self.d.text(self.pt(a, b), s, font=f, fill=fill, anchor=anchor,
                    stroke_width=max(1, int(f.size / 22)) if stroke is not None else 0, stroke_fill=stroke)


class _Canvas:
    """A separate image for one region (plus a PAD/2 margin), pasted into the atlas when done, so that
    nothing drawn for one region can spill into another."""

    def __init__(self, img: Image.Image, region: Region, fill) -> None:
        m = PAD // 2
        self.img, self.region, self.m = img, region, m
        self.sub = Image.new("RGB", (region.w + 2 * m, region.h + 2 * m), fill)
        local = Region(region.name, m, m, region.w, region.h, region.ua, region.ub, region.su, region.va, region.vb,
                       region.sv)
        self.pen = _Pen(ImageDraw.Draw(self.sub), local)

    def paste(self) -> None:
        self.img.paste(self.sub, (self.region.x0 - self.m, self.region.y0 - self.m))


def _seed(spec: CarriageSpec, car_number: str, what: str) -> int:
    return zlib.crc32(f"{spec.id}|{car_number}|{what}".encode())


# --------------------------------------------------------------------------------------------------------
def _paint_side(img: Image.Image, atlas: Atlas, side: str, number: str) -> None:
    spec, d, lv = atlas.spec, atlas.spec.dimensions, atlas.spec.livery
    r = atlas.regions[side]
    canvas = _Canvas(img, r, _rgb(lv.body_color))
    pen = canvas.pen
    rng = np.random.default_rng(_seed(spec, number, side))
    body = _rgb(lv.body_color)
    under = _rgb(lv.underframe_color)
    dark = _shade(body, 0.72)
    hl, bb, h = atlas.half_l, d.body_bottom_m, d.height_m
    hb = d.body_length_m / 2
    wb = wall_bottom(spec)
    eave = spec.profile.eave_height_m
    pen.rect(-hl - 1, hl + 1, -1, bb, fill=under)
    # roof-edge band (the rounded part of the roof projects here) a little darker
    pen.rect(-hl - 1, hl + 1, eave, h + 1, fill=_shade(body, 0.9))
    pen.line([(-hl, eave), (hl, eave)], dark, 0.015)
    # corrugated (fluted) stainless: thin horizontal lines
    if lv.fluting:
        z0, z1 = lv.fluting_z_m
        for z in np.arange(z0, z1, 0.045):
            pen.line([(-hb, z), (hb, z)], _shade(body, 0.8), 0.008)
            pen.line([(-hb, z + 0.012), (hb, z + 0.012)], _shade(body, 1.12), 0.006)
    # body panel seams and rivet rows
    for x in np.arange(-hb + 1.6, hb - 1.0, 1.9):
        pen.line([(x, wb + 0.02), (x, eave - 0.02)], _shade(body, 0.82), 0.01)
    for z in (wb + 0.06, d.floor_height_m, eave - 0.06):
        for x in np.arange(-hb + 0.1, hb - 0.05, 0.16):
            pen.circle(x, z, 0.009, fill=_shade(body, 0.6))
    pen.line([(-hb, wb + 0.01), (hb, wb + 0.01)], _shade(body, 0.5), 0.02)
    # stripes
    for st in lv.stripes:
        pen.rect(-hb, hb, st.z_bottom_m, st.z_top_m, fill=_rgb(st.color))
        pen.line([(-hb, st.z_top_m), (hb, st.z_top_m)], _shade(_rgb(st.color), 0.7), 0.008)
    # windows
    frame = _rgb(lv.frame_color)
    glass = _rgb(lv.window_color)
    for g in spec.windows:
        if side not in g.sides:
            continue
        for xc in g.centres():
            _window(pen, rng, xc - g.width_m / 2, xc + g.width_m / 2, g.z_bottom_m, g.z_top_m, g.corner_radius_m,
                    frame, glass)
    # cab side windows
    for end in ("front", "rear"):
        e = getattr(spec, end)
        if not e.cab:
            continue
        sgn = 1.0 if end == "front" else -1.0
        xt = nose_x(spec, end, eave)
        x_in = xt - sgn * 0.25
        z_top = eave - 0.2
        z_bot = max(wb + 0.3, z_top - 0.75)
        _window(pen, rng, min(x_in, x_in - sgn * 0.9), max(x_in, x_in - sgn * 0.9), z_bot, z_top, 0.08, frame, glass)
    # doors
    door_fill = _rgb(lv.door_color) if lv.door_color else _shade(body, 0.95)
    for i, dr in enumerate(spec.doors):
        if side not in dr.sides:
            continue
        x0, x1 = dr.x_m - dr.width_m / 2, dr.x_m + dr.width_m / 2
        pen.rect(x0 - 0.03, x1 + 0.03, dr.z_bottom_m - 0.02, dr.z_top_m + 0.03, fill=_shade(body, 0.55))
        pen.rect(x0, x1, dr.z_bottom_m, dr.z_top_m, fill=door_fill, outline=(25, 25, 25), width_m=0.02)
        leaves = [(x0, x1)] if dr.leaves == 1 else [(x0, dr.x_m), (dr.x_m, x1)]
        for a0, a1 in leaves:
            pen.rect(a0, a1, dr.z_bottom_m, dr.z_top_m, outline=(30, 30, 30), width_m=0.015)
            if dr.window:
                wz1 = dr.z_top_m - 0.2
                wz0 = max(dr.z_bottom_m + 0.9, wz1 - 0.8)
                if wz0 < wz1 - 0.2:
                    pen.rect(a0 + 0.08, a1 - 0.08, wz0, wz1, fill=glass, outline=frame, width_m=0.03, radius_m=0.05)
                    pen.line([(a0 + 0.12, wz1 - 0.08), (a0 + 0.3, wz1 - 0.3)], _shade(glass, 2.2), 0.02)
            pen.rect(a0 + 0.05, a1 - 0.05, dr.z_bottom_m + 0.05, dr.z_bottom_m + 0.45, outline=_shade(door_fill, 0.6),
                     width_m=0.012)
        pen.rect(x0, x1, dr.z_bottom_m - 0.0, dr.z_bottom_m + 0.04, fill=(220, 190, 30))  # yellow step edge
        pen.text(dr.x_m, dr.z_top_m + 0.12, number, 0.08, fill=_rgb(lv.text_color))
    # grilles / louvres
    for gr in spec.grilles:
        if side not in gr.sides:
            continue
        pen.rect(gr.x_start_m, gr.x_end_m, gr.z_bottom_m, gr.z_top_m, fill=_shade(body, 0.45), outline=(40, 40, 40),
                 width_m=0.02)
        for z in np.arange(gr.z_bottom_m + 0.04, gr.z_top_m - 0.02, 0.055):
            pen.line([(gr.x_start_m + 0.03, z), (gr.x_end_m - 0.03, z)], _shade(body, 0.85), 0.012)
        for x in np.arange(gr.x_start_m + 0.6, gr.x_end_m - 0.1, 0.6):
            pen.line([(x, gr.z_bottom_m), (x, gr.z_top_m)], (40, 40, 40), 0.015)
    # lettering: operator name, logo, car number near both ends and small placards
    tc = _rgb(lv.text_color)
    if lv.operator_text:
        pen.text(lv.operator_text_x_m, lv.operator_text_z_m, lv.operator_text,
                 lv.operator_text_height_m, fill=tc)
    if lv.logo_text:
        _logo(pen, lv.logo_x_m, lv.logo_z_m, lv.logo_size_m, _rgb(lv.logo_color), lv.logo_text)
    nc = _rgb(lv.number_color)
    for xn in (hb - 2.3, -hb + 2.3):
        if _clear_of_doors(spec, side, xn, 1.0):
            pen.text(xn, lv.number_z_m, number, lv.number_height_m, fill=nc)
        else:
            pen.text(xn - np.sign(xn) * 1.6, lv.number_z_m, number, lv.number_height_m, fill=nc)
    zp = (d.body_bottom_m + wb) / 2 if wb - d.body_bottom_m > 0.2 else wb + 0.13
    for k, xp in enumerate(np.linspace(-hb + 3.5, hb - 3.5, 4)):
        pen.rect(xp - 0.2, xp + 0.2, zp - 0.06, zp + 0.06, fill=(235, 235, 225), outline=(30, 30, 30), width_m=0.01)
        pen.text(xp, zp, ["CAUTION", "HEP 480V", "BRAKE", "NO STEP"][k], 0.045, fill=(20, 20, 20))
    # builder's plate near the front-ish end
    pen.rect(hb * 0.62 - 0.18, hb * 0.62 + 0.18, zp - 0.07, zp + 0.07, fill=(60, 60, 60))
    pen.text(hb * 0.62, zp, spec.id.upper()[:10], 0.05, fill=(230, 230, 230))
    _underframe_side(pen, spec, rng, under)
    canvas.paste()


def _clear_of_doors(spec: CarriageSpec, side: str, x: float, half: float) -> bool:
    for dr in spec.doors:
        if side in dr.sides and abs(dr.x_m - x) < dr.width_m / 2 + half:
            return False
    return True


def _window(pen: _Pen, rng, x0, x1, z0, z1, radius, frame, glass) -> None:
    pen.rect(x0 - 0.04, x1 + 0.04, z0 - 0.04, z1 + 0.04, fill=frame, radius_m=radius + 0.04)
    pen.rect(x0, x1, z0, z1, fill=glass, radius_m=radius)
    # seat backs / heads behind the glass, and a reflection
    n = max(1, int((x1 - x0) / 0.45))
    for k in range(n):
        xs = x0 + (k + 0.5) * (x1 - x0) / n
        if rng.random() < 0.8:
            pen.rect(xs - 0.16, xs + 0.16, z0, z0 + min(0.35, 0.45 * (z1 - z0)), fill=_shade(glass, 1.35),
                     radius_m=0.05)
        if rng.random() < 0.35:
            pen.circle(xs + rng.uniform(-0.05, 0.05), z0 + min(0.45, 0.55 * (z1 - z0)), 0.09, fill=_shade(glass, 1.6))
    dz = z1 - z0
    pen.polygon([(x0 + 0.05, z1 - 0.05), (x0 + 0.05 + 0.35 * dz, z1 - 0.05), (x0 + 0.05, z1 - 0.05 - 0.7 * dz)],
                fill=_shade(glass, 1.9))


def _logo(pen: _Pen, x, z, size, color, text) -> None:
    r = size / 2
    pen.circle(x, z, r, fill=color, outline=(255, 255, 255), width_m=0.03)
    pen.circle(x, z, r * 0.8, outline=(255, 255, 255), width_m=0.015)
    pen.text(x, z, text, size * 0.28, fill=(255, 255, 255))


def _underframe_side(pen: _Pen, spec: CarriageSpec, rng, under) -> None:
    d = spec.dimensions
    r = d.wheel_diameter_m / 2
    for lo, hi in bogie_boxes(spec):
        xb = (lo[0] + hi[0]) / 2
        pen.rect(lo[0] + 0.1, hi[0] - 0.1, r - 0.15, r + 0.25, fill=_shade(under, 1.25), outline=(15, 15, 15),
                 width_m=0.02)  # side frame
        for xa in (xb - d.bogie_wheelbase_m / 2, xb + d.bogie_wheelbase_m / 2):
            pen.circle(xa, r, r, fill=(38, 36, 34), outline=(120, 115, 105), width_m=0.03)
            pen.circle(xa, r, r * 0.55, outline=(70, 68, 64), width_m=0.02)
            pen.circle(xa, r, r * 0.18, fill=(150, 140, 120))  # axle box / hub
            for k in range(6):
                a = k * np.pi / 3
                pen.line([(xa + 0.2 * r * np.cos(a), r + 0.2 * r * np.sin(a)),
                          (xa + 0.5 * r * np.cos(a), r + 0.5 * r * np.sin(a))], (80, 78, 72), 0.015)
        for xs in (xb - 0.35, xb + 0.35):  # springs
            for z in np.arange(r + 0.28, min(d.body_bottom_m - 0.05, r + 0.6), 0.05):
                pen.line([(xs - 0.12, z), (xs + 0.12, z + 0.02)], (90, 90, 90), 0.015)
    eq = equipment_box(spec)
    if eq is not None:
        lo, hi = eq
        pen.rect(lo[0], hi[0], lo[2], hi[2], fill=_shade(under, 1.15), outline=(10, 10, 10), width_m=0.015)
        for x in np.arange(lo[0] + 0.8, hi[0] - 0.3, 1.1):
            pen.rect(x - 0.35, x + 0.35, lo[2] + 0.06, hi[2] - 0.06, outline=(70, 70, 70), width_m=0.012)
            pen.circle(x, (lo[2] + hi[2]) / 2, 0.04, fill=(160, 150, 60))


def _paint_end(img: Image.Image, atlas: Atlas, end: str, number: str) -> None:
    spec, d, lv = atlas.spec, atlas.spec.dimensions, atlas.spec.livery
    r = atlas.regions[end]
    e = getattr(spec, end)
    body = _rgb(lv.end_color or lv.body_color)
    canvas = _Canvas(img, r, body)
    pen = canvas.pen
    under = _rgb(lv.underframe_color)
    hw, bb, h, fl = d.width_m / 2, d.body_bottom_m, d.height_m, d.floor_height_m
    eave = spec.profile.eave_height_m
    pen.rect(-hw - 1, hw + 1, -1, bb, fill=under)
    nc = _rgb(lv.number_color)
    for st in lv.stripes:
        if st.on_ends:
            pen.rect(-hw, hw, st.z_bottom_m, st.z_top_m, fill=_rgb(st.color))
    glass = _rgb(lv.window_color)
    frame = _rgb(lv.frame_color)
    if e.shape == "nose":
        base = e.nose_base_height_m
        nose = _rgb(lv.nose_color or lv.end_color or lv.body_color)
        pen.rect(-hw, hw, bb, base, fill=nose)
        for st in lv.stripes:
            if st.on_ends and st.z_top_m <= base:
                pen.rect(-hw, hw, st.z_bottom_m, st.z_top_m, fill=_rgb(st.color))
        pen.line([(-hw, base), (hw, base)], _shade(body, 0.5), 0.03)
        # windscreen on the slope
        z0 = base + 0.3 * (h - base)
        z1 = base + 0.78 * (h - base)
        pen.rect(-hw + 0.25, hw - 0.25, z0 - 0.06, z1 + 0.06, fill=(25, 25, 25), radius_m=0.08)
        for a0, a1 in ((-hw + 0.3, -0.06), (0.06, hw - 0.3)):
            pen.rect(a0, a1, z0, z1, fill=glass, radius_m=0.06)
            pen.polygon([(a0 + 0.05, z1 - 0.04), (a0 + 0.45, z1 - 0.04), (a0 + 0.05, z0 + 0.2)], fill=_shade(glass, 2.2))
            pen.line([((a0 + a1) / 2, z0 + 0.02), ((a0 + a1) / 2 + 0.35, z0 + 0.3)], (15, 15, 15), 0.025)  # wiper
        pen.text(0.0, z1 + 0.18, number, 0.16, fill=(250, 250, 250), stroke=(20, 20, 20))  # number board
        # headlights and ditch lights on the lower nose
        zl = base - 0.3
        for ys in (-1, 1):
            pen.circle(ys * 0.55, zl, 0.11, fill=(245, 245, 225), outline=(30, 30, 30), width_m=0.025)
            pen.circle(ys * (hw - 0.3), bb + 0.25, 0.08, fill=(250, 240, 190), outline=(30, 30, 30), width_m=0.02)
        nh = min(0.2, 0.3 * (base - bb))
        pen.text(0.0, bb + 0.16 + nh / 2, number, nh, fill=(250, 250, 250), stroke=(20, 20, 20))
        pen.rect(-hw + 0.05, hw - 0.05, bb, bb + 0.12, fill=(20, 20, 20))  # anticlimber
    elif spec.kind == "freight_car":  # a wagon's end (a tank's head): no door, no diaphragm; the number only
        pen.text(0.0, (bb + h) / 2 + 0.4, number, 0.16, fill=nc)
        for ys in (-1, 1):  # ladders / grab irons at the corners
            pen.line([(ys * (hw - 0.25), bb + 0.1), (ys * (hw - 0.25), min(fl, h - 0.3))], (200, 170, 40), 0.03)
    else:
        # end door with window, diaphragm, handrails, number
        if e.cab:
            z0, z1 = eave - 1.0, eave - 0.15
            for a0, a1 in ((-hw + 0.2, -0.5), (0.5, hw - 0.2)):
                pen.rect(a0, a1, z0, z1, fill=glass, outline=frame, width_m=0.05, radius_m=0.05)
                pen.line([(a0 + 0.1, z1 - 0.1), (a0 + 0.4, z1 - 0.4)], _shade(glass, 2.2), 0.03)
            for ys in (-1, 1):
                pen.circle(ys * 0.8, fl + 0.25, 0.1, fill=(245, 245, 225), outline=(30, 30, 30), width_m=0.02)
                pen.circle(ys * (hw - 0.3), bb + 0.2, 0.07, fill=(250, 240, 190), outline=(30, 30, 30), width_m=0.02)
        door_top = min(fl + 2.0, h - 0.55)
        pen.rect(-0.72, 0.72, fl - 0.05, door_top + 0.2, outline=(35, 35, 35), width_m=0.06)  # diaphragm
        pen.rect(-0.4, 0.4, fl, door_top, fill=_shade(body, 0.85), outline=(30, 30, 30), width_m=0.025)
        pen.rect(-0.28, 0.28, door_top - 0.95, door_top - 0.25, fill=glass, outline=frame, width_m=0.025,
                 radius_m=0.04)
        pen.circle(0.3, door_top - 1.05, 0.03, fill=(30, 30, 30))
        for ys in (-1, 1):
            pen.line([(ys * 0.95, fl + 0.1), (ys * 0.95, door_top - 0.1)], (230, 190, 30), 0.035)  # grab irons
            pen.line([(ys * (hw - 0.15), bb + 0.1), (ys * (hw - 0.15), fl + 1.2)], (30, 30, 30), 0.03)
        zl0, zl1 = fl + 1.2, min(fl + 1.9, eave - 0.1)
        if not e.cab and zl1 > zl0 + 0.2:
            for k, ys in enumerate((-1, 1)):  # louvres / MU receptacles
                y0 = ys * 1.05
                pen.rect(min(y0, ys * (hw - 0.2)), max(y0, ys * (hw - 0.2)), zl0, zl1, fill=_shade(body, 0.5))
                for z in np.arange(zl0 + 0.05, zl1 - 0.02, 0.05):
                    pen.line([(y0, z), (ys * (hw - 0.2), z)], _shade(body, 0.9), 0.012)
        if door_top + 0.45 < h - 0.15:
            pen.text(0.0, door_top + 0.38, number, 0.22, fill=nc)
        else:
            pen.text(1.2 if hw > 1.45 else 0.9, fl + 0.35, number, 0.13, fill=nc)
        for ys in (-1, 1):  # jumper boxes and hoses
            pen.rect(ys * 0.5 - 0.12, ys * 0.5 + 0.12, bb + 0.05, bb + 0.3, fill=(45, 45, 45), outline=(10, 10, 10),
                     width_m=0.01)
            pen.line([(ys * 0.5, bb + 0.05), (ys * 0.3, bb - 0.3)], (20, 20, 20), 0.04)
        pen.rect(-hw + 0.05, hw - 0.05, bb, bb + 0.1, fill=(25, 25, 25))  # end sill
    # underframe / coupler seen end-on
    zc = d.coupler_height_m
    pen.rect(-0.3, 0.3, zc - 0.2, zc + 0.2, fill=(50, 50, 50), outline=(10, 10, 10), width_m=0.02)
    pen.rect(-0.14, 0.14, zc - 0.13, zc + 0.13, fill=(70, 65, 60), outline=(15, 15, 15), width_m=0.02)
    for ys in (-1, 1):
        yw = ys * (d.gauge_m / 2 + 0.035)
        pen.rect(yw - 0.07, yw + 0.07, 0.0, d.wheel_diameter_m, fill=(40, 38, 35))
    canvas.paste()


def _paint_roof(img: Image.Image, atlas: Atlas, region: str, number: str) -> None:
    spec, d, lv = atlas.spec, atlas.spec.dimensions, atlas.spec.livery
    r = atlas.regions[region]
    base = _rgb(lv.roof_color if region == "roof" else lv.underframe_color)
    canvas = _Canvas(img, r, base)
    pen = canvas.pen
    if region != "roof":
        canvas.paste()
        return
    hb, hw = d.body_length_m / 2, d.width_m / 2
    rng = np.random.default_rng(_seed(spec, number, "roof"))
    for x in np.arange(-hb + 0.8, hb, 1.25):
        pen.line([(x, -hw + 0.2), (x, hw - 0.2)], _shade(base, 0.8), 0.015)
    for x in np.linspace(-hb * 0.7, hb * 0.7, 5):  # hatches / A/C units / fans
        if spec.kind == "locomotive":
            pen.circle(x, 0.0, 0.5, fill=_shade(base, 0.55), outline=(30, 30, 30), width_m=0.03)
            for k in range(8):
                a = k * np.pi / 4 + rng.uniform(0, 0.2)
                pen.line([(x, 0.0), (x + 0.45 * np.cos(a), 0.45 * np.sin(a))], (40, 40, 40), 0.02)
        else:
            pen.rect(x - 0.9, x + 0.9, -0.8, 0.8, fill=_shade(base, 1.15), outline=(50, 50, 50), width_m=0.02,
                     radius_m=0.1)
            for y in np.arange(-0.6, 0.61, 0.12):
                pen.line([(x - 0.7, y), (x + 0.7, y)], _shade(base, 0.7), 0.012)
    pen.text(hb - 1.5, 0.0, number, 0.3, fill=(40, 40, 40))
    canvas.paste()


def _grime(img: Image.Image, atlas: Atlas, number: str, strength: float) -> Image.Image:
    if strength <= 0:
        return img
    a = np.asarray(img, dtype=np.float32)
    rng = np.random.default_rng(_seed(atlas.spec, number, "grime"))
    for name, r in atlas.regions.items():
        sl = (slice(r.y0, r.y0 + r.h), slice(r.x0, r.x0 + r.w))
        hh, ww = r.h, r.w
        low = rng.random((max(2, hh // 48), max(2, ww // 48))).astype(np.float32)
        low = np.asarray(Image.fromarray((low * 255).astype(np.uint8)).resize((ww, hh), Image.BILINEAR),
                         dtype=np.float32) / 255.0
        f = 1.0 - strength * 0.22 * low
        if name in ("left", "right", "front", "rear"):
            rows = np.linspace(0.0, 1.0, hh, dtype=np.float32)[:, None]
            f = f * (1.0 - strength * 0.25 * rows ** 3)  # dirtier towards the bottom
            # rain streaks running down from the roof and the windows
            for _ in range(int(ww / 12)):
                c = int(rng.integers(0, ww))
                r0 = int(rng.integers(0, hh // 2))
                r1 = min(hh, r0 + int(rng.integers(hh // 8, hh // 2)))
                f[r0:r1, c:c + 2] *= 1.0 - strength * rng.uniform(0.05, 0.2)
        spots = rng.integers(0, [hh, ww], size=(int(hh * ww / 900), 2))
        f[spots[:, 0], spots[:, 1]] *= 1.0 - strength * 0.5
        a[sl] *= f[..., None]
    out = Image.fromarray(np.clip(a, 0, 255).astype(np.uint8))
    return out.filter(ImageFilter.SMOOTH) if strength > 0.8 else out


def paint_atlas(spec: CarriageSpec, car_number: str) -> tuple[Atlas, Image.Image]:
    """Paint the texture atlas for one car (deterministic for a given type and car number)."""
    atlas = Atlas(spec)
    img = Image.new("RGB", (atlas.width, atlas.height), _rgb(spec.livery.underframe_color))
    for region in ("roof", "under"):
        _paint_roof(img, atlas, region, car_number)
    for side in ("left", "right"):
        _paint_side(img, atlas, side, car_number)
    for end in ("front", "rear"):
        _paint_end(img, atlas, end, car_number)
    img = _grime(img, atlas, car_number, spec.livery.grime)
    return atlas, img
