"""Independent pieces of one photo's work on two threads, results in their order.

The photos of a set are matched on worker processes (``parallel.py``), one photo per task; the last photo's
pose search then often runs alone while the other core has nothing left to do. Its heavy calls (OpenCV's
template matching, ECC, RANSAC; NumPy's matrix products) release the interpreter lock, so the independent
pieces of a photo's work (each face reference's detection, each roll class of the coarse pose search, each
seed's refinement, each candidate's verification) run on two threads. Each piece is computed as alone and the
results are used in their order: the output does not depend on the threads. In a worker process the threads
are used only once no photo is left for the other workers (``use_threads_when``): while every worker has a photo,
a second thread would only share its process's core, at some cost.
"""

from __future__ import annotations

import os
import threading
from typing import Callable, Iterable, TypeVar

T = TypeVar("T")
R = TypeVar("R")

THREADS = 2  # at most this many threads per map (and no more than the CPUs this process may use)
_local = threading.local()  # marks the pool's threads: a map inside a piece runs in that thread
_gate: Callable[[], bool] | None = None  # set in a worker process: whether a core is free for a second thread


def use_threads_when(gate: Callable[[], bool] | None) -> None:
    """In a worker of ``parallel.map_photos``: maps use threads only while ``gate()`` says a core is free (no other
    photo left for the other workers); None: always (one process)."""
    global _gate
    _gate = gate


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def ordered_map(fn: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """``[fn(x) for x in items]``, on up to ``THREADS`` threads; in this thread where there is one item, one CPU,
    or where this is already a piece of another map (no nested pools)."""
    items = list(items)
    n = min(THREADS, _cpus(), len(items))
    if n <= 1 or getattr(_local, "inside", False) or (_gate is not None and not _gate()):
        return [fn(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor

    def piece(x: T) -> R:
        _local.inside = True
        try:
            return fn(x)
        finally:
            _local.inside = False

    with ThreadPoolExecutor(max_workers=n) as pool:
        return list(pool.map(piece, items))


__all__ = ["ordered_map", "use_threads_when", "THREADS"]
