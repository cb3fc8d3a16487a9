"""A pilot's ground station on a vehicle's second MAVLink link (our simulator's ``pilot_links``, real
ArduCopter's SERIAL1): what an RC mode switch or a supervisor's QGroundControl does to the vehicle; and the
mode questions PilotWatch asks of an ArduPilot backend, for the pilot units."""

from __future__ import annotations

import time
from typing import Any

from pymavlink import mavutil

from agent.autopilot.flavours.ardupilot import ArduPilotFlavour

COPTER_MODES = {"STABILIZE": 0, "ALT_HOLD": 2, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9}
PILOT_SYSTEM = 200  # not the agent's (it takes the vehicle's GCS id 255 or its own)
PILOT_COMPONENT = 190  # MAV_COMP_ID_MISSIONPLANNER


class PilotStation:
    """Blocking (call it through ``asyncio.to_thread`` from a loop); every wait is bounded."""

    def __init__(self, url: str) -> None:
        self.conn: Any = mavutil.mavlink_connection(
            url, source_system=PILOT_SYSTEM, source_component=PILOT_COMPONENT
        )

    def wait_heartbeat(self, timeout: float = 20.0) -> None:
        if self.conn.wait_heartbeat(timeout=timeout) is None:
            raise AssertionError("no heartbeat on the pilot's link")

    def set_mode(self, name: str, timeout: float = 10.0) -> int:
        """MAV_CMD_DO_SET_MODE as a mode switch does (ArduCopter's mode numbers); the ACK's MAV_RESULT
        (0 = accepted)."""
        return self.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, 1, COPTER_MODES[name], timeout=timeout)

    def command(self, command: int, *params: float, timeout: float = 10.0) -> int:
        """COMMAND_LONG to the vehicle's autopilot; the ACK's MAV_RESULT (0 = accepted)."""
        target = self.conn.target_system or 1
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(target, 1, command, 0, *p)
        for _ in range(round(timeout / 0.2)):
            ack = self.conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.2)
            if ack is not None and ack.command == command:
                return int(ack.result)
        raise AssertionError(f"no ACK for command {command} on the station's link within {timeout:.0f} s")

    def close(self) -> None:
        self.conn.close()


class ArduPilotModes:
    """The two questions PilotWatch asks of a backend (an ArduPilot one)."""

    adopted = False

    def pilot_modes(self) -> tuple[tuple[str, ...], tuple[str, ...]]:
        flavour = ArduPilotFlavour()
        return flavour.failsafe_modes, flavour.release_modes

    def adopt_mode(self) -> None:
        self.adopted = True


def drain_for(station: PilotStation, seconds: float, limit: int = 20_000) -> list[Any]:
    """Every message the station receives in the next ``seconds`` (bounded in count and time)."""
    out = []
    until = time.monotonic() + seconds
    for _ in range(limit):
        msg = station.conn.recv_match(blocking=True, timeout=0.1)
        if msg is not None:
            out.append(msg)
        if time.monotonic() > until:
            break
    return out


def drain(station: PilotStation, limit: int = 20_000) -> list[Any]:
    """Every message the station has received so far (bounded)."""
    out = []
    for _ in range(limit):
        msg = station.conn.recv_match(blocking=False)
        if msg is None:
            break
        out.append(msg)
    return out
