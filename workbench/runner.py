"""The stage runner: stage order, input hashing, skipping, forcing, and a record of every run.

A stage is a :class:`StageSpec`: a name, the stages it depends on, a function listing its input files,
the settings sections it reads, and ``run(project, progress) -> StageResult``. The runner records in
``out/state.json``, per stage: status, the SHA-256 of every input file, a hash of its settings sections,
the hashes of its dependencies' outputs, its outputs with their hashes, the run time, and the error if
it failed. A stage is *done* when that record matches the current inputs, *stale* when it does not,
*failed* when its last run raised, and *not run* otherwise. Running skips done stages unless forced.

With ``jobs`` > 1 a stage runs in a forked process beside the stage after it when that one declares it may
(``StageSpec.runs_beside``: it reads none of the earlier stage's outputs), e.g. the export beside the render; and a
stage with work that needs none of its dependencies' outputs (``StageSpec.ahead``) gets its own process when an
earlier stage starts (``ahead_from``), which does that work on the cores left idle meanwhile and then runs the
stage in its turn (the render: its models read while the correspond stage runs). The runner's process alone writes
``out/state.json``; each stage's record is written as soon as it ends, and a stage that needs one still running
waits for it.

The stages are declared in ``workbench/pipeline.py``.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import importlib
import json
import logging
import os
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from .core.io import hash_file
from .core.stage_api import Progress, StageResult  # noqa: F401 - re-exported for the CLI and tests
from .errors import StageError, WorkbenchError

if TYPE_CHECKING:  # the runner is handed a Project; importing it here would load the settings models
    from .project import Project

log = logging.getLogger(__name__)


def _no_progress(fraction: float, message: str = "") -> None:  # pragma: no cover - trivial
    pass


@dataclass(frozen=True)
class StageSpec:
    """A stage. ``run`` is the function ``(project, progress) -> StageResult``, or its name ``"module:function"``,
    imported the first time the stage runs (so listing or checking stages loads none of their code)."""

    name: str
    description: str
    run: Callable[[Project, Progress], StageResult] | str
    inputs: Callable[[Project], dict[str, Path]] = lambda project: {}
    settings_sections: tuple[str, ...] = ()
    depends_on: tuple[str, ...] = ()
    applies: Callable[[Project], bool] = lambda project: True  # False: the stage has nothing to do here
    # "module:function" ``(project) -> None`` that starts, on threads, work the stage will take when it runs (its
    # photos' features while the stages before it run); what it leaves unused is dropped
    prefetch: str | None = None
    # earlier stages that may still be running while this one runs, in another process (this stage reads none of
    # their outputs, nor they this one's); such a stage must declare no prefetch (it is forked)
    runs_beside: tuple[str, ...] = ()
    # "module:function" ``(project) -> iterator``: work of this stage that reads none of its dependencies' outputs (a
    # generator, one step of the work per item), started when the stage ``ahead_from`` (an earlier one) starts, in
    # this stage's own forked process, a step whenever a core is idle (``_early_process``); when this stage's turn
    # comes its process runs the stage, which does what was not done ahead (``Runner``)
    ahead: str | None = None
    ahead_from: str | None = None

    def function(self) -> Callable[[Project, Progress], StageResult]:
        """The stage's code, imported on first use when ``run`` names it."""
        if not isinstance(self.run, str):
            return self.run
        module, _, attr = self.run.partition(":")
        return getattr(importlib.import_module(module), attr)


@dataclass
class StageStatus:
    name: str
    status: str  # done | stale | failed | not run | skipped (not applicable)
    reason: str = ""
    record: dict | None = None


def _settings_hash(project: Project, sections: tuple[str, ...]) -> str:
    blob = json.dumps(project.settings_section(*sections), sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()


def _outputs_digest(record: dict) -> str:
    """Digest of a stage's outputs (not its stats, whose run time changes every run)."""
    outs = {k: v for k, v in record.get("outputs", {}).items() if k != "stats"}
    blob = json.dumps(outs, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()


class Runner:
    def __init__(self, project: Project, stages: list[StageSpec], *, jobs: int = 1) -> None:
        """``jobs``: how many stages may run at once (1: one after another; more: see ``StageSpec.runs_beside``)."""
        names = [s.name for s in stages]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate stage names in {names}")
        if not isinstance(jobs, int) or jobs < 1:
            raise ValueError(f"jobs = {jobs!r}; expected an integer >= 1")
        self.project = project
        self.stages = stages
        self.jobs = jobs
        self._hashes: dict[tuple, str] = {}
        self._state_lock = threading.Lock()  # the record is read, changed and written by one thread at a time
        self.by_name = {s.name: s for s in stages}
        for s in stages:
            for d in s.depends_on:
                if d not in self.by_name or names.index(d) >= names.index(s.name):
                    raise ValueError(f"stage {s.name!r} depends on {d!r}, which does not run before it")
        # what each stage may run beside in this list: its declared stages that come before it here and that it does
        # not depend on (a list that leaves one out or puts it later, such as a test's own stage order, runs the
        # two one after another)
        self._beside: dict[str, tuple[str, ...]] = {}
        for s in stages:
            ok = []
            for d in s.runs_beside:
                if d not in self.by_name or names.index(d) >= names.index(s.name) or d in s.depends_on:
                    continue
                if self.by_name[d].prefetch:
                    raise ValueError(f"stage {d!r} has a prefetch: it cannot run in another process beside {s.name!r}")
                ok.append(d)
            self._beside[s.name] = tuple(ok)
            if (s.ahead is None) != (s.ahead_from is None):
                raise ValueError(f"stage {s.name!r}: ahead and ahead_from go together")
            if s.ahead is not None and s.prefetch:
                raise ValueError(f"stage {s.name!r} has a prefetch: it cannot run in a process of its own")
        self._early: dict[str, _EarlyStage] = {}  # the stages whose process was forked ahead of their turn

    # -- fingerprints -------------------------------------------------------------------------------------
    def _hash(self, path: Path) -> str:
        """SHA-256 of a file, computed once per run for a file that has not changed since (same inode, size and
        modification time): a run checks every stage's inputs before and while running it, and lists them after,
        and the photos were hashed at each of those."""
        st = path.stat()
        key = (str(path.resolve()), st.st_ino, st.st_size, st.st_mtime_ns)
        if key not in self._hashes:
            self._hashes[key] = hash_file(path)
        return self._hashes[key]

    def _fingerprint(self, spec: StageSpec, state: dict) -> dict:
        inputs = spec.inputs(self.project)
        missing = [f"{k} ({p})" for k, p in inputs.items() if not Path(p).is_file()]
        if missing:
            raise StageError(f"stage {spec.name!r}: input file(s) missing: {', '.join(missing)}")
        return {
            "inputs": {k: self._hash(Path(p)) for k, p in sorted(inputs.items())},
            "settings": _settings_hash(self.project, spec.settings_sections),
            "upstream": {d: _outputs_digest(state.get(d, {})) for d in spec.depends_on},
        }

    def status(self) -> list[StageStatus]:
        """Every stage's status, in order; a stage is done only if every stage it depends on is done (or skipped)
        now, not merely recorded as done (after a run killed half-way, the later records are out of date)."""
        state = self.project.read_state()
        out: dict[str, StageStatus] = {}
        for spec in self.stages:
            out[spec.name] = self._status_of(spec, state, out)
        return list(out.values())

    def _status_of(self, spec: StageSpec, state: dict, known: dict[str, StageStatus] | None = None) -> StageStatus:
        rec = state.get(spec.name)
        if not spec.applies(self.project):
            return StageStatus(spec.name, "skipped", "not applicable to this incident", rec)
        if rec is None:
            return StageStatus(spec.name, "not run")
        if rec.get("status") == "failed":
            return StageStatus(spec.name, "failed", rec.get("error", ""), rec)
        for d in spec.depends_on:
            if state.get(d, {}).get("status") != "done" and self.by_name[d].applies(self.project):
                return StageStatus(spec.name, "stale", f"depends on {d!r}, which is not done", rec)
            if known is not None and d in known and known[d].status not in ("done", "skipped"):
                return StageStatus(spec.name, "stale", f"depends on {d!r}, which is {known[d].status}", rec)
        try:
            fp = self._fingerprint(spec, state)
        except WorkbenchError as exc:
            return StageStatus(spec.name, "stale", str(exc), rec)
        if fp["inputs"] != rec.get("inputs"):
            changed = sorted(set(fp["inputs"]) ^ set(rec.get("inputs", {}))
                             | {k for k in fp["inputs"] if rec.get("inputs", {}).get(k) != fp["inputs"][k]})
            return StageStatus(spec.name, "stale", f"inputs changed: {', '.join(changed)}", rec)
        if fp["settings"] != rec.get("settings"):
            return StageStatus(spec.name, "stale", f"settings changed ({', '.join(spec.settings_sections)})", rec)
        if fp["upstream"] != rec.get("upstream"):
            return StageStatus(spec.name, "stale", "an upstream stage produced new outputs", rec)
        for name, o in rec.get("outputs", {}).items():
            p = self.project.root / o["path"]
            if not p.is_file() or self._hash(p) != o["sha256"]:
                return StageStatus(spec.name, "stale", f"output {o['path']} missing or modified", rec)
        return StageStatus(spec.name, "done", "", rec)

    # -- running -------------------------------------------------------------------------------------------
    def prefetch(self, names: list[str] | None = None, force: bool = False) -> None:
        """Start the early work (``StageSpec.prefetch``) of the stages among ``names`` (default all) that will run
        (not done, or ``force``). Nothing depends on it: a stage uses what is ready and still valid. The later
        stages' first: one that forks a process (correspond) does so before another's threads start (stitch)."""
        state = self.project.read_state()
        for spec in reversed(self.stages):
            if not spec.prefetch or (names is not None and spec.name not in names):
                continue
            try:
                if self._status_of(spec, state).status == "skipped" or (
                        not force and self._status_of(spec, state).status == "done"):
                    continue
                module, _, attr = spec.prefetch.partition(":")
                getattr(importlib.import_module(module), attr)(self.project)
            except Exception as exc:  # noqa: BLE001 - only a head start: the stage does the work, and reports errors
                log.info("stage %s: no prefetch (%s: %s)", spec.name, type(exc).__name__, exc)

    def run(self, *, only: list[str] | None = None, until: str | None = None, force: bool = False,
            progress_factory: Callable[[StageSpec], Progress] | None = None,
            on_event: Callable[[str, StageSpec, dict], None] | None = None,
            prefetch: list[str] | None | bool = False) -> list[StageStatus]:
        """Run the stages in order (or only those named, or those up to ``until``), skipping done ones unless
        ``force``. ``prefetch``: the stages whose early work (:meth:`prefetch`) to start once the stages that start
        at once in their own process have been forked (None: every stage; False: none).

        Stops at the first failure (raises the stage's :class:`WorkbenchError` after recording it, once the stages
        running beside it have ended).
        """
        if only:
            unknown = [n for n in only if n not in self.by_name]
            if unknown:
                raise StageError(f"unknown stage(s) {unknown}; the stages are {list(self.by_name)}")
        if until is not None and until not in self.by_name:
            raise StageError(f"unknown stage {until!r}; the stages are {list(self.by_name)}")
        selected = [s for s in self.stages if not only or s.name in only]
        if until is not None:  # the stage and every stage before it (those not done run; done ones are skipped)
            last = [s.name for s in self.stages].index(until)
            selected = [s for s in selected if [x.name for x in self.stages].index(s.name) <= last]
        with self.project.lock():  # one run at a time on an incident: a second one is refused, not interleaved
            self._run_selected(selected, force, progress_factory, on_event, prefetch)
        return self.status()

    def _run_selected(self, selected: list[StageSpec], force: bool, progress_factory, on_event,
                      prefetch: list[str] | None | bool = False) -> None:
        beside: dict[str, _SideStage] = {}  # the stages running in other processes, by name
        try:
            # first the forks (a stage at once in its process), then the prefetches' threads and processes
            self._start_early(selected, beside, force, progress_factory, on_event)
            if prefetch is not False:
                self.prefetch(prefetch, force=force)
            self._run_in_order(selected, beside, force, progress_factory, on_event)
        except BaseException:
            # a stage failed here, or an interrupt: the stages running beside end (an interrupt reaches them too,
            # as part of the same process group) and their records are kept; this error is the one raised
            self._stop_ahead()
            for side in beside.values():
                side.thread.join()
            raise
        self._stop_ahead()  # (stages whose turn did not come: not run, e.g. with --until)
        for side in beside.values():  # the last ones, in order: the first error is raised, after every record
            side.thread.join()
        for side in beside.values():
            self._join(side)

    def _run_in_order(self, selected: list[StageSpec], beside: dict, force: bool, progress_factory,
                      on_event) -> None:
        order = [s.name for s in self.stages]
        for k, spec in enumerate(selected):
            if spec.name in beside:  # started early, running
                continue
            if not set(spec.depends_on) & set(beside) and not spec.applies(self.project):
                on_event and on_event("not-applicable", spec, {})
                continue
            nxt = next((s for s in selected[k + 1:] if s.name not in beside and s.applies(self.project)), None)
            for name in [n for n in beside if order.index(n) < order.index(spec.name)
                         and n not in self._beside[spec.name]]:  # the earlier stages this one may read
                self._join(beside.pop(name))
            state = self.project.read_state()
            st = self._status_of(spec, state)
            if st.status == "skipped" or (st.status == "done" and not force):
                self._stop_ahead(spec.name)
            if st.status == "skipped":
                on_event and on_event("not-applicable", spec, {})
                continue
            if st.status == "done" and not force:
                log.info("stage %s: up to date, skipped", spec.name)
                on_event and on_event("skipped", spec, st.record or {})
                continue
            for d in spec.depends_on:
                dst = self._status_of(self.by_name[d], state)
                if dst.status not in ("done", "skipped"):
                    raise StageError(f"stage {spec.name!r} needs stage {d!r}, which is {dst.status}"
                                     f"{': ' + dst.reason if dst.reason else ''}; run `workbench run "
                                     f"{self.project.root}` (or with --only {d})")
            self._start_ahead(spec, selected[k + 1:], state, force)
            early = self._early.pop(spec.name, None)
            if early is not None:  # its process did the work it could do ahead: it runs the stage now
                side = self._go(early, spec, state, progress_factory, on_event)
                if side is not None:
                    beside[spec.name] = side
                    continue
            if (nxt is not None and spec.name in self._beside[nxt.name] and len(beside) + 1 < self.jobs
                    and hasattr(os, "fork") and self._will_run(nxt, state, force)):
                beside[spec.name] = self._start_beside(spec, state, progress_factory, on_event)
            else:
                self._run_one(spec, state, progress_factory, on_event)

    def _run_one(self, spec: StageSpec, state: dict, progress_factory, on_event) -> None:
        fp = self._fingerprint(spec, state)
        progress = progress_factory(spec) if progress_factory else _no_progress
        on_event and on_event("start", spec, {})
        started = _dt.datetime.now(_dt.timezone.utc)
        t0 = time.perf_counter()
        log.info("stage %s: running", spec.name)
        try:
            result = spec.function()(self.project, progress)
        except Exception as exc:
            self._record_failure(spec, state, exc, started, time.perf_counter() - t0, on_event)
            if isinstance(exc, WorkbenchError):
                raise
            raise self._failed_error(spec, exc) from exc
        self._record_done(spec, fp, result, started, time.perf_counter() - t0, on_event)

    def _write_record(self, name: str, rec: dict) -> None:
        """Record a stage's end in ``out/state.json``, the stages in their order (whichever ended first)."""
        with self._state_lock:
            state = self.project.read_state()
            state[name] = rec
            order = {s.name: i for i, s in enumerate(self.stages)}
            self.project.write_state(dict(sorted(state.items(), key=lambda kv: order.get(kv[0], len(order)))))

    def _failed_error(self, spec: StageSpec, exc: BaseException) -> StageError:
        return StageError(f"stage {spec.name!r} failed: {type(exc).__name__}: {exc} (details in "
                          f"{self.project.state_path})")

    def _record_failure(self, spec: StageSpec, state: dict, exc: BaseException, started, duration: float,
                        on_event, tb: str | None = None) -> None:
        msg = str(exc) if isinstance(exc, WorkbenchError) else f"{type(exc).__name__}: {exc}"
        rec = {"status": "failed", "error": msg, "started_utc": started.isoformat(timespec="seconds"),
               "duration_s": round(duration, 3)}
        if not isinstance(exc, WorkbenchError):
            rec["traceback"] = tb or traceback.format_exc()
        # keep the previous successful outputs recorded, so nothing is lost
        prev = state.get(spec.name, {})
        if prev.get("status") == "done":
            rec["previous"] = {k: prev[k] for k in ("outputs", "started_utc", "duration_s") if k in prev}
        self._write_record(spec.name, rec)
        on_event and on_event("failed", spec, rec)

    def _record_done(self, spec: StageSpec, fp: dict, result: StageResult, started, duration: float,
                     on_event) -> None:
        stats = dict(result.stats)
        stats.setdefault("stage", spec.name)
        stats["duration_s"] = round(duration, 3)
        stats_path = self.project.stage_dir(spec.name) / "stats.json"
        self.project.write_json(stats_path, stats)
        outputs = {"stats": stats_path, **result.outputs}
        rec = {
            "status": "done",
            **fp,
            "outputs": {k: {"path": self.project.relative(p), "sha256": self._hash(Path(p))}
                        for k, p in outputs.items()},
            "started_utc": started.isoformat(timespec="seconds"),
            "duration_s": round(duration, 3),
        }
        self._write_record(spec.name, rec)
        log.info("stage %s: done in %.2f s", spec.name, duration)
        on_event and on_event("done", spec, rec)

    # -- a stage beside another ---------------------------------------------------------------------------
    def _start_early(self, selected: list[StageSpec], beside: dict, force: bool, progress_factory,
                     on_event) -> None:
        """Fork, before anything else runs, each stage that may run beside every selected stage before it (its
        ``runs_beside``), whose dependencies are done and which the stage after it does not wait for (e.g. the
        terrain, beside the inputs, stitch, georef and correspond stages)."""
        if self.jobs < 2 or not hasattr(os, "fork"):
            return
        state = self.project.read_state()
        for k, spec in enumerate(selected):
            if k == 0 or len(beside) + 1 >= self.jobs:
                continue
            if spec.prefetch or not {s.name for s in selected[:k]} <= set(self._beside[spec.name]):
                continue
            # the stage after it that will run (those that do not apply are passed by) must not wait for it
            nxt = next((s for s in selected[k + 1:] if self._will_run(s, state, force, deps=False)), None)
            if nxt is not None and spec.name in self._beside[nxt.name] and self._will_run(spec, state, force):
                beside[spec.name] = self._start_beside(spec, state, progress_factory, on_event)

    def _will_run(self, spec: StageSpec, state: dict, force: bool, deps: bool = True) -> bool:
        """Whether ``spec`` would run now: it applies, is not done (or ``force``), and (``deps``) its dependencies
        are done."""
        st = self._status_of(spec, state)
        if st.status == "skipped" or (st.status == "done" and not force):
            return False
        return not deps or all(self._status_of(self.by_name[d], state).status in ("done", "skipped")
                               for d in spec.depends_on)

    def _start_beside(self, spec: StageSpec, state: dict, progress_factory, on_event) -> "_SideStage":
        """Start ``spec`` in a forked process; a thread here forwards its progress and records its end (the
        record, stats.json and the events as :meth:`_run_one`); :meth:`_join` waits for it and raises its error."""
        import multiprocessing

        fp = self._fingerprint(spec, state)
        progress = progress_factory(spec) if progress_factory else _no_progress
        on_event and on_event("start", spec, {})
        started = _dt.datetime.now(_dt.timezone.utc)
        log.info("stage %s: running (in process beside the next stage)", spec.name)
        ours, theirs = multiprocessing.get_context("fork").Pipe(duplex=False)
        proc = multiprocessing.get_context("fork").Process(target=_stage_process, args=(spec, self.project, theirs),
                                                           name=f"stage {spec.name}", daemon=False)
        t0 = time.perf_counter()
        proc.start()
        theirs.close()
        return self._watch(spec, proc, ours, fp, state, started, t0, progress, on_event)

    def _watch(self, spec: StageSpec, proc, ours, fp: dict, state: dict, started, t0: float, progress,
               on_event) -> "_SideStage":
        """A thread that forwards the progress of ``spec`` running in process ``proc`` (its messages on ``ours``) and
        records its end."""
        side = _SideStage(spec, proc)

        def watch() -> None:
            end = None
            try:
                while True:
                    msg = ours.recv()
                    if msg[0] == "progress":
                        progress(*msg[1:])
                    else:
                        end = msg
                        break
            except (EOFError, OSError):
                pass
            proc.join()
            duration = time.perf_counter() - t0
            try:
                if end is not None and end[0] == "done":
                    self._record_done(spec, fp, StageResult(outputs=end[1], stats=end[2]), started, end[3],
                                      on_event)
                    return
                if end is not None:  # ("failed", exception or None, message, traceback, duration)
                    exc = end[1] if isinstance(end[1], BaseException) else RuntimeError(end[2])
                    self._record_failure(spec, state, exc, started, end[4], on_event, tb=end[3])
                else:
                    code = proc.exitcode if proc.exitcode is not None else "?"
                    signal = f"; killed by signal {-code}" if isinstance(code, int) and code < 0 else ""
                    exc = StageError(f"stage {spec.name!r}: its process ended without a result (exit code {code}"
                                     f"{signal}); run `workbench run {self.project.root} --only {spec.name}` again")
                    self._record_failure(spec, state, exc, started, duration, on_event, tb="")
                side.error = exc if isinstance(exc, WorkbenchError) else self._failed_error(spec, exc)
            except BaseException as exc:  # noqa: BLE001 - the record could not be written: the join raises it
                side.error = exc
            finally:
                ours.close()

        side.thread = threading.Thread(target=watch, name=f"stage {spec.name} watcher", daemon=True)
        side.thread.start()
        return side

    # -- a stage's work ahead of its turn -----------------------------------------------------------------
    def _start_ahead(self, spec: StageSpec, later: list[StageSpec], state: dict, force: bool) -> None:
        """``spec`` is about to run: fork the process of each later stage that starts its work ahead when ``spec``
        starts (``StageSpec.ahead_from``) and will run (applies, not done or ``force``)."""
        if self.jobs < 2 or not hasattr(os, "fork"):
            return
        import multiprocessing

        for s in later:
            if s.ahead_from != spec.name or s.name in self._early or not self._will_run(s, state, force, deps=False):
                continue
            ctx = multiprocessing.get_context("fork")
            try:
                ours, theirs = ctx.Pipe(duplex=True)
                proc = ctx.Process(target=_early_process, args=(s, self.project, theirs, ours),
                                   name=f"stage {s.name}", daemon=False)
                proc.start()
            except OSError as exc:  # (no memory for a fork, too many processes): the stage runs in its turn as before
                log.info("stage %s: no work ahead (%s)", s.name, exc)
                continue
            theirs.close()
            self._early[s.name] = _EarlyStage(s, proc, ours)
            log.info("stage %s: its work ahead started beside stage %s (process %d)", s.name, spec.name, proc.pid)

    def _go(self, early: "_EarlyStage", spec: StageSpec, state: dict, progress_factory,
            on_event) -> "_SideStage | None":
        """The turn of a stage whose process was forked ahead: it runs the stage now (a stage running beside the ones
        after it, :meth:`_watch`). None where that process is gone (the stage then runs here)."""
        fp = self._fingerprint(spec, state)
        started = _dt.datetime.now(_dt.timezone.utc)
        t0 = time.perf_counter()
        try:
            early.conn.send(("go",))
        except OSError:
            log.info("stage %s: its process ahead ended (exit code %s); run here", spec.name, early.process.exitcode)
            early.conn.close()
            early.process.join()
            return None
        progress = progress_factory(spec) if progress_factory else _no_progress
        on_event and on_event("start", spec, {})
        log.info("stage %s: running (in its process, started ahead)", spec.name)
        return self._watch(spec, early.process, early.conn, fp, state, started, t0, progress, on_event)

    def _stop_ahead(self, name: str | None = None) -> None:
        """End the processes started ahead whose stage will not run (``name``, or every one left)."""
        for n in [name] if name is not None else list(self._early):
            early = self._early.pop(n, None)
            if early is None:
                continue
            try:
                early.conn.send(("stop",))
            except OSError:  # it has ended already (its end of the pipe closed): nothing to stop, only to join
                pass
            early.conn.close()
            early.process.join()

    def _join(self, side: "_SideStage") -> None:
        """Wait for a stage running beside; raise its error (its record is written by then)."""
        side.thread.join()
        if side.error is not None:
            raise side.error


@dataclass
class _EarlyStage:
    spec: StageSpec
    process: object
    conn: object


@dataclass
class _SideStage:
    spec: StageSpec
    process: object
    thread: threading.Thread | None = None
    error: BaseException | None = None


def _stage_process(spec: StageSpec, project: Project, conn) -> None:
    """In the forked process: run the stage, send its progress (at most every 0.2 s, and its last) and its end:
    ``("done", outputs, stats, duration)`` or ``("failed", exception or None, message, traceback, duration)``."""
    last = [0.0]

    def progress(fraction: float, message: str = "") -> None:
        now = time.monotonic()
        if now - last[0] >= 0.2 or fraction >= 1.0:
            last[0] = now
            conn.send(("progress", float(fraction), str(message)))

    t0 = time.perf_counter()
    try:
        result = spec.function()(project, progress)
        conn.send(("done", {k: Path(v) for k, v in result.outputs.items()}, dict(result.stats),
                   time.perf_counter() - t0))
    except Exception as exc:  # noqa: BLE001 - sent to the runner, which records and raises it
        tb = traceback.format_exc()
        msg = str(exc) if isinstance(exc, WorkbenchError) else f"{type(exc).__name__}: {exc}"
        try:
            conn.send(("failed", exc, msg, tb, time.perf_counter() - t0))
        except Exception:  # noqa: BLE001 - an exception that does not pickle: its message
            conn.send(("failed", None, msg, tb, time.perf_counter() - t0))
    finally:
        conn.close()


def _early_process(spec: StageSpec, project: Project, conn, parent_end=None) -> None:
    """In the process forked ahead of a stage's turn: the steps of its work ahead (``StageSpec.ahead``, a generator)
    on a thread, each one when a core has been idle (:func:`_idle_cores`: the stages running then come first, and so
    does work at a lower priority, such as the correspond prefetch), until the runner says "go" (then the stage runs
    as :func:`_stage_process` runs it, and does itself what was not done ahead) or "stop" (the stage will not run).
    The thread runs at the stage's priority: the step it is in when the stage's turn comes (one model, one layer;
    under a second) is finished first, never left to a starved thread. Work ahead that fails is left to the stage
    (logged)."""
    if parent_end is not None:  # the runner's end of the pipe: closed here, so that a runner killed is an end of file
        parent_end.close()
    go = threading.Event()
    lock = threading.Lock()
    state: dict = {"steps": None, "over": False}

    def step() -> bool:
        with lock:
            if state["over"]:
                return False
            try:
                if state["steps"] is None:
                    module, _, attr = spec.ahead.partition(":")
                    state["steps"] = iter(getattr(importlib.import_module(module), attr)(project))
                next(state["steps"])
                return True
            except StopIteration:  # every step of the work ahead done: over, as after a failure
                pass
            except Exception as exc:  # noqa: BLE001 - only a head start: the stage does the work, and reports errors
                log.info("stage %s: work ahead stopped (%s: %s)", spec.name, type(exc).__name__, exc)
            state["over"] = True
            return False

    def background() -> None:
        while not go.is_set():
            if _idle_cores(AHEAD_SAMPLE_S) < AHEAD_IDLE_CORES:
                continue
            if go.is_set() or not step():
                break

    thread = threading.Thread(target=background, name=f"stage {spec.name} ahead", daemon=True)
    thread.start()
    try:
        msg = conn.recv()
    except (EOFError, OSError):
        msg = ("stop",)
    go.set()
    with lock:  # the step the thread is in is finished; the steps not begun are left to the stage, which does what it
        state["over"] = True  # needs (the render: only the carriages the solution poses)
    if msg[0] != "go":
        conn.close()
        return
    _stage_process(spec, project, conn)


AHEAD_SAMPLE_S = 0.2  # the work ahead takes a step when, over this long, ...
AHEAD_IDLE_CORES = 0.5  # ... at least this much of a core was idle


def _idle_cores(interval_s: float) -> float:
    """How many cores were idle (the kernel's idle and I/O-wait time, ``/proc/stat``) over the next ``interval_s``;
    where that cannot be read, as many as there are."""
    def read() -> tuple[int, int] | None:
        try:
            with open("/proc/stat") as f:
                fields = [int(x) for x in f.readline().split()[1:]]
        except (OSError, ValueError):
            return None
        return fields[3] + fields[4], sum(fields[:8])

    a = read()
    time.sleep(interval_s)
    b = read()
    if a is None or b is None or b[1] <= a[1]:
        return float(os.cpu_count() or 1)
    return (b[0] - a[0]) / (b[1] - a[1]) * (os.cpu_count() or 1)
