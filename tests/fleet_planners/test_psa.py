"""PSA: constraints re-checked by check_plan, Theorem 1 accounting, baselines on the paper's setting."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs.planning._psa_geometry import convex_hull, edge_frame, locate
from gcs.planning._psa_mission import psa_mission
from gcs.planning._psa_trajectory import FleetTrajectory, TrajectoryBuilder, formation, pivot
from gcs.planning.baselines import minmax_routes, route_lengths, split_tour, tsp_split_routes
from gcs.planning.geodesy import LocalFrame
from gcs.planning.psa import PsaInfeasible, check_plan, excursion_shifts, plan_psa, spacing_bounds
from protocol.actions import Hold, Waypoints


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
    margin=st.sampled_from([0.0, 1.0]),
)
def test_any_instance_is_feasible_and_bounded(
    n: int, drones: int, link: float, seed: int, adaptive: bool, margin: float
) -> None:
    pts = np.random.default_rng(seed).uniform(0.0, 120.0, (n, 2))
    if drones > 1 and link - 2 * margin < (5.0 + 2 * margin) / np.cos(np.pi / 8):
        with pytest.raises(PsaInfeasible, match="collision margin"):
            plan_psa(pts, drones, link, track_margin=margin, adaptive_width=adaptive)
        return
    plan = plan_psa(pts, drones, link, track_margin=margin, adaptive_width=adaptive)
    report = plan.check(sample_dt=0.5)
    assert report.ok, report.violations[:5]
    if drones > 1:  # the flown tracks keep both bounds with the track margin to spare
        assert report.max_neighbour_distance <= link - 2 * margin + 1e-6
        assert report.min_separation >= 5.0 + 2 * margin - 1e-6
    c = plan.costs
    assert c.fleet_length - c.lower_bound <= c.adjust + 1e-6
    assert sum(len(r.targets) for r in plan.rounds) == n


def test_rounds_peel_rings_of_width_w_max() -> None:
    pts = _paper_instance(60, seed=7)
    plan = plan_psa(pts, drones=3, link_range=10.0, track_margin=0.0)  # the paper: no tracking error
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
        plan = plan_psa(pts, drones=3, link_range=5.0, min_separation=3.0, track_margin=0.0)
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


def _turn(sync_each_substep: bool) -> FleetTrajectory:
    """Three drones 10 m apart turn 180 degrees about the outer one, in two 90-degree sub-steps."""
    b = TrajectoryBuilder(formation(np.zeros(2), np.array([0.0, 1.0]), 10.0, 3), speed=4.0)
    pivot(b, np.zeros(2), np.array([0.0, -1.0]), np.array([0.0, 1.0]), 10.0, min_separation=5.0)
    traj = b.build()
    if not sync_each_substep:  # the old task file: one barrier at the end of the whole turn
        traj = FleetTrajectory(
            traj.times, traj.positions, np.array([True] + [False] * (len(traj.times) - 2) + [True])
        )
    return traj


def test_turn_substeps_are_barriers_so_the_flown_line_keeps_w_and_the_margin() -> None:
    synced = _turn(True)
    assert synced.sync.sum() == 3  # start + one barrier per sub-step
    ok = check_plan(synced, np.zeros((0, 2)), 10.0, min_separation=5.0, flown_speed=4.0, sample_dt=0.05)
    assert ok.ok, ok.violations[:3]
    assert ok.max_neighbour_distance <= 10.0 + 1e-9
    assert ok.min_separation == pytest.approx(10.0 * np.cos(np.pi / 4))  # chords: s cos(45 deg)
    # Synced only at the end, equal-speed drones drift apart: the inner one lags on its longer chord.
    lagging = check_plan(_turn(False), np.zeros((0, 2)), 10.0, flown_speed=4.0, sample_dt=0.05)
    assert lagging.count("connectivity") > 0 and lagging.max_neighbour_distance > 10.5
    # The planner's own timing (all arrive together at every knot) hides it: that is why the
    # certificate checks the flown tracks.
    assert check_plan(_turn(False), np.zeros((0, 2)), 10.0).ok


def test_turn_is_split_finer_when_the_separation_floor_asks() -> None:
    b = TrajectoryBuilder(formation(np.zeros(2), np.array([0.0, 1.0]), 6.0, 3), speed=4.0)
    pivot(b, np.zeros(2), np.array([0.0, -1.0]), np.array([1.0, 0.0]), 6.0, min_separation=5.5)
    traj = b.build()
    # 90 degrees at 6 m would pass 6 cos 45 = 4.2 m: needs cos(a/2) >= 5.5/6, i.e. sub-steps <= 47 deg
    assert traj.sync.sum() - 1 == 2
    assert check_plan(traj, np.zeros((0, 2)), 6.0, min_separation=5.5, flown_speed=4.0).ok
    with pytest.raises(ValueError, match="cannot keep neighbours"):
        pivot(b, np.zeros(2), np.array([1.0, 0.0]), np.array([-1.0, 0.0]), 6.0, min_separation=6.5)


def test_flown_tracks_use_one_speed_per_leg_and_wait_at_barriers() -> None:
    times = np.array([0.0, 5.0, 10.0])
    positions = np.array([[[0, 0], [20, 0], [20, 20]], [[0, 5], [10, 5], [10, 25]]], dtype=float)
    traj = FleetTrajectory(times, positions, np.array([True, True, True]))
    flown = traj.flown(4.0)
    # leg 1: drone 0 flies 20 m in 5 s, drone 1 flies 10 m in 2.5 s then hovers until the barrier
    np.testing.assert_allclose(flown.at(np.array([2.5]))[:, 0], [[10, 0], [10, 5]])
    np.testing.assert_allclose(flown.at(np.array([4.0]))[:, 0], [[16, 0], [10, 5]])
    assert flown.times[-1] == pytest.approx(10.0)
    assert check_plan(traj, np.zeros((0, 2)), 100.0, max_speed=4.0, flown_speed=4.0).ok


def test_separation_is_exact_between_samples() -> None:
    """Two drones crossing between knots: sampling every 10 s would miss it; the check does not."""
    times = np.array([0.0, 10.0])
    positions = np.array([[[0, 0], [20, 0]], [[20, 1], [0, 1]]], dtype=float)
    report = check_plan(
        FleetTrajectory(times, positions, np.array([True, True])),
        np.zeros((0, 2)),
        100.0,
        sample_dt=10.0,
        min_separation=4.0,
    )
    assert report.min_separation == pytest.approx(1.0)
    assert report.count("separation") == 1 and report.violations[0].time == pytest.approx(5.0)


def test_refusal_names_both_bounds() -> None:
    assert spacing_bounds(20.0, 5.0, 1.0) == pytest.approx((7.0 / np.cos(np.pi / 8), 18.0))
    pts = _paper_instance(10, seed=1)
    with pytest.raises(PsaInfeasible, match=r"w = 8 m and at least 5 m apart.*needs w >= 9\.6 m"):
        plan_psa(pts, 3, 8.0, min_separation=5.0, track_margin=1.0)


def test_paper_setting_with_default_margins_flies_within_w_and_clear_of_the_margin() -> None:
    """n = 30, w = 20 m (the issue's case): the task file's legs keep both bounds as flown."""
    pts = _paper_instance(30, seed=30)
    plan = plan_psa(pts, 3, 20.0, 4.0, min_separation=5.0, track_margin=1.0)
    report = plan.check(sample_dt=0.1)
    assert report.ok, report.violations[:3]
    assert report.max_neighbour_distance <= 18.0 + 1e-6 and report.min_separation >= 7.0 - 1e-6
    task = psa_mission(plan.trajectory, LocalFrame(47.0, 8.0), 20.0, 4.0)
    actions = task.plans[0].actions
    legs = [a for a in actions if isinstance(a, Waypoints)]
    assert len(legs) == len(plan.trajectory.legs())
    # every leg ends at a barrier; where the line flies back (excursion ends) a hold stops it first
    for a, b in itertools.pairwise(actions):
        if isinstance(a, Waypoints):
            assert a.sync or (isinstance(b, Hold) and b.sync and b.seconds > 0.0)
    assert any(isinstance(a, Hold) for a in actions)
    assert {len(p.actions) for p in task.plans} == {len(task.plans[0].actions)}


def test_assembly_from_homes_arrives_together_without_crossing() -> None:
    pts = _paper_instance(30, seed=30)
    plan = plan_psa(pts, 3, 20.0, 4.0, min_separation=5.0, track_margin=1.0)
    start = plan.trajectory.positions[:, 0]
    # homes 6 m apart on a line parallel to the formation but in the opposite order
    axis = (start[2] - start[0]) / np.hypot(*(start[2] - start[0]))
    homes = np.array([start[0] + (60 - 6 * j) * axis + np.array([40.0, -30.0]) for j in range(3)])
    flown = plan.from_homes(homes)
    assert flown.assembly is not None
    assert flown.assembly.order.tolist() == [2, 1, 0]  # reversed: nobody crosses
    np.testing.assert_allclose(flown.trajectory.positions[:, 0], start[[2, 1, 0]])
    knots = flown.assembly.trajectory.positions
    for k in range(knots.shape[1] - 1):  # every sub-step: all arrive together
        dist = np.hypot(*(knots[:, k + 1] - knots[:, k]).T)
        np.testing.assert_allclose(flown.assembly.speeds[k] / 4.0, np.maximum(dist / dist.max(), 0.05))
    report = flown.check(sample_dt=0.1)
    assert report.ok, report.violations[:3]
    assert report.max_neighbour_distance <= 20.0 and report.min_separation >= 5.0
    task = psa_mission(
        flown.trajectory,
        LocalFrame(47.0, 8.0),
        20.0,
        4.0,
        assembly=flown.assembly.trajectory,
        assembly_speeds=flown.assembly.speeds.tolist(),
    )
    gotos = [[a for a in p.actions if a.kind == "goto"] for p in task.plans]
    assert all(len(g) == knots.shape[1] - 1 and all(a.sync for a in g) for g in gotos)
    assert [g[0].speed for g in gotos] == pytest.approx(flown.assembly.speeds[0].tolist())


def test_cli_refuses_a_link_range_too_short_for_the_margin(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from gcs.cli import main

    f = tmp_path / "t.json"
    f.write_text(
        json.dumps(
            {
                "origin": {"lat": 47.0, "lon": 8.0},
                "targets": [{"x": float(x), "y": float(y)} for x, y in _paper_instance(10, 2)],
                "config": {"drones": 3, "link_range_m": 8},
            }
        )
    )
    assert main(["plan", "--targets", str(f), "--method", "psa", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (
        "gcs plan: error: PSA cannot keep neighbours within the link range w = 8 m and at least 5 m "
        "apart (collision margin) with 2 m of tracking error: it needs w >= 13.7 m, or a smaller "
        "separation or track margin"
    )
    # with homes in the file the assembly is timed and certified too
    doc = json.loads(f.read_text())
    doc["config"]["link_range_m"] = 20
    doc["homes"] = [{"lat": 47.0, "lon": 8.0 + k * 8e-5} for k in range(3)]
    f.write_text(json.dumps(doc))
    assert main(["plan", "--targets", str(f), "--method", "psa", "--out", str(tmp_path / "o")]) == 0
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    assert report["check_ok"] and report["planned_max_neighbour_m"] <= 20.0
    assert report["planned_min_separation_m"] >= 5.0
    doc["homes"] = doc["homes"][:2]
    f.write_text(json.dumps(doc))
    assert main(["plan", "--targets", str(f), "--method", "psa", "--out", str(tmp_path / "o")]) == 2
    assert "2 homes for 3 drones" in capsys.readouterr().err
