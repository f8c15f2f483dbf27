"""The intrinsics of each photo of a run, from the files that give them (``docs/intrinsics.md``).

One resolver for every stage that needs a photo's camera before georef has placed it: the camera profile
(``calibrated``), the SfM reconstruction (``sfm``), the photos' EXIF focal (``exif``), else a fallback whose
focal the solver estimates.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..core.camera import CameraIntrinsics
from ..errors import InputError
from .exif import exif_focal_prior
from .profile import load_camera_profile, profile_for_size

if TYPE_CHECKING:
    from ..project import Project

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


def photo_size(path: Path) -> tuple[int, int]:
    """(width, height) px of the photo as stored; :class:`InputError` naming it when it cannot be read."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except OSError as exc:
        raise InputError(f"{path}: cannot read this photo ({exc})") from None


def centred(w: int, h: int, f: float) -> CameraIntrinsics:
    """A pinhole of focal ``f`` px for a ``w`` x ``h`` photo: principal point at the centre, no distortion."""
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
    sizes = {p.name: photo_size(p) for p in photos}
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
                        per[n], known[n] = centred(w, h, fallback_f[n]), False
                return IntrinsicsChoice("sfm", per, known, detail)
        detail = {"note": "camera.source = 'sfm' but the sfm stage has no result; EXIF or fallback used"}

    if source in ("exif", "sfm"):
        exif = {}
        for p in photos:
            w, h = sizes[p.name]
            prior = exif_focal_prior(p)
            if prior is not None:
                per[p.name], known[p.name] = centred(w, h, prior.focal_px), True
                exif[p.name] = prior.to_dict()
            else:
                per[p.name], known[p.name] = centred(w, h, fallback_f[p.name]), False
        detail = {**detail, "exif": exif, "without_exif": sorted(n for n in sizes if n not in exif)}
        return IntrinsicsChoice("exif" if exif else "fallback", per, known, detail)

    for n, (w, h) in sizes.items():
        per[n], known[n] = centred(w, h, fallback_f[n]), False
    return IntrinsicsChoice("fallback", per, known, {"initial_hfov_deg": FALLBACK_HFOV_DEG})
