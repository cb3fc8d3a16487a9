"""MavlinkAutopilot through a lossy agent <-> autopilot link (issue 26): our simulator behind a
:class:`tests.faults.links.MavlinkRelay` that drops whole MAVLink frames, real loopback TCP.

A command whose ACK is lost is sent again with the confirmation field counted up; a re-sent
takeoff the vehicle refuses because the first one is already climbing (ArduCopter: FAILED) is
the first one's success; a mission upload whose final ACK is lost is checked on the vehicle; at
10 % loss both ways the vehicle is armed, flown and given a mission.
"""

from __future__ import annotations

from typing import Any

import pytest

from agent.autopilot.base import MissionPoint
from agent.autopilot.mavlink_backend import MavlinkAutopilot
from agent.autopilot.mavlink_link import mavlink
from protocol.geo import offset_latlon
from tests.backends.conftest import HOME, wait_until
from tests.faults.links import COMMAND_ACK, MavlinkRelay

MISSION_ACK = 47

pytestmark = pytest.mark.slow


# 0.5 s ACK timeout: at 4x a lost frame costs 2 s of vehicle time, far from ArduCopter's 10 s
# auto-disarm (DISARM_DELAY) between the arm and a takeoff re-sent twice.
SLOW = {"speedup": 4.0}


async def through(relay: MavlinkRelay, closing: Any) -> MavlinkAutopilot:
    ap = MavlinkAutopilot(relay.url, command_timeout_s=0.5, command_retries=4)
    closing(ap)
    await ap.connect(timeout=10.0)
    await wait_until(ap, lambda t: t.has_position, "3D fix and home position", timeout=20.0)
    return ap


def confirmations(relay: MavlinkRelay, command: int) -> list[int]:
    return [c.confirmation for c in relay.commands if c.command == command]


async def test_a_takeoff_whose_ack_is_lost_is_resent_counted_and_taken(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet(**SLOW)
    async with MavlinkRelay(fleet.endpoints[0]) as relay:
        ap = await through(relay, closing)
        await ap.arm(deadline_s=20.0)
        relay.down.drop_next[COMMAND_ACK] = 1  # the takeoff's ACK: the vehicle climbs, we hear nothing
        await ap.takeoff(10.0)
        assert confirmations(relay, mavlink.MAV_CMD_NAV_TAKEOFF) == [0, 1]
        assert relay.stats["down_dropped"] == 1
        await wait_until(ap, lambda t: t.alt_rel >= 9.5, "the climb to 10 m", timeout=20.0)
        # Two ACKs lost: three sends, confirmation 0, 1, 2 (a mode change is idempotent).
        relay.down.drop_next[COMMAND_ACK] = 2
        await ap.set_mode("LOITER")
        assert confirmations(relay, mavlink.MAV_CMD_DO_SET_MODE)[-3:] == [0, 1, 2]
        assert ap.telemetry().mode == "LOITER" or fleet.vehicle(0).state.mode == "LOITER"


async def test_a_mission_upload_whose_final_ack_is_lost_is_checked_on_the_vehicle(
    sim_fleet: Any, closing: Any
) -> None:
    fleet = sim_fleet(**SLOW)
    async with MavlinkRelay(fleet.endpoints[0]) as relay:
        ap = await through(relay, closing)
        points = [MissionPoint(*offset_latlon(HOME[0], HOME[1], 5.0 * i, 0.0), 10.0) for i in range(1, 6)]
        relay.down.drop_next[MISSION_ACK] = 1  # the vehicle stored them; we never hear it
        await ap.upload_mission(points)  # the re-sent last item is refused: a download says it went
        assert relay.stats["down_dropped"] == 1
        assert fleet.vehicle(0).state.mission_count == len(points) + 1
        relay.down.drop_next[MISSION_ACK] = 1
        await ap.upload_mission(points[:3])  # the same check with a mission the vehicle did not have
        assert fleet.vehicle(0).state.mission_count == 4


async def test_arm_takeoff_and_a_mission_upload_at_ten_percent_loss(sim_fleet: Any, closing: Any) -> None:
    fleet = sim_fleet(**SLOW)
    async with MavlinkRelay(fleet.endpoints[0], loss=0.10, seed=5) as relay:
        ap = await through(relay, closing)
        points = [MissionPoint(*offset_latlon(HOME[0], HOME[1], 5.0 * i, 0.0), 10.0) for i in range(1, 21)]
        await ap.upload_mission(points)
        assert fleet.vehicle(0).state.mission_count == len(points) + 1
        await ap.arm(deadline_s=20.0)
        await ap.takeoff(8.0)
        await wait_until(ap, lambda t: t.alt_rel >= 7.5, "the climb to 8 m", timeout=20.0)
        assert relay.stats["up_dropped"] > 0 and relay.stats["down_dropped"] > 0
