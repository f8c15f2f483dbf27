#!/usr/bin/env python
"""Chessboard calibration (workbench.intrinsics.calibrate) against OpenCV's reference calibration.

Calibrates OpenCV's sample left01..14 (13 views, 640x480, 9x6 inner corners, 25 mm) and compares with
``left_intrinsics.yml`` (../shared/data/calibration/opencv_stereo_chessboard); also the right camera, and the
left camera with the worst view dropped. Prints a table and writes bench_out/calibrate.json.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BOARD = ROOT.parent / "shared" / "data" / "calibration" / "opencv_stereo_chessboard"
sys.path.insert(0, str(ROOT))

from workbench.core.io import atomic_write_json  # noqa: E402
from workbench.intrinsics.calibrate import CalibrationOptions, calibrate_chessboard  # noqa: E402


def reference() -> dict:
    import cv2

    fs = cv2.FileStorage(str(BOARD / "left_intrinsics.yml"), cv2.FILE_STORAGE_READ)
    K = fs.getNode("camera_matrix").mat()
    d = fs.getNode("distortion_coefficients").mat().ravel()
    rms = fs.getNode("avg_reprojection_error").real()
    return {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "k1": d[0], "k2": d[1], "p1": d[2],
            "p2": d[3], "k3": d[4], "rms_px": rms}


def main() -> None:
    if not BOARD.is_dir():
        sys.exit(f"{BOARD} is not here")
    rows = [{"run": "OpenCV reference (left)", **reference()}]
    runs = [("left, 13 views", sorted(BOARD.glob("left*.jpg")), CalibrationOptions()),
            ("left, views > 0.8 px dropped", sorted(BOARD.glob("left*.jpg")), CalibrationOptions(max_view_rms_px=0.8)),
            ("right, 13 views", sorted(BOARD.glob("right*.jpg")), CalibrationOptions())]
    for label, images, opts in runs:
        t0 = time.perf_counter()
        profile, stats = calibrate_chessboard(images, options=opts)
        k = profile["intrinsics"]
        rows.append({"run": label, **{n: k[n] for n in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")},
                     "rms_px": stats["rms_px"], "n_used": stats["n_used"], "sigma_fx": stats["sigma"]["fx"],
                     "time_s": time.perf_counter() - t0})
    cols = ["run", "fx", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "rms_px", "n_used", "time_s"]
    print(" | ".join(f"{c:>10}" if c != "run" else f"{c:<30}" for c in cols))
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c)
            if c == "run":
                cells.append(f"{v:<30}")
            elif v is None:
                cells.append(f"{'-':>10}")
            elif isinstance(v, int):
                cells.append(f"{v:>10}")
            else:
                cells.append(f"{v:>10.5g}")
        print(" | ".join(cells))
    out = ROOT / "bench_out" / "calibrate.json"
    atomic_write_json(out, {"rows": rows})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
