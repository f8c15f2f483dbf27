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
other photo's features are done, and waited for by the worker that reaches it (:func:`wait_for`): while the workers
compute the other photos' features (and the parent the cars' references) the niced process gets no core; the
worker that reaches it later leaves it its core. Where other work holds the cores (a loaded machine), the process
may get none for minutes: a worker that sees it get less than :data:`STARVED_SHARE` of a core over
:data:`STARVED_WINDOW_S` computes the photo itself, and the stage's end ends the process (:func:`finish`). The
others are computed by the stage as before. Entries are written atomically, and the features are the same arrays
whichever process computes them (``match.photo_features``, OpenCV single-threaded in both).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
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
    own name for it; another name: nothing to wait for), and while it gets a core: one that got less than
    :data:`STARVED_SHARE` of a core over :data:`STARVED_WINDOW_S` is left (the worker computes the photo)."""
    t0 = time.monotonic()
    if not computing(name, entry):
        return
    pid = _STATE["proc"].pid
    w0, c0 = t0, _cpu_s(pid)
    while computing(name, entry) and time.monotonic() - t0 < WAIT_MAX_S:
        time.sleep(0.02)
        now = time.monotonic()
        if now - w0 >= STARVED_WINDOW_S:
            c1 = _cpu_s(pid)
            if c0 is not None and c1 is not None and c1 - c0 < STARVED_SHARE * (now - w0):
                log.info("correspond: the prefetch computing %s got %.0f %% of a core in the last %.1f s (other work "
                         "holds the cores): computed here after waiting %.1f s", name, 100 * (c1 - c0) / (now - w0),
                         now - w0, now - t0)
                return
            w0, c0 = now, c1
    log.info("correspond: waited %.1f s for the prefetch computing %s", time.monotonic() - t0, name)


WAIT_MAX_S = 300.0  # a prefetch that has not finished a photo by then: the worker computes it itself
# A worker reaches the photo the prefetch is computing only once every other photo's features are done and the
# parent's references built (``parallel.map_photos(hold=...)``): its core is then the prefetch's, unless other work
# holds the cores (a loaded machine, where a process at niceness 19 may get none for minutes). The worker then
# computes the photo itself.
STARVED_WINDOW_S = 2.0
STARVED_SHARE = 0.25


def _cpu_s(pid: int) -> float | None:
    """Process ``pid``'s CPU time so far (user + system, s), from ``/proc``; None where it cannot be read."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


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
    """The stage ends: the prefetch process is reaped. The stage has every photo's features then, so a process still
    computing one (a worker left it, :func:`wait_for`) is ended, not waited for (its entry is written atomically: a
    temp file it leaves is deleted with the entries the stage did not use)."""
    proc = _STATE.get("proc")
    if proc is not None:
        if BUSY in _STATE["status"][:] and proc.is_alive():
            log.info("correspond: the prefetch still computing a photo the stage computed itself is ended")
            # SIGKILL, not SIGTERM: the fork carries pycolmap's (glog's) failure handler, which on SIGTERM writes a
            # symbolised stack trace first, seconds on a loaded machine; the entry is written atomically
            proc.kill()
        proc.join(timeout=60)
    _STATE.clear()


__all__ = ["start", "stop", "computing", "wait_for", "finish"]
