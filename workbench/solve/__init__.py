"""Pose solver: simultaneous pose of all carriages of a consist from a few 2D-3D marked points each, chained at
the couplers. The method and the module map are in ``docs/solver.md``.

    from workbench.solve import CarriageInput, ChainLink, SolveOptions, View, solve_consist
    result = solve_consist(carriages, links, views, SolveOptions(estimate_focal=True), terrain=None)
"""

from .model import (CarriageInput, CarriageResult, ChainLink, Observation, SolveOptions, SolveResult, SolveWarning,
                    StepStats, View)
from .projection import project_with_jacobians
from .solver import refine_from, solve_consist
from .terrain import rest_on_terrain
from .uncertainty import crb

__all__ = ["CarriageInput", "CarriageResult", "ChainLink", "Observation", "SolveOptions", "SolveResult",
           "SolveWarning", "StepStats", "View", "crb", "project_with_jacobians", "refine_from", "rest_on_terrain",
           "solve_consist"]
