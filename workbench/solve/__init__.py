"""Pose solver: simultaneous pose of all carriages of a consist from a few 2D-3D marked points each, chained at
the couplers (see :mod:`.chain` for the method, :mod:`.uncertainty` for the covariance, :mod:`.projection`
for the exact projection Jacobians, :mod:`.simulate` for synthetic problems).

    from workbench.solve import CarriageInput, ChainLink, SolveOptions, View, solve_consist
    result = solve_consist(carriages, links, views, SolveOptions(estimate_focal=True), terrain=None)
"""

from .chain import (CarriageInput, CarriageResult, ChainLink, Observation, SolveOptions, SolveResult, SolveWarning,
                    StepStats, View, refine_from, rest_on_terrain, solve_consist)
from .projection import project_with_jacobians
from .uncertainty import crb

__all__ = ["CarriageInput", "CarriageResult", "ChainLink", "Observation", "SolveOptions", "SolveResult",
           "SolveWarning", "StepStats", "View", "crb", "project_with_jacobians", "refine_from", "rest_on_terrain", "solve_consist"]
