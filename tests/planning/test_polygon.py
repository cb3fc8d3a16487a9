import math

import numpy as np
import pytest
from hypothesis import given, settings

from gcs.planning.polygon import (
    PolygonType,
    SelfIntersectionError,
    centroid,
    classify,
    convex_hull,
    height_at,
    min_height_rotation,
    regularity,
    require_simple,
    rotate,
    scan_min_height,
    signed_area,
)

from .conftest import convex_polygons, star_polygons

SQUARE = [(0, 0), (10, 0), (10, 10), (0, 10)]
L_SHAPE = [(0, 0), (10, 0), (10, 2), (2, 2), (2, 10), (0, 10)]


def test_types():
    assert classify(SQUARE) == PolygonType.CONVEX
    assert classify(L_SHAPE) == PolygonType.CONCAVE
    assert classify([(0, 0), (10, 10), (10, 0), (0, 10)]) == PolygonType.SELF_INTERSECTING
    # collinear extra vertex keeps a polygon convex
    assert classify([(0, 0), (5, 0), (10, 0), (10, 10), (0, 10)]) == PolygonType.CONVEX


def test_self_intersection_error_names_edges_and_coordinates():
    bow = [(0, 0), (10, 10), (10, 0), (0, 10)]
    with pytest.raises(SelfIntersectionError) as info:
        require_simple(bow)
    msg = str(info.value)
    assert "edge 0 crosses edge 2" in msg and "(5.00, 5.00)" in msg
    assert "(0.00, 0.00)->(10.00, 10.00)" in msg
    c = info.value.crossings[0]
    assert (c.edge_a, c.edge_b) == (0, 2) and c.point == pytest.approx((5.0, 5.0))


def test_figure_eight_with_no_vertex_inside_is_rejected():
    # the paper's vertex-inside test cannot see this crossing; the edge test does
    ring = [(0, 0), (4, 0), (4, 1), (1, 1), (1, -1), (0, -1)]
    assert classify(ring) == PolygonType.SELF_INTERSECTING


def test_concave_to_convex_drops_inner_points():
    hull = convex_hull(L_SHAPE)
    assert len(hull) == 5 and classify(hull) == PolygonType.CONVEX
    assert [2.0, 2.0] not in hull.tolist()  # the reflex vertex is gone
    assert signed_area(hull) == pytest.approx(100.0 - 32.0)


def test_area_and_centroid_equations():
    assert signed_area(SQUARE) == pytest.approx(100.0)
    assert signed_area(SQUARE[::-1]) == pytest.approx(-100.0)
    assert centroid(L_SHAPE) == pytest.approx(((20 * 5 + 16 * 1) / 36, (20 * 1 + 16 * 6) / 36))


def test_regularity_alg1():
    assert regularity(SQUARE) == pytest.approx(1.0)
    hexagon = [(math.cos(a), math.sin(a)) for a in np.linspace(0, 2 * math.pi, 6, endpoint=False)]
    assert regularity(hexagon) == pytest.approx(1.0)
    # by hand: angles 5x90 + 270 (mean 120) -> 1 - 300/360/6; edges 10,2,8,8,2,10 -> 1 - 2.8/6
    expected = 0.5 * ((1 - 300 / 360 / 6) + (1 - 2.8 / 6))
    assert regularity(L_SHAPE) == pytest.approx(expected)
    assert regularity([(0, 0), (100, 0), (100, 10), (0, 10)]) < regularity(SQUARE)


def test_min_height_of_rotated_rectangle_is_exact():
    rect = rotate([(0, 0), (100, 0), (100, 20), (0, 20)], 0.7)
    angle, h = min_height_rotation(rect)
    assert h == pytest.approx(20.0)
    assert height_at(rect, angle) == pytest.approx(20.0)
    _, h_scan = scan_min_height(rect, 0.1)
    assert h <= h_scan


@settings(max_examples=60, deadline=None)
@given(convex_polygons())
def test_min_width_never_worse_than_paper_scan(poly):
    angle, h = min_height_rotation(poly)
    _, h_scan = scan_min_height(poly, 0.1)
    assert h <= h_scan + 1e-9
    assert height_at(poly, angle) == pytest.approx(h, rel=1e-9, abs=1e-9)


@settings(max_examples=30, deadline=None)
@given(star_polygons())
def test_min_width_of_concave_uses_hull(poly):
    _, h = min_height_rotation(poly)
    _, h_scan = scan_min_height(poly, 0.1)
    assert h <= h_scan + 1e-9
