"""ArduPilot (Copter first): GUIDED targets, BRAKE holds, RTL_ALT in cm, FENCE_* parameters."""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

from agent.autopilot.base import FenceSpec, Telemetry
from agent.autopilot.flavours.base import Flavour
from agent.autopilot.mavlink_link import mavlink, mavutil

# ArduCopter modes whose controller takes MAV_CMD_DO_CHANGE_SPEED (Mode::set_speed_xy).
SPEED_MODES = frozenset({"AUTO", "GUIDED", "RTL"})


class ArduPilotFlavour(Flavour):
    """ArduPilot, and any MAVLink autopilot that is not PX4 (they follow ArduPilot's conventions)."""

    name = "ardupilot"
    mav_autopilot = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    guided_mode = "GUIDED"
    hold_modes = ("BRAKE", "LOITER")  # LOITER when BRAKE is refused or absent
    mission_home_item = True
    return_alt_param = "RTL_ALT"
    fence_actions: ClassVar[Mapping[str, int]] = {
        "report": 0,
        "rtl": 1,
        "land": 2,
        "hold": 4,
    }  # FENCE_ACTION (4 = brake)
    failsafe_modes = ("RTL", "LAND", "SMART_RTL", "BRAKE")
    release_modes = ("LOITER", "POSHOLD", "BRAKE")

    def decode_mode(self, mav_type: int, base_mode: int, custom_mode: int) -> str:
        if not base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return "UNKNOWN"
        mapping = mavutil.mode_mapping_bynumber(mav_type) or mavutil.mode_mapping_acm
        return str(mapping.get(custom_mode, f"MODE({custom_mode})")).upper()

    def mode_command(self, name: str, mav_type: int) -> tuple[tuple[float, ...], int]:
        mapping = mavutil.mode_mapping_byname(mav_type) or {v: k for k, v in mavutil.mode_mapping_acm.items()}
        custom = int(mapping[name])
        return (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom), custom

    def takeoff_params(self, alt_rel_m: float, tel: Telemetry) -> tuple[float, ...]:
        # param7 is the altitude above home; lat/lon 0 (NaN breaks ArduCopter).
        return (0, 0, 0, 0, 0, 0, alt_rel_m)

    def speed_accepted_in(self, mode: str) -> bool:
        # BRAKE, LOITER, LAND refuse DO_CHANGE_SPEED with MAV_RESULT_FAILED.
        return mode in SPEED_MODES

    def return_alt_value(self, alt_rel_m: float) -> float:
        return float(round(alt_rel_m * 100.0))  # RTL_ALT is in centimetres

    def fence_params(self, fence: FenceSpec, has_items: bool) -> list[tuple[str, float]]:
        fence_type = (4 if has_items else 0) | (1 if fence.max_alt_m is not None else 0)
        params: list[tuple[str, float]] = []
        if fence.max_alt_m is not None:
            params.append(("FENCE_ALT_MAX", fence.max_alt_m))
        params += [
            ("FENCE_ACTION", self.fence_action(fence.breach_action)),
            ("FENCE_TYPE", fence_type),
            ("FENCE_ENABLE", 1 if fence_type else 0),  # last: enabled only once configured
        ]
        return params
