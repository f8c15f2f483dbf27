"""Track picks checked against the truth of a synthetic incident (issue 17): the panorama's photos as the central
georef solver sees them, the true track picks with noise, and what a camera placed with some error does to the
carriages' chainage. Used by ``tests/test_georef_track.py`` and ``scripts/bench_track_georef.py``.

The carriages are moved rigidly with the camera: ``world_from_carriage`` placed as ``world_from_rig (estimated) .
rig_from_world (true) . world_from_carriage (true)``, i.e. each carriage's pose relative to the camera taken as
the solve would find it without error; so the chainage error here is the camera placement's share alone (the
solve's own error, docs/gis.md "Railway lines", adds to it).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.camera import CameraIntrinsics
from ..core.frames import SceneFrame
from ..core.geometry import exp_so3, log_so3
from ..core.track import RailwayLine
from ..errors import InputError
from ..files.control_points import parse_track_picks
from ..files.panorama import RigView
from ..files.railways import read_railways
from ..georef.track_picks import TrackTerm, build_track_term
from .control_points import true_world_from_pano

__all__ = ["PanoramaTruth", "panorama_truth", "noisy_track_term", "chainage_errors", "rotation_error"]


@dataclass(frozen=True)
class PanoramaTruth:
    """The truth's panorama: its photos as rig views (rig = ``true_world_from_pano``'s frame), the true
    ``rig_from_world`` and centre, the railway line as the layer file gives it (top-of-rail heights), and the
    carriages' true body centres (k, 3) and chainages (k,) on that line."""

    views: list[RigView]
    rig_from_world: np.ndarray
    centre_enu: np.ndarray
    line: RailwayLine
    body_centres: np.ndarray
    chainages: np.ndarray
    frame: SceneFrame


def panorama_truth(root: str | Path) -> PanoramaTruth:
    root = Path(root)
    truth = json.loads((root / "truth" / "ground_truth.json").read_text(encoding="utf-8"))
    fr = truth["frame"]
    frame = SceneFrame(fr["crs"], fr["lat"], fr["lon"], fr["height_m"])
    Rwp = true_world_from_pano(root)
    views = []
    for ph in truth["photos"]:
        if ph["set"] == "panorama":
            R = np.asarray(ph["cam_from_world"], float)[:3, :3]
            views.append(RigView(Path(ph["photo"]).name, CameraIntrinsics.from_dict(ph["intrinsics"]), R @ Rwp))
    layer = read_railways(root / truth["layers"]["railways"], frame)
    if layer is None or not views:
        raise InputError(f"{root}: the truth has no railway line or no panorama photo")
    line = layer.lines[0]
    centres = np.array([c["body_centre_enu"] for c in truth["carriages"]], float)
    chain = np.array([line.foot(b[:2]).chainage_m for b in centres])
    return PanoramaTruth(views, Rwp.T, np.asarray(truth["panorama_center_enu"], float), line, centres, chain, frame)


def noisy_track_term(pt: PanoramaTruth, entries: list[dict], rng: np.random.Generator, sigma_px: float, *,
                     line_sigma_m: float = 0.0, height_sigma_m: float = 0.0) -> TrackTerm:
    """The track term of the noise-free ``entries`` (``track_picks`` of :func:`track_picks_document` with
    ``sigma_px=0``) with Gaussian noise of ``sigma_px`` drawn from ``rng``, weighted with that sigma."""
    size = {v.name: (v.intrinsics.width, v.intrinsics.height) for v in pt.views}
    noisy = []
    for e in entries:
        uv = np.asarray(e["pixels"], float) + rng.normal(0.0, sigma_px, (len(e["pixels"]), 2))
        w, h = size.get(e["photo"], (np.inf, np.inf))
        noisy.append({**e, "pixels": np.clip(uv, -0.5, [w - 0.5, h - 0.5]).tolist()})  # kept inside the photo
    picks = parse_track_picks({"crs": "EPSG:4326", "track_picks": noisy})
    term = build_track_term(picks, [pt.line], pt.views, sigma_px=sigma_px, line_sigma_m=line_sigma_m,
                            height_sigma_m=height_sigma_m, where="synthetic track picks")
    if term is None:
        raise InputError("no track pick in the panorama's photos")
    return term


def _moved(pt: PanoramaTruth, theta: np.ndarray, R_est: np.ndarray, c_est: np.ndarray) -> np.ndarray:
    """(k, 3) body centres moved rigidly with the camera placed at (``Exp(theta) R_est^T``, ``c_est``)."""
    local = (pt.body_centres - pt.centre_enu) @ pt.rig_from_world.T  # in the rig frame
    return local @ (exp_so3(theta) @ R_est.T).T + c_est


def chainage_errors(pt: PanoramaTruth, R_est: np.ndarray, c_est: np.ndarray, cov_world: np.ndarray | None,
                    step: float = 1e-4) -> tuple[np.ndarray, np.ndarray | None]:
    """(each carriage's chainage error (k,) m, its 1-sigma from the camera's covariance (k,) or None) with the
    camera placed at ``rig_from_world`` R_est and centre c_est; ``cov_world`` (6, 6): the scene-frame rotation
    vector and centre (the solver's ``covariance_world_rotation_centre``), propagated by central differences."""
    def chain(x):
        b = _moved(pt, x[:3], R_est, c_est + x[3:])
        return np.array([pt.line.foot(p[:2]).chainage_m for p in b])

    err = chain(np.zeros(6)) - pt.chainages
    if cov_world is None:
        return err, None
    J = np.zeros((len(err), 6))
    for i in range(6):
        e = np.zeros(6)
        e[i] = step
        J[:, i] = (chain(e) - chain(-e)) / (2 * step)
    var = np.einsum("ki,ij,kj->k", J, np.asarray(cov_world, float), J)
    return err, np.sqrt(np.maximum(var, 0.0))


def rotation_error(R_est: np.ndarray, R_true: np.ndarray) -> tuple[np.ndarray, float]:
    """(scene-frame rotation vector of the error ``world_from_rig`` est . true^T (3,), its angle deg)."""
    v = log_so3(R_est.T @ R_true)
    return v, math.degrees(float(np.linalg.norm(v)))
