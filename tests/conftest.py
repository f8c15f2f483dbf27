import os

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI runs (workbench.cli.single_threaded_blas)


# --------------------------------------------------------------------------------------------------------------
# A small generated incident, built once per test run and shared by the test files that need photos of a
# synthetic incident with ground truth (tests/test_georef.py, test_stitch.py, test_exif.py). Tests never read
# projects/ (a suite run must not depend on whether `scripts/demo.sh` generated the samples there); tests that
# write into the incident copy it first.
# --------------------------------------------------------------------------------------------------------------
import json as _json  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest as _pytest  # noqa: E402

SMALL_INCIDENT_OPTIONS = dict(scenario="spuyten-duyvil", seed=1, n_cars=4, photo_width=800, photo_height=600,
                              n_panorama=4, n_multiview=8, supersample=1, layers_dir="../../terrain/bronx")


def body_centre_z(res, sim) -> list:
    """The body centres' errors over their sigmas (3 per carriage, east / north / up) of the solve result ``res``
    of the simulated consist ``sim`` (``solve.simulate.SimProblem``), against its truth."""
    import numpy as np

    out = []
    for c, ci, M in zip(res.carriages, sim.carriages, sim.truth):
        truth = M[:3, :3] @ [0.0, 0.0, ci.carriage_type.height_m / 2] + M[:3, 3]
        out.extend((np.asarray(c.body_centre_m) - truth) / np.asarray(c.sigma_body_centre_m))
    return out


def with_solver_lines(text: str, *lines: str) -> str:
    """A project.toml's ``text`` with the TOML ``lines`` (``key = value``) first in its ``[solver]`` table, in
    place of the same keys there (the generator writes one: the couplers' play it drew from), or with that table
    added where there is none."""
    new = "".join(f"{ln}\n" for ln in lines)
    if "\n[solver]\n" not in "\n" + text:
        return text + "\n[solver]\n" + new
    head, rest = text.split("[solver]\n", 1)
    table, sep, tail = rest.partition("\n[")
    keys = {ln.split("=")[0].strip() for ln in lines}
    kept = [ln for ln in table.split("\n") if ln.split("=")[0].strip() not in keys]
    return head + "[solver]\n" + new + "\n".join(kept) + sep + tail


def built_once(tmp_path_factory, name: str, build) -> Path:
    """The folder ``name`` that ``build(folder)`` fills, built once for the whole test run: with pytest-xdist every
    worker is its own session, so the workers share the run's temporary folder (the parent of each worker's), and
    the first to come builds while the others wait on a lock (fcntl), then read what it built. A build that
    failed half-way is started again from an empty folder. Read-only for the tests."""
    import fcntl
    import shutil

    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent  # the run's folder, shared by its workers
    folder, done = base / f"shared-{name}", base / f"shared-{name}.done"
    with open(base / f"shared-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            done.touch()
    return folder


@_pytest.fixture(scope="session")
def small_incident(tmp_path_factory):
    """(root, truth) of a small Spuyten Duyvil incident (4 cars, 4 panorama and 8 multi-view photos of 800x600,
    its DEM and buildings in ``root/../../terrain/bronx``) with synthetic control points; about 40 s, once per
    test run (:func:`built_once`: shared by the pytest-xdist workers).
    Read-only for the tests: copy it (with ``root.parent.parent``) before writing into it."""

    def build(base):
        from workbench.synth.control_points import write_control_points
        from workbench.synth.generate import SynthOptions, generate_incident

        root = base / "projects" / "spuyten-duyvil"
        generate_incident(root, SynthOptions(**SMALL_INCIDENT_OPTIONS))
        write_control_points(root)

    root = built_once(tmp_path_factory, "small_incident", build) / "projects" / "spuyten-duyvil"
    return root, _json.loads((root / "truth" / "ground_truth.json").read_text())


HAND_PICKED_OPTIONS = dict(scenario="spuyten-duyvil", seed=2, n_cars=3, photo_width=480, photo_height=360,
                           n_panorama=3, n_multiview=0, supersample=1, terrain_size_m=200.0)


def hand_picked_incident(tmp_path_factory) -> Path:
    """A small Spuyten Duyvil incident (3 cars, 3 panorama photos of 480x360, on 200 m of terrain) with its true
    cameras (``cameras.json``) and true picks with 1 px of noise (``correspondences.json``, seed 5), the automatic
    finder off, built once per test run (:func:`built_once`) for the files that solve hand-written incidents
    (tests/test_solve_stage.py, test_mesh_type_incident.py). Read-only: copy it before running stages."""

    def build(base):
        from workbench.synth.generate import SynthOptions, generate_incident
        from workbench.synth.handpicks import write_known_cameras, write_true_correspondences

        root = base / "inc"
        generate_incident(root, SynthOptions(**HAND_PICKED_OPTIONS))
        write_known_cameras(root, "panorama")
        write_true_correspondences(root, "panorama", sigma_px=1.0, seed=5)
        toml = root / "project.toml"  # the hand picks only (the tests solve what a user picked by hand)
        assert "[correspond]" not in toml.read_text()
        toml.write_text(toml.read_text() + '\n[correspond]\nfinder = "off"\n')

    return built_once(tmp_path_factory, "hand_picked_incident", build) / "inc"


# --------------------------------------------------------------------------------------------------------------
# The order of the test files. `scripts/test.sh` runs them on one pytest-xdist worker per CPU, a file's tests on one
# worker (`--dist loadfile`), and hands out the files in the collection's order (`--no-loadscope-reorder`; xdist's
# own order is by number of tests, which put the one-test end-to-end file, about 150 s, last: the other worker
# waited for it). Longest first, so the workers finish together (greedy scheduling, longest processing time
# first). The seconds are what each file took in a full run on the 2-core machine, idle but for the suite
# (session 27, `scripts/test.sh --junitxml`, a file's test times summed: 890 s in all, 467 s of wall; after the pose
# search's faster correlation; docs/performance.md); files not listed (each under 13 s) follow in their usual
# order. Re-measure when a file's cost changes much: a wrong order costs time, never a test.
# --------------------------------------------------------------------------------------------------------------
SLOW_FILES_SECONDS = {
    "test_cli_end_to_end.py": 108, "test_correspond.py": 106, "test_georef.py": 78, "test_sfm.py": 55,
    "test_report.py": 49, "test_solve.py": 47, "test_picker.py": 40, "test_cli.py": 36, "test_synth.py": 34,
    "test_picker_map.py": 28, "test_georef_gps.py": 26, "test_stitch.py": 24, "test_viewer.py": 21,
    "test_relative.py": 21, "test_export.py": 17, "test_multiview_uncertainty.py": 16,
    "test_georef_covariance.py": 16, "test_uncertainty_model.py": 15, "test_georef_track.py": 14,
    "test_solve_stage.py": 13,
}


def pytest_collection_modifyitems(items):
    """The slow files' tests first, longest file first (a stable sort: each file's tests keep their order)."""
    items.sort(key=lambda item: -SLOW_FILES_SECONDS.get(item.path.name, 0))
