"""The interactive marked-point picker: a small local web page (see :mod:`.server`)."""

from .server import PickerServer, serve

__all__ = ["PickerServer", "serve"]
