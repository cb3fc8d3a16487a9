"""PSA: constraints re-checked by check_plan, Theorem 1 accounting, baselines on the paper's setting."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs.planning._psa_geometry import convex_hull, edge_frame, locate
from gcs.planning._psa_trajectory import FleetTrajectory
from gcs.planning.baselines import minmax_routes, route_lengths, split_tour, tsp_split_routes
from gcs.planning.psa import check_plan, excursion_shifts, plan_psa


def _paper_instance(n: int, seed: int) -> np.ndarray:
    """Seed 004 Fig. 11 setting: n random targets in a 120 m x 120 m field."""
    return np.random.default_rng(seed).uniform(0.0, 120.0, (n, 2))


@pytest.mark.parametrize("n", [5, 10, 20, 30])
def test_paper_setting_plans_are_connected_and_complete(n: int) -> None:
    pts = _paper_instance(n, seed=n)
    plan = plan_psa(pts, drones=3, link_range=20.0, speed=4.0)
    report = check_plan(plan.trajectory, pts, 20.0, sample_dt=0.25, max_speed=4.0)
    assert report.ok, report.violations[:5]
    assert report.max_target_miss < 1e-6
    c = plan.costs
    assert c.fleet_length - c.lower_bound <= c.adjust + 1e-6  # Theorem 1 with the honest L_adjust
    assert c.fleet_length == pytest.approx(max(report.lengths))


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(1, 40),
    drones=st.integers(1, 5),
    link=st.floats(3.0, 60.0),
    seed=st.integers(0, 10_000),
    adaptive=st.booleans(),
)
def test_any_instance_is_feasible_and_bounded(
    n: int, drones: int, link: float, seed: int, adaptive: bool
) -> None:
    pts = np.random.default_rng(seed).uniform(0.0, 120.0, (n, 2))
    plan = plan_psa(pts, drones, link, adaptive_width=adaptive)
    report = plan.check(sample_dt=0.5)
    assert report.ok, report.violations[:5]
    c = plan.costs
    assert c.fleet_length - c.lower_bound <= c.adjust + 1e-6
    assert sum(len(r.targets) for r in plan.rounds) == n


def test_rounds_peel_rings_of_width_w_max() -> None:
    pts = _paper_instance(60, seed=7)
    plan = plan_psa(pts, drones=3, link_range=10.0)
    assert len(plan.rounds) >= 2
    for k, rnd in enumerate(plan.rounds[:-1]):
        later = np.concatenate([r.targets for r in plan.rounds[k + 1 :]])
        depth, _, _ = locate(edge_frame(rnd.hull), pts[later])
        assert np.all(depth > 20.0)  # everything left for later is deeper than w_max = 2 w
    # the transfer points lie on one segment c_1 .. c_K
    c = np.array([r.entry for r in plan.rounds])
    d = c[-1] - c[0]
    cross = d[0] * (c[:, 1] - c[0, 1]) - d[1] * (c[:, 0] - c[0, 0])
    assert np.allclose(cross, 0.0, atol=1e-6)


def test_remark_1_is_wrong_formation_turns_cost_the_inner_drone() -> None:
    """Targets only on the hull: the paper says L_PSA = sum L_k, but inner drones swing at corners."""
    square = np.array([[0, 0], [60, 0], [60, 60], [0, 60], [30, 10]], dtype=float)
    plan = plan_psa(square, drones=3, link_range=20.0, adaptive_width=False)
    c = plan.costs
    assert c.fleet_length > c.lower_bound + c.scan_adjust + 1.0
    assert c.fleet_length - c.lower_bound <= c.adjust + 1e-6


def test_theorem_1_bound_is_not_a_lower_bound_on_the_optimum() -> None:
    """A connected 3-drone plan on a 20 m square flies 20 m; Theorem 1 'bounds' it by 80 m."""
    corners = np.array([[0, 0], [20, 0], [20, 20], [0, 20]], dtype=float)
    times = np.array([0.0, 5.0])
    positions = np.array([[[0, 0], [20, 0]], [[0, 20], [20, 20]], [[10, 10], [10, 10]]], dtype=float)
    traj = FleetTrajectory(times=times, positions=positions, sync=np.array([True, True]))
    assert check_plan(traj, corners, link_range=100.0).ok
    psa = plan_psa(corners, drones=3, link_range=100.0)
    assert psa.costs.lower_bound == pytest.approx(80.0)
    assert max(traj.lengths()) < psa.costs.lower_bound


def test_checker_reports_disconnection_and_missed_targets() -> None:
    times = np.array([0.0, 10.0, 20.0])
    positions = np.array([[[0, 0], [0, 0], [0, 0]], [[5, 0], [50, 0], [5, 0]]], dtype=float)
    traj = FleetTrajectory(times=times, positions=positions, sync=np.array([True, False, True]))
    report = check_plan(traj, np.array([[0, 0], [30, 30]]), link_range=10.0, sample_dt=1.0, max_speed=4.0)
    assert not report.ok
    assert report.count("connectivity") > 0
    assert report.count("fleet-split") > 0
    assert report.count("coverage") == 1
    assert report.count("speed") > 0  # 45 m in 10 s


def test_excursion_shifts_choose_cheapest_direction() -> None:
    # drones at depths 0, 10, 20; a target at 18 is 2 m above drone 2's line: go outward 2 m
    assert excursion_shifts(np.array([18.0]), 10.0, 3) == pytest.approx((2.0, 0.0))
    assert excursion_shifts(np.array([13.0]), 10.0, 3) == pytest.approx((0.0, 3.0))
    assert excursion_shifts(np.array([20.0, 0.0]), 10.0, 3) == pytest.approx((0.0, 0.0))
    out, inn = excursion_shifts(np.array([2.0, 8.0]), 10.0, 3)
    assert out + inn == pytest.approx(4.0)


def test_degenerate_inputs() -> None:
    for pts in (np.array([[5.0, 5.0]]), np.array([[0.0, 0.0], [10.0, 0.0], [30.0, 0.0]])):
        plan = plan_psa(pts, drones=3, link_range=5.0)
        assert plan.check().ok
    assert len(convex_hull(np.array([[0, 0], [1, 1], [2, 2]], dtype=float))) == 2
    with pytest.raises(ValueError):
        plan_psa(np.zeros((0, 2)), 3, 10.0)


@pytest.mark.parametrize("n", [5, 15, 30])
def test_baselines_on_the_same_instances(n: int) -> None:
    pts = _paper_instance(n, seed=100 + n)
    plan = plan_psa(pts, drones=3, link_range=20.0)
    start = plan.rounds[0].entry
    for routes in (minmax_routes(pts, start, 3, time_limit_s=0.3), tsp_split_routes(pts, start, 3, 0.3)):
        assert len(routes) == 3
        visited = np.vstack([r[1:] for r in routes if len(r) > 1])
        assert sorted(map(tuple, visited)) == sorted(map(tuple, pts))
        # no connectivity constraint: a lower reference for PSA's longest route
        assert route_lengths(routes).max() <= plan.costs.fleet_length + 1e-6


def test_split_tour_is_optimal_against_brute_force() -> None:
    rng = np.random.default_rng(5)
    pts = rng.uniform(0, 50, (7, 2))
    start = np.zeros(2)
    tour = list(range(7))
    pieces = split_tour(pts, start, tour, 3)
    best = route_lengths([np.vstack([start, pts[p]]) for p in pieces]).max()
    brute = np.inf
    for i in range(8):
        for j in range(i, 8):
            parts = [tour[:i], tour[i:j], tour[j:]]
            brute = min(brute, route_lengths([np.vstack([start, pts[p]]) for p in parts]).max())
    assert best == pytest.approx(brute)
