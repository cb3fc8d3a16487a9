"""PX4: main/sub custom modes, AMSL take-off, goto and hold both as DO_REPOSITION, byte-wise int params."""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from typing import ClassVar

from agent.autopilot.base import FenceSpec, Telemetry
from agent.autopilot.flavours.base import RETURN_ALT_FLOOR_M, Flavour, base_altitude_amsl
from agent.autopilot.mavlink_link import mavlink

# custom_mode = main << 16 | sub << 24. Names follow ArduPilot's where the meaning matches so the
# queue sees one vocabulary: PX4 "Hold" (AUTO.LOITER) reports LOITER, "Mission" reports AUTO.
PX4_MAIN = {1: "MANUAL", 2: "ALTCTL", 3: "POSCTL", 5: "ACRO", 6: "OFFBOARD", 7: "STABILIZED", 8: "RATTITUDE"}
PX4_AUTO_SUB = {
    1: "READY",
    2: "TAKEOFF",
    3: "LOITER",
    4: "AUTO",
    5: "RTL",
    6: "LAND",
    8: "FOLLOW_ME",
    9: "PRECLAND",
    10: "VTOL_TAKEOFF",
}
PX4_SET = {  # our mode name -> (main, sub)
    "MANUAL": (1, 0),
    "ALTCTL": (2, 0),
    "POSCTL": (3, 0),
    "GUIDED": (4, 3),  # PX4 flies position targets (DO_REPOSITION) in Hold
    "LOITER": (4, 3),
    "BRAKE": (4, 3),
    "HOLD": (4, 3),
    "AUTO": (4, 4),
    "MISSION": (4, 4),
    "RTL": (4, 5),
    "LAND": (4, 6),
    "TAKEOFF": (4, 2),
    "OFFBOARD": (6, 0),
    "STABILIZED": (7, 0),
}
_INT_TYPES = frozenset(
    {
        mavlink.MAV_PARAM_TYPE_UINT8,
        mavlink.MAV_PARAM_TYPE_INT8,
        mavlink.MAV_PARAM_TYPE_UINT16,
        mavlink.MAV_PARAM_TYPE_INT16,
        mavlink.MAV_PARAM_TYPE_UINT32,
        mavlink.MAV_PARAM_TYPE_INT32,
    }
)


class Px4Flavour(Flavour):
    """PX4 (v1.16 measured). There is no GUIDED: a goto is DO_REPOSITION, which PX4 flies in Hold.

    So asking for Hold while a reposition leg is flown changes nothing; the backends hold with
    :meth:`pause_params` instead, PX4's own pause. Because the vehicle reports Hold in both cases,
    :meth:`shown_mode` reports ``GUIDED`` while one of our legs is being flown and ``LOITER`` once
    held (or in any Hold we did not send a leg in).
    """

    name = "px4"
    mav_autopilot = mavlink.MAV_AUTOPILOT_PX4
    hold_modes = ("LOITER",)  # on the ground / disarmed, where DO_REPOSITION is refused
    params_bytewise = True
    return_alt_param = "RTL_RETURN_ALT"
    fence_actions: ClassVar[Mapping[str, int]] = {"report": 1, "hold": 2, "rtl": 3, "land": 5}  # GF_ACTION
    failsafe_modes = ("RTL", "LAND", "LOITER")
    handback_mode = "LOITER"  # Hold
    release_modes = ("POSCTL",)  # the pilot's position mode; Hold (LOITER) is the agent's own already

    def decode_mode(self, mav_type: int, base_mode: int, custom_mode: int) -> str:
        main = (custom_mode >> 16) & 0xFF
        sub = (custom_mode >> 24) & 0xFF
        if main == 4:
            return PX4_AUTO_SUB.get(sub, f"AUTO.{sub}")
        return PX4_MAIN.get(main, f"MODE({custom_mode})")

    def mode_command(self, name: str, mav_type: int) -> tuple[tuple[float, ...], int]:
        main, sub = PX4_SET[name]
        return (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub), (main << 16) | (sub << 24)

    def takeoff_params(self, alt_rel_m: float, tel: Telemetry) -> tuple[float, ...]:
        # param7 is AMSL on PX4: an ArduPilot-style "10" is "already higher than takeoff altitude".
        # On the ground the base is where the vehicle stands, not HOME_POSITION: PX4 takes its home
        # where it arms, and the take-off goes out before the new home is heard. The last flight's home
        # lies up to 0.7 m off the ground after a few flights (SIH baro drift, measured), so a drone
        # flew to 9.3 m above its new home and never reached 95 % of a 10 m take-off.
        base = tel.alt_amsl if tel.landed else base_altitude_amsl(tel)
        return (0, 0, 0, math.nan, tel.lat, tel.lon, base + alt_rel_m)

    def reposition_params(
        self, lat: float, lon: float, alt_amsl: float, speed_mps: float | None
    ) -> tuple[float, ...]:
        # param1 ground speed (-1 = MPC_XY_CRUISE): carried here, a DO_CHANGE_SPEED can reach a
        # drone still in AUTO.TAKEOFF and be lost. param2 CHANGE_MODE (0 gives UNSUPPORTED).
        speed = speed_mps if speed_mps is not None and speed_mps > 0 else -1.0
        return (speed, mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, math.nan, lat, lon, alt_amsl)

    def pause_params(self) -> tuple[float, ...]:
        # PX4's pause (navigator: "All three set to NaN - pause vehicle", as QGroundControl's Pause):
        # a multicopter brakes with its own jerk and acceleration limits and holds at the point where
        # it comes to rest. A reposition to the current point overshoots and flies back, and one to
        # a stopping point we estimate creeps the last metres at about 1 m/s (both measured).
        return (-1.0, mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, math.nan, math.nan, math.nan, math.nan)

    def return_alt_value(self, alt_rel_m: float) -> float:
        return float(alt_rel_m)  # RTL_RETURN_ALT is in metres above home

    def default_return_alt(self, tel: Telemetry) -> float | None:
        # PX4 would climb every drone to RTL_RETURN_ALT (30 m stock): return at the current height,
        # which keeps the altitude layers of a mission apart (homes may be metres apart).
        return round(max(tel.alt_rel, RETURN_ALT_FLOOR_M), 1)

    def fence_params(self, fence: FenceSpec, has_items: bool) -> list[tuple[str, float]]:
        params: list[tuple[str, float]] = [("GF_ACTION", self.fence_action(fence.breach_action))]
        if fence.max_alt_m is not None:
            params.append(("GF_MAX_VER_DIST", fence.max_alt_m))
        return params

    def decode_param(self, raw: float, param_type: int) -> float:
        if param_type in _INT_TYPES:
            return float(struct.unpack("<i", struct.pack("<f", raw))[0])
        return float(raw)

    def encode_param(self, value: float, param_type: int) -> float:
        if param_type in _INT_TYPES:
            return float(struct.unpack("<f", struct.pack("<i", round(value)))[0])
        return float(value)

    def shown_mode(self, mode: str, leg_active: bool) -> str:
        return "GUIDED" if mode == "LOITER" and leg_active else mode

    def follows(self, previous: str, mode: str) -> bool:
        # A take-off, a mission, a return or a landing ends in Hold by itself; a return lands.
        return (mode == "LOITER" and previous in ("TAKEOFF", "AUTO", "RTL", "LAND", "READY")) or (
            previous == "RTL" and mode == "LAND"
        )
