#!/usr/bin/env python
"""The face alignments' stated covariance against the truth, point by point (issue 21).

    .venv/bin/python scripts/bench_alignment_points.py --work DIR [--work DIR ...]

For every incident ``inc_*`` under each ``--work`` folder (or an incident folder itself) with a
``truth/ground_truth.json`` (``workbench synth``) and an ``out/correspond/correspondences.json`` whose points carry
``alignment`` loadings (docs/correspondences.md, "What a face's alignment measures"), it compares each aligned
point's error (found pixel minus the true pixel of the photo on disk) with its stated covariance:

* per coordinate, RMS of error / stated sigma (``sqrt`` of the diagonal of ``L L^T``; 1 when the stated
  covariance is right);
* per alignment (carriage, face, view), the squared Mahalanobis length of its points' errors in ``L L^T`` (its
  pseudo-inverse) over its rank (1 when right);
* the share of the error common to the views: for a point seen through its face in two photos, the cosine
  between its two error vectors (0 for errors independent from photo to photo, as the stated blocks are);
* the RMS error, and the stated sigma's RMS;
* the faces' shape (:func:`shape_errors`): per kind of face (its name, matched by its own SIFT matches or guided by
  a pose), the mean relative error of its points' spread along the face's long axis in the photo and across it,
  and the pose predictions' (``method = "pose"``) spread about their face's points (-0.003: 0.3 % too small,
  the car placed 0.3 % too far). A mean away from 0 over many faces is a bias no stated covariance holds
  (docs/calibration.md, "Session 26").
"""

from __future__ import annotations

import argparse
import json
from itertools import combinations
from pathlib import Path

import numpy as np


def incidents(paths: list[Path]) -> list[Path]:
    out = []
    for p in paths:
        out += [p] if (p / "truth").is_dir() else sorted(q for q in p.glob("inc_*") if (q / "truth").is_dir())
    return out


def true_pixels(truth: dict) -> dict[tuple[str, str, str], np.ndarray]:
    """``{(car, point, photo file name): true pixel (2,)}`` of the photos on disk, from ground_truth.json."""
    return {(car, pt, Path(ph["photo"]).name): np.asarray(o["uv"], float)
            for ph in truth["photos"] for car, pts in ph.get("observations", {}).items() for pt, o in pts.items()}


def _scale(found: np.ndarray, true: np.ndarray, axes: np.ndarray | None = None):
    """The relative error of the spread of points ``found`` (n, 2) about their mean against ``true`` (n, 2): along
    the rows of ``axes`` (2, 2), least squares of each axis's component on the true offsets (the along one: the
    true spread's principal direction); without ``axes`` one radial scale."""
    r = true - true.mean(0)
    e = (found - true) - (found - true).mean(0)
    if axes is None:
        return float(np.sum(e * r) / np.sum(r * r))
    X = r @ axes.T
    return [float(np.linalg.lstsq(X, e @ ax, rcond=None)[0][k]) for k, ax in enumerate(axes)]


SHAPE_MIN_ACROSS_PX = 3.0  # a face whose points spread less than this across (RMS, px) does not measure it


def shape_errors(corr: dict, truth: dict) -> list[dict]:
    """Per face alignment (car, face, photo) with 3 or more points on its plane (``method = "homography"``), the
    relative error of their spread along the face's long axis and across it (``along``, ``across``: -0.01 is 1 %
    too short), and per car and photo with 3 or more pose predictions, their radial spread's error about the
    true mean (``radial``); points off by over 5 px RMS (a mismatch) are left out."""
    true_uv = true_pixels(truth)
    groups: dict[tuple, list] = {}
    for o in corr["observations"]:
        t = true_uv.get((o["carriage"], o["point"], o["view"]))
        m = o.get("method")
        if t is None or m not in ("homography", "pose"):
            continue
        kind = (o["face"] + ("/matched" if o.get("alignment") else "/guided")) if m == "homography" else "pose"
        groups.setdefault((o["carriage"], o["view"], kind), []).append((np.asarray(o["uv"], float), t))
    out = []
    for (car, view, kind), pts in groups.items():
        F, T = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
        if len(pts) < 3 or np.sqrt(np.mean(np.sum((F - T) ** 2, axis=1))) > 5.0:
            continue
        rec = {"carriage": car, "view": view, "kind": kind, "n": len(pts)}
        if kind == "pose":
            rec["radial"] = _scale(F, T)
        else:
            ev, V = np.linalg.eigh(np.cov((T - T.mean(0)).T, bias=True))
            if np.sqrt(ev[0]) < SHAPE_MIN_ACROSS_PX:
                continue
            rec["along"], rec["across"] = _scale(F, T, np.vstack([V[:, 1], V[:, 0]]))
        out.append(rec)
    return out


def print_shapes(recs: list[dict]) -> None:
    kinds = sorted({r["kind"] for r in recs})
    print("the faces' shape against the truth (relative error of the points' spread; mean +- its standard error):")
    for k in kinds:
        rs = [r for r in recs if r["kind"] == k]
        parts = []
        for key in ("along", "across", "radial"):
            x = np.array([r[key] for r in rs if key in r])
            if len(x):
                parts.append(f"{key} {x.mean():+.4f} +- {x.std() / np.sqrt(len(x)):.4f} (median {np.median(x):+.4f})")
        print(f"  {k:16s} {len(rs):5d} faces: " + "; ".join(parts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, nargs="+", required=True)
    ap.add_argument("--out", type=Path, default=None, help="save the per-point records as JSON")
    a = ap.parse_args()
    z, maha, cos, err, sig, recs, shapes = [], [], [], [], [], [], []
    for root in incidents(a.work):
        corr = json.loads((root / "out/correspond/correspondences.json").read_text())
        truth = json.loads((root / "truth/ground_truth.json").read_text())
        shapes += [{"incident": root.name, **r} for r in shape_errors(corr, truth)]
        true_uv = true_pixels(truth)
        blocks: dict[tuple, list] = {}
        for o in corr["observations"]:
            al = o.get("alignment")
            t = true_uv.get((o["carriage"], o["point"], o["view"]))
            if al is None or t is None:
                continue
            e = np.asarray(o["uv"], float) - t
            L = np.asarray(al["loading_px"], float)
            blocks.setdefault((o["carriage"], o["face"], o["view"]), []).append((o["point"], e, L))
        by_point: dict[tuple, list] = {}
        for (car, face, view), pts in blocks.items():
            e = np.concatenate([p[1] for p in pts])
            L = np.vstack([p[2] for p in pts])
            s = np.sqrt(np.sum(L**2, axis=1))
            if np.any(np.abs(e) > 20):  # a mismatched point, not the alignment's noise
                continue
            z += list(e / s)
            err += list(e)
            sig += list(s)
            C = L @ L.T
            ev, V = np.linalg.eigh(C)
            keep = ev > ev[-1] * 1e-8
            maha.append(float(np.sum((V[:, keep].T @ e) ** 2 / ev[keep])) / int(keep.sum()))
            for p in pts:
                by_point.setdefault((car, face, p[0]), []).append(p[1])
            recs.append({"incident": root.name, "carriage": car, "face": face, "view": view,
                         "error_px": e.tolist(), "sigma_px": s.tolist(), "mahalanobis_per_rank": maha[-1]})
        for es in by_point.values():
            for e1, e2 in combinations(es, 2):
                n1, n2 = np.linalg.norm(e1), np.linalg.norm(e2)
                if n1 > 0 and n2 > 0:
                    cos.append(float(e1 @ e2 / (n1 * n2)))
    z, err, sig = np.array(z), np.array(err), np.array(sig)
    print(f"{len(incidents(a.work))} incidents, {len(maha)} alignments, {len(z) // 2} points")
    print(f"RMS error {np.sqrt(np.mean(err**2)):.3f} px per coordinate; stated sigma RMS {np.sqrt(np.mean(sig**2)):.3f} px")
    print(f"RMS z per coordinate {np.sqrt(np.mean(z**2)):.2f}; robust z {np.median(np.abs(z)) / 0.6745:.2f}")
    print(f"Mahalanobis per rank: median {np.median(maha):.2f}, mean {np.mean(maha):.2f}")
    if cos:
        print(f"the same point's error in two photos: mean cosine {np.mean(cos):.2f} over {len(cos)} pairs "
              f"(0: independent)")
    print_shapes(shapes)
    if a.out:
        a.out.write_text(json.dumps({"alignments": recs, "shapes": shapes}))


if __name__ == "__main__":
    main()
