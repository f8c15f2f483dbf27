#!/usr/bin/env python
"""Peak memory and time of the workbench on large photos (issue 20: phones take 100-200 MP photos).

Real photo sets from ../shared/data/stitching, enlarged (bicubic) to ``--megapixels`` each, go through:
  decode     the inputs stage's check of one photo (workbench.pipeline: Pillow decode)
  stitch     workbench.stitch.stitch_photos with ``max_output_megapix`` = each of ``--caps``
  features   the correspond stage's per-photo step (undistort, SIFT at most ``max_photo_side_px``) on one photo
each in its own subprocess, timed from the call, with the peak resident memory of that process
(getrusage). Prints a table and writes bench_out/large_photos.json. On a shared machine run it niced:
    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python scripts/bench_large_photos.py
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "stitching"
SETS = {"weir": ("opencv_weir", ["weir_1.jpg", "weir_2.jpg", "weir_3.jpg"]),
        "budapest": ("opencv_budapest", [f"budapest{i}.jpg" for i in range(1, 7)])}

CHILD = r"""
import json, resource, sys, time
from pathlib import Path
kind, arg, photos = sys.argv[1], sys.argv[2], [Path(p) for p in sys.argv[3:]]
t = time.perf_counter()
out = {}
if kind == "decode":
    from PIL import Image
    with Image.open(photos[0]) as im:
        im.load()
        out["size"] = list(im.size)
elif kind == "stitch":
    from workbench.stitch.options import StitchOptions
    from workbench.stitch.stitcher import stitch_photos
    res = stitch_photos(photos, options=StitchOptions(max_output_megapix=float(arg)))
    out["panorama_px"] = None if res.image is None else list(res.image.shape[:2])
    out["kept"] = len(photos) - len(res.rejected)
elif kind == "features":
    import numpy as np
    from PIL import Image
    from workbench.core.camera import CameraIntrinsics
    from workbench.correspond.match import MatchOptions, photo_features
    with Image.open(photos[0]) as im:
        rgb = np.asarray(im.convert("RGB"))
    h, w = rgb.shape[:2]
    K = CameraIntrinsics(width=w, height=h, fx=1.2 * w, fy=1.2 * w, cx=(w - 1) / 2, cy=(h - 1) / 2, k1=-0.05)
    f = photo_features(photos[0].name, rgb, K, MatchOptions())
    out["keypoints"] = int(len(f.keypoints))
out["time_s"] = round(time.perf_counter() - t, 2)
out["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
print("RESULT " + json.dumps(out))
"""


def enlarge(name: str, megapixels: float, work: Path) -> list[Path]:
    from PIL import Image

    folder, files = SETS[name]
    out = []
    for f in files:
        dst = work / f"{name}_{megapixels:g}mp_{f}"
        if not dst.is_file():
            with Image.open(DATA / folder / f) as im:
                s = (megapixels * 1e6 / (im.size[0] * im.size[1])) ** 0.5
                im.convert("RGB").resize((round(im.size[0] * s), round(im.size[1] * s)),
                                         Image.Resampling.BICUBIC).save(dst, quality=90)
        out.append(dst)
    return out


def run(kind: str, arg: str, photos: list[Path]) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    p = subprocess.run([sys.executable, "-c", CHILD, kind, arg, *map(str, photos)], capture_output=True, text=True,
                       env=env, cwd=ROOT)
    line = next((ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")), None)
    if p.returncode != 0 or line is None:
        return {"error": (p.stderr or p.stdout)[-400:]}
    return json.loads(line[len("RESULT "):])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", default="weir,budapest")
    ap.add_argument("--megapixels", type=float, default=81.0, help="size of each enlarged photo")
    ap.add_argument("--caps", default="400,100,30", help="max_output_megapix values for the stitch runs")
    ap.add_argument("--out", type=Path, default=ROOT / "bench_out" / "large_photos.json")
    a = ap.parse_args()
    work = ROOT / "bench_out" / "large_photos"
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    print(f"{'set':10s} {'step':22s} {'time s':>7s} {'peak MB':>8s}  detail")
    for name in a.sets.split(","):
        photos = enlarge(name, a.megapixels, work)
        jobs = [("decode", "", photos[:1]), ("features", "", photos[:1])]
        jobs += [("stitch", cap, photos) for cap in a.caps.split(",")]
        for kind, arg, ph in jobs:
            t0 = time.perf_counter()
            r = run(kind, arg, ph)
            r.update(set=name, step=kind + (f" cap {arg} MP" if arg else ""), n_photos=len(ph),
                     photo_megapixels=a.megapixels, wall_s=round(time.perf_counter() - t0, 1))
            rows.append(r)
            detail = r.get("error") or {k: v for k, v in r.items() if k in ("panorama_px", "kept", "keypoints", "size")}
            print(f"{name:10s} {r['step']:22s} {r.get('time_s', float('nan')):7.1f} "
                  f"{r.get('peak_rss_mb', float('nan')):8.0f}  {detail}", flush=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"rows": rows, "cpu_count": os.cpu_count(),
                                 "parent_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024},
                                indent=1))
    print(f"wrote {a.out}")
    return 0 if not any("error" in r for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
