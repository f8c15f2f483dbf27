"""A one-face pose's two branches, told apart by the face's own fit and by where each puts the car on the ground.

A plane seen in one photo fits two poses (planar PnP, IPPE: the face mirrored about the line of sight). Seen far
and thin, a side 170 px long and 20 px high at 130 m, the face's own pixels hardly tell them apart, yet the
branch decides where the car's other points (its couplers, the corners of its other faces) are predicted, and the
wrong one tilts the car 10-60 deg. On the four automatic benchmark sets (seeds 240000- to 243000-, 1785 one-face
poses with pose predictions and a true branch) the lattice's own fit picked the wrong branch in 22, and one of them
ended 60 deg off in roll with an interval that did not doubt it (``docs/calibration.md``, session 32).

Where the photo has a camera pose in the scene and the incident a terrain model, each branch is also judged by its
**clearance**: the car's lowest collision-box corner above the terrain. A car rests on the ground; the wrong branch
rolls its body into it or off it. Each branch's score is a negative log-likelihood:

- the face's fit: ``FIT_DOF ln(rms)``, the profile likelihood of its residuals with the noise unknown. A face
  aligned by ECC gives its pose through a lattice mapped by one homography, whose residual to a pose has
  ``FIT_DOF`` = 2 degrees of freedom (a homography's 8 less a pose's 6); a face of raw matches has ``2 n - 6``.
- the ground: ``min(z^2, GROUND_CAP) / 2``, ``z`` the clearance over ``hypot(DEM accuracy, ONE_FACE_HEIGHT_M)``.
  Capped: a car 3 sigma off the terrain is no less likely 6 sigma off (debris, a neighbour, a bridge under it, a
  DEM that is wrong there).

Without a camera pose or a terrain model the face's fit alone decides. Units: pixels undistorted,
``cam_from_carriage`` and ``cam_from_world`` (4, 4) in metres, ``docs/conventions.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..rolling_stock import CarriageType
from .resting import collision_corners

FIT_DOF = 2.0  # an ECC lattice's residual degrees of freedom about a pose
ONE_FACE_HEIGHT_M = 0.25  # a one-face pose's own height error at the car's lowest corner (1 sigma, m)
GROUND_CAP = 9.0  # the ground's squared z counts up to 3 sigma


@dataclass(frozen=True)
class Ground:
    """The photo's camera in the scene and the terrain under it: what a one-face pose's branches are judged by."""

    cam_from_world: np.ndarray  # (4, 4)
    terrain: Any  # ``TerrainModel`` (``height_at((n, 2)) -> (n,)`` in the scene frame, NaN off the model)
    dem_accuracy_m: float  # the DEM's vertical accuracy (1 sigma, m), ``[terrain] dem_vertical_accuracy_m``

    @property
    def sigma_m(self) -> float:
        return math.hypot(self.dem_accuracy_m, ONE_FACE_HEIGHT_M)

    def clearance(self, ct: CarriageType, cam_from_carriage: np.ndarray) -> float:
        """Metres from the car's lowest collision-box corner down to the terrain at ``cam_from_carriage`` (negative:
        into it); NaN where the terrain model does not reach."""
        W = np.linalg.inv(self.cam_from_world) @ cam_from_carriage
        P = collision_corners(ct) @ W[:3, :3].T + W[:3, 3]
        h = np.asarray(self.terrain.height_at(P[:, :2]), float)
        return float(np.nanmin(P[:, 2] - h)) if np.any(np.isfinite(h)) else math.nan

    def score(self, clearance_m: float) -> float:
        """The ground's negative log-likelihood of a clearance (0 where it is unknown)."""
        if not math.isfinite(clearance_m):
            return 0.0
        return 0.5 * min((clearance_m / self.sigma_m) ** 2, GROUND_CAP)


@dataclass
class FacePose:
    """A one-face pose: ``cam_from_carriage`` (4, 4), which evidence chose its branch (``"fit"``: the face's
    residuals; ``"ground"``: the terrain overruled them), and each branch's residual RMS (px) and clearance (m)."""

    cam_from_carriage: np.ndarray
    chosen_by: str = "fit"
    rms_px: tuple[float, ...] = ()
    clearance_m: tuple[float, ...] = ()


def _as_matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = cv2.Rodrigues(rvec)[0]
    M[:3, 3] = np.asarray(tvec, float).ravel()
    return M


def planar_pose(X: np.ndarray, x: np.ndarray, K: np.ndarray, *, dof: float = FIT_DOF, ct: CarriageType | None = None,
                ground: Ground | None = None) -> FacePose | None:
    """The pose of a plane's points ``X`` (n, 3, carriage frame, coplanar) seen at ``x`` (n, 2, undistorted px) by
    the pinhole ``K`` (3, 3): both of IPPE's branches refined (Levenberg-Marquardt), and the one the face fits
    better, unless ``ground`` (with the car's type ``ct``) scores the other better (module doc). None: no pose in
    front of the camera. ``dof``: the residual's degrees of freedom (:data:`FIT_DOF` for an ECC lattice, ``2 n -
    6`` for raw matches). The refined fits are compared, not IPPE's own order (that of its closed-form poses, which
    the refinement reverses on far, thin faces: on a side 107 px by 10 px at 200 m, the refined order was right
    169 times in 200, IPPE's 160)."""
    X, x = np.asarray(X, np.float64), np.asarray(x, np.float64)
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(X, x, K, None, flags=cv2.SOLVEPNP_IPPE)
    branches = []
    for rvec, tvec in zip(rvecs[:n], tvecs[:n]):
        rvec, tvec = cv2.solvePnPRefineLM(X, x, K, None, rvec.copy(), tvec.copy())
        M = _as_matrix(rvec, tvec)
        if M[2, 3] <= 0:
            continue
        p = (K @ (M[:3, :3] @ X.T + M[:3, 3:4])).T
        rms = float(np.sqrt(np.mean(np.sum((p[:, :2] / p[:, 2:] - x) ** 2, axis=1))))
        branches.append((M, rms, ground.clearance(ct, M) if ground is not None and ct is not None else math.nan))
    if not branches:
        return None
    fit_only = min(range(len(branches)), key=lambda i: branches[i][1])
    if ground is None or ct is None:
        best = fit_only
    else:
        scores = [dof * math.log(max(rms, 1e-9)) + ground.score(c) for _, rms, c in branches]
        best = min(range(len(branches)), key=lambda i: scores[i])
    return FacePose(branches[best][0], "fit" if best == fit_only else "ground",
                    tuple(b[1] for b in branches), tuple(b[2] for b in branches))


__all__ = ["Ground", "FacePose", "planar_pose", "FIT_DOF", "ONE_FACE_HEIGHT_M", "GROUND_CAP"]
