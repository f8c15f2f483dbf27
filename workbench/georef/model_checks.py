"""Whether an SfM model's similarity can be trusted: a surveyor's test of the control points that place it."""

from __future__ import annotations

import numpy as np

from ..files.reconstruction import SfmView
from .options import GeorefOptions
from .picks import misfit_doubt
from .similarity import SimilarityResult

__all__ = ["model_verdict"]


def _model_figures(res: SimilarityResult, views: list[SfmView]) -> tuple[list[str], dict]:
    """The control points triangulated in the model whose picks all fit it, and the figures checked."""
    by_point: dict[str, list[dict]] = {}
    for r in res.residuals:
        by_point.setdefault(r["point"], []).append(r)
    good = [name for name, X in res.triangulated.items()
            if by_point.get(name) and all(r["inlier"] for r in by_point[name])]
    X = np.array([res.apply(res.triangulated[n]) for n in good]).reshape(-1, 3)
    spread = float(np.linalg.svd(X - X.mean(axis=0), compute_uv=False)[1] / np.sqrt(len(X))) if len(X) >= 3 else 0.0
    n_obs = len(res.residuals)
    n_out = sum(1 for r in res.residuals if not r["inlier"])
    sig = [res.centre_sigma_m(v.cam_from_model) for v in views]
    sig_max = None if any(x is None for x in sig) else float(max(sig))
    finite = [r["error_px"] for r in res.residuals if r["error_px"] is not None]
    rms_all = float(np.sqrt(np.mean(np.square(finite)))) if finite else None
    return good, {"n_fitting_triangulated": len(good), "spread_m": spread, "n_observations": n_obs,
                  "n_outliers": n_out, "rms_px": res.stats.get("rms_px"), "rms_all_px": rms_all,
                  "sigma_centre_max_m": sig_max}


def model_verdict(res: SimilarityResult, views: list[SfmView], opts: GeorefOptions) -> tuple[str | None, dict]:
    """Why an SfM model's similarity cannot be trusted (None: it can), and the figures checked.

    Enough of the model's own control points triangulated in it and fitting, spread out (not on a line), small
    residuals (:func:`~workbench.georef.picks.misfit_doubt`: the points' stated survey error counted), and the fit
    fixing every camera centre to ``model_max_sigma_centre_m``."""
    good, figures = _model_figures(res, views)
    n_obs, n_out, spread = figures["n_observations"], figures["n_outliers"], figures["spread_m"]
    rms_all, sig_max = figures["rms_all_px"], figures["sigma_centre_max_m"]
    if len(good) < opts.model_min_points and len(res.triangulated) >= opts.model_min_points:
        # the points are there (picked in two or more photos, their rays meet): the model disagrees with them
        behind = n_obs - sum(1 for r in res.residuals if r["error_px"] is not None)
        return (f"control-point RMS residual {'-' if rms_all is None else f'{rms_all:.1f}'} px over its {n_obs} "
                f"picks ({n_out} beyond {opts.ransac_threshold_px:g} px"
                + (f", {behind} behind the camera" if behind else "")
                + f"): of the {len(res.triangulated)} control points triangulated in it, {len(good)} fit it "
                f"({opts.model_min_points} are needed): the model or its camera (focal) disagrees with the control "
                f"points"), figures
    if len(good) < opts.model_min_points:
        return (f"{len(good)} control point(s) triangulated in this model fit it (all picks within "
                f"{opts.ransac_threshold_px:g} px); {opts.model_min_points} are needed: pick more control points in "
                f"two or more of its photos ({', '.join(v.name for v in views)})"), figures
    if spread < opts.model_min_spread_m:
        return (f"its {len(good)} fitting control points lie {spread:.2f} m (RMS) from one line; "
                f"{opts.model_min_spread_m:g} m is needed to fix the rotation: add a point off that line"), figures
    if res.stats.get("rms_px") is None:
        return "no control-point pick fits the model: the model or the points are wrong", figures
    doubt = misfit_doubt(res.residuals, res.stats["rms_px"], opts, 7)
    if doubt is not None:
        return f"{doubt}: the model or a point is wrong", figures
    if n_out > opts.model_max_outlier_fraction * n_obs:
        return (f"{n_out} of {n_obs} control-point picks are outliers (more than "
                f"{100 * opts.model_max_outlier_fraction:.0f} %): the model or the points disagree"), figures
    if sig_max is None or sig_max > opts.model_max_sigma_centre_m:
        return (f"the control points fix its cameras only to {sig_max if sig_max is None else round(sig_max, 2)} m "
                f"(1-sigma; {opts.model_max_sigma_centre_m:g} m allowed): add control points spread over its "
                f"photos"), figures
    return None, figures
