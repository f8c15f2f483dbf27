"""The correspond stage's photo features computed ahead of the stage, in a ``workbench run``.

The stages before it (inputs, terrain, stitch, georef) leave a core free most of the time, and SIFT on the
upsampled photos is a third of the stage's CPU. When the run begins (``StageSpec.prefetch``:
``stage.prefetch_features``), :func:`start` forks one process that computes each photo's features into the stage's
cache (``out/correspond/cache/``, ``cache.py``), under the name the stage's first task of the photo reads: the
photo's digest, its intrinsics as known when the run begins (the incident's own cameras, else the last georef's,
else the camera profile, else EXIF) and the options. Where georef then gives the photo other intrinsics, the names
differ and the entry is not used (it is pruned at the end of the stage).

The process runs at the lowest priority (:data:`NICE`): it takes the cores the run's own stages leave idle, not
theirs. When the stage starts it stops the process from taking another photo (:func:`stop`); a photo the process is
computing then is held back (:func:`computing`, ``stage._match_photos``) until the process has written it or every
other photo's work is queued, and waited for by the worker that reaches it (:func:`wait_for`): while the workers
compute the other photos the niced process gets no core, and at the end of the queue the waiting worker leaves it
its core. The others are computed by the stage as before. Entries are written atomically, and the features are the same arrays whichever process
computes them (``match.photo_features``, OpenCV single-threaded in both).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import time
from pathlib import Path
from typing import Callable

log = logging.getLogger(__name__)

_STATE: dict = {}  # the prefetch of this process's run: "files" (photo name -> cache entry), "status", "stop", "proc"
PENDING, BUSY, DONE = 0, 1, 2
NICE = 19  # the process's niceness (the run's own processes come first; an idle core is still all its own)


def start(photos: list[Path], files: dict[str, Path], compute: Callable[[Path], None]) -> None:
    """Fork the process that runs ``compute(photo)`` (the photo's features into its entry ``files[photo.name]``)
    for each photo whose entry is not there yet, in order (see the module); nothing where there is no ``fork``."""
    if "fork" not in mp.get_all_start_methods() or not photos:
        return
    import cv2

    ctx = mp.get_context("fork")
    status = ctx.Array("b", [DONE if files[p.name].is_file() else PENDING for p in photos])  # its lock guards stop
    stop_flag = ctx.Value("b", 0, lock=False)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # in the child, as in the stage's workers (set in a forked child it can hang)
    try:
        proc = ctx.Process(target=_work, args=(photos, compute, status, stop_flag), name="correspond prefetch",
                           daemon=True)
        proc.start()
    finally:
        cv2.setNumThreads(threads)
    _STATE.clear()
    _STATE.update(files=dict(files), names=[p.name for p in photos], status=status, stop=stop_flag, proc=proc)
    log.info("correspond: the photos' features started ahead of the stage (process %d)", proc.pid)


def _work(photos: list[Path], compute: Callable[[Path], None], status, stop_flag) -> None:
    import os

    try:  # the core the stages before leave free, not theirs: under load they were slowed by it (terrain 2.5 -> 6 s)
        os.nice(NICE)
    except (AttributeError, OSError):
        pass
    for i, p in enumerate(photos):
        with status.get_lock():
            if stop_flag.value or status[i] != PENDING:
                continue
            status[i] = BUSY
        try:
            compute(p)
        except Exception as exc:  # noqa: BLE001 - the stage computes it, and reports what fails
            log.debug("correspond prefetch: %s: %s", p.name, exc)
        finally:
            status[i] = DONE


def stop() -> dict:
    """The stage starts: the prefetch takes no other photo. Returns what it had done (for the statistics)."""
    if not _STATE:
        return {}
    status = _STATE["status"]
    with status.get_lock():
        _STATE["stop"].value = 1
        states = list(status[:])
    done = [n for n, s in zip(_STATE["names"], states) if s == DONE]
    busy = [n for n, s in zip(_STATE["names"], states) if s == BUSY]
    log.info("correspond: features computed ahead of the stage: %s; being computed: %s", done, busy)
    return {"done": done, "busy": busy}


def computing(name: str, entry: Path) -> bool:
    """Whether the prefetch is computing the photo ``name``'s features into ``entry`` now (the stage's own name for
    it; another name: False)."""
    if not _STATE or _STATE["files"].get(name) != entry:
        return False
    return _STATE["status"][_STATE["names"].index(name)] == BUSY and _alive(_STATE["proc"].pid)


def wait_for(name: str, entry: Path) -> None:
    """In a worker: wait while the prefetch computes the photo ``name``'s features into ``entry`` (the stage's
    own name for it; another name: nothing to wait for)."""
    t0 = time.monotonic()
    while computing(name, entry) and time.monotonic() - t0 < WAIT_MAX_S:
        time.sleep(0.02)


WAIT_MAX_S = 300.0  # a prefetch that has not finished a photo by then: the worker computes it itself


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (not ended, not a zombie); from any process, not only its parent."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False
    except IndexError:
        return True


def finish() -> None:
    """The stage ends: the prefetch process is reaped."""
    proc = _STATE.get("proc")
    if proc is not None:
        proc.join(timeout=60)
    _STATE.clear()


__all__ = ["start", "stop", "computing", "wait_for", "finish"]
