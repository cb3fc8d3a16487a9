"""The local frame over numpy arrays: ``protocol.geo``'s formulae run with numpy's functions.

Why a tangent plane and not UTM: a mission area is a few kilometres across, so a tangent plane at
its centre is as accurate as UTM there, needs no zone bookkeeping (areas straddling a zone edge,
poles), and needs no pyproj. The formulae, constants and axis order (east, north) live once, in
``protocol.geo``; this module only hands them numpy as their math backend, so planning and the
fleet-wide monitors project whole arrays with the very lines the agent and simulator use.

Accuracy (documented in docs/planning.md, checked in tests/planning/test_geodesy.py):
* round trip ``to_geodetic(to_local(p))`` returns ``p`` to better than 1e-9 degrees (~0.1 mm)
  anywhere within 100 km of the origin;
* a distance ``d`` from the origin measured in the plane is shorter than the geodesic by about
  ``d**3 / (6 R**2)``: 4 mm at 10 km, 0.5 m at 50 km. Lengths between two points near each other
  are scaled by at most ``cos(d / R)``, i.e. 1.2 ppm at 10 km from the origin.
"""

from __future__ import annotations

from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from protocol import geo

FloatArray = NDArray[np.float64]


_NUMPY_NAMES = {"asin": "arcsin", "atan2": "arctan2"}  # where numpy's name differs from math's


def _all_below(x: FloatArray, tol: float) -> bool:
    return bool(np.all(np.abs(x) < tol))


# protocol.geo's math backend with numpy's element-wise namesakes.
NUMPY = SimpleNamespace(
    **{name: getattr(np, _NUMPY_NAMES.get(name, name)) for name in geo.MATH_FUNCTIONS},
    minimum=np.minimum,
    maximum=np.maximum,
    all_below=_all_below,
)


def _f(x: ArrayLike) -> FloatArray:
    return np.asarray(x, dtype=float)


def geodetic_to_ecef(lat: ArrayLike, lon: ArrayLike, alt: ArrayLike = 0.0) -> tuple[FloatArray, ...]:
    """Latitude/longitude in degrees and ellipsoidal height in metres to ECEF metres."""
    return geo.geodetic_to_ecef(NUMPY, _f(lat), _f(lon), _f(alt))


def ecef_to_geodetic(x: ArrayLike, y: ArrayLike, z: ArrayLike) -> tuple[FloatArray, ...]:
    """ECEF metres to latitude/longitude degrees and height (``protocol.geo.ecef_to_geodetic``)."""
    return geo.ecef_to_geodetic(NUMPY, _f(x), _f(y), _f(z))


def distance_m_array(lat1: ArrayLike, lon1: ArrayLike, lat2: ArrayLike, lon2: ArrayLike) -> FloatArray:
    """``protocol.geo.distance_m`` (haversine, metres) element by element, the same formula."""
    out: FloatArray = geo.haversine_m(NUMPY, _f(lat1), _f(lon1), _f(lat2), _f(lon2))
    return out


def ned_offset_m_array(
    lat0: ArrayLike, lon0: ArrayLike, lat: ArrayLike, lon: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """``protocol.geo.ned_offset_m`` (flat-earth north/east metres) element by element."""
    return geo.flat_offset_m(NUMPY, _f(lat0), _f(lon0), _f(lat), _f(lon))


class LocalFrame(geo.LocalFrame):
    """``protocol.geo.LocalFrame`` over arrays: vectorised both ways (scalars give 0-d results)."""

    _m = NUMPY

    @classmethod
    def centred_on(cls, lats: ArrayLike, lons: ArrayLike) -> LocalFrame:
        """Frame at the bounding-box centre of the points, so the planar error is smallest."""
        la = _f(lats).ravel()
        lo = _f(lons).ravel()
        if la.size == 0 or la.size != lo.size:
            raise ValueError("centred_on needs equally many (>0) latitudes and longitudes")
        # unwrap longitudes around the first one so an area across the antimeridian centres correctly
        lo = lo[0] + (lo - lo[0] + 180.0) % 360.0 - 180.0
        lat0 = 0.5 * (float(la.min()) + float(la.max()))
        lon0 = 0.5 * (float(lo.min()) + float(lo.max()))
        lon0 = (lon0 + 180.0) % 360.0 - 180.0
        return cls(lat0, lon0)

    def enu(self, lat: ArrayLike, lon: ArrayLike, alt: ArrayLike | None = None) -> tuple[Any, Any, Any]:
        """Full east/north/up of points (``alt`` defaults to the origin's height)."""
        return super().enu(_f(lat), _f(lon), None if alt is None else _f(alt))

    def to_geodetic(self, east: ArrayLike, north: ArrayLike) -> tuple[Any, Any]:
        """Latitude, longitude of the surface points whose projections are (east, north)."""
        e, n = np.broadcast_arrays(_f(east), _f(north))
        return super().to_geodetic(e, n)

    def stack_local(self, lat: ArrayLike, lon: ArrayLike) -> FloatArray:
        """(..., 2) east/north metres of the given points."""
        e, n = self.to_local(lat, lon)
        return np.stack([e, n], axis=-1)

    def points_to_local(self, latlon: Sequence[Sequence[float]] | FloatArray) -> FloatArray:
        """(N, 2) array of [lat, lon] rows to (N, 2) array of [east, north] rows."""
        arr = _f(latlon).reshape(-1, 2)
        return self.stack_local(arr[:, 0], arr[:, 1])

    def points_to_geodetic(self, en: Sequence[Sequence[float]] | FloatArray) -> FloatArray:
        """(N, 2) array of [east, north] rows to (N, 2) array of [lat, lon] rows."""
        arr = _f(en).reshape(-1, 2)
        lat, lon = self.to_geodetic(arr[:, 0], arr[:, 1])
        return np.column_stack([lat, lon])
