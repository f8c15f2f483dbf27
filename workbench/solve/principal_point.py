"""The principal point a guessed camera model puts at the image centre, and what its error does to the carriages
(docs/solver.md, "Relative scenes").

A photo with no camera profile (``camera.source = "unknown"``: the fallback model, or a focal from EXIF) is
solved with its principal point at the image centre, which a real camera's is not: lens and sensor are assembled
to a tolerance, and calibrations put the point some pixels to tens of pixels off (the OpenCV sample camera of
``shared/data/calibration``: 23 px and 4 px off on 640 x 480). The solve holds it there, so its error is a
systematic error of every marked point of the photo, and the poses respond to it as the least squares does to any
shift of its pixels: to first order ``d_x = H^-1 J^T W E d_c`` (``E`` the pixels' derivative with respect to the
principal point: 1 in u for c_x, in v for c_y), with the focal free where it is estimated. A relative scene's
levelled frame follows the same cars (its up) and the ray through the centre pixel (its y), which the true
principal point turns with the truth's frame; the shift moves the cars sideways as a turned camera would but
hardly turns them, so what is left is mostly an error of every car's heading, nearly alike, of about the shift
over the focal. It is added to each carriage's covariance (:func:`add_principal_point_uncertainty`).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from .model import CarriageInput, ChainLink, SolveOptions, View
from .problem import Problem, carriage_weights, focal_groups, held_chains, prepare_cars
from .camera_residual import ViewCameraErrors
from .camera_term import add_pose_covariance, camera_pose_jacobian, inverse_psd
from .uncertainty import pixel_rows, prior_rows

__all__ = ["GUESSED_PRINCIPAL_POINT_SIGMA", "GUESSED_SOURCES", "guessed_principal_point_sigma_px",
           "principal_point_response", "add_principal_point_uncertainty", "guessed_principal_point_term",
           "guessed_principal_point_errors"]

# 1 sigma per axis of a guessed principal point, as a fraction of the photo's larger side
GUESSED_PRINCIPAL_POINT_SIGMA = 0.01


def guessed_principal_point_sigma_px(width: int, height: int) -> float:
    """The 1-sigma error (px, per axis) of a principal point taken at the centre of a ``width`` x ``height``
    photo."""
    return GUESSED_PRINCIPAL_POINT_SIGMA * float(max(width, height))


def _active_chains(n: int, links: Sequence[ChainLink], active: set[int]) -> tuple[list[list[int]], list[list[float]]]:
    """The held chains cut at every carriage not in ``active`` (it has no pose to hold its neighbours by)."""
    members, slacks = [], []
    for ch, sl in zip(*held_chains(n, links)):
        run, rs = [], []
        for j, k in enumerate(ch):
            if k not in active:
                if run:
                    members.append(run)
                    slacks.append(rs[:len(run) - 1])
                run, rs = [], []
                continue
            run.append(k)
            if j < len(ch) - 1:
                rs.append(sl[j])
        if run:
            members.append(run)
            slacks.append(rs[:len(run) - 1])
    return members, slacks


def principal_point_response(carriages: Sequence[CarriageInput], links: Sequence[ChainLink], views: Sequence[View],
                             res: Any, options: SolveOptions) -> dict[str, np.ndarray]:
    """Carriage number -> (6, 2): the first-order response of its solved pose (scene rotation vector, origin: the
    order of ``covariance_pose``) to an error of the principal point (c_x, c_y in px) shared by every view (one
    camera), at the solution ``res`` of ``carriages`` seen in ``views``: the least squares' own response (its
    pixel rows weighted as the solve weights them, the held couplings' prior, the focal free where
    ``options.estimate_focal``; predictions carry nothing). Carriages without a pose are left out."""
    cars = prepare_cars(carriages, views, options)
    active = [k for k, cr in enumerate(res.carriages) if cr.world_from_carriage is not None]
    if not active:
        return {}
    prob = Problem(cars, active, views, carriage_weights(cars, active, options.weighting))
    R = np.array([np.asarray(c.world_from_carriage, float)[:3, :3] if c.world_from_carriage is not None else np.eye(3)
                  for c in res.carriages])
    t = np.array([np.asarray(c.world_from_carriage, float)[:3, 3] if c.world_from_carriage is not None else np.zeros(3)
                  for c in res.carriages])
    f = np.array([float(res.focal_px.get(v.name, v.intrinsics.fx)) for v in views])
    used = [v for v in range(len(views)) if len(prob.by_view[v]) > 0]
    free = [v for v in used if not views[v].focal_known] or used
    fv = focal_groups(views, free) if options.estimate_focal else []
    J, _, col, P = pixel_rows(prob, R, t, f, fv)
    meas = np.repeat(prob.measured, 2)
    E = np.zeros((len(J), 2))  # the weighted rows' derivative with respect to (c_x, c_y)
    E[0::2, 0] = prob.w
    E[1::2, 1] = prob.w
    J, E = J[meas], E[meas]
    sigma = float(res.sigma_px) if np.isfinite(getattr(res, "sigma_px", np.nan)) else options.pixel_sigma_px
    chains, slacks = _active_chains(len(cars), links, set(active))
    Jp = prior_rows(cars, R, t, chains, slacks, col, P)
    H = J.T @ J / sigma**2 + Jp.T @ Jp
    D = inverse_psd(0.5 * (H + H.T)) @ (J.T @ E) / sigma**2  # (P, 2): a pixel shift the poses follow
    return {res.carriages[k].number: D[col[k]:col[k] + 6] for k in active}


def add_principal_point_uncertainty(res: Any, carriages: Sequence[CarriageInput], links: Sequence[ChainLink],
                                    views: Sequence[View], options: SolveOptions, sigma_px: float,
                                    levelling: Any = None, levelled_from_world: np.ndarray | None = None,
                                    centre: np.ndarray | None = None) -> dict:
    """Add a guessed principal point's error (``sigma_px`` per axis, shared by every view) to every carriage's
    covariance, in place. ``levelling``: the relative scene's :class:`~workbench.solve.level.Levelling`, whose
    frame follows the cars it was levelled from (:meth:`~workbench.solve.level.Levelling.frame_turn`), so that
    the scene's common turn is taken back; ``levelled_from_world`` (3, 3) the rotation from the solve's frame to
    the levelled one (None: the same frame, the relative scene; a scene placed by GPS and compass after levelling
    gives its own) and ``centre`` (3,) the camera centre there (None: the origin). Returns the record:
    ``sigma_px``, and per carriage the sigmas (heading / pitch / roll deg, body centre m) this term alone gives."""
    D = principal_point_response(carriages, links, views, res, options)
    L = np.eye(3) if levelled_from_world is None else np.asarray(levelled_from_world, float)
    c = np.zeros(3) if centre is None else np.asarray(centre, float)
    if levelling is not None and D:
        turn = levelling.frame_turn({n: L @ d[:3] for n, d in D.items()})  # (3, 2), levelled frame
        if levelling.forward_response is not None:
            # the frame's y follows the ray through the centre pixel, which a true principal point off the centre
            # turns: the truth's frame turns with it (to first order the photo turned), and so the error is the
            # solution's response less that turn
            R = np.asarray(views[0].cam_from_world, float)[:3, :3]
            f = float(res.focal_px.get(views[0].name, views[0].intrinsics.fx))
            d_ray = np.array([[-1.0 / f, 0.0], [0.0, -1.0 / f], [0.0, 0.0]])  # d K^-1(centre) / d (c_x, c_y)
            turn = turn - levelling.forward_response @ L @ R.T @ d_ray
        turn = L.T @ turn  # the solve's frame
        for number, d in D.items():
            M = np.asarray(res.carriage(number).world_from_carriage, float)
            D[number] = d + camera_pose_jacobian(M, c)[:, :3] @ turn
    extra = {n: sigma_px**2 * d @ d.T for n, d in D.items()}
    return {"sigma_px": float(sigma_px), "carriages": add_pose_covariance(res, extra)}


GUESSED_SOURCES = ("fallback", "exif")  # cameras.json intrinsics_source whose principal point is the centre


def guessed_principal_point_errors(views: Sequence[View], intrinsics_source: str | None) -> ViewCameraErrors | None:
    """A relative scene's guessed principal point (``intrinsics_source`` in :data:`GUESSED_SOURCES`, where
    :func:`guessed_principal_point_term` adds its error) as the camera errors the fit sets aside when it estimates
    its pixel sigma (:mod:`.camera_residual`): ``(c_x, c_y)`` shared by every view,
    :data:`GUESSED_PRINCIPAL_POINT_SIGMA` of the reference photo's larger side per axis. A principal point off the
    centre is not a turn of the camera: the pixels it moves differ from a turn's by about the shift times (distance
    from the centre / focal)^2, 3 px at a 1600 px photo's edge for a 16 px shift, which no pose follows. The
    residuals then hold it, and a pixel sigma estimated from them would count it as noise while
    :func:`add_principal_point_uncertainty` adds its effect on the poses: twice. None for a camera that is not
    guessed, or without views."""
    if not views or intrinsics_source not in GUESSED_SOURCES:
        return None
    intr = views[0].intrinsics
    sigma = guessed_principal_point_sigma_px(intr.width, intr.height)
    return ViewCameraErrors(sigma**2 * np.eye(2), {}, {v.name: (("cx", "cy"), np.eye(2)) for v in views})


def guessed_principal_point_term(res: Any, carriages: Sequence[CarriageInput], links: Sequence[ChainLink],
                                 views: Sequence[View], options: SolveOptions, levelling: Any,
                                 intrinsics_source: str | None) -> dict | None:
    """A relative scene's (``levelling`` not None) guessed principal point added to its carriages' intervals
    (:func:`add_principal_point_uncertainty`, :data:`GUESSED_PRINCIPAL_POINT_SIGMA` of the reference photo's
    larger side), also where the levelled scene was then placed by GPS and compass (``levelling.placement``).
    None, and nothing changed, for a calibrated camera or a georeferenced scene. The record: ``sigma_px``, a
    note, and per carriage the sigmas of the term alone."""
    if levelling is None or intrinsics_source not in GUESSED_SOURCES or not views:
        return None
    intr = views[0].intrinsics
    sigma = guessed_principal_point_sigma_px(intr.width, intr.height)
    placed = getattr(levelling, "placement", None)
    L, c = None, None
    if placed is not None:
        L = np.linalg.inv(np.asarray(placed["world_from_levelled"], float))[:3, :3]
        c = np.asarray(placed["centre_enu"], float)
    rec = add_principal_point_uncertainty(res, carriages, links, views, options, sigma, levelling, L, c)
    rec["note"] = (f"the camera's principal point is taken at the photo's centre ({intrinsics_source} intrinsics): "
                   f"its error ({GUESSED_PRINCIPAL_POINT_SIGMA:.0%} of the larger side, {sigma:.1f} px, 1 sigma per "
                   f"axis) is added to every carriage's interval (first order: mostly the headings, nearly alike; "
                   f"the tilt it brings is taken back by the levelling)")
    return rec
