"""Issue 27's four measured causes of paths longer than Fields2Cover's, each pinned by a test.

(1) the sweep angle of a concave area is chosen by the length flown, not the hull's width;
(2) a height that is an exact multiple of the step (up to lat/lon rounding) gets no extra leg;
(3) no leg reaches outside the area beyond half a spacing (the turn margin) through a rounding sliver;
(4) ``plan_psa``'s library default plans with the CLI's track margin.
"""

import math

import numpy as np
import pytest
from shapely.geometry import LineString, Polygon

from gcs.planning._fleet_io import PsaConfig
from gcs.planning.areas import SearchArea
from gcs.planning.camera import spacing_from_swath
from gcs.planning.decompose import candidate_angles, cover_area, sweep_angle
from gcs.planning.division import DroneSpec
from gcs.planning.geodesy import LocalFrame
from gcs.planning.patterns import line_grid, swept_footprint
from gcs.planning.planner import plan_search
from gcs.planning.psa import DEFAULT_TRACK_MARGIN_M, plan_psa

# 300 x 300 m minus a 180 x 180 m corner; Fields2Cover 2.1 flies it in 3,162 m at swath 20 m
L_FIELD = np.array([(0, 0), (300, 0), (300, 120), (120, 120), (120, 300), (0, 300)], dtype=float)
F2C_L_FIELD_M = 3162.0


def _latlon_area(local: np.ndarray, name: str) -> SearchArea:
    frame = LocalFrame(47.0, 8.0)
    return SearchArea(vertices=[(float(a), float(b)) for a, b in frame.points_to_geodetic(local)], name=name)


def _leg_overflight(lines: np.ndarray, area: np.ndarray) -> float:
    """Longest piece of any leg flown outside the area (a leg along an edge counts as inside)."""
    poly = Polygon(area).buffer(0.01)  # 1 cm: a leg along a tilted edge is inside
    worst = 0.0
    for leg in lines:
        out = LineString(leg).difference(poly)
        worst = max([worst, *(g.length for g in getattr(out, "geoms", [out]) if not g.is_empty)])
    return worst


def test_l_field_sweeps_along_an_arm_in_one_cell() -> None:
    sw = cover_area(L_FIELD, 20.0)
    assert sw.meta["cells"] == 1
    assert len(sw.lines) == 15
    assert abs(sw.length - F2C_L_FIELD_M) <= 0.05 * F2C_L_FIELD_M  # was 4,363 m in 23 legs, 3 cells
    missed = Polygon(L_FIELD).difference(swept_footprint(sw.points, 10.0 + 1e-6))
    assert missed.area <= 1e-6 * Polygon(L_FIELD).area


def test_planner_picks_the_shortest_angle_for_a_concave_area_given_in_latlon() -> None:
    plan = plan_search(
        _latlon_area(L_FIELD, "L"), [DroneSpec(name="a", endurance_s=1e5)], spacing_from_swath(20.0, 30.0)
    )
    # the lat/lon round trip tilts the edges by ~1e-5 rad, which may split off a sliver cell
    assert plan.summary["sweep"]["lines"] == 15
    assert plan.summary["total_length_m"] <= 1.05 * F2C_L_FIELD_M
    assert plan.coverage.covered_pct >= 99.99


def test_angle_candidates_start_with_the_minimum_height_and_stay_bounded() -> None:
    cands = candidate_angles(L_FIELD)
    assert cands[0] == pytest.approx(math.radians(45.0))  # the hull's narrowest direction
    assert len(cands) == 3  # 45 deg, then the two edge directions (0 and 90 deg)
    blob = np.column_stack([np.cos(np.linspace(0, 6.2, 1000)), np.sin(np.linspace(0, 6.2, 1000))]) * 500
    assert len(candidate_angles(blob, 1)) == 1
    convex = np.array([(0, 0), (200, 0), (200, 50), (0, 50)], dtype=float)
    assert sweep_angle(convex, 20.0) == pytest.approx(0.0, abs=1e-9)  # a rectangle keeps its long legs


def test_exact_multiple_height_in_latlon_gets_no_extra_leg() -> None:
    rect = np.array([(0, 0), (300, 0), (300, 200), (0, 200)], dtype=float)
    plan = plan_search(
        _latlon_area(rect, "rect"), [DroneSpec(name="a", endurance_s=1e5)], spacing_from_swath(20.0, 30.0)
    )
    assert plan.summary["sweep"]["lines"] == 10  # was 11 legs at 18.18 m
    assert plan.summary["sweep"]["spacing_m"] == pytest.approx(20.0, abs=1e-6)
    ys, spacing = line_grid(0.0, 200.0 + 2.5e-8, 20.0)
    assert len(ys) == 10 and spacing == pytest.approx(20.0)
    assert len(line_grid(0.0, 200.01, 20.0)[0]) == 11  # a real centimetre more still needs a leg


@pytest.mark.parametrize("angle_deg", [0.0, 90.0])
def test_no_leg_leaves_the_area_beyond_the_turn_margin(angle_deg: float) -> None:
    sw = cover_area(L_FIELD, 20.0, angle=math.radians(angle_deg))
    # before: a leg touching the inner edge only along a rounding sliver flew 180 m outside
    assert _leg_overflight(sw.lines, L_FIELD) <= sw.spacing / 2 + 1e-6
    missed = Polygon(L_FIELD).difference(swept_footprint(sw.points, 10.0 + 1e-6))
    assert missed.area <= 1e-6 * Polygon(L_FIELD).area


def test_tilted_l_field_legs_stay_within_the_turn_margin() -> None:
    """The L given in lat/lon: its arm's top edge is tilted by ~1e-5 rad and one strip ends 1.9 m above it."""
    local = _latlon_area(L_FIELD, "L").local()
    sw = cover_area(local, 20.0, angle=0.0)
    assert len(sw.lines) > 16  # 16 legs, one of them flown in two pieces
    assert _leg_overflight(sw.lines, local) <= sw.spacing / 2 + 1e-6  # before: 181 m
    missed = Polygon(local).difference(swept_footprint(sw.points, 10.0 + 1e-6))
    assert missed.area <= 1e-6 * Polygon(local).area


def test_psa_library_default_is_as_safe_as_the_cli() -> None:
    assert PsaConfig().track_margin_m == DEFAULT_TRACK_MARGIN_M == 2.0
    pts = np.random.default_rng(20).uniform(0.0, 120.0, (20, 2))
    plan = plan_psa(pts, drones=3, link_range=20.0, speed=4.0)
    assert plan.track_margin == DEFAULT_TRACK_MARGIN_M
    report = plan.check(sample_dt=0.5)
    assert report.ok, report.violations[:5]
    # flown within 2 m of the plan, neighbours stay within w = 20 m (before: planned up to 20 m)
    assert report.max_neighbour_distance <= 20.0 - 2 * DEFAULT_TRACK_MARGIN_M + 1e-6
