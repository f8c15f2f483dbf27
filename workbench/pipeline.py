"""The stages of ``workbench run``, in order. Later stages (stitch, solve, render, report, export) plug in here.

Each stage is a plain function ``(project, progress) -> StageResult``; the runner handles hashing,
skipping, timing and the record in ``out/state.json``.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np

from .errors import InputError
from .project import Project
from .runner import Progress, StageResult, StageSpec

log = logging.getLogger(__name__)

MAX_PIXELS = 120_000_000  # refuse decompression bombs (a 24 MP photo has 24 M pixels)


# ---------------------------------------------------------------------------------------------------
# inputs: check everything the later stages will read, and record it
# ---------------------------------------------------------------------------------------------------
def _inputs_files(project: Project) -> dict[str, Path]:
    files = {"settings": project.settings_path}
    for p in project.photo_paths():
        files[f"photo:{p.name}"] = p
    cam = project.settings.camera
    if cam.profile:
        files["camera_profile"] = project.path(cam.profile)
    if project.rolling_stock_dir.is_dir():
        for t in sorted(project.rolling_stock_dir.glob("*.toml")):
            files[f"rolling_stock:{t.name}"] = t
    return files


def read_photo_info(path: Path) -> dict:
    """Size and EXIF focal of a photo; :class:`InputError` naming the file if it is corrupt or too large."""
    from PIL import Image, UnidentifiedImageError

    from .render.exif import read_focal_px

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                w, h = im.size
                if w * h > MAX_PIXELS:
                    raise InputError(f"{path}: {w}x{h} pixels is larger than the {MAX_PIXELS // 1_000_000} MP limit; "
                                     f"downscale the photo")
                im.load()  # decodes fully: a truncated file fails here
    except InputError:
        raise
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError, Image.DecompressionBombError,
            Image.DecompressionBombWarning) as exc:
        raise InputError(f"{path}: cannot read this photo ({exc}); replace it with an intact copy or remove it "
                         f"from the folder") from None
    return {"width": w, "height": h, "exif_focal_px": read_focal_px(path)}


def run_inputs(project: Project, progress: Progress) -> StageResult:
    s = project.settings
    types = project.carriage_types()
    photos = project.photo_paths()
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
# terrain: DEM and buildings to meshes in the scene frame
# ---------------------------------------------------------------------------------------------------
def _terrain_files(project: Project) -> dict[str, Path]:
    t = project.settings.terrain
    files = {"dem": project.require_file(t.dem, "terrain.dem")}
    if t.buildings:
        files["buildings"] = project.require_file(t.buildings, "terrain.buildings")
    return files


def run_terrain(project: Project, progress: Progress) -> StageResult:
    from .synth.buildings import building_meshes, read_buildings_geojson
    from .terrain.dem import TerrainModel

    t = project.settings.terrain
    files = _terrain_files(project)
    progress(0.1, "DEM")
    tm = TerrainModel.from_geotiff(files["dem"], project.frame, aoi_radius_m=t.aoi_radius_m)
    mesh = tm.mesh()
    out = project.stage_dir("terrain")
    terrain_ply = project.write_with(out / "terrain.ply", lambda p: mesh.export(p))
    outputs = {"terrain_mesh": terrain_ply}
    stats = {"dem": project.relative(files["dem"]), "n_vertices": int(len(mesh.vertices)),
             "n_faces": int(len(mesh.faces)), "bounds_enu": np.asarray(tm.bounds_enu).tolist(),
             "height_at_origin_m": float(tm.height_at(np.zeros((1, 2)))[0]),
             "vertical_accuracy_m": t.dem_vertical_accuracy_m}
    if "buildings" in files:
        progress(0.6, "buildings")
        import trimesh

        blds = read_buildings_geojson(files["buildings"])
        meshes = building_meshes(blds, tm, project.frame)
        if meshes:
            merged = trimesh.util.concatenate(meshes)
            outputs["buildings_mesh"] = project.write_with(out / "buildings.ply", lambda p: merged.export(p))
        stats["n_buildings"] = len(blds)
    return StageResult(outputs=outputs, stats=stats)


def _stages() -> list[StageSpec]:
    from .solve.stage import STAGE as SOLVE

    return [SOLVE]


STAGES: list[StageSpec] = [
    StageSpec("inputs", "check photos, camera profile and consist", run_inputs, inputs=_inputs_files,
              settings_sections=("consist", "camera")),
    StageSpec("terrain", "DEM and buildings to meshes in the scene frame", run_terrain, inputs=_terrain_files,
              settings_sections=("location", "terrain"), depends_on=(),
              applies=lambda project: project.settings.terrain.dem is not None),
] + _stages()
