"""The stages of ``workbench run``, in order: the registry.

Each stage is declared here (name, the files it reads, the settings sections it depends on, when it applies)
and its code, a plain function ``(project, progress) -> StageResult`` in its own module, is imported only when
the stage runs. The runner handles hashing, skipping, timing and the record in ``out/state.json``.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

from .core.layout import LIBRARY_TYPES_DIR
from .core.stage_api import Progress, StageResult
from .errors import InputError
from .runner import StageSpec

if TYPE_CHECKING:  # stages are handed the Project; the registry itself loads nothing (a CLI that starts at once)
    from .project import Project

log = logging.getLogger(__name__)

MAX_PIXELS = 120_000_000  # larger photos are refused as decompression bombs (phones take 108 and 200 MP: 200 is)


# ---------------------------------------------------------------------------------------------------
# inputs: check everything the later stages will read, and record it
# ---------------------------------------------------------------------------------------------------
def _inputs_files(project: Project) -> dict[str, Path]:
    files = {"settings": project.settings_path}
    for p in project.photo_paths_if_any():
        files[f"photo:{p.name}"] = p
    cam = project.settings.camera
    if cam.profile:
        files["camera_profile"] = project.path(cam.profile)
    files.update(_rolling_stock_files(project))
    return files


def read_photo_info(path: Path) -> dict:
    """Size and EXIF focal of a photo; :class:`InputError` naming the file if it is corrupt or too large."""
    from PIL import Image, ImageFile, UnidentifiedImageError

    too_big = (f"{path}: larger than the {MAX_PIXELS // 1_000_000} MP limit (a decompression bomb, or a photo "
               f"to downscale first)")
    try:
        with warnings.catch_warnings():
            # PIL's own bomb check (89 MP) would refuse a 100 MP phone photo: ours is MAX_PIXELS, from the header
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            limit, Image.MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS, MAX_PIXELS
            try:
                im = Image.open(path)
            finally:
                Image.MAX_IMAGE_PIXELS = limit
            with im:
                w, h = im.size
                if w * h > MAX_PIXELS:
                    raise InputError(f"{too_big}: {w}x{h} pixels")
                if im.format in ("JPEG", "MPO"):
                    # libjpeg's 1/8 scale: every entropy-coded segment is still decoded (only the inverse DCT
                    # is cut to one coefficient a block), so a truncated or corrupt stream fails as in a full
                    # decode, at about 40 % of its CPU (tests/test_pipeline_photos.py)
                    im.draft(im.mode, (max(1, w // 8), max(1, h // 8)))
                # a truncated file fails in load() unless some library has told PIL to accept one, process-wide
                # (WeasyPrint does when it is imported: the report's), so the flag is held off for this decode
                lenient, ImageFile.LOAD_TRUNCATED_IMAGES = ImageFile.LOAD_TRUNCATED_IMAGES, False
                try:
                    im.load()  # decodes the whole stream: a truncated file fails here
                finally:
                    ImageFile.LOAD_TRUNCATED_IMAGES = lenient
    except InputError:
        raise
    except Image.DecompressionBombError:  # more than twice the limit: PIL refuses before reading the size to us
        raise InputError(too_big) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError,
            Image.DecompressionBombWarning) as exc:
        raise InputError(f"{path}: cannot read this photo ({exc}); replace it with an intact copy or remove it "
                         f"from the folder") from None
    from .files.exif import exif_focal_prior

    with warnings.catch_warnings():  # the size is checked above; the EXIF reader opens it with PIL's own limit
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        prior = exif_focal_prior(path)
    focal_px = None if prior is None else prior.focal_px  # (what read_focal_px gives: the tags read once)
    return {"width": w, "height": h, "exif_focal_px": focal_px,
            "exif_prior": prior.to_dict() if prior is not None else None}


def run_inputs(project: Project, progress: Progress) -> StageResult:
    s = project.settings
    types = project.carriage_types()
    photos = project.photo_paths_if_any()
    infos = {}
    for i, p in enumerate(photos):
        progress(i / max(len(photos), 1), p.name)
        infos[project.relative(p)] = read_photo_info(p)
    profile = None
    if s.camera.profile:
        pf = project.require_file(s.camera.profile, "camera.profile")
        profile = project.read_json(pf)
        if "intrinsics" not in profile:
            raise InputError(f"{pf}: no 'intrinsics' object; see docs/formats.md (camera_profile.json)")
    consist = []
    for car in s.consist:
        ct = types[car.number]
        consist.append({"number": car.number, "type": ct.id, "name": ct.name, "length_m": ct.length_m,
                        "marked_points": list(ct.marked_points),
                        "coupling_to_next": car.coupling_to_next.value if car.coupling_to_next else None})
    chains = 1 + sum(1 for c in s.consist if c.coupling_to_next and c.coupling_to_next.value == "broken")
    stats = {
        "photos": infos, "n_photos": len(photos), "camera_source": s.camera.source.value,
        "camera_profile": s.camera.profile, "consist": consist, "n_carriages": len(consist), "n_chains": chains,
    }
    path = project.write_json(project.stage_dir("inputs") / "inputs.json", stats)
    return StageResult(outputs={"inputs": path}, stats={"n_photos": len(photos), "n_carriages": len(consist),
                                                         "n_chains": chains, "camera_source": s.camera.source.value})


# ---------------------------------------------------------------------------------------------------
# The stages' input files: what each stage reads, for the runner's hashes (every path from the Project)
# ---------------------------------------------------------------------------------------------------
def _rolling_stock_files(project: Project) -> dict[str, Path]:
    """The shipped type files of the consist's types, the incident's own type files, and the files a mesh type's
    ``[mesh] file`` names (with whatever else its folder holds: a glTF's buffers and textures), so a changed
    type or CAD export makes the stages stale."""
    import tomllib

    files = {}
    for tid in sorted({str(c.type).strip().lower() for c in project.settings.consist}):
        shipped = LIBRARY_TYPES_DIR / f"{tid}.toml"
        if shipped.is_file():
            files[f"library:{shipped.name}"] = shipped
    d = project.rolling_stock_dir
    if not d.is_dir():
        return files
    for t in sorted(d.glob("*.toml")):
        files[f"rolling_stock:{t.name}"] = t
        try:
            mesh = tomllib.loads(t.read_text(encoding="utf-8")).get("mesh")
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
            continue  # the type loader names the file and the error
        if isinstance(mesh, dict) and isinstance(mesh.get("file"), str):
            m = (t.parent / mesh["file"]).resolve()
            for f in sorted(m.parent.iterdir()) if m.parent.is_dir() else []:
                if f.is_file() and f.suffix.lower() != ".toml":
                    files[f"rolling_stock:{t.stem}:{f.name}"] = f
    return files


def _dem_files(project: Project) -> dict[str, Path]:
    paths = project.dem_paths()
    return {"dem": paths[0]} if len(paths) == 1 else {f"dem:{p.name}": p for p in paths}


def _setting_file(project: Project, name: str, key: str) -> dict[str, Path]:
    """``{name: path}`` of the file that setting ``key`` (``section.field``) names, which must exist; ``{}`` when
    the setting is empty."""
    section, field = key.split(".")
    rel = getattr(getattr(project.settings, section), field)
    return {name: project.require_file(rel, key)} if rel else {}


def _railway_files(project: Project) -> dict[str, Path]:
    """The railway layer, which the map, the report's track table and the GeoJSON export read."""
    return _setting_file(project, "railways", "terrain.railways")


def _terrain_inputs(project: Project) -> dict[str, Path]:
    return {**_dem_files(project), **_setting_file(project, "buildings", "terrain.buildings")}


def _photo_files(project: Project) -> dict[str, Path]:
    return {f"photo:{p.name}": p for p in project.photo_paths()}


def _n_photos(project: Project) -> int:
    try:
        return len(project.photo_paths())
    except InputError:
        return 0


def _stitch_applies(project: Project) -> bool:
    return project.settings.camera.source.value != "sfm" and _n_photos(project) >= 2


def _stitch_inputs(project: Project) -> dict[str, Path]:
    files = _photo_files(project)
    cam = project.settings.camera
    if cam.source.value == "calibrated" and cam.profile:
        files["camera_profile"] = project.path(cam.profile)
    return files


def _sfm_inputs(project: Project) -> dict[str, Path]:
    return {**_photo_files(project), **_setting_file(project, "camera_profile", "camera.profile")}


def _has_track_picks(path: Path) -> bool:
    """Whether a control-points file has picks on the track (then georef reads the railway layer and the DEM
    its heights may come from); a file that does not parse: no (its reader names the error)."""
    import json

    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(doc, dict) and bool(doc.get("track_picks"))


def _georef_inputs(project: Project) -> dict[str, Path]:
    files: dict[str, Path] = {}
    route = project.georef_route()
    if route == "known":
        files["cameras"] = project.own_cameras_path
    if project.control_points_path.is_file():
        files["control_points"] = project.control_points_path
        if _has_track_picks(project.control_points_path):
            files.update(_railway_files(project))
            files.update(_dem_files(project))
    if route == "panorama":
        p = project.panorama_model_path
        if p.is_file():
            files["panorama_model"] = p
    elif route == "multiview":
        p = project.reconstruction_path
        if p.is_file():
            files["reconstruction"] = p
    elif route == "relative":
        files["photos"] = project.photo_paths()[0]
        p = project.panorama_model_path
        if p.is_file():
            files["panorama_model"] = p
    elif route == "single":
        files["photo"] = project.photo_paths()[0]
        if project.settings.camera.profile:
            prof = project.path(project.settings.camera.profile)
            if prof.is_file():
                files["camera_profile"] = prof
    return files


def _georef_applies(project: Project) -> bool:
    """Known cameras, control points, no survey at all (the relative route), or (multiview) an SfM model that the
    photos' GPS can place."""
    if project.own_cameras_path.is_file() or project.control_points_path.is_file():
        return True
    if project.georef_route() == "relative":
        return True
    return project.georef_route() == "multiview" and project.reconstruction_path.is_file()


def _correspond_inputs(project: Project) -> dict[str, Path]:
    files = _photo_files(project)
    if project.manual_picks_path.is_file():
        files["manual"] = project.manual_picks_path
    cams = project.cameras_path()
    if cams is not None:
        files["cameras"] = cams
    if project.settings.camera.profile:
        files["camera_profile"] = project.path(project.settings.camera.profile)
    files.update(_rolling_stock_files(project))
    pano = project.stage_dir("stitch") / "panorama.jpg"
    if pano.is_file():
        files["panorama"] = pano
    files.update(_dem_files(project))  # the pose search's ground
    return files


def _panorama_model_path(project: Project, cameras: Path | None) -> Path | None:
    """The panorama model a ``cameras.json`` refers to (its ``panorama.model``), if any."""
    if cameras is None:
        return None
    try:
        doc = project.read_json(cameras)
    except InputError:
        return None
    pano = doc.get("panorama") if isinstance(doc, dict) else None
    if isinstance(pano, dict) and pano.get("model"):
        return project.path(pano["model"])
    return None


def _solve_inputs(project: Project) -> dict[str, Path]:
    files: dict[str, Path] = {}
    cams = project.cameras_path()
    if cams is not None:
        files["cameras"] = cams
    corr = project.correspondences_path()
    if corr is not None:
        files["correspondences"] = corr
    pano = _panorama_model_path(project, cams)
    if pano is not None:
        files["panorama_model"] = pano
    files.update(_dem_files(project))
    files.update(_rolling_stock_files(project))  # the models: marked points, bounds, the surface that settles
    if any(c.on_track for c in project.settings.consist):  # the line the carriages on the rails keep to
        files.update(_setting_file(project, "railways", "terrain.railways"))
    return files


def _solve_applies(project: Project) -> bool:
    return project.correspondences_path() is not None or project.cameras_path() is not None


def _export_inputs(project: Project) -> dict[str, Path]:
    files = {"solution": project.solution_path}
    for name in ("terrain.ply", "buildings.ply"):
        if (project.stage_dir("terrain") / name).is_file():
            files[name.replace(".ply", "_mesh")] = project.stage_dir("terrain") / name
    if project.settings.terrain.dem:
        ortho = project.orthophoto_path()
        if ortho is not None:
            files["orthophoto"] = ortho
    files.update(_rolling_stock_files(project))
    files.update(_railway_files(project))
    return files


def scene_input_files(project: Project) -> dict[str, Path]:
    """The files the scene of renders, report, exports and viewer is read from (solution, cameras, terrain)."""
    files: dict[str, Path] = {"solution": project.require_solution("render stage")}
    cams = project.cameras_path()
    if cams is not None:
        files["cameras"] = cams
    for name in ("terrain.ply", "buildings.ply"):
        p = project.stage_dir("terrain") / name
        if p.is_file():
            files[f"terrain:{name}"] = p
    ortho = project.orthophoto_path()
    if ortho is not None and project.settings.terrain.dem:
        files["ortho"] = ortho
        for i, d in enumerate(project.dem_paths()):
            files["dem" if i == 0 else f"dem:{d.name}"] = d
    files.update(_railway_files(project))
    return files


def _report_inputs(project: Project) -> dict[str, Path]:
    renders = project.stage_dir("render") / "renders.json"
    if not renders.is_file():
        raise InputError(f"{renders}: not found; the report needs the 'render' stage's output, and the 'render' "
                         f"stage has not run for this incident. Run `workbench run {project.root}` (or `--only "
                         f"render`)")
    files = {"solution": project.require_solution("report"), "renders": renders}
    cams = project.cameras_path()
    if cams is not None:
        files["cameras"] = cams
    files.update(_railway_files(project))
    # The stages' stats.json files are read but not hashed: they hold run times, which change on every run (and
    # stages after the report, such as export, would make it stale forever). A new solution reaches the report
    # through the solution's hash and the render stage's outputs.
    return files


# The settings the terrain model is built from (Project.terrain_model), which the pose search and the
# solve read: changing the mesh's simplification, the buildings or the orthophoto re-runs neither
TERRAIN_MODEL_KEYS = ("terrain.dem", "terrain.aoi_radius_m", "terrain.dem_vertical_accuracy_m")


# ---------------------------------------------------------------------------------------------------
# The registry. A stage's code is named "module:function" and imported only when the stage runs, so
# `workbench --help` and `workbench status` start without loading the pipeline.
# ---------------------------------------------------------------------------------------------------
STAGES: list[StageSpec] = [
    StageSpec("inputs", "check photos, camera profile and consist", run_inputs, inputs=_inputs_files,
              settings_sections=("consist", "camera")),
    StageSpec("terrain", "DEM and buildings to meshes in the scene frame", "workbench.terrain.stage:run_terrain",
              inputs=_terrain_inputs, settings_sections=("location", "terrain"),
              applies=lambda project: project.settings.terrain.dem is not None),
    StageSpec("stitch", "stitch the panorama photos into one panorama with its exact camera model",
              "workbench.stitch.stage:run_stitch", inputs=_stitch_inputs, settings_sections=("camera",),
              depends_on=("inputs",), applies=_stitch_applies, prefetch="workbench.stitch.stage:prefetch"),
    StageSpec("sfm", "multi-view structure from motion (pycolmap): intrinsics and every camera's pose",
              "workbench.intrinsics.stage:run_sfm_stage", inputs=_sfm_inputs, settings_sections=("camera", "sfm"),
              depends_on=("inputs",), applies=lambda project: project.settings.camera.source.value == "sfm"),
    StageSpec("georef", "place the cameras in the scene frame from control points (or known cameras)",
              "workbench.georef.stage:run_georef", inputs=_georef_inputs, settings_sections=("location", "camera", "georef"),
              depends_on=("stitch", "sfm"), applies=_georef_applies),
    StageSpec("correspond", "marked points in the photos: SIFT against each car's livery, plus manual picks",
              "workbench.correspond.stage:run_correspond", inputs=_correspond_inputs,
              settings_sections=("consist", "camera", "location", "correspond", *TERRAIN_MODEL_KEYS),
              depends_on=("inputs",), prefetch="workbench.correspond.stage:prefetch_features",
              applies=lambda project: _n_photos(project) > 0 or not project.photos_optional),
    StageSpec("solve", "every carriage's pose from the marked points (chained least squares, four steps)",
              "workbench.solve.stage:run_solve", inputs=_solve_inputs,
              settings_sections=("consist", "solver", "location", *TERRAIN_MODEL_KEYS),
              depends_on=("inputs", "terrain", "georef", "correspond"), applies=_solve_applies),
    StageSpec("export", "the scene as glTF, GeoJSON, KMZ, CityJSON and 3D Tiles, georeferenced",
              "workbench.export.stage:run_export", inputs=_export_inputs,
              settings_sections=("location", "consist", "terrain"), depends_on=("terrain", "solve"),
              applies=lambda project: project.solution_path.is_file()),
    StageSpec("render", "off-screen renders of the reconstructed scene (overview, map, photo overlays, close-ups, "
              "orbit)", "workbench.report.render_stage:run_render", inputs=scene_input_files,
              settings_sections=("incident", "location", "terrain", "consist"), depends_on=("solve",),
              runs_beside=("export",),  # the export's files are read by neither (the report waits for both)
              # Open3D, the carriages' models, the terrain and its shading: read while the correspond stage runs
              ahead="workbench.report.render_stage:ahead", ahead_from="correspond"),
    StageSpec("report", "incident report (HTML and PDF) from the stages' statistics and renders",
              "workbench.report.report_stage:run_report", inputs=_report_inputs,
              settings_sections=("incident", "location", "consist", "terrain.railways"), depends_on=("render",),
              # WeasyPrint and matplotlib imported on the cores the solve, the export and the render leave idle (the
              # end of the correspond stage is the render's work ahead)
              ahead="workbench.report.report_stage:ahead", ahead_from="solve"),
]
STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)


def stage(name: str) -> StageSpec:
    """The registered stage ``name``."""
    for s in STAGES:
        if s.name == name:
            return s
    raise KeyError(f"no stage {name!r}; the stages are {list(STAGE_NAMES)}")
