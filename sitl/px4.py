"""The PX4 personality: the simulated copter as PX4 v1.16 (SITL, SIH) shows itself to a ground station.

Flight (physics, position controller, landing, fence geometry, battery physics) is the engine of
sitl/vehicle/; this module changes what the ground station sees and what it may do, as observed on
the real PX4 with pymavlink (/work/shared/notes/px4-behaviour.md and the probes in docs/simulator.md):

* HEARTBEAT autopilot MAV_AUTOPILOT_PX4, ``custom_mode = main << 16 | sub << 24``; DO_SET_MODE takes
  main in param2, sub in param3; no GUIDED (an ArduCopter 4 is main AUTO, sub 0: AUTO.MISSION).
* Hold (AUTO.LOITER) flies DO_REPOSITION targets; the take-off switches to AUTO.TAKEOFF itself,
  climbs to an AMSL altitude and goes to Hold; auto-disarm COM_DISARM_PRFLT / COM_DISARM_LAND.
* PX4 parameter names, integer parameters byte-wise in PARAM_VALUE and PARAM_SET.

Every PX4 mode runs on one engine mode (``_ENGINE_MODE``); ``px4_mode`` is what the heartbeat says.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping

from sitl.dialect import mavlink as mav
from sitl.mission import MISSION as MISSION_TYPE
from sitl.mission import MissionItem, MissionProtocol
from sitl.params import INT32, ParamStore
from sitl.physics import latlon_to_local
from sitl.px4_params import ENGINE_FIXED, PX4_DEFAULTS, TO_ENGINE, int_to_wire, wire_to_int
from sitl.vehicle import (
    ACRO,
    ALT_HOLD,
    AUTO,
    BRAKE,
    GUIDED,
    LAND,
    LOITER,
    POSHOLD,
    RTL,
    RTL_CLIMB,
    SEV_CRITICAL,
    SEV_INFO,
    STABILIZE,
    Failure,
    SimVehicle,
    Telemetry,
    param_name,
)

# PX4 (main, sub) modes (px4_custom_mode.h)
MANUAL = (1, 0)
ALTCTL = (2, 0)
POSCTL = (3, 0)
TAKEOFF = (4, 2)
HOLD = (4, 3)
MISSION = (4, 4)
RETURN = (4, 5)
LAND_MODE = (4, 6)
ACRO_MODE = (5, 0)
OFFBOARD = (6, 0)
STABILIZED = (7, 0)

PX4_MODE_NAMES: dict[tuple[int, int], str] = {
    MANUAL: "MANUAL",
    ALTCTL: "ALTCTL",
    POSCTL: "POSCTL",
    TAKEOFF: "AUTO.TAKEOFF",
    HOLD: "AUTO.LOITER",
    MISSION: "AUTO.MISSION",
    RETURN: "AUTO.RTL",
    LAND_MODE: "AUTO.LAND",
    ACRO_MODE: "ACRO",
    OFFBOARD: "OFFBOARD",
    STABILIZED: "STABILIZED",
}
# The words PX4 uses in "Switching to <mode> is currently not available".
_MANUAL_WORDS = {1: "Manual", 2: "Altitude", 3: "Position", 5: "Acro", 7: "Stabilized"}
# Engine mode -> the PX4 mode shown (failsafes and the fence switch engine modes).
_FROM_ENGINE: dict[int, tuple[int, int]] = {
    LOITER: HOLD,
    BRAKE: HOLD,
    POSHOLD: POSCTL,
    GUIDED: OFFBOARD,
    AUTO: MISSION,
    RTL: RETURN,
    LAND: LAND_MODE,
    ALT_HOLD: ALTCTL,
    STABILIZE: MANUAL,
    ACRO: ACRO_MODE,
}
_INT32_MAX = 0x7FFFFFFF  # COMMAND_INT's "no value" for x/y
ARMING_DENIED = "Arming denied: Resolve system health failures first"
REACHED_REPEAT_S = 10.0  # PX4 repeats MISSION_ITEM_REACHED about once a second for about 10 s

ACCEPTED = mav.MAV_RESULT_ACCEPTED
REJECTED = mav.MAV_RESULT_TEMPORARILY_REJECTED
UNSUPPORTED = mav.MAV_RESULT_UNSUPPORTED
FAILED = mav.MAV_RESULT_FAILED

# What PX4's onboard/API link streams unasked (the real one sends more, and faster: ATTITUDE ~100 Hz,
# positions ~30 Hz; these rates keep the simulator cheap).
PX4_DEFAULT_STREAMS: dict[int, float] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 0.2,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 0.2,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 0.1,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 0.1,
    mav.MAVLINK_MSG_ID_ATTITUDE: 0.1,
    mav.MAVLINK_MSG_ID_VFR_HUD: 0.1,
    mav.MAVLINK_MSG_ID_GPS_RAW_INT: 0.2,
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: 2.0,
    mav.MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
    mav.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mav.MAVLINK_MSG_ID_HOME_POSITION: 2.0,
}


class Px4MissionProtocol(MissionProtocol):
    """PX4's upload quirks: MISSION_REQUEST until the GCS has answered with MISSION_ITEM_INT once, and a
    return-to-launch item outside MAV_FRAME_MISSION refused (MAV_MISSION_UNSUPPORTED, upload ended).

    PX4 keeps no home at seq 0: its item 0 is the first mission item. The engine's stored list keeps
    ArduPilot's layout (a home placeholder at 0, added by :meth:`Px4Vehicle.mission_stored`), so
    MISSION counts and downloads here are shifted by one.
    """

    int_items_seen = False

    def count(self, mission_type: int) -> int:
        """PX4's count: no home item in a MISSION download."""
        if mission_type == MISSION_TYPE:
            return max(0, len(self.stores[MISSION_TYPE]) - 1)
        return super().count(mission_type)

    def download_item(self, mission_type: int, seq: int) -> MissionItem | None:
        """PX4's item ``seq`` (the engine's ``seq + 1``) of a MISSION download."""
        if mission_type != MISSION_TYPE:
            return super().download_item(mission_type, seq)
        items = self.stores[MISSION_TYPE]
        if not 0 <= seq < len(items) - 1:
            return None
        it = items[seq + 1]
        return MissionItem(
            seq, it.frame, it.command, it.current, it.autocontinue,
            it.param1, it.param2, it.param3, it.param4, it.x, it.y, it.z, it.mission_type,
        )  # fmt: skip

    def _request(self, seq: int, mission_type: int) -> None:
        self.legacy_request = not self.int_items_seen
        super()._request(seq, mission_type)

    def handle(self, msg: mav.MAVLink_message, now: float) -> bool:
        """As ArduPilot's, with PX4's item checks first."""
        t = msg.get_type()
        if t in ("MISSION_ITEM_INT", "MISSION_ITEM") and self.upload is not None:
            if t == "MISSION_ITEM_INT":
                self.int_items_seen = True
            if (
                msg.command == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH
                and msg.frame != mav.MAV_FRAME_MISSION
                and msg.seq == self.upload.next_seq
            ):
                mtype = self.upload.mission_type
                self.upload = None
                self._ack(mav.MAV_MISSION_UNSUPPORTED, mtype)  # PX4: "IGN MISSION_ITEM: Invalid item"
                return True
        return super().handle(msg, now)


class Px4Telemetry(Telemetry):
    """PX4's HEARTBEAT, AUTOPILOT_VERSION and MISSION_CURRENT numbering; the rest as the engine's."""

    def __init__(self, v: Px4Vehicle) -> None:
        super().__init__(v)
        self.px4 = v

    def msg_heartbeat(self) -> mav.MAVLink_message:
        """HEARTBEAT: quadrotor, MAV_AUTOPILOT_PX4, PX4 custom mode and base mode flags."""
        v = self.px4
        main = v.px4_mode[0]
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if main in (1, 2, 3, 5, 7):
            base |= mav.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        if main not in (1, 5):
            base |= mav.MAV_MODE_FLAG_STABILIZE_ENABLED
        if main in (3, 4, 6):
            base |= mav.MAV_MODE_FLAG_GUIDED_ENABLED
        if main in (4, 6):
            base |= mav.MAV_MODE_FLAG_AUTO_ENABLED
        if v.armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        if v.booting:
            status = mav.MAV_STATE_UNINIT
        elif v.batt_failsafe or v.ekf_failsafe or v.gcs_failsafe:
            status = mav.MAV_STATE_CRITICAL
        else:
            status = mav.MAV_STATE_ACTIVE if v.armed else mav.MAV_STATE_STANDBY
        return mav.MAVLink_heartbeat_message(
            mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, base, v.wire_custom_mode(), status, 3
        )

    def msg_mission_current(self) -> mav.MAVLink_message:
        """MISSION_CURRENT in PX4's numbering (no home item)."""
        msg = super().msg_mission_current()
        msg.seq = max(0, msg.seq - 1)
        return msg

    # AUTOPILOT_VERSION of PX4 v1.16.0, byte-wise parameters advertised
    param_capability = mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    firmware = (1, 16, 0)


class Px4Vehicle(SimVehicle):
    """One simulated quadrotor with PX4's personality (see the module docstring)."""

    armable_modes = frozenset({LOITER, POSHOLD, ALT_HOLD, STABILIZE, ACRO, GUIDED, AUTO, BRAKE})

    def __init__(
        self,
        index: int,
        home: tuple[float, float, float],
        seed: int = 0,
        prearm_delay_s: float = 3.0,
        legacy_mission_request: bool = False,
        gps_boot_s: float | None = None,
        wind: tuple[float, float] = (0.0, 0.0),
        gust_mps: float = 0.0,
        params: Mapping[str, float] | None = None,
        lock: threading.RLock | None = None,
    ) -> None:
        super().__init__(
            index, home, seed, prearm_delay_s, legacy_mission_request, gps_boot_s, wind, gust_mps, None, lock
        )
        self.px4_params = ParamStore(defaults=PX4_DEFAULTS)
        self.px4_params.define("MAV_SYS_ID", self.sysid)
        for name, value in (params or {}).items():
            if name.upper() not in self.px4_params:
                raise ValueError(f"unknown PX4 parameter {name!r}")
            self.px4_params.set(name.upper(), float(value))
        self.px4_params.on_change = lambda _name, _value: self._sync_engine()
        self._sync_engine()
        self.mission = Px4MissionProtocol(
            self.sysid, self.send, self.auto.home_item, self.auto.can_clear, self.mission_stored, False
        )
        self.telemetry = Px4Telemetry(self)
        self.px4_mode = HOLD
        self.shown_only = False  # px4_mode was taken while disarmed but cannot run (nothing flies)
        self.mode = LOITER  # PX4 boots in Hold
        self.flew = False  # airborne since arming: decides COM_DISARM_LAND against COM_DISARM_PRFLT
        self.takeoff_pending: float | None = None  # AMSL target of a take-off sent while disarmed
        self.cruise: float | None = None  # DO_CHANGE_SPEED: the speed of repositions until a mode change
        self.last_setpoint_t = -math.inf  # last SET_POSITION_TARGET_* (PX4's offboard signal)
        self.pauses: list[float] = []  # ground speed at each pause (a reposition without position)
        self.reached: tuple[int, float, float] | None = None  # seq, first sent, next repeat
        self.sim_bat_pct = 100.0

    # ------------------------------------------------------------------ parameters
    def _sync_engine(self) -> None:
        """Translate the PX4 table into the engine's ArduCopter-named parameters."""
        get = self.px4_params.get
        for name, fn in TO_ENGINE.items():
            self._set_engine_param(name, fn(get))
        for name, value in ENGINE_FIXED.items():
            self._set_engine_param(name, value)

    def _set_engine_param(self, name: str, value: float) -> None:
        if name in self.params:
            self.params.set(name, value)
        else:
            self.params.define(name, value)

    def _send_param(self, name: str, index: int | None = None) -> None:
        p = self.px4_params
        value = p[name]
        wire = int_to_wire(round(value)) if p.ptype(name) == INT32 else value
        self.send(
            mav.MAVLink_param_value_message(
                name.encode(), wire, p.ptype(name), len(p), p.index(name) if index is None else index
            )
        )

    def _param_message(self, msg: mav.MAVLink_message) -> None:
        p = self.px4_params
        t = msg.get_type()
        if t == "PARAM_REQUEST_LIST":
            for i, name in enumerate(p):
                self._send_param(name, i)
            return
        name = param_name(msg.param_id)
        if t == "PARAM_REQUEST_READ":
            if msg.param_index >= 0:
                name = p.name_at(msg.param_index) or ""
            if name in p:
                self._send_param(name)
            return
        # PARAM_SET: unknown names and a type other than the parameter's are ignored (PX4 logs
        # "unknown param" / "param types mismatch" and answers nothing); INT32 values are byte-wise.
        if name not in p or int(msg.param_type) != p.ptype(name):
            return
        value = float(wire_to_int(msg.param_value)) if p.ptype(name) == INT32 else float(msg.param_value)
        if p.set(name, value):
            self._send_param(name)

    # ------------------------------------------------------------------ modes
    def mode_name(self) -> str:
        """PX4's name of the mode shown (AUTO.LOITER for Hold...)."""
        return PX4_MODE_NAMES.get(self.px4_mode, str(self.px4_mode))

    def wire_custom_mode(self) -> int:
        """``main << 16 | sub << 24``."""
        return (self.px4_mode[0] << 16) | (self.px4_mode[1] << 24)

    def default_streams(self) -> dict[int, float]:
        """PX4's API link streams telemetry unasked."""
        return PX4_DEFAULT_STREAMS

    def set_mode(self, mode: int, reason: str = "") -> bool:
        """Engine mode change (failsafes, fence); the shown PX4 mode follows, the cruise speed resets."""
        if not super().set_mode(mode, reason):
            return False
        self.px4_mode = _FROM_ENGINE.get(mode, HOLD)
        self.shown_only = False
        self.cruise = None
        self.takeoff_pending = None
        return True

    def _hold(self) -> None:
        if self.px4_mode != HOLD:
            self.set_mode(LOITER)

    def set_px4_mode(self, main: int, sub: int) -> tuple[int, list[str]]:
        """DO_SET_MODE / SET_MODE as PX4 v1.16 answers them (main, sub)."""
        if main == 4:
            sub = sub or MISSION[1]  # AUTO with sub 0 is Mission: an ArduCopter "GUIDED" lands here
            if (main, sub) not in PX4_MODE_NAMES:
                return REJECTED, ["Unsupported auto mode"]
        elif main not in _MANUAL_WORDS and main != OFFBOARD[0]:
            return ACCEPTED, []  # unknown main modes (an ArduCopter LAND, 9...): nothing happens
        wanted = (main, sub if main == 4 else 0)
        if wanted == self.px4_mode:
            return ACCEPTED, []  # Hold while holding (or flying a reposition) changes nothing
        if wanted == TAKEOFF:
            return self._takeoff(math.nan)
        if wanted == HOLD:
            self.set_mode(LOITER)
            return ACCEPTED, []
        refused = self._unavailable(wanted)
        if refused is not None:
            if not self.armed:
                # PX4 always takes a mode while disarmed and shows it; nothing flies, arming is refused
                if self.mode != LOITER:
                    self.set_mode(LOITER)
                self.px4_mode, self.shown_only = wanted, True
                return ACCEPTED, []
            return ACCEPTED, [refused]  # ACCEPTED, then refused: the heartbeat keeps the mode it had
        if wanted == MISSION:
            self._start_mission()
        elif wanted == OFFBOARD:
            self.set_mode(GUIDED)
        elif wanted == RETURN:
            self.set_mode(RTL)
        elif wanted == LAND_MODE:
            self.set_mode(LAND)
        return ACCEPTED, []

    def _unavailable(self, wanted: tuple[int, int]) -> str | None:
        """PX4's refusal of a mode it cannot run now, or None."""
        if wanted[0] in _MANUAL_WORDS:  # COM_RC_IN_MODE: no stick input here, never available
            return f"Switching to {_MANUAL_WORDS[wanted[0]]} is currently not available"
        if wanted == OFFBOARD and self.t - self.last_setpoint_t > self.px4_params["COM_OF_LOSS_T"]:
            return "Switching to Offboard is currently not available"
        if wanted == MISSION and len(self.mission.mission_items()) <= 1:
            return "Switching to Mission is currently not available"
        if wanted in (RETURN, LAND_MODE) and (not self.armed or self.landed):
            return f"Switching to {'Return' if wanted == RETURN else 'Land'} is currently not available"
        return None

    def _start_mission(self) -> None:
        armed = self.armed
        self.armed = False  # PX4 needs no takeoff item check on the ground: enter Mission as disarmed
        ok = super().set_mode(AUTO)
        self.armed = armed
        if ok:
            self.px4_mode = MISSION
            self.cruise = None

    # ------------------------------------------------------------------ arming, take-off, landing
    def _arm_command(self, arm: bool, force: bool) -> tuple[int, list[str]]:
        if not arm:
            if not self.armed:
                return ACCEPTED, []
            if not self.landed and not force:
                return REJECTED, ["Disarming denied: not landed"]
            self.disarm("Disarmed by external command")
            return ACCEPTED, []
        if self.armed:
            return ACCEPTED, []
        if not force and self.arming.prearm_failure() is not None:
            return REJECTED, [ARMING_DENIED]
        if self.shown_only or self.px4_mode in (RETURN, LAND_MODE):
            return REJECTED, [ARMING_DENIED]
        ok, why = self.arm(force=True)
        if not ok:
            return REJECTED, [why]
        self.flew = False
        self.statustext(SEV_INFO, "Armed by external command")
        if self.takeoff_pending is not None:
            target, self.takeoff_pending = self.takeoff_pending, None
            self._climb_to(target)
        return ACCEPTED, []

    def _takeoff(self, alt_amsl: float) -> tuple[int, list[str]]:
        """NAV_TAKEOFF: param7 AMSL (NaN: home + MIS_TAKEOFF_ALT); switches to AUTO.TAKEOFF itself."""
        if self.booting:
            return REJECTED, []
        target = self.home[2] + self.px4_params["MIS_TAKEOFF_ALT"] if math.isnan(alt_amsl) else alt_amsl
        here = self.origin[2] - self.belief()[2]
        if target <= here + self.px4_params["NAV_MC_ALT_RAD"]:
            self._hold()
            return ACCEPTED, ["Already higher than takeoff altitude"]
        self.set_mode(LOITER)
        self.px4_mode = TAKEOFF
        if self.armed:
            self._climb_to(target)
        else:
            self.takeoff_pending = target  # arming climbs at once
        return ACCEPTED, []

    def _climb_to(self, target_amsl: float) -> None:
        b = self.belief()
        self.takeoff_alt = target_amsl - self.origin[2]
        self.target = (b[0], b[1], -self.takeoff_alt)
        self.landed = False
        self.leg = None
        self.px4_mode = TAKEOFF
        self.speed_up_override = self.px4_params["MPC_TKO_SPEED"]

    def disarm(self, reason: str = "") -> None:
        super().disarm("")
        if reason:
            self.statustext(SEV_INFO, reason)
        self.flew = False
        self.takeoff_pending = None
        self.reached = None
        super().set_mode(LOITER)  # PX4 shows Hold on the ground after a flight
        self.px4_mode = HOLD
        self.cruise = None

    def control(self, dt: float) -> None:
        """Auto-disarm as PX4 (COM_DISARM_LAND after a flight, COM_DISARM_PRFLT before), then the engine."""
        p = self.px4_params
        if self.armed and self.landed and self.takeoff_alt is None:
            if self.flew:
                if self.t - self.landed_since >= p["COM_DISARM_LAND"]:
                    auto = self.auto
                    if self.mode == AUTO and not auto.complete and (auto.landing or auto.returning):
                        auto.advance()
                    self.disarm("Disarmed by landing")
                return
            if p["COM_DISARM_PRFLT"] > 0 and self.t - self.arm_time >= p["COM_DISARM_PRFLT"]:
                self.disarm("Disarmed by auto preflight disarming")
                return
        if self.armed and not self.landed:
            self.flew = True
        super().control(dt)
        if self.px4_mode == TAKEOFF and self.takeoff_alt is not None:
            if -self.belief()[2] >= self.takeoff_alt - p["NAV_MC_ALT_RAD"]:
                self.px4_mode = HOLD  # PX4 calls the take-off done NAV_MC_ALT_RAD early; Hold climbs on
                self.cruise = self.speed_xy_override = None
        elif self.px4_mode == TAKEOFF and self.takeoff_alt is None and not self.landed:
            self.px4_mode = HOLD

    def start_rtl(self) -> None:
        """PX4's return altitude: RTL_RETURN_ALT, lowered near home by the RTL_CONE_ANG cone."""
        p = self.px4_params
        b = self.belief()
        hn, he, hd = self.home_ned
        dist = math.hypot(b[0] - hn, b[1] - he)
        acc = p["NAV_ACC_RAD"]
        ret = p["RTL_RETURN_ALT"]
        if dist <= acc:
            ret = 2.0 * dist
        else:
            cone = p["RTL_CONE_ANG"]
            if cone > 0 and dist <= p["RTL_MIN_DIST"]:
                ret = min(dist / math.tan(math.radians(min(89.0, max(1.0, cone)))), ret)
            ret = max(ret, 2.0 * acc)
        ret = max(ret, -(b[2] - hd))  # never descends to return
        self.guidance.rtl_alt = ret - hd
        self.guidance.rtl_state = RTL_CLIMB
        self.target = (b[0], b[1], -self.guidance.rtl_alt)
        self.leg = None

    # ------------------------------------------------------------------ simulation step
    def step(self, dt: float) -> None:
        """The engine step, then PX4's SITL battery (SIM_BAT_DRAIN), offboard loss and repeated reaches."""
        super().step(dt)
        p = self.px4_params
        if p["SIM_BAT_ENABLE"] and p["SIM_BAT_DRAIN"] > 0:
            if self.armed:
                floor = min(p["SIM_BAT_MIN_PCT"], self.sim_bat_pct)
                self.sim_bat_pct = max(floor, self.sim_bat_pct - 100.0 * dt / p["SIM_BAT_DRAIN"])
            else:
                self.sim_bat_pct = 100.0
            self.battery.set_pct(self.sim_bat_pct)
        if self.px4_mode == OFFBOARD and self.t - self.last_setpoint_t > p["COM_OF_LOSS_T"]:
            self.statustext(SEV_CRITICAL, "Failsafe activated")
            self.set_mode(POSHOLD)
        if self.reached is not None and self.t >= self.reached[2]:
            seq, first, _next = self.reached
            if self.t - first > REACHED_REPEAT_S:
                self.reached = None
            else:
                self.send(mav.MAVLink_mission_item_reached_message(seq))
                self.reached = (seq, first, self.t + 1.0)

    def gnss_failsafe_delay(self) -> float | None:
        """EKF2 dead-reckons for EKF2_NOAID_TOUT (us) without GPS, then declares no position."""
        return self.px4_params["EKF2_NOAID_TOUT"] / 1e6

    def gnss_failsafe(self) -> None:
        """PX4's mode fallback when the mode's position requirement fails (failsafe framework).

        Position (POSCTL) falls back to Altitude; the position modes (Hold, Mission, Return, Offboard,
        Takeoff) to Land, which needs a local position too, so to Descend, shown as AUTO.LAND.
        The event says "Failsafe activated: Autopilot disengaged, switching to Descend"; the
        STATUSTEXT a MAVLink ground station sees is "Failsafe activated".
        """
        if self.px4_mode in (MANUAL, ALTCTL, STABILIZED, ACRO_MODE, LAND_MODE):
            return
        self.set_mode(ALT_HOLD if self.px4_mode == POSCTL else LAND)
        self.statustext(SEV_CRITICAL, "Failsafe activated")

    def gnss_failsafe_cleared(self) -> None:
        """PX4 stays in Descend until the pilot or a ground station selects another mode."""

    def set_battery(self, pct: float) -> None:
        """Set the charge; PX4's SITL drain goes on from there."""
        with self.lock:
            self.sim_bat_pct = pct
            self.battery.set_pct(pct)

    def _apply_failure(self, f: Failure) -> None:
        super()._apply_failure(f)
        if f.kind == "battery":
            self.sim_bat_pct = self.battery.remaining_pct

    # ------------------------------------------------------------------ missions (PX4 seq = engine seq - 1)
    def item_reached(self, seq: int) -> None:
        super().item_reached(seq - 1)
        self.reached = (seq - 1, self.t, self.t + 1.0)

    def mission_stored(self, mission_type: int) -> None:
        if mission_type == MISSION_TYPE and self.mission.stores[MISSION_TYPE]:
            self.mission.stores[MISSION_TYPE].insert(0, self.auto.home_item())
        super().mission_stored(mission_type)

    def set_mission_current(self, seq: int) -> bool:
        return super().set_mission_current(seq + 1)

    # ------------------------------------------------------------------ messages and commands
    def handle(self, msg: mav.MAVLink_message, wall_now: float) -> None:
        """PX4's parameters, modes and offboard setpoints; the rest as the engine."""
        t = msg.get_type()
        if t in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET", "SET_MODE") or t.startswith(
            "SET_POSITION_TARGET"
        ):
            tgt = getattr(msg, "target_system", 0)
            if tgt not in (0, self.sysid):
                return
            if t == "SET_MODE":
                cm = int(msg.custom_mode)
                self.set_px4_mode((cm >> 16) & 0xFF, (cm >> 24) & 0xFF)
                return
            if t.startswith("SET_POSITION_TARGET"):
                self.last_setpoint_t = self.t  # PX4 ignores them outside OFFBOARD (engine: GUIDED only)
            else:
                self._param_message(msg)
                return
        super().handle(msg, wall_now)

    def command_result(self, msg: mav.MAVLink_message, is_int: bool) -> tuple[int | None, list[str]]:
        """PX4's answers to the commands where it differs from ArduCopter; the rest as the engine."""
        cmd = msg.command
        p1, p2 = msg.param1, msg.param2
        if cmd == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            return self._arm_command(p1 >= 0.5, round(p2) == 21196)
        if cmd == mav.MAV_CMD_DO_SET_MODE:
            if not int(p1) & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return ACCEPTED, []
            return self.set_px4_mode(int(p2), int(msg.param3))
        if cmd == mav.MAV_CMD_NAV_TAKEOFF:
            return self._takeoff(msg.z if is_int else msg.param7)
        if cmd == mav.MAV_CMD_NAV_LAND:
            return self.set_px4_mode(*LAND_MODE)
        if cmd == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self.set_px4_mode(*RETURN)
        if cmd == mav.MAV_CMD_DO_REPOSITION:
            return self._reposition(msg, is_int)
        if cmd == mav.MAV_CMD_DO_CHANGE_SPEED:
            return self._px4_change_speed(int(p1), p2)
        if cmd == mav.MAV_CMD_SET_MESSAGE_INTERVAL and int(p1) == mav.MAVLINK_MSG_ID_MISSION_CURRENT:
            return FAILED, []  # PX4 streams MISSION_CURRENT itself and refuses to change it
        if cmd == mav.MAV_CMD_MISSION_START:
            if len(self.mission.mission_items()) <= 1:
                return mav.MAV_RESULT_DENIED, []
            self._start_mission()
            if int(p1) > 0:
                self.set_mission_current(int(p1))
            return ACCEPTED, []
        if cmd in (mav.MAV_CMD_CONDITION_YAW, mav.MAV_CMD_DO_PAUSE_CONTINUE):
            return UNSUPPORTED, []
        return super().command_result(msg, is_int)

    def command(self, msg: mav.MAVLink_message, is_int: bool) -> None:
        """As the engine, but PX4's refusals are warnings, not ArduPilot's PreArm criticals."""
        if msg.command == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            result, texts = self.command_result(msg, is_int)
            for text in texts:
                self.statustext(SEV_CRITICAL, text)
            self.send(
                mav.MAVLink_command_ack_message(
                    msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
                )
            )
            return
        super().command(msg, is_int)

    def _px4_change_speed(self, speed_type: int, speed: float) -> tuple[int, list[str]]:
        """DO_CHANGE_SPEED: always ACCEPTED; the speed holds for repositions until the mode changes."""
        if speed_type in (0, 1):
            self.cruise = speed if speed > 0 else None
            self.speed_xy_override = self.cruise
        elif speed_type == 2 and speed > 0:
            self.speed_up_override = speed
        elif speed_type == 3 and speed > 0:
            self.speed_dn_override = speed
        return ACCEPTED, []

    def _stopping_point(self, n: float, e: float) -> tuple[float, float]:
        """Where braking at the effective horizontal deceleration (half MPC_ACC_HOR) ends."""
        vn, ve = self.kin.vn, self.kin.ve
        decel = max(self.px4_params["MPC_ACC_HOR"] * 0.5, 0.1)
        reach = math.hypot(vn, ve) / (2.0 * decel)  # v^2 / 2a along the unit velocity: v / 2a per m/s
        return n + vn * reach, e + ve * reach

    def _reposition(self, msg: mav.MAVLink_message, is_int: bool) -> tuple[int, list[str]]:
        """DO_REPOSITION: param2 bit 0 required (else UNSUPPORTED, though Hold still takes the target);
        z always AMSL whatever the frame; flown in Hold, only while armed and airborne."""
        flags = int(msg.param2) if math.isfinite(msg.param2) else 0
        result = UNSUPPORTED if (flags & 1) == 0 or flags & ~1 else ACCEPTED
        if result == ACCEPTED:
            self._hold()
        if self.px4_mode != HOLD or not self.armed or self.landed:
            return result, []
        b = self.belief()
        n, e, d = b[0], b[1], self.target[2]
        if is_int:
            lat = None if msg.x == _INT32_MAX else msg.x / 1e7
            lon = None if msg.y == _INT32_MAX else msg.y / 1e7
            alt = msg.z
        else:
            lat = msg.param5 if math.isfinite(msg.param5) else None
            lon = msg.param6 if math.isfinite(msg.param6) else None
            alt = msg.param7
        if lat is not None and lon is not None:
            n, e = latlon_to_local(self.origin[0], self.origin[1], lat, lon)
        else:  # no position: PX4's pause (navigator: brake, then hold where the vehicle comes to rest)
            n, e = self._stopping_point(n, e)
            self.pauses.append(math.hypot(*self.ground_velocity()))
        if math.isfinite(alt):
            d = -(alt - self.origin[2])
        self.guidance.goto(n, e, d)
        vmax = self.px4_params["MPC_XY_VEL_MAX"]
        self.speed_xy_override = min(msg.param1, vmax) if msg.param1 > 0 else self.cruise
        return result, []
