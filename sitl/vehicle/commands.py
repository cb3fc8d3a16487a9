"""COMMAND_LONG / COMMAND_INT: what the simulated ArduCopter does with each MAV_CMD and what it answers
(arm, mode, take-off, land, RTL, DO_REPOSITION, DO_CHANGE_SPEED, DO_SET_HOME, message intervals, missions)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from sitl.dialect import mavlink as mav
from sitl.mission import GLOBAL_FRAMES_AMSL
from sitl.physics import latlon_to_local, local_to_latlon
from sitl.vehicle.constants import (
    AUTO,
    FORCE_MAGIC,
    GUIDED,
    LAND,
    RTL,
    SEV_CRITICAL,
    SEV_WARNING,
)
from sitl.vehicle.telemetry import BUILDERS

if TYPE_CHECKING:
    from collections.abc import Callable

    from sitl.vehicle.core import SimVehicle

Result = tuple[int | None, list[str]]  # MAV_RESULT (None: no ACK) and STATUSTEXTs to send before it
ACCEPTED, FAILED = mav.MAV_RESULT_ACCEPTED, mav.MAV_RESULT_FAILED


class Commands:
    """Executes one command and sends its COMMAND_ACK (and any STATUSTEXT first)."""

    def __init__(self, v: SimVehicle) -> None:
        self.v = v
        self.handlers: dict[int, Callable[[mav.MAVLink_message, bool], Result]] = self._table()

    def handle(self, msg: mav.MAVLink_message, is_int: bool) -> None:
        """Execute, send the STATUSTEXTs and the COMMAND_ACK, then any requested message."""
        v = self.v
        cmd = msg.command
        result, extra = v.command_result(msg, is_int)
        for text in extra:
            v.statustext(SEV_CRITICAL if text.startswith(("PreArm", "Arm")) else SEV_WARNING, text)
        if result is not None:
            v.send(
                mav.MAVLink_command_ack_message(
                    cmd, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
                )
            )
        if cmd == mav.MAV_CMD_REQUEST_MESSAGE and result == mav.MAV_RESULT_ACCEPTED:
            out = v.build(int(msg.param1))
            if out is not None:
                v.send(out)
        elif cmd == mav.MAV_CMD_GET_HOME_POSITION and (home := v.telemetry.msg_home_position()) is not None:
            v.send(home)
        elif cmd == mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES and result == mav.MAV_RESULT_ACCEPTED:
            v.send(v.telemetry.msg_autopilot_version())

    def location(
        self, msg: mav.MAVLink_message, is_int: bool
    ) -> tuple[float | None, float | None, float | None]:
        """lat, lon (deg) and local down of a command's location; None where 'keep current'."""
        v = self.v
        if is_int:
            lat = msg.x / 1e7 if msg.x != 0 else None
            lon = msg.y / 1e7 if msg.y != 0 else None
            frame, alt = msg.frame, msg.z
        else:
            lat = msg.param5 if msg.param5 != 0 and not math.isnan(msg.param5) else None
            lon = msg.param6 if msg.param6 != 0 and not math.isnan(msg.param6) else None
            frame, alt = mav.MAV_FRAME_GLOBAL_RELATIVE_ALT, msg.param7
        d = None if math.isnan(alt) else v.guidance.alt_to_d(frame, alt)
        return lat, lon, d

    def result(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """Execute a COMMAND_LONG/INT; returns (MAV_RESULT, STATUSTEXTs to send first)."""
        run = self.handlers.get(msg.command)
        return run(msg, is_int) if run is not None else (mav.MAV_RESULT_UNSUPPORTED, [])

    def arm_disarm(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """COMPONENT_ARM_DISARM: param1 arm/disarm, param2 21196 forces."""
        v = self.v
        force = round(msg.param2) == FORCE_MAGIC
        if msg.param1 >= 0.5:
            ok, why = v.arm(force)
            return (ACCEPTED, []) if ok else (FAILED, [why])
        if not v.armed:
            return ACCEPTED, []
        if not v.landed and not force:
            return FAILED, []
        v.disarm()
        return ACCEPTED, []

    def do_set_mode(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """DO_SET_MODE: the ArduCopter custom mode in param2."""
        return (ACCEPTED if self.v.set_mode(int(msg.param2)) else FAILED), []

    def nav_takeoff(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """NAV_TAKEOFF: armed, landed, in GUIDED, to an altitude above home higher than the current one."""
        v = self.v
        alt = msg.z if is_int else msg.param7
        if is_int and msg.frame in GLOBAL_FRAMES_AMSL:
            alt -= v.home[2]
        if (
            not v.armed
            or v.mode != GUIDED
            or not v.landed
            or v.takeoff_alt is not None
            or math.isnan(alt)
            or alt <= v.alt_rel_est()
        ):
            return FAILED, []
        b = v.belief()
        v.guided_wp_active = False
        v.takeoff_alt = alt + v.home[2] - v.origin[2]
        v.target = (b[0], b[1], -v.takeoff_alt)
        v.landed = False
        v.leg = None
        return ACCEPTED, []

    def nav_land(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """NAV_LAND: switch to LAND."""
        return (ACCEPTED if self.v.set_mode(LAND) else FAILED), []

    def nav_return_to_launch(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """NAV_RETURN_TO_LAUNCH: switch to RTL."""
        return (ACCEPTED if self.v.set_mode(RTL) else FAILED), []

    def do_reposition(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """DO_REPOSITION: GUIDED (switching if needed) to the location; stored but not flown while landed."""
        v = self.v
        lat, lon, d = self.location(msg, is_int)
        if v.mode != GUIDED and not v.set_mode(GUIDED):
            return FAILED, []
        b = v.belief()
        n, e = b[0], b[1]
        if lat is not None and lon is not None:
            n, e = latlon_to_local(v.origin[0], v.origin[1], lat, lon)
        if d is None:
            d = v.target[2] if not v.landed else b[2]
        if not v.landed or v.takeoff_alt is not None:
            v.guidance.goto(n, e, d)
        if msg.param1 > 0:
            v.speed_xy_override = msg.param1
        return ACCEPTED, []

    def do_change_speed(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """DO_CHANGE_SPEED: only AUTO, GUIDED and RTL take it (their Mode::set_speed_xy)."""
        if self.v.mode not in (AUTO, GUIDED, RTL):
            return FAILED, []
        return (ACCEPTED if self.change_speed(msg.param1, msg.param2) else FAILED), []

    def do_set_home(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """DO_SET_HOME: param1 1 = here, else lat/lon/alt AMSL; HOME_POSITION follows."""
        v = self.v
        if msg.param1 >= 0.5:
            en, ee, ed = v.est()
            lat_, lon_ = local_to_latlon(v.origin[0], v.origin[1], en, ee)
            v.home = (lat_, lon_, v.origin[2] - ed)
        else:
            if is_int:
                lat_, lon_, alt_ = msg.x / 1e7, msg.y / 1e7, msg.z
            else:
                lat_, lon_, alt_ = msg.param5, msg.param6, msg.param7
            if (lat_ == 0 and lon_ == 0) or math.isnan(alt_):
                return FAILED, []
            v.home = (lat_, lon_, alt_)
        if (home := v.telemetry.msg_home_position()) is not None:
            v.send(home)
        return ACCEPTED, []

    def set_message_interval(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """SET_MESSAGE_INTERVAL: param1 message id, param2 us (-1 stop, 0 default 1 Hz)."""
        mid, us = int(msg.param1), msg.param2
        if mid not in BUILDERS:
            return FAILED, []
        if us < 0:
            (self.v.reply_link or self.v.link).set_message_interval(mid, None)
        elif us == 0:
            (self.v.reply_link or self.v.link).set_message_interval(mid, 1.0)
        else:
            (self.v.reply_link or self.v.link).set_message_interval(mid, us / 1e6)
        return ACCEPTED, []

    def request_message(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """REQUEST_MESSAGE: any message we can build (sent after the ACK by :meth:`handle`)."""
        return (ACCEPTED if int(msg.param1) in BUILDERS else FAILED), []

    def accept(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """Commands answered ACCEPTED (GET_HOME_POSITION and capabilities reply after the ACK)."""
        return ACCEPTED, []

    def mission_start(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """MISSION_START: AUTO from param1 (if > 0); FAILED without a mission."""
        v = self.v
        if len(v.mission.mission_items()) <= 1:
            return FAILED, []
        if v.mode != AUTO and not v.set_mode(AUTO):
            return FAILED, []
        if int(msg.param1) > 0:
            v.set_mission_current(int(msg.param1))
        return ACCEPTED, []

    def do_set_mission_current(self, msg: mav.MAVLink_message, is_int: bool) -> Result:
        """DO_SET_MISSION_CURRENT: the current item (param1)."""
        return (ACCEPTED if self.v.set_mission_current(int(msg.param1)) else FAILED), []

    def _table(self) -> dict[int, Callable[[mav.MAVLink_message, bool], Result]]:
        """MAV_CMD -> handler; anything else is MAV_RESULT_UNSUPPORTED."""
        return {
            mav.MAV_CMD_COMPONENT_ARM_DISARM: self.arm_disarm,
            mav.MAV_CMD_DO_SET_MODE: self.do_set_mode,
            mav.MAV_CMD_NAV_TAKEOFF: self.nav_takeoff,
            mav.MAV_CMD_NAV_LAND: self.nav_land,
            mav.MAV_CMD_NAV_RETURN_TO_LAUNCH: self.nav_return_to_launch,
            mav.MAV_CMD_DO_REPOSITION: self.do_reposition,
            mav.MAV_CMD_DO_CHANGE_SPEED: self.do_change_speed,
            mav.MAV_CMD_DO_SET_HOME: self.do_set_home,
            mav.MAV_CMD_SET_MESSAGE_INTERVAL: self.set_message_interval,
            mav.MAV_CMD_REQUEST_MESSAGE: self.request_message,
            mav.MAV_CMD_GET_HOME_POSITION: self.accept,
            mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self.accept,
            mav.MAV_CMD_MISSION_START: self.mission_start,
            mav.MAV_CMD_DO_SET_MISSION_CURRENT: self.do_set_mission_current,
            mav.MAV_CMD_CONDITION_YAW: self.accept,
        }

    def change_speed(self, speed_type: float, speed: float) -> bool:
        """Speed override for horizontal (0/1), climb (2) or descent (3); -1/0 leaves it unchanged."""
        v = self.v
        if speed <= 0:
            return speed == -1 or speed == 0
        st = int(speed_type)
        if st in (0, 1):
            v.speed_xy_override = speed
        elif st == 2:
            v.speed_up_override = speed
        elif st == 3:
            v.speed_dn_override = speed
        else:
            return False
        return True
