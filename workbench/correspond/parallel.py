"""The photos of a set matched in parallel: one task per photo, on worker processes.

Each photo's work (SIFT features, the faces of every car, the chain/terrain pose search, the marked points) is
independent of the other photos': only the panorama carry (``transfer.carry``) needs every photo's features,
and the stage does it in the parent (the pairs' homographies as soon as both photos of a pair are done). The
work is mostly Python and NumPy between OpenCV calls, so threads would share one interpreter lock; the photos
go to ``fork``-ed worker processes instead (``concurrent.futures``: a worker that dies fails the stage instead
of leaving it waiting), which inherit the references, the carriage types and the terrain without copying
them (the parent builds them once). Results come back in the photos' order, so the output does not depend on
which worker finished first.

OpenCV's own thread pool: each worker runs OpenCV single-threaded (the photos are the parallel work; two
levels of threads on two cores only contend). ``cv2.setNumThreads(1)`` is set in the parent before the
fork and restored after: set in a forked child whose parent had already used OpenCV's pthreads pool, it
hangs (OpenCV 4.14, pthreads backend).

Progress: every worker reports each step of its photo (features, cars found, pose search, done) through a
queue; the parent passes them on to the stage's ``progress`` while it waits, so a long set is never silent.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)

STEPS = ("features", "cars", "search", "done")  # the steps a photo reports, in order


@dataclass
class PhotoResult:
    """What the stage keeps of one photo: its points, its statistics and (for the panorama carry) its
    features without the image."""

    name: str
    points: list  # assign.PointObservation
    stats: dict
    keypoints: np.ndarray | None = None
    descriptors: np.ndarray | None = None


def _available_memory() -> int | None:
    """MemAvailable of /proc/meminfo in bytes (None where there is none)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def default_workers(bytes_per_worker: float = 0.0) -> int:
    """Worker processes for the photos: the CPUs this process may run on, and no more than 60 % of the
    available memory holds at ``bytes_per_worker`` each (SIFT on an upsampled photo: about 3 GB at 4000 x 3000)."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        n = os.cpu_count() or 1
    avail = _available_memory()
    if bytes_per_worker > 0 and avail is not None:
        n = min(n, int(0.6 * avail // bytes_per_worker))
    return max(1, n)


_JOB: dict = {}  # the job of the current map (set before the fork: the workers inherit it)


def _run_one(index: int, phase: int = 2, token=None):
    job = _JOB
    q = job.get("queue")

    def note(step: str, message: str = "") -> None:
        if q is not None:
            q.put((index, step, message))
        elif job.get("note") is not None:
            job["note"](index, step, message)

    left = job.get("left")
    if left is not None:  # a worker: a second thread only while no other photo is left for the other workers
        from .threads import use_threads_when

        use_threads_when(lambda: left.value < job["workers"])
    item = job["items"][index]
    if job.get("first") is None:
        return job["fn"](item, note)
    if phase == 1:
        return job["first"](item, note)
    return job["fn"](item, note, token)


def _map_here(fn: Callable, items: list, progress: Callable, on_result: Callable | None, first: Callable | None,
              on_first: Callable | None, before_second: Callable | None, order: list[int]) -> list:
    """:func:`map_photos` in this process, the items in ``order``, the results in the items' order."""
    _JOB.clear()
    _JOB.update(fn=fn, items=items, note=progress, first=first)
    try:
        if before_second is not None:
            before_second()
        out: dict[int, object] = {}
        for i in order:
            token = _run_one(i, 1) if first is not None else None
            if first is not None and on_first is not None:
                on_first(i, token)
            out[i] = _run_one(i, 2, token)
            if on_result is not None:
                on_result(i, out[i])
        return [out[i] for i in range(len(items))]
    finally:
        _JOB.clear()


class _ParentWork:
    """``map_photos``' ``before_second``, the parent's own work, on a thread of its own: meanwhile the map's thread
    hands out the held items as they are released (a photo computed by the prefetch, or all of them where it gets
    no core); second tasks wait for it (:meth:`done`). Its exception is raised in the map's thread."""

    def __init__(self) -> None:
        self._thread: threading.Thread | None = None
        self._failed: list[BaseException] = []

    def start(self, fn: Callable[[], None]) -> None:
        def run() -> None:
            try:
                fn()
            except BaseException as exc:  # noqa: BLE001 - raised in the map's thread (done, join)
                self._failed.append(exc)

        self._thread = threading.Thread(target=run, name="map_photos parent work")
        self._thread.start()

    def done(self) -> bool:
        """Whether the work is done (or there is none); its exception, if it raised one."""
        if self._thread is not None and self._thread.is_alive():
            return False
        if self._failed:
            raise self._failed[0]
        return True

    def join(self, raise_failure: bool = True) -> None:
        if self._thread is not None:
            self._thread.join()
        if raise_failure:
            self.done()


def map_photos(fn: Callable, items: list, workers: int, progress: Callable[[int, str, str], None],
               on_result: Callable[[int, object], None] | None = None, first: Callable | None = None,
               on_first: Callable[[int, object], None] | None = None,
               before_second: Callable[[], None] | None = None, hold: Callable[[int, bool], bool] | None = None
               ) -> list:
    """``[fn(item, note) for item in items]``, on up to ``workers`` forked processes (in order).

    ``fn(item, note)`` does one photo and calls ``note(step, message)`` at each of its steps; the parent calls
    ``progress(index, step, message)`` for each, and ``on_result(index, result)`` as each item finishes (in
    any order; both in the parent's thread, while the others run). With ``first``, every item is done in two
    tasks: ``token = first(item, note)`` (the photo's features, written where the second task reads them),
    all of them queued first, then ``fn(item, note, token)``, queued as its first task finishes: the workers
    share the first, even tasks, and the uneven second ones start as early as they can (the last photo's
    pose search alone on one core is the imbalance left). With one worker, one item, or no ``fork`` on this
    platform, the items run here, one after the other. ``on_first(index, token)``: called in the parent as each
    item's first task finishes (any order). ``before_second()``: work of the parent's own, done once the workers
    are forked and the first tasks queued, on a thread of its own (held items are handed out meanwhile), before
    any second task is queued (what the second tasks need and the workers, forked before it, read from files).
    Second tasks are queued in the order their first tasks finished.
    ``hold(index, idle)``: true for an item to hold back (a photo whose features another process computes:
    ``prefetch.py``); ``idle``: a worker has nothing to do. Asked for every item when the map starts, such an
    item's first task is queued as soon as ``hold`` turns false for it (the parent asks while it waits, every
    0.2 s at most); while an item is held, second tasks are queued only while a worker is free (and one more, so
    that a worker finishing while the parent runs a callback finds one), so the held one goes ahead of those not
    queued yet. Without ``first``, a held item's task is queued last; one process takes them last. The results
    are in the items' order whatever the order of the tasks. A worker that dies (killed, out of memory) fails the
    map with a RuntimeError instead of leaving it waiting.
    """
    import cv2

    if before_second is not None and first is None:
        raise ValueError("before_second needs first tasks")
    held = [i for i in range(len(items)) if hold is not None and hold(i, False)]
    n = min(max(1, int(workers)), len(items))
    if n <= 1 or "fork" not in mp.get_all_start_methods():
        return _map_here(fn, items, progress, on_result, first, on_first, before_second,
                         [i for i in range(len(items)) if i not in held] + held)
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    ctx = mp.get_context("fork")
    q = ctx.SimpleQueue()
    left = ctx.Value("i", len(items), lock=False)  # the items not finished (the workers read it)
    _JOB.clear()
    _JOB.update(fn=fn, items=items, queue=q, first=first, left=left, workers=n)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # in the workers (set here: in a forked child it hangs)
    ex = ProcessPoolExecutor(max_workers=n, mp_context=ctx)
    parent = _ParentWork()
    try:
        phase0 = 1 if first is not None else 2
        ex.submit(int).result()  # the workers forked now, before the parent uses OpenCV's threads (below)
        futures = {ex.submit(_run_one, i, phase0): (i, phase0) for i in range(len(items)) if i not in held}
        if before_second is not None:  # with the parent's own OpenCV threads
            cv2.setNumThreads(threads)
            parent.start(before_second)
        results: dict[int, object] = {}
        ready: list[tuple[int, object]] = []  # (item, token): first task done, second not queued yet
        pending = set(futures)

        def submit(i: int, phase: int, *args) -> None:
            g = ex.submit(_run_one, i, phase, *args)
            futures[g] = (i, phase)
            pending.add(g)

        def dispatch() -> None:
            # a held item as soon as it need not be held, ahead of the second tasks not queued yet (while an item is
            # held, they are queued only while a worker is free, and one more)
            for i in [i for i in held if not hold(i, len(pending) < n)]:
                held.remove(i)
                submit(i, phase0)
            while ready and parent.done() and (not held or len(pending) <= n):
                i, token = ready.pop(0)
                submit(i, 2, token)

        while pending or held or ready:
            dispatch()
            if not pending:  # every item left is held, or waits for the parent's work: asked again shortly
                time.sleep(0.02)
                continue
            done, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
            while not q.empty():
                progress(*q.get())
            finished = sorted(done, key=futures.get)
            for f in finished:
                i, phase = futures[f]
                if phase == 1:  # its second task: queued by dispatch
                    ready.append((i, f.result()))
                else:
                    results[i] = f.result()  # re-raises a worker's exception here
            left.value = len(items) - len(results)
            dispatch()  # before the callbacks (the panorama's pairs): a worker may be free
            for f in finished:
                i, phase = futures[f]
                if phase == 1 and on_first is not None:
                    on_first(i, f.result())
                elif phase == 2 and on_result is not None:
                    on_result(i, results[i])
        parent.join()  # (its failure raised here where no second task was left to wait for it)
        while not q.empty():
            progress(*q.get())
        ex.shutdown(wait=True)
        return [results[i] for i in range(len(items))]
    except BrokenProcessPool as exc:
        raise RuntimeError(f"a worker process matching the photos died ({exc}); out of memory? Set "
                           f"MatchOptions.workers lower") from None
    finally:
        ex.shutdown(wait=False, cancel_futures=True)
        parent.join(raise_failure=False)
        cv2.setNumThreads(threads)
        _JOB.clear()


__all__ = ["PhotoResult", "map_photos", "default_workers", "STEPS"]
