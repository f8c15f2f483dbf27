"""The ``workbench`` command: it only parses arguments and calls the library."""

from __future__ import annotations

import atexit
import datetime as _dt
import gc
import logging
import os
import sys
import threading
from pathlib import Path
from typing import Optional

import typer

from .errors import WorkbenchError

# Plain help (click's formatter): rich's help panels cost half a second at every `--help`.
app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode=None,
                  help="Reconstruction workbench for train-accident scenes: one incident folder per incident.")


class _Console:
    """A rich ``Console`` made on first use (:attr:`real`; any other attribute is the console's): rich's console
    (about 20 ms of imports) is loaded once a command prints something that is not a plain line to a file that is
    not a terminal (:meth:`print`), not before a stage command has started its stages' early work (the panorama's
    descriptions, :meth:`Runner.prefetch`)."""

    def __init__(self, **options) -> None:
        self._options = options
        self._console = None
        self._lock = threading.Lock()  # (stages report progress from their threads)

    @property
    def real(self):
        with self._lock:
            if self._console is None:
                from rich.console import Console

                self._console = Console(**self._options)
            return self._console

    def __getattr__(self, name: str):
        return getattr(self.real, name)

    def _plain_file(self):
        """This console's file where rich would write plain text to it (not a tty, neither ``TTY_COMPATIBLE`` nor
        ``FORCE_COLOR`` set, no IPython, rich's console not made yet); else None (rich decides and writes)."""
        if self._console is not None or "TTY_COMPATIBLE" in os.environ or "FORCE_COLOR" in os.environ \
                or "IPython" in sys.modules:
            return None
        file = sys.stderr if self._options.get("stderr") else sys.stdout
        try:
            return None if file is None or file.isatty() else file
        except (AttributeError, ValueError):  # no isatty, or closed: rich's business
            return None

    @property
    def is_terminal(self) -> bool:
        return False if self._plain_file() is not None else self.real.is_terminal

    def print(self, *objects, **options) -> None:
        """rich's ``Console.print``; plain strings to a file that is not a terminal (:meth:`_plain_file`) are written
        as rich writes them (the control characters rich takes out taken out, tabs expanded) but not folded at 80
        columns (a log line stays one line), without loading rich (15-20 ms of a `workbench stitch`)."""
        file = self._plain_file()
        if file is None or not all(isinstance(o, str) for o in objects) or set(options) - {"highlight"}:
            self.real.print(*objects, **options)
            return
        file.write(" ".join(objects).translate(_CONTROL_CODES).expandtabs(8) + "\n")
        file.flush()


_CONTROL_CODES = dict.fromkeys((7, 8, 11, 12, 13))  # what rich's Text takes out of a string (BEL, BS, VT, FF, CR)


# markup and emoji codes off: a photo or folder named like "[red]x" or ":fire:" is printed as it is, never parsed
console = _Console(stderr=True, markup=False, highlight=False, emoji=False)
out = _Console(markup=False, highlight=False, emoji=False)


class _Bars:
    """The commands' progress: rich's bars where the CLI's console is a terminal, else nothing drawn (what rich's
    ``Progress(disable=True)`` did). Decided at the first task, so rich's console and live display (7-15 ms of
    imports) are loaded after a stage command has started its stages' early work, and not at all without a
    terminal."""

    def __init__(self) -> None:
        self._bars = None  # rich's Progress, started at the first task on a terminal
        self._tasks: dict[int, dict] = {}  # without a terminal: each task's fields, nothing drawn

    def __enter__(self) -> "_Bars":
        return self

    def __exit__(self, *exc):
        return self._bars.__exit__(*exc) if self._bars is not None else None

    @property
    def console(self):
        return self._bars.console if self._bars is not None else console

    def add_task(self, description: str, **fields) -> int:
        if self._bars is None and not self._tasks and console.is_terminal:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            self._bars = Progress(TextColumn("[bold]{task.description:<10}"), BarColumn(),
                                  TextColumn("{task.fields[msg]}", markup=False), TimeElapsedColumn(),
                                  console=console.real, transient=False)
            self._bars.__enter__()
        if self._bars is not None:
            return self._bars.add_task(description, **fields)
        self._tasks[len(self._tasks)] = {"description": description, **fields}
        return len(self._tasks) - 1

    def update(self, task: int, **fields) -> None:
        if self._bars is not None:
            self._bars.update(task, **fields)
        else:
            self._tasks[task].update(fields)


def _progress() -> _Bars:
    return _Bars()


@app.callback()
def _main(verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="-v info, -vv debug logging"),
          ctx: typer.Context = None) -> None:
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    _one_line_warnings()
    if ctx is None or ctx.invoked_subcommand not in _RUNS_STAGES:  # (those resume it as their first stage starts)
        _resume_collection()


_RUNS_STAGES: set[str] = {"run"}  # the commands that run stages (through _execute): `run` and one per stage
_COLLECTION = {"paused": False}


def _pause_collection() -> None:
    """The garbage collector paused while the command starts: imports, parses its arguments, validates the settings
    and (a stage command) starts its stages' early work. What is made then (modules, classes, validators) lives as
    long as the process; collecting among it found nothing and cost a fresh `workbench stitch` 60-90 ms of its main
    thread's CPU at load 5 (a full collection of every object, in the inputs stage, and the young generations'
    during the imports). Resumed by :func:`_resume_collection`: by the command (at once, or as its first stage
    starts), and in a process forked before that (a stage's or its early work's)."""
    if gc.isenabled():
        gc.disable()
        _COLLECTION["paused"] = True
        os.register_at_fork(after_in_child=_resume_collection)


def _resume_collection() -> None:
    """Where :func:`_pause_collection` paused the garbage collector (once; else nothing): the objects made so far
    moved out of its reach (``gc.freeze``: the process's modules, classes and settings, not scanned again by later
    collections) and the collector resumed."""
    if _COLLECTION["paused"]:
        _COLLECTION["paused"] = False
        gc.freeze()
        gc.enable()


def _one_line_warnings() -> None:
    """The library's warnings (``WorkbenchWarning``) as one line each, ``WARNING <category>: <message>``, and not
    at all when the library has just logged the same message (most warn and log both); others as Python's."""
    import warnings

    from .errors import WorkbenchWarning

    logged: set[str] = set()

    class _Seen(logging.Filter):
        def filter(self, record: logging.LogRecord) -> bool:
            if record.levelno >= logging.WARNING:
                logged.add(record.getMessage())
            return True

    for h in logging.getLogger().handlers:
        h.addFilter(_Seen())
    plain = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if not (isinstance(category, type) and issubclass(category, WorkbenchWarning)):
            return plain(message, category, filename, lineno, file, line)
        if str(message) not in logged:
            console.print(f"WARNING {category.__name__}: {message}")

    warnings.showwarning = show


@app.command()
def init(path: Path = typer.Argument(..., help="new incident folder, e.g. projects/my-incident"),
         name: Optional[str] = typer.Option(None, help="incident name"),
         lat: float = typer.Option(0.0, help="reference point latitude (WGS84 degrees)"),
         lon: float = typer.Option(0.0, help="reference point longitude (WGS84 degrees)"),
         crs: str = typer.Option("EPSG:32618", help="projected CRS of the project (metres)"),
         date: Optional[str] = typer.Option(None, help="incident date YYYY-MM-DD (default today)")) -> None:
    """Create an incident folder with a documented project.toml."""
    from .project import Project

    d = None
    if date:
        try:
            d = _dt.date.fromisoformat(date)
        except ValueError:
            raise WorkbenchError(f"--date {date!r}: give the date as YYYY-MM-DD") from None
    p = Project.create(path, name=name, lat=lat, lon=lon, crs=crs, date=d)
    out.print(f"created {p.settings_path}; edit it (see docs/formats.md), put photos in {p.root / 'photos/panorama'}")


@app.command()
def synth(path: Path = typer.Argument(..., help="incident folder to generate (created if missing)"),
          scenario: str = typer.Option("spuyten-duyvil", help="spuyten-duyvil | frankford-junction"),
          seed: int = typer.Option(1, help="random seed (the incident is deterministic for a seed)"),
          cars: Optional[int] = typer.Option(None, help="number of carriages (default: the scenario's consist)"),
          width: int = typer.Option(1600, help="photo width, px"),
          height: int = typer.Option(1200, help="photo height, px"),
          panorama: Optional[int] = typer.Option(None, help="photos in the panorama set (default 5-8, automatic)"),
          multiview: int = typer.Option(12, help="photos in the multi-position set (0: none)"),
          terrain_size: float = typer.Option(500.0, help="side of the generated DEM and orthophoto, metres"),
          layers_dir: str = typer.Option("layers", help="where the DEM and buildings go, relative to the folder"),
          force: bool = typer.Option(False, "--force", help="regenerate even if already generated")) -> None:
    """Generate a synthetic incident with ground truth (DEM, buildings, derailed consist, photos)."""
    from .synth.generate import SynthOptions, generate_incident

    opts = SynthOptions(scenario=scenario, seed=seed, n_cars=cars, photo_width=width, photo_height=height,
                        n_panorama=panorama, n_multiview=multiview, terrain_size_m=terrain_size,
                        layers_dir=layers_dir)
    path.mkdir(parents=True, exist_ok=True)
    with _progress() as prog:
        task = prog.add_task("synth", total=1.0, msg="")

        def progress(f: float, m: str = "") -> None:
            prog.update(task, completed=f, msg=m)
            if not console.is_terminal:
                console.print(f"synth: {m}", highlight=False)

        res = generate_incident(path, opts, force=force, progress=progress)
    if res.get("skipped"):
        out.print(f"{path}: already generated with these options (use --force to regenerate)")
    else:
        out.print(f"{path}: {res['carriages']} carriages, {res['photos']} photos; truth in {res['truth']}")


def _runner(path: Path, jobs: int | None = None):
    from .pipeline import STAGES
    from .project import Project
    from .runner import Runner

    project = Project(path)
    project.settings  # validate first: a typo fails before anything runs
    return project, Runner(project, STAGES, jobs=default_jobs() if jobs is None else jobs)


def default_jobs() -> int:
    """Stages run at once where they may (the export beside the render): 2 where the process may use two CPUs."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    return 2 if cpus >= 2 else 1


LOG_PROGRESS_EVERY_S = 2.0  # without a terminal, a stage's progress is a line at most this often


def _execute(path: Path, **kw) -> None:
    """Run stages with progress bars (a terminal), or lines in a log: a stage's start, its progress (a line when
    its step changes, at most every LOG_PROGRESS_EVERY_S), and its end; then list the outputs."""
    import time

    project, runner = _runner(path, kw.pop("jobs", None))
    with _progress() as prog:
        tasks = {}

        def factory(spec):
            tasks[spec.name] = prog.add_task(spec.name, total=1.0, msg="")
            if console.is_terminal:
                return lambda f, m="": prog.update(tasks[spec.name], completed=f, msg=m)
            last = {"t": time.monotonic(), "msg": None}

            def log_line(f: float, m: str = "") -> None:
                now = time.monotonic()
                if m != last["msg"] and now - last["t"] >= LOG_PROGRESS_EVERY_S:
                    console.print(f"{spec.name}: {100 * f:3.0f} % {m}")
                    last.update(t=now, msg=m)
            return log_line

        def event(kind, spec, rec):
            if kind == "start":  # (the collector paused at the command's start resumes: _pause_collection)
                _resume_collection()
            if kind == "done" and spec.name in tasks:
                prog.update(tasks[spec.name], completed=1.0, msg=f"done in {rec['duration_s']:.1f} s")
            if kind == "skipped":
                prog.console.print(f"{spec.name}: up to date, skipped")
            if not console.is_terminal and kind == "start":
                console.print(f"{spec.name}: running")
            if not console.is_terminal and kind == "done":
                console.print(f"{spec.name}: done in {rec['duration_s']:.1f} s")

        steps = kw.pop("steps", None) or [kw]
        for step, prefetch in zip(steps, _prefetches(runner, steps)):
            statuses = runner.run(progress_factory=factory, on_event=event, prefetch=prefetch, **step)
    _print_outputs(project, statuses)


def _prefetches(runner, steps: list[dict]) -> list[list[str] | None | bool]:
    """The early work (``Runner.run``'s ``prefetch``) of each of the runner's ``steps``, always started by a step's
    run, which forks its processes first, so that no thread runs when a process is forked. The first step starts
    that of every stage the steps may run, but that of a stage which a later step forces and which is done now
    (the runner passes a done stage by unless forced): that step starts it (``workbench stitch --force``)."""
    ahead = _stages_of(runner, steps)
    forced = {k: _stages_of(runner, [st]) for k, st in enumerate(steps) if k and st.get("force")}
    out: list[list[str] | None | bool] = [ahead] + [False] * (len(steps) - 1)
    if forced:
        every = [s.name for s in runner.stages]
        done = {st.name for st in runner.status() if st.status == "done"}
        own = {k: [n for n in (names if names is not None else every) if n in done] for k, names in forced.items()}
        later = {n for names in own.values() for n in names}
        out[0] = [n for n in (ahead if ahead is not None else every) if n not in later]
        for k, names in own.items():
            out[k] = names or False
    return out


def _stages_of(runner, steps: list[dict]) -> list[str] | None:
    """The stages that the runner's ``steps`` (``run`` arguments) may run; None: every stage."""
    names: list[str] = []
    order = [s.name for s in runner.stages]
    for st in steps:
        if st.get("only"):
            names += st["only"]
        elif st.get("until"):
            names += order[:order.index(st["until"]) + 1]
        else:
            return None
    return names


@app.command()
def run(path: Path = typer.Argument(..., help="incident folder"),
        only: Optional[list[str]] = typer.Option(None, "--only", help="run only this stage (repeatable)"),
        force: bool = typer.Option(False, "--force", help="run stages even if their inputs did not change"),
        jobs: Optional[int] = typer.Option(None, "--jobs", "-j", min=1,
                                           help="stages run at once where one does not read another's files (the "
                                                "export beside the render); default 2 on two or more CPUs, 1 "
                                                "runs them one after another")) -> None:
    """Run every stage in order, skipping those whose inputs did not change."""
    _execute(path, only=only, force=force, jobs=jobs)


def _stage_command(name: str, description: str) -> None:
    def command(path: Path = typer.Argument(..., help="incident folder"),
                force: bool = typer.Option(False, "--force", help=f"run {name} even if its inputs did not change")
                ) -> None:
        from .pipeline import STAGES

        names = [s.name for s in STAGES]
        before = names[names.index(name) - 1] if names.index(name) > 0 else None
        steps = ([{"until": before}] if before else []) + [{"only": [name], "force": force}]
        _execute(path, steps=steps)

    command.__doc__ = f"Run the {name} stage ({description}), and the stages before it that are not done."
    app.command(name=name)(command)
    _RUNS_STAGES.add(name)


def _print_outputs(project, statuses) -> None:
    out.print(f"incident {project.root}")
    for st in statuses:
        if st.status == "done" and st.record:
            files = ", ".join(o["path"] for k, o in st.record["outputs"].items() if k != "stats")
            out.print(f"  {st.name:<10} done     {files}")
        else:
            out.print(f"  {st.name:<10} {st.status:<8} {st.reason}")


@app.command()
def status(path: Path = typer.Argument(..., help="incident folder")) -> None:
    """Show which stages are done, stale, failed or not run."""
    from rich.table import Table

    project, runner = _runner(path)
    table = Table(title=f"{project.settings.incident.name} ({project.root})")
    for col in ("stage", "status", "last run (UTC)", "time (s)", "note"):
        table.add_column(col)
    for st in runner.status():
        rec = st.record or {}
        table.add_row(st.name, st.status, rec.get("started_utc", ""), str(rec.get("duration_s", "")), st.reason)
    out.print(table)


@app.command()
def types(project: Optional[Path] = typer.Option(None, help="also list an incident's own types"),
          check: bool = typer.Option(False, "--check", help="also build every model and check it (marked points "
                                                           "given by xyz on its surface, a mesh type's file)")
          ) -> None:
    """List the rolling-stock types (carriage models) the workbench knows."""
    from rich.table import Table

    from .rolling_stock import load_library, load_specs

    extra = [project / "rolling_stock"] if project and (project / "rolling_stock").is_dir() else []
    specs = load_specs(extra_dirs=extra)  # every file read and its keys checked
    if check:
        load_library(extra_dirs=extra)
    table = Table(title="rolling stock" + (" (models built and checked)" if check else ""))
    for col in ("id", "name", "length over couplers (m)", "marked points", "file"):
        table.add_column(col)
    for tid, (spec, path) in sorted(specs.items()):
        table.add_row(tid, spec.name, f"{spec.dimensions.length_over_couplers_m:.2f}", str(len(spec.marked_points)),
                      str(path))
    out.print(table)


@app.command()
def view(path: Path = typer.Argument(..., help="incident folder (its solve must have run)"),
         screenshot: Optional[Path] = typer.Option(None, help="draw one frame, save it as PNG and exit"),
         select: Optional[str] = typer.Option(None, help="car number to select at start"),
         width: int = typer.Option(1280, min=320, max=7680), height: int = typer.Option(800, min=240, max=4320)
         ) -> None:
    """Open the 3D viewer: orbit the scene, toggle layers, pick a carriage to see its numbers (needs a display;
    use `xvfb-run -a workbench view ...` on a machine without one)."""
    from .viewer.app import view as open_view

    shot = open_view(path, screenshot=screenshot, select=select, width=width, height=height)
    if shot is not None:
        out.print(f"screenshot {shot}")


@app.command()
def pick(path: Path = typer.Argument(..., help="incident folder"),
         port: int = typer.Option(8765, min=1024, max=65535, help="local port of the picker page"),
         no_browser: bool = typer.Option(False, "--no-browser", help="do not open a browser; print the address")
         ) -> None:
    """Pick marked points by hand (and review the automatic ones) in a local web page: the photo beside the
    carriage model; saves the incident's correspondences.json (a manual point overrides an automatic one; a
    rejected automatic one is dropped)."""
    from .picker import serve

    serve(path, host="127.0.0.1", port=port, open_browser=not no_browser)


@app.command()
def calibrate(images_dir: Path = typer.Argument(..., help="folder of chessboard photos"),
              out_path: Path = typer.Option(Path("camera_profile.json"), "--out", help="camera profile to write"),
              pattern: str = typer.Option("9x6", help="inner corners per row x per column, e.g. 9x6"),
              square_mm: float = typer.Option(25.0, "--square-mm", help="side of one square, millimetres"),
              glob: str = typer.Option("*", help="which photos of the folder, e.g. 'left*.jpg'"),
              fix_k3: bool = typer.Option(False, "--fix-k3", help="hold k3 at 0 (lenses with little distortion)"),
              max_view_rms_px: Optional[float] = typer.Option(None, "--max-view-rms-px",
                                                              help="drop photos whose RMS exceeds this, refit"),
              sensor_width_mm: Optional[float] = typer.Option(None, "--sensor-width-mm")) -> None:
    """Calibrate a camera from chessboard photos and write a camera profile that incidents reuse."""
    from .intrinsics.calibrate import run_calibrate

    st = run_calibrate(images_dir, out_path, pattern=pattern, square_mm=square_mm, fix_k3=fix_k3,
                       max_view_rms_px=max_view_rms_px, sensor_width_mm=sensor_width_mm, glob=glob)
    out.print(f"wrote {out_path}: {st['n_used']} of {st['n_images']} photos used, RMS {st['rms_px']:.3f} px")
    for r in st.get("rejected", []):
        out.print(f"  not used: {r}")


@app.command(name="type-fit")
def type_fit(path: Path = typer.Argument(..., help="a folder of photos of intact cars of one type, picked by hand "
                                              "(an incident folder: project.toml, photos, correspondences.json)"),
             free: str = typer.Option(..., help="the dimensions to measure, comma-separated, e.g. "
                                                "profile.eave_height_m,front.nose_base_height_m"),
             type_id: Optional[str] = typer.Option(None, "--type", help="the type to fit (default: the consist's)"),
             out_path: Optional[Path] = typer.Option(None, "--out", help="write the fit as JSON here")) -> None:
    """Measure a carriage type's estimated dimensions from photos of intact cars of its class: every photo its
    own focal, every car its own pose, the chosen dimensions shared (docs/rolling_stock.md)."""
    from .core.io import atomic_write_json
    from .project import Project
    from .solve.type_fit import fit_type_dimensions, project_picks

    ctype, picks = project_picks(Project(path), type_id)
    fit = fit_type_dimensions(ctype, picks, [k.strip() for k in free.split(",") if k.strip()])
    out.print(f"{fit.type_id}: {fit.n_picks} picks on {len(fit.focal_px)} photos, RMS {fit.rms_px:.2f} px "
              f"(pixel sigma {fit.sigma_px:.2f} px, {fit.dof} degrees of freedom)")
    for k, v in fit.values.items():
        out.print(f"  {k:<30} {v:7.3f} m  ± {fit.sigmas[k]:.3f} (1 sigma; the type file has {fit.before[k]:.3f})")
    for v, f in fit.focal_px.items():
        out.print(f"  {v}: focal {f:.0f} px, {fit.hfov_deg[v]:.1f} deg horizontal")
    if out_path is not None:
        atomic_write_json(out_path, fit.to_json())
        out.print(f"wrote {out_path}")


@app.command(name="control-points")
def control_points(path: Path = typer.Argument(..., help="synthetic incident folder"),
                   force: bool = typer.Option(False, "--force", help="replace an existing control_points.json"),
                   track_picks: bool = typer.Option(False, "--track-picks",
                                                    help="also the rails' true pixels in the panorama's photos "
                                                         "(track picks, docs/gis.md)")
                   ) -> None:
    """Write control_points.json for a synthetic incident: surveyed landmarks and their pixels, from its truth
    (`workbench synth` does this too)."""
    from .synth.control_points import write_control_points

    out.print(f"wrote {write_control_points(path, force=force, track_picks=track_picks)}")


def _register_stage_commands() -> None:
    from .pipeline import STAGES  # the registry only: no stage's code is imported

    for spec in STAGES:
        if spec.name not in ("inputs",) and spec.name not in {c.name for c in app.registered_commands}:
            _stage_command(spec.name, spec.description)


_register_stage_commands()


def _error(message: str, limit: int = 2000) -> None:
    """One line on stderr: ``error: message`` (cut to ``limit`` characters; never parsed as markup)."""
    from rich.text import Text

    message = " ".join(str(message).split())
    if len(message) > limit:
        message = message[:limit] + f"... ({len(message) - limit} more characters)"
    console.print(Text.assemble(("error:", "red"), " ", message), soft_wrap=True)


def single_threaded_blas() -> None:
    """One BLAS thread unless the user sets ``OPENBLAS_NUM_THREADS``: the workbench's linear algebra is many small
    matrices (2x2 to a few hundred rows), where OpenBLAS's threads only synchronise, and on a busy 2-core machine
    they spin: the terrain stage's Delaunay refinement took 90-112 s at load 7 with them, 1.9 s without
    (docs/performance.md). Must run before numpy is imported (the CLI imports it only inside commands)."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def no_pydantic_plugins() -> None:
    """Pydantic's plugins not looked for unless the user sets ``PYDANTIC_DISABLE_PLUGINS`` (to an empty value: every
    installed plugin; see pydantic's documentation): the workbench's models (settings, rolling-stock types) use
    none, and looking for them reads every installed package's entry points, 5-8 ms of CPU before a stage command
    starts its work. Must run before the settings' models are built."""
    os.environ.setdefault("PYDANTIC_DISABLE_PLUGINS", "__all__")


MALLOC_MMAP_BYTES = 2**31 - 1  # blocks up to this size from the heap (mallopt's value is a C int)


def _freed_memory_kept() -> None:
    """Large blocks taken from and kept in the process's heap (glibc ``mallopt``: ``M_MMAP_THRESHOLD`` 2 GiB,
    ``M_TRIM_THRESHOLD`` -1: never trimmed) instead of mapped for each allocation and unmapped when freed. SIFT on
    an upsampled photo allocates and frees about 3 GB of images; with fresh pages each time the kernel faulted them
    in and zeroed them again for every photo, 1.2-1.6 s of system time each (docs/performance.md, seventh pass);
    kept, a process's next photo reuses them. Set before the stages fork their workers, which inherit it. The
    process keeps its peak heap until it ends (a command's process ends with the command). Nothing where the C
    library is not glibc, or where the user tunes its allocator (``GLIBC_TUNABLES``, ``MALLOC_MMAP_THRESHOLD_``,
    ``MALLOC_TRIM_THRESHOLD_``)."""
    if any(k in os.environ for k in ("GLIBC_TUNABLES", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")):
        return
    try:
        import ctypes

        libc = ctypes.CDLL(None)
        if not hasattr(libc, "gnu_get_libc_version") or not hasattr(libc, "mallopt"):
            return
        m_trim_threshold, m_mmap_threshold = -1, -3  # glibc's malloc.h
        libc.mallopt(m_mmap_threshold, MALLOC_MMAP_BYTES)
        # mallopt(3): -1 disables trimming (with a limit of 2 GiB, SIFT's ~3 GB went back after every photo)
        libc.mallopt(m_trim_threshold, -1)
    except (OSError, AttributeError):  # no C library to ask: the allocator's defaults
        pass


def _no_collection_at_exit() -> None:
    """The objects of a process about to end moved out of the garbage collector's reach (``gc.freeze``): the
    interpreter's collections at exit walked every one of them, 0.1-0.4 s after a `workbench stitch` (NumPy,
    OpenCV, SciPy loaded; docs/performance.md). The memory goes back with the process; the workbench closes its
    files itself, and the ``atexit`` handlers still run."""
    gc.freeze()


def main(argv: list[str] | None = None) -> None:
    """The ``workbench`` entry point: every error a user can cause is one line on stderr and exit status 2.
    ``argv`` None: the process's own command line, and the process ends with the command."""
    if argv is None:
        _freed_memory_kept()
        _pause_collection()
        _head_start(sys.argv[1:])
    try:
        _run_command(argv)
    except SystemExit as exc:
        if argv is None:
            _end_process(exc.code)
        raise
    finally:
        if argv is None:
            _no_collection_at_exit()
    if argv is None:
        _end_process(0)


def _end_process(code) -> None:
    """End the process with the command's exit status (``code`` as ``SystemExit``'s), as the interpreter does but
    for its teardown of every module and object (15-30 ms after a `workbench stitch`: docs/performance.md, ninth
    pass): the exit handlers run (``atexit``), the standard streams are flushed, ``os._exit``. Threads still running
    (early work a failed command did not take) are not waited for. Without ``atexit._run_exitfuncs``: nothing."""
    run_handlers = getattr(atexit, "_run_exitfuncs", None)
    if run_handlers is None:
        return
    status = 0 if code is None else code if isinstance(code, int) else 1
    if not isinstance(code, (int, type(None))):  # (as the interpreter: the message on stderr, status 1)
        print(code, file=sys.stderr)
    run_handlers()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, ValueError, OSError):  # a stream replaced, closed or gone: nothing left to flush
            pass
    os._exit(status & 0xFF)


_VERBOSE = ("-v", "-vv", "-vvv", "--verbose")


def _head_start(args: list[str]) -> None:
    """``workbench [-v] stitch PATH [--force]``: the panorama's photos described (and matched) on two threads from
    the process's start (:func:`workbench.stitch.stage.head_start`, from the photo folder and camera source as
    written in ``project.toml``), while this thread parses the arguments, loads the settings' models and validates
    the settings (pydantic, pyproj: about 0.15 s); OpenCV releases the interpreter. The stage takes the work only
    where the validated settings give the same photos and options (else it is dropped, and any error is the
    command's to report, as without the head start). Nothing for any other command line, where a stage up to the
    stitch may run in a forked process (beside another, or ahead) or start other early work (threads only after
    forks), or where the stitch is recorded done and not forced (the runner decides whether it runs)."""
    words = [a for a in args if a not in _VERBOSE]
    if words[:1] != ["stitch"] or any(w.startswith("-") and w != "--force" for w in words[1:]):
        return
    paths = [w for w in words[1:] if w != "--force"]
    if len(paths) != 1 or len(words) > 3:
        return
    force = "--force" in words
    try:
        from .pipeline import STAGES

        upto = STAGES[:[s.name for s in STAGES].index("stitch") + 1]
        if any(s.runs_beside or getattr(s, "ahead", None) or (s.prefetch and s.name != "stitch") for s in upto):
            return
        from .project import Project

        project = Project(paths[0])
        if not force and project.recorded_status("stitch") == "done":
            return
        single_threaded_blas()  # (before NumPy is loaded)
        from .stitch.stage import head_start

        head_start(project)
    except Exception as exc:  # noqa: BLE001 - only a head start: the command does the work and reports its errors
        logging.getLogger(__name__).debug("no head start: %s: %s", type(exc).__name__, exc)


def _run_command(argv: list[str] | None) -> None:
    single_threaded_blas()
    no_pydantic_plugins()
    try:
        result = app(args=argv, standalone_mode=False)
    except WorkbenchError as exc:
        _error(str(exc))
        sys.exit(2)
    except (typer.Abort, KeyboardInterrupt):
        console.print("aborted")
        sys.exit(130)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.TyperException as exc:  # usage errors: no or unknown command, bad option or value
        if type(exc).__name__ == "NoArgsIsHelpError":  # `workbench` alone: the help, as a usage error
            out.print(exc.format_message())
            sys.exit(2)
        ctx = getattr(exc, "ctx", None)
        where = f" (see `{ctx.command_path} --help`)" if ctx is not None else " (see `workbench --help`)"
        _error(exc.format_message() + where)
        sys.exit(getattr(exc, "exit_code", 2) or 2)
    except OSError as exc:  # a folder that cannot be written, a full disk, ...
        _error(f"{exc.filename or ''}: {exc.strerror or exc}; check that the folder exists, is writable and has "
               f"free space, then run the command again (finished stages are kept)")
        sys.exit(2)
    if isinstance(result, int) and result:
        sys.exit(result)


if __name__ == "__main__":
    main()
