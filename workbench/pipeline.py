"""The stages of ``workbench run``, in order. Each later stage lives with its module and is listed in _stages().

Each stage is a plain function ``(project, progress) -> StageResult``; the runner handles hashing,
skipping, timing and the record in ``out/state.json``.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path


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
    from .intrinsics.exif import exif_focal_prior

    prior = exif_focal_prior(path)
    return {"width": w, "height": h, "exif_focal_px": read_focal_px(path),
            "exif_prior": prior.to_dict() if prior is not None else None}


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


def _stages() -> list[StageSpec]:
    """The stages after ``inputs``, in order (each module owns its stage; see docs/pipeline.md)."""
    from .correspond.stage import STAGE as CORRESPOND
    from .export.stage import STAGE as EXPORT
    from .georef.stage import STAGE as GEOREF
    from .intrinsics.stage import STAGE as SFM
    from .report.render_stage import STAGE as RENDER
    from .report.report_stage import STAGE as REPORT
    from .solve.stage import STAGE as SOLVE
    from .stitch.stage import STAGE as STITCH
    from .terrain.stage import STAGE as TERRAIN

    return [TERRAIN, STITCH, SFM, GEOREF, CORRESPOND, SOLVE, EXPORT, RENDER, REPORT]


STAGES: list[StageSpec] = [
    StageSpec("inputs", "check photos, camera profile and consist", run_inputs, inputs=_inputs_files,
              settings_sections=("consist", "camera")),
] + _stages()
