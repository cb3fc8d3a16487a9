"""RSA on hand-built maps: zone counts, coverage, flight budget, separated lanes."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import LineString, Polygon

from gcs.planning._rsa_channels import channel_count, channel_sets
from gcs.planning.rsa import MissedMap, RsaError, label_zones, plan_rsa, separate_lanes, zone_rectangles


def _grid(shape: tuple[int, int], holes: list[tuple[slice, slice]]) -> np.ndarray:
    g = np.ones(shape, dtype=np.uint8)
    for r, c in holes:
        g[r, c] = 0
    return g


def test_zone_count_uses_eight_connectivity_and_merges_labels() -> None:
    g = np.ones((12, 12), dtype=np.uint8)
    g[1, 1] = g[2, 2] = g[3, 3] = 0  # diagonal chain: one zone
    # a "U" that a single left-to-right pass first labels as two zones (the paper's second pass)
    g[6:10, 6] = 0
    g[6:10, 9] = 0
    g[9, 6:10] = 0
    g[0, 11] = 0
    labels, n = label_zones(g)
    assert n == 3
    assert labels[1, 1] == labels[3, 3]
    assert labels[6, 6] == labels[6, 9]


def test_zone_rectangles_are_minimal_and_merged_when_touching() -> None:
    g = _grid((40, 40), [(slice(2, 6), slice(2, 12)), (slice(20, 30), slice(20, 24))])
    zones, n = zone_rectangles(MissedMap(g, 1.0))
    assert n == 2 and len(zones) == 2
    areas = sorted(Polygon(z.rectangle).area for z in zones)
    assert areas == pytest.approx([40.0, 40.0])
    # a diagonal bar: the rotated rectangle is much smaller than the axis-aligned box
    d = np.ones((30, 30), dtype=np.uint8)
    for i in range(25):
        d[i, i] = d[i, min(i + 1, 29)] = 0
    (zone,), _ = zone_rectangles(MissedMap(d, 1.0))
    assert Polygon(zone.rectangle).area < 0.3 * 26 * 26
    # a "C" and a cell in its hollow are separate zones but the C's rectangle covers the cell
    c = np.ones((20, 20), dtype=np.uint8)
    c[2, 2:12] = c[12, 2:12] = c[2:13, 2] = 0
    c[7, 8] = 0
    z3, n3 = zone_rectangles(MissedMap(c, 1.0))
    assert n3 == 2 and len(z3) == 1 and z3[0].labels == (1, 2)


def test_channel_cases() -> None:
    rect = np.array([[0, 0], [0, 3], [20, 3], [20, 0]], dtype=float)  # l = 20, w = 3
    assert len(channel_sets(rect, 4.0)) == 1  # case 2
    assert len(channel_sets(np.array([[0, 0], [0, 3], [3, 3], [3, 0]], float), 4.0)) == 2  # case 1
    assert len(channel_sets(np.array([[0, 0], [0, 12], [12, 12], [12, 0]], float), 4.0)) == 4  # case 4
    assert len(channel_sets(np.array([[0, 0], [0, 9], [20, 9], [20, 0]], float), 4.0)) == 2  # case 5
    assert channel_count(4.1, 4.0) == 2 and channel_count(4.0, 4.0) == 1


def _check_plan(missed: MissedMap, d_nbh: float, d_flt: float, d_sfty: float, side: str) -> None:
    plan = plan_rsa(missed, d_nbh, d_flt, side, d_sfty)  # type: ignore[arg-type]
    cells = missed.cell_centres(missed.grid == 0)
    rects = shapely.union_all([Polygon(z.rectangle).buffer(1e-6) for z in plan.zones])
    assert shapely.contains_xy(rects, cells[:, 0], cells[:, 1]).all()
    lines = shapely.union_all([LineString(d.path) for d in plan.drones])
    assert np.all(shapely.distance(lines, shapely.points(cells)) <= d_nbh / 2 + 1e-6)
    assert all(d.length <= d_flt + 1e-6 for d in plan.drones)
    covered = sorted(z for d in plan.drones for z in d.zones)
    assert covered == list(range(len(plan.zones)))
    for lanes in ("entry_lane", "exit_lane"):
        for a, b in itertools.combinations(plan.drones, 2):
            gap = LineString(getattr(a, lanes)).distance(LineString(getattr(b, lanes)))
            assert gap >= d_sfty - 1e-6


@pytest.mark.parametrize("side", ["west", "east", "south", "north"])
def test_hand_built_map_every_side(side: str) -> None:
    g = _grid(
        (80, 100),
        [(slice(5, 15), slice(10, 40)), (slice(40, 70), slice(60, 66)), (slice(60, 75), slice(5, 20))],
    )
    g[30, 30] = 0
    _check_plan(MissedMap(g, 2.0), d_nbh=8.0, d_flt=900.0, d_sfty=6.0, side=side)


def test_tighter_budget_needs_more_drones() -> None:
    g = _grid((60, 60), [(slice(5 + 12 * k, 10 + 12 * k), slice(20, 50)) for k in range(4)])
    many = plan_rsa(MissedMap(g, 1.0), 4.0, 200.0)
    few = plan_rsa(MissedMap(g, 1.0), 4.0, 2000.0)
    assert len(few.drones) == 1 < len(many.drones)
    with pytest.raises(RsaError):
        plan_rsa(MissedMap(g, 1.0), 4.0, 50.0)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), d_nbh=st.floats(2.0, 12.0), d_sfty=st.floats(0.0, 10.0))
def test_random_maps(seed: int, d_nbh: float, d_sfty: float) -> None:
    rng = np.random.default_rng(seed)
    g = np.ones((50, 50), dtype=np.uint8)
    for _ in range(rng.integers(1, 6)):
        r, c = rng.integers(0, 45, 2)
        h, w = rng.integers(1, 8, 2)
        g[r : r + h, c : c + w] = 0
    _check_plan(MissedMap(g, 1.0), d_nbh, 600.0, d_sfty, "west")


def test_separate_lanes_is_minimal_and_spaced() -> None:
    v = np.array([0.0, 1.0, 20.0, 2.0])
    out = separate_lanes(v, 5.0)
    s = np.sort(out)
    assert np.all(np.diff(s) >= 5.0 - 1e-9)
    assert out[2] == pytest.approx(20.0)  # far lane untouched
    assert np.mean(out[[0, 1, 3]]) == pytest.approx(1.0)  # a clash is spread about its centre
