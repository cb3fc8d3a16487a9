"""SET_POSITION_TARGET_GLOBAL_INT / _LOCAL_NED: GUIDED position and velocity targets (never acknowledged)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from sitl.dialect import mavlink as mav
from sitl.mission import GLOBAL_FRAMES_AMSL
from sitl.physics import latlon_to_local
from sitl.vehicle.constants import (
    GUIDED,
)

if TYPE_CHECKING:
    from sitl.vehicle.core import SimVehicle


class Setpoints:
    """Turns position/velocity targets into GUIDED destinations."""

    def __init__(self, v: SimVehicle) -> None:
        self.v = v

    def global_int(self, msg: mav.MAVLink_message) -> None:
        """GUIDED position (or velocity) target; never acknowledged, like ArduCopter."""
        v = self.v
        if v.mode != GUIDED or not v.armed:
            return
        mask = msg.type_mask
        pos_ignore = mask & 0b111
        vel_ignore = mask & 0b111000
        if not pos_ignore:
            frame = msg.coordinate_frame
            n, e = latlon_to_local(v.origin[0], v.origin[1], msg.lat_int / 1e7, msg.lon_int / 1e7)
            if frame in GLOBAL_FRAMES_AMSL:
                d = -(msg.alt - v.origin[2])
            else:  # relative-alt (and terrain frames, treated as relative over flat ground)
                d = -(msg.alt + v.home[2] - v.origin[2])
            if v.landed and v.takeoff_alt is None:
                return  # ArduCopter ignores position targets on the ground
            v.guidance.goto(n, e, d)
        elif not vel_ignore:
            v.vel_target = (msg.vx, msg.vy, msg.vz)
            v.vel_target_t = v.t
            v.leg = None

    def local_ned(self, msg: mav.MAVLink_message) -> None:
        """SET_POSITION_TARGET_LOCAL_NED: LOCAL_NED, LOCAL_OFFSET_NED or BODY frames; velocity-only masks."""
        v = self.v
        if v.mode != GUIDED or not v.armed or (v.landed and v.takeoff_alt is None):
            return
        mask = msg.type_mask
        frame = msg.coordinate_frame
        if not mask & 0b111:
            if frame == mav.MAV_FRAME_LOCAL_NED:
                n, e, d = msg.x, msg.y, msg.z
            elif frame == mav.MAV_FRAME_LOCAL_OFFSET_NED:
                b = v.belief()
                n, e, d = b[0] + msg.x, b[1] + msg.y, b[2] + msg.z
            elif frame in (mav.MAV_FRAME_BODY_OFFSET_NED, mav.MAV_FRAME_BODY_NED):
                b = v.belief()
                c, s = math.cos(v.heading), math.sin(v.heading)
                n, e, d = b[0] + c * msg.x - s * msg.y, b[1] + s * msg.x + c * msg.y, b[2] + msg.z
            else:
                return
            v.guidance.goto(n, e, d)
        elif not mask & 0b111000:
            vx, vy = msg.vx, msg.vy
            if frame in (mav.MAV_FRAME_BODY_OFFSET_NED, mav.MAV_FRAME_BODY_NED):
                c, s = math.cos(v.heading), math.sin(v.heading)
                vx, vy = c * msg.vx - s * msg.vy, s * msg.vx + c * msg.vy
            v.vel_target = (vx, vy, msg.vz)
            v.vel_target_t = v.t
            v.leg = None
