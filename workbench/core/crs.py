"""The project CRS, parsed and checked (pyproj only: settings are validated without loading numpy)."""

from __future__ import annotations

from pyproj import CRS
from pyproj.exceptions import CRSError

from ..errors import SettingsError


def parse_projected_crs(value: str | int, *, where: str = "location.crs") -> CRS:
    """Parse a CRS and require it to be projected (metres); raise :class:`SettingsError` naming ``where``."""
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
