"""Options dataclasses: what each field takes is declared with the field and checked in one place.

A field states its allowed values in its annotation, as the settings' pydantic models do (``core/settings.py``):
``sigma_px: Annotated[float, Range(gt=0)] = 1.0`` (an ``int`` field with a range takes whole numbers only, not
booleans), ``loss: Literal["linear", "huber"] = "linear"`` (one of the listed values). The dataclass calls
:func:`check_options` from ``__post_init__``; a bad value is a :class:`~workbench.errors.SettingsError` that
names the options, the key, the value and what the key takes. Unknown keys are refused where a dict becomes
options (:func:`workbench.core.settings.options_from_dict`).
"""

from __future__ import annotations

import dataclasses
import functools
import numbers
import typing
from dataclasses import dataclass
from typing import Any, Literal

from ..errors import SettingsError

__all__ = ["Range", "check_options", "field_checks"]


@dataclass(frozen=True)
class Range:
    """The bounds a number must keep (``gt`` / ``ge`` below, ``lt`` / ``le`` above; None: open), and values
    ``also`` taken outside them (e.g. 0 for "off")."""

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    also: tuple[float, ...] = ()

    def holds(self, v: Any) -> bool:
        if v in self.also:
            return True
        return ((self.gt is None or v > self.gt) and (self.ge is None or v >= self.ge)
                and (self.lt is None or v < self.lt) and (self.le is None or v <= self.le))

    def describe(self, integer: bool) -> str:
        """What the range takes, in words: ``an integer >= 2``, ``in (0, 1]``, ``0 or >= 1000``."""
        low = (f"({self.gt:g}" if self.gt is not None else f"[{self.ge:g}" if self.ge is not None else None)
        high = (f"{self.lt:g})" if self.lt is not None else f"{self.le:g}]" if self.le is not None else None)
        if low and high:
            bound = f"in {low}, {high}"
        elif low:
            bound = ("> " if low[0] == "(" else ">= ") + low[1:]
        elif high:
            bound = ("< " if high[-1] == ")" else "<= ") + high[:-1]
        else:
            bound = "any value"
        kind = "an integer " if integer else ""
        extra = "".join(f"{a:g} or " for a in self.also)
        return f"{extra}{kind}{bound}"


@functools.cache
def field_checks(cls: type) -> tuple[tuple[str, str, Any], ...]:
    """(field, kind, rule) for every field of ``cls`` that declares its values: kind ``range`` or ``int`` (rule:
    the :class:`Range`; an ``int`` field takes whole numbers only) or ``choice`` (rule: the allowed values)."""
    hints = typing.get_type_hints(cls, include_extras=True)
    found = []
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        if typing.get_origin(hint) is typing.Annotated:
            base, *extras = typing.get_args(hint)
            found += [(f.name, "int" if base is int else "range", r) for r in extras if isinstance(r, Range)]
        elif typing.get_origin(hint) is Literal:
            found.append((f.name, "choice", typing.get_args(hint)))
    return tuple(found)


def _is_number(v: Any, integer: bool) -> bool:
    """Whether ``v`` is a number (a whole one where ``integer``), booleans not; Python's own types checked first."""
    if type(v) is int or (type(v) is float and not integer):
        return True
    return not isinstance(v, bool) and isinstance(v, int if integer else numbers.Real)


def check_options(options: Any, what: str) -> None:
    """Check every field of the dataclass ``options`` that declares its values (:class:`Range`, ``Literal``);
    :class:`SettingsError` ``"{what}: {key} = {value!r}: must be ..."`` for the first that does not hold."""
    for name, kind, rule in field_checks(type(options)):
        v = getattr(options, name)
        if kind == "choice":
            if v not in rule:
                raise SettingsError(f"{what}: {name} = {v!r}: must be one of {list(rule)}")
        elif not (_is_number(v, kind == "int") and rule.holds(v)):
            raise SettingsError(f"{what}: {name} = {v!r}: must be {rule.describe(kind == 'int')}")
