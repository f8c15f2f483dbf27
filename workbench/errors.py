"""One exception base and the named warnings users must see.

Every error a user can cause (bad settings, missing photo, unknown model type, ...) is a
:class:`WorkbenchError` whose message names the file, the key or value, and what to do.
The CLI turns it into a one-line message and a non-zero exit.
"""

from __future__ import annotations


class WorkbenchError(Exception):
    """Base of every error the workbench reports to its user."""


class SettingsError(WorkbenchError):
    """A settings file (TOML) is missing, malformed, or has an unknown key or a bad value."""


class InputError(WorkbenchError):
    """An input file (photo, DEM, correspondence file, ...) is missing, unreadable or invalid."""


class UnknownModelType(WorkbenchError):
    """A carriage type named in a consist is not in the rolling-stock library."""


class OutputError(WorkbenchError):
    """An output cannot be written: a read-only folder, a full disk, a missing permission."""


class StageError(WorkbenchError):
    """A stage failed or a stage's required input (an earlier stage's output) is missing."""


class RenderError(WorkbenchError):
    """Off-screen rendering is not available (e.g. no Vulkan driver)."""


class WorkbenchWarning(UserWarning):
    """Base of the warnings a user must see (logged and recorded in stage statistics)."""
