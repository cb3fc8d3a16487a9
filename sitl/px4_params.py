"""PX4's parameter table for the PX4 personality, and PX4's byte-wise encoding of integer parameters.

PX4 (v1.16, read from the real SITL) sends an INT32 parameter in PARAM_VALUE as the float whose bytes are
the integer (``MAV_SYS_ID`` = 1 arrives as 1.4e-45), and takes PARAM_SET of an INT32 parameter the same
way: a GCS that casts (sends 2.0) sets 1073741824. ArduPilot casts both ways (sitl/params.py).

The vehicle engine (sitl/vehicle/) reads ArduCopter-named parameters, so every PX4 parameter that
changes its behaviour is translated into the hidden ArduCopter table (:data:`TO_ENGINE`); the GCS only
ever sees the PX4 names.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from sitl.params import INT32, REAL32

# name -> (default, MAV_PARAM_TYPE): the real PX4 v1.16 SITL (sihsim_quadx) defaults.
PX4_DEFAULTS: dict[str, tuple[float, int]] = {
    "MAV_SYS_ID": (1, INT32),
    "MAV_COMP_ID": (1, INT32),
    "SYS_AUTOSTART": (10040, INT32),
    "MPC_XY_CRUISE": (5.0, REAL32),
    "MPC_XY_VEL_MAX": (12.0, REAL32),
    "MPC_ACC_HOR": (3.0, REAL32),
    "MPC_ACC_HOR_MAX": (5.0, REAL32),
    "MPC_Z_VEL_MAX_UP": (3.0, REAL32),
    "MPC_Z_VEL_MAX_DN": (1.5, REAL32),
    "MPC_ACC_UP_MAX": (4.0, REAL32),
    "MPC_ACC_DOWN_MAX": (3.0, REAL32),
    "MPC_TKO_SPEED": (1.5, REAL32),
    "MPC_LAND_SPEED": (0.7, REAL32),
    "MPC_LAND_ALT1": (10.0, REAL32),
    "MPC_LAND_ALT2": (5.0, REAL32),
    "NAV_ACC_RAD": (2.0, REAL32),
    "NAV_MC_ALT_RAD": (0.8, REAL32),
    "MIS_TAKEOFF_ALT": (2.5, REAL32),
    "MIS_DIST_1WP": (10000.0, REAL32),
    "RTL_RETURN_ALT": (30.0, REAL32),
    "RTL_DESCEND_ALT": (10.0, REAL32),
    "RTL_LAND_DELAY": (0.0, REAL32),
    "RTL_MIN_DIST": (10.0, REAL32),
    "RTL_CONE_ANG": (45, INT32),
    "RTL_TYPE": (0, INT32),
    "GF_ACTION": (2, INT32),
    "GF_MAX_HOR_DIST": (0.0, REAL32),
    "GF_MAX_VER_DIST": (0.0, REAL32),
    "GF_SOURCE": (0, INT32),
    "GF_PREDICT": (0, INT32),
    "NAV_DLL_ACT": (0, INT32),
    "NAV_RCL_ACT": (2, INT32),
    "COM_DL_LOSS_T": (10, INT32),
    "COM_RC_IN_MODE": (1, INT32),
    "COM_RCL_EXCEPT": (0, INT32),
    "COM_OF_LOSS_T": (1.0, REAL32),
    "COM_OBL_RC_ACT": (0, INT32),
    "COM_DISARM_PRFLT": (10.0, REAL32),
    "COM_DISARM_LAND": (2.0, REAL32),
    "COM_ARM_WO_GPS": (1, INT32),
    "EKF2_NOAID_TOUT": (5000000, INT32),
    "COM_LOW_BAT_ACT": (3, INT32),
    "COM_FLTMODE1": (-1, INT32),
    "BAT_LOW_THR": (0.15, REAL32),
    "BAT_CRIT_THR": (0.07, REAL32),
    "BAT_EMERGEN_THR": (0.05, REAL32),
    "BAT1_CAPACITY": (-1.0, REAL32),
    "BAT1_N_CELLS": (4, INT32),
    "SIM_BAT_ENABLE": (1, INT32),
    "SIM_BAT_DRAIN": (60.0, REAL32),
    "SIM_BAT_MIN_PCT": (50.0, REAL32),
    "SDLOG_MODE": (0, INT32),
}


def _fence_type(p: Callable[[str], float]) -> float:
    ftype = 4  # an uploaded fence always counts
    if p("GF_MAX_VER_DIST") > 0:
        ftype |= 1
    if p("GF_MAX_HOR_DIST") > 0:
        ftype |= 2
    return ftype


# GF_ACTION -> ArduCopter FENCE_ACTION the engine runs: 0 none / 1 warning -> report, 2 Hold -> BRAKE
# (shown as Hold), 3 Return -> RTL, 4 terminate and 5 Land -> LAND.
_GF_ACTION = {0: 0, 1: 0, 2: 4, 3: 1, 4: 2, 5: 2}
# NAV_DLL_ACT -> FS_GCS_ENABLE: 0 off, 2 Return -> RTL, 3 Land -> LAND (1 Hold and 5/6 are not modelled).
_DLL_ACT = {0: 0, 2: 1, 3: 5}

# engine (ArduCopter) parameter -> function of the PX4 table giving its value.
TO_ENGINE: dict[str, Callable[[Callable[[str], float]], float]] = {
    "WPNAV_SPEED": lambda p: p("MPC_XY_CRUISE") * 100.0,
    # Effective, not nominal: PX4's jerk-limited trajectory (MPC_JERK_AUTO) brakes from 4.5 m/s over
    # 6.9 m and is below 0.5 m/s only after about 3 s (measured on v1.16 SIH), i.e. about 1.5 m/s^2.
    "WPNAV_ACCEL": lambda p: p("MPC_ACC_HOR") * 50.0,
    "WPNAV_SPEED_UP": lambda p: p("MPC_Z_VEL_MAX_UP") * 100.0,
    "WPNAV_SPEED_DN": lambda p: p("MPC_Z_VEL_MAX_DN") * 100.0,
    "WPNAV_ACCEL_Z": lambda p: p("MPC_ACC_DOWN_MAX") * 100.0,
    "WPNAV_RADIUS": lambda p: p("NAV_ACC_RAD") * 100.0,
    "LAND_SPEED": lambda p: p("MPC_LAND_SPEED") * 100.0,
    "LAND_ALT_LOW": lambda p: p("MPC_LAND_ALT2") * 100.0,
    "FENCE_ENABLE": lambda p: 1.0,
    "FENCE_TYPE": _fence_type,
    "FENCE_ALT_MAX": lambda p: p("GF_MAX_VER_DIST"),
    "FENCE_RADIUS": lambda p: p("GF_MAX_HOR_DIST"),
    "FENCE_ACTION": lambda p: _GF_ACTION.get(int(p("GF_ACTION")), 0),
    "FS_GCS_ENABLE": lambda p: _DLL_ACT.get(int(p("NAV_DLL_ACT")), 0),
    "FS_GCS_TIMEOUT": lambda p: p("COM_DL_LOSS_T"),
}
# Engine parameters pinned for PX4: PX4 checks no battery voltage (SIM_BAT_* drives the percentage),
# the fence has no margin, and auto-disarm is the personality's own (COM_DISARM_*).
ENGINE_FIXED: dict[str, float] = {
    "BATT_LOW_VOLT": 0.0,
    "FENCE_MARGIN": 0.0,
    "DISARM_DELAY": 0.0,
    "RTL_LOIT_TIME": 0.0,
    "RTL_ALT_FINAL": 0.0,
    "LAND_SPEED_HIGH": 0.0,
}


def int_to_wire(value: int) -> float:
    """An INT32 parameter as PX4 puts it in PARAM_VALUE.param_value: its bytes read as a float."""
    return float(struct.unpack("<f", struct.pack("<i", int(value)))[0])


def wire_to_int(value: float) -> int:
    """The integer a PX4 PARAM_SET of an INT32 parameter carries (the float's bytes read as an int)."""
    return int(struct.unpack("<i", struct.pack("<f", value))[0])
