"""The multi-view route's camera adjustment: every placed photo's stated uncertainty, and each shared SfM
camera's intrinsics refined from the control-point picks where that predicts held-out picks better than SfM's
(the photos then take the adjusted poses). Method and figures: docs/gis.md (the shared camera adjusted from the
control points; stated uncertainty).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.geometry import skew
from ..files.control_points import ControlPoint
from .documents import cov_report
from .options import GeorefOptions
from .shared_camera import INTRINSIC_SETS, adjust_shared_camera, held_out_errors, held_out_picks, robust_rms

__all__ = ["adjust_cameras", "intrinsics_key", "only_picks"]


def intrinsics_key(it: CameraIntrinsics) -> str:
    """A key equal for equal intrinsics: the photos of one SfM camera share it."""
    return repr(sorted(it.to_dict().items()))


def only_picks(cps: list[ControlPoint], use: set) -> list[ControlPoint]:
    """The control points with only the picks in ``use`` ((point, photo) pairs)."""
    out = []
    for cp in cps:
        pix = {ph: uv for ph, uv in cp.pixels.items() if (cp.name, ph) in use}
        if pix:
            out.append(replace(cp, pixels=pix))
    return out


def _camera_groups(models, by_name: dict[str, dict]) -> tuple[dict[str, list[str]], dict[str, CameraIntrinsics]]:
    """The placed photos grouped by SfM camera (its key -> photos), and each camera's SfM intrinsics."""
    sfm_intr: dict[str, CameraIntrinsics] = {}
    for _, vs in models:
        for v in vs:
            sfm_intr.setdefault(v.name, v.intrinsics)
    main_cam = models[0][1][0].intrinsics if models and models[0][1] else None
    groups: dict[str, list[str]] = {}
    base_of: dict[str, CameraIntrinsics] = {}
    for name in by_name:
        it = sfm_intr.get(name) or main_cam
        if it is None:
            continue
        key = intrinsics_key(it)
        groups.setdefault(key, []).append(name)
        base_of[key] = it
    return groups, base_of


def _fitting_poses(names: list[str], by_name: dict[str, dict], cps: list[ControlPoint],
                   opts: GeorefOptions) -> tuple[dict[str, np.ndarray], list[tuple[str, str]]]:
    """The photos with ``resect_min_points`` picks within the outlier threshold of their pose (photo ->
    cam_from_world), and those (point, photo) picks."""
    poses, fit = {}, []
    for n in sorted(names):
        v = by_name[n]
        M = np.asarray(v["cam_from_world"], float)
        it = CameraIntrinsics.from_dict(v["intrinsics"])
        ok = []
        for cp in cps:
            uv = cp.pixels.get(n)
            if uv is None:
                continue
            q = M[:3, :3] @ cp.enu + M[:3, 3]
            if q[2] > 0 and np.hypot(*(it.project(q[None])[0] - uv)) < opts.ransac_threshold_px:
                ok.append(cp.name)
        if len(ok) >= opts.resect_min_points:
            poses[n] = M
            fit.extend((p, n) for p in ok)
    return poses, fit


def _held_out_as_placed(base: CameraIntrinsics, poses: dict[str, np.ndarray], picks_use: list[ControlPoint],
                        placed: dict, resected: dict, refit: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The held-out errors of SfM's camera kept (``sfm``), scored on the poses it keeps (docs/gis.md): a photo
    placed by its model by its picks' errors under the model pose (nearly held out: the similarity's 7
    parameters are fitted to all the model's picks; inflated by sqrt(m / (m - 7)), m the fit's residuals), a
    resected photo by its pose refitted on held-out halves (``refit``)."""
    hp = held_out_picks(poses, picks_use)
    cps_by = {cp.name: cp for cp in picks_use}
    as_placed = {}
    for n, names_ in hp.items():
        if n in placed and n not in resected:
            label, res_m, _ = placed[n]
            M = poses[n]
            X = np.array([cps_by[p].enu for p in names_])
            q = X @ M[:3, :3].T + M[:3, 3]
            uv = np.array([cps_by[p].pixels[n] for p in names_], float)
            e = np.full(len(names_), np.inf)
            front = q[:, 2] > 1e-6
            e[front] = np.hypot(*(base.project(q[front]) - uv[front]).T)
            m = 2 * int(res_m.stats.get("n_observations") or 0)
            as_placed[n] = e * (math.sqrt(m / (m - 7)) if m > 14 else 1.0)
        else:
            as_placed[n] = refit[n]
    return as_placed


def _adjust_group(base: CameraIntrinsics, names: list[str], by_name: dict[str, dict], placed: dict, resected: dict,
                  cps: list[ControlPoint], opts: GeorefOptions):
    """One SfM camera's photos adjusted: (report or None when too few picks, photo -> stated uncertainty, photo ->
    adjusted centre, refined intrinsics or None). The chosen intrinsics and poses are written into ``by_name``."""
    poses, fit = _fitting_poses(names, by_name, cps, opts)
    n_par = 4 + 6 * len(poses)
    if not poses or 2 * len(fit) < n_par + 4:
        return None, {}, {}, None
    use = set(fit)
    report: dict[str, Any] = {"photos": sorted(poses), "n_observations": len(fit),
                              "sfm_intrinsics": {"f": base.fx, "cx": base.cx, "cy": base.cy, "k1": base.k1}}
    try:
        free_adj = adjust_shared_camera(base, poses, cps, opts, free=INTRINSIC_SETS["f_pp_k1"], use=use)
        picks_use = only_picks(cps, use)
        cv = {"sfm_poses_refit": held_out_errors(base, poses, picks_use, opts, ())}
        for lbl, fr in INTRINSIC_SETS.items():
            cv[lbl] = held_out_errors(base, poses, picks_use, opts, fr)
    except (ValueError, np.linalg.LinAlgError) as exc:
        report["error"] = str(exc)
        return report, {}, {}, None
    as_placed = _held_out_as_placed(base, poses, picks_use, placed, resected, cv["sfm_poses_refit"])
    cv = {"sfm": as_placed, **cv}
    ho = {k: (robust_rms(np.concatenate(list(v.values())), opts) if v else None) for k, v in cv.items()}
    report.update({"free_intrinsics": {k: free_adj["values"][k] for k in ("f", "cx", "cy", "k1")},
                   "sigma_intrinsics": free_adj["sigma_intrinsics"], "condition": free_adj["condition"],
                   "chi2_red": free_adj["chi2_red"], "dof": free_adj["dof"],
                   "variance_factor": free_adj["variance_factor"], "rms_px": free_adj["rms_px"],
                   "held_out_rms_px": ho, "n_held_out": int(sum(len(v) for v in as_placed.values()))})
    scored = {k: v for k, v in ho.items() if v is not None and k != "sfm_poses_refit"}
    best = min(scored, key=scored.get) if "sfm" in scored else "sfm"
    report["chosen"] = best
    chosen, refined = free_adj, None
    if best != "sfm":
        chosen = (free_adj if best == "f_pp_k1"
                  else adjust_shared_camera(base, poses, cps, opts, free=INTRINSIC_SETS[best], use=use))
        report["refined_intrinsics"] = chosen["intrinsics"].to_dict()
        refined = chosen["intrinsics"]
        report["sigma_refined"] = chosen["sigma_intrinsics"]
        for n, M in chosen["poses"].items():
            by_name[n]["intrinsics"] = chosen["intrinsics"].to_dict()
            by_name[n]["cam_from_world"] = M.tolist()
            by_name[n]["center_enu"] = (-M[:3, :3].T @ M[:3, 3]).tolist()
    uncertainty, centres = {}, {}
    for n in poses:
        # the stated uncertainty: the intrinsics-free adjustment's (or the chosen one's, if larger)
        C = free_adj["cov_centre"][n]
        if np.linalg.eigvalsh(chosen["cov_centre"][n]).max() > np.linalg.eigvalsh(C).max():
            C = chosen["cov_centre"][n]
        uncertainty[n] = {**cov_report(C), "sigma_rotation_deg": max(free_adj["sigma_rot_deg"][n],
                                                                     chosen["sigma_rot_deg"][n]),
                          "from": "joint adjustment of the shared camera (intrinsics free)",
                          "intrinsics": "refined (" + best + ")" if best != "sfm" else "sfm"}
        if best != "sfm":  # the photo takes the chosen adjustment's pose and intrinsics: their joint error
            fac = chosen["factor"]
            uncertainty[n]["joint"] = {"pose_factor": fac["poses"][n], "params": fac["params"],
                                       "intrinsics_factor": fac["intrinsics"]}
        M = free_adj["poses"][n]
        centres[n] = -M[:3, :3].T @ M[:3, 3]
    return report, uncertainty, centres, refined


def _model_uncertainty(n: str, placed: dict, adjusted_centres: dict[str, np.ndarray]) -> dict:
    """A photo placed by its model but not adjusted: the similarity's covariance plus the model's own scatter
    (its adjusted photos about their model poses)."""
    label, res, sv = placed[n]
    C = np.zeros((3, 3))
    if res.covariance is not None:
        q = res.scale * res.rotation @ (-sv.cam_from_model[:3, :3].T @ sv.cam_from_model[:3, 3])
        Jc = np.hstack([q[:, None], -skew(q), np.eye(3)])
        C = Jc @ res.covariance @ Jc.T
    d2 = []
    for m, c_adj in adjusted_centres.items():
        if m in placed and placed[m][0] == label:
            A = res.cam_from_world(placed[m][2].cam_from_model)
            d2.append(float(np.sum((-A[:3, :3].T @ A[:3, 3] - c_adj) ** 2)))
    shape = float(np.mean(d2) / 3.0) if d2 else None
    return {**cov_report(C + (shape or 0.0) * np.eye(3)),
            "from": "similarity of SfM " + label + (
                f" plus its photos' scatter about their adjusted poses ({len(d2)} photos)" if d2 else
                " (the SfM model's own error not included: no photo of it could be adjusted)")}


def adjust_cameras(models, placed: dict, resected: dict, out_views: list[dict], cps: list[ControlPoint],
                   opts: GeorefOptions) -> tuple[dict, list, dict]:
    """(photo -> stated uncertainty, the adjustments' reports, SfM camera key -> refined intrinsics); see the
    module docstring. ``placed``: photo -> (model label, similarity, SfM view); ``resected``: photo -> its
    resection. ``out_views`` (cameras.json entries) is updated in place."""
    by_name = {v["name"]: v for v in out_views}
    groups, base_of = _camera_groups(models, by_name)
    uncertainty: dict[str, dict] = {}
    adjustments: list[dict] = []
    adjusted_centres: dict[str, np.ndarray] = {}  # photo -> centre from the intrinsics-free adjustment
    refined: dict[str, CameraIntrinsics] = {}  # SfM camera (key) -> its refined intrinsics
    for key, names in (groups.items() if opts.adjust_camera else ()):
        report, unc, centres, intr = _adjust_group(base_of[key], names, by_name, placed, resected, cps, opts)
        if report is None:
            continue
        for u in unc.values():  # the photos of one adjusted camera share its error (one factor)
            if "joint" in u:
                u["joint"]["group"] = f"camera_adjustment[{len(adjustments)}]"
        if intr is not None:
            refined[key] = intr
        uncertainty.update(unc)
        adjusted_centres.update(centres)
        adjustments.append(report)
    for n, v in by_name.items():
        if n in uncertainty:
            continue
        if n in placed:
            uncertainty[n] = _model_uncertainty(n, placed, adjusted_centres)
        elif n in resected:
            r = resected[n]["report"]
            uncertainty[n] = {"sigma_centre_m": r.get("sigma_centre_max_m"),
                              "from": "resection (the intrinsics' error not included: too few picks to adjust)"}
    return uncertainty, adjustments, refined
