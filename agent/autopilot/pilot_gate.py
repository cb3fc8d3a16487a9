"""The pilot gate both MAVLink backends share: who owns the vehicle's mode, and the refusal.

The pymavlink and MAVSDK backends tell the gate which mode each of their commands puts the
vehicle in (:meth:`PilotGate.expect`) and feed it every autopilot heartbeat; from the first
heartbeat that shows a mode nobody on our side asked for, :meth:`PilotGate.movable` refuses
everything that would move the vehicle (:class:`PilotInControl`) until the pilot hands back or
the operator releases (docs/cooperation.md, "The pilot in control").
"""

from __future__ import annotations

import threading

from agent.autopilot.base import PilotInControl
from agent.autopilot.flavours.base import Flavour, ModeOwner
from agent.autopilot.mavlink_link import mavlink

# HEARTBEAT.system_status while the autopilot flies a failsafe of its own (Telemetry.autopilot_failsafe):
# PX4 v1.16 goes CRITICAL with "Failsafe activated" (measured on a GNSS loss) and back when disarmed.
FAILSAFE_STATES = frozenset({mavlink.MAV_STATE_CRITICAL, mavlink.MAV_STATE_EMERGENCY})


class PilotGate:
    """A :class:`ModeOwner` behind the backend's telemetry lock, with the refusal of commands."""

    def __init__(self, lock: threading.Lock) -> None:
        self._lock = lock
        self._owner = ModeOwner()

    @property
    def pilot_mode(self) -> str | None:
        """The pilot's mode while a pilot flies the vehicle (read under the caller's lock)."""
        return self._owner.foreign

    def movable(self, what: str) -> None:
        """Raise :class:`PilotInControl` while a pilot has the vehicle (checked against the newest
        heartbeat, before the agent's monitor has seen it): the gate of every moving command."""
        with self._lock:
            mode = self._owner.foreign
        if mode is not None:
            raise PilotInControl(f"{what}: pilot in control (mode {mode}); nothing sent")

    def expect(self, raw: str) -> str | None:
        """Our next command puts the vehicle in ``raw``; returns the mode expected before it."""
        with self._lock:
            before = self._owner.expected
            self._owner.expect(raw)
        return before

    def refused(self, raw: str, before: str | None) -> None:
        """The vehicle refused the command that would have put it in ``raw``."""
        with self._lock:
            self._owner.withdraw(raw, before)

    def heartbeat(self, flavour: Flavour, raw: str, armed: bool) -> str | None:
        """One autopilot heartbeat (the caller holds the lock); the pilot's mode after it."""
        self._owner.heartbeat(flavour, raw, armed)
        return self._owner.foreign

    def adopt(self) -> None:
        """The operator's release: the present mode is the agent's (the caller holds the lock)."""
        self._owner.adopt()
