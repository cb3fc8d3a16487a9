"""The one scalar geodesy (protocol/geo.py): the local frame and the flat-earth offsets."""

import math
import random

import pytest

from protocol.geo import (
    ARDUPILOT_EARTH_RADIUS_M,
    LocalFrame,
    distance_m,
    ned_offset_m,
    offset_latlon,
)

# ArduPilot's AP_Math LATLON_TO_M (metres per 1e-7 degree) times 1e7: the simulator's old constant.
ARDUPILOT_METRES_PER_DEG = 111318.84502145034


def test_scalar_frame_round_trips_to_a_nanodegree() -> None:
    rng = random.Random(7)
    for _ in range(300):
        frame = LocalFrame(rng.uniform(-80, 80), rng.uniform(-179, 179), rng.uniform(-100, 3000))
        east, north = rng.uniform(-50_000, 50_000), rng.uniform(-50_000, 50_000)
        lat, lon = frame.geodetic_point(east, north)
        e2, n2 = frame.local_point(lat, lon)
        assert abs(e2 - east) < 1e-6 and abs(n2 - north) < 1e-6
        assert isinstance(lat, float) and isinstance(e2, float)


def test_frame_axes_are_east_then_north() -> None:
    frame = LocalFrame(47.4, 8.5)
    e, n = frame.local_point(*offset_latlon(47.4, 8.5, 0.0, 100.0))
    assert e == pytest.approx(100.0, rel=5e-3) and abs(n) < 0.01
    e, n = frame.local_point(*offset_latlon(47.4, 8.5, 100.0, 0.0))
    assert n == pytest.approx(100.0, rel=5e-3) and abs(e) < 0.01


def test_ardupilot_radius_reproduces_ardupilot_scaling() -> None:
    """The simulator's offsets (sitl/physics.py) are these with ArduPilot's radius: the same
    numbers as its former constant, to well below a nanometre per kilometre."""
    assert math.radians(1.0) * ARDUPILOT_EARTH_RADIUS_M == pytest.approx(ARDUPILOT_METRES_PER_DEG, rel=1e-15)
    rng = random.Random(3)
    for _ in range(1000):
        lat0, lon0 = rng.uniform(-80, 80), rng.uniform(-179, 179)
        lat, lon = lat0 + rng.uniform(-0.1, 0.1), lon0 + rng.uniform(-0.1, 0.1)
        north, east = ned_offset_m(lat0, lon0, lat, lon, ARDUPILOT_EARTH_RADIUS_M)
        assert abs(north - (lat - lat0) * ARDUPILOT_METRES_PER_DEG) < 1e-9
        assert abs(east - (lon - lon0) * ARDUPILOT_METRES_PER_DEG * math.cos(math.radians(lat0))) < 1e-9
        lat2, lon2 = offset_latlon(lat0, lon0, north, east, ARDUPILOT_EARTH_RADIUS_M)
        assert abs(lat2 - (lat0 + north / ARDUPILOT_METRES_PER_DEG)) < 1e-12
        assert abs(lat2 - lat) < 1e-12 and abs(lon2 - lon) < 1e-12


def test_ellipsoidal_frame_against_the_sphere() -> None:
    """What moving the cooperation monitors from the spherical flat frame to the WGS84 frame
    changes: at most 0.6 % of a distance (the ellipsoid's radii of curvature against the mean
    radius; the meridian's is smallest at the equator), i.e. 6 cm on a 10 m separation."""
    rng = random.Random(11)
    worst = 0.0
    for _ in range(2000):
        lat0, lon0 = rng.uniform(-80, 80), rng.uniform(-179, 179)
        frame = LocalFrame(lat0, lon0)
        east, north = rng.uniform(-3000, 3000), rng.uniform(-3000, 3000)
        lat, lon = frame.geodetic_point(east, north)
        n_s, e_s = ned_offset_m(lat0, lon0, lat, lon)
        rel = math.hypot(e_s - east, n_s - north) / math.hypot(east, north)
        worst = max(worst, rel)
        assert distance_m(lat0, lon0, lat, lon) == pytest.approx(math.hypot(east, north), rel=6e-3)
    assert worst < 6e-3
