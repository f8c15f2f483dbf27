"""``out/solve/solution.json``: every carriage's pose and uncertainty (format in ``docs/pipeline.md``), the one
reader.

The solve stage writes it; the render stage, the report, the exports and the viewer read it through
:meth:`workbench.project.Project.solution`, which checks it against the incident (its frame and consist).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Collection

import numpy as np

from ..core.frames import SceneFrame, is_rotation
from ..core.io import read_json
from ..errors import InputError

__all__ = ["SolvedCarriage", "Solution", "doubts_of", "parse_solution", "read_solution", "record_floats"]

STATUSES = ("solved", "carried", "left_out")


def record_floats(record: dict, key: str) -> list[float] | None:
    """``record[key]`` as a list of floats, or None when it is absent or not all finite numbers."""
    v = record.get(key)
    if v is None:
        return None
    try:
        a = [float(x) for x in v]
    except (TypeError, ValueError):
        return None
    return a if all(math.isfinite(x) for x in a) else None


@dataclass(frozen=True)
class SolvedCarriage:
    """One carriage of the solution: ``world_from_carriage`` (4, 4) or None (left out), and its whole record
    (intervals, residuals, observations) as written."""

    index: int
    number: str
    status: str
    world_from_carriage: np.ndarray | None
    record: dict = field(compare=False, repr=False)

    @property
    def posed(self) -> bool:
        return self.world_from_carriage is not None

    @property
    def reason(self) -> str:
        return str(self.record.get("reason") or "no pose in the solution")

    def floats(self, key: str) -> list[float] | None:
        """The record's list of numbers under ``key``, or None when it is absent or not all finite numbers."""
        return record_floats(self.record, key)


@dataclass(frozen=True)
class Solution:
    """A read ``solution.json``: its carriages (file order), the focal the solve used per view, the document."""

    path: Path
    carriages: tuple[SolvedCarriage, ...]
    focal_px: dict[str, float]
    doc: dict = field(compare=False, repr=False)
    # (4, 4) the solution's frame from the cameras file's: identity, except in a relative scene (levelled)
    world_from_cameras: np.ndarray = field(default_factory=lambda: np.eye(4), compare=False, repr=False)

    @property
    def relative(self) -> bool:
        """True when the scene is relative (no survey): local frame at the camera, no CRS or WGS84 figures."""
        fr = self.doc.get("frame")
        return isinstance(fr, dict) and fr.get("kind") == "relative"

    def cam_from_world(self, cam_from_world_of_cameras: np.ndarray) -> np.ndarray:
        """(4, 4) a ``cameras.json`` view's ``cam_from_world`` in the solution's frame (the same matrix unless
        the scene is relative and was levelled)."""
        return np.asarray(cam_from_world_of_cameras, float) @ np.linalg.inv(self.world_from_cameras)

    @property
    def posed(self) -> list[SolvedCarriage]:
        return [c for c in self.carriages if c.posed]

    @property
    def left_out(self) -> list[SolvedCarriage]:
        return [c for c in self.carriages if not c.posed]

    def doubts(self) -> dict[str, str]:
        """``{car number: the solver's message}`` for each carriage whose pose and interval are doubtful (warnings of
        :data:`DOUBT_KINDS`: its solution does not fit its measured points, a wrong branch or mismatched points; or
        its measured points and its matched face's pose disagree beyond the noise model).
        Every reader that shows a pose shows this beside it."""
        return doubts_of(self.doc)


def doubts_of(doc: dict) -> dict[str, str]:
    """:meth:`Solution.doubts` of a ``solution.json`` document (dict): the carriages of the solver's
    :data:`DOUBT_KINDS` warnings, and each carriage ``carried`` (placed from its neighbours, too few points of its own) through a
    held coupling from a doubtful one, along the chain."""
    out: dict[str, str] = {}
    for w in doc.get("warnings") or []:
        if isinstance(w, dict) and w.get("kind") in DOUBT_KINDS and w.get("car") is not None:
            out.setdefault(str(w["car"]), str(w.get("message") or w["kind"]))
    cars = [c for c in doc.get("carriages") or [] if isinstance(c, dict)]
    number = {c.get("index"): str(c.get("number")) for c in cars}
    carried = {str(c.get("number")) for c in cars if c.get("status") == "carried"}
    pairs = [(number.get(L.get("front")), number.get(L.get("rear"))) for L in doc.get("links") or []
             if isinstance(L, dict)]
    grew = True
    while grew:  # along the chain: a carried car carried from a car carried from a doubtful one
        grew = False
        for a, b in pairs + [(b, a) for a, b in pairs]:
            if a in out and b in carried and b not in out:
                out[b] = (f"car {b}: placed from car {a} through their coupling (too few points of its own), and "
                          f"car {a}'s pose is doubtful; so is its own")
                grew = True
    return out


# warning kinds that make a posed carriage's pose and interval doubtful: its solution does not fit its measured
# points; its measured points and its matched face's pose disagree (solve step 4b); another pose fits its points
# about as well (solve step 4's branch check); its body and another carriage's share space (the solver's last check)
DOUBT_KINDS = ("misfit", "predictions_disagree", "ambiguous", "overlap")


def _rigid(value: Any, where: str) -> np.ndarray:
    try:
        M = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{where}: not a 4x4 matrix of numbers") from None
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise InputError(f"{where}: shape {M.shape}, expected a finite 4x4 matrix")
    if not is_rotation(M[:3, :3], tol=1e-6) or not np.allclose(M[3], [0, 0, 0, 1]):
        raise InputError(f"{where}: not a rigid transform [[R, t], [0, 0, 0, 1]] (R must be a rotation)")
    return M


def _focal(doc: dict, where: str) -> dict[str, float]:
    focal = doc.get("focal_px") or {}
    if not isinstance(focal, dict):
        raise InputError(f"{where}: 'focal_px' must map view names to focal lengths (px)")
    for name, f in focal.items():
        if not isinstance(f, (int, float)) or isinstance(f, bool) or not math.isfinite(f) or f <= 0:
            raise InputError(f"{where}: focal_px[{name!r}] = {f!r}: not a positive focal length (px)")
    return {str(k): float(v) for k, v in focal.items()}


def _check_frame(doc: dict, frame: SceneFrame, where: str) -> None:
    fr = doc.get("frame")
    if not isinstance(fr, dict) or fr.get("kind") == "relative":
        return
    try:
        same = (abs(float(fr.get("lat", frame.lat_deg)) - frame.lat_deg) < 1e-9
                and abs(float(fr.get("lon", frame.lon_deg)) - frame.lon_deg) < 1e-9
                and abs(float(fr.get("height_m", frame.height_m)) - frame.height_m) < 1e-6)
    except (TypeError, ValueError):
        raise InputError(f"{where}: 'frame' = {fr}: lat, lon and height_m must be numbers") from None
    if not same:
        raise InputError(f"{where}: 'frame' = {fr} differs from the project's location ({frame.lat_deg}, "
                         f"{frame.lon_deg}, {frame.height_m} m); the solution is stale: run the solve again")


def parse_solution(doc: Any, path: Path | str, *, frame: SceneFrame | None = None,
                   numbers: Collection[str] | None = None) -> Solution:
    """Check a parsed ``solution.json``: against the project's ``frame`` and consist car ``numbers`` when given;
    :class:`InputError` naming the file and the entry (a stale solution says to run the solve again)."""
    where = str(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("carriages"), list):
        raise InputError(f"{where}: no 'carriages' list; see docs/pipeline.md (solution.json)")
    if frame is not None:
        _check_frame(doc, frame, where)
    cars = []
    for i, c in enumerate(doc["carriages"]):
        w = f"{where}: carriages[{i}]"
        if not isinstance(c, dict) or "number" not in c:
            raise InputError(f"{w}: not an object with a 'number'")
        number = str(c["number"])
        status = str(c.get("status", "solved"))
        if status not in STATUSES:
            raise InputError(f"{w}.status = {status!r}: give one of {', '.join(STATUSES)}")
        M = None
        if status != "left_out" and c.get("world_from_carriage") is not None:
            if numbers is not None and number not in numbers:
                raise InputError(f"{w}.number = {number!r} is not in the project's consist ({', '.join(numbers)}); "
                                 f"the solution is stale: run the solve again")
            M = _rigid(c["world_from_carriage"], f"{w}.world_from_carriage")
        try:
            index = int(c.get("index", i))
        except (TypeError, ValueError):
            raise InputError(f"{w}.index = {c.get('index')!r}: not a whole number") from None
        cars.append(SolvedCarriage(index, number, status, M, c))
    fr = doc.get("frame")
    W = np.eye(4)
    if isinstance(fr, dict) and fr.get("kind") in ("relative", "gps"):
        W = _rigid(fr.get("world_from_cameras"), f"{where}: frame.world_from_cameras")
    return Solution(Path(path), tuple(cars), _focal(doc, where), doc, W)


def read_solution(path: Path, *, frame: SceneFrame | None = None,
                  numbers: Collection[str] | None = None) -> Solution:
    """Read and check the ``solution.json`` at ``path`` (see :func:`parse_solution`)."""
    doc = read_json(Path(path), missing="not found; run the solve stage first (`workbench run`)")
    return parse_solution(doc, path, frame=frame, numbers=numbers)
