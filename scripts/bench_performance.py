#!/usr/bin/env python
"""How fast the workbench answers, old and new code side by side in one run (issue 18's table).

Each figure is the wall time of a fresh process, as a user types it, for the code at ``--base`` (a git
worktree made under the system temp folder, run with PYTHONPATH pointing at it) and for this working tree:

  help         `workbench --help` (median of --repeat runs)
  status       `workbench status INCIDENT` on a run incident (every input hashed; median)
  types        `workbench types` (median)
  run          `workbench run` on a fresh copy of the sample incident (photos there, nothing run), with the
               run time of every stage from out/state.json, the CPU time of the run (user + sys of the
               process and its workers) and the load average before and after; ``--rounds N`` repeats it N
               times, the versions alternating (base, head, base, head, ...), and the versions' outputs are
               compared: solution.json (every number but the timings) and the render stage's pictures
  stitch       `workbench stitch` on a fresh incident holding one real photo set of ../shared/data/stitching,
               against cv2.Stitcher (PANORAMA defaults) in a fresh process (imread to the written JPEG): per set,
               --repeat rounds of cv2, the old and the new code back to back; the ratio of the medians, and
               whether the versions wrote the same panorama.jpg, panorama.json and inputs.json (to the byte)

The same sample incident (``--incident``, default projects/spuyten-duyvil; generate it with scripts/demo.sh or
`workbench synth`) is copied for each version, with its terrain layers. Results: printed, and saved as JSON
(bench_out/performance.json). Run it on an idle machine; it takes a few minutes per version:

    .venv/bin/python scripts/bench_performance.py [--base 9f57319] [--parts help,status,types,run,stitch]
        [--rounds 2] [--head-tree DIR]

``--head-tree`` benchmarks another tree than this working tree as the new code (a snapshot: on a machine where
others edit the working tree while the benchmark runs); ``--base-tree`` another tree than a worktree of ``--base``
as the old code (e.g. a snapshot with only some files put back as they were).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "stitching"
STITCH_SETS = {
    "weir": ("opencv_weir", ["weir_1.jpg", "weir_2.jpg", "weir_3.jpg", "weir_noise.jpg"]),
    "budapest": ("opencv_budapest", [f"budapest{i}.jpg" for i in range(1, 7)]),
    "arches_9518": ("skimage_pano_arches", ["JDW_9518.jpg", "JDW_9519.jpg", "JDW_9520.jpg"]),
    "petra": ("skimage_pano_petra", ["DFM_4209.jpg", "DFM_4210.jpg", "DFM_4211.jpg"]),
}
TARGETS = {"help": 0.5, "status": 1.0, "types": 1.0, "run": 45.0, "stitch_ratio": 1.5}
CV2_STITCH = """
import sys, cv2
imgs = [cv2.imread(p) for p in sys.argv[2:]]
status, pano = cv2.Stitcher_create(cv2.Stitcher_PANORAMA).stitch(imgs)
if status != 0:
    sys.exit(f"cv2.Stitcher status {status}")
cv2.imwrite(sys.argv[1], pano)
"""


NEUTRAL_CWD = Path(tempfile.gettempdir())  # not the repository: `python -c` puts the cwd first on sys.path


def _timed(cmd: list[str], env: dict, cwd: Path | None = None, check: bool = True) -> float:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=env, cwd=cwd or NEUTRAL_CWD, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if check and r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}): {r.stderr[-2000:]}")
    return dt


def _timed_cpu(cmd: list[str], env: dict, check: bool = True) -> tuple[float, float]:
    """(wall s, CPU s: user + sys of the command and the processes it waited for, its workers)."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = _timed(cmd, env, check=check)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return t, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def _median(cmd: list[str], env: dict, repeat: int) -> dict:
    times = [_timed(cmd, env) for _ in range(repeat)]
    return {"median_s": round(statistics.median(times), 3), "min_s": round(min(times), 3),
            "max_s": round(max(times), 3), "n": repeat}


def _copy_incident(src: Path, dst_root: Path) -> Path:
    """A copy of ``src`` (without out/) and of the terrain layers its settings name, at the same relative place."""
    dst = dst_root / "projects" / src.name
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("out"), symlinks=True)
    truth = src / "truth" / "ground_truth.json"
    layers = json.loads(truth.read_text())["layers"] if truth.is_file() else {}
    for rel in layers.values():
        s = (src / rel).resolve().parent
        d = (dst / rel).resolve().parent
        if s.is_dir() and not d.exists():
            shutil.copytree(s, d)
    return dst


def _version(name: str, tree: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    env.pop("OPENBLAS_NUM_THREADS", None)  # each version runs as its own entry point sets up
    return {"name": name, "tree": str(tree), "env": env,
            "cli": [sys.executable, "-c", "import sys, workbench; assert workbench.__file__.startswith(sys.argv[1]); "
                    "from workbench.cli import main; del sys.argv[1]; sys.argv[0] = 'workbench'; main()", str(tree)]}


def _bench_version(v: dict, args, work: Path) -> dict:
    res: dict = {}
    cli, env = v["cli"], v["env"]
    parts = args.parts
    if "help" in parts:
        res["help"] = _median([*cli, "--help"], env, args.repeat)
        print(f"  {v['name']}: help {res['help']['median_s']:.2f} s", flush=True)
    if "types" in parts:
        res["types"] = _median([*cli, "types"], env, args.repeat)
        print(f"  {v['name']}: types {res['types']['median_s']:.2f} s", flush=True)
    if "run" in parts or "status" in parts:
        inc = _run_sample(v, args, work, res)
        if "status" in parts:
            res["status"] = _median([*cli, "status", str(inc)], env, args.repeat)
            print(f"  {v['name']}: status {res['status']['median_s']:.2f} s", flush=True)
    return res


def _stitch_once(v: dict, set_name: str, inc: Path) -> tuple[float, float]:
    """`workbench stitch` on a fresh incident holding the set's photos (made by `workbench init`): its wall and CPU
    time."""
    folder, files = STITCH_SETS[set_name]
    r = subprocess.run([*v["cli"], "init", str(inc), "--lat", "0", "--lon", "0"], env=v["env"], capture_output=True,
                       cwd=NEUTRAL_CWD)
    if r.returncode != 0:
        raise RuntimeError(r.stderr)
    for f in files:
        shutil.copy(DATA / folder / f, inc / "photos" / "panorama" / f)
    return _timed_cpu([*v["cli"], "stitch", str(inc)], v["env"])


def _stitch_rounds(versions: list[dict], work: Path, repeat: int, results: dict) -> None:
    """Per set, ``repeat`` rounds of cv2.Stitcher, then each version's `workbench stitch`, back to back (fresh
    processes, fresh incidents): the median of each, in results[version]["stitch"] and results["cv2"]."""
    results["cv2"] = {}
    for v in versions:
        results[v["name"]]["stitch"] = {}
    for set_name, (folder, files) in STITCH_SETS.items():
        if not all((DATA / folder / f).is_file() for f in files):
            print(f"  stitch {set_name}: photos not in {DATA / folder}; left out", flush=True)
            continue
        times: dict[str, list[float]] = {}
        cpu: dict[str, list[float]] = {}
        loads = [os.getloadavg()[0]]
        for k in range(repeat):
            t, c = _timed_cpu([sys.executable, "-c", CV2_STITCH, str(work / f"cv2_{set_name}.jpg"),
                               *[str(DATA / folder / f) for f in files]], dict(os.environ), check=False)
            times.setdefault("cv2", []).append(t)
            cpu.setdefault("cv2", []).append(c)
            for v in versions:
                inc = work / "stitch" / f"{v['name'].replace(' ', '_')}_{set_name}_{k}"
                t, c = _stitch_once(v, set_name, inc)
                times.setdefault(v["name"], []).append(t)
                cpu.setdefault(v["name"], []).append(c)
            loads.append(os.getloadavg()[0])
        if len(versions) == 2:  # the same outputs to the byte (each version's first round)
            a, b = (work / "stitch" / f"{v['name'].replace(' ', '_')}_{set_name}_0" for v in versions)
            results.setdefault("stitch_same_outputs", {})[set_name] = {
                f: (a / f).read_bytes() == (b / f).read_bytes()
                for f in ("out/stitch/panorama.jpg", "out/stitch/panorama.json", "out/inputs/inputs.json")}
        results["cv2"][set_name] = round(statistics.median(times["cv2"]), 2)
        results.setdefault("cv2_cpu", {})[set_name] = round(statistics.median(cpu["cv2"]), 2)
        for v in versions:
            results[v["name"]]["stitch"][set_name] = {"ours_s": round(statistics.median(times[v["name"]]), 2),
                                                      "runs_s": [round(t, 2) for t in times[v["name"]]],
                                                      "cpu_s": round(statistics.median(cpu[v["name"]]), 2),
                                                      "ratios": [round(t / c, 2) for t, c in zip(times[v["name"]],
                                                                                                 times["cv2"])],
                                                      "load": [round(x, 2) for x in loads]}
        print(f"  stitch {set_name} (medians of {repeat}, load {min(loads):.1f}-{max(loads):.1f}): cv2 "
              f"{results['cv2'][set_name]} s (CPU {results['cv2_cpu'][set_name]} s), "
              + ", ".join(f"{v['name']} {results[v['name']]['stitch'][set_name]['ours_s']} s (CPU "
                          f"{results[v['name']]['stitch'][set_name]['cpu_s']} s; each round / cv2's: "
                          f"{results[v['name']]['stitch'][set_name]['ratios']})" for v in versions)
              + (f"; the same outputs: {results['stitch_same_outputs'][set_name]}" if len(versions) == 2 else ""),
              flush=True)


def _run_sample(v: dict, args, work: Path, res: dict, round_: int = 0) -> Path:
    """`workbench run` on a fresh copy of the sample: res["run"] (the first round) or res["runs"] (each round)."""
    inc = _copy_incident(args.incident, work / f"{v['name']}_{round_}")
    load0 = os.getloadavg()[0]
    t, cpu = _timed_cpu([*v["cli"], "run", str(inc)], v["env"])
    state = json.loads((inc / "out" / "state.json").read_text())
    run = {"wall_s": round(t, 2), "cpu_s": round(cpu, 1), "load": [round(load0, 2), round(os.getloadavg()[0], 2)],
           "stages_s": {k: r.get("duration_s") for k, r in state.items()},
           "all_done": all(r.get("status") == "done" for r in state.values()), "incident": str(inc)}
    run["stages_sum_s"] = round(sum(x or 0.0 for x in run["stages_s"].values()), 2)
    sol = json.loads((inc / "out" / "solve" / "solution.json").read_text())
    run["placed"] = sorted(c["number"] for c in sol["carriages"] if c.get("world_from_carriage"))
    truth = inc / "truth" / "ground_truth.json"
    if truth.is_file():
        run["centre_errors_m"] = _centre_errors(sol, json.loads(truth.read_text()))
    res.setdefault("run", run)
    res.setdefault("runs", []).append(run)
    print(f"  {v['name']}: run {t:.1f} s (CPU {cpu:.1f} s, load {run['load']}), stages {run['stages_sum_s']} s: "
          f"{run['stages_s']}", flush=True)
    return inc


_TIMING_KEYS = ("time_s", "duration_s", "timings_s", "time_by_kind_s", "elapsed_s")


def _numbers(doc, path: str = "") -> dict:
    """Every number of a JSON document by its path, but the timings."""
    out: dict = {}
    if isinstance(doc, dict):
        for k, x in doc.items():
            if k not in _TIMING_KEYS:
                out.update(_numbers(x, f"{path}/{k}"))
    elif isinstance(doc, list):
        for i, x in enumerate(doc):
            out.update(_numbers(x, f"{path}/{i}"))
    else:
        out[path] = doc
    return out


def _compare_outputs(a: Path, b: Path) -> dict:
    """The two incidents' solution.json (every number but the timings) and render pictures compared."""
    import numpy as np
    from PIL import Image

    na = _numbers(json.loads((a / "out" / "solve" / "solution.json").read_text()))
    nb = _numbers(json.loads((b / "out" / "solve" / "solution.json").read_text()))
    differ = sorted(k for k in set(na) | set(nb) if na.get(k) != nb.get(k))
    pictures = sorted(p.name for p in (a / "out" / "render").glob("*.png"))
    changed = {}
    for name in pictures:
        pa = np.asarray(Image.open(a / "out" / "render" / name).convert("RGB")).astype(int)
        pb = np.asarray(Image.open(b / "out" / "render" / name).convert("RGB")).astype(int)
        if pa.shape != pb.shape or not np.array_equal(pa, pb):
            changed[name] = "size" if pa.shape != pb.shape else int(np.count_nonzero(np.any(pa != pb, axis=-1)))
    same_bytes = {rel: (a / "out" / rel).read_bytes() == (b / "out" / rel).read_bytes()
                  for rel in ("correspond/correspondences.json", "render/orbit.gif", "report/report.json",
                              "export/scene.glb", "export/carriages.geojson", "export/scene.city.json")
                  if (a / "out" / rel).is_file() and (b / "out" / rel).is_file()}
    return {"solution_numbers": len(na), "solution_numbers_differing": differ[:50],
            "pictures": len(pictures), "pictures_differing": changed, "identical_files": same_bytes}


def _centre_errors(sol: dict, truth: dict) -> dict:
    import numpy as np

    true_by = {str(c["number"]): c for c in truth.get("carriages", [])}
    out = {}
    for c in sol["carriages"]:
        t = true_by.get(str(c["number"]))
        if c.get("world_from_carriage") is None or t is None or "world_from_carriage" not in t:
            continue
        out[c["number"]] = round(float(np.linalg.norm(np.asarray(c["world_from_carriage"])[:3, 3]
                                                      - np.asarray(t["world_from_carriage"])[:3, 3])), 3)
    return out


YARDSTICK = """
import json, time
import numpy as np, cv2
cv2.setNumThreads(1)
img = cv2.GaussianBlur((np.random.default_rng(0).random((900, 1200)) * 255).astype(np.uint8), (0, 0), 1.5)
t = time.perf_counter()
kp, _ = cv2.SIFT_create().detectAndCompute(img, None)
out = {"sift_s": time.perf_counter() - t, "sift_keypoints": len(kp)}
t, x = time.perf_counter(), 0
for i in range(3_000_000):
    x += i * i
out["python_loop_s"] = time.perf_counter() - t
print(json.dumps(out))
"""


def _yardstick() -> dict:
    """The host's speed on a fixed workload, in a fresh process, so that figures from different machines can be set
    side by side (this project's sessions have run on hosts about twice as fast as each other): SIFT on one thread
    on a seeded 1200 x 900 image (its memory faulted in afresh, as a process's first photo is) and a pure-Python
    loop of 3 million steps; medians of three processes."""
    runs = []
    for _ in range(3):
        r = subprocess.run([sys.executable, "-c", YARDSTICK], capture_output=True, text=True, cwd=NEUTRAL_CWD,
                           env={**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"})
        if r.returncode != 0:
            return {"error": r.stderr.strip()[-500:]}
        runs.append(json.loads(r.stdout))
    return {k: round(statistics.median(r[k] for r in runs), 3) for k in runs[0]}


def _table(results: dict) -> list[str]:
    base, head = results["versions"]
    b, h = results[base], results[head]
    rows = [f"| what | {base} | {head} | target |", "|---|---|---|---|"]
    y = results["machine"].get("yardstick", {})
    if "sift_s" in y:
        rows.append(f"| this host's yardstick: SIFT on a fixed image / a Python loop | {y['sift_s']:.2f} / "
                    f"{y['python_loop_s']:.2f} s | | |")
    for key, label in (("help", "`workbench --help`"), ("status", "`workbench status` (sample, run)"),
                       ("types", "`workbench types`")):
        if key in b:
            rows.append(f"| {label} | {b[key]['median_s']:.2f} s | {h[key]['median_s']:.2f} s | < {TARGETS[key]} s |")
    if "run" in b:
        def each(d: dict, f) -> str:
            return " / ".join(f(r) for r in d["runs"])

        def stages(r: dict) -> str:
            return f"{r['stages_sum_s']:.1f}"

        def wall_cpu(r: dict) -> str:
            return f"{r['wall_s']:.1f}, {r['cpu_s']:.1f}"

        # the command's wall time is the figure a user waits for (stages that run at once overlap in their sum)
        rows.append(f"| `workbench run` (sample), wall, CPU | {each(b, wall_cpu)} s | {each(h, wall_cpu)} s | "
                    f"< {TARGETS['run']:.0f} s (wall) |")
        rows.append(f"| &nbsp; the stages' sum | {each(b, stages)} s | {each(h, stages)} s | |")
        for st in h["run"]["stages_s"]:
            rows.append(f"| &nbsp; {st} | {each(b, lambda r: str(r['stages_s'].get(st)))} s | "
                        f"{each(h, lambda r: str(r['stages_s'].get(st)))} s | |")
    if "stitch" in b and "cv2" in results:
        for set_name, t in results["cv2"].items():
            rows.append(f"| &nbsp; {set_name}: cv2.Stitcher / `workbench stitch` (s, medians) | {t:.2f} / "
                        f"{b['stitch'][set_name]['ours_s']:.2f} | {t:.2f} / {h['stitch'][set_name]['ours_s']:.2f} | |")
            rb, rh = b["stitch"][set_name]["ours_s"] / t, h["stitch"][set_name]["ours_s"] / t
            rows.append(f"| `workbench stitch` / cv2.Stitcher, {set_name} | {rb:.2f} | {rh:.2f} | "
                        f"<= {TARGETS['stitch_ratio']} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", default="9f57319", help="git revision of the old code (default: 9f57319)")
    ap.add_argument("--incident", type=Path, default=ROOT / "projects" / "spuyten-duyvil")
    ap.add_argument("--parts", default="help,status,types,run,stitch")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=1, help="runs of the sample per version, alternating")
    ap.add_argument("--head-tree", type=Path, default=None, help="the new code's tree (default: this one)")
    ap.add_argument("--base-tree", type=Path, default=None,
                    help="the old code's tree, instead of a worktree of --base (named by --base in the table)")
    ap.add_argument("--out", type=Path, default=ROOT / "bench_out" / "performance.json")
    args = ap.parse_args()
    args.parts = set(args.parts.split(","))
    if ({"run", "status"} & args.parts) and not (args.incident / "truth" / "ground_truth.json").is_file():
        sys.exit(f"{args.incident}: no generated sample incident; run scripts/demo.sh (or `workbench synth`) first")
    work = Path(tempfile.mkdtemp(prefix="bench_performance_"))
    base_tree = args.base_tree or work / "base"
    if args.base_tree is None:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-f", str(base_tree), args.base],
                       check=True, capture_output=True)
    try:
        versions = [_version(f"base {args.base}", base_tree), _version("head", args.head_tree or ROOT)]
        results: dict = {"versions": [v["name"] for v in versions], "machine": {"cpus": os.cpu_count(),
                         "load_before": os.getloadavg()}, "date": time.strftime("%Y-%m-%d %H:%M:%S")}
        results["machine"]["yardstick"] = _yardstick()
        print(f"this host's yardstick: {results['machine']['yardstick']}", flush=True)
        for v in versions:
            print(f"{v['name']} ({v['tree']})", flush=True)
            results[v["name"]] = _bench_version(v, args, work)
        if "run" in args.parts:
            for r in range(1, args.rounds):  # more rounds, back to back, the versions alternating
                for v in versions:
                    _run_sample(v, args, work, results[v["name"]], r)
            a, b = (Path(results[v["name"]]["run"]["incident"]) for v in versions)
            results["same_outputs"] = _compare_outputs(a, b)
            print(f"outputs compared: {results['same_outputs']}", flush=True)
        if "stitch" in args.parts and DATA.is_dir():
            _stitch_rounds(versions, work, args.repeat, results)
        results["machine"]["load_after"] = os.getloadavg()
        print("\n".join(["", *_table(results)]))
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2, default=str) + "\n")
        print(f"\nsaved {args.out}")
    finally:
        if args.base_tree is None:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(base_tree)],
                           capture_output=True)
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
