"""The ``sfm`` stage: the cameras of a multi-view photo set, recovered with pycolmap.

``sfm`` (route ``multiview``, ``camera.source = "sfm"``) runs pycolmap on the photos of ``camera.photos`` and
writes ``out/sfm/reconstruction.json`` (format in ``docs/intrinsics.md``): every registered photo's Brown
intrinsics and ``cam_from_model`` pose in COLMAP's arbitrary similarity frame, the photos left out of it (with
the reason), the separate smaller models (``models``, each in its own frame), a subsample of the 3-D points,
``intrinsics_source = "sfm"`` and the statistics. The camera profile (``camera.profile``) or else the photos'
EXIF focal is the initial camera.

:func:`workbench.files.intrinsics.resolve_intrinsics` gives the other routes' intrinsics per photo.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.stage_api import Progress, StageResult
from ..files.exif import FocalPrior, exif_focal_prior
from ..files.intrinsics import centred
from ..files.profile import load_camera_profile
from ..project import Project
from .sfm import SfmOptions, run_sfm

log = logging.getLogger(__name__)

# -------------------------------------------------------------------------------------------------------
# the sfm stage
# -------------------------------------------------------------------------------------------------------
def _sfm_options(project: Project):
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
    intr = centred(w, h, float(np.median(f)))
    return intr, {"source": "exif", "used": True, "focal_px": intr.fx, "sigma_px": pr.sigma_px,
                  "exif_source": pr.source, "tags": pr.tags, "warnings": list(pr.warnings),
                  "n_photos_with_exif": len(priors)}


def run_sfm_stage(project: Project, progress: Progress) -> StageResult:
    photos = project.photo_paths()
    options = _sfm_options(project)
    progress(0.0, "initial camera")
    prior, prior_info = _initial_camera(project, photos)
    if prior_info is not None and prior_info.get("used") is False:
        prior = None
    focal_sd = (prior_info or {}).get("sigma_px") if prior is not None else None  # the EXIF's; a profile: exact
    result = run_sfm(photos, options=options, prior=prior, prior_focal_sigma_px=focal_sd,
                     progress=lambda f, m="": progress(0.02 + 0.95 * f, m))
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
        "pose_covariance": {k: v for k, v in (st.get("pose_covariance") or {}).items() if k != "parametrisation"}
        or None,
    }
    return StageResult(outputs={"reconstruction": path}, stats=stats)
