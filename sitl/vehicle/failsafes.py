"""Failsafes: battery (BATT_LOW_*), EKF on GPS loss (FS_EKF_ACTION) and GCS heartbeat loss (FS_GCS_*)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from sitl.vehicle.constants import (
    AUTO,
    GPS_FS_S,
    LAND,
    POSITION_MODES,
    RTL,
    SEV_CRITICAL,
)

if TYPE_CHECKING:
    from sitl.vehicle.core import SimVehicle


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
        # EKF failsafe on GPS loss in a position mode
        if (
            v.gps_lost_since is not None
            and not v.ekf_failsafe
            and v.armed
            and not v.landed
            and v.t - v.gps_lost_since >= GPS_FS_S
        ):
            v.ekf_failsafe = True
            action = int(p["FS_EKF_ACTION"])
            if action and v.mode in POSITION_MODES:
                v.set_mode(LAND)
                v.statustext(SEV_CRITICAL, "EKF Failsafe: changed to LAND Mode")
            else:
                v.statustext(SEV_CRITICAL, "EKF variance")
        if v.gps_lost_since is None:
            v.ekf_failsafe = False
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
