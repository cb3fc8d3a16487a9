"""What differs between autopilot firmwares, written once for both backends.

A :class:`Flavour` answers the questions a backend has to ask before it talks to a vehicle: how a
mode is encoded and decoded, how to take off (altitude above home or above sea level), how to hold,
how to fly to a point (with its speed), which parameter holds the return altitude and the fence
settings, how integer parameter values travel. The pymavlink and MAVSDK backends pick one from the
vehicle heartbeat's ``autopilot`` field (:func:`agent.autopilot.flavours.flavour_for`) and only
ask it; nothing here opens a link. The layout follows Skybrush's ``autopilots/`` (one class per
firmware). Measured behaviours and the tests that pin them: ``docs/autopilot-backends.md``.
"""

from __future__ import annotations

import abc
import math
import time
from collections.abc import Mapping
from typing import ClassVar

from agent.autopilot.base import FenceSpec, Telemetry

# Used when a return is asked for without an altitude and the autopilot's own default is a poor
# fit (PX4: RTL_RETURN_ALT 30 m for every drone): return at the current altitude, never below this.
RETURN_ALT_FLOOR_M = 5.0


class Flavour(abc.ABC):
    """One autopilot firmware's conventions (subclasses: ArduPilot, PX4)."""

    name: str = ""
    mav_autopilot: int = 0
    # Mode to enter before arming, taking off and sending position targets (ArduPilot GUIDED).
    guided_mode: str | None = None
    hold_modes: tuple[str, ...] = ()
    # Mission seq 0 is the home position (ArduPilot), not the first point.
    mission_home_item: bool = False
    # Integer parameters travel as their bytes in PARAM_VALUE.param_value (PX4), not cast (ArduPilot).
    params_bytewise: bool = False
    return_alt_param: str = ""
    fence_actions: ClassVar[Mapping[str, int]] = {}
    # Modes the vehicle enters by itself on a failsafe (battery, EKF/position loss, fence, RC/GCS loss).
    failsafe_modes: tuple[str, ...] = ("RTL", "LAND")
    # Modes a pilot's control may be released from by the operator: the vehicle holds its position
    # there without anyone on the sticks, so the pilot can flip the switch again (docs/cooperation.md).
    release_modes: tuple[str, ...] = ()
    # The pilot's hand-back: selecting this mode gives the vehicle back to the agent (ArduPilot
    # GUIDED, PX4 Hold), as well as the mode the agent last asked for.
    handback_mode = "GUIDED"

    @abc.abstractmethod
    def decode_mode(self, mav_type: int, base_mode: int, custom_mode: int) -> str:
        """The upper-case mode name of a HEARTBEAT, in the agent's vocabulary."""

    @abc.abstractmethod
    def mode_command(self, name: str, mav_type: int) -> tuple[tuple[float, ...], int]:
        """(MAV_CMD_DO_SET_MODE params, custom_mode) for a mode name; KeyError when there is none."""

    @abc.abstractmethod
    def takeoff_params(self, alt_rel_m: float, tel: Telemetry) -> tuple[float, ...]:
        """MAV_CMD_NAV_TAKEOFF params 1-7 for a take-off to ``alt_rel_m`` above home."""

    def reposition_params(
        self, lat: float, lon: float, alt_amsl: float, speed_mps: float | None
    ) -> tuple[float, ...]:
        """MAV_CMD_DO_REPOSITION params 1-7 (COMMAND_INT, frame GLOBAL: z is AMSL)."""
        raise NotImplementedError(f"{self.name} does not fly DO_REPOSITION")

    def pause_params(self) -> tuple[float, ...] | None:
        """MAV_CMD_DO_REPOSITION params 1-7 that make a flying vehicle brake and hold where it comes to
        rest (NaN: no position, altitude or yaw), or None when the flavour holds by switching to one
        of :attr:`hold_modes` (ArduPilot BRAKE). Sent as COMMAND_INT, NaN lat/lon as x = y = INT32_MAX."""
        return None

    def speed_accepted_in(self, mode: str) -> bool:
        """Whether MAV_CMD_DO_CHANGE_SPEED takes effect in ``mode`` (else keep it for the next target)."""
        return True

    @abc.abstractmethod
    def return_alt_value(self, alt_rel_m: float) -> float:
        """The value of :attr:`return_alt_param` for a return at ``alt_rel_m`` above home."""

    def default_return_alt(self, tel: Telemetry) -> float | None:
        """Return altitude when none is asked for; None keeps the autopilot's own setting."""
        return None

    @abc.abstractmethod
    def fence_params(self, fence: FenceSpec, has_items: bool) -> list[tuple[str, float]]:
        """Parameters to write, in order, after the fence items are uploaded."""

    def fence_action(self, breach_action: str) -> int:
        """The firmware's code for a breach action; ValueError when it has none."""
        if breach_action not in self.fence_actions:
            raise ValueError(f"unknown breach action {breach_action!r}")
        return self.fence_actions[breach_action]

    def decode_param(self, raw: float, param_type: int) -> float:
        """PARAM_VALUE.param_value as the number it stands for."""
        return float(raw)

    def encode_param(self, value: float, param_type: int) -> float:
        """The float to put in PARAM_SET.param_value for ``value`` of ``param_type``."""
        return float(value)

    def shown_mode(self, mode: str, leg_active: bool) -> str:
        """The mode to report: PX4 flies a goto and a hold in the same mode; see :class:`Px4Flavour`."""
        return mode

    def follows(self, previous: str, mode: str) -> bool:
        """Whether the vehicle goes from ``previous`` to ``mode`` by itself when a manoeuvre we started
        ends (PX4: a take-off, a mission or a landing ends in Hold): not a pilot's switch."""
        return False


def base_altitude_amsl(tel: Telemetry) -> float:
    """Home altitude above sea level (or the best estimate: current AMSL minus height above home)."""
    if tel.home_alt_amsl is not None and math.isfinite(tel.home_alt_amsl):
        return tel.home_alt_amsl
    return tel.alt_amsl - tel.alt_rel


class ShownMode:
    """The mode a backend reports, kept from heartbeats and from the legs it sends.

    PX4 flies a goto and a hold in the same vehicle mode (Hold); this remembers whether one of our
    legs is being flown, so the report tells them apart (:meth:`Flavour.shown_mode`). A leg ends
    when we hold, change mode or take off, or when the vehicle itself leaves Hold (RTL, LAND, ...).
    Not thread-safe by itself: callers hold their telemetry lock.
    """

    __slots__ = ("leg_active", "raw")

    def __init__(self) -> None:
        self.raw = ""
        self.leg_active = False

    def from_heartbeat(self, flavour: Flavour, raw: str) -> str:
        """The mode to show for a heartbeat's decoded mode."""
        if raw != self.raw and raw != "LOITER":
            self.leg_active = False
        self.raw = raw
        return flavour.shown_mode(raw, self.leg_active)

    def leg(self, flavour: Flavour, active: bool) -> str | None:
        """Mark a leg started or ended; the mode to show now (None before any heartbeat)."""
        self.leg_active = active
        return flavour.shown_mode(self.raw, active) if self.raw else None


class ModeOwner:
    """Whose mode the vehicle is in: one the agent asked for, or someone else's.

    A pilot's mode switch (RC or a second ground station) changes the vehicle's mode without the
    agent asking. The backend tells :meth:`expect` the raw mode before each command that changes
    it and feeds every heartbeat to :meth:`heartbeat`. Requests are kept until a heartbeat shows
    them (at most :data:`REQUEST_SEEN_WITHIN_S`): two commands sent within one heartbeat period (a
    leg, then a collision hold) show their modes one after the other, and both are ours. A change
    to any other mode (that is not the vehicle's own end of one of our manoeuvres,
    :meth:`Flavour.follows`, nor the agent's :attr:`Flavour.handback_mode`) while armed makes
    :attr:`foreign` that mode, until the vehicle is in an expected mode again (the pilot's
    hand-back) or the agent :meth:`adopt` s the mode (the operator's release). Not thread-safe by
    itself: callers hold their telemetry lock.
    """

    __slots__ = ("_requests", "expected", "foreign", "raw")

    def __init__(self) -> None:
        self.expected: str | None = None  # the mode of the agent's last request
        self.raw = ""
        self.foreign: str | None = None
        self._requests: list[tuple[str, float]] = []  # (mode, when asked), not yet seen, oldest first

    def expect(self, raw: str | None, now: float | None = None) -> None:
        """The agent is about to put the vehicle in ``raw`` (a decoded heartbeat mode name)."""
        self.expected = raw
        if raw is not None:
            self._requests.append((raw, time.monotonic() if now is None else now))
            del self._requests[:-REQUESTS_KEPT]

    def withdraw(self, raw: str | None, before: str | None) -> None:
        """The vehicle refused the request for ``raw``: the agent still expects ``before``."""
        self.expected = before
        for i in range(len(self._requests) - 1, -1, -1):
            if self._requests[i][0] == raw:
                del self._requests[i]
                break

    def _requested(self, raw: str, now: float) -> bool:
        """Whether ``raw`` answers one of our requests still in flight (it and older ones are done)."""
        fresh = [(mode, t) for mode, t in self._requests if now - t <= REQUEST_SEEN_WITHIN_S]
        for i, (mode, _t) in enumerate(fresh):
            if mode == raw:
                self._requests = fresh[i + 1 :]
                return True
        self._requests = fresh
        return False

    def heartbeat(self, flavour: Flavour, raw: str, armed: bool, now: float | None = None) -> None:
        previous, self.raw = self.raw, raw
        requested = self._requested(raw, time.monotonic() if now is None else now)
        if raw == previous or not previous:
            return
        if raw == self.expected or requested:
            self.foreign = None  # our own request (the last one, or one sent just before it)
        elif raw == flavour.handback_mode:
            # The agent's own mode: the pilot handed back, or the vehicle left a mode that was ours
            # (e.g. an adopted BRAKE failsafe) for it; never a pilot's takeover.
            self.expected = raw
            self.foreign = None
        elif self.foreign is not None:
            self.foreign = raw  # the pilot flies on, in another mode (or the vehicle's next one)
        elif not armed or flavour.follows(previous, raw):
            self.expected = raw  # on the ground, or the end of our own manoeuvre: still ours
        else:
            self.foreign = raw

    def adopt(self) -> None:
        """The operator's release: the vehicle's present mode is the agent's from now on."""
        self.expected = self.raw
        self.foreign = None


# How long a mode request waits to be seen in a heartbeat (1 Hz, later under load) before a
# change to that mode is no longer taken as its answer; and how many requests are remembered.
REQUEST_SEEN_WITHIN_S = 5.0
REQUESTS_KEPT = 8
