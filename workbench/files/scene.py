"""The solved carriages as every consumer sees them: renders, report, exports, viewer (one scene model).

:func:`scene_carriages` turns a read ``solution.json`` (:mod:`workbench.files.solution`) and the consist's
carriage types into :class:`SceneCarriage` objects: the pose as a :class:`~workbench.core.frames.Rigid`
``world_from_carriage``, the figures the solution gives (body centre, intervals), the derived geometry (corners,
footprint, front) and the model's meshes, in the carriage frame or placed in the scene. Nothing here reads a
file: :func:`workbench.export.scene.build_scene` and :func:`workbench.report.scene.load_scene` call it on
:meth:`workbench.project.Project.solution` and the consist's types.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from operator import attrgetter
from typing import TYPE_CHECKING, Any

import numpy as np

from ..core.frames import Rigid, hpr_from_rotation
from .solution import record_floats

if TYPE_CHECKING:
    import trimesh

    from .solution import Solution

__all__ = ["SceneCarriage", "scene_carriages"]


@dataclass(frozen=True, eq=False)
class SceneCarriage:
    """One posed carriage (status ``solved`` or ``carried``). ``world_from_carriage`` maps the carriage frame (x
    forward, y left, z up, origin at top-of-rail midway between the couplers) into the scene frame; ``record`` is
    its ``solution.json`` entry; ``carriage_type`` its :class:`~workbench.rolling_stock.CarriageType`. Metres and
    degrees."""

    index: int
    number: str
    status: str
    carriage_type: Any
    world_from_carriage: Rigid
    record: dict = field(repr=False)
    _meshes: dict = field(default_factory=dict, repr=False)
    doubt: str = ""  # the solver's message when its solution does not fit its points (Solution.doubts), else ""

    # -- the type: its id and name, its size (metres) ----------------------------------------------------
    type_id = property(attrgetter("carriage_type.id"))
    type_name = property(attrgetter("carriage_type.name"))
    length_m = property(attrgetter("carriage_type.length_m"))
    width_m = property(attrgetter("carriage_type.width_m"))
    height_m = property(attrgetter("carriage_type.height_m"))

    @property
    def matrix(self) -> np.ndarray:
        """(4, 4) ``world_from_carriage``."""
        return self.world_from_carriage.matrix

    # -- figures of the solution --------------------------------------------------------------------------
    def floats(self, key: str) -> list[float] | None:
        """The record's list of numbers under ``key``, or None when it is absent or not all finite numbers."""
        return record_floats(self.record, key)

    @property
    def ci95_body_centre_m(self) -> list[float] | None:
        return self.floats("ci95_body_centre_m")

    @property
    def ci95_hpr_deg(self) -> list[float] | None:
        return self.floats("ci95_hpr_deg")

    @cached_property
    def hpr_deg(self) -> tuple[float, float, float]:
        return hpr_from_rotation(self.world_from_carriage.rotation)

    @property
    def heading_deg(self) -> float:
        return self.hpr_deg[0]

    @property
    def pitch_deg(self) -> float:
        return self.hpr_deg[1]

    @property
    def roll_deg(self) -> float:
        return self.hpr_deg[2]

    # -- geometry ------------------------------------------------------------------------------------------
    @cached_property
    def bbox_carriage(self) -> np.ndarray:
        """(2, 3) min / max corners of the whole model (couplers included), carriage frame."""
        return np.asarray(self.carriage_type.bounding_box(), dtype=float)

    @cached_property
    def body_box(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo (3,), hi (3,)) of the body (no couplers, no running gear), carriage frame."""
        centre, half = self.carriage_type.collision_boxes()[0]
        return centre - half, centre + half

    @cached_property
    def body_centre_carriage(self) -> np.ndarray:
        """(3,) the body centre in the carriage frame: the solver's (``body_centre_enu``), else the box's."""
        given = self.floats("body_centre_enu")
        if given is not None and len(given) == 3:
            return self.world_from_carriage.inverse().apply(np.asarray(given, dtype=float))
        return self.bbox_carriage.mean(axis=0)

    @property
    def body_centre_enu(self) -> np.ndarray:
        return self.world_from_carriage.apply(self.body_centre_carriage)

    @staticmethod
    def _corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])

    def corners_enu(self) -> np.ndarray:
        """(8, 3) corners of the model's bounding box (couplers included) in the scene frame."""
        return self.world_from_carriage.apply(self._corners(*self.bbox_carriage))

    def body_corners_enu(self) -> np.ndarray:
        """(8, 3) corners of the body box in the scene frame."""
        return self.world_from_carriage.apply(self._corners(*self.body_box))

    def footprint_enu(self) -> np.ndarray:
        """(k, 2) x/y outline (convex hull, counter-clockwise) of the model's bounding box seen from above."""
        from scipy.spatial import ConvexHull

        xy = self.corners_enu()[:, :2]
        return xy[ConvexHull(xy).vertices]

    def front_enu(self) -> np.ndarray:
        """(3,) the front coupler face's centre (carriage +x end) in the scene frame."""
        lo, hi = self.bbox_carriage
        return self.world_from_carriage.apply(np.array([hi[0], 0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2])]))

    # -- the model ----------------------------------------------------------------------------------------
    def mesh(self, *, textured: bool = True, in_scene: bool = False) -> trimesh.Trimesh:
        """The model (textured with its livery and number, or plain with shared vertices), in the carriage frame
        or placed in the scene; built once per kind (the same object on later calls: copy before changing it)."""
        key = (bool(textured), bool(in_scene))
        if key not in self._meshes:
            m = self.carriage_type.mesh(car_number=self.number, textured=textured)
            if in_scene:
                m.apply_transform(self.matrix)
            self._meshes[key] = m
        return self._meshes[key]


def scene_carriages(solution: Solution, carriage_types: dict[str, Any]) -> tuple[list[SceneCarriage], list[dict]]:
    """The posed carriages of a read solution with their types (``{car number: CarriageType}``), in the file's
    order, and the left-out ones ``[{number, reason}]``."""
    doubts = solution.doubts()
    cars = [SceneCarriage(c.index, c.number, c.status, carriage_types[c.number],
                          Rigid.from_matrix(c.world_from_carriage, "world", "carriage"), c.record,
                          doubt=doubts.get(c.number, ""))
            for c in solution.posed]
    return cars, [{"number": c.number, "reason": c.reason} for c in solution.left_out]
