"""``camera_profile.json``: a calibrated camera (format in ``docs/formats.md``), the one reader and writer.

``workbench calibrate`` writes it; ``camera.profile`` in ``project.toml`` names it; every stage that needs the
photos' intrinsics from it reads it here and scales it to the photo's size with :func:`profile_for_size`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..core.camera import CameraIntrinsics
from ..core.io import atomic_write_json, read_json
from ..errors import InputError


@dataclass(frozen=True)
class CameraProfile:
    """A read and checked ``camera_profile.json``: its intrinsics and the whole document."""

    path: Path
    intrinsics: CameraIntrinsics
    doc: dict = field(compare=False, repr=False)

    def for_size(self, w: int, h: int) -> CameraIntrinsics:
        """The intrinsics for a photo of ``w`` x ``h`` px (:func:`profile_for_size`)."""
        return profile_for_size(self.intrinsics, w, h, str(self.path))


def read_profile(path: Path) -> CameraProfile:
    """Read and check the ``camera_profile.json`` at ``path``."""
    intr, doc = load_camera_profile(path)
    return CameraProfile(Path(path), intr, doc)


def write_camera_profile(path: Path, profile: dict) -> Path:
    """Check ``profile`` (``docs/formats.md``) and write it atomically as JSON."""
    validate_profile(profile, str(path))
    return atomic_write_json(Path(path), profile)


def validate_profile(profile: dict, where: str = "camera profile") -> CameraIntrinsics:
    """The :class:`CameraIntrinsics` of a ``camera_profile.json`` object; :class:`InputError` naming what is wrong."""
    if not isinstance(profile, dict):
        raise InputError(f"{where}: a camera profile is a JSON object (see docs/formats.md, camera_profile.json)")
    unknown = sorted(set(profile) - {"model", "source", "intrinsics", "sensor_width_mm"})
    if unknown:
        raise InputError(f"{where}: unknown key(s) {unknown}; see docs/formats.md (camera_profile.json)")
    if profile.get("model", "brown") != "brown":
        raise InputError(f"{where}: model = {profile.get('model')!r}; only 'brown' is supported")
    d = profile.get("intrinsics")
    if not isinstance(d, dict):
        raise InputError(f"{where}: no 'intrinsics' object; see docs/formats.md (camera_profile.json)")
    fields = {"width", "height", "fx", "fy", "cx", "cy", "skew", "k1", "k2", "k3", "p1", "p2"}
    bad = sorted(set(d) - fields)
    missing = sorted({"width", "height", "fx", "fy", "cx", "cy"} - set(d))
    if bad or missing:
        raise InputError(f"{where}: intrinsics has unknown key(s) {bad} / lacks {missing}; see docs/formats.md")
    try:
        return CameraIntrinsics.from_dict(d)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: intrinsics are invalid ({exc})") from None


def load_camera_profile(path: Path) -> tuple[CameraIntrinsics, dict]:
    """Read and check a ``camera_profile.json``: (intrinsics, the whole profile)."""
    path = Path(path)
    profile = read_json(path, missing="camera profile not found; make one with `workbench calibrate`")
    return validate_profile(profile, str(path)), profile


def profile_for_size(intr: CameraIntrinsics, w: int, h: int, where: str) -> CameraIntrinsics:
    """The profile's intrinsics for a photo of ``w`` x ``h`` px: as they are, or scaled when the photo was
    resized; :class:`InputError` naming ``where`` when the aspect ratio differs (cropped or rotated)."""
    if (intr.width, intr.height) == (w, h):
        return intr
    if abs(intr.width / intr.height - w / h) < 1e-3:
        return intr.scaled(w / intr.width)
    raise InputError(f"{where}: the profile is for {intr.width}x{intr.height} photos but a photo is {w}x{h} "
                     f"(another aspect ratio: cropped or rotated); calibrate this camera at this size")
