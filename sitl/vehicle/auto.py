"""AUTO mode: flying the stored mission item by item (take-off, waypoints, land, RTL, speed changes),
and how a new upload or DO_SET_MISSION_CURRENT moves the current item."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from sitl.dialect import mavlink as mav
from sitl.mission import FENCE, GLOBAL_FRAMES_AMSL, MISSION, MissionItem, build_fence
from sitl.physics import Limits, latlon_to_local
from sitl.vehicle.constants import (
    AUTO,
    NAV_CMDS,
    NAV_NAMES,
    SEV_INFO,
    TAKEOFF_DONE_M,
)

if TYPE_CHECKING:
    from sitl.vehicle.core import SimVehicle


class AutoMission:
    """Executes the MISSION store; the transfer protocol itself is sitl/mission.py."""

    def __init__(self, v: SimVehicle) -> None:
        self.v = v
        self.idx = 1  # current item (engine numbering: 0 is home)
        self.started = False  # the current item has begun
        self.hold_until: float | None = None
        self.reached = False
        self.complete = False
        self.returning = False  # flying a NAV_RETURN_TO_LAUNCH item
        self.landing = False  # flying a NAV_LAND item

    def ground_start(self) -> bool:
        """On the ground in AUTO only a takeoff item (or DO items before it) may run."""
        v = self.v
        items = v.mission.mission_items()
        if not 0 < self.idx < len(items):
            return False
        cmd = items[self.idx].command
        return cmd == mav.MAV_CMD_NAV_TAKEOFF or cmd not in NAV_CMDS

    def starts_with_takeoff(self) -> bool:
        """True when the first NAV item is a take-off (ArduCopter refuses AUTO on the ground otherwise)."""
        v = self.v
        for it in v.mission.mission_items()[1:]:
            if it.command in NAV_CMDS:
                return it.command == mav.MAV_CMD_NAV_TAKEOFF
        return False

    def begin(self) -> None:
        """Entering AUTO: restart from item 1 unless a mission is under way."""
        v = self.v
        n = len(v.mission.mission_items())
        if self.idx < 1 or self.idx >= n or self.complete:
            self.idx = 1
        self.started = False
        self.complete = False
        self.returning = self.landing = False
        self.send_current()

    def send_current(self) -> None:
        """MISSION_CURRENT at once when the current item changes."""
        v = self.v
        v.send(v.telemetry.msg_mission_current())

    def item_target(self, it: MissionItem, b: tuple[float, float, float]) -> tuple[float, float, float]:
        """An item's location in the local frame; 0,0 keeps the current position, alt 0 the altitude."""
        v = self.v
        if it.x == 0 and it.y == 0:
            n, e = b[0], b[1]
        else:
            n, e = latlon_to_local(v.origin[0], v.origin[1], it.lat, it.lon)
        d = v.guidance.alt_to_d(it.frame, it.z) if (it.z != 0 or it.frame in GLOBAL_FRAMES_AMSL) else b[2]
        return n, e, d

    def item_reached(self, seq: int) -> None:
        """MISSION_ITEM_REACHED for stored item ``seq``."""
        v = self.v
        v.send(mav.MAVLink_mission_item_reached_message(seq))

    def advance(self, reached: bool = True) -> None:
        """Go to the next item (MISSION_ITEM_REACHED unless skipped); after the last, 'Mission complete'."""
        v = self.v
        if reached:
            v.item_reached(self.idx)
        self.idx += 1
        self.started = False
        self.hold_until = None
        self.reached = False
        if self.idx >= len(v.mission.mission_items()):
            self.complete = True
            v.statustext(SEV_INFO, "Mission complete")
            b = v.belief()
            v.target = (b[0], b[1], b[2]) if not self.landing else v.target
            v.leg = None
        self.send_current()

    def step(self, lim: Limits, dt: float, b: tuple[float, float, float]) -> None:
        """Fly the current item for one step, starting it first (STATUSTEXT 'Mission: N ...')."""
        v = self.v
        k = v.kin
        items = v.mission.mission_items()
        if self.complete or self.idx >= len(items):
            if self.landing:
                v.guidance.land_step(lim, dt, b)
            elif self.returning:
                v.guidance.rtl_step(lim, dt, b)
            else:
                tn, te, td = v.target
                k.position_step(tn, te, td, lim, dt, b[0], b[1], b[2])
            return
        it = items[self.idx]
        cmd = it.command
        if not self.started:
            self.started = True
            v.statustext(SEV_INFO, f"Mission: {self.idx} {NAV_NAMES.get(cmd, str(cmd))}")
            self.returning = self.landing = False
            if cmd in (mav.MAV_CMD_NAV_WAYPOINT, mav.MAV_CMD_NAV_LOITER_UNLIM, mav.MAV_CMD_NAV_LOITER_TIME):
                v.guidance.goto(*self.item_target(it, b))
            elif cmd == mav.MAV_CMD_NAV_TAKEOFF:
                alt = it.z if it.frame not in GLOBAL_FRAMES_AMSL else it.z - v.home[2]
                d = -(alt + v.home[2] - v.origin[2])
                if -b[2] < -d - TAKEOFF_DONE_M:
                    v.target = (b[0], b[1], d)
                    if v.landed:
                        v.takeoff_alt = -d
                        v.landed = False
                else:
                    self.advance()
                    return
            elif cmd == mav.MAV_CMD_NAV_LAND:
                tn, te, _ = self.item_target(it, b)
                v.target = (tn, te, b[2])
                v.guidance.set_leg(tn, te)
                self.landing = True
                v.guidance.land_target = (tn, te)
            elif cmd == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH:
                self.returning = True
                v.start_rtl()
            elif cmd == mav.MAV_CMD_DO_CHANGE_SPEED:
                v.commands.change_speed(it.param1, it.param2)
                self.advance()
                return
            else:  # other DO/condition commands: not simulated, skipped
                self.advance(reached=False)
                return
        if cmd in (mav.MAV_CMD_NAV_WAYPOINT, mav.MAV_CMD_NAV_LOITER_UNLIM, mav.MAV_CMD_NAV_LOITER_TIME):
            tn, te, td = v.target
            k.position_step(tn, te, td, lim, dt, b[0], b[1], b[2])
            dist = math.sqrt((tn - b[0]) ** 2 + (te - b[1]) ** 2 + (td - b[2]) ** 2)
            hold = it.param1 if cmd != mav.MAV_CMD_NAV_LOITER_UNLIM else math.inf
            if not self.reached:
                radius = max(0.05, v.params["WPNAV_RADIUS"] / 100.0)
                if hold > 0:  # a hold needs the vehicle stopped on the point
                    radius = min(radius, 0.5)
                if dist <= radius and (hold <= 0 or math.hypot(k.vn, k.ve) < 0.3):
                    self.reached = True
                    self.hold_until = v.t + hold
            if self.reached and self.hold_until is not None and v.t >= self.hold_until:
                self.advance()
        elif cmd == mav.MAV_CMD_NAV_TAKEOFF:
            if v.takeoff_alt is None:
                tn, te, td = v.target
                k.position_step(tn, te, td, lim, dt, b[0], b[1], b[2])
                if abs(td - b[2]) < TAKEOFF_DONE_M:
                    self.advance()
        elif cmd == mav.MAV_CMD_NAV_LAND:
            tn, te, td = v.target
            if not self.reached:
                k.position_step(tn, te, td, lim, dt, b[0], b[1], b[2])
                if math.hypot(tn - b[0], te - b[1]) < 0.5 and math.hypot(k.vn, k.ve) < 0.5:
                    self.reached = True
                    v.leg = None
            else:
                v.guidance.land_step(lim, dt, b)
        elif cmd == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            v.guidance.rtl_step(lim, dt, b)

    def can_clear(self, mission_type: int) -> bool:
        """A MISSION may not be cleared while it is flown in AUTO."""
        v = self.v
        return not (mission_type == MISSION and v.mode == AUTO and v.armed)

    def mission_stored(self, mission_type: int) -> None:
        """An upload replaced a list: rebuild the fence, or put the current item back in range."""
        v = self.v
        if mission_type == FENCE:
            v.fence.zones = build_fence(v.mission.stores[FENCE], v.origin[0], v.origin[1])
            v.params.define("FENCE_TOTAL", len(v.mission.stores[FENCE]))
        elif mission_type == MISSION:
            if v.mode != AUTO:
                self.idx = 1
                self.complete = False
                self.started = False
            elif self.idx >= len(v.mission.mission_items()):
                self.idx = max(1, len(v.mission.mission_items()) - 1)
                self.started = False

    def home_item(self) -> MissionItem:
        """Item 0 of an ArduPilot mission download: home."""
        v = self.v
        return MissionItem(
            0,
            mav.MAV_FRAME_GLOBAL,
            mav.MAV_CMD_NAV_WAYPOINT,
            0,
            1,
            0,
            0,
            0,
            0,
            round(v.home[0] * 1e7),
            round(v.home[1] * 1e7),
            v.home[2],
        )

    def set_current(self, seq: int) -> bool:
        """DO_SET_MISSION_CURRENT / MISSION_SET_CURRENT; False for an item that does not exist."""
        v = self.v
        if not 0 < seq < len(v.mission.mission_items()):
            return False
        self.idx = seq
        self.started = False
        self.complete = False
        self.reached = False
        self.send_current()
        return True
