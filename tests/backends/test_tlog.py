"""The agent's MAVLink traffic log (.tlog) is readable by pymavlink, both directions included."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pymavlink import mavutil

from agent.autopilot.base import Autopilot
from agent.autopilot.mavlink_backend import MavlinkAutopilot


async def test_tlog_records_received_and_sent_messages(
    sim_fleet: Callable[..., Any], closing: Callable[[Autopilot], Autopilot], tmp_path: Path
) -> None:
    started = time.time()
    fleet = sim_fleet()
    tlog = tmp_path / "drone.tlog"
    autopilot = closing(MavlinkAutopilot(fleet.endpoints[0], tlog_path=str(tlog)))
    await autopilot.connect(timeout=20)
    await asyncio.sleep(1.0)
    await autopilot.close()

    log = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    senders: dict[str, set[tuple[int, int]]] = {}
    stamps = []
    for _ in range(100_000):  # bounded read of the whole file
        msg = log.recv_match()
        if msg is None:
            break
        senders.setdefault(msg.get_type(), set()).add((msg.get_srcSystem(), msg.get_srcComponent()))
        stamps.append(msg._timestamp)
    assert (1, 1) in senders["HEARTBEAT"]  # the vehicle
    assert any(comp == 191 for _, comp in senders["HEARTBEAT"])  # us, the onboard computer
    assert "GLOBAL_POSITION_INT" in senders and "COMMAND_LONG" in senders  # telemetry in, stream requests out
    assert started - 1 <= min(stamps) and max(stamps) <= time.time()  # wall-clock stamps of this run
