"""What the report says beside the carriages table: what the 95 % intervals include (:func:`interval_scope`), and
how often they held the truth in simulation, per route (docs/calibration.md has the commands and the full
tables)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

# How often the 95 % intervals held the truth in simulation, per route (docs/calibration.md, where the commands
# and the full tables are; measured 2026-11-26 to 2026-11-28 with scripts/bench_calibration.py): a reader's check on
# the ±.
CALIBRATION = {
    "hand_known": "On simulated consists with hand-picked points and a known focal the 95 % intervals held the "
                  "truth in 94.0-95.6 % of cases per axis (2607 carriages), and in 93.1-95.5 % on a fresh set "
                  "(202 carriages): calibrated.",
    "hand_focal": "On simulated consists with hand-picked points and the focal estimated, without a terrain model, "
                  "they held the truth in 94.3-95.2 % of cases per axis (2607 carriages) and 92.1-96.5 % on a fresh "
                  "set (202); with a terrain model as accurate as it states (0.03, 0.05 or 0.10 m per carriage; "
                  "scripts/bench_terrain_focal.py), in 93.4-96.1 % of cases per axis on fresh sets of 3003 "
                  "carriages each (546 problems), the typical error 0.98-1.06 times what the intervals say: "
                  "calibrated. With a terrain model more accurate than it states, the intervals are wider than the "
                  "errors.",
    "auto": "On six sets of fresh generated incidents with automatic points (800x600 photos, each DEM given the "
            "0.25 m error it states; 203, 202, 200, 200, 204 and 212 carriages) the intervals of the unmarked "
            "carriages held the truth in 88.5-96.7 %, 94.8-97.9 %, 94.1-97.3 %, 93.3-98.9 %, 95.7-98.4 % and "
            "93.1-97.4 % of cases per axis (the last with today's code; the four before it run again with today's "
            "finder and covariance and pooled, 739 carriages, two far off named below left out: 94.7-97.3 %, the "
            "typical error 0.90-1.00 times what the intervals say). 21, 11, 13, 22, 17 and 23 carriages were "
            "marked doubtful (‡); of the 24 that lay far outside their intervals 3 were not: one 3.3 m off along "
            "the line of sight (its face's alignment was off by more than its matches showed), one on the wrong "
            "one of its face's two poses (today's finder, which also asks the terrain, places it right), one "
            "matched on something else in the scene; run again today, one more far side given to the wrong coach "
            "of its type goes unmarked. The "
            "carriages stood on average a little too far from the camera (0.2-0.6 sigma along the line of sight: "
            "the faces' alignments come out a little short across; not corrected). Pitch is a little wide, most on "
            "the carriages the pose search found. Heed the ‡ mark, and check every carriage against its photo "
            "overlay.",
    "relative": "On simulated relative incidents (no survey; hand-picked points, a known focal, the track tilted "
                "0.5° against gravity) they held the truth in 94.5-98.0 % of cases per axis (600 carriages), and "
                "94.0-98.0 % on two fresh sets measured with the current code (600 carriages each; 94.7-97.1 % "
                "pooled, the typical error 0.95-1.02 times what the intervals say): calibrated.",
    "relative_focal": "On simulated relative incidents (no survey; hand-picked points, the focal and the principal "
                      "point not known, the track tilted 0.5° against gravity) they held the truth in 93.8-98.0 % "
                      "of cases per axis on two fresh sets measured with the current code (600 carriages each; "
                      "94.9-97.2 % pooled, the typical error 0.94-1.02 times what the intervals say): calibrated.",
    "multiview": "On generated multi-view incidents with hand-picked points (SfM poses exact relative to one "
                 "another) they held the truth in 91.4-97.5 % and 93.4-95.9 % of cases per axis on two sets (197 "
                 "unmarked carriages each; RMS of error / sigma 0.92-1.05 and 1.04-1.13); 4 and 3 more, far off "
                 "their intervals, were marked doubtful. With pycolmap's own models (the SfM model's poses and "
                 "intrinsics carried together) they held it in 94.2-96.3 % of cases per axis (242 unmarked "
                 "carriages in 9 incidents; RMS of error / sigma 0.92-1.08), and 94.2-97.1 % on a fresh set (413 "
                 "unmarked carriages in 14 incidents, 10 draws each; RMS 0.93-1.01; 14 more marked doubtful, the 2 "
                 "far off among them); a third fresh set of 7 incidents was a little narrow alone in north and "
                 "heading (88.4 and 89.8 %), and with the second 92.6-96.4 % (638 unmarked carriages in 21 "
                 "incidents; RMS 0.94-1.06). Heed the ‡ mark.",
}


def calibration_note(solution: dict) -> str:
    """The calibration figures (:data:`CALIBRATION`) of the route this solution took: automatic points (any point
    from the finder), multi-view, a relative scene, else hand picks; with the focal estimated or known."""
    by_source = (solution.get("correspondences") or {}).get("by_source") or {}
    if by_source.get("sift"):
        return CALIBRATION["auto"]
    if solution.get("route") == "multiview":
        return CALIBRATION["multiview"]
    if (solution.get("frame") or {}).get("kind") == "relative":
        return CALIBRATION["relative_focal" if solution.get("sigma_focal_px") else "relative"]
    return CALIBRATION["hand_focal" if solution.get("sigma_focal_px") else "hand_known"]


def alignment_phrase(n_aligned: int, more_px: float | None) -> str:
    """What the ± include for the automatic points placed by their face's alignment: its error from its own
    matches (``n_aligned`` points), and, where a face's reference matched the photo less closely, the misfit added
    to it (up to ``more_px``, ``aligned_misfit_max_px`` of solution.json; docs/calibration.md, "Session 25")."""
    more = (f"; up to {float(more_px):.2f} px more where a face's reference matched the photo less closely, from "
            f"its alignment's correlation") if more_px else ""
    return (f"each automatically matched face's alignment error, from its own matches and shared by the photos it "
            f"is aligned in ({n_aligned} points{more})")


def face_misfit_phrase(face_px: float, largest_px: float | None, estimated: bool) -> str:
    """What the ± include for the automatic faces without an alignment error of their own: their shared misfit
    ``face_px`` (estimated or configured), and, when a face's ECC correlation gave more, the largest
    (``face_misfit_max_px`` of solution.json; docs/calibration.md, "Session 23"); configured, it is the face's
    alignment loading, in its own axes and shared with its pose predictions (docs/calibration.md, "Session 31")."""
    how = "estimated from the residuals" if estimated else "configured"
    if not estimated and largest_px is not None and float(largest_px) > face_px + 5e-3:
        how += (f"; up to {float(largest_px):.2f} px where a face's reference matched the photo less closely, from "
                f"its alignment's correlation")
    where = "" if estimated else (", in the face's own axes, less across it than along it, and carried into the "
                                  "points predicted from the car's pose fitted to those faces")
    return (f"a misfit shared by each automatically matched face without its own alignment error ({face_px:.2f} px, "
            f"{how}){where}")


def interval_scope(solution: dict, solver: Any, dem_accuracy_m: float | None) -> dict:
    """What the carriages' 95 % intervals include and leave out, from ``solution.json`` and the solver settings:
    ``{"included": [...], "excluded": [...], "text": a sentence or two}`` (docs/calibration.md)."""
    inc, exc = [], []
    sig, est, dof, q = (solution.get(k) for k in ("sigma_px", "sigma_px_estimated", "dof", "ci95_factor"))
    fit = "the fit of the marked points"
    estimated = bool(solution.get("noise_estimated"))
    if sig is not None and estimated:
        fit += (f" (pixel noise {number_text(sig, 2)} px, estimated from the residuals with the faces' shared misfit "
                f"({number_text(dof, 0)} degrees of freedom)"
                + (f"; ± = {number_text(q, 2)} σ" if q is not None else "") + ")")
    elif sig is not None:
        aside = ("the misfit a principal point off the photo's centre leaves" if (solution.get(
            "camera_uncertainty") or {}).get("principal_point") else "the photos' disagreement that their stated "
            "camera errors account for")
        fit += f" (pixel noise {number_text(sig, 2)} px" + (
            f": the residuals' {number_text(est, 2)} px ({number_text(dof, 0)} degrees of freedom) pooled with the "
            f"configured {number_text(solver.pixel_sigma_px, 2)} px" if est is not None and dof else "") + (
            f"; {aside} ({number_text(solution['sigma_px_camera'], 2)} px RMS) set aside"
            if solution.get("sigma_px_camera") else "") + (
            f"; ± = {number_text(q, 2)} σ" if q is not None else "") + ")"
    inc.append(fit)
    by_source = (solution.get("correspondences") or {}).get("by_source") or {}
    face = solution.get("face_sigma_px")
    if face is None and solver.face_sigma_px != "estimate":  # a solution.json written before the field
        face = float(solver.face_sigma_px)
    n_aligned = (solution.get("correspondences") or {}).get("n_with_alignment") or 0
    if by_source.get("sift") and n_aligned:
        inc.append(alignment_phrase(n_aligned, solution.get("aligned_misfit_max_px")))
    if by_source.get("sift") and face is not None and float(face) > 0 and int(by_source["sift"]) > n_aligned:
        inc.append(face_misfit_phrase(float(face), solution.get("face_misfit_max_px"), estimated))
    if solution.get("links"):
        inc.append(f"the couplers' play ({number_text(100 * float(solver.slack_held_m), 0)} cm)")
    swung = [c for c in solution.get("carriages", []) if c.get("centre_curvature_m2") is not None]
    if swung:  # docs/solver.md: a carried carriage's swing about its held coupling, to second order
        big = max(math.sqrt(max(float(np.trace(np.asarray(c["centre_curvature_m2"], float))), 0.0)) for c in swung)
        inc.append(f"for the {len(swung)} carriage(s) carried by their couplings, the curve of their swing about "
                   f"the coupling (up to {number_text(big, 2)} m)")
    if any((st.get("facts") or {}).get("terrain_contact") for st in solution.get("steps", [])) \
            and dem_accuracy_m is not None:
        inc.append(f"the contact with the terrain model (±{number_text(dem_accuracy_m, 2)} m, carriage by carriage)")
    cu = solution.get("camera_uncertainty") or {}
    if cu.get("included"):
        what = {"relative": "the levelling of the relative scene", "gps": "the GPS and compass placement"}.get(
            (solution.get("frame") or {}).get("kind"), "the cameras' georegistration" if solution.get("route") ==
            "multiview" else "the camera's georegistration")
        centre = max(cu.get("sigma_centre_m") or [0.0])
        inc.append(f"{what} (1σ up to " + (f"{number_text(centre, 2)} m and " if centre > 0 else "") +
                   f"{number_text(max(cu.get('sigma_rotation_deg') or [0.0]), 3)}°" +
                   (", a turn about the camera" if not centre > 0 else "") + ")")
    else:
        exc.append("the cameras' georegistration (taken as exact)")
    pp = cu.get("principal_point") or {}
    if pp.get("sigma_px") is not None:
        inc.append(f"the principal point, not known (1σ {number_text(pp['sigma_px'], 0)} px from the photo's centre)")
    sf = solution.get("sigma_focal_px") or {}
    if sf:
        inc.append("the focal length, estimated (1σ "
                   + ", ".join(sorted({f"{number_text(v, 0)} px" for v in sf.values()})) + ")")
    else:
        exc.append(f"the focal length (taken as known: {solution.get('intrinsics_source') or 'given'})")
    exc += ["errors of the carriage models", "a common offset of the terrain model",
            "a wrong match the outlier check kept"]
    text = "The ± include " + ", ".join(inc[:-1]) + (" and " if len(inc) > 1 else "") + inc[-1] + \
        ". Not included: " + ", ".join(exc) + "."
    return {"included": inc, "excluded": exc, "text": text, "calibration": calibration_note(solution)}


def number_text(x, nd: int) -> str:
    """``x`` with ``nd`` decimals and a true minus sign; \u2013 for None or a number that is not finite."""
    if x is None:
        return "–"
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(x):
        return "–"
    return f"{x:.{nd}f}".replace("-", "\u2212")
