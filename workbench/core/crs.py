"""The project CRS, parsed and checked (pyproj only: settings are validated without loading numpy).

pyproj is loaded by the first check in a process. A command may start the check of the CRS as written in the
settings in a forked process before it starts any thread (:func:`check_ahead`): the settings' validation then
takes that process's verdict (:func:`check_projected_crs`), and the command never loads pyproj itself where no
stage of it uses the CRS (docs/performance.md, ninth pass).
"""

from __future__ import annotations

import os
import select
import signal
from typing import TYPE_CHECKING

from ..errors import SettingsError

if TYPE_CHECKING:
    from pyproj import CRS

CHECK_AHEAD_TIMEOUT_S = 30.0  # a check ahead that has not answered by then is done again here

_AHEAD: dict[tuple[str, str], tuple[int, int]] = {}  # (value, where) -> (pid, read end) of a check under way
_VERDICTS: dict[tuple[str, str], str | None] = {}  # (value, where) -> None (projected, metres) or the error


def parse_projected_crs(value: str | int, *, where: str = "location.crs") -> CRS:
    """Parse a CRS and require it to be projected (metres); raise :class:`SettingsError` naming ``where``."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        crs = CRS.from_user_input(value)
    except CRSError as exc:
        raise SettingsError(f"{where} = {value!r} is not a CRS pyproj knows ({exc}); give an EPSG code such as "
                            f"'EPSG:32618'") from None
    if not crs.is_projected:
        raise SettingsError(f"{where} = {value!r} ({crs.name}) is not a projected CRS; give a projected EPSG code "
                            f"in metres, such as the UTM zone of the incident (e.g. 'EPSG:32618')")
    unit = crs.axis_info[0].unit_name if crs.axis_info else "metre"
    if unit not in ("metre", "meter"):
        raise SettingsError(f"{where} = {value!r} has axis unit {unit!r}; the workbench needs a projected CRS in metres")
    return crs


def check_projected_crs(value: str, *, where: str = "location.crs") -> None:
    """:func:`parse_projected_crs` without the parsed CRS: raise its :class:`SettingsError`, or return. Takes the
    verdict of a check started ahead (:func:`check_ahead`) of the same value, else checks here."""
    key = (value, where)
    if key in _AHEAD:
        _collect(key)
    if key not in _VERDICTS:
        parse_projected_crs(value, where=where)
        return
    if _VERDICTS[key] is not None:
        raise SettingsError(_VERDICTS[key])


def check_ahead(value: str, *, where: str = "location.crs") -> bool:
    """Start :func:`parse_projected_crs` of ``value`` in a forked process, whose verdict (the error's message, or
    none) :func:`check_projected_crs` takes: a command that validates its settings later checks its CRS beside
    its own start instead of loading pyproj (31-44 ms of CPU) on its way. Call it only where no thread but the
    calling one runs (a fork copies one thread). False where the process cannot fork."""
    key = (value, where)
    if not hasattr(os, "fork") or key in _AHEAD or key in _VERDICTS:
        return False
    read, write = os.pipe()
    try:
        pid = os.fork()
    except OSError:
        os.close(read)
        os.close(write)
        return False
    if pid == 0:  # the checking process: its verdict into the pipe, then out without the parent's exit handlers
        status = 0
        try:
            os.close(read)
            try:
                parse_projected_crs(value, where=where)
                answer = b"ok"
            except SettingsError as exc:
                answer = b"error " + str(exc).encode("utf-8", "replace")
            while answer:
                answer = answer[os.write(write, answer):]
        except BaseException:  # noqa: BLE001 - no verdict: the parent checks itself
            status = 1
        finally:
            os._exit(status)
    os.close(write)
    _AHEAD[key] = (pid, read)
    return True


def _collect(key: tuple[str, str]) -> None:
    """The verdict of the check ahead ``key`` into :data:`_VERDICTS` (none where it did not answer in time or
    answered nothing: then the caller checks), its process waited for."""
    pid, read = _AHEAD.pop(key)
    chunks = []
    try:
        while select.select([read], [], [], CHECK_AHEAD_TIMEOUT_S)[0]:
            chunk = os.read(read, 65536)
            if not chunk:
                break
            chunks.append(chunk)
        else:  # no answer in time: that process is ended
            os.kill(pid, signal.SIGKILL)
            chunks = []
    finally:
        os.close(read)
        try:
            os.waitpid(pid, 0)
        except ChildProcessError:
            pass
    answer = b"".join(chunks)
    if answer == b"ok":
        _VERDICTS[key] = None
    elif answer.startswith(b"error "):
        _VERDICTS[key] = answer[len(b"error "):].decode("utf-8", "replace")
