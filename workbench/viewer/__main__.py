"""``python -m workbench.viewer INCIDENT [--screenshot PATH] [--select CAR]`` (until the CLI has ``workbench view``)."""

from __future__ import annotations

import argparse
import sys

from ..errors import WorkbenchError
from .app import view


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m workbench.viewer", description=__doc__)
    ap.add_argument("incident")
    ap.add_argument("--screenshot", help="write one frame to this PNG and exit")
    ap.add_argument("--select", help="car number to select at start")
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=800)
    a = ap.parse_args(argv)
    try:
        view(a.incident, screenshot=a.screenshot, select=a.select, width=a.width, height=a.height)
    except WorkbenchError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
