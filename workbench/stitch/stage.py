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
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import cv2

from ..errors import InputError
from ..core.stage_api import Progress, StageResult
from .options import StitchOptions, StitchResult
from .photo_matching import describe_photo, match_described

if TYPE_CHECKING:  # (the project's settings are validated while the head start describes the photos)
    from ..project import Project

log = logging.getLogger(__name__)

JPEG_QUALITY = 92


_PREFETCH: dict = {}  # the photos described ahead of the stage (prefetch): their stamps, options and futures
_PREFETCH_LOCK = threading.Lock()


def _stamps(photos: list[Path]) -> tuple:
    return tuple((str(p.resolve()), p.stat().st_size, p.stat().st_mtime_ns) for p in photos)


def prefetch(project: Project, options: StitchOptions = StitchOptions()) -> None:
    """Start describing the panorama photos (read, SIFT, FLANN index: ``photo_matching.describe_photo``) on two
    threads while the command does what comes before the stage (starting, the inputs and terrain stages): OpenCV
    releases the interpreter, so the second core works. Unless the lens is calibrated (its keypoints are matched
    undistorted), every pair is then matched there too (``photo_matching.match_described``), each once its two
    photos are described. The stage takes the results when its photos are unchanged since (paths, sizes,
    modification times) and its options the same; else they are dropped. Nothing new where the same photos are
    being described already (:func:`head_start`)."""
    describe_ahead(project.photo_paths(), match=project.settings.camera.source.value != "calibrated",
                   options=options)


def head_start(project: Project) -> bool:
    """:func:`prefetch` from the photo folder and camera source as written in ``project.toml`` (not yet validated),
    for a command that starts describing the photos before it has loaded the settings' models and validated them
    (``workbench stitch``: docs/performance.md, ninth pass). The stage takes the work only where the validated
    settings give the same photos, stamps and options, and the same matching (:func:`prefetch` then starts nothing
    new). Nothing is started (False) where ``camera.photos`` or ``camera.source`` is not written as a string, the
    source is ``sfm`` (no panorama), or the folder holds fewer than two photos."""
    folder, source = project.written_setting("camera", "photos"), project.written_setting("camera", "source")
    if not isinstance(folder, str) or not isinstance(source, str) or source == "sfm":
        return False
    try:
        photos = project.photo_paths(folder)
    except InputError:
        return False
    if len(photos) < 2:
        return False
    describe_ahead(photos, match=source != "calibrated")
    return True


def describe_ahead(photos: list[Path], *, match: bool, options: StitchOptions = StitchOptions()) -> None:
    """Describe ``photos`` on two threads and (``match``) match every pair, for the stage to take
    (:func:`_take_prefetch`); nothing new where the same photos (paths, sizes, modification times) are being
    described already with these options and this matching."""
    stamps = _stamps(photos)  # before reading: a photo changed meanwhile is described again by the stage
    with _PREFETCH_LOCK:
        if (_PREFETCH and _PREFETCH["stamps"] == stamps and _PREFETCH["options"] == options
                and _PREFETCH["match"] == match):
            log.info("stitch: the photos are being described already (the command's head start)")
            return
    pool = ThreadPoolExecutor(max_workers=2, thread_name_prefix="stitch prefetch")
    futures = {k: pool.submit(describe_photo, p, p.name, k, options) for k, p in enumerate(photos)}
    matched = {}
    if match:
        # (queued after every description: a match waiting for its photos never holds up one of them)
        matched = {(i, j): pool.submit(match_described, (i, j), futures, options)
                   for j in range(len(photos)) for i in range(j)}
    pool.shutdown(wait=False)
    with _PREFETCH_LOCK:
        _PREFETCH.clear()
        _PREFETCH.update(stamps=stamps, options=options, match=match, futures=futures, matched=matched, pool=pool)


def _take_prefetch(photos: list[Path], options: StitchOptions, pools: list) -> tuple[dict, dict] | None:
    """The prefetched descriptions of ``photos`` (index -> future) and matches (pair -> future), if they are of
    these photos as they are now; their threads' pool appended to ``pools`` (used or not), for the stage to wait for
    its threads' end."""
    with _PREFETCH_LOCK:
        pre = dict(_PREFETCH)
        _PREFETCH.clear()
    if not pre:
        return None
    pools.append(pre["pool"])
    if pre["options"] != options or pre["stamps"] != _stamps(photos):
        log.info("stitch: the photos changed since they were described ahead of the stage; described again")
        return None
    log.info("stitch: %d photos described ahead of the stage (and %d pairs matched)", len(pre["futures"]),
             len(pre["matched"]))
    return pre["futures"], pre["matched"]


def stitch_project(project: Project, progress: Progress = lambda f, m="": None,
                   options: StitchOptions = StitchOptions()) -> StitchResult:
    """Stitch the project's photo set along its intrinsics route (no files written)."""
    photos = project.photo_paths()
    pools: list[ThreadPoolExecutor] = []
    try:
        return _stitch_project(project, photos, options, progress, _take_prefetch(photos, options, pools))
    finally:  # no prefetch thread outlives the stage (a later stage may fork: threads only after forks)
        for pool in pools:
            pool.shutdown(wait=True, cancel_futures=True)


def _stitch_project(project: Project, photos: list[Path], options: StitchOptions, progress: Progress,
                    pre: tuple[dict, dict] | None) -> StitchResult:
    # (imported here, not with the module: the prefetch starts describing the photos without them)
    from ..files.exif import read_focal_px
    from ..files.intrinsics import photo_size
    from .stitcher import stitch_photos

    cam = project.settings.camera
    described, matched = pre or (None, None)
    names = [p.name for p in photos]
    calibrated = None
    priors = None
    if cam.source.value == "calibrated":
        prof = project.camera_profile()
        if prof is None:
            raise InputError(f"{project.settings_path}: camera.source = 'calibrated' needs camera.profile (a "
                             f"camera_profile.json from `workbench calibrate`), or set camera.source = 'exif'")
        calibrated = {}
        for p in photos:
            w, h = photo_size(p)
            calibrated[p.name] = prof.for_size(w, h)  # scaled when the photos were resized; another aspect: refused
    elif cam.source.value == "exif":
        priors = {p.name: read_focal_px(p) for p in photos}
        missing = [n for n, f in priors.items() if not f]
        if missing:
            log.warning("stitch: no EXIF focal length in %s; the focal is estimated from the photos", missing)
    return stitch_photos(photos, names=names, options=options, calibrated=calibrated, focal_priors_px=priors,
                         image_refs=[project.relative(p) for p in photos], progress=progress, described=described,
                         matched=matched if calibrated is None else None)


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
