import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs.planning.areas import AreaFormatError, load_area, parse_area
from gcs.planning.geodesy import LocalFrame, ecef_to_geodetic, geodetic_to_ecef
from protocol.geo import distance_m


@settings(max_examples=60, deadline=None)
@given(
    st.floats(-80, 80),
    st.floats(-179, 179),
    st.floats(-50_000, 50_000),
    st.floats(-50_000, 50_000),
)
def test_round_trip_below_a_millimetre(lat0, lon0, east, north):
    f = LocalFrame(lat0, lon0, 100.0)
    lat, lon = f.to_geodetic(east, north)
    e2, n2 = f.to_local(lat, lon)
    assert abs(e2 - east) < 1e-4 and abs(n2 - north) < 1e-4
    lat2, lon2 = f.to_geodetic(e2, n2)
    assert abs(lat2 - lat) < 1e-9 and abs(((lon2 - lon + 180) % 360) - 180) < 1e-9


def test_vectorised_and_scalar_agree():
    f = LocalFrame(47.4, 8.5)
    lats = np.array([47.41, 47.39, 47.4])
    lons = np.array([8.51, 8.49, 8.5])
    e, n = f.to_local(lats, lons)
    assert e.shape == (3,)
    for i in range(3):
        es, ns = f.to_local(float(lats[i]), float(lons[i]))
        assert float(es) == pytest.approx(e[i]) and float(ns) == pytest.approx(n[i])
    assert float(e[2]) == pytest.approx(0.0, abs=1e-9)


def test_distances_match_geodesic_scale():
    # one arcminute of latitude at 45 deg is 1852.2 m on WGS84 (meridian radius of curvature)
    f = LocalFrame(45.0, 0.0)
    _, n = f.to_local(45.0 + 1 / 60, 0.0)
    assert float(n) == pytest.approx(1852.25, abs=0.5)
    # agrees with the spherical haversine to its own 0.5 % accuracy over 2 km
    lat, lon = f.to_geodetic(1500.0, 1300.0)
    assert distance_m(45.0, 0.0, float(lat), float(lon)) == pytest.approx(np.hypot(1500, 1300), rel=5e-3)


def test_ecef_known_point():
    x, y, z = geodetic_to_ecef(0.0, 0.0, 0.0)
    assert (float(x), float(y), float(z)) == pytest.approx((6378137.0, 0.0, 0.0))
    lat, _lon, h = ecef_to_geodetic(0.0, 0.0, 6356752.314245 + 10)
    assert float(lat) == pytest.approx(90.0) and float(h) == pytest.approx(10.0, abs=1e-6)


def test_centred_on_antimeridian():
    f = LocalFrame.centred_on([10.0, 10.1], [179.95, -179.95])
    assert abs(abs(f.origin_lon) - 180.0) < 1e-9
    e, _ = f.to_local(10.05, -179.99)
    assert 0 < float(e) < 2000


def test_bad_origin():
    with pytest.raises(ValueError):
        LocalFrame(90.0, 0.0)


def test_readers(tmp_path):
    ring = [[47.0, 8.0], [47.0, 8.01], [47.01, 8.01], [47.01, 8.0]]
    gj = {
        "type": "Feature",
        "properties": {"name": "field"},
        "geometry": {"type": "Polygon", "coordinates": [[[p[1], p[0]] for p in [*ring, ring[0]]]]},
    }
    plan = {
        "fileType": "Plan",
        "version": 1,
        "mission": {
            "items": [
                {"type": "SimpleItem", "command": 22, "params": [0] * 7},
                {
                    "type": "ComplexItem",
                    "complexItemType": "survey",
                    "polygon": ring,
                    "TransectStyleComplexItem": {"CameraCalc": {}},
                },
            ]
        },
    }
    for obj, fname in ((gj, "a.geojson"), (plan, "b.plan"), (ring, "c.json")):
        p = tmp_path / fname
        p.write_text(json.dumps(obj))
        area = load_area(p)
        assert [list(v) for v in area.vertices] == ring
    assert load_area(tmp_path / "a.geojson").name == "field"
    with pytest.raises(AreaFormatError):
        parse_area({"type": "Point", "coordinates": [0, 0]})
    with pytest.raises(AreaFormatError):
        parse_area({"fileType": "Plan", "mission": {"items": []}})
    with pytest.raises(ValueError):
        parse_area([[95.0, 0.0], [0, 1], [1, 1]])


def test_numpy_frame_runs_the_scalar_formulae():
    """The vectorised frame is ``protocol.geo.LocalFrame`` with numpy as its math: the same
    numbers point by point (no second copy of the formulae to drift apart)."""
    from protocol.geo import LocalFrame as ScalarFrame

    rng = np.random.default_rng(5)
    for _ in range(40):
        lat0, lon0 = rng.uniform(-80, 80), rng.uniform(-179, 179)
        vec, one = LocalFrame(lat0, lon0), ScalarFrame(lat0, lon0)
        east, north = rng.uniform(-50_000, 50_000, 8), rng.uniform(-50_000, 50_000, 8)
        lats, lons = vec.to_geodetic(east, north)
        es, ns = vec.to_local(lats, lons)
        for k in range(8):
            lat, lon = one.geodetic_point(float(east[k]), float(north[k]))
            assert abs(lat - lats[k]) < 1e-12 and abs(((lon - lons[k] + 180) % 360) - 180) < 1e-12
            e, n = one.local_point(float(lats[k]), float(lons[k]))
            assert abs(e - es[k]) < 1e-9 and abs(n - ns[k]) < 1e-9


def test_array_helpers_equal_the_scalar_ones():
    from gcs.planning.geodesy import distance_m_array, ned_offset_m_array
    from protocol.geo import ned_offset_m

    rng = np.random.default_rng(9)
    lat1, lon1 = rng.uniform(-80, 80, 200), rng.uniform(-179, 179, 200)
    lat2, lon2 = lat1 + rng.uniform(-0.05, 0.05, 200), lon1 + rng.uniform(-0.05, 0.05, 200)
    dist = distance_m_array(lat1, lon1, lat2, lon2)
    north, east = ned_offset_m_array(lat1, lon1, lat2, lon2)
    for k in range(200):
        a, b, c, d = float(lat1[k]), float(lon1[k]), float(lat2[k]), float(lon2[k])
        assert abs(dist[k] - distance_m(a, b, c, d)) < 1e-9
        assert np.hypot(north[k] - ned_offset_m(a, b, c, d)[0], east[k] - ned_offset_m(a, b, c, d)[1]) < 1e-9
