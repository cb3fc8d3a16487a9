"""Outgoing telemetry: every message the vehicle streams or sends on request, built from its state now."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from sitl.dialect import mavlink as mav
from sitl.physics import local_to_latlon
from sitl.vehicle.constants import (
    AUTO,
    BRAKE,
    GUIDED,
    LAND,
    LOITER,
    POSHOLD,
    RTL,
    RTL_FINAL,
)

if TYPE_CHECKING:
    from sitl.vehicle.core import SimVehicle
from collections.abc import Callable


class Telemetry:
    """Builds MAVLink messages from the vehicle state (a personality subclasses it: sitl/px4.py)."""

    def __init__(self, v: SimVehicle) -> None:
        self.v = v

    def time_boot_ms(self) -> int:
        """Sim milliseconds since boot (wraps like the uint32 field)."""
        v = self.v
        return int(v.t * 1000) & 0xFFFFFFFF

    def landed_state(self) -> int:
        """MAV_LANDED_STATE as ArduCopter reports it."""
        v = self.v
        if v.landed and v.takeoff_alt is None:
            return mav.MAV_LANDED_STATE_ON_GROUND
        if v.takeoff_alt is not None:
            return mav.MAV_LANDED_STATE_TAKEOFF
        landing = (
            v.mode == LAND
            or (v.mode == RTL and v.guidance.rtl_state == RTL_FINAL)
            or (v.mode == AUTO and v.auto.landing and v.auto.reached)
            or (v.mode == AUTO and v.auto.returning and v.guidance.rtl_state == RTL_FINAL)
        )
        return mav.MAV_LANDED_STATE_LANDING if landing else mav.MAV_LANDED_STATE_IN_AIR

    def msg_heartbeat(self) -> mav.MAVLink_message:
        """HEARTBEAT: quadrotor, ArduPilot, custom mode + armed flag."""
        v = self.v
        base = (
            mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            | mav.MAV_MODE_FLAG_STABILIZE_ENABLED
            | mav.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        )
        if v.mode in (AUTO, GUIDED, RTL, LAND, LOITER, POSHOLD, BRAKE):
            base |= mav.MAV_MODE_FLAG_GUIDED_ENABLED
        if v.mode == AUTO:
            base |= mav.MAV_MODE_FLAG_AUTO_ENABLED
        if v.armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        if v.batt_failsafe or v.ekf_failsafe or v.gcs_failsafe:
            status = mav.MAV_STATE_CRITICAL
        else:
            status = mav.MAV_STATE_ACTIVE if v.armed else mav.MAV_STATE_STANDBY
        return mav.MAVLink_heartbeat_message(
            mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, base, v.mode, status, 3
        )

    def msg_sys_status(self) -> mav.MAVLink_message:
        """SYS_STATUS with sensor health (GPS, battery, fence, pre-arm) and battery figures."""
        v = self.v
        s = mav
        present = (
            s.MAV_SYS_STATUS_SENSOR_3D_GYRO
            | s.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | s.MAV_SYS_STATUS_SENSOR_3D_MAG
            | s.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | s.MAV_SYS_STATUS_SENSOR_GPS
            | s.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
            | s.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
            | s.MAV_SYS_STATUS_SENSOR_YAW_POSITION
            | s.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
            | s.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
            | s.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
            | s.MAV_SYS_STATUS_AHRS
            | s.MAV_SYS_STATUS_SENSOR_BATTERY
            | s.MAV_SYS_STATUS_PREARM_CHECK
        )
        if v.fence.enabled() or v.fence.zones:
            present |= s.MAV_SYS_STATUS_GEOFENCE
        enabled = present
        if not v.fence.enabled():
            enabled &= ~s.MAV_SYS_STATUS_GEOFENCE
        health = present
        if not v.gps_ok:
            health &= ~s.MAV_SYS_STATUS_SENSOR_GPS
        if v.batt_failsafe:
            health &= ~s.MAV_SYS_STATUS_SENSOR_BATTERY
        if v.fence.breaches:
            health &= ~s.MAV_SYS_STATUS_GEOFENCE
        if v.arming.prearm_failure() is not None:
            health &= ~s.MAV_SYS_STATUS_PREARM_CHECK
        bat = v.battery
        return mav.MAVLink_sys_status_message(
            present,
            enabled,
            health,
            150,
            int(bat.voltage_v * 1000),
            int(bat.current_a * 100),
            int(bat.remaining_pct),
            0,
            0,
            0,
            0,
            0,
            0,
            0,
            0,
            0,
        )

    def msg_global_position_int(self) -> mav.MAVLink_message:
        """GLOBAL_POSITION_INT from the estimate (what ArduPilot's EKF would report); zeros at boot."""
        v = self.v
        if v.booting:
            return mav.MAVLink_global_position_int_message(self.time_boot_ms(), 0, 0, 0, 0, 0, 0, 0, 65535)
        en, ee, ed = v.est()
        lat, lon = local_to_latlon(v.origin[0], v.origin[1], en, ee)
        alt = v.origin[2] - ed
        gvn, gve = v.ground_velocity()
        return mav.MAVLink_global_position_int_message(
            self.time_boot_ms(),
            round(lat * 1e7),
            round(lon * 1e7),
            round(alt * 1000),
            round((alt - v.home[2]) * 1000),
            round(gvn * 100),
            round(gve * 100),
            round(v.kin.vd * 100 if not v.landed else 0),
            round(math.degrees(v.heading) % 360 * 100) % 36000,
        )

    def msg_local_position_ned(self) -> mav.MAVLink_message:
        """LOCAL_POSITION_NED relative to the EKF origin."""
        v = self.v
        en, ee, ed = v.est()
        gvn, gve = v.ground_velocity()
        return mav.MAVLink_local_position_ned_message(
            self.time_boot_ms(), en, ee, ed, gvn, gve, v.kin.vd if not v.landed else 0.0
        )

    def msg_gps_raw_int(self) -> mav.MAVLink_message:
        """GPS_RAW_INT: 3D fix with 10 satellites, or fix 0 / frozen position while GPS is lost."""
        v = self.v
        gvn, gve = v.ground_velocity()
        if v.gps_ok:
            en, ee, ed = v.est()
            lat, lon = local_to_latlon(v.origin[0], v.origin[1], en, ee)
            alt = v.origin[2] - ed
            fix, sats, eph, epv = 3, 10, 121, 200
            vel = round(math.hypot(gvn, gve) * 100)
            cog = round(math.degrees(math.atan2(gve, gvn)) % 360 * 100) % 36000 if vel > 0 else 0
        else:
            lat, lon, alt = v.gps_fix_lat, v.gps_fix_lon, v.origin[2] - v.est()[2]
            if v.booting:
                lat = lon = alt = 0.0
            fix, sats, eph, epv, vel, cog = 0, 0, 9999, 9999, 0, 0
        return mav.MAVLink_gps_raw_int_message(
            int(v.t * 1e6),
            fix,
            round(lat * 1e7),
            round(lon * 1e7),
            round(alt * 1000),
            eph,
            epv,
            vel,
            cog,
            sats,
            0,
            500 if fix else 0,
            800 if fix else 0,
            300 if fix else 0,
            0,
            0,
        )

    def msg_attitude(self) -> mav.MAVLink_message:
        """ATTITUDE: lean angles from the horizontal acceleration, yaw from the heading."""
        v = self.v
        k = v.kin
        c, s = math.cos(v.heading), math.sin(v.heading)
        a_fwd = k.an * c + k.ae * s
        a_right = -k.an * s + k.ae * c
        pitch = -math.atan2(a_fwd, 9.81)
        roll = math.atan2(a_right, 9.81)
        yaw = (v.heading + math.pi) % (2 * math.pi) - math.pi
        return mav.MAVLink_attitude_message(self.time_boot_ms(), roll, pitch, yaw, 0.0, 0.0, 0.0)

    def msg_vfr_hud(self) -> mav.MAVLink_message:
        """VFR_HUD: air/ground speed, heading, throttle %, AMSL altitude, climb rate."""
        v = self.v
        gvn, gve = v.ground_velocity()
        gs = math.hypot(gvn, gve)
        airspeed = math.hypot(gvn - v.wind.north - v.gust[0], gve - v.wind.east - v.gust[1])
        p = v.power.power_w(not v.landed, v.armed, airspeed, -v.kin.vd)
        thr = 0 if not v.armed else min(100, round(50 * math.sqrt(p / v.power.p_hover)))
        alt = v.origin[2] - v.est()[2]
        return mav.MAVLink_vfr_hud_message(
            airspeed if not v.landed else 0.0,
            gs,
            round(math.degrees(v.heading)) % 360,
            thr,
            alt,
            -v.kin.vd if not v.landed else 0.0,
        )

    def msg_battery_status(self) -> mav.MAVLink_message:
        """BATTERY_STATUS: pack voltage in cell 0 (as ArduPilot without cell monitoring), charge state."""
        v = self.v
        bat = v.battery
        volts = [min(65534, int(bat.voltage_v * 1000))] + [65535] * 9
        charge_state = mav.MAV_BATTERY_CHARGE_STATE_OK
        if v.batt_failsafe:
            charge_state = mav.MAV_BATTERY_CHARGE_STATE_LOW
        remaining_s = 0
        if bat.current_a > 0.5:
            remaining_s = int((bat.capacity_mah - bat.consumed_mah) / 1000.0 / bat.current_a * 3600)
        return mav.MAVLink_battery_status_message(
            0,
            mav.MAV_BATTERY_FUNCTION_ALL,
            mav.MAV_BATTERY_TYPE_LIPO,
            32767,
            volts,
            int(bat.current_a * 100),
            int(bat.consumed_mah),
            int(bat.energy_j / 100),
            int(bat.remaining_pct),
            max(0, remaining_s),
            charge_state,
            [0, 0, 0, 0],
            0,
            0,
        )

    def msg_home_position(self) -> mav.MAVLink_message | None:
        """HOME_POSITION (AMSL mm) plus its local NED offset; none before the first fix."""
        v = self.v
        if v.booting:
            return None
        hn, he, hd = v.home_ned
        return mav.MAVLink_home_position_message(
            round(v.home[0] * 1e7),
            round(v.home[1] * 1e7),
            round(v.home[2] * 1000),
            hn,
            he,
            hd,
            [1.0, 0.0, 0.0, 0.0],
            0.0,
            0.0,
            0.0,
            int(v.t * 1e6),
        )

    def msg_extended_sys_state(self) -> mav.MAVLink_message:
        """EXTENDED_SYS_STATE with the landed state."""
        return mav.MAVLink_extended_sys_state_message(mav.MAV_VTOL_STATE_UNDEFINED, self.landed_state())

    def msg_mission_current(self) -> mav.MAVLink_message:
        """MISSION_CURRENT: seq, total (home excluded) and mission state."""
        v = self.v
        n = len(v.mission.mission_items())
        if n <= 1:
            state = mav.MISSION_STATE_NO_MISSION
        elif v.auto.complete:
            state = mav.MISSION_STATE_COMPLETE
        elif v.mode == AUTO and v.armed:
            state = mav.MISSION_STATE_ACTIVE
        elif v.auto.started:
            state = mav.MISSION_STATE_PAUSED
        else:
            state = mav.MISSION_STATE_NOT_STARTED
        seq = min(v.auto.idx, max(0, n - 1))
        return mav.MAVLink_mission_current_message(seq, max(0, n - 1), state, 1 if v.mode == AUTO else 0)

    def msg_nav_controller_output(self) -> mav.MAVLink_message:
        """NAV_CONTROLLER_OUTPUT: bearing and distance to the current position target."""
        v = self.v
        b = v.belief()
        tn, te, td = v.target
        bearing = round(math.degrees(math.atan2(te - b[1], tn - b[0]))) if v.armed else 0
        wp_dist = min(65535, round(math.hypot(tn - b[0], te - b[1]))) if v.armed else 0
        return mav.MAVLink_nav_controller_output_message(
            0.0, 0.0, bearing, bearing, wp_dist, float(b[2] - td) if v.armed else 0.0, 0.0, 0.0
        )

    def msg_fence_status(self) -> mav.MAVLink_message | None:
        """FENCE_STATUS, only while the fence is enabled (as ArduPilot)."""
        v = self.v
        if not v.fence.enabled():
            return None
        return mav.MAVLink_fence_status_message(
            1 if v.fence.breaches else 0, v.fence.breach_count, v.fence.breach_type, v.fence.breach_time_ms, 0
        )

    def msg_system_time(self) -> mav.MAVLink_message:
        """SYSTEM_TIME: Unix time unknown (0), sim boot time."""
        return mav.MAVLink_system_time_message(0, self.time_boot_ms())

    # What AUTOPILOT_VERSION advertises: how parameters are encoded, and the firmware (major, minor, patch).
    param_capability = mav.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    firmware = (4, 5, 0)

    def msg_autopilot_version(self) -> mav.MAVLink_message:
        """AUTOPILOT_VERSION with the capabilities a GCS checks (MISSION_INT, COMMAND_INT, FENCE...)."""
        c = mav
        caps = (
            c.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
            | self.param_capability
            | c.MAV_PROTOCOL_CAPABILITY_MISSION_INT
            | c.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | c.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
            | c.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
            | c.MAV_PROTOCOL_CAPABILITY_MAVLINK2
            | c.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
            | c.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
        )
        major, minor, patch = self.firmware
        version = (major << 24) | (minor << 16) | (patch << 8) | c.FIRMWARE_VERSION_TYPE_OFFICIAL
        return mav.MAVLink_autopilot_version_message(
            caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, self.v.sysid, [0] * 18
        )


def _telemetry(name: str) -> Callable[[SimVehicle], mav.MAVLink_message | None]:
    """Calls the vehicle's telemetry object of the moment: a personality's override is the one streamed."""
    return lambda v: getattr(v.telemetry, name)()


BUILDERS: dict[int, Callable[[SimVehicle], mav.MAVLink_message | None]] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: _telemetry("msg_heartbeat"),
    mav.MAVLINK_MSG_ID_SYS_STATUS: _telemetry("msg_sys_status"),
    mav.MAVLINK_MSG_ID_SYSTEM_TIME: _telemetry("msg_system_time"),
    mav.MAVLINK_MSG_ID_GPS_RAW_INT: _telemetry("msg_gps_raw_int"),
    mav.MAVLINK_MSG_ID_ATTITUDE: _telemetry("msg_attitude"),
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: _telemetry("msg_local_position_ned"),
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: _telemetry("msg_global_position_int"),
    mav.MAVLINK_MSG_ID_MISSION_CURRENT: _telemetry("msg_mission_current"),
    mav.MAVLINK_MSG_ID_NAV_CONTROLLER_OUTPUT: _telemetry("msg_nav_controller_output"),
    mav.MAVLINK_MSG_ID_VFR_HUD: _telemetry("msg_vfr_hud"),
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: _telemetry("msg_battery_status"),
    mav.MAVLINK_MSG_ID_HOME_POSITION: _telemetry("msg_home_position"),
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: _telemetry("msg_extended_sys_state"),
    mav.MAVLINK_MSG_ID_FENCE_STATUS: _telemetry("msg_fence_status"),
    mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION: _telemetry("msg_autopilot_version"),
}

DEFAULT_STREAMS: dict[int, float] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
}
