"""Fleet-scale returns (issue 29): the layer colouring and landing spots of a 2,000-drone RTL are
computed without comparing every pair, and decide exactly what the pairwise scan decided."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs.cooperation import returns
from gcs.cooperation.returns import Returner, ReturnPlan, assign_layers, spread_landing_spots


def _layers_by_every_pair(
    drones: list[Returner], spacing: float, base_alt: float, layer_step: float
) -> list[ReturnPlan]:
    """The colouring as it was before issue 29: every leg against every coloured leg."""
    order = sorted(drones, key=lambda d: math.dist(d.position, d.home))
    layers: dict[str, int] = {}
    for drone in order:
        taken = {
            layers[other.ident]
            for other in order
            if other.ident in layers
            and returns.segment_distance(drone.position, drone.home, other.position, other.home) < spacing
        }
        layers[drone.ident] = next(k for k in range(len(drones) + 1) if k not in taken)
    floor = max([base_alt, 0.0])
    return [ReturnPlan(d.ident, layers[d.ident], floor + layers[d.ident] * layer_step) for d in drones]


def _spots_by_every_spot(
    drones: list[Returner], plans: list[ReturnPlan], margin: float
) -> dict[str, tuple[float, float]]:
    """The landing spots as they were before issue 29: each spot against every spot taken."""
    by_layer = sorted(zip(drones, plans, strict=True), key=lambda dp: (dp[1].alt, dp[0].ident))
    spots: dict[str, tuple[float, float]] = {}
    for drone, _ in by_layer:
        spot = drone.position
        for _ in range(len(drones) * 4):
            near = [s for s in spots.values() if math.dist(s, spot) < margin]
            if not near:
                break
            other = near[0]
            dx, dy = spot[0] - other[0], spot[1] - other[1]
            norm = math.hypot(dx, dy)
            ux, uy = (dx / norm, dy / norm) if norm > 1e-6 else (1.0, 0.0)  # east: x is east
            spot = (other[0] + ux * margin * 1.25, other[1] + uy * margin * 1.25)
        spots[drone.ident] = spot
    return spots


coordinate = st.floats(-60.0, 60.0, allow_nan=False).map(lambda v: round(v, 1))
point = st.tuples(coordinate, coordinate)
fleets = st.lists(st.tuples(point, st.floats(1.0, 40.0), point), min_size=0, max_size=40).map(
    lambda rows: [Returner(f"d{i}", pos, alt, home) for i, (pos, alt, home) in enumerate(rows)]
)


@settings(max_examples=300, deadline=None)
@given(fleets, st.sampled_from([0.0, 3.0, 6.0, 9.0, 25.0]))
def test_layers_equal_the_every_pair_colouring(fleet: list[Returner], spacing: float) -> None:
    assert assign_layers(fleet, spacing, 15.0, 3.0) == _layers_by_every_pair(fleet, spacing, 15.0, 3.0)


@settings(max_examples=300, deadline=None)
@given(fleets, st.sampled_from([0.5, 4.0, 8.0, 15.0]))
def test_landing_spots_equal_the_every_spot_scan(fleet: list[Returner], margin: float) -> None:
    plans = [ReturnPlan(d.ident, 0, d.alt) for d in fleet]  # by altitude, as a fleet land orders them
    assert spread_landing_spots(fleet, plans, margin) == _spots_by_every_spot(fleet, plans, margin)


def test_a_spread_fleet_of_2000_compares_only_nearby_legs(monkeypatch: pytest.MonkeyPatch) -> None:
    """2,000 drones on a 40 m grid flying 30 m home: each leg is compared with its neighbours
    only (the pairwise scan made 2 million comparisons), and no two close legs share a layer."""
    calls = [0]
    exact = returns.segment_distance

    def counted(*args: tuple[float, float]) -> float:
        calls[0] += 1
        return exact(*args)

    monkeypatch.setattr(returns, "segment_distance", counted)
    fleet = [
        Returner(
            f"d{i}", (40.0 * (i % 50), 40.0 * (i // 50)), 12.0, (40.0 * (i % 50) + 30.0, 40.0 * (i // 50))
        )
        for i in range(2000)
    ]
    plans = {p.ident: p for p in assign_layers(fleet, 15.0, 15.0, 3.0)}
    assert calls[0] < 20 * len(fleet), calls[0]
    for a, b in (("d0", "d1"), ("d1", "d2"), ("d50", "d51")):  # legs 10 m apart end to start
        assert plans[a].layer != plans[b].layer
    assert {p.layer for p in plans.values()} == {0, 1}
