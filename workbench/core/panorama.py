"""The exact camera model of a stitched panorama: projection, scale, offset and every source photo's rotation.

A panorama made by the stitch stage (``workbench/stitch``) is a central image: every pixel is a ray from
one camera centre. Its frame ``pano`` is camera-like (``docs/conventions.md``): x right, y down, z forward,
the centre at the origin. A direction ``d = (x, y, z)`` in ``pano`` maps to *warped* coordinates exactly as
OpenCV's rotation warpers (``cv2.PyRotationWarper``) map them, with ``s = scale``:

* ``planar``:      ``(s x / z, s y / z)`` (the panorama is an exact pinhole image; ``z > 0`` only)
* ``cylindrical``: ``(s atan2(x, z), s y / sqrt(x^2 + z^2))``
* ``spherical``:   ``(s atan2(x, z), s (pi/2 + asin(y / |d|)))``

and a panorama pixel is ``uv = warped - offset`` (pixel (0, 0) is the centre of the top-left pixel, as in
``docs/conventions.md``). Each source photo ``i`` sees the direction as ``cam_from_pano_i @ d`` through its
own :class:`~workbench.core.camera.CameraIntrinsics` (the photo as on disk, with its distortion), so a
panorama pixel maps exactly into the photo it came from and back. No I/O here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .camera import CameraIntrinsics

PROJECTIONS = ("planar", "cylindrical", "spherical")
# keys of panorama.json that are metadata of the stitch run (read and ignored by PanoramaModel.from_dict)
METADATA_KEYS = ("rejected", "intrinsics_source", "parallax", "registration", "format")


def _rows(x: np.ndarray, width: int, name: str) -> np.ndarray:
    """``x`` as an (N, width) float array (one row given as (width,) becomes (1, width)); else ValueError."""
    a = np.asarray(x, dtype=float)
    if a.shape == (width,):
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != width:
        raise ValueError(f"{name}.shape={np.shape(x)} but expected (N, {width})")
    return a


@dataclass(frozen=True, kw_only=True)
class PanoramaSource:
    """One source photo of a panorama: its name, path, intrinsics as on disk, and ``cam_from_pano`` (3, 3)."""

    name: str
    image: str
    intrinsics: CameraIntrinsics
    cam_from_pano: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        R = np.asarray(self.cam_from_pano, dtype=float)
        if R.shape != (3, 3):
            raise ValueError(f"source {self.name!r}: cam_from_pano.shape={R.shape} but expected (3, 3)")
        if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and abs(np.linalg.det(R) - 1.0) < 1e-6):
            raise ValueError(f"source {self.name!r}: cam_from_pano is not a rotation (orthonormal, det +1)")
        R = R.copy()
        R.setflags(write=False)
        object.__setattr__(self, "cam_from_pano", R)

    def to_dict(self) -> dict:
        return {"name": self.name, "image": self.image, "intrinsics": self.intrinsics.to_dict(),
                "cam_from_pano": self.cam_from_pano.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "PanoramaSource":
        unknown = set(d) - {"name", "image", "intrinsics", "cam_from_pano"}
        if unknown:
            raise ValueError(f"panorama source: unknown key(s) {sorted(unknown)}")
        return cls(name=str(d["name"]), image=str(d["image"]), intrinsics=CameraIntrinsics.from_dict(d["intrinsics"]),
                   cam_from_pano=np.asarray(d["cam_from_pano"], dtype=float))


@dataclass(frozen=True, kw_only=True)
class PanoramaModel:
    """A panorama's exact camera model (see the module docstring for the formulas).

    ``scale``: warped units per radian (cylindrical, spherical) or per unit of the z = 1 plane (planar), i.e.
    the panorama's focal length in pixels. ``offset = (x0, y0)``: panorama pixel = warped - offset.
    ``width``, ``height``: the panorama image size in pixels.
    """

    projection: str
    scale: float
    offset: tuple[float, float]
    width: int
    height: int
    sources: tuple[PanoramaSource, ...]

    def __post_init__(self) -> None:
        if self.projection not in PROJECTIONS:
            raise ValueError(f"projection={self.projection!r}; expected one of {PROJECTIONS}")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"scale={self.scale} must be finite and positive")
        off = tuple(float(x) for x in self.offset)
        if len(off) != 2 or not all(np.isfinite(off)):
            raise ValueError(f"offset={self.offset!r} must be two finite numbers (x0, y0)")
        object.__setattr__(self, "offset", off)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"panorama size {self.width}x{self.height} must be positive")
        object.__setattr__(self, "sources", tuple(self.sources))

    # -- the projection ------------------------------------------------------------------------------------
    def project(self, dirs_pano: np.ndarray) -> np.ndarray:
        """Directions in ``pano`` (N, 3) (any length) -> panorama pixels (N, 2). NaN where undefined.

        Undefined: planar with ``z <= 0``; the zero vector.
        """
        return self.project_with_jacobian(dirs_pano, jacobian=False)[0]

    def project_with_jacobian(self, dirs_pano: np.ndarray, jacobian: bool = True
                              ) -> tuple[np.ndarray, np.ndarray | None]:
        """Panorama pixels (N, 2) and the exact Jacobian d(u, v)/d(x, y, z) (N, 2, 3) of :meth:`project`."""
        d = _rows(dirs_pano, 3, "dirs_pano")
        x, y, z = d[:, 0], d[:, 1], d[:, 2]
        s = self.scale
        J = np.zeros((len(d), 2, 3)) if jacobian else None
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.projection == "planar":
                bad = ~(z > 0)
                a, b = x / z, y / z
                if jacobian:
                    J[:, 0, 0] = s / z
                    J[:, 0, 2] = -s * x / z**2
                    J[:, 1, 1] = s / z
                    J[:, 1, 2] = -s * y / z**2
            else:
                rho2 = x * x + z * z
                rho = np.sqrt(rho2)
                a = np.arctan2(x, z)
                if jacobian:
                    J[:, 0, 0] = s * z / rho2
                    J[:, 0, 2] = -s * x / rho2
                if self.projection == "cylindrical":
                    bad = ~(rho > 0)
                    b = y / rho
                    if jacobian:
                        J[:, 1, 0] = -s * y * x / rho**3
                        J[:, 1, 1] = s / rho
                        J[:, 1, 2] = -s * y * z / rho**3
                else:  # spherical
                    n2 = rho2 + y * y
                    bad = ~(rho > 0)
                    b = np.pi / 2 + np.arctan2(y, rho)  # = pi/2 + asin(y / |d|), stable near the poles
                    if jacobian:
                        J[:, 1, 0] = -s * y * x / (rho * n2)
                        J[:, 1, 1] = s * rho / n2
                        J[:, 1, 2] = -s * y * z / (rho * n2)
        uv = np.column_stack([s * a - self.offset[0], s * b - self.offset[1]])
        uv[bad] = np.nan
        if jacobian:
            J[bad] = np.nan
        return uv, J

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Panorama pixels (N, 2) -> unit directions in ``pano`` (N, 3)."""
        p = _rows(uv, 2, "uv")
        a = (p[:, 0] + self.offset[0]) / self.scale
        b = (p[:, 1] + self.offset[1]) / self.scale
        if self.projection == "planar":
            d = np.column_stack([a, b, np.ones(len(p))])
        elif self.projection == "cylindrical":
            d = np.column_stack([np.sin(a), b, np.cos(a)])
        else:
            phi = b - np.pi / 2
            d = np.column_stack([np.cos(phi) * np.sin(a), np.sin(phi), np.cos(phi) * np.cos(a)])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    # -- source photos ---------------------------------------------------------------------------------------
    def source_index(self, name: str) -> int:
        for i, s in enumerate(self.sources):
            if s.name == name:
                return i
        raise KeyError(f"{name!r} is not a source of this panorama; sources: {[s.name for s in self.sources]}")

    def to_source(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Panorama pixels (N, 2) -> (source index (N,) int, pixels in that source photo as on disk (N, 2)).

        Among the photos whose image contains the ray, the one whose optical axis is closest to it is chosen.
        Index -1 and NaN pixels where no source photo sees the ray.
        """
        d = self.rays(uv)
        n = len(d)
        best = np.full(n, -1, dtype=int)
        best_cos = np.full(n, -np.inf)
        best_uv = np.full((n, 2), np.nan)
        for i, src in enumerate(self.sources):
            cam = d @ src.cam_from_pano.T
            with np.errstate(invalid="ignore"):
                px = src.intrinsics.project(cam)
            ok = (cam[:, 2] > 0) & np.all(np.isfinite(px), axis=1)
            ok[ok] = src.intrinsics.in_image(px[ok])
            # distortion folds back far outside the image: keep only rays that map back onto themselves
            if ok.any() and src.intrinsics.has_distortion:
                back = src.intrinsics.rays(px[ok])
                ok[np.flatnonzero(ok)] = np.einsum("ij,ij->i", back, cam[ok]) > 1.0 - 1e-9
            take = ok & (cam[:, 2] > best_cos)
            best[take] = i
            best_cos[take] = cam[take, 2]
            best_uv[take] = px[take]
        return best, best_uv

    def from_source(self, index: int | np.ndarray, uv_src: np.ndarray) -> np.ndarray:
        """Pixels of source photo(s) ``index`` (int or (N,) ints) as on disk (N, 2) -> panorama pixels (N, 2)."""
        p = _rows(uv_src, 2, "uv_src")
        idx = np.broadcast_to(np.asarray(index, dtype=int), (len(p),))
        d = np.full((len(p), 3), np.nan)
        for i in np.unique(idx):
            if not (0 <= i < len(self.sources)):
                raise IndexError(f"source index {i} out of range (0..{len(self.sources) - 1})")
            m = idx == i
            src = self.sources[i]
            d[m] = src.intrinsics.rays(p[m]) @ src.cam_from_pano  # pano_from_cam = cam_from_pano.T
        return self.project(d)

    # -- files -----------------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {"projection": self.projection, "scale": float(self.scale), "offset": [*self.offset],
                "width": int(self.width), "height": int(self.height),
                "sources": [s.to_dict() for s in self.sources]}

    @classmethod
    def from_dict(cls, d: dict) -> "PanoramaModel":
        """From ``panorama.json`` (the stitch run's metadata keys are accepted and ignored; others are refused)."""
        known = {"projection", "scale", "offset", "width", "height", "sources", *METADATA_KEYS}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"panorama model: unknown key(s) {sorted(unknown)}")
        missing = {"projection", "scale", "offset", "width", "height", "sources"} - set(d)
        if missing:
            raise ValueError(f"panorama model: missing key(s) {sorted(missing)}")
        return cls(projection=str(d["projection"]), scale=float(d["scale"]),
                   offset=(float(d["offset"][0]), float(d["offset"][1])), width=int(d["width"]),
                   height=int(d["height"]), sources=tuple(PanoramaSource.from_dict(s) for s in d["sources"]))


def warped_from_dirs(projection: str, dirs: np.ndarray) -> np.ndarray:
    """Unit-scale warped coordinates (N, 2) of directions (N, 3) (the model's formulas with scale 1, no offset)."""
    m = PanoramaModel(projection=projection, scale=1.0, offset=(0.0, 0.0), width=1, height=1, sources=())
    return m.project(dirs)


