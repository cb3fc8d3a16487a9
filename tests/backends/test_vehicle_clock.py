"""The vehicle's own clock reaches the status report, and the simulator says when it falls behind."""

from __future__ import annotations

import time
from typing import Any

import pytest

from agent.autopilot.mavlink_backend import MavlinkAutopilot
from sitl.fleet import SimFleet
from tests.backends.conftest import fleet_config, wait_until

pytestmark = pytest.mark.slow


async def test_telemetry_carries_the_simulator_clock(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet(speedup=8.0)
    ap = MavlinkAutopilot(fleet.endpoints[0])
    closing(ap)
    await ap.connect(timeout=10.0)
    first = await wait_until(ap, lambda t: t.vehicle_time_s is not None, "a vehicle clock")
    assert first.vehicle_time_s is not None
    later = await wait_until(
        ap, lambda t: (t.vehicle_time_s or 0.0) > 40.0, "40 vehicle seconds (5 s of wall time at 8x)", 60.0
    )
    assert later.vehicle_time_s is not None
    # time_boot_ms of the last position: the sim clock, a little behind it (telemetry period and
    # read latency); a wall clock would be 1/8 of it, a UNIX clock 1.7e9
    assert fleet.sim_time - 15.0 <= later.vehicle_time_s <= fleet.sim_time + 1e-3


def test_simulator_counts_and_reports_a_speed_up_it_cannot_keep(caplog: pytest.LogCaptureFixture) -> None:
    fleet = SimFleet(fleet_config(speedup=50_000.0, vehicles=4))  # far beyond what one core can step
    with caplog.at_level("WARNING", logger="sitl"), fleet:
        deadline = time.monotonic() + 20.0
        while fleet.overruns < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
    assert fleet.overruns >= 3 and fleet.dropped_sim_s > 0.0
    assert fleet.speedup_kept < 50_000.0
    assert any("simulator behind" in r.getMessage() for r in caplog.records)


async def test_a_hold_lasts_its_seconds_on_the_vehicle_clock(sim_fleet: Any, closing: Any) -> None:
    """At 8x a 16 s hold is 16 s of the simulator's time, about 2 s of wall time (not 16)."""
    from agent.config import AgentConfig
    from agent.executor import ActionExecutor
    from protocol.actions import Hold

    fleet = sim_fleet(speedup=8.0)
    ap = MavlinkAutopilot(fleet.endpoints[0])
    closing(ap)
    await ap.connect(timeout=10.0)
    await wait_until(ap, lambda t: t.has_position and t.vehicle_time_s is not None, "a fix and a clock")
    executor = ActionExecutor(ap, AgentConfig(identity="clock", key_hex="00" * 32))
    started_wall, started_sim = time.monotonic(), fleet.sim_time
    await executor.run(Hold(step=0, seconds=16.0))
    wall, sim = time.monotonic() - started_wall, fleet.sim_time - started_sim
    assert sim >= 15.0, f"the hold ended after {sim:.1f} s of vehicle time"
    assert wall < 8.0, f"the hold took {wall:.1f} s of wall time: timed on the wall clock"
