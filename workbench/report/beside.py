"""The report's work beside itself: its figures drawn in forked processes (two: they are most of the stage's first
part) while the stage copies the renders and loads the PDF engine."""

from __future__ import annotations

import os
from typing import Callable

from ..errors import StageError


def run_beside(jobs: list[tuple], processes: int = 2) -> Callable[[], list]:
    """Start ``jobs`` ([(function, args)]) in up to ``processes`` forked processes (the jobs dealt in turn, each
    process doing its share one after another); returns a function that waits for them and returns their results in
    the jobs' order (or raises the first error, once every process has ended). Without ``fork``: run here."""
    if not hasattr(os, "fork"):
        results = [fn(*args) for fn, args in jobs]
        return lambda: results
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    n = max(1, min(int(processes), len(jobs)))
    started = []
    for k in range(n):
        ours, theirs = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_run_jobs, args=(jobs[k::n], theirs), name=f"report figures {k + 1}", daemon=True)
        proc.start()
        theirs.close()
        started.append((ours, proc))

    def wait() -> list:
        shares, error = [], None
        for ours, proc in started:
            try:
                msg = ours.recv()
            except EOFError:
                msg = None
            finally:
                proc.join()
                ours.close()
            if msg is None:
                msg = ("error", StageError(f"report: the process drawing the figures ended without them (exit code "
                                           f"{proc.exitcode}); run the report again (`workbench run PATH --only "
                                           f"report --force`)"))
            if msg[0] == "error":
                error = error or msg[1]
            else:
                shares.append(msg[1])
        if error is not None:
            raise error
        return [shares[i % n][i // n] for i in range(len(jobs))]
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
