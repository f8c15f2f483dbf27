"""The central routes' priors (docs/gis.md, "Priors from the photos' GPS and compass"): the camera centre from
``camera.position_enu`` or the photos' EXIF GPS, and each photo's heading from its EXIF ``GPSImgDirection``,
with their 1-sigmas, and the record of what was used (``georegistration.priors`` in cameras.json and the stage
statistics).

* **Centre**: ``camera.position_enu`` (1-sigma ``prior_sigma_m`` on every axis), else the mean EXIF GPS position
  of the photos. East/north 1-sigma: ``GPSHPositioningError / sqrt(2)`` where a photo has that tag (iOS writes its
  horizontal accuracy as sqrt(sigma_e^2 + sigma_n^2), Android as the 68 % radius, 1.51 sigma), else the phone
  default ``gps_h_sigma_m``; up: ``gps_v_sigma_m`` where the photo has ``GPSAltitude``, free otherwise (the
  residual is left out). Photos of one panorama are taken from one place by one phone within seconds: their GPS
  errors are shared, so the mean's 1-sigma is the photos' RMS 1-sigma (not divided by sqrt(n)), and at least the
  photos' own scatter.
* **Heading**: ``GPSImgDirection`` with ``GPSImgDirectionRef = T`` (true north), 1-sigma ``compass_sigma_deg``.
  ``M`` (magnetic north) is **not used**: the declination (up to +-20 deg outside the polar regions, changing by
  the year) is not known offline; a note in the record says so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.frames import SceneFrame
from .gps import GpsFix, read_gps_fix
from .options import GeorefOptions, HeadingPrior

__all__ = ["Priors", "central_priors", "prior_outcome"]


@dataclass
class Priors:
    """``centre`` (3,) ENU m and ``sigma_m`` (3,) (inf: that axis free) or None; ``headings``; ``record``: what
    was used, for cameras.json (JSON-ready)."""

    centre: np.ndarray | None = None
    sigma_m: np.ndarray | None = None
    source: str = "none"
    headings: list[HeadingPrior] = field(default_factory=list)
    record: dict = field(default_factory=dict)


def _json_sigma(s: np.ndarray) -> list:
    return [float(x) if np.isfinite(x) else None for x in s]


def _gps_centre(frame: SceneFrame, fixes: list[GpsFix], opts: GeorefOptions) -> tuple[np.ndarray, np.ndarray, dict]:
    """The photos' mean GPS centre, its (3,) 1-sigma and the record."""
    enus, sigmas, photos = [], [], []
    for f in fixes:
        alt = f.alt_m if f.alt_m is not None else frame.height_m
        enus.append(frame.enu_from_wgs84(np.array([f.lon_deg, f.lat_deg, alt])))
        s_h = f.h_error_m / np.sqrt(2.0) if f.h_error_m is not None else opts.gps_h_sigma_m
        s_u = opts.gps_v_sigma_m if f.alt_m is not None else np.inf
        sigmas.append([s_h, s_h, s_u])
        photos.append({"photo": f.photo, "lon_deg": f.lon_deg, "lat_deg": f.lat_deg, "alt_m": f.alt_m,
                       "GPSHPositioningError_m": f.h_error_m, "sigma_h_m": float(s_h),
                       "sigma_h_from": "GPSHPositioningError / sqrt(2)" if f.h_error_m is not None
                       else f"phone default (GeorefOptions.gps_h_sigma_m = {opts.gps_h_sigma_m:g} m)",
                       "sigma_up_m": float(s_u) if np.isfinite(s_u) else None,
                       "sigma_up_from": f"GeorefOptions.gps_v_sigma_m = {opts.gps_v_sigma_m:g} m"
                       if f.alt_m is not None else "no GPSAltitude: the height is free"})
    E, S = np.array(enus), np.array(sigmas)
    centre = E.mean(axis=0)
    sigma = np.full(3, np.inf)
    for a in range(3):
        fin = np.isfinite(S[:, a])
        if fin.any():
            centre[a] = float(np.mean(E[fin, a]))
            sigma[a] = float(np.sqrt(np.mean(S[fin, a] ** 2)))
            if fin.sum() >= 2:
                sigma[a] = max(sigma[a], float(np.std(E[fin, a])))
    return centre, sigma, {"source": "exif_gps", "photos": photos}


def central_priors(frame: SceneFrame, position_enu: Sequence[float] | None, photos: Sequence[tuple[str, Path | None]],
                   opts: GeorefOptions) -> Priors:
    """The priors of a central rig whose views are ``photos`` (name, path or None, in the solver's view order)."""
    fixes: dict[int, GpsFix] = {}
    notes: list[str] = []
    for i, (_name, path) in enumerate(photos):
        if path is not None and Path(path).is_file():
            fix = read_gps_fix(path)
            if fix is not None:
                fixes[i] = fix
                notes.extend(fix.ignored)
    out = Priors()
    if position_enu is not None:
        out.centre = np.asarray(position_enu, float)
        out.sigma_m = np.full(3, float(opts.prior_sigma_m))
        out.source = "camera.position_enu"
        centre_rec = {"source": out.source}
    else:
        with_pos = [f for f in fixes.values() if f.has_position]
        centre_rec = None
        if with_pos:
            out.centre, out.sigma_m, centre_rec = _gps_centre(frame, with_pos, opts)
            out.source = "exif_gps"
    if centre_rec is not None:
        centre_rec.update({"centre_enu": out.centre.tolist(), "sigma_enu_m": _json_sigma(out.sigma_m)})
    headings = []
    for i, fix in sorted(fixes.items()):
        if fix.direction_deg is None:
            continue
        if fix.direction_ref != "T":
            notes.append(f"{fix.photo}: GPSImgDirection {fix.direction_deg:.1f} deg is magnetic "
                         f"(GPSImgDirectionRef = M); the magnetic declination is not known offline, so it is not "
                         f"used as a heading prior")
            continue
        out.headings.append(HeadingPrior(i, float(fix.direction_deg), float(opts.compass_sigma_deg), fix.photo))
        headings.append({"photo": fix.photo, "azimuth_deg": float(fix.direction_deg), "ref": "T",
                         "sigma_deg": float(opts.compass_sigma_deg),
                         "sigma_from": f"GeorefOptions.compass_sigma_deg = {opts.compass_sigma_deg:g} deg"})
    out.record = {"centre": centre_rec, "heading": headings, "notes": notes}
    return out


def prior_outcome(priors: Priors, stats: dict) -> dict:
    """``priors.record`` with what the solve made of them: the fitted centre's offset from the prior (in prior
    sigmas too) and each heading's fitted azimuth and residual (from :func:`solve_central`'s statistics)."""
    rec = {k: (dict(v) if isinstance(v, dict) else list(v) if isinstance(v, list) else v)
           for k, v in priors.record.items()}
    if rec.get("centre") is not None and "centre_minus_prior_m" in stats:
        d = np.asarray(stats["centre_minus_prior_m"], float)
        rec["centre"]["fitted_minus_prior_m"] = d.tolist()
        rec["centre"]["fitted_minus_prior_sigmas"] = [float(x / s) if np.isfinite(s) else None
                                                      for x, s in zip(d, priors.sigma_m)]
    fitted = {h["view"]: h for h in stats.get("heading_priors", [])}
    rec["heading"] = [{**h, **{k: v for k, v in fitted.get(p.view, {}).items() if k != "view"}}
                      for h, p in zip(rec.get("heading", []), priors.headings)]
    rec["used"] = sorted(({"centre"} if priors.centre is not None else set())
                         | ({"heading"} if priors.headings else set()))
    return rec
