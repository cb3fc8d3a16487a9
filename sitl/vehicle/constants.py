"""ArduCopter's numbers the simulated vehicle shares across its parts: mode numbers, tunables, severities."""

from __future__ import annotations

from sitl.dialect import mavlink as mav

# ArduCopter custom mode numbers (ArduCopter/mode.h)
MODES: dict[str, int] = {
    "STABILIZE": 0,
    "ACRO": 1,
    "ALT_HOLD": 2,
    "AUTO": 3,
    "GUIDED": 4,
    "LOITER": 5,
    "RTL": 6,
    "LAND": 9,
    "POSHOLD": 16,
    "BRAKE": 17,
}
MODE_NAMES: dict[int, str] = {v: k for k, v in MODES.items()}
STABILIZE, ACRO, ALT_HOLD, AUTO, GUIDED, LOITER, RTL, LAND, POSHOLD, BRAKE = (
    0,
    1,
    2,
    3,
    4,
    5,
    6,
    9,
    16,
    17,
)
ARMABLE_MODES = {STABILIZE, ACRO, ALT_HOLD, GUIDED, LOITER, POSHOLD}
POSITION_MODES = {AUTO, GUIDED, LOITER, RTL, POSHOLD, BRAKE}
FORCE_MAGIC = 21196

WIND_LEAK = 0.1  # fraction of steady wind the position controller fails to reject instantly
GUST_LEAK = 0.3  # gusts are faster than the loop, so more of them gets through
BRAKE_DECEL = 7.5  # m/s^2, ArduCopter BRAKE mode deceleration
TAKEOFF_DONE_M = 0.3
LAND_DETECT_S = 1.0
# ArduCopter's EKF failsafe on GPS loss: EKF3 times its position out after EK3's posRetryTimeNoVel
# (7 s without GPS), then ekf_check (10 Hz) needs 10 bad iterations (1 s) before "EKF variance" and
# the FS_EKF_ACTION failsafe.
EK3_POS_TIMEOUT_S = 7.0
EKF_CHECK_S = 1.0
GPS_FS_S = EK3_POS_TIMEOUT_S + EKF_CHECK_S  # GPS loss to the EKF failsafe, airborne
VEL_TIMEOUT_S = 3.0  # GUIDED velocity targets expire like ArduCopter's

# RTL sub-states
RTL_CLIMB, RTL_RETURN, RTL_LOITER, RTL_DESCEND, RTL_FINAL = range(5)

SEV_CRITICAL = mav.MAV_SEVERITY_CRITICAL
SEV_WARNING = mav.MAV_SEVERITY_WARNING
SEV_NOTICE = mav.MAV_SEVERITY_NOTICE
SEV_INFO = mav.MAV_SEVERITY_INFO

NAV_NAMES = {
    mav.MAV_CMD_NAV_WAYPOINT: "WP",
    mav.MAV_CMD_NAV_TAKEOFF: "Takeoff",
    mav.MAV_CMD_NAV_LAND: "Land",
    mav.MAV_CMD_NAV_RETURN_TO_LAUNCH: "RTL",
    mav.MAV_CMD_NAV_LOITER_UNLIM: "LoitUnlim",
    mav.MAV_CMD_NAV_LOITER_TIME: "LoitTime",
    mav.MAV_CMD_DO_CHANGE_SPEED: "ChangeSpeed",
}
NAV_CMDS = {
    mav.MAV_CMD_NAV_WAYPOINT,
    mav.MAV_CMD_NAV_TAKEOFF,
    mav.MAV_CMD_NAV_LAND,
    mav.MAV_CMD_NAV_RETURN_TO_LAUNCH,
    mav.MAV_CMD_NAV_LOITER_UNLIM,
    mav.MAV_CMD_NAV_LOITER_TIME,
}

# REQUEST_DATA_STREAM groups -> message ids (as ArduCopter's SRx stream groups, restricted to ours)
STREAM_GROUPS: dict[int, tuple[int, ...]] = {
    mav.MAV_DATA_STREAM_EXTENDED_STATUS: (
        mav.MAVLINK_MSG_ID_SYS_STATUS,
        mav.MAVLINK_MSG_ID_MISSION_CURRENT,
        mav.MAVLINK_MSG_ID_GPS_RAW_INT,
        mav.MAVLINK_MSG_ID_NAV_CONTROLLER_OUTPUT,
        mav.MAVLINK_MSG_ID_FENCE_STATUS,
    ),
    mav.MAV_DATA_STREAM_POSITION: (
        mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
        mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
    ),
    mav.MAV_DATA_STREAM_EXTRA1: (mav.MAVLINK_MSG_ID_ATTITUDE,),
    mav.MAV_DATA_STREAM_EXTRA2: (mav.MAVLINK_MSG_ID_VFR_HUD,),
    mav.MAV_DATA_STREAM_EXTRA3: (
        mav.MAVLINK_MSG_ID_BATTERY_STATUS,
        mav.MAVLINK_MSG_ID_SYSTEM_TIME,
        mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
    ),
}


def param_name(raw: str | bytes) -> str:
    """A PARAM_* message's parameter name, NUL padding stripped, upper case."""
    if isinstance(raw, bytes):
        raw = raw.decode(errors="replace")
    return raw.split("\x00", 1)[0].strip().upper()
