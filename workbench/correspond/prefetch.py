"""The correspond stage's photo features computed ahead of the stage, in a ``workbench run``, by one process.

The stages before it (inputs, terrain, stitch, georef) leave a core free most of the time, and SIFT on the
upsampled photos is a third of the stage's CPU. When the run begins (``StageSpec.prefetch``:
``stage.prefetch_features``), :func:`start` forks one process that computes each photo's features into the stage's
cache (``out/correspond/cache/``, ``cache.py``), under the name the stage's first task of the photo reads: the
photo's digest, its intrinsics as known when the run begins (the incident's own cameras, else the last georef's,
else the camera profile, else EXIF) and the options. Where georef then gives the photo other intrinsics, the names
differ and the entry is not used (it is pruned at the end of the stage).

When the stage starts it takes the process on (:func:`adopt`): where the stage reads the photos under the names the
process writes, the process goes on with every photo it has not done, in order, and the stage's workers match each
photo once its entry is there (``stage._match_photos`` holds a photo back while the process owns it: :func:`owns`).
One process computes every photo's features: SIFT on a 4000 x 3000 photo allocates about 3 GB, which a process
keeps for its next photo (``cli._freed_memory_kept``), while every other process computing one faults those pages
in and zeroes them afresh, several at once on two cores: 12-19 s of system time on the sample incident when the
stage's two workers and this process each computed some (docs/performance.md, session 28). Elsewhere the stage
stops the process from taking another photo (:func:`stop`), and a photo it is computing then is waited for.

The process runs at the lowest priority (:data:`NICE`): it takes the cores the run's own stages leave idle, not
theirs, so while the stage's workers match photos it waits, and a worker left without a photo leaves its core to it.
Where other work holds the cores (a loaded machine), the process may get none for minutes: where it gets less than
:data:`STARVED_SHARE` of a core over :data:`STARVED_WINDOW_S` while a worker is idle, the stage takes its photos back
(:func:`owns`; a worker waiting for the photo it is computing does the same in :func:`wait_for`), and the stage's end
ends the process (:func:`finish`). Entries are written atomically, and the features are the same arrays whichever
process computes them (``match.photo_features``, OpenCV single-threaded in both).
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


def start(photos: list[Path], files: dict[str, Path], compute: Callable[[Path], None], *, ahead: bool = True
          ) -> None:
    """Fork the process that runs ``compute(photo)`` (the photo's features into its entry ``files[photo.name]``)
    for each photo whose entry is not there yet, in order (see the module); nothing where there is no ``fork``.
    ``ahead``: started when the run begins (else by the stage itself, for the same reason: one process computing
    every photo's features, where no run started one whose entries are the stage's)."""
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
    log.info("correspond: the photos' features started %s (process %d)",
             "ahead of the stage" if ahead else "in one process", proc.pid)


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
    """The stage starts without taking the process on (:func:`adopt`): the prefetch takes no other photo. Returns
    what it had done (for the statistics)."""
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


def adopt(files: dict[str, Path]) -> list[str]:
    """The stage starts, reading each photo's features from ``files`` (photo name -> entry). Where those are the
    entries the process writes (the intrinsics it used are the stage's), the process goes on with every photo it
    has not done: returns their names (the photos it owns, :func:`owns`). Else it is stopped (:func:`stop`) and
    none are its (a photo it is computing is still waited for: :func:`wait_for`)."""
    if not _STATE:
        return []
    if any(files.get(n) != e for n, e in _STATE["files"].items()) or not _alive(_STATE["proc"].pid):
        stop()
        return []
    status = _STATE["status"]
    with status.get_lock():
        states = list(status[:])
        stopped = bool(_STATE["stop"].value)
    owned = [n for n, s in zip(_STATE["names"], states) if s == BUSY or (s == PENDING and not stopped)]
    log.info("correspond: features computed ahead of the stage: %s; the prefetch computes the others: %s",
             [n for n, s in zip(_STATE["names"], states) if s == DONE], owned)
    _STATE["watch"] = None  # (monotonic time, the process's CPU s) where a window of idle waiting began
    _STATE["owned"] = frozenset(owned)
    return owned


def took(name: str) -> bool:
    """Whether the process took the photo ``name`` on when the stage started (:func:`adopt`; in the stage's
    workers, forked after it): for the stage's progress, which says where a photo's features came from."""
    return name in _STATE.get("owned", ())


def owns(name: str, entry: Path, idle: bool = False) -> bool:
    """Whether the prefetch will compute, or is computing, the photo ``name``'s features into ``entry`` (the
    stage's own name for it), so that the stage waits for them; False once they are written. ``idle``: the caller
    has a worker with nothing to do. Where the process got less than :data:`STARVED_SHARE` of a core over
    :data:`STARVED_WINDOW_S` of such idle waiting (other work holds the cores), it is stopped and False is returned
    for every photo from then on: the stage computes them."""
    if not _pending(name, entry):
        return False
    if not idle:
        _STATE["watch"] = None
        return True
    now, cpu = time.monotonic(), _cpu_s(_STATE["proc"].pid)
    if _STATE.get("watch") is None or cpu is None:
        _STATE["watch"] = (now, cpu)
        return True
    t0, c0 = _STATE["watch"]
    if now - t0 < STARVED_WINDOW_S:
        return True
    if c0 is not None and cpu - c0 < STARVED_SHARE * (now - t0):
        log.info("correspond: the prefetch got %.0f %% of a core in the last %.1f s while a worker waited (other "
                 "work holds the cores): the stage computes the photos' features", 100 * (cpu - c0) / (now - t0),
                 now - t0)
        stop()
        return False
    _STATE["watch"] = (now, cpu)
    return True


def computing(name: str, entry: Path) -> bool:
    """Whether the prefetch is computing the photo ``name``'s features into ``entry`` now (the stage's own name for
    it; another name: False)."""
    if not _STATE or _STATE["files"].get(name) != entry:
        return False
    return _STATE["status"][_STATE["names"].index(name)] == BUSY and _alive(_STATE["proc"].pid)


def wait_for(name: str, entry: Path) -> None:
    """In a worker (or the stage's own process): wait while the prefetch computes the photo ``name``'s features
    into ``entry`` (the stage's own name for it; another name: nothing to wait for), or will compute them (a photo
    it owns, :func:`adopt`), and while it gets a core: one that got less than :data:`STARVED_SHARE` of a core over
    :data:`STARVED_WINDOW_S` is left (the caller computes the photo; a photo not begun is not begun then)."""
    t0 = time.monotonic()
    if not _pending(name, entry):
        return
    pid = _STATE["proc"].pid
    w0, c0 = t0, _cpu_s(pid)
    while _pending(name, entry) and time.monotonic() - t0 < WAIT_MAX_S:
        time.sleep(0.02)
        now = time.monotonic()
        if now - w0 >= STARVED_WINDOW_S:
            c1 = _cpu_s(pid)
            if c0 is not None and c1 is not None and c1 - c0 < STARVED_SHARE * (now - w0):
                log.info("correspond: the prefetch computing %s got %.0f %% of a core in the last %.1f s (other work "
                         "holds the cores): computed here after waiting %.1f s", name, 100 * (c1 - c0) / (now - w0),
                         now - w0, now - t0)
                with _STATE["status"].get_lock():
                    _STATE["stop"].value = 1
                return
            w0, c0 = now, c1
    log.info("correspond: waited %.1f s for the prefetch computing %s", time.monotonic() - t0, name)


def _pending(name: str, entry: Path) -> bool:
    """Whether the prefetch is computing the photo's features into ``entry`` now, or will (not begun, not stopped),
    and is alive."""
    if not _STATE or _STATE["files"].get(name) != entry:
        return False
    state = _STATE["status"][_STATE["names"].index(name)]
    if state == DONE or (state == PENDING and _STATE["stop"].value):
        return False
    return _alive(_STATE["proc"].pid)


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


__all__ = ["start", "stop", "adopt", "owns", "took", "computing", "wait_for", "finish"]
