"""Leg ends cut back where the turns see the area (issue 27): worked examples with the lengths
computed by hand, and the check that gives a leg its strip-rule ends back when a cut would leave
ground unseen."""

import math

import numpy as np
import pytest
from shapely.geometry import Polygon

from gcs.planning.patterns import strip_extent, swept_footprint, zigzag
from gcs.planning.turn_trim import half_strip_extents, trim_at_turns, trimmed_ends


def _unseen(poly: np.ndarray, points: np.ndarray, half: float) -> float:
    return float(Polygon(poly).difference(swept_footprint(points, half + 1e-6)).area)


def test_parallelogram_turns_see_half_of_each_slanted_overshoot() -> None:
    # 45 degree sides, legs along x at y = 10, 30, ..., 90 (100 m / 20 m: five legs, spacing 20).
    # The strip rule runs each leg to its strip's extent [y - 10, y + 210]: 5 x 220 m of legs and
    # four 20 x 20 m diagonal jogs, 1,213.1 m. At each turn the leg whose own half strip (the one
    # away from the turn) is the narrow one ends 10 m earlier; the jog grows to 30 x 20 m.
    par = np.array([(0, 0), (200, 0), (300, 100), (100, 100)], dtype=float)
    sw = zigzag(par, 20.0, 0.0)
    strip_rule = 5 * 220.0 + 4 * math.hypot(20.0, 20.0)
    expected = 5 * 220.0 - 4 * 10.0 + 4 * math.hypot(30.0, 20.0)
    assert sw.length == pytest.approx(expected, abs=1e-3)
    assert strip_rule - sw.length == pytest.approx(8.92, abs=0.01)
    # leg 0 flies left to right and turns up on the right: its right end moves from 220 to 210
    assert np.allclose(sw.lines[0], [[0.0, 10.0], [210.0, 10.0]], atol=1e-5)
    assert _unseen(par, sw.points, 10.0) <= 1e-6 * Polygon(par).area


def test_edges_square_to_the_legs_leave_nothing_to_cut() -> None:
    rect = np.array([(0, 0), (100, 0), (100, 40), (0, 40)], dtype=float)
    sw = zigzag(rect, 20.0, 0.0)
    assert sw.length == pytest.approx(2 * 100.0 + 20.0)  # the jog already runs along the edge


def test_footprint_wider_than_the_spacing_cuts_every_end() -> None:
    # 50 m high at step 20: three legs 16.67 m apart; a footprint of half width 10 sees the strip's
    # corner from sqrt(10^2 - 8.33^2) = 5.53 m inside it; every leg end moves in by that much, for
    # the 32-gon disc of swept_footprint by sqrt((10 cos(pi/32))^2 - 8.33^2) = 5.44 m
    rect = np.array([(0, 0), (100, 0), (100, 50), (0, 50)], dtype=float)
    sw = zigzag(rect, 20.0, 0.0)
    cut = math.sqrt((10.0 * math.cos(math.pi / 32)) ** 2 - (50.0 / 6.0) ** 2)
    assert cut == pytest.approx(5.44, abs=0.01)
    assert sw.length == pytest.approx(3 * (100.0 - 2 * cut) + 2 * 50.0 / 3.0, abs=1e-6)
    assert _unseen(rect, sw.points, 10.0) <= 1e-9 * Polygon(rect).area


def test_trimmed_ends_cut_only_the_ends_next_to_a_turn() -> None:
    legs = [[(10.0, 0.0, 120.0)], [(30.0, -20.0, 140.0)], [(50.0, 5.0, 100.0)]]
    halves = [((0.0, 110.0), (-5.0, 118.0)), ((-10.0, 125.0), (-20.0, 140.0)), ((3.0, 99.0), (5.0, 100.0))]
    out = trimmed_ends(legs, halves, left_to_right_first=True)
    # turn 0-1 on the right: leg 0 to its lower half's 110, leg 1 to its upper half's 140 (no change);
    # turn 1-2 on the left: leg 1 to its lower half's -10, leg 2 to its upper half's 5 (no change);
    # the outer ends (leg 0's left, leg 2's right) stay put
    assert out == [[(10.0, 0.0, 110.0)], [(30.0, -10.0, 140.0)], [(50.0, 5.0, 100.0)]]
    # never past the leg's other end, and a leg of several pieces is left alone
    short = trimmed_ends([[(10.0, 50.0, 60.0)], [(30.0, 0.0, 60.0), (35.0, 60.0, 80.0)]],
                         [((0.0, 20.0), None), (None, (0.0, 10.0))], True)  # fmt: skip
    assert short == [[(10.0, 50.0, 50.0)], [(30.0, 0.0, 60.0), (35.0, 60.0, 80.0)]]


def test_a_cut_that_leaves_ground_unseen_gives_the_leg_its_strip_ends_back() -> None:
    # a 30 m tooth between the two legs' ordinates: by the half-strip rule leg 0 would end at 100,
    # but the tooth's tip (130, 15) is 30 m from the vertical jog; the check restores leg 0's end
    toothed = Polygon([(0, 0), (100, 0), (100, 12), (130, 15), (100, 18), (100, 40), (0, 40)])
    ys = [10.0, 30.0]
    legs = [[(y, *strip_extent(toothed, y, 10.0))] for y in ys]  # type: ignore[misc]
    assert legs[0][0][2] == pytest.approx(130.0)
    halves = half_strip_extents(toothed, ys, ys, 10.0)
    assert trimmed_ends(legs, halves, True)[0][0][2] == pytest.approx(100.0)  # what the rule alone says
    lines = trim_at_turns(toothed, legs, ys, 10.0, True)
    assert lines[0, 1, 0] == pytest.approx(130.0)
    assert toothed.difference(swept_footprint(lines.reshape(-1, 2), 10.0 + 1e-6)).area <= 1e-6


def _random_fields(seed: int, n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        k = int(rng.integers(5, 10))
        ang = (np.arange(k) + rng.uniform(0.0, 0.7, k)) * 2 * math.pi / k
        r = rng.uniform(100.0, 250.0) * rng.uniform(0.4, 1.0, k)
        out.append(np.column_stack([r * np.cos(ang), r * np.sin(ang)]))
    return out


@pytest.mark.parametrize("field", _random_fields(45, 4), ids=lambda f: f"{len(f)}-gon")
def test_sweep_angle_is_the_shortest_checked_candidate(field: np.ndarray) -> None:
    # candidates are compared by the unchecked trimmed length; a cut the check gives back must
    # not leave a longer plan than another candidate's checked one
    from gcs.planning.decompose import candidate_angles, cover_area, sweep_angle
    from gcs.planning.polygon import PolygonType, classify

    plan = cover_area if classify(field) == PolygonType.CONCAVE else zigzag
    chosen = plan(field, 20.0, sweep_angle(field, 20.0)).length
    assert chosen <= min(plan(field, 20.0, a).length for a in candidate_angles(field)) * (1 + 1e-9)
    seen = plan(field, 20.0, sweep_angle(field, 20.0)).points
    assert _unseen(field, seen, 10.0) <= 1e-6 * Polygon(field).area


def test_no_plan_beats_the_physical_floor() -> None:
    # the bench's floor: a path of length L with a footprint w wide sees at most w L + pi w^2 / 4
    from bench.bench_planning import L_FIELD, _fly, floor_m_per_ha

    assert floor_m_per_ha(1e4, 20.0) == pytest.approx((1e4 - math.pi * 100.0) / 20.0)
    for field in (L_FIELD, *_random_fields(46, 2)):
        r = _fly(field, 20.0)
        assert r["covered_pct"] >= 99.999
        assert r["floor_m_per_ha"] < r["m_per_ha"] < 1.3 * r["floor_m_per_ha"]
