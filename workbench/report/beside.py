"""The report's work beside itself: its figures drawn in a forked process while the stage copies the renders and
loads the PDF engine."""

from __future__ import annotations

import os
from typing import Callable

from ..errors import StageError


def run_beside(jobs: list[tuple]) -> Callable[[], list]:
    """Start ``jobs`` ([(function, args)]) one after another in a forked process; returns a function that waits for
    them and returns their results in order (or raises the first one's error). Without ``fork``: run here."""
    if not hasattr(os, "fork"):
        results = [fn(*args) for fn, args in jobs]
        return lambda: results
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    ours, theirs = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_run_jobs, args=(jobs, theirs), name="report figures", daemon=True)
    proc.start()
    theirs.close()

    def wait() -> list:
        try:
            msg = ours.recv()
        except EOFError:
            msg = None
        finally:
            proc.join()
            ours.close()
        if msg is None:
            raise StageError(f"report: the process drawing the figures ended without them (exit code "
                             f"{proc.exitcode}); run the report again (`workbench run PATH --only report --force`)")
        if msg[0] == "error":
            raise msg[1]
        return msg[1]
    return wait


def _run_jobs(jobs: list[tuple], conn) -> None:
    try:
        conn.send(("done", [fn(*args) for fn, args in jobs]))
    except Exception as exc:  # noqa: BLE001 - raised by the stage
        try:
            conn.send(("error", exc))
        except Exception:  # noqa: BLE001 - an exception that does not pickle: its message
            conn.send(("error", StageError(f"report: {type(exc).__name__}: {exc}")))
    finally:
        conn.close()


def load_pdf_engine() -> None:
    """Import WeasyPrint now (while the figures are drawn beside); a failure is reported by :func:`write_pdf`."""
    try:
        import weasyprint  # noqa: F401
    except (ImportError, OSError):
        pass
