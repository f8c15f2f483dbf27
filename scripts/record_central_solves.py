"""Record every ``solve_central`` result of a test run, and compare two recordings to the bit (docs/performance.md,
twelfth pass): the check that a change to the central fit's start or refinement leaves its results as they were.

As a pytest plugin, in the tree under test (its ``workbench`` is imported):

    cd TREE && PYTHONPATH=/path/to/scripts RECORD_CENTRAL_OUT=/tmp/old.pkl .venv/bin/python -m pytest -q \\
        -p no:xdist -p record_central_solves tests/test_georef_covariance.py tests/test_georef.py ...

Then ``python scripts/record_central_solves.py /tmp/old.pkl /tmp/new.pkl`` lists the calls whose results differ
(rotation, centre, ``repr`` of the stats and residuals; an error's type and message) and the CPU spent inside
``solve_central`` in each run. Error messages that name pytest's temporary folders differ between runs by that
path alone.
"""

from __future__ import annotations

import atexit
import importlib
import os
import pickle
import sys
import time

_records: list[tuple] = []


def pytest_configure(config) -> None:  # noqa: ARG001 (the pytest hook's signature)
    central = importlib.import_module("workbench.georef.central")
    solve = central.solve_central

    def recorded(*args, **kwargs):
        t = time.process_time()
        try:
            res = solve(*args, **kwargs)
        except Exception as exc:
            _records.append(("error", type(exc).__name__, str(exc), time.process_time() - t))
            raise
        _records.append(("ok", res.rig_from_world.copy(), res.centre_enu.copy(), repr(res.stats),
                         repr(res.residuals), time.process_time() - t))
        return res

    central.solve_central = recorded
    for name in ("workbench.georef.route_central", "workbench.georef.resection"):  # imported it by name
        importlib.import_module(name).solve_central = recorded

    def dump() -> None:
        with open(os.environ["RECORD_CENTRAL_OUT"], "wb") as f:
            pickle.dump(_records, f)

    atexit.register(dump)


def compare(old_path: str, new_path: str) -> int:
    """Print the differing calls of two recordings; 0 when every result is the same."""
    import numpy as np

    with open(old_path, "rb") as f:
        old = pickle.load(f)
    with open(new_path, "rb") as f:
        new = pickle.load(f)
    differ = []
    for k, (a, b) in enumerate(zip(old, new)):
        if a[0] != b[0]:
            differ.append(k)
        elif a[0] == "ok" and not (np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2]) and a[3:5] == b[3:5]):
            differ.append(k)
        elif a[0] == "error" and a[1:3] != b[1:3]:
            differ.append(k)
    print(f"{len(old)} and {len(new)} calls; {len(differ)} differ: {differ[:20]}")
    for k in differ[:5]:
        print(k, old[k][:3] if old[k][0] == "error" else "ok", "|", new[k][:3] if new[k][0] == "error" else "ok")
    print("CPU inside solve_central: %.1f s, %.1f s" % (sum(r[-1] for r in old), sum(r[-1] for r in new)))
    return int(bool(differ) or len(old) != len(new))


if __name__ == "__main__":
    sys.exit(compare(sys.argv[1], sys.argv[2]))
