"""The ``sfm`` stage, and the choice of intrinsics route for a run (calibrated, EXIF, SfM, fallback).

``sfm`` (route ``multiview``, ``camera.source = "sfm"``) runs pycolmap on the photos of ``camera.photos`` and
writes ``out/sfm/reconstruction.json`` (format in ``docs/intrinsics.md``): every registered photo's Brown
intrinsics and ``cam_from_model`` pose in COLMAP's arbitrary similarity frame, the photos left out of it (with
the reason), the separate smaller models (``models``, each in its own frame), a subsample of the 3-D points,
``intrinsics_source = "sfm"`` and the statistics. The camera profile (``camera.profile``) or else the photos'
EXIF focal is the initial camera.

:func:`resolve_intrinsics` gives the other routes' intrinsics per photo and says which route was taken.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.camera import CameraIntrinsics
from ..errors import InputError
from ..project import Project
from ..runner import Progress, StageResult
from ..files.profile import load_camera_profile, profile_for_size
from .exif import FocalPrior, exif_focal_prior

log = logging.getLogger(__name__)

FALLBACK_HFOV_DEG = 55.0  # initial guess of the fallback route (the solver estimates the focal)


@dataclass
class IntrinsicsChoice:
    """The intrinsics of a run's photos and where they come from.

    ``source``: ``calibrated``, ``exif``, ``sfm`` or ``fallback``; ``per_photo``: photo name ->
    :class:`CameraIntrinsics` (for the photo as stored); ``focal_known``: False where the solver should
    estimate the focal; ``detail``: what was used (profile path, EXIF tags, warnings) for the report.
    """

    source: str
    per_photo: dict[str, CameraIntrinsics]
    focal_known: dict[str, bool]
    detail: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"intrinsics_source": self.source,
                "photos": {n: {"intrinsics": i.to_dict(), "focal_known": self.focal_known[n]}
                           for n, i in self.per_photo.items()},
                "detail": self.detail}


def _photo_size(path: Path) -> tuple[int, int]:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except OSError as exc:
        raise InputError(f"{path}: cannot read this photo ({exc})") from None


def _centred(w: int, h: int, f: float) -> CameraIntrinsics:
    return CameraIntrinsics(width=w, height=h, fx=f, fy=f, cx=(w - 1) / 2.0, cy=(h - 1) / 2.0)


def resolve_intrinsics(project: Project, photos: list[Path] | None = None) -> IntrinsicsChoice:
    """Intrinsics for each photo following ``camera.source`` (``docs/intrinsics.md``):

    * ``calibrated``: the camera profile (scaled to the photo's size if it was resized);
    * ``exif``: each photo's EXIF focal prior (principal point at the centre, no distortion); photos without
      a usable prior fall back (``focal_known`` False) and the route is ``exif`` only if at least one had one;
    * ``sfm``: the ``sfm`` stage's intrinsics where available (``out/sfm/reconstruction.json``: the main model's,
      then the separate models');
    * ``unknown`` -> ``fallback``: a simplified pinhole (focal for a 55 degree field of view, centred principal
      point, no distortion) whose focal the pose solver estimates.
    """
    s = project.settings
    photos = photos if photos is not None else project.photo_paths()
    sizes = {p.name: _photo_size(p) for p in photos}
    source = s.camera.source.value
    per, known, detail = {}, {}, {}
    fallback_f = {n: w / 2.0 / np.tan(np.deg2rad(FALLBACK_HFOV_DEG) / 2.0) for n, (w, h) in sizes.items()}

    if source == "calibrated":
        pf = project.require_file(s.camera.profile, "camera.profile")
        intr, profile = load_camera_profile(pf)
        for n, (w, h) in sizes.items():
            per[n] = profile_for_size(intr, w, h, str(pf))
            known[n] = True
        detail = {"profile": project.relative(pf), "profile_source": profile.get("source", "")}
        return IntrinsicsChoice("calibrated", per, known, detail)

    if source == "sfm":
        rec_path = project.stage_dir("sfm") / "reconstruction.json"
        if rec_path.is_file():
            rec = project.read_json(rec_path)
            # the main model first, then the separate models (a photo in several keeps the main model's camera)
            for images in [rec.get("images", [])] + [m.get("images", []) for m in rec.get("models", [])]:
                for im in images:
                    if im["name"] in sizes and im["name"] not in per:
                        per[im["name"]] = CameraIntrinsics.from_dict(im["intrinsics"])
                        known[im["name"]] = True
            detail = {"reconstruction": project.relative(rec_path),
                      "unregistered": [u["name"] for u in rec.get("unregistered", [])],
                      "in_separate_models": sorted({u["name"] for u in rec.get("unregistered", []) if "model" in u})}
            if per:
                for n, (w, h) in sizes.items():  # unregistered photos: fall back
                    if n not in per:
                        per[n], known[n] = _centred(w, h, fallback_f[n]), False
                return IntrinsicsChoice("sfm", per, known, detail)
        detail = {"note": "camera.source = 'sfm' but the sfm stage has no result; EXIF or fallback used"}

    if source in ("exif", "sfm"):
        exif = {}
        for p in photos:
            w, h = sizes[p.name]
            prior = exif_focal_prior(p)
            if prior is not None:
                per[p.name], known[p.name] = _centred(w, h, prior.focal_px), True
                exif[p.name] = prior.to_dict()
            else:
                per[p.name], known[p.name] = _centred(w, h, fallback_f[p.name]), False
        detail = {**detail, "exif": exif, "without_exif": sorted(n for n in sizes if n not in exif)}
        return IntrinsicsChoice("exif" if exif else "fallback", per, known, detail)

    for n, (w, h) in sizes.items():
        per[n], known[n] = _centred(w, h, fallback_f[n]), False
    return IntrinsicsChoice("fallback", per, known, {"initial_hfov_deg": FALLBACK_HFOV_DEG})


# -------------------------------------------------------------------------------------------------------
# the sfm stage
# -------------------------------------------------------------------------------------------------------
def _sfm_options(project: Project):
    from .sfm import SfmOptions

    section = getattr(project.settings, "sfm", None)  # an optional [sfm] table, when settings have one
    if section is None:
        return SfmOptions()
    d = section.model_dump(exclude_none=True) if hasattr(section, "model_dump") else dict(section)
    preset = d.pop("preset", None)
    if preset == "forward_motion":
        return SfmOptions.forward_motion(**d)
    return SfmOptions.from_dict(d)


def _initial_camera(project: Project, photos: list[Path]) -> tuple[CameraIntrinsics | None, dict | None]:
    """The camera profile, else the EXIF focal of the photos (if they agree), as SfM's initial camera."""
    s = project.settings
    if s.camera.profile:
        pf = project.require_file(s.camera.profile, "camera.profile")
        intr, profile = load_camera_profile(pf)
        return intr, {"source": "calibrated", "profile": project.relative(pf), "focal_px": intr.fx}
    priors: list[FocalPrior] = [pr for p in photos if (pr := exif_focal_prior(p)) is not None]
    if not priors:
        return None, None
    sizes = {(pr.width, pr.height) for pr in priors}
    f = np.array([pr.focal_px for pr in priors])
    if len(sizes) > 1 or (f.max() - f.min()) > 0.01 * np.median(f):
        log.info("sfm: EXIF focal differs between photos (%.1f..%.1f px); no common prior", f.min(), f.max())
        return None, {"source": "exif", "used": False, "reason": "EXIF focal differs between photos",
                      "focal_px_range": [float(f.min()), float(f.max())]}
    pr = priors[0]
    w, h = pr.width, pr.height
    intr = _centred(w, h, float(np.median(f)))
    return intr, {"source": "exif", "used": True, "focal_px": intr.fx, "sigma_px": pr.sigma_px,
                  "exif_source": pr.source, "tags": pr.tags, "warnings": list(pr.warnings),
                  "n_photos_with_exif": len(priors)}


def run_sfm_stage(project: Project, progress: Progress) -> StageResult:
    from .sfm import run_sfm

    photos = project.photo_paths()
    options = _sfm_options(project)
    progress(0.0, "initial camera")
    prior, prior_info = _initial_camera(project, photos)
    if prior_info is not None and prior_info.get("used") is False:
        prior = None
    result = run_sfm(photos, options=options, prior=prior, progress=lambda f, m="": progress(0.02 + 0.95 * f, m))
    data = result.to_json(project.relative, prior=prior_info)
    path = project.write_json(project.stage_dir("sfm") / "reconstruction.json", data)
    v0 = result.views[0].intrinsics
    st = result.stats
    stats = {
        "route": "multiview", "intrinsics_source": "sfm",
        "initial_camera": (prior_info or {}).get("source", "none") if prior is not None else "none",
        "n_images": st["n_images"], "n_registered": st["n_registered"],
        "unregistered": result.unregistered, "n_points": st["n_points"],
        "n_models": st["n_models"], "separate_models": st["separate_models"],
        "n_in_separate_models": st["n_in_separate_models"],
        "mean_reprojection_error_px": st["mean_reprojection_error_px"],
        "mean_track_length": st["mean_track_length"], "focal_px": v0.fx, "k1": v0.k1, "k2": v0.k2,
        "hfov_deg": float(np.degrees(2 * np.arctan(v0.width / 2.0 / v0.fx))),
        "camera_model": st["camera_model"], "matcher": st["matcher"],
        "retried_forward_motion": st["retried_forward_motion"], "timings_s": st["timings_s"],
        "warnings": st["warnings"],
    }
    return StageResult(outputs={"reconstruction": path}, stats=stats)
