"""The one geodesy: scalar formulae every side imports (agent, simulator, daemon).

Two models, each for its own job, written once here:

* **Small offsets on a sphere** (mean radius 6 371 008.8 m): :func:`distance_m` (haversine),
  :func:`offset_latlon` and :func:`ned_offset_m` (flat-earth north/east metres). The agent's
  arrival checks, go_by offsets and fences, the simulator's world and the cooperation monitors'
  short legs use these; over the few kilometres a fleet flies the error against WGS84 is below
  0.5 %, far under GPS noise at the acceptance radii we use, and both ends of a link agree on
  what a metre is.
* **The local frame** (:class:`LocalFrame`): east/north metres on the tangent plane of the WGS84
  ellipsoid at an origin, the planar space of planning and of the fleet-wide monitors. Axis
  order is **east, north** (x, y) because planning's geometry (shapely polygons, swaths,
  headings measured from x) is written in x/y; a monitor's distances do not care.

The formulae take a math backend (``m``): :data:`SCALAR` (``math``) here, numpy's in
``gcs.planning.geodesy`` for arrays, so the vectorised versions run these very lines and
``protocol`` stays free of numpy (the agent and the simulator import it).
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any, ClassVar

EARTH_RADIUS_M = 6_371_008.8
# ArduPilot's flat-earth radius (AP_Math RADIUS_OF_EARTH; LATLON_TO_M = 0.011131884502145034 m per
# 1e-7 degree): the simulator offsets with it so its local metres match a real ArduCopter's.
ARDUPILOT_EARTH_RADIUS_M = 6_378_100.0

WGS84_A = 6_378_137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)


# The functions the formulae below call on their math backend ``m``: ``math``'s here, numpy's
# namesakes in ``gcs.planning.geodesy`` (plus ``minimum``/``maximum`` and ``all_below``).
MATH_FUNCTIONS = ("sin", "cos", "sqrt", "cbrt", "asin", "atan2", "hypot", "radians", "degrees")


def _all_below(x: float, tol: float) -> bool:
    return abs(x) < tol


SCALAR = SimpleNamespace(
    **{name: getattr(math, name) for name in MATH_FUNCTIONS}, minimum=min, maximum=max, all_below=_all_below
)


def haversine_m(m: Any, lat1: Any, lon1: Any, lat2: Any, lon2: Any) -> Any:
    """Great-circle distance in metres with backend ``m`` (see :func:`distance_m`)."""
    p1, p2 = m.radians(lat1), m.radians(lat2)
    dp = p2 - p1
    dl = m.radians(lon2 - lon1)
    a = m.sin(dp / 2) ** 2 + m.cos(p1) * m.cos(p2) * m.sin(dl / 2) ** 2
    return 2 * EARTH_RADIUS_M * m.asin(m.minimum(1.0, m.sqrt(a)))


def flat_offset_m(
    m: Any, lat0: Any, lon0: Any, lat: Any, lon: Any, radius_m: float = EARTH_RADIUS_M
) -> tuple[Any, Any]:
    """North/east metres with backend ``m`` (see :func:`ned_offset_m`)."""
    north = m.radians(lat - lat0) * radius_m
    east = m.radians(lon - lon0) * radius_m * m.cos(m.radians(lat0))
    return north, east


def distance_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Great-circle (haversine) distance in metres between two lat/lon points in degrees."""
    return float(haversine_m(SCALAR, lat1, lon1, lat2, lon2))


def offset_latlon(
    lat: float, lon: float, north_m: float, east_m: float, radius_m: float = EARTH_RADIUS_M
) -> tuple[float, float]:
    """The point ``north_m``/``east_m`` metres from ``lat``/``lon`` (flat-earth, fine below ~10 km)."""
    dlat = math.degrees(north_m / radius_m)
    dlon = math.degrees(east_m / (radius_m * math.cos(math.radians(lat))))
    return lat + dlat, lon + dlon


def ned_offset_m(
    lat0: float, lon0: float, lat: float, lon: float, radius_m: float = EARTH_RADIUS_M
) -> tuple[float, float]:
    """North/east metres of ``lat``/``lon`` from ``lat0``/``lon0`` (inverse of :func:`offset_latlon`)."""
    north, east = flat_offset_m(SCALAR, lat0, lon0, lat, lon, radius_m)
    return float(north), float(east)


def geodetic_to_ecef(m: Any, lat: Any, lon: Any, alt: Any = 0.0) -> tuple[Any, Any, Any]:
    """Latitude/longitude in degrees and ellipsoidal height in metres to ECEF metres."""
    phi = m.radians(lat)
    lam = m.radians(lon)
    n = WGS84_A / m.sqrt(1.0 - WGS84_E2 * m.sin(phi) ** 2)
    x = (n + alt) * m.cos(phi) * m.cos(lam)
    y = (n + alt) * m.cos(phi) * m.sin(lam)
    z = (n * (1.0 - WGS84_E2) + alt) * m.sin(phi)
    return x, y, z


def ecef_to_geodetic(m: Any, x: Any, y: Any, z: Any) -> tuple[Any, Any, Any]:
    """ECEF metres to latitude/longitude degrees and height, Heikkinen's closed form (nm-exact)."""
    a, b, e2, ep2 = WGS84_A, WGS84_B, WGS84_E2, WGS84_EP2
    p = m.hypot(x, y)
    big_f = 54.0 * b * b * z * z
    g = p * p + (1.0 - e2) * z * z - e2 * (a * a - b * b)
    c = e2 * e2 * big_f * p * p / (g**3)
    s = m.cbrt(1.0 + c + m.sqrt(c * c + 2.0 * c))
    k = s + 1.0 + 1.0 / s
    big_p = big_f / (3.0 * k * k * g * g)
    q = m.sqrt(1.0 + 2.0 * e2 * e2 * big_p)
    rad = 0.5 * a * a * (1.0 + 1.0 / q) - big_p * (1.0 - e2) * z * z / (q * (1.0 + q)) - 0.5 * big_p * p * p
    r0 = -(big_p * e2 * p) / (1.0 + q) + m.sqrt(m.maximum(rad, 0.0))
    u = m.sqrt((p - e2 * r0) ** 2 + z * z)
    v = m.sqrt((p - e2 * r0) ** 2 + (1.0 - e2) * z * z)
    z0 = b * b * z / (a * v)
    h = u * (1.0 - b * b / (a * v))
    lat = m.degrees(m.atan2(z + ep2 * z0, p))
    lon = m.degrees(m.atan2(y, x))
    return lat, lon, h


class LocalFrame:
    """East/north metres on the tangent plane of WGS84 at ``origin`` (see the module docstring).

    ``to_local`` drops the up component (orthographic projection of the ellipsoid surface onto
    the plane); ``to_geodetic`` is its exact inverse for points at the origin's height. Accuracy
    (docs/planning.md): round trip to 1e-9 degrees within 100 km; a distance ``d`` from the
    origin is shorter than the geodesic by about ``d**3 / (6 R**2)`` (4 mm at 10 km).
    Methods compute with the class's backend ``_m`` (floats here; arrays in the numpy subclass
    ``gcs.planning.geodesy.LocalFrame``); ``local_point``/``geodetic_point`` always take and
    give plain floats, for per-drone use in the monitors.
    """

    _m: ClassVar[Any] = SCALAR

    def __init__(self, origin_lat: float, origin_lon: float, origin_alt: float = 0.0) -> None:
        if not -90.0 < origin_lat < 90.0:
            raise ValueError(f"origin latitude {origin_lat} must be strictly between -90 and 90")
        if not -180.0 <= origin_lon <= 360.0:
            raise ValueError(f"origin longitude {origin_lon} out of range")
        self.origin_lat = float(origin_lat)
        self.origin_lon = float(origin_lon)
        self.origin_alt = float(origin_alt)
        phi, lam = math.radians(self.origin_lat), math.radians(self.origin_lon)
        sp, cp, sl, cl = math.sin(phi), math.cos(phi), math.sin(lam), math.cos(lam)
        # rows: east, north, up unit vectors in ECEF
        self._rot = ((-sl, cl, 0.0), (-sp * cl, -sp * sl, cp), (cp * cl, cp * sl, sp))
        self._origin_ecef = geodetic_to_ecef(SCALAR, self.origin_lat, self.origin_lon, self.origin_alt)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.origin_lat!r}, {self.origin_lon!r}, {self.origin_alt!r})"

    def _enu(self, m: Any, lat: Any, lon: Any, alt: Any) -> tuple[Any, Any, Any]:
        x, y, z = geodetic_to_ecef(m, lat, lon, alt)
        ox, oy, oz = self._origin_ecef
        dx, dy, dz = x - ox, y - oy, z - oz
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self._rot
        return r00 * dx + r01 * dy + r02 * dz, r10 * dx + r11 * dy + r12 * dz, r20 * dx + r21 * dy + r22 * dz

    def _geodetic(self, m: Any, e: Any, n: Any) -> tuple[Any, Any]:
        """Walk along the plane normal until the ellipsoidal height equals the origin's; the
        height changes with ``up`` at rate cos(angle from origin), so Newton converges to machine
        precision in three steps for any point within hundreds of km."""
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = self._rot
        ox, oy, oz = self._origin_ecef
        u = -(e * e + n * n) / (2.0 * WGS84_A)  # the sphere drops below the plane by ~ d^2 / 2R
        lat = lon = e
        for _ in range(5):
            x = r00 * e + r10 * n + r20 * u + ox
            y = r01 * e + r11 * n + r21 * u + oy
            z = r02 * e + r12 * n + r22 * u + oz
            lat, lon, h = ecef_to_geodetic(m, x, y, z)
            dh = h - self.origin_alt
            phi, lam = m.radians(lat), m.radians(lon)
            cosang = r20 * m.cos(phi) * m.cos(lam) + r21 * m.cos(phi) * m.sin(lam) + r22 * m.sin(phi)
            u = u - dh / cosang
            if m.all_below(dh, 1e-7):
                break
        lon = (lon + 180.0) % 360.0 - 180.0
        return lat, lon

    def enu(self, lat: Any, lon: Any, alt: Any = None) -> tuple[Any, Any, Any]:
        """Full east/north/up of points (``alt`` defaults to the origin's height)."""
        return self._enu(self._m, lat, lon, self.origin_alt if alt is None else alt)

    def to_local(self, lat: Any, lon: Any) -> tuple[Any, Any]:
        """East, north metres of surface points (at the origin's height)."""
        e, n, _ = self.enu(lat, lon)
        return e, n

    def to_geodetic(self, east: Any, north: Any) -> tuple[Any, Any]:
        """Latitude, longitude of the surface point whose projection on the plane is (east, north)."""
        return self._geodetic(self._m, east, north)

    def local_point(self, lat: float, lon: float) -> tuple[float, float]:
        """East, north metres of one point, as plain floats."""
        e, n, _ = self._enu(SCALAR, lat, lon, self.origin_alt)
        return e, n

    def geodetic_point(self, east: float, north: float) -> tuple[float, float]:
        """Latitude, longitude of one local point, as plain floats."""
        lat, lon = self._geodetic(SCALAR, east, north)
        return lat, lon


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
