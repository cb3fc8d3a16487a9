"""Flight mode changes: ArduCopter's rules for entering a mode and what entering it resets."""

from __future__ import annotations

from typing import TYPE_CHECKING

from sitl.vehicle.constants import (
    AUTO,
    BRAKE,
    BRAKE_DECEL,
    GUIDED,
    LAND,
    LOITER,
    MODE_NAMES,
    POSHOLD,
    POSITION_MODES,
    RTL,
    SEV_NOTICE,
    SEV_WARNING,
)

if TYPE_CHECKING:
    from sitl.vehicle.core import SimVehicle


class ModeSwitch:
    """Decides whether a mode change is allowed and sets up the new mode's targets."""

    def __init__(self, v: SimVehicle) -> None:
        self.v = v

    def set_mode(self, mode: int, reason: str = "") -> bool:
        """ArduCopter's mode change rules; returns False (and says why) when refused."""
        v = self.v
        if mode not in MODE_NAMES:
            return False
        if v.armed and mode in POSITION_MODES and not v.gps_ok:
            v.statustext(SEV_WARNING, "Flight mode change failed")
            return False
        if mode == AUTO and v.armed:
            items = v.mission.mission_items()
            if len(items) <= 1:
                v.statustext(SEV_WARNING, "Flight mode change failed")
                return False
            if v.landed and not v.auto.starts_with_takeoff():
                v.statustext(SEV_WARNING, "Auto: Missing Takeoff Cmd")
                return False
        prev = v.mode
        v.mode = mode
        v.guided_wp_active = False
        v.speed_xy_override = v.speed_up_override = v.speed_dn_override = None
        v.vel_target = None
        if mode != AUTO:
            v.auto.returning = v.auto.landing = False
        if mode in (GUIDED, LOITER, POSHOLD):
            v.target = v.guidance.stopping_point() if not v.landed else v.belief()
            v.leg = None
        elif mode == BRAKE:
            v.target = v.guidance.stopping_point(BRAKE_DECEL) if not v.landed else v.belief()
            v.leg = None
        elif mode == LAND:
            sp = v.guidance.stopping_point() if not v.landed else v.belief()
            v.guidance.land_target = (sp[0], sp[1])
            v.leg = None
        elif mode == RTL:
            v.start_rtl()
        elif mode == AUTO and (prev != AUTO or not v.auto.started):
            v.auto.begin()
        if reason:
            v.statustext(SEV_NOTICE, reason)
        return True
