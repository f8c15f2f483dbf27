"""The camera model's undistortion (``CameraIntrinsics.undistort``): the inverse of its distortion."""

from __future__ import annotations

import numpy as np
import pytest

from workbench.core.camera import CameraIntrinsics

LENSES = [(-0.12, 0.03, 0.0, 0.001, -0.0005), (0.08, -0.02, 0.005, 0.0, 0.0), (-0.3, 0.1, -0.01, 0.002, 0.001)]


@pytest.mark.parametrize("k1, k2, k3, p1, p2", LENSES)
def test_undistort_inverts_distort(k1, k2, k3, p1, p2):
    K = CameraIntrinsics(width=800, height=600, fx=700.0, fy=690.0, cx=401.0, cy=298.0, skew=0.5,
                         k1=k1, k2=k2, k3=k3, p1=p1, p2=p2)
    u, v = np.meshgrid(np.linspace(-0.5, 799.5, 41), np.linspace(-0.5, 599.5, 31))
    xy_d = K.normalized_from_pixels(np.column_stack([u.ravel(), v.ravel()]))
    xy_d[0] = [0.0, 0.0]
    xy = K.undistort(xy_d)
    assert xy.shape == xy_d.shape and xy.flags.writeable
    assert np.abs(K.distort(xy) - xy_d).max() < 1e-12  # every point, the corners of the image included
    assert np.array_equal(xy[0], [0.0, 0.0])
    # a pixel through the camera and back
    uv = np.array([[12.5, 580.0], [400.0, 300.0], [790.0, 3.0]])
    assert np.abs(K.project(K.rays(uv) * 7.0) - uv).max() < 1e-8


def test_undistort_keeps_a_nan_and_copies_without_distortion():
    K = CameraIntrinsics(width=800, height=600, fx=700.0, fy=700.0, cx=400.0, cy=300.0, k1=-0.2, k2=0.05)
    xy_d = np.array([[0.1, -0.2], [np.nan, 0.3], [0.25, 0.15]])
    xy = K.undistort(xy_d)
    assert np.isnan(xy[1, 0]) and np.all(np.isfinite(xy[[0, 2]]))
    assert np.abs(K.distort(xy[[0, 2]]) - xy_d[[0, 2]]).max() < 1e-12
    plain = CameraIntrinsics(width=800, height=600, fx=700.0, fy=700.0, cx=400.0, cy=300.0)
    out = plain.undistort(xy_d)
    assert np.array_equal(out, xy_d, equal_nan=True) and out is not xy_d
