"""Which carriages are solved, carried by their chain or left out, and the chains of held couplings.

A carriage is observable alone with 4 non-degenerate points. One showing one face only (4 or more coplanar
points: a side seen in a 3/4 view) needs the focal of its photo: with a known focal it is observable alone; with an
unknown focal it is when that focal is pinned, by a carriage with points off one plane in a photo of that camera,
and the joint problem (the information matrix of all the carriages' points, the couplings and one focal per
camera: :func:`information_matrix`) fixes it well enough (:data:`FOCAL_PINNED_REL_SD`, checked at step 4's
solution: :func:`focal_rel_sd`, ``steps.one_face_check``). A carriage with 2 or more points can be carried by a chain that has an observable
carriage; the rest are left out (warned, with what is missing).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..core.geometry import skew
from ..errors import InputError
from .model import ChainLink, SolveOptions, View
from .problem import SQRT5, Car, Chains, Poses, Problem, degeneracy, focal_groups, record_warning

# An unknown focal pinned by a two-face carriage admits the one-face carriages of its photos when the joint
# problem's information at step 4's solution fixes it to this relative standard deviation (at the configured
# pixel sigma) or better; else they are refused and the solve starts again without them.
FOCAL_PINNED_REL_SD = 0.10


@dataclass
class Plan:
    """Per carriage its status ("solved" | "carried" | "left_out") and distinct points; the chains solved; the
    carriages observable alone among them (``solo``), all solved or carried ones (``active``), and the solo ones
    that pin an unknown focal by themselves (``pinning``: points off one plane; the others of ``solo`` show one
    face and are posed at the focal the pinning ones give). ``observability``: the one-face carriages admitted and
    refused (step 1's facts). ``coplanar``: the solo carriages whose points lie on one plane, at a known focal
    too (their PnP has two poses that fit about equally: the branch check tries both)."""

    status: list[str]
    n_points: list[int]
    chains: Chains
    solo: list[int]
    active: list[int]
    pinning: list[int] = field(default_factory=list)
    observability: dict = field(default_factory=dict)
    coplanar: list[int] = field(default_factory=list)

    @property
    def one_face(self) -> list[int]:
        """The solo carriages that do not pin the focal: one-face ones admitted with an unknown focal (none at a
        known focal, where every solo carriage counts as pinning)."""
        pins = set(self.pinning)
        return [k for k in self.solo if k not in pins]


def link_slacks(links: Sequence[ChainLink], n: int) -> dict[int, float]:
    """Front index -> slack (m) of every held link; a link is checked (consecutive carriages, given once)."""
    link_slack: dict[int, float] = {}
    seen_pairs = set()
    for L in links:
        for idx in (L.front, L.rear):
            if not (0 <= int(idx) < n):
                raise InputError(f"chain link {L.front}->{L.rear}: carriage index {idx} is not in the consist "
                                 f"(0..{n - 1})")
        if int(L.rear) != int(L.front) + 1:
            raise InputError(f"chain link {L.front}->{L.rear}: a link joins consecutive carriages (rear = front + 1)")
        if L.front in seen_pairs:
            raise InputError(f"chain link {L.front}->{L.rear} is given twice")
        seen_pairs.add(L.front)
        if L.slack_m is None:
            continue
        if not (np.isfinite(L.slack_m) and L.slack_m > 0):
            raise InputError(f"chain link {L.front}->{L.rear}: slack_m = {L.slack_m!r} must be positive (or None for "
                             f"no link)")
        link_slack[int(L.front)] = float(L.slack_m)
    return link_slack


def _candidate_chains(candidate: list[bool], link_slack: dict[int, float]) -> list[list[int]]:
    """Runs of consecutive candidates joined by held links."""
    N = len(candidate)
    chains: list[list[int]] = []
    k = 0
    while k < N:
        if not candidate[k]:
            k += 1
            continue
        ch = [k]
        while k in link_slack and k + 1 < N and candidate[k + 1]:
            ch.append(k + 1)
            k += 1
        chains.append(ch)
        k += 1
    return chains


# ----------------------------------------------------------------------------------------------------------
# The joint problem's information
# ----------------------------------------------------------------------------------------------------------
def information_matrix(prob: Problem, poses: Poses, chains: Chains, focal_views: list[list[int]],
                       sigma_px: float) -> np.ndarray:
    """The information ``J^T J / sigma^2`` of the measured pixel rows of ``prob`` and the held couplings' offset
    prior (sigma_T = slack / sqrt 5) at ``poses``. Parameters: per carriage of ``prob.active`` (in that order) a
    scene-frame rotation increment and the origin's translation (6), then the focal (px) of each focal group."""
    na, nf = len(prob.active), len(focal_views)
    col = {k: 6 * i for i, k in enumerate(prob.active)}
    H = np.zeros((6 * na + nf, 6 * na + nf))
    _, _, JX, Jf = prob.project(poses.R, poses.t, poses.f, jac=True)
    w = np.where(prob.measured, prob.w, 0.0) / sigma_px  # predictions carry no information
    RP = np.einsum("nij,nj->ni", poses.R[prob.car], prob.P)
    Jp = np.concatenate([-np.einsum("nij,njk->nik", JX, np.array([skew(x) for x in RP])), JX], axis=2)
    Jp *= w[:, None, None]
    Jfw = Jf * w[:, None]
    for k, idx in prob.by_car.items():
        H[col[k]:col[k] + 6, col[k]:col[k] + 6] += np.einsum("nai,naj->ij", Jp[idx], Jp[idx])
    for g, grp in enumerate(focal_views):
        idx = prob.rows_of_views(grp)
        c = 6 * na + g
        H[c, c] += float(np.sum(Jfw[idx] ** 2))
        for k in np.unique(prob.car[idx]):
            sel = idx[prob.car[idx] == k]
            v = np.einsum("nai,na->i", Jp[sel], Jfw[sel])
            H[col[k]:col[k] + 6, c] += v
            H[c, col[k]:col[k] + 6] += v
    cars = prob.cars
    for ch, sl in zip(chains.members, chains.slacks):
        for a, b, s in zip(ch[:-1], ch[1:], sl):
            J = np.zeros((3, H.shape[0]))
            J[:, col[a]:col[a] + 3] = skew(poses.R[a] @ cars[a].c_rear)
            J[:, col[a] + 3:col[a] + 6] = -np.eye(3)
            J[:, col[b]:col[b] + 3] = -skew(poses.R[b] @ cars[b].c_front)
            J[:, col[b] + 3:col[b] + 6] = np.eye(3)
            J *= SQRT5 / s
            H += J.T @ J
    return H


def marginal_sd(H: np.ndarray, rcond: float = 1e-12) -> np.ndarray:
    """Each parameter's standard deviation from the information ``H`` (inf where the parameter lies in its null
    space: the rank; and where ``H`` scaled to a unit diagonal has eigenvalues below ``rcond`` times its
    largest, those directions count as null: the conditioning)."""
    d = np.sqrt(np.maximum(np.diag(H), 0.0))
    zero = d <= 0
    d = np.where(zero, 1.0, d)
    ev, V = np.linalg.eigh(H / np.outer(d, d))
    good = ev > rcond * max(float(ev.max()), 0.0) if len(ev) else ev > 0
    var = np.sum(V[:, good] ** 2 / ev[good], axis=1)
    null = np.sum(V[:, ~good] ** 2, axis=1) > 1e-6
    sd = np.sqrt(var) / d
    sd[null | zero] = np.inf
    return sd


def _shows_two_faces(c: Car, group: list[int]) -> bool:
    """Whether the carriage shows 4 or more points off one plane in the views ``group``."""
    names = sorted({n for n, v in zip(c.names, c.views) if int(v) in group})
    return len(names) >= 4 and degeneracy(c.ctype, names) == ""


def focal_rel_sd(cars: list[Car], active: list[int], views: Sequence[View], poses: Poses, chains: Chains,
                 focal_views: list[list[int]], sigma_px: float) -> list[float]:
    """Each focal group's relative standard deviation (sd / focal) in the joint problem of the carriages
    ``active`` at ``poses``: :func:`information_matrix` with every measured point weighted alike (the information
    proper), then :func:`marginal_sd`."""
    prob = Problem(cars, active, views, {k: 1.0 for k in active})
    sd = marginal_sd(information_matrix(prob, poses, chains, focal_views, sigma_px))[6 * len(active):]
    return [float(x / poses.f[g[0]]) for x, g in zip(sd, focal_views)]


def focal_reason(names: str, pinned_by_a_car: bool, rel: float = float("nan"), sigma_px: float = 1.0) -> str:
    """What a one-face carriage misses: the focal of its photo ``names`` pinned by no car, or only weakly (``rel``:
    the relative sd the joint problem gives it)."""
    if not pinned_by_a_car:
        return (f"its points are coplanar (one face) and the focal of view(s) {names} is pinned by no car: no "
                f"carriage there shows points off one plane (two faces) and the view's focal is unknown")
    fixed = ("the joint problem does not fix it" if not np.isfinite(rel) else
             f"the joint problem fixes it to {100 * rel:.0f} % (1 sd at {sigma_px:g} px)")
    return (f"its points are coplanar (one face) and the focal of view(s) {names} is pinned too weakly: {fixed}, "
            f"{100 * FOCAL_PINNED_REL_SD:.0f} % needed")


def best_view(c: Car) -> int:
    """The view where the carriage has most points (where step 1 takes its PnP)."""
    vs, n = np.unique(c.views, return_counts=True)
    return int(vs[int(np.argmax(n))])


def coplanar_admission(cars: list[Car], degenerate: list[str], alone_ok: list[bool], views: Sequence[View],
                       refused: dict[int, str] | None = None) -> tuple[list[int], dict[int, str], dict]:
    """With an unknown focal: the one-face carriages (4 or more coplanar points) observable alone, because the
    focal of their photo (the view where they show most points) is held (its view's focal known) or pinned by a
    carriage with 4 or more points off one plane in a photo of that camera. ``refused``: carriages the joint
    problem's conditioning refused (step 1's check, :func:`focal_rel_sd`) and why. Returns (admitted,
    refused -> what is missing, facts)."""
    refused = dict(refused or {})
    cop = [k for k, c in enumerate(cars) if len(c.distinct) >= 4 and degenerate[k] == "coplanar"]
    if not cop:
        return [], refused, {}
    seen = sorted({int(v) for c in cars if len(c.distinct) >= 2 for v in c.views})
    groups = focal_groups(views, [v for v in seen if not views[v].focal_known] or seen)
    group_of = {v: g for g, grp in enumerate(groups) for v in grp}
    pins = [k for k, ok in enumerate(alone_ok) if ok]
    # a focal is pinned only where a carriage with points off one plane shows 4 of them in a view of its camera:
    # what a face alone says about the focal hangs on its tilt, which it fixes poorly itself (docs/solver.md)
    has_pin = [any(_shows_two_faces(cars[k], g) for k in pins) for g in groups]
    admitted = []
    for k in cop:
        g = group_of.get(best_view(cars[k]))
        if k in refused:
            continue
        if g is None or has_pin[g]:
            admitted.append(k)
        else:
            refused[k] = focal_reason(", ".join(views[v].name for v in groups[g]), False)
    facts = {"one_face_admitted": [cars[k].number for k in admitted],
             "one_face_refused": [cars[k].number for k in sorted(refused)]}
    return admitted, refused, facts


# ----------------------------------------------------------------------------------------------------------
# The plan
# ----------------------------------------------------------------------------------------------------------
def _not_alone_why(k: int, n_pts: list[int], degenerate: list[str], focal_why: dict[int, str]) -> str:
    if n_pts[k] < 4:
        return f"{n_pts[k]} visible point(s), 4 needed for an unlinked carriage"
    if k in focal_why:
        return focal_why[k]
    return f"its points are {degenerate[k]}" + (" and the focal is unknown" if degenerate[k] == "coplanar" else "")


def _settle_chain(ch: list[int], cars: list[Car], n_pts: list[int], degenerate: list[str], alone_ok: list[bool],
                  status: list[str], options: SolveOptions, wl: list, focal_why: dict[int, str]) -> bool:
    """Set the status of a chain's carriages (with warnings); False when the chain is left out."""
    if len(ch) == 1:
        k = ch[0]
        if alone_ok[k]:
            status[k] = "solved"
            return True
        why = _not_alone_why(k, n_pts, degenerate, focal_why)
        record_warning(wl, cars[k], "left_out", f"car {cars[k].number}: not observable alone ({why}) and not "
                                                f"linked to a neighbour; left out")
        return False
    if not any(alone_ok[k] for k in ch):
        by_why: dict[str, list[str]] = {}  # what is missing -> the carriages it is missing for
        for i in ch:
            by_why.setdefault(f"{n_pts[i]} visible point(s)" if n_pts[i] < 4 else
                              _not_alone_why(i, n_pts, degenerate, focal_why), []).append(cars[i].number)
        whys = "; ".join(f"car {', '.join(nums)}: {why}" for why, nums in by_why.items())
        for k in ch:
            record_warning(wl, cars[k], "left_out", f"car {cars[k].number}: no carriage of its chain "
                                                    f"({', '.join(cars[i].number for i in ch)}) is observable alone "
                                                    f"({whys}); left out")
        return False
    for k in ch:
        if alone_ok[k]:
            status[k] = "solved"
            continue
        status[k] = "carried"
        if n_pts[k] < 3 or degenerate[k] not in ("", "coplanar") or (
                degenerate[k] == "coplanar" and options.estimate_focal):
            why = (f"{n_pts[k]} visible point(s), 3 needed" if n_pts[k] < 3 else
                   focal_why.get(k, f"its points are {degenerate[k]}"))
            record_warning(wl, cars[k], "carried", f"car {cars[k].number}: not observable alone ({why}); carried by "
                                                   f"its chain")
    return True


def plan_consist(cars: list[Car], links: Sequence[ChainLink], options: SolveOptions, wl: list,
                 views: Sequence[View] | None = None, refused: dict[int, str] | None = None) -> Plan:
    """Check the links, decide what each carriage's points allow (with an unknown focal and the ``views``, the
    one-face carriages whose focal is held or pinned: :func:`coplanar_admission`; ``refused``: one-face carriages
    the joint problem's conditioning refused, and why), and build the chains to solve (warnings go to ``wl``, see
    :func:`.problem.record_warning`)."""
    N = len(cars)
    link_slack = link_slacks(links, N)
    n_pts = [len(c.distinct) for c in cars]
    degenerate, planar = [], []
    for k, c in enumerate(cars):
        d = degeneracy(c.ctype, c.distinct) if len(c.distinct) >= 2 else "too few"
        if d == "coplanar" and len(c.distinct) >= 4:
            planar.append(k)
            if not options.estimate_focal:
                d = ""
        degenerate.append(d)
    alone_ok = [n_pts[k] >= 4 and degenerate[k] == "" for k in range(N)]
    pins = set(k for k in range(N) if alone_ok[k])
    focal_why: dict[int, str] = {}
    facts: dict = {}
    if options.estimate_focal and views is not None:
        admitted, focal_why, facts = coplanar_admission(cars, degenerate, alone_ok, views, refused)
        for k in admitted:
            alone_ok[k] = True
    candidate = [n_pts[k] >= 2 for k in range(N)]
    for k in range(N):
        if not candidate[k]:
            lk = (k in link_slack) or (k - 1 in link_slack)
            record_warning(wl, cars[k], "left_out",
                           f"car {cars[k].number}: {n_pts[k]} visible marked point(s) — at least 2 are needed even "
                           f"when carried by its chain{' (its links are dropped)' if lk else ''}; left out")
    status = ["left_out"] * N
    final = [ch for ch in _candidate_chains(candidate, link_slack)
             if _settle_chain(ch, cars, n_pts, degenerate, alone_ok, status, options, wl, focal_why)]
    active = [k for ch in final for k in ch]
    chains = Chains(final, [[link_slack[ch[j]] for j in range(len(ch) - 1)] for ch in final])
    solo = [k for k in active if alone_ok[k]]
    return Plan(status, n_pts, chains, solo, active, [k for k in active if k in pins], facts,
                [k for k in solo if k in planar])
