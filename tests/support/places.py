"""Places a test flies to: metres north/east of a home, as lat/lon (one implementation of ``at``)."""

from __future__ import annotations

from protocol.geo import offset_latlon

HOME = (47.397742, 8.545594, 488.0)
"""Zurich, lat/lon/alt AMSL: the home of the in-process daemon, cooperation and scenario tests."""


def at(north: float, east: float, home: tuple[float, ...] = HOME) -> tuple[float, float]:
    """Lat/lon ``north``/``east`` metres from ``home``."""
    return offset_latlon(home[0], home[1], north, east)


def at_vehicle(
    home: tuple[float, ...], spacing_m: float, north: float, east: float, index: int = 0
) -> tuple[float, float]:
    """Lat/lon ``north``/``east`` metres from vehicle ``index``'s home, homes ``spacing_m`` apart east."""
    return at(north, east, at(0.0, spacing_m * index, home))
