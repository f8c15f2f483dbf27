"""COLMAP's cameras and the workbench's Brown model (``docs/conventions.md``): the models that map exactly, and the
conversions both ways. COLMAP puts the centre of the top-left pixel at (0.5, 0.5), we put it at (0, 0)."""

from __future__ import annotations

from typing import Literal, get_args

from ..core.camera import CameraIntrinsics

CameraModel = Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"]
CAMERA_MODELS = get_args(CameraModel)


def intrinsics_from_colmap(model: str, width: int, height: int, params) -> CameraIntrinsics:
    """Our :class:`CameraIntrinsics` of a COLMAP camera (exact for the models of :data:`CAMERA_MODELS`).

    COLMAP's principal point is 0.5 px larger than ours (its top-left pixel centre is at (0.5, 0.5)).
    """
    p = [float(x) for x in params]
    if model == "SIMPLE_PINHOLE":
        f, cx, cy = p
        d = dict(fx=f, fy=f, cx=cx, cy=cy)
    elif model == "PINHOLE":
        fx, fy, cx, cy = p
        d = dict(fx=fx, fy=fy, cx=cx, cy=cy)
    elif model == "SIMPLE_RADIAL":
        f, cx, cy, k = p
        d = dict(fx=f, fy=f, cx=cx, cy=cy, k1=k)
    elif model == "RADIAL":
        f, cx, cy, k1, k2 = p
        d = dict(fx=f, fy=f, cx=cx, cy=cy, k1=k1, k2=k2)
    elif model == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = p
        d = dict(fx=fx, fy=fy, cx=cx, cy=cy, k1=k1, k2=k2, p1=p1, p2=p2)
    else:
        raise ValueError(f"COLMAP camera model {model!r} has no exact Brown equivalent; use one of {CAMERA_MODELS}")
    d["cx"] -= 0.5
    d["cy"] -= 0.5
    return CameraIntrinsics(width=int(width), height=int(height), **d)


def colmap_params_from_intrinsics(model: str, intr: CameraIntrinsics) -> tuple[list[float], list[str]]:
    """COLMAP ``params`` of ``model`` for our intrinsics, and the terms the model cannot hold (dropped)."""
    cx, cy = intr.cx + 0.5, intr.cy + 0.5
    f = 0.5 * (intr.fx + intr.fy)
    dropped = []
    if intr.skew != 0.0:
        dropped.append("skew")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL") and intr.fx != intr.fy:
        dropped.append("fx != fy")
    names = {"SIMPLE_PINHOLE": ("k1", "k2", "k3", "p1", "p2"), "PINHOLE": ("k1", "k2", "k3", "p1", "p2"),
             "SIMPLE_RADIAL": ("k2", "k3", "p1", "p2"), "RADIAL": ("k3", "p1", "p2"), "OPENCV": ("k3",)}[model]
    dropped += [n for n in names if getattr(intr, n) != 0.0]
    params = {"SIMPLE_PINHOLE": [f, cx, cy], "PINHOLE": [intr.fx, intr.fy, cx, cy],
              "SIMPLE_RADIAL": [f, cx, cy, intr.k1], "RADIAL": [f, cx, cy, intr.k1, intr.k2],
              "OPENCV": [intr.fx, intr.fy, cx, cy, intr.k1, intr.k2, intr.p1, intr.p2]}[model]
    return [float(x) for x in params], dropped
