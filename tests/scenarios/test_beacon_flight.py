"""Release beacons in flight: daemon + in-process MAVLink agents + our simulator, with the authority.

A beacon is one more way a barrier's release reaches an agent; like the TCP release it must
never undo a higher-priority command. Here an operator holds a drone while it waits at a barrier;
the barrier is released by beacon (verified against the mission's chain) and the drone stays
put until the operator lets it go, then the mission completes.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from gcs.cooperation.config import CooperationConfig
from gcs.link.beacon import loopback_beacon_address
from protocol.geo import distance_m
from tests.cooperation.rig import SPEEDUP, rig, wait_for
from tests.scenarios.scenarios import barrier_task

pytestmark = pytest.mark.slow

COOP = CooperationConfig(vehicle_time_scale=SPEEDUP)


async def test_a_beacon_release_does_not_undo_an_operator_hold_at_the_barrier(tmp_path: Path) -> None:
    address = loopback_beacon_address()
    async with rig(tmp_path, 2, COOP, release_beacon=address, agent_options={"release_beacon": address}) as r:
        mission_id = await r.daemon.missions.submit(barrier_task(r.names))
        await wait_for(lambda: r.status("drone-1").waiting_sync == 1, 60, "drone-1 at barrier 1")
        assert await r.daemon.pause_agent("drone-1", "operator: check the camera")
        await wait_for(lambda: r.status("drone-1").paused, 10, "drone-1 reports the hold")
        mission = r.daemon.missions.active[mission_id]
        await wait_for(lambda: 1 in mission.barriers.released, 90, "barrier 1 released (drone-2 arrived)")
        listener = r.agents["drone-1"].beacon
        assert listener is not None
        await wait_for(
            lambda: listener.stats.accepted + listener.stats.late >= 2, 10, "beacons 0 and 1 heard"
        )
        held = r.status("drone-1").position
        await asyncio.sleep(4.0)  # 32 s of vehicle time at 8x: drone-2 flies on, drone-1 must not
        now = r.status("drone-1")
        assert now.paused and now.step <= 1, f"drone-1 left its hold: step {now.step}, paused {now.paused}"
        moved = distance_m(held.lat, held.lon, now.position.lat, now.position.lon)
        assert moved < 1.5, f"drone-1 drifted {moved:.1f} m while held"
        assert await r.daemon.resume_agent("drone-1", "operator: carry on")
        await wait_for(lambda: mission_id not in r.daemon.missions.active, 120, "mission end")
        assert r.daemon.missions.progress(mission_id).state == "completed"
        await wait_for(lambda: all(r.landed(n) for n in r.names), 60, "both landed")
        for name in r.names:
            stats = r.agents[name].beacon.stats  # type: ignore[union-attr]
            assert stats.rejected == 0 and stats.malformed == 0, stats
            assert stats.accepted >= 1, f"{name} never took a release from a beacon: {stats}"
        assert r.daemon.missions.beacon is not None and r.daemon.missions.beacon.sent == 2  # steps 0, 1
