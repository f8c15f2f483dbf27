"""Stand-ins for what a person supplies by hand, made from a synthetic incident's ground truth.

* :func:`write_known_cameras` writes the incident's ``cameras.json`` (docs/pipeline.md) with the true
  cameras of a photo set: the "known cameras" input that replaces stitching and georegistration.
* :func:`write_true_correspondences` writes the incident's ``correspondences.json`` with the true pixels of
  visible marked points plus Gaussian noise: a person's careful picks, or the reference against which the
  automatic finder is compared (the same solve on true points with 1 px noise).

Both refuse real incidents (no ``truth/ground_truth.json``) and write atomically. Nothing here is used by a
stage: they only write the inputs a user could have written.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..core.io import atomic_write_json
from ..core.layout import CAMERAS_FILE, CORRESPONDENCES_FILE
from ..errors import InputError

log = logging.getLogger(__name__)


def _truth(root: Path) -> dict:
    p = Path(root) / "truth" / "ground_truth.json"
    if not p.is_file():
        raise InputError(f"{p}: not found; hand-pick stand-ins are made only for synthetic incidents "
                         f"(`workbench synth`)")
    return json.loads(p.read_text(encoding="utf-8"))


def _photos(truth: dict, photo_set: str, root: Path) -> list[dict]:
    photos = [ph for ph in truth["photos"] if ph["set"] == photo_set]
    if not photos:
        sets = sorted({ph["set"] for ph in truth["photos"]})
        raise InputError(f"{Path(root) / 'truth' / 'ground_truth.json'}: no photos in set {photo_set!r}; "
                         f"sets: {', '.join(sets)}")
    return photos


def known_cameras(root: str | Path, photo_set: str = "panorama") -> dict:
    """The ``cameras.json`` document (docs/pipeline.md) of the true cameras of ``photo_set``."""
    root = Path(root)
    truth = _truth(root)
    views = []
    for ph in _photos(truth, photo_set, root):
        views.append({"name": Path(ph["photo"]).name, "image": ph["photo"], "intrinsics": ph["intrinsics"],
                      "focal_known": True, "cam_from_world": ph["cam_from_world"],
                      "center_enu": ph["center_enu"]})
    return {"route": "panorama" if photo_set == "panorama" else "multiview", "intrinsics_source": "calibrated",
            "georegistration": {"method": "known", "note": "true cameras of a synthetic incident"},
            "views": views, "panorama": None}


def write_known_cameras(root: str | Path, photo_set: str = "panorama") -> Path:
    """Write ``<root>/cameras.json`` with the true cameras of ``photo_set``; returns its path."""
    root = Path(root)
    path = atomic_write_json(root / CAMERAS_FILE, known_cameras(root, photo_set))
    log.info("wrote %s (%s set, true cameras)", path, photo_set)
    return path


def true_correspondences(root: str | Path, photo_set: str = "panorama", *, sigma_px: float = 1.0, seed: int = 0,
                         points_per_car: int | None = 7) -> dict:
    """The ``correspondences.json`` document of the visible marked points of ``photo_set``, true pixel plus
    N(0, sigma_px²) noise per coordinate; at most ``points_per_car`` (random, fixed seed) per carriage and photo
    (``None``: all visible points)."""
    if not (np.isfinite(sigma_px) and sigma_px >= 0):
        raise InputError(f"sigma_px = {sigma_px!r}: must be a non-negative number of pixels")
    root = Path(root)
    truth = _truth(root)
    rng = np.random.default_rng(seed)
    obs = []
    for ph in _photos(truth, photo_set, root):
        w, h = ph["intrinsics"]["width"], ph["intrinsics"]["height"]
        name = Path(ph["photo"]).name
        for car in truth["carriages"]:
            pts = ph["observations"].get(car["number"], {})
            vis = [p for p, o in pts.items() if o.get("visible") and o.get("uv") is not None]
            if points_per_car is not None and len(vis) > points_per_car:
                vis = sorted(rng.choice(vis, size=points_per_car, replace=False).tolist())
            for p in vis:
                uv = np.asarray(pts[p]["uv"], dtype=float) + rng.normal(0.0, sigma_px, 2)
                uv = np.clip(uv, [-0.5, -0.5], [w - 0.5, h - 0.5])
                obs.append({"carriage": car["number"], "point": p, "view": name, "uv": [float(uv[0]), float(uv[1])],
                            "source": "manual", "confidence": 1.0, "sigma_px": float(max(sigma_px, 0.1))})
    return {"observations": obs, "needs_manual": [],
            "note": f"true pixels + N(0, {sigma_px} px) noise, {photo_set} set, seed {seed} (synthetic stand-in)"}


def write_true_correspondences(root: str | Path, photo_set: str = "panorama", *, sigma_px: float = 1.0, seed: int = 0,
                               points_per_car: int | None = 7) -> Path:
    """Write ``<root>/correspondences.json`` (see :func:`true_correspondences`); returns its path."""
    root = Path(root)
    doc = true_correspondences(root, photo_set, sigma_px=sigma_px, seed=seed, points_per_car=points_per_car)
    path = atomic_write_json(root / CORRESPONDENCES_FILE, doc)
    log.info("wrote %s (%d observations)", path, len(doc["observations"]))
    return path
