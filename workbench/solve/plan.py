"""Which carriages are solved, carried by their chain or left out, and the chains of held couplings.

A carriage is observable alone with 4 non-degenerate points (coplanar ones only with a known focal); one with
2 or more points can be carried by a chain that has an observable carriage; the rest are left out (warned).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..errors import InputError
from .model import ChainLink, SolveOptions
from .problem import Car, Chains, degeneracy, record_warning


@dataclass
class Plan:
    """Per carriage its status ("solved" | "carried" | "left_out") and distinct points; the chains solved; the
    carriages observable alone among them (``solo``) and all solved or carried ones (``active``)."""

    status: list[str]
    n_points: list[int]
    chains: Chains
    solo: list[int]
    active: list[int]


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


def _settle_chain(ch: list[int], cars: list[Car], n_pts: list[int], degenerate: list[str], alone_ok: list[bool],
                  status: list[str], options: SolveOptions, wl: list) -> bool:
    """Set the status of a chain's carriages (with warnings); False when the chain is left out."""
    if len(ch) == 1:
        k = ch[0]
        if alone_ok[k]:
            status[k] = "solved"
            return True
        why = (f"{n_pts[k]} visible point(s), 4 needed for an unlinked carriage" if n_pts[k] < 4
               else f"its points are {degenerate[k]}" + (" and the focal is unknown"
                                                         if degenerate[k] == "coplanar" else ""))
        record_warning(wl, cars[k], "left_out", f"car {cars[k].number}: not observable alone ({why}) and not "
                                                f"linked to a neighbour; left out")
        return False
    if not any(alone_ok[k] for k in ch):
        for k in ch:
            record_warning(wl, cars[k], "left_out", f"car {cars[k].number}: no carriage of its chain "
                                                    f"({', '.join(cars[i].number for i in ch)}) is observable alone; "
                                                    f"left out")
        return False
    for k in ch:
        if alone_ok[k]:
            status[k] = "solved"
            continue
        status[k] = "carried"
        if n_pts[k] < 3 or degenerate[k] not in ("", "coplanar") or (
                degenerate[k] == "coplanar" and options.estimate_focal):
            why = f"{n_pts[k]} visible point(s), 3 needed" if n_pts[k] < 3 else f"its points are {degenerate[k]}"
            record_warning(wl, cars[k], "carried", f"car {cars[k].number}: not observable alone ({why}); carried by "
                                                   f"its chain")
    return True


def plan_consist(cars: list[Car], links: Sequence[ChainLink], options: SolveOptions, wl: list) -> Plan:
    """Check the links, decide what each carriage's points allow, and build the chains to solve (warnings go to
    ``wl``, see :func:`.problem.record_warning`)."""
    N = len(cars)
    link_slack = link_slacks(links, N)
    n_pts = [len(c.distinct) for c in cars]
    degenerate = []
    for c in cars:
        d = degeneracy(c.ctype, c.distinct) if len(c.distinct) >= 2 else "too few"
        if d == "coplanar" and not options.estimate_focal and len(c.distinct) >= 4:
            d = ""
        degenerate.append(d)
    alone_ok = [n_pts[k] >= 4 and degenerate[k] == "" for k in range(N)]
    candidate = [n_pts[k] >= 2 for k in range(N)]
    for k in range(N):
        if not candidate[k]:
            lk = (k in link_slack) or (k - 1 in link_slack)
            record_warning(wl, cars[k], "left_out",
                           f"car {cars[k].number}: {n_pts[k]} visible marked point(s) — at least 2 are needed even "
                           f"when carried by its chain{' (its links are dropped)' if lk else ''}; left out")
    status = ["left_out"] * N
    final = [ch for ch in _candidate_chains(candidate, link_slack)
             if _settle_chain(ch, cars, n_pts, degenerate, alone_ok, status, options, wl)]
    active = [k for ch in final for k in ch]
    chains = Chains(final, [[link_slack[ch[j]] for j in range(len(ch) - 1)] for ch in final])
    return Plan(status, n_pts, chains, [k for k in active if alone_ok[k]], active)
