"""The agent's MAVLink router on its own (agent/autopilot/mavlink_router.py): MavlinkAutopilot on our
simulator with a ``tcpin`` and a ``udpin`` endpoint, two pymavlink ground stations on them.

Both see the vehicle; a command from one is answered to that one only (routed by target system);
the autopilot's answers to the agent reach neither; a ground station that disconnects costs the
agent nothing.
"""

from __future__ import annotations

import asyncio
import socket
from typing import Any

import pytest

from agent.autopilot.mavlink_backend import MavlinkAutopilot
from tests.backends.conftest import wait_until
from tests.support.pilot import PilotStation, drain

pytestmark = pytest.mark.slow


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def test_two_ground_stations_on_tcp_and_udp_each_get_their_own_answers(
    sim_fleet: Any, closing: Any
) -> None:
    fleet = sim_fleet()
    tcp_port, udp_port = free_port(socket.SOCK_STREAM), free_port(socket.SOCK_DGRAM)
    ap = MavlinkAutopilot(
        fleet.endpoints[0], mavlink_out=[f"tcpin:127.0.0.1:{tcp_port}", f"udpin:127.0.0.1:{udp_port}"]
    )
    closing(ap)
    await ap.connect(timeout=10.0)
    await wait_until(ap, lambda t: t.has_position, "3D fix and home position")
    qgc = await asyncio.to_thread(PilotStation, f"tcp:127.0.0.1:{tcp_port}")
    other = await asyncio.to_thread(PilotStation, f"udpout:127.0.0.1:{udp_port}")
    other.conn.mav.srcSystem = 201  # a second ground station, its own system id
    try:
        await asyncio.to_thread(qgc.wait_heartbeat)
        other.conn.mav.heartbeat_send(6, 8, 0, 0, 4)  # udpin learns where to send from this
        await asyncio.to_thread(other.wait_heartbeat)
        assert await asyncio.to_thread(qgc.set_mode, "LOITER") == 0
        # On the ground and disarmed this is no takeover (agent/pilot.py); in flight it is: the
        # scenario test tests/scenarios/test_router_flight.py.
        await wait_until(ap, lambda t: t.mode == "LOITER", "the vehicle in the station's mode")
        await ap.set_mode("GUIDED")  # the agent's own command: its ACK reaches neither station
        await asyncio.sleep(0.3)
        acks = [m for m in await asyncio.to_thread(drain, other) if m.get_type() == "COMMAND_ACK"]
        assert acks == [], [(a.command, a.target_system) for a in acks]
        acks = [m for m in await asyncio.to_thread(drain, qgc) if m.get_type() == "COMMAND_ACK"]
        assert acks == [], [(a.command, a.target_system) for a in acks]  # its own was read by set_mode
        router = ap.link.router
        assert router is not None and router.stats["in"] > 0 and router.peers == 2
        qgc.close()
        await asyncio.sleep(0.5)
        assert router.peers == 1
        await wait_until(ap, lambda t: t.mode == "GUIDED", "the link still working")
    finally:
        qgc.close()
        other.close()
