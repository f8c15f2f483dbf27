"""The project CRS, parsed and checked: pyproj, imported where a CRS is parsed (not numpy: settings are validated
without it), and not at all for the settings' check of a UTM zone's EPSG code (:func:`check_projected_crs`)."""

from __future__ import annotations

import re
from typing import TYPE_CHECKING

from ..errors import SettingsError

if TYPE_CHECKING:
    from pyproj import CRS

# The UTM zones of the datums a railway incident's data usually comes in, as EPSG numbers: each is a projected CRS
# with metre axes (tests/test_settings.py checks every one against pyproj's database).
UTM_EPSG_RANGES = (
    (32601, 32660),  # WGS 84 / UTM zone 1N-60N
    (32701, 32760),  # WGS 84 / UTM zone 1S-60S
    (25828, 25838),  # ETRS89 / UTM zone 28N-38N
    (26901, 26923),  # NAD83 / UTM zone 1N-23N
)
_EPSG_CODE = re.compile(r"EPSG:([0-9]{4,6})", re.IGNORECASE)


def is_utm_epsg(value: str | int) -> bool:
    """Whether ``value`` is written ``EPSG:<n>`` (any case) with ``n`` one of :data:`UTM_EPSG_RANGES`: a projected
    CRS in metres, known without pyproj (whose import, about 45 ms, every command that loads the settings paid
    for the check alone: docs/performance.md). Anything else is for :func:`parse_projected_crs`."""
    m = _EPSG_CODE.fullmatch(value) if isinstance(value, str) else None
    return m is not None and any(lo <= int(m.group(1)) <= hi for lo, hi in UTM_EPSG_RANGES)


def check_projected_crs(value: str | int, *, where: str = "location.crs") -> None:
    """:func:`parse_projected_crs`'s check without its result: nothing to load for a UTM zone's EPSG code
    (:func:`is_utm_epsg`), else pyproj's verdict."""
    if not is_utm_epsg(value):
        parse_projected_crs(value, where=where)


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
        raise SettingsError(f"{where} = {value!r} has axis unit {unit!r}; the workbench needs a projected CRS in "
                            f"metres")
    return crs
