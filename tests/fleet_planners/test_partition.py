"""Capability-proportional partition: divide protocol, simulation of both strategies, planner API."""

from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import Point, Polygon, box

from gcs.planning.partition import (
    Raster,
    capability,
    divide_block,
    divide_polygon,
    meeting_schedule,
    partition_for_search,
    simulate,
    target_areas,
)


def _area() -> Polygon:
    outer = Polygon([(0, 0), (100, 0), (110, 60), (70, 90), (10, 80), (-5, 40)])
    return outer.difference(Point(40, 40).buffer(8)).difference(box(70, 20, 80, 35))


def test_target_areas_follow_eq_2() -> None:
    a = capability(np.array([3.0, 3.0, 6.0]), np.array([1.0, 0.5, 0.5]))
    assert a.tolist() == [6.0, 3.0, 6.0]
    assert target_areas(150.0, a).tolist() == pytest.approx([60.0, 30.0, 60.0])


def test_divide_polygon_is_exact_and_a_partition() -> None:
    area = _area()
    cap = capability(
        np.array([[3.0, 4.0, 5.0], [2.0, 3.0, 3.0]]), np.array([[1.0, 0.7, 0.6], [0.9, 0.5, 1.0]])
    )
    cells = divide_polygon(area, cap)
    want = target_areas(area.area, cap.ravel())
    got = np.array([c.area for row in cells for c in row])
    assert got == pytest.approx(want, rel=1e-6)
    union = cells[0][0]
    for row in cells:
        for cell in row:
            union = union.union(cell)
    assert union.symmetric_difference(area).area < 1e-6 * area.area
    # column 0 lies west of column 1: straight vertical cuts
    assert cells[0][0].bounds[2] <= cells[0][1].bounds[0] + 1e-6


def test_partition_for_search_gives_one_polygon_per_drone() -> None:
    area = _area()
    caps = [1.0, 2.0, 1.0, 1.5, 0.5]
    parts = partition_for_search(area, caps)
    assert len(parts) == 5
    assert [p.area for p in parts] == pytest.approx(list(target_areas(area.area, np.array(caps))), rel=1e-6)


def test_meeting_schedule_each_pair_once_per_period_nobody_twice_at_once() -> None:
    q = meeting_schedule(4, 5)
    pairs = [p for quarter in q for p in quarter]
    assert len(pairs) == len(set(pairs)) == 4 * 4 + 3 * 5
    for quarter in q:
        seen = [u for pair in quarter for u in pair]
        assert len(seen) == len(set(seen))


def test_divide_block_matches_capabilities() -> None:
    union = np.ones((40, 40), dtype=bool)
    a = np.array([[1.0, 3.0], [2.0, 2.0]])
    parts = divide_block(union, [(0, 0), (0, 1), (1, 0), (1, 1)], a)
    sizes = np.array([[parts[(r, c)].sum() for c in range(2)] for r in range(2)])
    assert sizes.sum() == 1600
    assert sizes / 1600 == pytest.approx(a / a.sum(), abs=2e-3)


@pytest.mark.parametrize("strategy", ["one-to-one", "block"])
def test_simulation_converges_and_stays_a_partition(strategy: str) -> None:
    raster = Raster.from_polygon(_area(), 1.0)
    rng = np.random.default_rng(3)
    a = capability(3.0, rng.uniform(0.5, 1.0, (4, 4)))
    res = simulate(raster, a, strategy, max_periods=60, tol=0.01)  # type: ignore[arg-type]
    periods = res.periods_to(0.01)
    assert periods is not None and periods < 60
    assert res.errors[0] > 0.05  # the initial grid is unsuitable
    stack = np.stack(list(res.masks.values()))
    assert (stack.sum(axis=0) == raster.inside).all()  # disjoint and covering once converged


def test_block_sharing_first_division_takes_about_a_period() -> None:
    """Seed 003: in a (2,2) block the first division completes after 1.25 periods."""
    raster = Raster.from_polygon(box(0, 0, 60, 60), 1.0)
    a = capability(3.0, np.array([[1.0, 0.5], [0.5, 1.0]]))
    res = simulate(raster, a, "block", max_periods=3, tol=None)
    done = res.periods_to(0.01)
    assert done is not None and 0.5 <= done <= 1.25
    assert res.divisions >= 4
