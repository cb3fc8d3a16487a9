"""Failsafes: battery (BATT_LOW_*), EKF on GPS loss (FS_EKF_ACTION) and GCS heartbeat loss (FS_GCS_*)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from sitl.vehicle.constants import (
    ALT_HOLD,
    AUTO,
    GPS_FS_S,
    LAND,
    MODE_NAMES,
    POSITION_MODES,
    RTL,
    SEV_CRITICAL,
)

if TYPE_CHECKING:
    from sitl.vehicle.core import SimVehicle


def ekf_failsafe_delay(v: SimVehicle) -> float | None:
    """ArduCopter: sim seconds from GPS loss to the EKF failsafe; None when FS_EKF_THRESH <= 0 (off)."""
    return GPS_FS_S if v.params.get("FS_EKF_THRESH", 0.8) > 0 else None


def ekf_failsafe(v: SimVehicle) -> None:
    """ArduCopter's failsafe_ekf_event: "EKF variance", then FS_EKF_ACTION in a mode that needs GPS.

    1 (default) LAND, 2 ALT_HOLD (LAND if refused), 3 LAND even from a manual mode; 0 only reports.
    A vehicle already in LAND goes on landing (without GPS), with no mode change.
    """
    v.statustext(SEV_CRITICAL, "EKF variance")
    action = int(v.params["FS_EKF_ACTION"])
    if not action or v.mode == LAND or (v.mode not in POSITION_MODES and action != 3):
        return
    if not (action == 2 and v.set_mode(ALT_HOLD)):
        v.set_mode(LAND)
    v.statustext(SEV_CRITICAL, f"EKF Failsafe: changed to {MODE_NAMES.get(v.mode, v.mode)} Mode")


class Failsafes:
    """Checked once per physics step; switches mode through the vehicle's set_mode."""

    def __init__(self, v: SimVehicle) -> None:
        self.v = v
        self.batt_low_since: float | None = None  # pack below BATT_LOW_VOLT since (sim s)

    def check(self) -> None:
        """One step of the three failsafes; each acts once until it clears."""
        v = self.v
        p = v.params
        # battery (raw voltage against BATT_LOW_VOLT for BATT_LOW_TIMER seconds)
        low = p["BATT_LOW_VOLT"]
        if low > 0 and v.battery.voltage_v < low and v.armed:
            if self.batt_low_since is None:
                self.batt_low_since = v.t
            elif not v.batt_failsafe and v.t - self.batt_low_since >= p["BATT_LOW_TIMER"]:
                v.batt_failsafe = True
                bat = v.battery
                v.statustext(
                    SEV_CRITICAL, f"Battery 1 is low {bat.voltage_v:.2f}V used {bat.consumed_mah:.0f} mAh"
                )
                act = int(p["BATT_FS_LOW_ACT"])
                if not v.landed and v.mode not in (LAND,):
                    if act in (1,):
                        v.set_mode(LAND)
                    elif act in (2, 3, 4) and v.mode != RTL:
                        v.set_mode(RTL)
        elif self.batt_low_since is not None and v.battery.voltage_v >= low:
            self.batt_low_since = None
        # EKF failsafe on GPS loss: the personality says after how long and what it does
        delay = v.gnss_failsafe_delay()
        if (
            v.gps_lost_since is not None
            and delay is not None
            and not v.ekf_failsafe
            and v.armed
            and not v.landed
            and v.t - v.gps_lost_since >= delay
        ):
            v.ekf_failsafe = True
            v.gnss_failsafe()
        if v.gps_lost_since is None and v.ekf_failsafe:
            v.ekf_failsafe = False
            v.gnss_failsafe_cleared()
        # GCS failsafe (FS_GCS_ENABLE: 1 RTL, 2 continue AUTO else RTL, 5 LAND)
        fs_gcs = int(p["FS_GCS_ENABLE"])
        if (
            fs_gcs
            and v.armed
            and not v.landed
            and v.last_gcs_heartbeat is not None
            and v.t - v.last_gcs_heartbeat > p.get("FS_GCS_TIMEOUT", 5.0)
            and not v.gcs_failsafe
        ):
            v.gcs_failsafe = True
            v.statustext(SEV_CRITICAL, "GCS Failsafe")
            if fs_gcs == 5:
                v.set_mode(LAND)
            elif not (fs_gcs == 2 and v.mode == AUTO) and v.mode not in (RTL, LAND):
                v.set_mode(RTL)
        if v.last_gcs_heartbeat is not None and v.t - v.last_gcs_heartbeat <= 1.0:
            v.gcs_failsafe = False
