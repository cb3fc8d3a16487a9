import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import LineString, Point, Polygon

from gcs.planning.patterns import (
    count_turns,
    curved,
    curved_cover,
    line_grid,
    path_length,
    segmented,
    spiral,
    swept_footprint,
    zigzag,
)
from gcs.planning.polygon import rotate

from .conftest import convex_polygons

RECT = np.array([(0, 0), (200, 0), (200, 150), (0, 150)], float)


def _uncovered(poly, points, half):
    return Polygon(poly).convex_hull.difference(swept_footprint(points, half * (1 + 1e-9) + 1e-9)).area


@settings(max_examples=60, deadline=None)
@given(convex_polygons(), st.floats(2.0, 40.0))
def test_zigzag_every_point_within_half_a_swath(poly, step):
    sw = zigzag(poly, step)
    assert sw.spacing <= step + 1e-9
    assert _uncovered(poly, sw.points, step / 2) == pytest.approx(0.0, abs=1e-6 * Polygon(poly).area)
    # and pointwise, on random interior samples
    rng = np.random.default_rng(0)
    P = Polygon(poly)
    minx, miny, maxx, maxy = P.bounds
    line = LineString(sw.points) if len(sw.points) > 1 else Point(sw.points[0])
    for x, y in rng.uniform([minx, miny], [maxx, maxy], (200, 2)):
        if P.contains(Point(x, y)):
            assert line.distance(Point(x, y)) <= step / 2 + 1e-6


def test_lines_even_and_half_a_spacing_inside():
    ys, spacing = line_grid(0.0, 150.0, 20.0)
    assert len(ys) == 8 and spacing == pytest.approx(18.75)
    assert ys[0] == pytest.approx(spacing / 2) and ys[-1] == pytest.approx(150 - spacing / 2)
    sw = zigzag(RECT, 20.0)
    assert len(sw.lines) == 8 and sw.turns == 14
    # legs 18.75 m apart under a 20 m footprint: every leg end moves in by the corner's slack,
    # sqrt((10 cos(pi/32))^2 - 9.375^2) = 3.34 m (gcs.planning.turn_trim), 8 x 200 m before
    cut = math.sqrt((10.0 * math.cos(math.pi / 32)) ** 2 - 9.375**2)
    assert sw.length == pytest.approx(8 * (200 - 2 * cut) + 7 * 18.75)


def test_zigzag_runs_along_min_height():
    long_thin = rotate([(0, 0), (500, 0), (500, 40), (0, 40)], 0.5)
    sw = zigzag(long_thin, 10.0)
    assert len(sw.lines) == 4  # 40 m across / 10 m, not 500 / 10
    d = sw.lines[0, 1] - sw.lines[0, 0]
    assert abs(math.atan2(d[1], d[0]) % math.pi - 0.5) < 1e-9


def test_paper_chord_ends_miss_corners():
    tri = np.array([(0, 0), (300, 0), (150, 60)], float)
    chord = zigzag(tri, 20.0, extent="chord")
    strip = zigzag(tri, 20.0)
    assert _uncovered(tri, chord.points, 10.0) > 1.0
    assert _uncovered(tri, strip.points, 10.0) == pytest.approx(0.0, abs=1e-6)


def test_start_corner_nearest():
    sw = zigzag(RECT, 20.0, start=(210, 160))
    assert np.hypot(*(sw.points[0] - [200, 150])) < 20


@settings(max_examples=25, deadline=None)
@given(convex_polygons(), st.floats(3.0, 30.0))
def test_spiral_covers(poly, step):
    sw = spiral(poly, step)
    area = Polygon(poly).area
    assert _uncovered(poly, sw.points, step / 2) <= 2e-3 * area + 1e-6


def test_spiral_rings_and_centre():
    sw = spiral(RECT, 20.0)
    assert sw.meta["rings"] == 4  # 150 m across: rings at 10, 30, 50, 70 m deep
    assert np.hypot(*(sw.points[-1] - [100, 75])) < 70
    assert _uncovered(RECT, sw.points, 10.0) == pytest.approx(0.0, abs=1e-6)


def test_segmented_alg2():
    base = zigzag(RECT, 20.0)
    seg = segmented(base, 4)
    assert len(seg.points) == len(base.points) + 3 * len(base.lines)
    assert seg.length == pytest.approx(base.length)
    assert seg.turns == base.turns  # break points are collinear
    with pytest.raises(ValueError):
        segmented(base, 0)


def test_curved_alg3_shifts_midpoints_into_wind():
    base = zigzag(RECT, 20.0, angle=0.0)  # legs east-west
    cv = curved(base, 0.3, wind_from_deg=0.0)  # wind from north: midpoints move north
    mids, ends = cv.points[1::3], cv.points[0::3]
    assert np.allclose(mids[:, 1] - ends[: len(mids), 1], 0.3 * base.spacing)
    # the bend is centred on the straight leg: ends back by half, midpoint forward by half
    assert np.allclose(mids[:, 1] - base.lines[:, 0, 1], 0.15 * base.spacing)
    assert path_length(cv.points) > base.length
    with pytest.raises(ValueError, match="cross"):
        curved(base, 2.0)  # the paper's |S| <= 2 would cross neighbouring legs


@pytest.mark.parametrize("shift", [-0.5, -0.2, 0.2, 0.5])
def test_curved_without_wind_bends_every_leg_the_same_way(shift):
    # The paper's q_y + S x Step: one side for all legs. Following each leg's own left normal
    # flipped the bend on alternate legs, so legs met on one side and gaped on the other.
    base = zigzag(RECT, 20.0, angle=0.0)
    cv = curved(base, shift)
    mids, ends = cv.points[1::3], cv.points[0::3][: len(base.lines)]
    bends = mids[:, 1] - ends[:, 1]
    assert np.allclose(bends, shift * base.spacing)


CURVE_AREAS = {
    "rectangle": RECT,
    "triangle": np.array([(0, 0), (380, 0), (80, 440)], float),
    "kite": np.array([(0, 0), (120, -60), (300, 10), (90, 200)], float),
}


@pytest.mark.parametrize("area", sorted(CURVE_AREAS))
@pytest.mark.parametrize("wind", [None, 0.0, 45.0, 200.0])
@pytest.mark.parametrize("shift", [-0.5, -0.25, 0.0, 0.25, 0.5])
def test_curved_cover_leaves_no_gap_at_any_allowed_shift(area, wind, shift):
    poly = CURVE_AREAS[area]
    sw = curved_cover(poly, 30.0, shift, wind)
    assert sw.pattern == "curved-zigzag"
    assert sw.meta["line_step_m"] <= 30.0
    assert _uncovered(poly, sw.points, 15.0) <= 1e-6 * Polygon(poly).area


@settings(max_examples=25, deadline=None)
@given(convex_polygons(), st.floats(-0.5, 0.5), st.one_of(st.none(), st.floats(0.0, 360.0)))
def test_curved_cover_on_random_convex_polygons(poly, shift, wind):
    sw = curved_cover(poly, 20.0, shift, wind)
    assert _uncovered(poly, sw.points, 10.0) <= 1e-6 * Polygon(poly).area


def test_count_turns():
    assert count_turns([(0, 0), (1, 0), (2, 0), (2, 1)]) == 1
    assert count_turns([(0, 0), (1, 0)]) == 0


@pytest.mark.parametrize("corners", [14, 20])
def test_spiral_sees_the_wedges_of_obtuse_corners(corners):
    # 154 and 162 deg corners: a ring half a step inside passes them 1-3 % of a step too far
    # away; with detours only below 150 deg the plan itself left 43 and 25 m^2 unseen.
    poly = np.array(
        [(100 * math.cos(a), 100 * math.sin(a)) for a in np.arange(corners) * 2 * math.pi / corners]
    )
    assert _uncovered(poly, spiral(poly, 30.0).points, 15.0) == pytest.approx(0.0, abs=1e-6)
    assert _uncovered(poly, spiral(poly, 30.0, corner_deg=150.0).points, 15.0) > 10.0
