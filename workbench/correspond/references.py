"""Reference imagery of each carriage's planar faces, with the marked points' pixel positions.

A carriage's sides (and flat ends) are planes. Their orthographic, fronto-parallel view is exactly the
face's region of the car's livery atlas (``workbench/rolling_stock/livery.py`` paints each region in
carriage-frame metres, as seen from outside), so a reference is that region cropped to the planar wall
(``body_bottom_m`` to ``eave_height_m``; for a nose end, up to the nose base) and resampled to
``px_per_m``. It is painted per **car number**: the number and the grime are per car, which is what tells
identical coaches apart.

The resampling averages **light**, not sRGB code values (:func:`resize_linear_light`): a camera pixel, and the
renderer's supersampled pixel, integrate radiance and encode the result, so a dark window frame seen at a
fraction of a pixel comes out lighter than the average of the sRGB values. Averaging the sRGB values instead
moved the reference's light/dark edges against the rendered livery: the Shoreliner's side read as 0.5 %
compressed vertically against a render of the car (0.10 px RMS, 0.21 px at the corners, at 25 px/m); now
0.01-0.04 px RMS (``tests/test_livery_alignment.py``).

Reference pixels follow ``docs/conventions.md``: pixel (0, 0) is the centre of the top-left pixel.
``carriage_from_ref`` maps a reference pixel to carriage-frame metres on the face's plane.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..rolling_stock import CarriageType
from ..rolling_stock.geometry import nose_x
from ..rolling_stock.livery import Atlas

log = logging.getLogger(__name__)

FACES = ("left", "right", "front", "rear", "roof")
# carriage-frame axes of each face's (horizontal, vertical) reference coordinates, as in the livery atlas
_AXES = {"left": (0, 2), "right": (0, 2), "front": (1, 2), "rear": (1, 2), "roof": (0, 1)}
_PLANE_TOL_M = 0.01  # a marked point within 1 cm of the face plane is transferred by the face's homography


@dataclass
class FaceReference:
    """One planar face of one car, as a fronto-parallel image.

    ``image``: (h, w, 3) uint8 RGB; ``px_per_m``: reference pixels per metre; ``points``: marked point name
    -> (2,) reference pixel for the points on this face's plane; ``origin_m``, ``axis_u_m``, ``axis_v_m``:
    the carriage-frame point of reference pixel (0, 0) and the carriage-frame displacement (3,) metres of one
    pixel step in u and in v; ``mask``: (h, w) uint8, 255 where the pixel lies on the car's surface and 0 where
    it does not (the corner a sloped nose cuts off a side: painted there, but not on the car), or None when every
    pixel does.
    """

    type_id: str
    car_number: str
    face: str
    image: np.ndarray
    px_per_m: float
    points: dict[str, np.ndarray]
    origin_m: np.ndarray
    axis_u_m: np.ndarray
    axis_v_m: np.ndarray
    keypoints: np.ndarray | None = field(default=None, repr=False)  # (n, 2) reference px
    descriptors: np.ndarray | None = field(default=None, repr=False)  # (n, 128) float32
    frames: np.ndarray | None = field(default=None, repr=False)  # (n, 4) size, angle, tilt (sift_features)
    mask: np.ndarray | None = field(default=None, repr=False)

    @property
    def key(self) -> tuple[str, str]:
        return (self.car_number, self.face)

    def carriage_from_ref(self, uv: np.ndarray) -> np.ndarray:
        """Reference pixels (n, 2) -> carriage-frame points (n, 3) metres on the face's plane."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return self.origin_m + uv[:, :1] * self.axis_u_m + uv[:, 1:] * self.axis_v_m

    def corners(self) -> np.ndarray:
        """(4, 2) reference pixels of the image's corners (pixel edges), clockwise from top-left."""
        h, w = self.image.shape[:2]
        return np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])


def _face_window(ct: CarriageType, face: str) -> tuple[float, float, float, float, float]:
    """(a0, a1, b0, b1, plane coordinate) of the planar part of ``face``, metres: a and b are the face's two
    carriage-frame axes (``_AXES``: x and z for sides, y and z for ends, x and y for the roof); the plane is
    y = const (sides), x = const (ends) or z = const (the flat top of the roof)."""
    d, p = ct.spec.dimensions, ct.spec.profile
    wall_bottom = p.wall_bottom_m if p.wall_bottom_m is not None else d.body_bottom_m
    hw = d.width_m / 2
    if face in ("left", "right"):
        z0, z1 = wall_bottom, p.eave_height_m
        # the whole body length (a nose end cuts a corner off the wall: painted background there, harmless)
        xf = max(nose_x(ct.spec, "front", z0), nose_x(ct.spec, "front", z1))
        xr = min(nose_x(ct.spec, "rear", z0), nose_x(ct.spec, "rear", z1))
        return xr, xf, z0, z1, (hw if face == "left" else -hw)
    if face == "roof":
        top = hw - p.roof_edge_inset_m if p.roof_edge_inset_m > 0 else hw
        h = d.height_m
        return float(nose_x(ct.spec, "rear", h)), float(nose_x(ct.spec, "front", h)), -top, top, h
    end = getattr(ct.spec, face)
    z0 = d.body_bottom_m
    z1 = end.nose_base_height_m if end.shape == "nose" else p.eave_height_m
    return -hw, hw, z0, z1, float(nose_x(ct.spec, face, z0))


_SRGB_TO_LINEAR = np.where(np.arange(256) / 255.0 <= 0.04045, np.arange(256) / 255.0 / 12.92,
                           ((np.arange(256) / 255.0 + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_from_srgb8(image: np.ndarray) -> np.ndarray:
    """8-bit sRGB (any shape) -> linear light in [0, 1], float32."""
    return _SRGB_TO_LINEAR[np.asarray(image, dtype=np.uint8)]


def srgb8_from_linear(lin: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] -> 8-bit sRGB (rounded)."""
    c = np.clip(np.asarray(lin, dtype=np.float64), 0.0, 1.0)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


def resize_linear_light(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """An 8-bit sRGB image (h, w[, c]) resized to ``size`` = (width, height), averaging light.

    Area averaging (``INTER_AREA``) when shrinking, bicubic when enlarging, done on linear light and encoded
    back to sRGB. Pixel centres are kept (``cv2.resize``): output pixel centre ``c`` is input ``(c + 0.5) / s - 0.5``.
    """
    w, h = int(size[0]), int(size[1])
    shrink = w <= image.shape[1] and h <= image.shape[0]
    lin = cv2.resize(linear_from_srgb8(image), (w, h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC)
    return srgb8_from_linear(lin)


# the direction a face is seen along (from outside the car) and the image's up direction, carriage frame
_VIEW = {"left": ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)), "right": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
         "front": ((-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)), "rear": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
         "roof": ((0.0, 0.0, -1.0), (1.0, 0.0, 0.0))}


def mesh_face_view(ct: CarriageType, car_number: str, face: str, px_per_m: float) -> FaceReference:
    """A mesh type's face as the picker shows it: the model seen orthographically from outside that face,
    shaded by the slope of its triangles, with every marked point of the face where it projects (a mesh type
    has no painted livery to crop; nothing is matched against this view)."""
    from PIL import Image, ImageDraw

    view, up = (np.asarray(v, float) for v in _VIEW[face])
    right = np.cross(view, up)
    m = ct.mesh(car_number, textured=False)
    V, F = np.asarray(m.vertices, float), np.asarray(m.faces)
    a, b, depth = V @ right, V @ up, -(V @ view)
    margin = 0.25  # metres around the model: points at its extremes (couplers) are inside the image
    a0, b1 = float(a.min()) - margin, float(b.max()) + margin
    w = max(8, int(np.ceil((a.max() + margin - a0) * px_per_m)) + 1)
    h = max(8, int(np.ceil((b1 - b.min() + margin) * px_per_m)) + 1)
    img = Image.new("RGB", (w, h), (250, 250, 250))
    draw = ImageDraw.Draw(img)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    facing = np.abs(n @ view) / np.maximum(np.linalg.norm(n, axis=1), 1e-12)
    u, v = (a - a0) * px_per_m, (b1 - b) * px_per_m
    for t in np.argsort(depth[F].mean(axis=1)):  # far first: the near triangles are drawn over them
        g = int(60 + 130 * facing[t])  # faces square to the view lightest, grazing ones dark
        draw.polygon([(float(u[i]), float(v[i])) for i in F[t]], fill=(g - 15, g - 5, g))
    origin = a0 * right + b1 * up + float(depth.max()) * -view
    points = {name: np.array([(xyz @ right - a0) * px_per_m - 0.5, (b1 - xyz @ up) * px_per_m - 0.5])
              for name, xyz in ct.marked_points.items() if face in ct.marked_point_faces[name]}
    return FaceReference(ct.id, car_number, face, np.ascontiguousarray(np.asarray(img)), float(px_per_m), points,
                         origin, right / px_per_m, -up / px_per_m)


def face_reference(ct: CarriageType, car_number: str, face: str, px_per_m: float) -> FaceReference:
    """The reference of one face of car ``car_number`` of type ``ct``, resampled to ``px_per_m`` (a mesh type's:
    :func:`mesh_face_view`)."""
    if face not in FACES:
        raise ValueError(f"face={face!r} but expected one of {FACES}")
    if ct.is_mesh_type:
        return mesh_face_view(ct, car_number, face, px_per_m)
    atlas, img = ct.texture(car_number)
    assert isinstance(atlas, Atlas)
    A = np.asarray(img.convert("RGB"))
    r = atlas.regions[face]
    a0, a1, z0, z1, plane = _face_window(ct, face)  # z: the face's second axis (y on the roof)
    # atlas px/py are pixel-edge coordinates (UV * size); the crop spans the window's edges
    xs = sorted([float(r.px(a0)), float(r.px(a1))])
    ys = sorted([float(r.py(z0)), float(r.py(z1))])
    ix0, ix1 = int(np.floor(xs[0])), int(np.ceil(xs[1]))
    iy0, iy1 = int(np.floor(ys[0])), int(np.ceil(ys[1]))
    crop = A[iy0:iy1, ix0:ix1]
    s = px_per_m / float(r.su)
    w, h = max(8, int(round(crop.shape[1] * s))), max(8, int(round(crop.shape[0] * s)))
    sx, sy = w / crop.shape[1], h / crop.shape[0]
    image = resize_linear_light(crop, (w, h))

    # reference pixel centre (u, v) <-> atlas edge coordinate: ex = ix0 + (u + 0.5) / sx
    # region: ex = x0 + (ua * a + ub) * su  ->  a = ((ex - x0) / su - ub) / ua ; same for z with (va, vb, sv)
    def a_of_u(u):
        ex = ix0 + (np.asarray(u, float) + 0.5) / sx
        return ((ex - r.x0) / r.su - r.ub) / r.ua

    def z_of_v(v):
        ey = iy0 + (np.asarray(v, float) + 0.5) / sy
        return ((ey - r.y0) / r.sv - r.vb) / r.va

    ia, ib = _AXES[face]
    plane_axis = 3 - ia - ib

    def to3(a, z):
        xyz = np.empty(3)
        xyz[ia], xyz[ib], xyz[plane_axis] = a, z, plane
        return xyz

    mask = None
    if face in ("left", "right"):  # a nose's slope cuts a corner off the side's window: not on the car
        a, z = a_of_u(np.arange(w)), z_of_v(np.arange(h))
        on = (a[None, :] <= np.asarray(nose_x(ct.spec, "front", z))[:, None]) & \
            (a[None, :] >= np.asarray(nose_x(ct.spec, "rear", z))[:, None])
        mask = None if on.all() else np.where(on, 255, 0).astype(np.uint8)
    origin = to3(a_of_u(0.0), z_of_v(0.0))
    axis_u = to3(a_of_u(1.0), z_of_v(0.0)) - origin
    axis_v = to3(a_of_u(0.0), z_of_v(1.0)) - origin
    points = {}
    for name, xyz in ct.marked_points.items():
        if face not in ct.marked_point_faces[name] or abs(xyz[plane_axis] - plane) > _PLANE_TOL_M:
            continue
        u = (r.x0 + (r.ua * xyz[ia] + r.ub) * r.su - ix0) * sx - 0.5
        v = (r.y0 + (r.va * xyz[ib] + r.vb) * r.sv - iy0) * sy - 0.5
        points[name] = np.array([u, v])
    return FaceReference(ct.id, car_number, face, np.ascontiguousarray(image), float(px_per_m), points,
                         origin, axis_u, axis_v, mask=mask)


Tilt = tuple[float, float]


def sift_features(image: np.ndarray, tilts: tuple[Tilt, ...] = ((1.0, 1.0),), *, contrast_threshold: float = 0.02,
                  frames: bool = False) -> tuple[np.ndarray, ...]:
    """SIFT keypoints (n, 2) px and descriptors (n, 128) of an RGB/grey image, pooled over tilts.

    A tilt ``(tx, ty)`` compresses the image by ``tx`` horizontally and ``ty`` vertically before detection
    (the foreshortening of a carriage side seen at an angle along it, or from above; as in ASIFT);
    keypoints are mapped back to the untilted image. With ``frames``, a third array (n, 4) gives each
    keypoint's ``(size px, angle deg, tx, ty)``: its SIFT scale and orientation in the image it was detected
    in (the tilted one; OpenCV's angle convention) and that image's tilt.
    """
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    sift = cv2.SIFT_create(contrastThreshold=contrast_threshold)
    kps, descs, frs = [], [], []
    for tx, ty in tilts:
        w = max(8, int(round(gray.shape[1] / tx)))
        h = max(8, int(round(gray.shape[0] / ty)))
        img = gray if (w, h) == (gray.shape[1], gray.shape[0]) else cv2.resize(gray, (w, h),
                                                                                interpolation=cv2.INTER_AREA)
        kp, d = sift.detectAndCompute(img, None)
        if d is None or not kp:
            continue
        xy = np.array([k.pt for k in kp], dtype=np.float64)
        xy[:, 0] = (xy[:, 0] + 0.5) * gray.shape[1] / w - 0.5
        xy[:, 1] = (xy[:, 1] + 0.5) * gray.shape[0] / h - 0.5
        kps.append(xy)
        descs.append(d.astype(np.float32))
        sx, sy = w / gray.shape[1], h / gray.shape[0]  # the exact compressions of the resized image
        frs.append(np.array([[k.size, k.angle, 1.0 / sx, 1.0 / sy] for k in kp], dtype=np.float64))
    if not kps:
        empty = (np.zeros((0, 2)), np.zeros((0, 128), np.float32))
        return empty + (np.zeros((0, 4)),) if frames else empty
    if frames:
        return np.vstack(kps), np.vstack(descs), np.vstack(frs)
    return np.vstack(kps), np.vstack(descs)


MATCH_FACES = ("left", "right", "front", "rear")  # the roof (hatches, few features) found nothing on the samples


def build_references(ct: CarriageType, car_number: str, *, px_per_m: float, tilts: tuple[Tilt, ...],
                     end_tilts: tuple[Tilt, ...] = ((1.0, 1.0),), faces: tuple[str, ...] = MATCH_FACES,
                     ) -> list[FaceReference]:
    """The face references of one car (``faces``), with SIFT features."""
    refs = []
    for face in faces:
        ref = face_reference(ct, car_number, face, px_per_m)
        ref.keypoints, ref.descriptors, ref.frames = sift_features(
            ref.image, tilts if face in ("left", "right", "roof") else end_tilts, frames=True)
        if ref.mask is not None:  # no features where the painted window is not the car
            ij = np.clip(np.round(ref.keypoints).astype(int), 0, [ref.mask.shape[1] - 1, ref.mask.shape[0] - 1])
            on = ref.mask[ij[:, 1], ij[:, 0]] > 0
            ref.keypoints, ref.descriptors, ref.frames = ref.keypoints[on], ref.descriptors[on], ref.frames[on]
        log.debug("reference %s %s %s: %d keypoints", ct.id, car_number, face, len(ref.keypoints))
        refs.append(ref)
    return refs
