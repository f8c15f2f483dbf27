"""Pieces of the georef stage's ``cameras.json`` (docs/pipeline.md): a view's entry, the ``georegistration``
block of a solver's result, and a centre covariance as reported."""

from __future__ import annotations

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.layout import CONTROL_POINTS_FILE

__all__ = ["view_entry", "georeg_block", "cov_report"]


def view_entry(name: str, image: str, intr: CameraIntrinsics, cam_from_world: np.ndarray, focal_known: bool) -> dict:
    """A ``views[]`` entry: the photo, its intrinsics, ``cam_from_world`` and its centre in the scene frame."""
    M = np.asarray(cam_from_world, float)
    return {"name": name, "image": image, "intrinsics": intr.to_dict(), "focal_known": bool(focal_known),
            "cam_from_world": M.tolist(), "center_enu": (-M[:3, :3].T @ M[:3, 3]).tolist()}


def georeg_block(method: str, res, extra: dict | None = None) -> dict:
    """The ``georegistration`` block of a central or similarity result (its residual figures), plus ``extra``."""
    s = res.stats
    block = {"method": method, "rms_m": s.get("rms_m"), "rms_px": s.get("rms_px"), "max_m": s.get("max_m"),
             "max_px": s.get("max_px"), "n_points": s.get("n_points"), "n_observations": s.get("n_observations"),
             "n_outliers": s.get("n_outliers"), "control_points": CONTROL_POINTS_FILE,
             "residuals": res.residuals, "warnings": res.warnings}
    for k in ("sigma_centre_m", "sigma_rotation_deg", "covariance_world_rotation_centre", "prior",
              "centre_minus_prior_m", "scale", "n_triangulated",
              "n_gps_centres", "gps_residuals_m", "gps_rms_m", "track"):
        if k in s:
            block[k] = s[k]
    block.update(extra or {})
    return block


def cov_report(C: np.ndarray) -> dict:
    """A centre covariance (3, 3) m^2 as reported: its largest 1-sigma, the ENU 1-sigmas and the matrix."""
    C = 0.5 * (np.asarray(C, float) + np.asarray(C, float).T)
    return {"sigma_centre_m": float(np.sqrt(max(np.linalg.eigvalsh(C).max(), 0.0))),
            "sigma_centre_enu_m": np.sqrt(np.clip(np.diag(C), 0.0, None)).tolist(), "cov_centre_enu_m2": C.tolist()}
