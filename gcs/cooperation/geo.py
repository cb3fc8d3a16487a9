"""A local flat frame (north, east, up metres) around a reference point, vectorised with numpy.

Over the few kilometres a fleet spans, an equirectangular projection is accurate to well under
GPS noise, and it lets conflict checks run on whole arrays at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from protocol.geo import EARTH_RADIUS_M

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LocalFrame:
    lat0: float
    lon0: float

    @cached_property
    def _k_north(self) -> float:
        return math.radians(1.0) * EARTH_RADIUS_M

    @cached_property
    def _k_east(self) -> float:  # (cached: the collision check projects every drone each pass)
        return math.radians(1.0) * EARTH_RADIUS_M * math.cos(math.radians(self.lat0))

    def to_ne(self, lat: ArrayLike, lon: ArrayLike) -> FloatArray:
        """(..., 2) north/east metres of the given points."""
        lat_a = np.asarray(lat, dtype=float)
        lon_a = np.asarray(lon, dtype=float)
        return np.stack([(lat_a - self.lat0) * self._k_north, (lon_a - self.lon0) * self._k_east], axis=-1)

    def point(self, lat: float, lon: float) -> tuple[float, float]:
        return (lat - self.lat0) * self._k_north, (lon - self.lon0) * self._k_east

    def to_latlon(self, north: float, east: float) -> tuple[float, float]:
        return self.lat0 + north / self._k_north, self.lon0 + east / self._k_east


def distance_m_array(lat1: ArrayLike, lon1: ArrayLike, lat2: ArrayLike, lon2: ArrayLike) -> FloatArray:
    """``protocol.geo.distance_m`` (haversine, metres) element by element, the same formula."""
    p1, p2 = np.radians(lat1), np.radians(lat2)
    dp = p2 - p1
    dl = np.radians(np.subtract(lon2, lon1))
    a = np.sin(dp / 2) ** 2 + np.cos(p1) * np.cos(p2) * np.sin(dl / 2) ** 2
    out: FloatArray = 2 * EARTH_RADIUS_M * np.arcsin(np.minimum(1.0, np.sqrt(a)))
    return out


def ned_offset_m_array(
    lat0: ArrayLike, lon0: ArrayLike, lat: ArrayLike, lon: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """``protocol.geo.ned_offset_m`` (flat-earth north/east metres) element by element."""
    north: FloatArray = np.radians(np.subtract(lat, lat0)) * EARTH_RADIUS_M
    east: FloatArray = np.radians(np.subtract(lon, lon0)) * EARTH_RADIUS_M * np.cos(np.radians(lat0))
    return north, east
