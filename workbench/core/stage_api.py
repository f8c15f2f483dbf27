"""What a stage is handed and what it returns: a progress callback and a :class:`StageResult`.

Stages import these from here, not from the runner above them (``docs/architecture.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol


class Progress(Protocol):
    """``progress(fraction in [0, 1], message)``: how far the stage is."""

    def __call__(self, fraction: float, message: str = "") -> None: ...


@dataclass
class StageResult:
    """A stage's outputs (name -> file it wrote atomically) and statistics (written to
    ``out/<stage>/stats.json`` by the runner)."""

    outputs: dict[str, Path]
    stats: dict = field(default_factory=dict)
