"""GNSS lost on one drone mid-leg (issue 26) on real ArduCopter SITL and on our simulator, through daemon
and agents: the GPS is dropped as ArduPilot SITL does it (PARAM_SET SIM_GPS1_ENABLE = 0, ArduPilot
4.7), the EKF failsafe lands the drone by itself, the agent reports ``gnss: land``, the daemon
excludes it and the other two complete.
"""

from __future__ import annotations

import pytest

from protocol.geo import distance_m
from tests.ardupilot.rig import Rig, at, fly_north_then_wait_for

pytestmark = [pytest.mark.ardupilot, pytest.mark.slow, pytest.mark.timeout(240)]


def test_gnss_lost_on_one_drone_mid_leg_it_lands_by_itself_and_the_others_complete(rig: Rig) -> None:
    mission_id = fly_north_then_wait_for(rig, "drone-2", "gnss")
    drone2 = rig.agents["drone-2"]
    home = at(0.0, 0.0, 1)
    try:
        rig.param("drone-2", "SIM_GPS1_ENABLE", 0.0)
        rig.wait(lambda: rig.d.authority.failsafe("drone-2") == "gnss: land", 30.0, "the daemon to see it")
        assert drone2.autopilot.telemetry().mode == "LAND"
        assert rig.d.authority.pilot("drone-2") is None
        progress = rig.finish_without(mission_id, "drone-2", 150.0)
        assert progress.state == "completed", progress
        assert any(e.agent == "drone-2" for e in rig.events("agent_excluded"))
        rig.wait(lambda: (t := drone2.autopilot.telemetry()).landed and not t.armed, 90.0, "drone-2 landed")
        down = drone2.autopilot.telemetry()
        assert distance_m(down.lat, down.lon, *home) > 25.0  # out on its leg, not back home
    finally:
        rig.param("drone-2", "SIM_GPS1_ENABLE", 1.0)
