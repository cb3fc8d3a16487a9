"""Small spherical-earth helpers both sides need (arrival checks, go_by offsets, fences).

Spherical model (mean radius 6 371 008.8 m): over the few kilometres a fleet flies, the error
against WGS84 is below 0.5 %, far under GPS noise at the acceptance radii we use. Planning uses
the ellipsoidal local frame in ``gcs.planning.geodesy`` instead.
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Sequence

EARTH_RADIUS_M = 6_371_008.8


def distance_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Great-circle (haversine) distance in metres between two lat/lon points in degrees."""
    p1, p2 = math.radians(lat1), math.radians(lat2)
    dp = p2 - p1
    dl = math.radians(lon2 - lon1)
    a = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2 * EARTH_RADIUS_M * math.asin(min(1.0, math.sqrt(a)))


def offset_latlon(lat: float, lon: float, north_m: float, east_m: float) -> tuple[float, float]:
    """The point ``north_m``/``east_m`` metres from ``lat``/``lon`` (flat-earth, fine below ~10 km)."""
    dlat = math.degrees(north_m / EARTH_RADIUS_M)
    dlon = math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat))))
    return lat + dlat, lon + dlon


def ned_offset_m(lat0: float, lon0: float, lat: float, lon: float) -> tuple[float, float]:
    """North/east metres of ``lat``/``lon`` from ``lat0``/``lon0`` (inverse of :func:`offset_latlon`)."""
    north = math.radians(lat - lat0) * EARTH_RADIUS_M
    east = math.radians(lon - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0))
    return north, east


def point_in_polygon(lat: float, lon: float, polygon: Sequence[tuple[float, float]]) -> bool:
    """Even-odd rule test of a lat/lon point against a polygon of (lat, lon) vertices."""
    inside = False
    n = len(polygon)
    for i in range(n):
        y1, x1 = polygon[i]
        y2, x2 = polygon[(i + 1) % n]
        if (y1 > lat) != (y2 > lat):
            x_cross = x1 + (lat - y1) * (x2 - x1) / (y2 - y1)
            if lon < x_cross:
                inside = not inside
    return inside


# A negative number, or a comma-separated list starting with one: "-35.36,149.16,584".
_NEGATIVE_NUMBERS = re.compile(r"^-\d*\.?\d+(?:[eE][-+]?\d+)?(?:,\s*-?\d*\.?\d+(?:[eE][-+]?\d+)?)*$")


def allow_negative_coordinates(parser: argparse.ArgumentParser) -> None:
    """Let ``--home -35.36,149.16,584`` parse: argparse takes an argument that starts with ``-``
    for an option unless it looks like a negative number, and a coordinate list does not."""
    parser._negative_number_matcher = _NEGATIVE_NUMBERS
