"""GNSS lost on one drone mid-mission (issue 26) on daemon + in-process agents + our simulator (real TCP,
real MAVLink, sim speedup).

The simulator drops drone-2's GPS mid-leg; the autopilot's own position failsafe lands it by itself
(ArduCopter's EKF failsafe: LAND after 8 s; PX4's: Descend, shown AUTO.LAND, after 5 s). The agent
must report it as the vehicle's own failsafe (``gnss: land``), not as a pilot, and send it nothing
that moves it (the simulator's command log); the daemon must show the failsafe, exclude it from the
mission (barriers stop waiting for it) and the other two must complete.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from protocol.geo import distance_m
from sitl.vehicle.constants import GPS_FS_S
from tests.cooperation.rig import rig, wait_for
from tests.scenarios.scenarios import legs_task, moving_commands, on_leg

pytestmark = pytest.mark.slow


# flavour -> (fleet options, the mode the failsafe shows, its delay in sim s)
FLAVOURS: dict[str, tuple[dict[str, Any], str, float]] = {
    "ardupilot": ({}, "LAND", GPS_FS_S),
    # PX4 SITL drains its battery to 50 % in a minute: the energy monitor would send everyone home.
    "px4": ({"flavour": "px4", "params": {"SIM_BAT_DRAIN": 0.0}}, "AUTO.LAND", 5.0),
}


@pytest.mark.parametrize("flavour", sorted(FLAVOURS))
async def test_gnss_lost_on_one_drone_mid_leg_it_lands_by_itself_and_the_others_complete(
    tmp_path: Path, flavour: str
) -> None:
    options, failsafe_mode, delay = FLAVOURS[flavour]
    async with rig(tmp_path, 3, fleet_options=options) as r:
        fleet, vehicle = r.fleet, r.fleet.vehicle(1)
        mission_id = await r.daemon.missions.submit(legs_task(r.names))
        await on_leg(r, "drone-2", 40.0)
        lost = fleet.sim_time
        vehicle.inject_gps_loss()
        await wait_for(lambda: vehicle.state.mode == failsafe_mode, 30, "drone-2's own position failsafe")
        landing = fleet.sim_time
        assert landing - lost >= delay - 0.1, "the failsafe came before the autopilot's delay"
        await wait_for(
            lambda: r.daemon.authority.failsafe("drone-2") == "gnss: land", 10, "the daemon to see it"
        )
        seen = fleet.sim_time  # the agent has reported it by now
        status = r.status("drone-2")
        assert status.failsafe == "gnss: land" and status.pilot is None
        control = r.daemon.authority.control("drone-2")
        assert control.level == "vehicle_failsafe" and control.pilot is None
        assert any(e.agent == "drone-2" for e in r.events("agent_excluded"))
        # The other two fly their legs and land: the barriers no longer wait for drone-2, which
        # stays in its failsafe mode until it is down.
        modes: set[str] = set()

        def others_done() -> bool:
            if vehicle.state.armed:
                modes.add(vehicle.state.mode)
            return mission_id not in r.daemon.missions.active

        await wait_for(others_done, 120, "the mission to end")
        progress = r.daemon.missions.progress(mission_id)
        assert progress is not None and progress.state == "completed", progress
        await wait_for(lambda: r.landed("drone-1") and r.landed("drone-3"), 60, "drone-1 and drone-3 landed")
        await wait_for(lambda: vehicle.state.landed and not vehicle.state.armed, 60, "drone-2 landed")
        assert modes <= {failsafe_mode}, modes
        # It landed out on its leg, where it lost its position, not at home; nothing from us moved it.
        spot = vehicle.state
        assert distance_m(spot.lat, spot.lon, spot.home_lat, spot.home_lon) > 40.0
        # A position target already on its way when the vehicle switched (its heartbeat is up to 1 s
        # away) is ignored outside GUIDED/Offboard; no mode change ever came from us, and nothing
        # that moves it once the agent knew.
        in_flight = moving_commands(fleet, 1, landing)
        assert not [e for e in in_flight if e[2] == "SET_MODE" or e[3] == 176], in_flight
        assert moving_commands(fleet, 1, seen) == [], (landing, seen, in_flight)
