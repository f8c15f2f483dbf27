"""Synthetic incident scenarios, modelled on two real derailments (consist, layout, terrain type); the records are
data, in ``scenarios.toml`` beside this module.

The photos and the exact layout are synthetic; car numbers are illustrative, not the historical ones.

* ``spuyten-duyvil``: Metro-North train 8808, Spuyten Duyvil, Bronx (NY), 1 December 2013. A push-pull
  train (a Shoreliner cab car leading, coaches, a P32AC-DM locomotive at the rear) derailed on a curve
  of an embankment beside the Harlem River; cars came to rest jackknifed, some on their side, the
  leading car near the water.
* ``frankford-junction``: Amtrak train 188, Frankford Junction, Philadelphia (PA), 12 May 2015. An
  ACS-64 locomotive and Amfleet I coaches derailed on a tight curve beside an industrial area; the
  locomotive and the first coaches overturned and separated.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from .layout import CarPlan


@dataclass(frozen=True)
class Scenario:
    id: str
    title: str
    date: str
    lat: float
    lon: float
    crs: str
    terrain: str  # workbench.synth.terrain scenario
    consist: tuple[tuple[str, str], ...]  # (car number, type id), front to rear
    p_broken: float  # probability that a coupling broke
    p_on_side: float
    p_tilted: float
    jackknife_deg: tuple[float, float]  # range of |heading change| between neighbours
    front_s_m: float  # where the front car came to rest, arc length along the synthetic track
    lateral_m: tuple[float, float]  # sideways displacement of the front car from the track
    region: str  # folder under terrain/ for the sample's layers


def _load_scenarios(path: Path) -> dict[str, Scenario]:
    """The scenarios of ``scenarios.toml`` (one table per scenario id; every field of :class:`Scenario` but ``id``,
    no other key)."""
    doc = tomllib.loads(path.read_text(encoding="utf-8"))
    names = [f.name for f in fields(Scenario) if f.name != "id"]
    out = {}
    for sid, t in doc.items():
        missing, extra = sorted(set(names) - set(t)), sorted(set(t) - set(names))
        if missing or extra:
            raise ValueError(f"{path}: [{sid}]: missing keys {missing}, unknown keys {extra}")
        out[sid] = Scenario(id=sid, **{k: tuple(map(tuple, t[k])) if k == "consist" else
                                       tuple(t[k]) if isinstance(t[k], list) else t[k] for k in names})
    return out


SCENARIOS: dict[str, Scenario] = _load_scenarios(Path(__file__).with_name("scenarios.toml"))


def plan_consist(scn: Scenario, types: dict, rng: np.random.Generator, n_cars: int | None = None):
    """Draw the derailment for a seed: state, roll and jackknife per car, which couplings held.

    At least one coupling holds and one breaks (when there are two or more couplings), and at least one
    carriage lies on its side, so every sample exercises chains, broken links and large rolls.
    """
    consist = list(scn.consist[: n_cars or len(scn.consist)])
    if n_cars and n_cars > len(scn.consist):  # extend with copies of the last coach type
        last_type = scn.consist[-2][1] if len(scn.consist) > 1 else scn.consist[0][1]
        consist += [(f"{9000 + i}", last_type) for i in range(n_cars - len(scn.consist))]
    n = len(consist)
    for _ in range(100):
        couplings = ["broken" if rng.random() < scn.p_broken else "held" for _ in range(n - 1)]
        states = rng.choice(["on_side", "tilted", "upright"], size=n,
                            p=[scn.p_on_side, scn.p_tilted, 1 - scn.p_on_side - scn.p_tilted])
        ok = (n < 3 or ("held" in couplings and "broken" in couplings)) and (n < 2 or "on_side" in states)
        if ok:
            break
    plans = []
    sign = rng.choice([-1.0, 1.0])
    for i, (number, type_id) in enumerate(consist):
        state = str(states[i])
        roll = {"on_side": 90.0 * rng.choice([-1.0, 1.0]), "tilted": rng.uniform(10, 35) * rng.choice([-1.0, 1.0]),
                "upright": rng.uniform(-3, 3)}[state]
        jk = rng.uniform(*scn.jackknife_deg) * sign if i > 0 else rng.uniform(-25, 25)
        sign = -sign if rng.random() < 0.7 else sign  # zig-zag mostly
        plans.append(CarPlan(number=number, ctype=types[type_id], state=state, roll_deg=float(roll),
                             jackknife_deg=float(jk), coupling_to_next=couplings[i] if i < n - 1 else None,
                             broken_gap_m=float(rng.uniform(1.5, 8.0))))
    return plans
