"""A chained step solved with the coupling bound |T| <= slack as an active set.

Links start free (the offset T itself the parameter); a link whose offset leaves the ball is moved onto the
sphere |T| = s (2 parameters) and the step re-solved; a link on the sphere whose multiplier has the wrong sign
is freed again. Every returned offset satisfies |T| <= s (to rounding).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .layout import ChainLayout, full_cost, residuals_and_jacobian
from .model import SolveOptions
from .problem import Car, Chains, Poses, Problem
from .terrain import Contact
from .trust_region import levenberg_marquardt

_MAX_ROUNDS = 12  # active-set rounds after which a link is no longer released


@dataclass
class ChainedFit:
    """A chained step's solution: the poses, each link's offset T (per chain, front to rear), the evaluations
    spent, the last round's message and convergence, the active-set rounds and the links left on the sphere."""

    poses: Poses
    links: list[list[np.ndarray]] = field(default_factory=list)
    nfev: int = 0
    message: str = ""
    ok: bool = True
    rounds: int = 0
    n_active: int = 0


def _links_to_release(prob: Problem, cars: list[Car], chains: Chains, rot_free: bool, focal_views, poses: Poses,
                      links: list[list[np.ndarray]], modes: list[list[str]], contact: Contact | None,
                      options: SolveOptions) -> bool:
    """Free (in ``modes``) every link on the sphere whose cost gradient points into the ball; True if any."""
    lay_free = ChainLayout(chains, rot_free, focal_views, cars, poses, None, options.pixel_sigma_px)
    r, J = residuals_and_jacobian(prob, lay_free, lay_free.x0, contact, True)
    g = J.T @ r
    changed = False
    for c, ch in enumerate(chains.members):
        for j in range(len(ch) - 1):
            if modes[c][j] != "sphere":
                continue
            T = links[c][j]
            o = lay_free.off[c] + lay_free.link_off[c][j]
            if float(g[o:o + 3] @ (T / np.linalg.norm(T))) > 1e-9 * max(1.0, float(np.abs(g).max())):
                modes[c][j] = "free"
                changed = True
    return changed


def solve_chained(prob: Problem, cars: list[Car], chains: Chains, rot_free: bool, focal_views: list[list[int]],
                  start: Poses, contact: Contact | None, options: SolveOptions) -> ChainedFit:
    """Minimise the chained cost from ``start`` (rotations free or held, the focal of ``focal_views`` free) with
    the coupling bound as an active set (see the module doc)."""
    modes = [["free"] * (len(ch) - 1) for ch in chains.members]
    nfev_tot, rounds = 0, 0
    poses = start
    for rounds in range(1, 40):
        lay = ChainLayout(chains, rot_free, focal_views, cars, poses, modes, options.pixel_sigma_px)
        res = levenberg_marquardt(prob, lay, contact, options)
        nfev_tot += res.nfev
        up = lay.unpack(res.x, with_derivs=False)
        poses, links = up.poses, up.links
        changed = False
        for c, ch in enumerate(chains.members):
            for j in range(len(ch) - 1):
                if modes[c][j] == "free" and np.linalg.norm(links[c][j]) > chains.slacks[c][j] * (1 + 1e-12):
                    modes[c][j] = "sphere"
                    changed = True
        if changed:
            continue
        if rounds >= _MAX_ROUNDS:
            break
        if not _links_to_release(prob, cars, chains, rot_free, focal_views, poses, links, modes, contact, options):
            break
    n_active = sum(m == "sphere" for ms in modes for m in ms)
    return ChainedFit(poses, links, nfev_tot, res.message, res.ok, rounds, n_active)


@dataclass
class ChainedProblem:
    """What a chained solve needs besides its start: the rows, the carriages, the chains, the focal groups
    estimated, the terrain contact term (or None) and the options."""

    prob: Problem
    cars: list[Car]
    chains: Chains
    focal_views: list[list[int]]
    contact: Contact | None
    options: SolveOptions

    def solve(self, start: Poses, rot_free: bool = True, options: SolveOptions | None = None) -> ChainedFit:
        """:func:`solve_chained` from ``start`` (with ``options`` instead of the problem's when given)."""
        return solve_chained(self.prob, self.cars, self.chains, rot_free, self.focal_views, start, self.contact,
                             self.options if options is None else options)

    def cost(self, poses: Poses) -> float:
        """The cost step 4 minimises, at ``poses`` (:func:`.layout.full_cost`)."""
        return full_cost(self.prob, self.cars, self.chains, poses, self.contact, self.options)
