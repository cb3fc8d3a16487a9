"""The vehicle state both MAVLink backends keep, written once.

The pymavlink backend decodes MAVLink messages and the MAVSDK backend receives plugin callbacks,
but both fold them into the same things: a :class:`Telemetry`, the pilot gate (whose mode is it),
the mode shown while a PX4 leg is flown, the landed state and the mission progress. This class
holds them behind one lock; the decoders (``mavlink_telemetry``, ``mavsdk_telemetry``) write
into it on their threads and the backend reads snapshots on the event loop.
"""

from __future__ import annotations

import dataclasses
import threading

from agent.autopilot.base import Telemetry
from agent.autopilot.flavours.base import Flavour, ShownMode
from agent.autopilot.mavlink_link import mavlink
from agent.autopilot.pilot_gate import FAILSAFE_STATES, PilotGate

__all__ = ["VehicleState"]

# MAV_LANDED_STATE (MAVSDK's telemetry.LandedState has the same numbers).
_ON_GROUND = mavlink.MAV_LANDED_STATE_ON_GROUND
_AIRBORNE = (
    mavlink.MAV_LANDED_STATE_IN_AIR,
    mavlink.MAV_LANDED_STATE_TAKEOFF,
    mavlink.MAV_LANDED_STATE_LANDING,
)


class VehicleState:
    """Telemetry, pilot gate, shown mode, landed state and mission progress under one lock.

    Methods named ``on_*`` / ``update_*`` expect the caller to hold :attr:`lock` (they run inside
    a decoder's locked handler); the others take it themselves.
    """

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.tel = Telemetry()
        self.pilot = PilotGate(self.lock)  # the mode we asked for, and a pilot's when the vehicle left it
        self.shown = ShownMode()  # PX4: GUIDED while our reposition leg is flown, LOITER once held
        self.landed_state: int | None = None  # None until the vehicle reports one
        self.mission_seq = -1
        self.mission_offset = 0  # seq of the first uploaded point (1 on ArduPilot: seq 0 is home)

    # ------------------------------------------------------------ written by decoders (lock held)

    def on_heartbeat(self, flavour: Flavour, raw: str, base_mode: int, system_status: int | None) -> None:
        """One autopilot heartbeat whose mode the flavour decoded as ``raw``."""
        tel = self.tel
        tel.mode = self.shown.from_heartbeat(flavour, raw)
        tel.armed = bool(base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        tel.autopilot_failsafe = system_status in FAILSAFE_STATES
        tel.pilot_mode = self.pilot.heartbeat(flavour, raw, tel.armed)
        self.update_landed()
        self.update_mission_current()

    def on_landed_state(self, state: int) -> None:
        self.landed_state = state
        self.update_landed()

    def on_mission_seq(self, seq: int) -> None:
        self.mission_seq = seq
        self.update_mission_current()

    def update_landed(self) -> None:
        tel = self.tel
        state = self.landed_state
        if state == _ON_GROUND:
            tel.landed = True
        elif state in _AIRBORNE:
            tel.landed = False
        else:  # no landed state: disarmed, or armed and still at ground level
            tel.landed = not tel.armed or tel.alt_rel < 0.3

    def update_mission_current(self) -> None:
        tel = self.tel
        if tel.mode in ("AUTO", "MISSION") and self.mission_seq >= 0:
            tel.mission_current = max(0, self.mission_seq - self.mission_offset)
        else:
            tel.mission_current = -1

    # ------------------------------------------------------------ used by the backend (takes the lock)

    def snapshot(self, status_texts: list[str], last_heartbeat: float) -> Telemetry:
        """A copy of the telemetry the queue may keep (never blocks on the link)."""
        with self.lock:
            snap = dataclasses.replace(self.tel, status_texts=status_texts)
        snap.last_heartbeat_monotonic = last_heartbeat
        return snap

    def mode_now(self) -> str:
        with self.lock:
            return self.tel.mode

    def show_mode(self, mode: str) -> None:
        """An accepted mode change, shown before the heartbeat that confirms it."""
        with self.lock:
            self.tel.mode = mode

    def mission_uploaded(self, offset: int) -> None:
        with self.lock:
            self.mission_offset = offset
            self.update_mission_current()

    def leg(self, flavour: Flavour, active: bool) -> None:
        """PX4: mark whether one of our reposition legs is being flown (the mode shown follows)."""
        with self.lock:
            mode = self.shown.leg(flavour, active)
            if mode is not None:
                self.tel.mode = mode

    def adopt(self) -> None:
        """The operator's release: the present mode is the agent's from now on."""
        with self.lock:
            self.pilot.adopt()
            self.tel.pilot_mode = None
