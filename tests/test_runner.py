"""The Project object and the runner: records, skipping, staleness, forcing, failures that lose nothing."""

import json
from pathlib import Path

import pytest

from workbench.errors import InputError, StageError
from workbench.project import Project
from workbench.runner import Runner, StageResult, StageSpec


def make_project(tmp_path: Path) -> Project:
    p = Project.create(tmp_path / "inc", lat=40.878, lon=-73.92)
    (p.root / "data.txt").write_text("one")
    return p


def stages(calls: list, fail: dict):
    def first(project, progress):
        calls.append("first")
        text = (project.root / "data.txt").read_text()
        if fail.get("first"):
            raise InputError("data.txt: bad data")
        path = project.write_json(project.stage_dir("first") / "upper.json", {"text": text.upper()})
        return StageResult(outputs={"upper": path}, stats={"chars": len(text)})

    def second(project, progress):
        calls.append("second")
        data = project.read_json(project.stage_dir("first") / "upper.json")
        if fail.get("second"):
            raise ZeroDivisionError("boom")
        path = project.write_json(project.stage_dir("second") / "twice.json", {"text": data["text"] * 2})
        return StageResult(outputs={"twice": path})

    return [
        StageSpec("first", "upper-case", first, inputs=lambda p: {"data": p.root / "data.txt"},
                  settings_sections=("solver",)),
        StageSpec("second", "twice", second, depends_on=("first",)),
    ]


def test_run_skip_stale_force(tmp_path):
    p = make_project(tmp_path)
    calls, fail = [], {}
    r = Runner(p, stages(calls, fail))
    assert [s.status for s in r.status()] == ["not run", "not run"]
    r.run()
    assert calls == ["first", "second"]
    st = p.read_state()
    assert st["first"]["status"] == "done" and "duration_s" in st["first"]
    assert json.loads((p.stage_dir("first") / "stats.json").read_text())["chars"] == 3
    assert [s.status for s in r.status()] == ["done", "done"]
    r.run()
    assert calls == ["first", "second"]  # nothing re-ran
    # input changed -> first is stale, and second runs again because first's outputs changed
    (p.root / "data.txt").write_text("two!")
    assert r.status()[0].status == "stale" and "inputs changed: data" in r.status()[0].reason
    r.run()
    assert calls == ["first", "second", "first", "second"]
    # settings section changed -> stale
    text = p.settings_path.read_text().replace("slack_held_m = 0.05", "slack_held_m = 0.04")
    p.settings_path.write_text(text)
    p.reload()
    assert r.status()[0].status == "stale" and "settings changed" in r.status()[0].reason
    r.run()
    assert calls[-2:] == ["second", "first"]  # first re-ran; its outputs did not change, so second did not
    n = len(calls)
    r.run(force=True, only=["second"])
    assert calls[n:] == ["second"]
    # an output modified by hand -> stale
    (p.stage_dir("second") / "twice.json").write_text("{}")
    assert r.status()[1].status == "stale"


def test_failure_is_recorded_and_keeps_outputs(tmp_path):
    p = make_project(tmp_path)
    calls, fail = [], {}
    r = Runner(p, stages(calls, fail))
    r.run()
    before = (p.stage_dir("first") / "upper.json").read_text()
    (p.root / "data.txt").write_text("changed")
    fail["first"] = True
    with pytest.raises(InputError, match="bad data"):
        r.run()
    st = r.status()
    assert st[0].status == "failed" and "bad data" in st[0].reason
    assert (p.stage_dir("first") / "upper.json").read_text() == before  # nothing lost
    assert p.read_state()["first"]["previous"]["outputs"]["upper"]["path"] == "out/first/upper.json"
    with pytest.raises(StageError, match="needs stage 'first', which is failed"):
        r.run(only=["second"])
    fail["first"] = False
    fail["second"] = True
    with pytest.raises(StageError, match="stage 'second' failed: ZeroDivisionError: boom"):
        r.run()
    assert "traceback" in p.read_state()["second"]


def test_unknown_stage_and_bad_order(tmp_path):
    p = make_project(tmp_path)
    r = Runner(p, stages([], {}))
    with pytest.raises(StageError, match="unknown stage"):
        r.run(only=["nope"])
    s = stages([], {})
    with pytest.raises(ValueError, match="does not run before it"):
        Runner(p, [s[1], s[0]])


def test_project_paths_and_atomic_json(tmp_path):
    p = make_project(tmp_path)
    assert p.path("photos/panorama") == p.root / "photos/panorama"
    assert p.relative(p.root / "out" / "x.json") == "out/x.json"
    with pytest.raises(InputError, match="no photos"):
        p.photo_paths()
    with pytest.raises(InputError, match="not a folder"):
        p.photo_paths("photos/nothing")
    path = p.write_json(p.out_dir / "a.json", {"v": 1})
    with pytest.raises(ValueError):
        p.write_json(path, {"v": float("nan")})  # NaN is refused...
    assert json.loads(path.read_text()) == {"v": 1}  # ...and the earlier file is intact
    assert not [f for f in path.parent.iterdir() if f.name.startswith(".")]  # no temp files left
    with pytest.raises(InputError, match="no such incident folder"):
        Project(tmp_path / "missing")


def test_a_stage_after_a_not_applicable_one_is_done_not_stale(tmp_path):
    p = make_project(tmp_path)
    calls = []

    def later(project, progress):
        calls.append("later")
        return StageResult(outputs={"x": project.write_json(project.stage_dir("later") / "x.json", {})})

    specs = [StageSpec("optional", "never applies", lambda project, progress: None, applies=lambda project: False),
             StageSpec("later", "after it", later, depends_on=("optional",))]
    r = Runner(p, specs)
    r.run()
    assert [s.status for s in r.status()] == ["skipped", "done"]
    r.run()
    assert calls == ["later"]


def test_until_runs_the_stages_up_to_one(tmp_path):
    p = make_project(tmp_path)
    calls = []
    r = Runner(p, stages(calls, {}))
    r.run(until="first")
    assert calls == ["first"]
    with pytest.raises(StageError, match="unknown stage"):
        r.run(until="nope")


def test_a_stage_whose_dependency_is_out_of_date_is_stale_not_done(tmp_path):
    """A run killed after an early stage wrote new outputs leaves the later stages' records saying 'done'; status
    must not show a stage done while one it depends on is not (two levels down too)."""
    p = make_project(tmp_path)
    calls = []
    specs = stages(calls, {})

    def third(project, progress):
        return StageResult(outputs={"three": project.write_json(project.stage_dir("third") / "t.json", {})})

    specs.append(StageSpec("third", "after second", third, depends_on=("second",)))
    r = Runner(p, specs)
    r.run()
    assert [s.status for s in r.status()] == ["done", "done", "done"]
    (p.root / "data.txt").write_text("changed")
    r.run(only=["first"])  # as if the run had been killed here: second and third keep their old records
    st = {s.name: s for s in r.status()}
    assert st["first"].status == "done"
    assert st["second"].status == "stale" and "upstream" in st["second"].reason
    assert st["third"].status == "stale" and "'second'" in st["third"].reason


def test_correspond_and_solve_are_not_rerun_for_settings_they_do_not_read(tmp_path):
    """The terrain mesh's simplification, the buildings and the orthophoto are not read by the pose search or the
    solve: changing them must not re-run those stages (issue 16); the DEM and its extent must."""
    from workbench.pipeline import stage
    from workbench.runner import _settings_hash

    p = make_project(tmp_path)
    text = p.settings_path.read_text()
    p.settings_path.write_text(text.replace("[terrain]", '[terrain]\ndem = "a.tif"\nsimplify_max_error_m = 0.05', 1))
    p.reload()
    hashes = {n: _settings_hash(p, stage(n).settings_sections) for n in ("correspond", "solve", "terrain")}
    p.settings_path.write_text(p.settings_path.read_text().replace("simplify_max_error_m = 0.05",
                                                                   "simplify_max_error_m = 0.2"))
    p.reload()
    for n in ("correspond", "solve"):
        assert _settings_hash(p, stage(n).settings_sections) == hashes[n], n
    assert _settings_hash(p, stage("terrain").settings_sections) != hashes["terrain"]
    p.settings_path.write_text(p.settings_path.read_text().replace('dem = "a.tif"', 'dem = "b.tif"'))
    p.reload()
    for n in ("correspond", "solve", "terrain"):
        assert _settings_hash(p, stage(n).settings_sections) != hashes[n], n
    assert p.settings_section("terrain.dem", "solver") == {"terrain.dem": "b.tif",
                                                          "solver": p.settings.solver.model_dump(mode="json")}


def test_a_changed_library_type_makes_the_solve_stale(tmp_path, monkeypatch):
    """The shipped type files of the consist's types are inputs of the stages that read the models, so an
    updated type (a corrected dimension, a new marked point) makes them stale; a type the consist does not use
    is not an input."""
    import shutil

    from workbench import pipeline
    from workbench.rolling_stock import TYPES_DIR

    lib = tmp_path / "types"
    shutil.copytree(TYPES_DIR, lib)
    monkeypatch.setattr(pipeline, "LIBRARY_TYPES_DIR", lib)
    p = make_project(tmp_path)
    consist = sorted({str(c.type) for c in p.settings.consist})
    assert consist, "the default incident has a consist"
    solve = next(s for s in pipeline.STAGES if s.name == "solve")
    assert {k for k in solve.inputs(p) if k.startswith("library:")} == {f"library:{t}.toml" for t in consist}
    calls = []

    def models(project, progress):  # the solve's model inputs, with a stand-in for its work
        calls.append(1)
        return StageResult(outputs={})

    stage = StageSpec("models", "the solve's models", models,
                      inputs=lambda q: {k: v for k, v in solve.inputs(q).items() if k.startswith("library:")})
    r = Runner(p, [stage])
    r.run()
    assert r.status()[0].status == "done"
    unused = next(f for f in lib.glob("*.toml") if f.stem not in consist)
    unused.write_text(unused.read_text() + "\n# not this incident's\n")
    assert r.status()[0].status == "done"
    f = lib / f"{consist[0]}.toml"
    f.write_text(f.read_text() + "\n# corrected\n")
    st = r.status()[0]
    assert st.status == "stale" and f"library:{consist[0]}.toml" in st.reason, st.reason
    r.run()
    assert len(calls) == 2


def test_track_picks_make_the_railway_layer_and_the_dem_georef_inputs(tmp_path):
    """With track picks in control_points.json, georef reads the railway layer and the DEM (the rails' heights):
    both are its inputs; without track picks neither is."""
    from workbench import pipeline

    p = make_project(tmp_path)
    (p.root / "rails.geojson").write_text('{"type": "FeatureCollection", "features": []}')
    (p.root / "dem.tif").write_bytes(b"")
    text = p.settings_path.read_text()
    assert "[terrain]" in text
    p.settings_path.write_text(text.replace("[terrain]", '[terrain]\nrailways = "rails.geojson"\ndem = "dem.tif"', 1))
    p.reload()
    georef = next(s for s in pipeline.STAGES if s.name == "georef")
    cp = p.root / "control_points.json"
    cp.write_text('{"crs": "EPSG:32618", "points": []}')
    assert not {"railways", "dem"} & set(georef.inputs(p))
    cp.write_text('{"crs": "EPSG:32618", "points": [], "track_picks": [{"photo": "a.jpg", "pixels": [[1, 2]]}]}')
    inputs = georef.inputs(p)
    assert inputs["railways"] == p.root / "rails.geojson" and inputs["dem"] == p.root / "dem.tif"


def beside_stages(fail: dict):
    """first; side (after first); main (after first, declared to run beside side); last (after both). side and main
    each wait for the other's marker file: they pass only when they run at the same time."""
    import os
    import time

    def wait_for(path: Path, what: str) -> None:
        t_end = time.monotonic() + fail.get("wait_s", 10.0)
        while not path.is_file():
            if time.monotonic() > t_end:
                raise StageError(f"{what}: {path} did not appear (the stages did not run at the same time)")
            time.sleep(0.01)

    def first(project, progress):
        return StageResult(outputs={"a": project.write_json(project.stage_dir("first") / "a.json", {"x": 1})})

    def side(project, progress):
        d = project.stage_dir("side")
        d.mkdir(parents=True, exist_ok=True)
        (d / "started").write_text(str(os.getpid()))
        if fail.get("side") == "crash":
            os._exit(3)
        progress(0.5, "half way")
        if fail.get("side"):
            raise InputError("side.txt: bad side")
        wait_for(project.stage_dir("main") / "started", "side")
        return StageResult(outputs={"s": project.write_json(d / "s.json", {"pid": os.getpid()})}, stats={"n": 2})

    def main(project, progress):
        d = project.stage_dir("main")
        d.mkdir(parents=True, exist_ok=True)
        (d / "started").write_text(str(os.getpid()))
        if not fail.get("side"):
            wait_for(project.stage_dir("side") / "started", "main")
        return StageResult(outputs={"m": project.write_json(d / "m.json", {"pid": os.getpid()})})

    def last(project, progress):
        return StageResult(outputs={"l": project.write_json(project.stage_dir("last") / "l.json", {
            "side": project.read_json(project.stage_dir("side") / "s.json")})})

    return [StageSpec("first", "", first), StageSpec("side", "", side, depends_on=("first",)),
            StageSpec("main", "", main, depends_on=("first",), runs_beside=("side",)),
            StageSpec("last", "", last, depends_on=("side", "main"))]


def test_a_stage_runs_in_a_process_beside_the_next_one(tmp_path):
    import os

    p = make_project(tmp_path)
    fail: dict = {}
    events, progress = [], []
    r = Runner(p, beside_stages(fail), jobs=2)
    r.run(progress_factory=lambda spec: lambda f, m="": progress.append((spec.name, f, m)),
          on_event=lambda kind, spec, rec: events.append((kind, spec.name)))
    assert [s.status for s in r.status()] == ["done"] * 4
    side_pid = p.read_json(p.stage_dir("side") / "s.json")["pid"]
    assert side_pid != os.getpid() and p.read_json(p.stage_dir("main") / "m.json")["pid"] == os.getpid()
    assert ("side", 0.5, "half way") in progress  # forwarded from its process
    assert events.index(("done", "side")) < events.index(("start", "last"))  # last waited for side
    assert p.read_json(p.stage_dir("side") / "stats.json")["n"] == 2
    r.run()
    assert [s.status for s in r.status()] == ["done"] * 4 and len(events) == 8  # nothing ran again
    # side fails: main still runs and is recorded; the run raises side's error; last does not run
    (p.root / "data.txt").write_text("changed")
    fail["side"] = True
    with pytest.raises(InputError, match="side.txt: bad side"):
        r.run(force=True)
    st = {s.name: s for s in r.status()}
    assert st["side"].status == "failed" and "bad side" in st["side"].reason
    assert st["main"].status == "done" and st["last"].status == "stale"
    # its process dies: a clear error, recorded
    fail["side"] = "crash"
    with pytest.raises(StageError, match=r"stage 'side': its process ended without a result \(exit code 3"):
        r.run(only=["side", "main"], force=True)
    assert r.status()[1].status == "failed"
    # jobs=1: one after another, in this process (side would wait for main's marker: it fails, and says so)
    fail.clear()
    fail["wait_s"] = 1.0
    for name in ("side", "main"):
        (p.stage_dir(name) / "started").unlink()
    with pytest.raises(StageError, match="did not run at the same time"):
        Runner(p, beside_stages(fail), jobs=1).run(force=True)


def test_runs_beside_is_checked(tmp_path):
    """A declared stage that is not before it in this list (a later one, or one left out, as a test's own stage
    order may) is not run beside: the two run one after another."""
    p = make_project(tmp_path)
    s = beside_stages({})
    r = Runner(p, [*s[:2], StageSpec("main", "", s[2].run, runs_beside=("last", "nowhere")), s[3]])
    assert r._beside["main"] == ()
    with pytest.raises(ValueError, match="jobs"):
        Runner(p, s, jobs=0)


def test_a_stage_that_runs_beside_the_ones_before_it_starts_first(tmp_path):
    """A stage declared to run beside every stage before it (the terrain beside the inputs) is forked before they run
    and keeps running beside the stages after it that declare it; the first stage that does not waits for it."""
    import os

    p = make_project(tmp_path)
    fail: dict = {}
    base = beside_stages(fail)  # first, side, main, last: side and main meet only when run at once
    stages_ = [base[0], StageSpec("side", "", base[1].run, runs_beside=("first",)),
               StageSpec("main", "", base[2].run, depends_on=("first",), runs_beside=("side",)),
               StageSpec("last", "", base[3].run, depends_on=("side", "main"))]
    events = []
    r = Runner(p, stages_, jobs=2)
    r.run(on_event=lambda kind, spec, rec: events.append((kind, spec.name)))
    assert [s.status for s in r.status()] == ["done"] * 4
    assert events[0] == ("start", "side") and events.index(("done", "side")) < events.index(("start", "last"))
    assert p.read_json(p.stage_dir("side") / "s.json")["pid"] != os.getpid()
    assert list(p.read_state()) == ["first", "side", "main", "last"]  # the record in the stages' order


def test_no_stage_is_forked_beside_one_that_does_not_apply(tmp_path):
    """The stage that may run beside the first does not apply (a stitch command on an incident without a DEM): the
    first runs here, not in a process of its own."""
    import os

    p = make_project(tmp_path)

    def first(project, progress):
        return StageResult(outputs={"a": project.write_json(project.stage_dir("first") / "a.json",
                                                            {"pid": os.getpid()})})

    def nothing(project, progress):
        raise AssertionError("does not apply")

    r = Runner(p, [StageSpec("first", "", first), StageSpec("early", "", nothing, runs_beside=("first",),
                                                           applies=lambda project: False),
                   StageSpec("after", "", first, runs_beside=("early",))], jobs=2)
    r.run(until="early")
    assert p.read_json(p.stage_dir("first") / "a.json")["pid"] == os.getpid()
    assert [s.status for s in r.status()] == ["done", "skipped", "not run"]


_AHEAD_DONE: list = []  # what the work ahead did in the process that runs its stage


def _ahead_steps(project):
    """The work ahead of stage 'late' in the test below: two steps, each leaving a marker."""
    import os

    d = project.stage_dir("late")
    d.mkdir(parents=True, exist_ok=True)
    (d / "ahead_1").write_text(str(os.getpid()))
    _AHEAD_DONE.append(1)
    yield
    (d / "ahead_2").write_text(str(os.getpid()))
    _AHEAD_DONE.append(2)


def test_a_stage_starts_its_work_ahead_in_its_own_process(tmp_path, monkeypatch):
    """A stage with work ahead (the render's models while the correspond stage runs): its process is forked when the
    declared earlier stage starts, does that work while that stage runs where a core is idle (the stage waits for its
    marker: it passes only so), and runs the stage itself once its dependencies are done; where no core is idle,
    nothing is done ahead (the stage does it); where the stage will not run, the process ends; with one job nothing
    is forked."""
    import os
    import time

    import workbench.runner as runner_module

    monkeypatch.setattr(runner_module, "AHEAD_IDLE_CORES", 0.0)  # this test's machine may be busy: any is idle
    p = make_project(tmp_path)
    seen: dict = {"wait": True}

    def first(project, progress):
        d = project.stage_dir("first")
        t_end = time.monotonic() + seen.get("wait_s", 10.0)
        while seen["wait"] and not (project.stage_dir("late") / "ahead_2").is_file():  # the work ahead meanwhile
            if time.monotonic() > t_end:
                raise StageError("the work ahead did not run beside the first stage")
            time.sleep(0.01)
        return StageResult(outputs={"a": project.write_json(d / "a.json", {"x": 1})})

    def middle(project, progress):
        if seen.get("fail"):
            raise InputError("middle: bad")
        return StageResult(outputs={"m": project.write_json(project.stage_dir("middle") / "m.json", {
            "x": project.read_json(project.stage_dir("first") / "a.json")["x"] + 1})})

    def late(project, progress):
        progress(0.5, "late half way")
        return StageResult(outputs={"l": project.write_json(project.stage_dir("late") / "l.json", {
            "pid": os.getpid(), "ahead": list(_AHEAD_DONE),
            "m": project.read_json(project.stage_dir("middle") / "m.json")["x"]})})

    def spec_list():
        return [StageSpec("first", "", first), StageSpec("middle", "", middle, depends_on=("first",)),
                StageSpec("late", "", late, depends_on=("middle",), ahead=f"{__name__}:_ahead_steps",
                          ahead_from="first")]

    events, progress = [], []
    r = Runner(p, spec_list(), jobs=2)
    r.run(progress_factory=lambda spec: lambda f, m="": progress.append((spec.name, m)),
          on_event=lambda kind, spec, rec: events.append((kind, spec.name)))
    assert [s.status for s in r.status()] == ["done"] * 3
    out = p.read_json(p.stage_dir("late") / "l.json")
    assert out["pid"] != os.getpid() and out["ahead"] == [1, 2] and out["m"] == 2  # its process, after the ahead
    assert int((p.stage_dir("late") / "ahead_1").read_text()) == out["pid"]
    assert ("late", "late half way") in progress and events[-2:] == [("start", "late"), ("done", "late")]
    assert _AHEAD_DONE == [] and not r._early  # not in the runner's process; nothing left behind
    # the middle stage fails: the process started ahead is stopped (the run does not hang), the late stage not run
    for f in p.stage_dir("late").iterdir():
        f.unlink()
    seen["fail"] = True
    with pytest.raises(InputError, match="middle: bad"):
        r.run(force=True)
    assert [s.status for s in r.status()] == ["done", "failed", "stale"] and not r._early
    assert not (p.stage_dir("late") / "l.json").exists()
    # no core idle: nothing is done ahead; the stage runs in its process at its turn and does the work itself
    monkeypatch.setattr(runner_module, "AHEAD_IDLE_CORES", 1e9)
    seen.update(wait=False, fail=False)
    for f in p.stage_dir("late").iterdir():
        f.unlink()
    r.run(force=True)
    out = p.read_json(p.stage_dir("late") / "l.json")
    assert out["pid"] != os.getpid() and out["ahead"] == [] and out["m"] == 2 and not r._early
    assert not (p.stage_dir("late") / "ahead_1").exists()
    # one job: nothing ahead (the first stage waits for the work ahead in vain)
    seen.update(wait=True, wait_s=0.5)
    for f in p.stage_dir("late").iterdir():
        f.unlink()
    with pytest.raises(StageError, match="did not run beside"):
        Runner(p, spec_list(), jobs=1).run(force=True)
    with pytest.raises(ValueError, match="go together"):
        Runner(p, [StageSpec("first", "", first), StageSpec("late", "", late, ahead="x:y")])
