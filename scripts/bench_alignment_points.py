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
* the RMS error, and the stated sigma's RMS.
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, nargs="+", required=True)
    ap.add_argument("--out", type=Path, default=None, help="save the per-point records as JSON")
    a = ap.parse_args()
    z, maha, cos, err, sig, recs = [], [], [], [], [], []
    for root in incidents(a.work):
        corr = json.loads((root / "out/correspond/correspondences.json").read_text())
        truth = json.loads((root / "truth/ground_truth.json").read_text())
        true_uv = {}
        for ph in truth["photos"]:
            name = Path(ph["photo"]).name
            for car, pts in ph.get("observations", {}).items():
                for pt, o in pts.items():
                    true_uv[(car, pt, name)] = np.asarray(o["uv"], float)
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
    if a.out:
        a.out.write_text(json.dumps(recs))


if __name__ == "__main__":
    main()
