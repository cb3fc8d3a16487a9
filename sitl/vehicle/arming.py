"""Arming and disarming: ArduCopter's pre-arm checks and the words it says when it refuses."""

from __future__ import annotations

from typing import TYPE_CHECKING

from sitl.vehicle.constants import (
    AUTO,
    SEV_INFO,
)

if TYPE_CHECKING:
    from sitl.vehicle.core import SimVehicle


class Arming:
    """Pre-arm checks, arm, disarm."""

    def __init__(self, v: SimVehicle) -> None:
        self.v = v

    def prearm_failure(self) -> str | None:
        """The first failing pre-arm check, in ArduCopter's words; None when all pass (or ARMING_CHECK=0)."""
        v = self.v
        if v.params["ARMING_CHECK"] == 0:
            return None
        if v.booting or v.t < v.prearm_delay_s:
            return "PreArm: Need Position Estimate"
        if not v.gps_ok:
            return "PreArm: GPS 1: Bad fix"
        if v.batt_failsafe:
            return "PreArm: Battery 1 low voltage failsafe"
        if v.params["BATT_ARM_VOLT"] > 0 and v.battery.voltage_v < v.params["BATT_ARM_VOLT"]:
            return "PreArm: Battery 1 below minimum arming voltage"
        if v.fence.enabled() and v.fence.breached_types() != 0:
            return "PreArm: Fence: vehicle outside fence"
        return None

    def arm(self, force: bool = False) -> tuple[bool, str]:
        """Try to arm; returns (ok, reason)."""
        v = self.v
        if v.armed:
            return True, ""
        if v.mode not in v.armable_modes:
            return False, "Arm: Mode not armable"
        if not force:
            why = self.prearm_failure()
            if why is not None:
                return False, why
        v.armed = True
        v.arm_time = v.t
        v.landed = True
        v.landed_since = v.t
        v.failsafes.batt_low_since = None
        v.ekf_failsafe = v.gcs_failsafe = False
        b = v.belief()
        v.target = (b[0], b[1], b[2])
        if v.mode == AUTO:
            v.auto.begin()
        return True, ""

    def disarm(self, reason: str = "") -> None:
        """Stop the motors; LAND/RTL touchdowns say 'Land complete, disarming'."""
        v = self.v
        v.armed = False
        v.takeoff_alt = None
        if reason:
            v.statustext(
                SEV_INFO,
                f"Disarming motors ({reason})" if reason != "Land complete" else "Land complete, disarming",
            )
