import numpy as np
import pytest
from shapely.geometry import Polygon

from gcs.planning.division import (
    DroneSpec,
    InsufficientCapabilityError,
    capability_fractions,
    cut_by_area,
    cut_path,
    path_division,
    region_division,
    split_lengths,
)
from gcs.planning.patterns import path_length, zigzag

RECT = [(0, 0), (200, 0), (200, 150), (0, 150)]


def test_paper_example_870m_c03_300m_gives_261m():
    lengths = split_lengths(870.0, [0.3, 0.5, 0.2], [300.0, 1000.0, 1000.0])
    assert lengths[0] == pytest.approx(261.0)
    assert lengths.sum() == pytest.approx(870.0)


def test_capped_share_goes_to_drones_with_spare_range():
    lengths = split_lengths(870.0, [0.5, 0.3, 0.2], [300.0, 1000.0, 1000.0])
    assert lengths[0] == pytest.approx(300.0)
    assert lengths[1] / lengths[2] == pytest.approx(1.5)
    assert lengths.sum() == pytest.approx(870.0)


def test_fleet_too_weak_is_an_error_not_a_gap():
    # seed 000 Fig. 12b: the paper leaves the tail unflown; we refuse and say how much
    with pytest.raises(InsufficientCapabilityError) as info:
        split_lengths(870.0, [0.5, 0.3, 0.2], [300.0, 200.0, 200.0])
    assert info.value.shortfall_m == pytest.approx(170.0)
    partial = split_lengths(870.0, [0.5, 0.3, 0.2], [300.0, 200.0, 200.0], allow_partial=True)
    assert partial.sum() == pytest.approx(700.0)


def test_capabilities_from_battery_endurance_speed():
    d = DroneSpec(name="a", battery=0.5, endurance_s=1000, speed_mps=4, reserve=0.25)
    assert d.range_m == pytest.approx(1500.0)
    assert capability_fractions([100, 300]) == pytest.approx([0.25, 0.75])


def test_cut_path_pieces_concatenate():
    pts = np.array([(0, 0), (100, 0), (100, 10), (0, 10)], float)
    pieces = cut_path(pts, [50, 100, 60])
    assert [path_length(p) for p in pieces] == pytest.approx([50, 100, 60])
    assert np.allclose(pieces[0][-1], pieces[1][0]) and np.allclose(pieces[2][-1], [0, 10])


def test_path_division_respects_ranges_and_home_cost():
    sw = zigzag(RECT, 20.0)
    drones = [DroneSpec(name=f"d{i}", battery=b) for i, b in enumerate([1.0, 0.6, 0.3])]
    shares = path_division(sw.points, drones, home=(-100.0, -100.0))
    assert sum(s.survey_m for s in shares) == pytest.approx(sw.length, rel=1e-6)
    for s, d in zip(shares, drones, strict=True):
        assert s.total_m <= d.range_m + 1e-6
        assert s.transit_m > 0
    assert shares[0].survey_m > shares[1].survey_m > shares[2].survey_m


def test_path_division_too_far_from_home():
    sw = zigzag(RECT, 20.0)
    weak = [DroneSpec(name="w", battery=0.05)]
    with pytest.raises(InsufficientCapabilityError):
        path_division(sw.points, weak, home=(-100.0, -100.0))


def test_region_division_fig13_fractions():
    fractions = [0.533, 0.3297, 0.1374]
    area = [(0, 0), (120, -10), (180, 60), (90, 140), (-10, 90)]
    drones = [DroneSpec(name=f"d{i}") for i in range(3)]
    shares = region_division(area, drones, angle=0.3, fractions=fractions, tol=1e-6)
    got = [s.region.area / Polygon(area).area for s in shares]
    want = np.asarray(fractions) / sum(fractions)
    assert got == pytest.approx(want, abs=2e-6)
    # slices tile the area without overlap
    union = shares[0].region.union(shares[1].region).union(shares[2].region)
    assert union.area == pytest.approx(Polygon(area).area)
    assert shares[0].region.intersection(shares[1].region).area == pytest.approx(0.0, abs=1e-6)


def test_region_division_by_capability_after_home_cost():
    drones = [DroneSpec(name="a", battery=1.0), DroneSpec(name="b", battery=0.5)]
    shares = region_division(RECT, drones, angle=0.0, home=(0.0, 0.0))
    usable = [d.range_m - 2 * np.hypot(200, 150) for d in drones]
    assert shares[0].fraction == pytest.approx(usable[0] / sum(usable), abs=1e-5)


def test_cut_by_area_bisection_tolerance():
    q = Polygon(RECT)
    cuts = cut_by_area(q, [1, 1, 2], tol=1e-9)
    assert cuts == pytest.approx([37.5, 75.0], abs=1e-6)


def test_partition_division_gives_areas_in_proportion_to_range_and_covers_the_area():
    from gcs.planning.areas import area_from_latlon
    from gcs.planning.camera import spacing_from_swath
    from gcs.planning.geodesy import LocalFrame
    from gcs.planning.planner import PlanConfig, plan_search

    frame = LocalFrame(47.39, 8.54)
    lats, lons = frame.to_geodetic(np.array([e for e, _ in RECT]), np.array([n for _, n in RECT]))
    area = area_from_latlon(list(zip(lats.tolist(), lons.tolist(), strict=True)))
    drones = [DroneSpec(name=f"d{i}", battery=b, endurance_s=1800) for i, b in enumerate((1.0, 0.5, 0.25))]
    plan = plan_search(area, drones, spacing_from_swath(20, 30), PlanConfig(division="partition"))
    areas = np.array([r.area for r in plan.regions_local])
    ranges = np.array([d.range_m for d in drones])
    assert areas / areas.sum() == pytest.approx(ranges / ranges.sum(), abs=0.01)
    union = plan.regions_local[0].union(plan.regions_local[1]).union(plan.regions_local[2])
    assert union.area == pytest.approx(Polygon(plan.area_local).area, rel=1e-3)
    assert plan.coverage.covered_pct > 99.0
    assert plan.summary["division"] == "partition"


def _six_legs() -> np.ndarray:
    """A 610 m zigzag (six 100 m legs, 2 m apart) whose ends are 5 m from home at (0, 5)."""
    pts: list[tuple[float, float]] = []
    for k in range(6):
        y = 2.0 * k
        pts += [(0.0, y), (100.0, y)] if k % 2 == 0 else [(100.0, y), (0.0, y)]
    return np.array(pts)


def _drone(name: str, range_m: float) -> DroneSpec:
    return DroneSpec(name=name, endurance_s=range_m / 5.0 / 0.8)  # 5 m/s, 20 % reserve


@pytest.mark.parametrize("range_m", [620.0, 650.0, 700.0, 1000.0])
def test_path_division_plans_a_path_the_drone_can_fly(range_m: float) -> None:
    # 610 m of path + 10 m of trips: the paper's bound (twice the farthest waypoint, ~200 m)
    # refused this at every range below 810 m.
    pts = _six_legs()
    assert path_length(pts) == pytest.approx(610.0)
    (share,) = path_division(pts, [_drone("a", range_m)], home=(0.0, 5.0))
    assert share.survey_m == pytest.approx(610.0)
    assert share.transit_m == pytest.approx(10.0)
    assert share.total_m <= range_m + 1e-6


def test_path_division_shortfall_is_exact() -> None:
    with pytest.raises(InsufficientCapabilityError) as short:
        path_division(_six_legs(), [_drone("a", 619.0)], home=(0.0, 5.0))
    assert short.value.shortfall_m == pytest.approx(1.0, abs=0.2)


def test_short_fleet_uses_every_drone_to_its_range() -> None:
    pts = _six_legs()
    up12, up24 = np.array([0.0, 12.0]), np.array([0.0, 24.0])
    long_path = np.vstack([pts, pts[::-1] + up12, pts + up24])  # 1830 m
    fleet = [_drone("big", 1200.0), _drone("small", 300.0)]
    with pytest.raises(InsufficientCapabilityError) as short:
        path_division(long_path, fleet, home=(0.0, 5.0))
    shares = path_division(long_path, fleet, home=(0.0, 5.0), allow_partial=True)
    for s, d in zip(shares, fleet, strict=True):
        assert s.total_m == pytest.approx(d.range_m, abs=0.01)  # nobody goes home with range to spare
    flown = sum(s.survey_m for s in shares)
    assert short.value.shortfall_m == pytest.approx(path_length(long_path) - flown, abs=0.01)


def test_path_division_shares_follow_capability_after_the_real_trips() -> None:
    fleet = [_drone("big", 1200.0), _drone("small", 300.0)]
    shares = path_division(_six_legs(), fleet, home=(0.0, 5.0))
    assert sum(s.survey_m for s in shares) == pytest.approx(610.0)
    spare = [d.range_m - s.transit_m for s, d in zip(shares, fleet, strict=True)]
    assert shares[0].survey_m / shares[1].survey_m == pytest.approx(spare[0] / spare[1], rel=0.02)
