"""Autopilot flavours (ArduPilot, PX4): the per-firmware conventions both backends share."""

from __future__ import annotations

from agent.autopilot.flavours.ardupilot import ArduPilotFlavour
from agent.autopilot.flavours.base import Flavour
from agent.autopilot.flavours.px4 import Px4Flavour
from agent.autopilot.mavlink_link import mavlink

__all__ = ["ARDUPILOT", "PX4", "ArduPilotFlavour", "Flavour", "Px4Flavour", "flavour_for"]

ARDUPILOT = ArduPilotFlavour()
PX4 = Px4Flavour()


def flavour_for(autopilot: int | None) -> Flavour:
    """The flavour of a heartbeat's ``autopilot`` field: PX4 for MAV_AUTOPILOT_PX4, else ArduPilot."""
    return PX4 if autopilot == mavlink.MAV_AUTOPILOT_PX4 else ARDUPILOT
