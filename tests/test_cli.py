"""The real CLI entry point on small incidents: bad input gives a one-line error, exit 2, nothing lost."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from workbench.files.exif import write_jpeg

WB = [sys.executable, "-m", "workbench.cli"]
FIRST = ("--only", "inputs", "--only", "terrain")  # noise photos: the later stages rightly refuse them


def wb(*args, cwd=None):
    return subprocess.run([*WB, *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=300)


def small_incident(tmp_path: Path) -> Path:
    root = tmp_path / "inc"
    r = wb("init", root, "--lat", "40.878", "--lon", "-73.9215", "--date", "2013-12-01")
    assert r.returncode == 0, r.stderr
    toml = (root / "project.toml").read_text()
    toml = toml.replace('[[consist]]\nnumber = "1"\ntype = "shoreliner"',
                        '[[consist]]\nnumber = "1"\ntype = "p32ac-dm"\ncoupling_to_next = "held"\n\n'
                        '[[consist]]\nnumber = "2"\ntype = "shoreliner"')
    (root / "project.toml").write_text(toml)
    rng = np.random.default_rng(0)
    for i in range(2):
        img = (rng.uniform(0, 255, (60, 80, 3))).astype(np.uint8)
        write_jpeg(root / "photos/panorama" / f"p{i}.jpg", img, focal_length_mm=20.0, sensor_width_mm=23.5)
    return root


def one_line_error(r, *needles):
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = [line for line in r.stderr.strip().splitlines() if line.startswith("error:")]
    assert len(lines) == 1, r.stderr  # one error line (progress lines of stages that ran may precede it)
    for n in needles:
        assert n in lines[0], (n, lines[0])


def test_run_status_and_skip(tmp_path):
    root = small_incident(tmp_path)
    r = wb("run", root, *FIRST)
    assert r.returncode == 0, r.stderr
    assert "inputs" in r.stdout and "out/inputs/inputs.json" in r.stdout
    data = json.loads((root / "out/inputs/inputs.json").read_text())
    assert data["n_photos"] == 2 and data["n_chains"] == 1
    assert abs(data["photos"]["photos/panorama/p0.jpg"]["exif_focal_px"] - 20.0 / 23.5 * 80) < 0.5
    r = wb("run", root, *FIRST)
    assert "up to date, skipped" in r.stdout + r.stderr
    r = wb("status", root)
    assert r.returncode == 0 and "done" in r.stdout


def test_bad_inputs_fail_cleanly_and_lose_nothing(tmp_path):
    root = small_incident(tmp_path)
    assert wb("run", root, *FIRST).returncode == 0
    good = (root / "out/inputs/inputs.json").read_bytes()
    settings = (root / "project.toml").read_text()

    # a corrupt photo
    (root / "photos/panorama/p1.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    one_line_error(wb("run", root, *FIRST), "p1.jpg", "cannot read this photo")
    assert (root / "out/inputs/inputs.json").read_bytes() == good
    (root / "photos/panorama/p1.jpg").unlink()

    # a typo in the settings
    (root / "project.toml").write_text(settings.replace("estimate_focal", "estimate_focl"))
    one_line_error(wb("run", root, *FIRST), "project.toml", "unknown key 'solver.estimate_focl'")
    # a CRS that is not projected
    (root / "project.toml").write_text(settings.replace('crs = "EPSG:32618"', 'crs = "EPSG:4326"'))
    one_line_error(wb("run", root, *FIRST), "project.toml", "location.crs", "not a projected CRS")
    # an unknown model type
    (root / "project.toml").write_text(settings.replace('type = "shoreliner"', 'type = "shorliner"'))
    one_line_error(wb("run", root, *FIRST), "consist[1].type = 'shorliner'", "shoreliner")
    # an empty consist
    head = settings.split("[[consist]]")[0]
    tail = "[camera]" + settings.split("[camera]")[1]
    (root / "project.toml").write_text("consist = []\n" + head + tail)
    one_line_error(wb("run", root, *FIRST), "consist is empty")
    # an unreadable DEM
    (root / "project.toml").write_text(settings.replace('# dem = "../../terrain/<region>/dem.tif"', 'dem = "dem.tif"'))
    (root / "dem.tif").write_bytes(b"II*\x00garbage")
    one_line_error(wb("run", root, *FIRST), "dem.tif")
    # a missing photo folder
    (root / "project.toml").write_text(settings.replace('photos = "photos/panorama"', 'photos = "photos/none"'))
    one_line_error(wb("run", root, *FIRST), "camera.photos = 'photos/none'")

    # the last good run (one photo, after p1 was removed) is intact; the failed terrain stage wrote nothing
    assert json.loads((root / "out/inputs/inputs.json").read_text())["n_photos"] == 1
    assert not (root / "out/terrain/terrain.ply").exists()
    assert json.loads((root / "out/state.json").read_text())["terrain"]["status"] == "failed"


def test_init_refuses_to_overwrite(tmp_path):
    root = small_incident(tmp_path)
    before = (root / "project.toml").read_text()
    one_line_error(wb("init", root), "already exists")
    assert (root / "project.toml").read_text() == before


def test_types_lists_the_library(tmp_path):
    """`workbench types` lists the files (read and their keys checked, no model built); `--check` builds every
    model and refuses a marked point off its surface, naming the file, the point and its distance."""
    r = wb("types")
    assert r.returncode == 0
    for t in ("shoreliner", "p32ac-dm", "amfleet-i", "acs-64", "dot-111", "meitetsu-3500"):
        assert t in r.stdout
    assert wb("types", "--check").returncode == 0
    from workbench.rolling_stock import TYPES_DIR

    own = tmp_path / "inc" / "rolling_stock"
    own.mkdir(parents=True)
    text = (TYPES_DIR / "keikyu-n1000-m.toml").read_text(encoding="utf-8")
    assert text.count("xyz = [-0.65, 1.40, 0.95]") == 1
    bad = text.replace('id = "keikyu-n1000-m"', 'id = "my-car"').replace("xyz = [-0.65, 1.40, 0.95]",
                                                                          "xyz = [-0.65, 1.10, 2.00]")
    (own / "my-car.toml").write_text(bad, encoding="utf-8")
    r = wb("types", "--project", tmp_path / "inc")
    assert r.returncode == 0 and "my-car" in r.stdout
    one_line_error(wb("types", "--check", "--project", tmp_path / "inc"), "my-car.toml", "xyz", "from the model's surface")


def test_synth_bad_options(tmp_path):
    one_line_error(wb("synth", tmp_path / "x", "--scenario", "nowhere"), "unknown scenario 'nowhere'", "spuyten-duyvil")
    one_line_error(wb("synth", tmp_path / "x", "--cars", "0"), "--cars 0")
    one_line_error(wb("synth", tmp_path / "x", "--terrain-size", "20"), "--terrain-size 20", "100 to 5000 m")


# -- usage errors, console markup, the state file, the folder lock, umask, start-up -------------------------
@pytest.mark.parametrize("args, needle", [
    ((), None),  # no command: the help, as a usage error
    (("bogus",), "No such command 'bogus'"),
    (("status",), "Missing argument"),
    (("run", "--bogus", "x"), "No such option: --bogus"),
    (("pick", ".", "--port", "abc"), "--port"),
    (("pick", ".", "--port", "80"), "--port"),
    (("calibrate", "."), None),
])
def test_usage_errors_are_one_line_and_exit_2(tmp_path, args, needle):
    r = wb(*args, cwd=tmp_path)
    assert "Traceback" not in r.stderr + r.stdout, r.stderr
    assert r.returncode == 2, (r.returncode, r.stderr)
    if args == ():
        assert "Commands:" in r.stdout
    elif needle is not None:
        one_line_error(r, needle)


def test_markup_in_a_path_is_printed_as_it_is(tmp_path):
    d = tmp_path / "[red]inc[bold]"
    d.mkdir()
    r = wb("status", d)
    one_line_error(r, "[red]inc[bold]", "settings file not found")


def test_emoji_codes_in_a_path_are_printed_as_they_are(tmp_path):
    r = wb("init", tmp_path / ":fire:inc:smile:")
    assert r.returncode == 0, r.stderr
    out = r.stdout.replace("\n", "")  # rich wraps a long path at the console's width, anywhere in it
    assert ":fire:inc:smile:" in out and "\N{FIRE}" not in out, r.stdout


def test_collection_paused_while_a_command_starts_and_resumed(tmp_path):
    """The CLI's own process pauses the garbage collector while it starts; every command resumes it (a stage
    command as its first stage starts), and so does a process forked while it is paused."""
    root = small_incident(tmp_path)
    fork = ("import gc, os\nfrom workbench import cli\ncli._pause_collection()\npaused = not gc.isenabled()\n"
            "pid = os.fork()\nif pid == 0:\n    os._exit(0 if gc.isenabled() else 3)\n"
            "child = os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])\ncli._resume_collection()\n"
            "print('PAUSED', paused, 'CHILD', child, 'RESUMED', gc.isenabled(), gc.get_freeze_count() > 0)\n")
    r = subprocess.run([sys.executable, "-c", fork], capture_output=True, text=True, timeout=120)
    assert "PAUSED True CHILD 0 RESUMED True True" in r.stdout, (r.stdout, r.stderr[-2000:])
    # (the process's own command ends the process: the check runs among its exit handlers)
    code = ("import atexit, gc, sys\nfrom workbench.cli import main\nsys.argv = ['workbench', *sys.argv[1:]]\n"
            "atexit.register(lambda: print('COLLECTING', gc.isenabled()))\nmain()\n")
    for args in (["types"], ["run", str(root), *FIRST]):
        r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300)
        assert "COLLECTING True" in r.stdout, (args, r.stdout[-500:], r.stderr[-2000:])


def test_pydantic_plugins_looked_for_only_when_the_user_says(tmp_path):
    """The CLI's settings are validated without reading every installed package's entry points for pydantic plugins,
    unless the user sets PYDANTIC_DISABLE_PLUGINS themselves (empty: every plugin)."""
    root = small_incident(tmp_path)
    code = ("import sys\nimport pydantic.plugin._loader as loader\ncalls = []\nscan = loader.entry_points\n"
            "loader.entry_points = lambda **kw: calls.append(kw) or scan(**kw)\n"
            "from workbench.cli import main\nsys.argv = ['workbench', 'status', sys.argv[1]]\n"
            "import atexit\natexit.register(lambda: print('SCANS', len(calls)))\nmain()\n")
    env = {k: v for k, v in os.environ.items() if k != "PYDANTIC_DISABLE_PLUGINS"}
    for value, want in ((None, "SCANS 0"), ("", "SCANS 1")):
        e = env if value is None else {**env, "PYDANTIC_DISABLE_PLUGINS": value}
        r = subprocess.run([sys.executable, "-c", code, str(root)], capture_output=True, text=True, timeout=120, env=e)
        assert want in r.stdout, (value, r.stdout[-500:], r.stderr[-2000:])


def test_init_with_a_bad_value_writes_nothing(tmp_path):
    root = tmp_path / "new"
    r = wb("init", root, "--crs", "EPSG:4326")
    one_line_error(r, "EPSG:4326", "projected")
    assert not root.exists()
    r = wb("init", root, "--crs", "EPSG:32618")  # the corrected retry is not refused
    assert r.returncode == 0, r.stderr


def test_outputs_follow_the_umask(tmp_path):
    root = small_incident(tmp_path)
    assert (root / "project.toml").stat().st_mode & 0o777 == 0o644  # the test process's umask is 022
    r = wb("run", root, "--only", "inputs")
    assert r.returncode == 0, r.stderr
    for p in (root / "out").rglob("*.json"):
        assert p.stat().st_mode & 0o777 == 0o644, p


def test_corrupt_state_file_is_kept_aside(tmp_path):
    root = small_incident(tmp_path)
    (root / "out").mkdir(exist_ok=True)
    (root / "out" / "state.json").write_text("[1, 2]")
    r = wb("status", root)
    assert r.returncode == 0 and "Traceback" not in r.stderr and "corrupt" in r.stderr
    r = wb("run", root, "--only", "inputs")
    assert r.returncode == 0, r.stderr
    assert (root / "out" / "state.json.corrupt").read_text() == "[1, 2]"
    assert json.loads((root / "out" / "state.json").read_text())["inputs"]["status"] == "done"


def test_read_only_folder_is_one_line_and_loses_nothing(tmp_path):
    import os

    if os.geteuid() == 0:  # root writes anyway: simulate the refusal where every write goes through
        from workbench.core import io

        root = small_incident(tmp_path)
        assert wb("run", root, "--only", "inputs").returncode == 0
        before = (root / "out" / "state.json").read_bytes()
        code = ("import errno, sys, tempfile\n"
                "def refuse(*a, **k): raise PermissionError(errno.EACCES, 'Permission denied')\n"
                "tempfile.mkstemp = refuse\n"
                "from workbench.cli import main\n"
                f"main(['run', {str(root)!r}, '--only', 'inputs', '--force'])\n")
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        one_line_error(r, "cannot write", "Permission denied", "writable")
        assert (root / "out" / "state.json").read_bytes() == before
        assert io is not None
    else:  # pragma: no cover - a non-root user gets the real refusal
        root = small_incident(tmp_path)
        assert wb("run", root, "--only", "inputs").returncode == 0
        os.chmod(root / "out" / "inputs", 0o555)
        try:
            one_line_error(wb("run", root, "--only", "inputs", "--force"), "cannot write", "writable")
        finally:
            os.chmod(root / "out" / "inputs", 0o755)


def test_a_second_run_on_the_same_incident_is_refused(tmp_path):
    from workbench.project import Project

    root = small_incident(tmp_path)
    with Project(root).lock():
        r = wb("run", root, "--only", "inputs")
    one_line_error(r, "another workbench command is running on this incident", f"pid {__import__('os').getpid()}")
    assert wb("run", root, "--only", "inputs").returncode == 0  # released


def test_help_and_status_load_no_stage_code(tmp_path):
    """`--help` and `status` import neither a stage's code nor the heavy libraries (they start at once)."""
    root = small_incident(tmp_path)
    code = ("import sys\nfrom workbench.cli import main\n"
            "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
            "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('scipy', 'trimesh', 'cv2', 'open3d', "
            "'rasterio', 'pycolmap') or m.endswith('.stage') or m.endswith('_stage'))\n"
            "print('HEAVY', heavy)\n")
    for args in (["--help"], ["status", str(root)], ["types"]):
        r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=120)
        assert "HEAVY []" in r.stdout, (args, r.stdout[-500:], r.stderr[-2000:])


def test_the_process_ends_with_the_command_its_exit_handlers_run(tmp_path):
    """The process's own command ends the process (cli._end_process): the exit status is the command's, what it
    printed and what its exit handlers print is flushed, and a thread still running (early work a failed command
    did not take) is not waited for."""
    code = ("import atexit, sys, threading, time\nfrom workbench.cli import main\n"
            "threading.Thread(target=time.sleep, args=(60,)).start()\n"
            "atexit.register(lambda: print('HANDLER', flush=False))\nsys.argv = ['workbench', *sys.argv[1:]]\n"
            "main()\nprint('NOT REACHED')\n")
    for args, status in ((["types"], 0), (["status", str(tmp_path / "none")], 2), (["bogus"], 2)):
        r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=30)
        assert r.returncode == status, (args, r.returncode, r.stderr[-2000:])
        assert r.stdout.rstrip().endswith("HANDLER") and "NOT REACHED" not in r.stdout, (args, r.stdout[-300:])
        assert ("shoreliner" in r.stdout) == (args == ["types"]), r.stdout[-300:]


def test_stage_commands_start_early_work_only_through_the_runner(tmp_path, monkeypatch):
    """A stage command's early work (the panorama's descriptions on threads) is started by a ``Runner.run``, which
    forks what it forks first: never by the CLI before the runner's forks (threads only after forks). With
    ``--force`` on a done stage, by the stage's own step (the runner passes a done stage's by unless forced)."""
    from types import SimpleNamespace

    from workbench import cli

    names = ["inputs", "terrain", "stitch", "correspond", "solve"]

    class Runner:
        stages = [SimpleNamespace(name=n) for n in names]

        def __init__(self, done):
            self.done, self.runs = done, []

        def status(self):
            return [SimpleNamespace(name=n, status="done" if n in self.done else "not run", record=None, reason="")
                    for n in names]

        def prefetch(self, *a, **k):
            raise AssertionError("early work started outside a run, before its forks")

        def run(self, **kw):
            self.runs.append((kw["prefetch"], kw.get("only"), kw.get("until"), kw.get("force", False)))
            return self.status()

    forced = [{"until": "terrain"}, {"only": ["stitch"], "force": True}]
    plain = [{"until": "terrain"}, {"only": ["stitch"], "force": False}]
    for steps, done, expect in (
            (forced, {"inputs", "stitch"}, [["inputs", "terrain"], ["stitch"]]),  # stitched: its own step
            (forced, {"inputs"}, [["inputs", "terrain", "stitch"], False]),  # not yet: with the first, as unforced
            (plain, {"inputs", "stitch"}, [["inputs", "terrain", "stitch"], False]),
            ([{"force": True}], set(names), [None])):  # `workbench run --force`: one step, every stage's
        runner = Runner(done)
        monkeypatch.setattr(cli, "_runner", lambda path, jobs=None, r=runner: (SimpleNamespace(root=tmp_path), r))
        cli._execute(tmp_path, steps=[dict(st) for st in steps])
        assert [p for p, *_ in runner.runs] == expect, (steps, done, runner.runs)
        assert [(o, u, f) for _, o, u, f in runner.runs] == [(st.get("only"), st.get("until"), st.get("force", False))
                                                            for st in steps]


def test_the_stitch_head_start_only_for_a_stitch_to_do(tmp_path, monkeypatch):
    """`workbench [-v] stitch PATH [--force]` starts describing the photos before it parses its arguments
    (cli._head_start): for exactly that command line, and not where the stitch is recorded done unless forced."""
    from workbench import cli
    from workbench.stitch import stage

    root = tmp_path / "inc"
    assert wb("init", root).returncode == 0
    started = []
    monkeypatch.setattr(stage, "head_start", lambda project: started.append(project.root) or True)
    cases = [(["stitch", str(root)], True), (["-v", "stitch", str(root), "--force"], True),
             (["--verbose", "stitch", "--force", str(root)], True), (["stitch"], False),
             (["stitch", str(root), "--help"], False), (["stitch", str(root), str(root)], False),
             (["run", str(root)], False), (["correspond", str(root)], False), (["stitch", str(tmp_path / "no")], False)]
    for force_only in (False, True):
        for args, expect in cases:
            started.clear()
            cli._head_start(args)
            assert started == ([root.resolve()] if expect and (not force_only or "--force" in args) else []), args
        (root / "out" / "state.json").write_text(json.dumps({"stitch": {"status": "done"}}))  # recorded done


def test_a_library_warning_is_one_line(tmp_path):
    """A WorkbenchWarning reaches the user once, as one line (no Python source line), even when the library also
    logs it."""
    script = (
        "import logging, warnings\n"
        "from workbench.cli import _main\n"
        "from workbench.errors import WorkbenchWarning\n"
        "class Odd(WorkbenchWarning): pass\n"
        "_main(0)\n"
        "logging.getLogger('workbench.x').warning('logged and warned')\n"
        "warnings.warn('logged and warned', Odd)\n"
        "warnings.warn('only warned', Odd)\n")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert lines == ["WARNING workbench.x: logged and warned", "WARNING Odd: only warned"], r.stderr


_FAULTS = """
import ctypes, resource, sys
if sys.argv[1] == "kept":
    from workbench.cli import _freed_memory_kept
    _freed_memory_kept()
libc = ctypes.CDLL(None)
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
def touched(n):  # a block as OpenCV allocates an image: malloc, written
    p = libc.malloc(n)
    ctypes.memset(p, 1, n)
    return p
libc.free(touched(64 << 20))  # 64 MB allocated, written and freed
f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
touched(64 << 20)
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_freed_memory_is_reused_without_faulting_it_in_again():
    """A command's process keeps large freed blocks (cli._freed_memory_kept): a second 64 MB block reuses the first's
    pages (16 384 page faults of 4 KiB when it is mapped afresh)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("GLIBC_TUNABLES", "MALLOC_"))}
    n = {mode: int(subprocess.run([sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, env=env,
                                  check=True, cwd=Path(__file__).parent.parent).stdout)
         for mode in ("default", "kept")}
    assert n["default"] > 8000, n
    assert n["kept"] < 1000, n
