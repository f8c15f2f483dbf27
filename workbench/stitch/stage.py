"""The ``stitch`` stage: the panorama route's photos -> ``out/stitch/panorama.jpg`` + ``panorama.json``.

Applies when ``camera.source`` is not ``sfm`` and the photo folder holds two or more photos. The
intrinsics route follows ``camera.source``:

* ``calibrated``: the camera profile's intrinsics (with distortion) are fixed; only rotations are estimated.
* ``exif``: the EXIF focal (``workbench.files.exif.read_focal_px``) is the starting value and a weak prior;
  focal, k1, k2 and the principal point are estimated. Photos without EXIF focal make the route ``fallback``.
* ``unknown``: everything estimated (``fallback``).

``panorama.json`` is :meth:`PanoramaModel.to_dict` plus ``rejected``, ``intrinsics_source`` and ``parallax``
(format in ``docs/stitching.md``). When the rotation-only model does not fit (parallax), the stage fails
with an :class:`InputError` that recommends ``camera.source = "sfm"``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
from PIL import Image

from ..core.camera import CameraIntrinsics
from ..errors import InputError
from ..project import Project
from ..files.exif import read_focal_px
from ..core.stage_api import Progress, StageResult
from .options import StitchOptions, StitchResult
from .stitcher import stitch_photos

log = logging.getLogger(__name__)

JPEG_QUALITY = 92


def load_profile_intrinsics(project: Project) -> CameraIntrinsics:
    """The camera profile's intrinsics (``camera.profile``); :class:`InputError` naming the file if bad."""
    cam = project.settings.camera
    path = project.require_file(cam.profile, "camera.profile")
    data = project.read_json(path)
    try:
        return CameraIntrinsics.from_dict(data["intrinsics"])
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: 'intrinsics' is not a valid camera model ({exc}); see docs/formats.md "
                         f"(camera_profile.json)") from None


def _photo_size(path: Path) -> tuple[int, int]:
    try:
        with Image.open(path) as im:
            return im.size
    except OSError as exc:
        raise InputError(f"{path}: cannot read this photo ({exc})") from None


def stitch_project(project: Project, progress: Progress = lambda f, m="": None,
                   options: StitchOptions = StitchOptions()) -> StitchResult:
    """Stitch the project's photo set along its intrinsics route (no files written)."""
    cam = project.settings.camera
    photos = project.photo_paths()
    names = [p.name for p in photos]
    calibrated = None
    priors = None
    if cam.source.value == "calibrated":
        prof = load_profile_intrinsics(project)
        calibrated = {}
        for p in photos:
            w, h = _photo_size(p)
            if (w, h) == (prof.width, prof.height):
                calibrated[p.name] = prof
            elif abs(w / prof.width - h / prof.height) < 1e-3:  # the same camera, resized photos
                calibrated[p.name] = prof.scaled(w / prof.width)
                log.info("stitch: %s is %dx%d; camera profile scaled from %dx%d", p.name, w, h, prof.width,
                         prof.height)
            else:
                raise InputError(f"{p}: {w}x{h} px does not match the camera profile "
                                 f"({project.path(cam.profile)}: {prof.width}x{prof.height}); use the photos as they "
                                 f"came from that camera, or set camera.source = 'exif'")
    elif cam.source.value == "exif":
        priors = {p.name: read_focal_px(p) for p in photos}
        missing = [n for n, f in priors.items() if not f]
        if missing:
            log.warning("stitch: no EXIF focal length in %s; the focal is estimated from the photos", missing)
    return stitch_photos(photos, names=names, options=options, calibrated=calibrated, focal_priors_px=priors,
                         image_refs=[project.relative(p) for p in photos], progress=progress)


def panorama_json(result: StitchResult) -> dict:
    """The content of ``panorama.json``: the model plus the run's metadata."""
    return {**result.model.to_dict(), "rejected": result.rejected, "intrinsics_source": result.intrinsics_source,
            "parallax": result.parallax}


def run_stitch(project: Project, progress: Progress) -> StageResult:
    result = stitch_project(project, progress)
    out = project.stage_dir("stitch")

    def write_jpeg(tmp: Path) -> None:
        if not cv2.imwrite(str(tmp), result.image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY]):
            raise OSError(f"cannot write {tmp}")

    image_path = project.write_with(out / "panorama.jpg", write_jpeg)
    model_path = project.write_json(out / "panorama.json", panorama_json(result))
    stats = {k: v for k, v in result.stats.items() if k != "pairs"}
    stats["route"] = "panorama"
    stats["pairs"] = result.stats.get("pairs", [])[:200]
    return StageResult(outputs={"panorama_image": image_path, "panorama_model": model_path}, stats=stats)
