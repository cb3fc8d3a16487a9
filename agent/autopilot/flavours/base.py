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
