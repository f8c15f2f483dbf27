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

import pytest as _pytest  # noqa: E402

SMALL_INCIDENT_OPTIONS = dict(scenario="spuyten-duyvil", seed=1, n_cars=4, photo_width=800, photo_height=600,
                              n_panorama=4, n_multiview=8, supersample=1, layers_dir="../../terrain/bronx")


@_pytest.fixture(scope="session")
def small_incident(tmp_path_factory):
    """(root, truth) of a small Spuyten Duyvil incident (4 cars, 4 panorama and 8 multi-view photos of 800x600,
    its DEM and buildings in ``root/../../terrain/bronx``) with synthetic control points; about 40 s, once.
    Read-only for the tests: copy it (with ``root.parent.parent``) before writing into it."""
    from workbench.synth.control_points import write_control_points
    from workbench.synth.generate import SynthOptions, generate_incident

    base = tmp_path_factory.mktemp("small_incident")
    root = base / "projects" / "spuyten-duyvil"
    generate_incident(root, SynthOptions(**SMALL_INCIDENT_OPTIONS))
    write_control_points(root)
    return root, _json.loads((root / "truth" / "ground_truth.json").read_text())
