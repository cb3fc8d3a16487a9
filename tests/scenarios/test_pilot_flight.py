"""The pilot in control (issue 26) on daemon + in-process agents + our simulator (real TCP, real MAVLink).

A pilot's ground station on each vehicle's second MAVLink link (``FleetConfig.pilot_links``, the
SERIAL1 of ArduPilot SITL) sets a mode as an RC mode switch does. The agent must stop commanding
that vehicle (the simulator's command log proves nothing came from the agent's link), the daemon
must show ``pilot`` and exclude it from the mission while the others complete, and the vehicle must
do what the pilot says (stay in LOITER, land where the pilot lands it).
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from protocol.geo import distance_m
from sitl.fleet import SimFleet
from tests.cooperation.rig import rig, wait_for
from tests.scenarios.scenarios import hover_task, legs_task, moving_commands, on_leg, refusals
from tests.support.pilot import PilotStation

pytestmark = pytest.mark.slow

FLEET = {"pilot_links": True}


async def pilot_station(fleet: SimFleet, index: int) -> PilotStation:
    station = await asyncio.to_thread(PilotStation, fleet.pilot_endpoints[index])
    await asyncio.to_thread(station.wait_heartbeat)
    return station


HEARTBEAT_S = 1.0
"""How late (sim time) the agent may learn of the pilot's mode: the vehicle's heartbeat period."""


async def test_pilot_takes_one_drone_mid_mission_and_the_others_complete(tmp_path: Path) -> None:
    async with rig(tmp_path, 3, fleet_options=FLEET) as r:
        fleet, vehicle = r.fleet, r.fleet.vehicle(1)
        station = await pilot_station(fleet, 1)
        try:
            mission_id = await r.daemon.missions.submit(legs_task(r.names))
            await on_leg(r, "drone-2", 40.0)
            assert await asyncio.to_thread(station.set_mode, "LOITER") == 0  # ACCEPTED
            switched = fleet.sim_time
            where = vehicle.state
            await wait_for(
                lambda: r.daemon.authority.pilot("drone-2") == "LOITER", 10, "the daemon to see the pilot"
            )
            assert r.daemon.authority.control("drone-2").level == "pilot"
            assert r.status("drone-2").pilot == "LOITER"
            assert any(e.agent == "drone-2" for e in r.events("agent_excluded"))
            # An operator order is refused while the pilot flies it, and nothing reaches the vehicle.
            delivered, _ = await r.daemon.operator.bring_down("rtl", ["drone-2"], "test")
            assert "drone-2" not in delivered
            decisions = r.daemon.authority.control("drone-2").decisions
            assert any(not d.accepted and "pilot in control" in d.detail for d in decisions), decisions
            # 30 s of vehicle time in the pilot's mode, with no command from the agent's link.
            modes: set[str] = set()
            while fleet.sim_time < switched + 30.0:
                modes.add(vehicle.state.mode)
                await asyncio.sleep(0.05)
            assert modes == {"LOITER"}, (modes, [e for e in vehicle.command_log if e[0] >= switched - 2])
            # A target the agent sent before it heard the vehicle's next heartbeat (1 Hz) may still
            # arrive; the vehicle ignores it outside GUIDED (its mode stayed LOITER, above).
            assert moving_commands(fleet, 1, switched + HEARTBEAT_S) == []
            here = vehicle.state
            braked = distance_m(where.lat, where.lon, here.lat, here.lon)
            assert braked < 15.0, f"drone-2 moved {braked:.1f} m after the pilot's switch"
            # The other two complete the mission without it.
            await wait_for(lambda: mission_id not in r.daemon.missions.active, 120, "the mission to end")
            progress = r.daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed", progress
            await wait_for(
                lambda: r.landed("drone-1") and r.landed("drone-3"), 60, "drone-1 and drone-3 landed"
            )
            # The pilot lands drone-2 where it is; the agent does not interfere.
            before_land = fleet.sim_time
            assert await asyncio.to_thread(station.set_mode, "LAND") == 0
            await wait_for(lambda: vehicle.state.landed and not vehicle.state.armed, 60, "drone-2 landed")
            spot = vehicle.state
            assert distance_m(spot.lat, spot.lon, here.lat, here.lon) < 10.0
            assert moving_commands(fleet, 1, before_land) == []
            await wait_for(
                lambda: r.daemon.authority.pilot("drone-2") == "LAND", 10, "the daemon to see LAND"
            )
        finally:
            station.close()


async def test_the_pilot_hands_back_with_guided_and_the_operator_releases_only_from_a_holding_mode(
    tmp_path: Path,
) -> None:
    async with rig(tmp_path, 1, fleet_options=FLEET) as r:
        fleet, vehicle = r.fleet, r.fleet.vehicle(0)
        station = await pilot_station(fleet, 0)
        try:
            await r.daemon.missions.submit(hover_task("drone-1"))
            await wait_for(lambda: (s := r.status("drone-1")) is not None and s.step == 1, 60, "hovering")
            # The pilot flies by hand (ALT_HOLD): the operator's release is refused there.
            assert await asyncio.to_thread(station.set_mode, "ALT_HOLD") == 0
            await wait_for(lambda: r.daemon.authority.pilot("drone-1") == "ALT_HOLD", 10, "pilot in ALT_HOLD")
            before = len(refusals(r, "drone-1"))
            await r.daemon.operator.resume(["drone-1"], "take it back")
            await wait_for(
                lambda: len(refusals(r, "drone-1")) > before, 10, "the agent to refuse the release"
            )
            assert "release from operator refused" in refusals(r, "drone-1")[-1]
            assert r.daemon.authority.pilot("drone-1") == "ALT_HOLD"
            # The pilot hands back by selecting GUIDED: the agent commands it again.
            assert await asyncio.to_thread(station.set_mode, "GUIDED") == 0
            await wait_for(lambda: r.daemon.authority.pilot("drone-1") is None, 10, "the hand-back")
            assert r.status("drone-1").pilot is None
            # The pilot takes it again (LOITER holds by itself): now the operator may release it.
            assert await asyncio.to_thread(station.set_mode, "LOITER") == 0
            await wait_for(lambda: r.daemon.authority.pilot("drone-1") == "LOITER", 10, "pilot in LOITER")
            released = fleet.sim_time
            await r.daemon.operator.resume(["drone-1"], "take it back")
            await wait_for(lambda: r.daemon.authority.pilot("drone-1") is None, 10, "the release")
            assert vehicle.state.mode == "LOITER"  # the release itself sends nothing
            assert moving_commands(fleet, 0, released) == []
            # The agent flies it again: the operator lands it.
            delivered, _ = await r.daemon.operator.bring_down("land", ["drone-1"], "test")
            assert delivered == ["drone-1"]
            await wait_for(lambda: vehicle.state.landed and not vehicle.state.armed, 60, "drone-1 landed")
        finally:
            station.close()
