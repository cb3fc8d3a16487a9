"""Local east/north frame on the WGS84 ellipsoid, the planar space every planner works in.

Why ENU and not UTM: a mission area is a few kilometres across, so a tangent plane at its centre
is as accurate as UTM there, needs no zone bookkeeping (areas straddling a zone edge, poles), and
needs no pyproj. The frame is the ellipsoid's tangent plane at the origin (east, north, up);
``to_local`` drops the up component (orthographic projection of the ellipsoid surface onto the
plane), ``to_geodetic`` is its exact inverse for points on the surface at the origin's height.

Accuracy (documented in docs/planning.md, checked in tests/planning/test_geodesy.py):
* round trip ``to_geodetic(to_local(p))`` returns ``p`` to better than 1e-9 degrees (~0.1 mm)
  anywhere within 100 km of the origin;
* a distance ``d`` from the origin measured in the plane is shorter than the geodesic by about
  ``d**3 / (6 R**2)``: 4 mm at 10 km, 0.5 m at 50 km. Lengths between two points near each other
  are scaled by at most ``cos(d / R)``, i.e. 1.2 ppm at 10 km from the origin.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

WGS84_A = 6_378_137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_EP2 = WGS84_E2 / (1.0 - WGS84_E2)

FloatArray = NDArray[np.float64]


def geodetic_to_ecef(lat: ArrayLike, lon: ArrayLike, alt: ArrayLike = 0.0) -> tuple[FloatArray, ...]:
    """Latitude/longitude in degrees and ellipsoidal height in metres to ECEF metres."""
    phi = np.radians(np.asarray(lat, dtype=float))
    lam = np.radians(np.asarray(lon, dtype=float))
    h = np.asarray(alt, dtype=float)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(phi) ** 2)
    x = (n + h) * np.cos(phi) * np.cos(lam)
    y = (n + h) * np.cos(phi) * np.sin(lam)
    z = (n * (1.0 - WGS84_E2) + h) * np.sin(phi)
    return x, y, z


def ecef_to_geodetic(x: ArrayLike, y: ArrayLike, z: ArrayLike) -> tuple[FloatArray, ...]:
    """ECEF metres to latitude/longitude degrees and height, Heikkinen's closed form (nm-exact)."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    z = np.asarray(z, dtype=float)
    a, b, e2, ep2 = WGS84_A, WGS84_B, WGS84_E2, WGS84_EP2
    p = np.hypot(x, y)
    big_f = 54.0 * b * b * z * z
    g = p * p + (1.0 - e2) * z * z - e2 * (a * a - b * b)
    c = e2 * e2 * big_f * p * p / (g**3)
    s = np.cbrt(1.0 + c + np.sqrt(c * c + 2.0 * c))
    k = s + 1.0 + 1.0 / s
    big_p = big_f / (3.0 * k * k * g * g)
    q = np.sqrt(1.0 + 2.0 * e2 * e2 * big_p)
    rad = 0.5 * a * a * (1.0 + 1.0 / q) - big_p * (1.0 - e2) * z * z / (q * (1.0 + q)) - 0.5 * big_p * p * p
    r0 = -(big_p * e2 * p) / (1.0 + q) + np.sqrt(np.maximum(rad, 0.0))
    u = np.sqrt((p - e2 * r0) ** 2 + z * z)
    v = np.sqrt((p - e2 * r0) ** 2 + (1.0 - e2) * z * z)
    z0 = b * b * z / (a * v)
    h = u * (1.0 - b * b / (a * v))
    lat = np.degrees(np.arctan2(z + ep2 * z0, p))
    lon = np.degrees(np.arctan2(y, x))
    return lat, lon, h


class LocalFrame:
    """East/north metres on the tangent plane of WGS84 at ``origin``; vectorised both ways."""

    def __init__(self, origin_lat: float, origin_lon: float, origin_alt: float = 0.0) -> None:
        if not -90.0 < origin_lat < 90.0:
            raise ValueError(f"origin latitude {origin_lat} must be strictly between -90 and 90")
        if not -180.0 <= origin_lon <= 360.0:
            raise ValueError(f"origin longitude {origin_lon} out of range")
        self.origin_lat = float(origin_lat)
        self.origin_lon = float(origin_lon)
        self.origin_alt = float(origin_alt)
        phi, lam = np.radians(self.origin_lat), np.radians(self.origin_lon)
        sp, cp, sl, cl = np.sin(phi), np.cos(phi), np.sin(lam), np.cos(lam)
        # rows: east, north, up unit vectors in ECEF
        self._rot = np.array(
            [
                [-sl, cl, 0.0],
                [-sp * cl, -sp * sl, cp],
                [cp * cl, cp * sl, sp],
            ]
        )
        self._origin_ecef = np.array(geodetic_to_ecef(self.origin_lat, self.origin_lon, self.origin_alt))

    def __repr__(self) -> str:
        return f"LocalFrame({self.origin_lat!r}, {self.origin_lon!r}, {self.origin_alt!r})"

    @classmethod
    def centred_on(cls, lats: ArrayLike, lons: ArrayLike) -> LocalFrame:
        """Frame at the bounding-box centre of the points, so the planar error is smallest."""
        la = np.asarray(lats, dtype=float).ravel()
        lo = np.asarray(lons, dtype=float).ravel()
        if la.size == 0 or la.size != lo.size:
            raise ValueError("centred_on needs equally many (>0) latitudes and longitudes")
        # unwrap longitudes around the first one so an area across the antimeridian centres correctly
        lo = lo[0] + (lo - lo[0] + 180.0) % 360.0 - 180.0
        lat0 = 0.5 * (float(la.min()) + float(la.max()))
        lon0 = 0.5 * (float(lo.min()) + float(lo.max()))
        lon0 = (lon0 + 180.0) % 360.0 - 180.0
        return cls(lat0, lon0)

    def enu(self, lat: ArrayLike, lon: ArrayLike, alt: ArrayLike | None = None) -> tuple[FloatArray, ...]:
        """Full east/north/up of points (``alt`` defaults to the origin's height)."""
        h = self.origin_alt if alt is None else alt
        x, y, z = geodetic_to_ecef(lat, lon, h)
        d = np.stack(np.broadcast_arrays(x, y, z)) - self._origin_ecef.reshape((3,) + (1,) * np.ndim(x))
        e, n, u = np.tensordot(self._rot, d, axes=1)
        return e, n, u

    def to_local(self, lat: ArrayLike, lon: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """East, north metres of surface points (at the origin's height); scalars give 0-d arrays."""
        e, n, _ = self.enu(lat, lon)
        return e, n

    def to_geodetic(self, east: ArrayLike, north: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Latitude, longitude of the surface point whose projection on the plane is (east, north).

        Inverse of :meth:`to_local`: walk along the plane normal until the ellipsoidal height equals
        the origin's; the height changes with ``up`` at rate cos(angle from origin) so Newton
        converges to machine precision in three steps for any point within hundreds of km.
        """
        e, n = np.broadcast_arrays(np.asarray(east, dtype=float), np.asarray(north, dtype=float))
        # first guess: the sphere of radius R drops below the plane by ~ d^2 / 2R
        u = -(e * e + n * n) / (2.0 * WGS84_A)
        lat = lon = e
        for _ in range(5):
            enu = np.stack([e, n, u])
            xyz = np.tensordot(self._rot.T, enu, axes=1) + self._origin_ecef.reshape((3,) + (1,) * e.ndim)
            lat, lon, h = ecef_to_geodetic(xyz[0], xyz[1], xyz[2])
            dh = h - self.origin_alt
            # d(h)/d(u) = cos of the angle between the local and origin verticals
            phi = np.radians(lat)
            lam = np.radians(lon)
            up_here = np.stack([np.cos(phi) * np.cos(lam), np.cos(phi) * np.sin(lam), np.sin(phi)])
            cosang = np.tensordot(self._rot[2], up_here, axes=1)
            u = u - dh / cosang
            if np.all(np.abs(dh) < 1e-7):
                break
        lon = (lon + 180.0) % 360.0 - 180.0
        return lat, lon

    def points_to_local(self, latlon: Sequence[Sequence[float]] | FloatArray) -> FloatArray:
        """(N, 2) array of [lat, lon] rows to (N, 2) array of [east, north] rows."""
        arr = np.asarray(latlon, dtype=float).reshape(-1, 2)
        e, n = self.to_local(arr[:, 0], arr[:, 1])
        return np.column_stack([e, n])

    def points_to_geodetic(self, en: Sequence[Sequence[float]] | FloatArray) -> FloatArray:
        """(N, 2) array of [east, north] rows to (N, 2) array of [lat, lon] rows."""
        arr = np.asarray(en, dtype=float).reshape(-1, 2)
        lat, lon = self.to_geodetic(arr[:, 0], arr[:, 1])
        return np.column_stack([lat, lon])
