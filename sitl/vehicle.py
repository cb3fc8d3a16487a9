"""One simulated ArduCopter: flight modes, arming, commands, mission execution, fence and failsafes.

The vehicle is driven by the fleet loop: :meth:`SimVehicle.step` advances it by one fixed physics step
(sim time), :meth:`SimVehicle.handle` processes one decoded MAVLink message from its link. Everything
it says goes through the :class:`LinkAPI` the endpoint attaches, so this module never touches sockets.
Public methods meant for other threads (``state``, ``inject_*``, ``set_*``) take the fleet lock.
"""

from __future__ import annotations

import math
import random
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from operator import methodcaller
from typing import Protocol

from sitl.dialect import mavlink as mav
from sitl.mission import (
    FENCE,
    GLOBAL_FRAMES_AMSL,
    MISSION,
    FenceZone,
    MissionItem,
    MissionProtocol,
    build_fence,
)
from sitl.params import ParamStore
from sitl.physics import (
    Battery,
    GpsError,
    Kinematics,
    Limits,
    PathWobble,
    PowerModel,
    Wind,
    latlon_to_local,
    local_to_latlon,
)

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
GPS_FS_S = 5.0  # dead reckoning tolerated before the EKF failsafe fires
VEL_TIMEOUT_S = 3.0  # GUIDED velocity targets expire like ArduCopter's

# RTL sub-states
RTL_CLIMB, RTL_RETURN, RTL_LOITER, RTL_DESCEND, RTL_FINAL = range(5)

SEV_CRITICAL = mav.MAV_SEVERITY_CRITICAL
SEV_WARNING = mav.MAV_SEVERITY_WARNING
SEV_NOTICE = mav.MAV_SEVERITY_NOTICE
SEV_INFO = mav.MAV_SEVERITY_INFO

_NAV_NAMES = {
    mav.MAV_CMD_NAV_WAYPOINT: "WP",
    mav.MAV_CMD_NAV_TAKEOFF: "Takeoff",
    mav.MAV_CMD_NAV_LAND: "Land",
    mav.MAV_CMD_NAV_RETURN_TO_LAUNCH: "RTL",
    mav.MAV_CMD_NAV_LOITER_UNLIM: "LoitUnlim",
    mav.MAV_CMD_NAV_LOITER_TIME: "LoitTime",
    mav.MAV_CMD_DO_CHANGE_SPEED: "ChangeSpeed",
}
_NAV_CMDS = {
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


class LinkAPI(Protocol):
    """What a vehicle needs from its endpoint."""

    def send(self, msg: mav.MAVLink_message) -> None:
        """Queue one message for the connected client (dropped when none or the link is down)."""

    def set_message_interval(self, msgid: int, interval_s: float | None) -> None:
        """Stream ``msgid`` every ``interval_s`` sim seconds; None stops it."""


class _NullLink:
    def send(self, msg: mav.MAVLink_message) -> None:
        pass

    def set_message_interval(self, msgid: int, interval_s: float | None) -> None:
        pass


@dataclass(slots=True, frozen=True)
class VehicleState:
    """Snapshot of a vehicle for Python callers. ``lat``/``lon``/``alt_*`` are ground truth; ``est_*`` is
    what the vehicle reports over MAVLink (GPS error, path wobble and dead reckoning included)."""

    sysid: int
    sim_time: float
    lat: float
    lon: float
    alt_rel: float
    alt_amsl: float
    est_lat: float
    est_lon: float
    est_alt_rel: float
    vn: float
    ve: float
    vd: float
    groundspeed: float
    heading_deg: float
    armed: bool
    mode: str
    custom_mode: int
    landed: bool
    battery_pct: float
    voltage_v: float
    current_a: float
    gps_fix: int
    home_lat: float
    home_lon: float
    home_alt_amsl: float
    mission_current: int
    mission_count: int
    link_down: bool
    fence_breached: bool
    energy_used_j: float
    distance_flown_m: float
    max_path_error_m: float


@dataclass(slots=True)
class Failure:
    """A scheduled failure: ``kind`` in link_drop, gps_loss, battery, wind; ``at`` sim seconds."""

    at: float
    kind: str
    duration: float = 0.0
    value: tuple[float, ...] = ()


class SimVehicle:
    """ArduCopter behaviour toward a ground station for one simulated quadrotor.

    Other autopilots' personalities (sitl/px4.py) subclass it and keep this engine for flight; the
    hooks they override are the class attributes below, :meth:`mode_name`, :meth:`wire_custom_mode`
    and :meth:`default_streams`.
    """

    armable_modes: frozenset[int] = frozenset(ARMABLE_MODES)

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
        self.index = index
        self.sysid = index + 1
        self.lock = lock if lock is not None else threading.RLock()
        self.rng = random.Random(seed * 1_000_003 + index * 7919 + 17)
        self.origin = home  # EKF origin: where the vehicle boots (ground level of the flat world)
        self.home = home
        self.prearm_delay_s = prearm_delay_s
        # ArduCopter reports GPS fix 0 and lat/lon 0,0 for ~11-13 s after boot, with no home:
        # nothing may be computed from "where the vehicle is" before that. Default: the fix comes
        # when the pre-arm checks would pass.
        self.gps_boot_s = prearm_delay_s if gps_boot_s is None else gps_boot_s
        self.params = ParamStore()
        self.params.define("SYSID_THISMAV", self.sysid)
        for k, v in (params or {}).items():
            if k.upper() in self.params:
                self.params.set(k.upper(), float(v))
            else:
                self.params.define(k, float(v))
        self.params.on_change = self._param_changed
        self.kin = Kinematics()
        self.wind = Wind(self.rng, wind[0], wind[1], gust_mps)
        self.wind_n = wind[0]
        self.wind_e = wind[1]
        self.gps = GpsError(self.rng, 0.3, 0.1)
        self.wobble = PathWobble(self.rng.uniform(0, 2 * math.pi))
        self.power = PowerModel()
        self.battery = Battery(capacity_mah=self.params["BATT_CAPACITY"])
        self.link: LinkAPI = _NullLink()
        self.mission = MissionProtocol(
            self.sysid,
            self.send,
            self._home_item,
            self._can_clear,
            self._mission_stored,
            legacy_mission_request,
        )
        self.t = 0.0
        self.mode = STABILIZE
        self.armed = False
        self.landed = True
        self.landed_since = 0.0
        self.arm_time = 0.0
        self.takeoff_alt: float | None = None  # metres above origin while a takeoff climbs
        self.target = (0.0, 0.0, 0.0)  # position target (n, e, d) of the position modes
        self.vel_target: tuple[float, float, float] | None = None
        self.vel_target_t = 0.0
        self.speed_xy_override: float | None = None
        self.speed_up_override: float | None = None
        self.speed_dn_override: float | None = None
        # GUIDED runs its waypoint controller only after a position target; the first target
        # after takeoff or after entering GUIDED (re)starts it at WPNAV_SPEED (ArduCopter's
        # ModeGuided::pos_control_start), dropping any speed change sent before.
        self.guided_wp_active = False
        self.rtl_state = RTL_CLIMB
        self.rtl_alt = 15.0
        self.rtl_loiter_until = 0.0
        self.land_target: tuple[float, float] = (0.0, 0.0)
        self.heading = 0.0
        # sensor / estimate state
        self.gerr = (0.0, 0.0, 0.0)
        self.dr_n = 0.0
        self.dr_e = 0.0
        self.gps_lost_until = 0.0
        self.gps_lost_since: float | None = None
        self.gps_fix_lat = home[0]
        self.gps_fix_lon = home[1]
        self.link_down_until = 0.0
        self.last_gcs_heartbeat: float | None = None
        self.wob = (0.0, 0.0)
        self.gust = (0.0, 0.0)
        self.prearm_announced = False
        # mission execution
        self.mis_idx = 1
        self.mis_started = False
        self.mis_hold_until: float | None = None
        self.mis_reached = False
        self.mis_complete = False
        self.mis_rtl = False
        self.mis_land = False
        # fence
        self.fence_zones: list[FenceZone] = []
        self.breaches = 0
        self.breach_count = 0
        self.breach_time_ms = 0
        self.breach_type = 0
        self.next_fence_check = 0.0
        # failsafes
        self.batt_low_since: float | None = None
        self.batt_failsafe = False
        self.gcs_failsafe = False
        self.ekf_failsafe = False
        # statistics
        self.distance_flown_m = 0.0
        self.max_path_error_m = 0.0
        self.leg: tuple[float, float, float, float] | None = None  # start n,e -> end n,e (true frame)
        self._true_prev = (0.0, 0.0, 0.0)
        self.failures: list[Failure] = []
        self._lim_cache: Limits | None = None

    # ------------------------------------------------------------------ helpers
    def send(self, msg: mav.MAVLink_message) -> None:
        """Send to the attached link (which drops it when nobody listens or the link is down)."""
        self.link.send(msg)

    def statustext(self, severity: int, text: str) -> None:
        """STATUSTEXT to the GCS (ArduPilot sends the words operators see)."""
        self.send(mav.MAVLink_statustext_message(severity, text.encode()[:50], 0, 0))

    @property
    def link_down(self) -> bool:
        """True while an injected link drop lasts."""
        return self.t < self.link_down_until

    @property
    def gps_ok(self) -> bool:
        """True when GPS has a fix (booted, no injected loss, SIM_GPS_DISABLE off)."""
        return (
            self.t >= self.gps_lost_until
            and self.t >= self.gps_boot_s
            and self.params.get("SIM_GPS_DISABLE") == 0
        )

    @property
    def booting(self) -> bool:
        """True before the first GPS fix: no position, no home (GLOBAL_POSITION_INT zeros)."""
        return self.t < self.gps_boot_s

    @property
    def home_ned(self) -> tuple[float, float, float]:
        """Home in the local frame (d is down from the origin)."""
        n, e = latlon_to_local(self.origin[0], self.origin[1], self.home[0], self.home[1])
        return n, e, -(self.home[2] - self.origin[2])

    def belief(self) -> tuple[float, float, float]:
        """The position the autopilot believes (GPS error / dead reckoning, no wobble)."""
        k = self.kin
        return k.n + self.gerr[0] + self.dr_n, k.e + self.gerr[1] + self.dr_e, k.d + self.gerr[2]

    def est(self) -> tuple[float, float, float]:
        """The position the vehicle reports (belief plus the uncorrected path wobble)."""
        b = self.belief()
        return b[0] + self.wob[0], b[1] + self.wob[1], b[2]

    def alt_rel_est(self) -> float:
        """Reported altitude above home (m)."""
        return -self.est()[2] + self.origin[2] - self.home[2]

    def _limits(self) -> Limits:
        if self._lim_cache is None:
            p = self.params
            self._lim_cache = Limits(
                speed_xy=max(0.2, p["WPNAV_SPEED"] / 100.0),
                accel_xy=max(0.5, p["WPNAV_ACCEL"] / 100.0),
                speed_up=max(0.1, p["WPNAV_SPEED_UP"] / 100.0),
                speed_dn=max(0.1, p["WPNAV_SPEED_DN"] / 100.0),
                accel_z=max(0.5, p["WPNAV_ACCEL_Z"] / 100.0),
            )
        base = self._lim_cache
        overrides = (self.speed_xy_override, self.speed_up_override, self.speed_dn_override)
        no_override = all(o is None for o in overrides)
        if no_override:
            if self.mode == RTL and self.params["RTL_SPEED"] > 0:
                return Limits(
                    self.params["RTL_SPEED"] / 100.0,
                    base.accel_xy,
                    base.speed_up,
                    base.speed_dn,
                    base.accel_z,
                )
            return base
        return Limits(
            self.speed_xy_override if self.speed_xy_override is not None else base.speed_xy,
            base.accel_xy,
            self.speed_up_override if self.speed_up_override is not None else base.speed_up,
            self.speed_dn_override if self.speed_dn_override is not None else base.speed_dn,
            base.accel_z,
        )

    def _param_changed(self, name: str, value: float) -> None:
        if name.startswith("WPNAV_"):
            self._lim_cache = None
        elif name in ("SIM_WIND_SPD", "SIM_WIND_DIR"):
            spd, frm = self.params["SIM_WIND_SPD"], math.radians(self.params["SIM_WIND_DIR"])
            self._set_wind(-spd * math.cos(frm), -spd * math.sin(frm), update_params=False)
        elif name == "SIM_WIND_TURB":
            self.wind.set_gust(max(0.0, value))
        elif name == "BATT_CAPACITY" and value > 0:
            pct = self.battery.remaining_pct
            self.battery.capacity_mah = value
            self.battery.set_pct(pct)

    def _set_wind(self, north: float, east: float, update_params: bool = True) -> None:
        self.wind.north, self.wind.east = north, east
        if update_params:
            spd = math.hypot(north, east)
            frm = (math.degrees(math.atan2(-east, -north)) + 360.0) % 360.0 if spd > 0 else 0.0
            self.params.define("SIM_WIND_SPD", spd)
            self.params.define("SIM_WIND_DIR", frm)

    def _stopping_point(self, decel: float | None = None) -> tuple[float, float, float]:
        """Where the vehicle would stop from its current (believed) position and velocity."""
        b = self.belief()
        k = self.kin
        a = decel if decel is not None else self._limits().accel_xy
        sp = math.hypot(k.vn, k.ve)
        if sp > 1e-3:
            dist = sp * sp / (2.0 * a)
            n, e = b[0] + k.vn / sp * dist, b[1] + k.ve / sp * dist
        else:
            n, e = b[0], b[1]
        d = b[2] + (k.vd * abs(k.vd) / (2.0 * self._limits().accel_z))
        return n, e, min(d, -0.5) if not self.landed else b[2]

    def _set_leg(self, tn: float, te: float) -> None:
        """Start a straight leg (for the path-error statistic) from the true position to (tn, te)."""
        self.leg = (self._true_prev[0], self._true_prev[1], tn, te)

    def _goto(self, n: float, e: float, d: float) -> None:
        if self.mode == GUIDED and not self.guided_wp_active:
            self.guided_wp_active = True
            self.speed_xy_override = self.speed_up_override = self.speed_dn_override = None
        self.takeoff_alt = None  # a new destination ends a GUIDED takeoff, as in ArduCopter
        self.target = (n, e, d)
        self.vel_target = None
        self._set_leg(n, e)

    def _alt_to_d(self, frame: int, alt: float) -> float:
        """Altitude of a command/mission item in ``frame`` to local down."""
        if frame in GLOBAL_FRAMES_AMSL:
            return -(alt - self.origin[2])
        return -(alt + self.home[2] - self.origin[2])

    def mode_name(self) -> str:
        """The flight mode's name as this autopilot calls it (VehicleState.mode)."""
        return MODE_NAMES.get(self.mode, str(self.mode))

    def wire_custom_mode(self) -> int:
        """HEARTBEAT.custom_mode of the current mode."""
        return self.mode

    def default_streams(self) -> dict[int, float]:
        """Messages (id -> interval, sim s) a fresh link gets unasked: ArduPilot's HEARTBEAT + SYS_STATUS."""
        return DEFAULT_STREAMS

    # ------------------------------------------------------------------ Python API (other threads)
    @property
    def state(self) -> VehicleState:
        """A consistent snapshot (taken under the fleet lock)."""
        with self.lock:
            k = self.kin
            tn, te = self.kin.n + self.wob[0], self.kin.e + self.wob[1]
            lat, lon = local_to_latlon(self.origin[0], self.origin[1], tn, te)
            en, ee, ed = self.est()
            elat, elon = local_to_latlon(self.origin[0], self.origin[1], en, ee)
            alt_amsl = self.origin[2] - k.d
            gvn, gve = self.ground_velocity()
            return VehicleState(
                sysid=self.sysid,
                sim_time=self.t,
                lat=lat,
                lon=lon,
                alt_rel=alt_amsl - self.home[2],
                alt_amsl=alt_amsl,
                est_lat=elat,
                est_lon=elon,
                est_alt_rel=self.origin[2] - ed - self.home[2],
                vn=gvn,
                ve=gve,
                vd=k.vd,
                groundspeed=math.hypot(gvn, gve),
                heading_deg=math.degrees(self.heading) % 360.0,
                armed=self.armed,
                mode=self.mode_name(),
                custom_mode=self.wire_custom_mode(),
                landed=self.landed,
                battery_pct=self.battery.remaining_pct,
                voltage_v=self.battery.voltage_v,
                current_a=self.battery.current_a,
                gps_fix=3 if self.gps_ok else 0,
                home_lat=self.home[0],
                home_lon=self.home[1],
                home_alt_amsl=self.home[2],
                mission_current=self.mis_idx if self.mode == AUTO else -1,
                mission_count=len(self.mission.mission_items()),
                link_down=self.link_down,
                fence_breached=self.breaches != 0,
                energy_used_j=self.battery.energy_j,
                distance_flown_m=self.distance_flown_m,
                max_path_error_m=self.max_path_error_m,
            )

    @property
    def energy_used_j(self) -> float:
        """Electrical energy drawn from the battery since boot (J)."""
        with self.lock:
            return self.battery.energy_j

    def inject_link_drop(self, seconds: float) -> None:
        """Silence the link (nothing sent, input ignored) for ``seconds`` of sim time from now."""
        with self.lock:
            self.link_down_until = max(self.link_down_until, self.t + seconds)

    def inject_gps_loss(self, seconds: float) -> None:
        """No GPS fix for ``seconds`` of sim time: dead reckoning, EKF failsafe after 5 s airborne."""
        with self.lock:
            self.gps_lost_until = max(self.gps_lost_until, self.t + seconds)

    def set_battery(self, pct: float) -> None:
        """Set the remaining battery charge in percent."""
        with self.lock:
            self.battery.set_pct(pct)

    def set_wind(self, north: float, east: float) -> None:
        """Set the steady wind vector (m/s toward north/east); also reflected in SIM_WIND_SPD/DIR."""
        with self.lock:
            self._set_wind(north, east)

    def set_gust(self, sigma_mps: float) -> None:
        """Set the gust standard deviation (m/s)."""
        with self.lock:
            self.wind.set_gust(sigma_mps)
            self.params.define("SIM_WIND_TURB", sigma_mps)

    def schedule(self, failure: Failure) -> None:
        """Add a failure to apply at ``failure.at`` sim seconds."""
        with self.lock:
            self.failures.append(failure)
            self.failures.sort(key=lambda f: f.at)

    def ground_velocity(self) -> tuple[float, float]:
        """Ground velocity: commanded plus the wind the controller has not rejected."""
        k = self.kin
        if self.landed:
            return 0.0, 0.0
        if self.mode in (STABILIZE, ACRO, ALT_HOLD):
            return k.vn, k.ve
        return (
            k.vn + WIND_LEAK * self.wind.north + GUST_LEAK * self.gust[0],
            k.ve + WIND_LEAK * self.wind.east + GUST_LEAK * self.gust[1],
        )

    # ------------------------------------------------------------------ simulation step
    def step(self, dt: float) -> None:
        """Advance the vehicle by one physics step of ``dt`` sim seconds."""
        self.t += dt
        t = self.t
        while self.failures and self.failures[0].at <= t:
            self._apply_failure(self.failures.pop(0))
        if not self.prearm_announced and t >= max(self.prearm_delay_s, self.gps_boot_s):
            self.prearm_announced = True
            self.statustext(SEV_INFO, "EKF3 IMU0 is using GPS")
            if (home := self.msg_home_position()) is not None:
                self.send(home)
        wn, we = self.wind.step(dt)
        self.gust = (wn - self.wind.north, we - self.wind.east)
        # GPS / estimate
        if self.gps_ok:
            self.gerr = self.gps.step(dt)
            self.dr_n = self.dr_e = 0.0
            self.gps_lost_since = None
        else:
            if self.gps_lost_since is None:
                self.gps_lost_since = t
        self._control(dt)
        k = self.kin
        if self.landed:
            k.vn = k.ve = k.vd = 0.0
            k.an = k.ae = 0.0
        else:
            dn, de = self.ground_velocity()
            dn -= k.vn
            de -= k.ve
            k.integrate(dt, dn, de)
            if not self.gps_ok:
                self.dr_n -= dn * dt
                self.dr_e -= de * dt
            if k.d >= 0.0 and k.vd >= 0.0 and self.takeoff_alt is None:
                self._touchdown()
        gvn, gve = self.ground_velocity()
        if math.hypot(gvn, gve) > 0.5:
            want = math.atan2(gve, gvn)
            diff = (want - self.heading + math.pi) % (2 * math.pi) - math.pi
            max_turn = math.radians(90.0) * dt
            self.heading += max(-max_turn, min(max_turn, diff))
        self.wob = self.wobble.step(gvn, gve, dt) if not self.landed else (0.0, 0.0)
        if self.gps_ok:
            en, ee, _ = self.est()
            self.gps_fix_lat, self.gps_fix_lon = local_to_latlon(self.origin[0], self.origin[1], en, ee)
        # statistics on the true position
        tn, te, td = k.n + self.wob[0], k.e + self.wob[1], k.d
        pn, pe, pd = self._true_prev
        if not self.landed:
            self.distance_flown_m += math.sqrt((tn - pn) ** 2 + (te - pe) ** 2 + (td - pd) ** 2)
            if self.leg is not None and math.hypot(gvn, gve) > 0.5:
                self._path_error(tn, te)
        self._true_prev = (tn, te, td)
        # battery
        v_air = math.hypot(gvn - wn, gve - we)
        self.battery.draw(self.power.power_w(not self.landed, self.armed, v_air, -k.vd), dt)
        self._failsafes()
        if t >= self.next_fence_check:
            self.next_fence_check = t + 0.1
            self._fence_check()

    def _path_error(self, tn: float, te: float) -> None:
        assert self.leg is not None
        sn, se, en, ee = self.leg
        dn, de = en - sn, ee - se
        length2 = dn * dn + de * de
        if length2 < 1e-6:
            return
        u = max(0.0, min(1.0, ((tn - sn) * dn + (te - se) * de) / length2))
        err = math.hypot(tn - (sn + u * dn), te - (se + u * de))
        if err > self.max_path_error_m:
            self.max_path_error_m = err

    def _apply_failure(self, f: Failure) -> None:
        if f.kind == "link_drop":
            self.link_down_until = max(self.link_down_until, f.at + f.duration)
        elif f.kind == "gps_loss":
            self.gps_lost_until = max(self.gps_lost_until, f.at + f.duration)
        elif f.kind == "battery":
            self.battery.set_pct(f.value[0])
        elif f.kind == "wind":
            self._set_wind(f.value[0], f.value[1])

    def _touchdown(self) -> None:
        k = self.kin
        k.d = 0.0
        k.vn = k.ve = k.vd = 0.0
        self.landed = True
        self.landed_since = self.t
        self.leg = None
        self.vel_target = None

    # ------------------------------------------------------------------ modes
    def _control(self, dt: float) -> None:
        """Run the current flight mode's controller for one step."""
        if not self.armed:
            if not self.landed:  # motors stopped in the air (forced disarm): fall
                self.kin.vn *= 0.98
                self.kin.ve *= 0.98
                self.kin.vd = min(self.kin.vd + 9.8 * dt, 15.0)
            return
        if self.landed and self.takeoff_alt is None:
            if self.mode in (LAND, RTL) or (self.mode == AUTO and (self.mis_land or self.mis_rtl)):
                if self.t - self.landed_since >= LAND_DETECT_S:
                    if self.mode == AUTO and not self.mis_complete:
                        self._auto_advance()
                    self._disarm("Land complete")
                return
            if self.mode == AUTO and not self.mis_complete and self._auto_ground_start():
                self._auto_step(self._limits(), dt, self.belief())
                if self.takeoff_alt is not None:
                    return
            if self.t - max(self.arm_time, self.landed_since) >= self.params["DISARM_DELAY"] > 0:
                self._disarm("Auto disarm")
            return
        lim = self._limits()
        k = self.kin
        b = self.belief()
        if self.takeoff_alt is not None:
            self.landed = False
            tn, te, _ = self.target
            k.position_step(tn, te, -self.takeoff_alt, lim, dt, b[0], b[1], b[2])
            if -b[2] >= self.takeoff_alt - TAKEOFF_DONE_M:
                self.target = (tn, te, -self.takeoff_alt)
                self.takeoff_alt = None
            return
        m = self.mode
        if m == GUIDED:
            if self.vel_target is not None:
                if self.t - self.vel_target_t > VEL_TIMEOUT_S:
                    self.vel_target = None
                    self.target = self._stopping_point()
                else:
                    vn, ve, vd = self.vel_target
                    k.step_velocity(vn, ve, vd, lim, dt)
                    return
            tn, te, td = self.target
            k.position_step(tn, te, td, lim, dt, b[0], b[1], b[2])
        elif m in (LOITER, POSHOLD):
            tn, te, td = self.target
            k.position_step(tn, te, td, lim, dt, b[0], b[1], b[2])
        elif m == BRAKE:
            tn, te, td = self.target
            blim = Limits(lim.speed_xy * 4, BRAKE_DECEL, lim.speed_up, lim.speed_dn, lim.accel_z)
            k.position_step(tn, te, td, blim, dt, b[0], b[1], b[2])
        elif m == LAND:
            self._land_step(lim, dt, b)
        elif m == RTL:
            self._rtl_step(lim, dt, b)
        elif m == AUTO:
            self._auto_step(lim, dt, b)
        elif m == ALT_HOLD:
            # no RC: sticks centred, altitude held, no position hold -> drifts with the air mass
            k.step_velocity(self.wind.north + self.gust[0], self.wind.east + self.gust[1], 0.0, lim, dt)
        else:  # STABILIZE / ACRO with no RC: throttle low -> sinks at 2.5 m/s, drifts with the air mass
            k.step_velocity(self.wind.north + self.gust[0], self.wind.east + self.gust[1], 2.5, lim, dt)

    def _land_descent_speed(self, b: tuple[float, float, float]) -> float:
        alt = -b[2]
        if alt > self.params["LAND_ALT_LOW"] / 100.0:
            high = self.params["LAND_SPEED_HIGH"]
            return high / 100.0 if high > 0 else self._limits().speed_dn
        return max(0.1, self.params["LAND_SPEED"] / 100.0)

    def _land_step(self, lim: Limits, dt: float, b: tuple[float, float, float]) -> None:
        ln, le = self.land_target
        llim = Limits(lim.speed_xy, lim.accel_xy, lim.speed_up, self._land_descent_speed(b), lim.accel_z)
        self.kin.position_step(ln, le, 1000.0, llim, dt, b[0], b[1], b[2])

    def _start_rtl(self) -> None:
        b = self.belief()
        alt = -b[2]
        rtl_alt = self.params["RTL_ALT"] / 100.0
        target = max(rtl_alt, alt + self.params["RTL_CLIMB_MIN"] / 100.0) if rtl_alt > 0 else alt
        if self._fence_enabled() and int(self.params["FENCE_TYPE"]) & 1:
            target = min(target, self.params["FENCE_ALT_MAX"] - self.params["FENCE_MARGIN"])
        _hn, _he, hd = self.home_ned
        self.rtl_alt = target - hd  # relative to home -> above origin
        self.rtl_alt = max(self.rtl_alt, -hd + 2.0)
        self.rtl_state = RTL_CLIMB
        self.target = (b[0], b[1], -self.rtl_alt)
        self.leg = None

    def _rtl_step(self, lim: Limits, dt: float, b: tuple[float, float, float]) -> None:
        k = self.kin
        hn, he, hd = self.home_ned
        if self.rtl_state == RTL_CLIMB:
            tn, te, _ = self.target
            k.position_step(tn, te, -self.rtl_alt, lim, dt, b[0], b[1], b[2])
            if abs(-b[2] - self.rtl_alt) < 0.5:
                self.rtl_state = RTL_RETURN
                self.target = (hn, he, -self.rtl_alt)
                self._set_leg(hn, he)
        elif self.rtl_state == RTL_RETURN:
            k.position_step(hn, he, -self.rtl_alt, lim, dt, b[0], b[1], b[2])
            if (
                math.hypot(hn - b[0], he - b[1]) < max(0.5, self.params["WPNAV_RADIUS"] / 100.0 * 0.25)
                and math.hypot(k.vn, k.ve) < 0.5
            ):
                self.rtl_state = RTL_LOITER
                self.rtl_loiter_until = self.t + self.params["RTL_LOIT_TIME"] / 1000.0
                self.leg = None
        elif self.rtl_state == RTL_LOITER:
            k.position_step(hn, he, -self.rtl_alt, lim, dt, b[0], b[1], b[2])
            if self.t >= self.rtl_loiter_until:
                final = self.params["RTL_ALT_FINAL"] / 100.0
                self.rtl_state = RTL_DESCEND if final > 0 else RTL_FINAL
                self.land_target = (hn, he)
        elif self.rtl_state == RTL_DESCEND:
            final = self.params["RTL_ALT_FINAL"] / 100.0
            k.position_step(hn, he, hd - final, lim, dt, b[0], b[1], b[2])
        else:
            self._land_step(lim, dt, b)

    def set_mode(self, mode: int, reason: str = "") -> bool:
        """ArduCopter's mode change rules; returns False (and says why) when refused."""
        if mode not in MODE_NAMES:
            return False
        if self.armed and mode in POSITION_MODES and not self.gps_ok:
            self.statustext(SEV_WARNING, "Flight mode change failed")
            return False
        if mode == AUTO and self.armed:
            items = self.mission.mission_items()
            if len(items) <= 1:
                self.statustext(SEV_WARNING, "Flight mode change failed")
                return False
            if self.landed and not self._mission_starts_with_takeoff():
                self.statustext(SEV_WARNING, "Auto: Missing Takeoff Cmd")
                return False
        prev = self.mode
        self.mode = mode
        self.guided_wp_active = False
        self.speed_xy_override = self.speed_up_override = self.speed_dn_override = None
        self.vel_target = None
        if mode != AUTO:
            self.mis_rtl = self.mis_land = False
        if mode in (GUIDED, LOITER, POSHOLD):
            self.target = self._stopping_point() if not self.landed else self.belief()
            self.leg = None
        elif mode == BRAKE:
            self.target = self._stopping_point(BRAKE_DECEL) if not self.landed else self.belief()
            self.leg = None
        elif mode == LAND:
            sp = self._stopping_point() if not self.landed else self.belief()
            self.land_target = (sp[0], sp[1])
            self.leg = None
        elif mode == RTL:
            self._start_rtl()
        elif mode == AUTO and (prev != AUTO or not self.mis_started):
            self._auto_begin()
        if reason:
            self.statustext(SEV_NOTICE, reason)
        return True

    # ------------------------------------------------------------------ AUTO
    def _auto_ground_start(self) -> bool:
        """On the ground in AUTO only a takeoff item (or DO items before it) may run."""
        items = self.mission.mission_items()
        if not 0 < self.mis_idx < len(items):
            return False
        cmd = items[self.mis_idx].command
        return cmd == mav.MAV_CMD_NAV_TAKEOFF or cmd not in _NAV_CMDS

    def _mission_starts_with_takeoff(self) -> bool:
        for it in self.mission.mission_items()[1:]:
            if it.command in _NAV_CMDS:
                return it.command == mav.MAV_CMD_NAV_TAKEOFF
        return False

    def _auto_begin(self) -> None:
        n = len(self.mission.mission_items())
        if self.mis_idx < 1 or self.mis_idx >= n or self.mis_complete:
            self.mis_idx = 1
        self.mis_started = False
        self.mis_complete = False
        self.mis_rtl = self.mis_land = False
        self._send_mission_current()

    def _send_mission_current(self) -> None:
        self.send(self.msg_mission_current())

    def _item_target(self, it: MissionItem, b: tuple[float, float, float]) -> tuple[float, float, float]:
        if it.x == 0 and it.y == 0:
            n, e = b[0], b[1]
        else:
            n, e = latlon_to_local(self.origin[0], self.origin[1], it.lat, it.lon)
        d = self._alt_to_d(it.frame, it.z) if (it.z != 0 or it.frame in GLOBAL_FRAMES_AMSL) else b[2]
        return n, e, d

    def _item_reached(self, seq: int) -> None:
        """MISSION_ITEM_REACHED for stored item ``seq``."""
        self.send(mav.MAVLink_mission_item_reached_message(seq))

    def _auto_advance(self, reached: bool = True) -> None:
        if reached:
            self._item_reached(self.mis_idx)
        self.mis_idx += 1
        self.mis_started = False
        self.mis_hold_until = None
        self.mis_reached = False
        if self.mis_idx >= len(self.mission.mission_items()):
            self.mis_complete = True
            self.statustext(SEV_INFO, "Mission complete")
            b = self.belief()
            self.target = (b[0], b[1], b[2]) if not self.mis_land else self.target
            self.leg = None
        self._send_mission_current()

    def _auto_step(self, lim: Limits, dt: float, b: tuple[float, float, float]) -> None:
        k = self.kin
        items = self.mission.mission_items()
        if self.mis_complete or self.mis_idx >= len(items):
            if self.mis_land:
                self._land_step(lim, dt, b)
            elif self.mis_rtl:
                self._rtl_step(lim, dt, b)
            else:
                tn, te, td = self.target
                k.position_step(tn, te, td, lim, dt, b[0], b[1], b[2])
            return
        it = items[self.mis_idx]
        cmd = it.command
        if not self.mis_started:
            self.mis_started = True
            self.statustext(SEV_INFO, f"Mission: {self.mis_idx} {_NAV_NAMES.get(cmd, str(cmd))}")
            self.mis_rtl = self.mis_land = False
            if cmd in (mav.MAV_CMD_NAV_WAYPOINT, mav.MAV_CMD_NAV_LOITER_UNLIM, mav.MAV_CMD_NAV_LOITER_TIME):
                self._goto(*self._item_target(it, b))
            elif cmd == mav.MAV_CMD_NAV_TAKEOFF:
                alt = it.z if it.frame not in GLOBAL_FRAMES_AMSL else it.z - self.home[2]
                d = -(alt + self.home[2] - self.origin[2])
                if -b[2] < -d - TAKEOFF_DONE_M:
                    self.target = (b[0], b[1], d)
                    if self.landed:
                        self.takeoff_alt = -d
                        self.landed = False
                else:
                    self._auto_advance()
                    return
            elif cmd == mav.MAV_CMD_NAV_LAND:
                tn, te, _ = self._item_target(it, b)
                self.target = (tn, te, b[2])
                self._set_leg(tn, te)
                self.mis_land = True
                self.land_target = (tn, te)
            elif cmd == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH:
                self.mis_rtl = True
                self._start_rtl()
            elif cmd == mav.MAV_CMD_DO_CHANGE_SPEED:
                self._change_speed(it.param1, it.param2)
                self._auto_advance()
                return
            else:  # other DO/condition commands: not simulated, skipped
                self._auto_advance(reached=False)
                return
        if cmd in (mav.MAV_CMD_NAV_WAYPOINT, mav.MAV_CMD_NAV_LOITER_UNLIM, mav.MAV_CMD_NAV_LOITER_TIME):
            tn, te, td = self.target
            k.position_step(tn, te, td, lim, dt, b[0], b[1], b[2])
            dist = math.sqrt((tn - b[0]) ** 2 + (te - b[1]) ** 2 + (td - b[2]) ** 2)
            hold = it.param1 if cmd != mav.MAV_CMD_NAV_LOITER_UNLIM else math.inf
            if not self.mis_reached:
                radius = max(0.05, self.params["WPNAV_RADIUS"] / 100.0)
                if hold > 0:  # a hold needs the vehicle stopped on the point
                    radius = min(radius, 0.5)
                if dist <= radius and (hold <= 0 or math.hypot(k.vn, k.ve) < 0.3):
                    self.mis_reached = True
                    self.mis_hold_until = self.t + hold
            if self.mis_reached and self.mis_hold_until is not None and self.t >= self.mis_hold_until:
                self._auto_advance()
        elif cmd == mav.MAV_CMD_NAV_TAKEOFF:
            if self.takeoff_alt is None:
                tn, te, td = self.target
                k.position_step(tn, te, td, lim, dt, b[0], b[1], b[2])
                if abs(td - b[2]) < TAKEOFF_DONE_M:
                    self._auto_advance()
        elif cmd == mav.MAV_CMD_NAV_LAND:
            tn, te, td = self.target
            if not self.mis_reached:
                k.position_step(tn, te, td, lim, dt, b[0], b[1], b[2])
                if math.hypot(tn - b[0], te - b[1]) < 0.5 and math.hypot(k.vn, k.ve) < 0.5:
                    self.mis_reached = True
                    self.leg = None
            else:
                self._land_step(lim, dt, b)
        elif cmd == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self._rtl_step(lim, dt, b)

    def _can_clear(self, mission_type: int) -> bool:
        return not (mission_type == MISSION and self.mode == AUTO and self.armed)

    def _mission_stored(self, mission_type: int) -> None:
        if mission_type == FENCE:
            self.fence_zones = build_fence(self.mission.stores[FENCE], self.origin[0], self.origin[1])
            self.params.define("FENCE_TOTAL", len(self.mission.stores[FENCE]))
        elif mission_type == MISSION:
            if self.mode != AUTO:
                self.mis_idx = 1
                self.mis_complete = False
                self.mis_started = False
            elif self.mis_idx >= len(self.mission.mission_items()):
                self.mis_idx = max(1, len(self.mission.mission_items()) - 1)
                self.mis_started = False

    def _home_item(self) -> MissionItem:
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
            round(self.home[0] * 1e7),
            round(self.home[1] * 1e7),
            self.home[2],
        )

    # ------------------------------------------------------------------ arming
    def _prearm_failure(self) -> str | None:
        if self.params["ARMING_CHECK"] == 0:
            return None
        if self.booting or self.t < self.prearm_delay_s:
            return "PreArm: Need Position Estimate"
        if not self.gps_ok:
            return "PreArm: GPS 1: Bad fix"
        if self.batt_failsafe:
            return "PreArm: Battery 1 low voltage failsafe"
        if self.params["BATT_ARM_VOLT"] > 0 and self.battery.voltage_v < self.params["BATT_ARM_VOLT"]:
            return "PreArm: Battery 1 below minimum arming voltage"
        if self._fence_enabled() and self._fence_breaches() != 0:
            return "PreArm: Fence: vehicle outside fence"
        return None

    def arm(self, force: bool = False) -> tuple[bool, str]:
        """Try to arm; returns (ok, reason)."""
        if self.armed:
            return True, ""
        if self.mode not in self.armable_modes:
            return False, "Arm: Mode not armable"
        if not force:
            why = self._prearm_failure()
            if why is not None:
                return False, why
        self.armed = True
        self.arm_time = self.t
        self.landed = True
        self.landed_since = self.t
        self.batt_low_since = None
        self.ekf_failsafe = self.gcs_failsafe = False
        b = self.belief()
        self.target = (b[0], b[1], b[2])
        if self.mode == AUTO:
            self._auto_begin()
        return True, ""

    def _disarm(self, reason: str = "") -> None:
        self.armed = False
        self.takeoff_alt = None
        if reason:
            self.statustext(
                SEV_INFO,
                f"Disarming motors ({reason})" if reason != "Land complete" else "Land complete, disarming",
            )

    # ------------------------------------------------------------------ failsafes and fence
    def _failsafes(self) -> None:
        p = self.params
        # battery (raw voltage against BATT_LOW_VOLT for BATT_LOW_TIMER seconds)
        low = p["BATT_LOW_VOLT"]
        if low > 0 and self.battery.voltage_v < low and self.armed:
            if self.batt_low_since is None:
                self.batt_low_since = self.t
            elif not self.batt_failsafe and self.t - self.batt_low_since >= p["BATT_LOW_TIMER"]:
                self.batt_failsafe = True
                bat = self.battery
                self.statustext(
                    SEV_CRITICAL, f"Battery 1 is low {bat.voltage_v:.2f}V used {bat.consumed_mah:.0f} mAh"
                )
                act = int(p["BATT_FS_LOW_ACT"])
                if not self.landed and self.mode not in (LAND,):
                    if act in (1,):
                        self.set_mode(LAND)
                    elif act in (2, 3, 4) and self.mode != RTL:
                        self.set_mode(RTL)
        elif self.batt_low_since is not None and self.battery.voltage_v >= low:
            self.batt_low_since = None
        # EKF failsafe on GPS loss in a position mode
        if (
            self.gps_lost_since is not None
            and not self.ekf_failsafe
            and self.armed
            and not self.landed
            and self.t - self.gps_lost_since >= GPS_FS_S
        ):
            self.ekf_failsafe = True
            action = int(p["FS_EKF_ACTION"])
            if action and self.mode in POSITION_MODES:
                self.set_mode(LAND)
                self.statustext(SEV_CRITICAL, "EKF Failsafe: changed to LAND Mode")
            else:
                self.statustext(SEV_CRITICAL, "EKF variance")
        if self.gps_lost_since is None:
            self.ekf_failsafe = False
        # GCS failsafe (FS_GCS_ENABLE: 1 RTL, 2 continue AUTO else RTL, 5 LAND)
        fs_gcs = int(p["FS_GCS_ENABLE"])
        if (
            fs_gcs
            and self.armed
            and not self.landed
            and self.last_gcs_heartbeat is not None
            and self.t - self.last_gcs_heartbeat > p.get("FS_GCS_TIMEOUT", 5.0)
            and not self.gcs_failsafe
        ):
            self.gcs_failsafe = True
            self.statustext(SEV_CRITICAL, "GCS Failsafe")
            if fs_gcs == 5:
                self.set_mode(LAND)
            elif not (fs_gcs == 2 and self.mode == AUTO) and self.mode not in (RTL, LAND):
                self.set_mode(RTL)
        if self.last_gcs_heartbeat is not None and self.t - self.last_gcs_heartbeat <= 1.0:
            self.gcs_failsafe = False

    def _fence_enabled(self) -> bool:
        return self.params["FENCE_ENABLE"] != 0

    def _fence_breaches(self) -> int:
        """Bitmask of breached fence types (1 max alt, 2 home circle, 4 uploaded polygons/circles)."""
        ftype = int(self.params["FENCE_TYPE"])
        b = self.belief()
        hn, he, hd = self.home_ned
        out = 0
        if ftype & 1 and -(b[2] - hd) > self.params["FENCE_ALT_MAX"]:
            out |= 1
        if ftype & 2 and math.hypot(b[0] - hn, b[1] - he) > self.params["FENCE_RADIUS"]:
            out |= 2
        if ftype & 4 and self.fence_zones:
            for z in self.fence_zones:
                if z.contains(b[0], b[1]) != z.inclusion:
                    out |= 4
                    break
        return out

    def _fence_check(self) -> None:
        if not self._fence_enabled() or self.landed:
            self.breaches = 0
            return
        if not self.armed:
            return
        now = self._fence_breaches()
        new = now & ~self.breaches
        self.breaches = now
        if not new:
            return
        self.breach_count += 1
        self.breach_time_ms = int(self.t * 1000)
        self.breach_type = mav.FENCE_BREACH_BOUNDARY if new & 6 else mav.FENCE_BREACH_MAXALT
        self.statustext(SEV_NOTICE, "Fence Breached")
        action = int(self.params["FENCE_ACTION"])
        if action == 0 or self.mode == LAND or (self.mode == AUTO and self.mis_land):
            return
        if action in (1, 3, 5):
            if self.mode != RTL and not (self.gps_ok and self.set_mode(RTL)):
                self.set_mode(LAND)
        elif action == 2 or (action == 4 and not (self.gps_ok and self.set_mode(BRAKE))):
            self.set_mode(LAND)

    # ------------------------------------------------------------------ incoming messages
    def handle(self, msg: mav.MAVLink_message, wall_now: float) -> None:
        """Process one decoded MAVLink message from the GCS."""
        t = msg.get_type()
        if t == "HEARTBEAT":
            if msg.type == mav.MAV_TYPE_GCS:
                self.last_gcs_heartbeat = self.t
            return
        tgt_sys = getattr(msg, "target_system", None)
        if tgt_sys is not None and tgt_sys not in (0, self.sysid):
            return
        tgt_comp = getattr(msg, "target_component", None)
        if tgt_comp is not None and tgt_comp not in (0, 1):
            return
        if t == "COMMAND_LONG":
            self._command(msg, False)
        elif t == "COMMAND_INT":
            self._command(msg, True)
        elif t == "SET_POSITION_TARGET_GLOBAL_INT":
            self._set_position_target_global(msg)
        elif t == "SET_POSITION_TARGET_LOCAL_NED":
            self._set_position_target_local(msg)
        elif t == "SET_MODE":
            self.set_mode(int(msg.custom_mode))
        elif t == "PARAM_REQUEST_LIST":
            for i, name in enumerate(self.params):
                self._send_param(name, i)
        elif t == "PARAM_REQUEST_READ":
            pname = self.params.name_at(msg.param_index) if msg.param_index >= 0 else _pname(msg.param_id)
            if pname is not None and pname in self.params:
                self._send_param(pname)
        elif t == "PARAM_SET":
            name = _pname(msg.param_id)
            if name in self.params and self.params.set(name, float(msg.param_value)):
                self._send_param(name)
        elif t == "REQUEST_DATA_STREAM":
            self._request_data_stream(msg)
        elif t == "MISSION_SET_CURRENT":
            self._set_mission_current(int(msg.seq))
        elif t.startswith("MISSION_"):
            self.mission.handle(msg, wall_now)

    def _send_param(self, name: str, index: int | None = None) -> None:
        self.send(
            mav.MAVLink_param_value_message(
                name.encode(),
                self.params[name],
                self.params.ptype(name),
                len(self.params),
                self.params.index(name) if index is None else index,
            )
        )

    def _request_data_stream(self, msg: mav.MAVLink_message) -> None:
        sid = msg.req_stream_id
        groups = list(STREAM_GROUPS) if sid == mav.MAV_DATA_STREAM_ALL else [sid]
        interval = 1.0 / msg.req_message_rate if (msg.start_stop and msg.req_message_rate > 0) else None
        for g in groups:
            for mid in STREAM_GROUPS.get(g, ()):
                self.link.set_message_interval(mid, interval)

    def _set_mission_current(self, seq: int) -> bool:
        if not 0 < seq < len(self.mission.mission_items()):
            return False
        self.mis_idx = seq
        self.mis_started = False
        self.mis_complete = False
        self.mis_reached = False
        self._send_mission_current()
        return True

    def _set_position_target_global(self, msg: mav.MAVLink_message) -> None:
        """GUIDED position (or velocity) target; never acknowledged, like ArduCopter."""
        if self.mode != GUIDED or not self.armed:
            return
        mask = msg.type_mask
        pos_ignore = mask & 0b111
        vel_ignore = mask & 0b111000
        if not pos_ignore:
            frame = msg.coordinate_frame
            n, e = latlon_to_local(self.origin[0], self.origin[1], msg.lat_int / 1e7, msg.lon_int / 1e7)
            if frame in GLOBAL_FRAMES_AMSL:
                d = -(msg.alt - self.origin[2])
            else:  # relative-alt (and terrain frames, treated as relative over flat ground)
                d = -(msg.alt + self.home[2] - self.origin[2])
            if self.landed and self.takeoff_alt is None:
                return  # ArduCopter ignores position targets on the ground
            self._goto(n, e, d)
        elif not vel_ignore:
            self.vel_target = (msg.vx, msg.vy, msg.vz)
            self.vel_target_t = self.t
            self.leg = None

    def _set_position_target_local(self, msg: mav.MAVLink_message) -> None:
        if self.mode != GUIDED or not self.armed or (self.landed and self.takeoff_alt is None):
            return
        mask = msg.type_mask
        frame = msg.coordinate_frame
        if not mask & 0b111:
            if frame == mav.MAV_FRAME_LOCAL_NED:
                n, e, d = msg.x, msg.y, msg.z
            elif frame == mav.MAV_FRAME_LOCAL_OFFSET_NED:
                b = self.belief()
                n, e, d = b[0] + msg.x, b[1] + msg.y, b[2] + msg.z
            elif frame in (mav.MAV_FRAME_BODY_OFFSET_NED, mav.MAV_FRAME_BODY_NED):
                b = self.belief()
                c, s = math.cos(self.heading), math.sin(self.heading)
                n, e, d = b[0] + c * msg.x - s * msg.y, b[1] + s * msg.x + c * msg.y, b[2] + msg.z
            else:
                return
            self._goto(n, e, d)
        elif not mask & 0b111000:
            vx, vy = msg.vx, msg.vy
            if frame in (mav.MAV_FRAME_BODY_OFFSET_NED, mav.MAV_FRAME_BODY_NED):
                c, s = math.cos(self.heading), math.sin(self.heading)
                vx, vy = c * msg.vx - s * msg.vy, s * msg.vx + c * msg.vy
            self.vel_target = (vx, vy, msg.vz)
            self.vel_target_t = self.t
            self.leg = None

    def _change_speed(self, speed_type: float, speed: float) -> bool:
        if speed <= 0:
            return speed == -1 or speed == 0
        st = int(speed_type)
        if st in (0, 1):
            self.speed_xy_override = speed
        elif st == 2:
            self.speed_up_override = speed
        elif st == 3:
            self.speed_dn_override = speed
        else:
            return False
        return True

    def _command(self, msg: mav.MAVLink_message, is_int: bool) -> None:
        cmd = msg.command
        result, extra = self._command_result(msg, is_int)
        for text in extra:
            self.statustext(SEV_CRITICAL if text.startswith(("PreArm", "Arm")) else SEV_WARNING, text)
        if result is not None:
            self.send(
                mav.MAVLink_command_ack_message(
                    cmd, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
                )
            )
        if cmd == mav.MAV_CMD_REQUEST_MESSAGE and result == mav.MAV_RESULT_ACCEPTED:
            out = self.build(int(msg.param1))
            if out is not None:
                self.send(out)
        elif cmd == mav.MAV_CMD_GET_HOME_POSITION and (home := self.msg_home_position()) is not None:
            self.send(home)
        elif cmd == mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES and result == mav.MAV_RESULT_ACCEPTED:
            self.send(self.msg_autopilot_version())

    def _cmd_location(
        self, msg: mav.MAVLink_message, is_int: bool
    ) -> tuple[float | None, float | None, float | None]:
        """lat, lon (deg) and local down of a command's location; None where 'keep current'."""
        if is_int:
            lat = msg.x / 1e7 if msg.x != 0 else None
            lon = msg.y / 1e7 if msg.y != 0 else None
            frame, alt = msg.frame, msg.z
        else:
            lat = msg.param5 if msg.param5 != 0 and not math.isnan(msg.param5) else None
            lon = msg.param6 if msg.param6 != 0 and not math.isnan(msg.param6) else None
            frame, alt = mav.MAV_FRAME_GLOBAL_RELATIVE_ALT, msg.param7
        d = None if math.isnan(alt) else self._alt_to_d(frame, alt)
        return lat, lon, d

    def _command_result(self, msg: mav.MAVLink_message, is_int: bool) -> tuple[int | None, list[str]]:
        """Execute a COMMAND_LONG/INT; returns (MAV_RESULT, STATUSTEXTs to send first)."""
        cmd = msg.command
        acc, failed = mav.MAV_RESULT_ACCEPTED, mav.MAV_RESULT_FAILED
        p1, p2 = msg.param1, msg.param2
        if cmd == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            force = round(p2) == FORCE_MAGIC
            if p1 >= 0.5:
                ok, why = self.arm(force)
                return (acc, []) if ok else (failed, [why])
            if not self.armed:
                return acc, []
            if not self.landed and not force:
                return failed, []
            self._disarm()
            return acc, []
        if cmd == mav.MAV_CMD_DO_SET_MODE:
            return (acc if self.set_mode(int(p2)) else failed), []
        if cmd == mav.MAV_CMD_NAV_TAKEOFF:
            alt = msg.z if is_int else msg.param7
            if is_int and msg.frame in GLOBAL_FRAMES_AMSL:
                alt -= self.home[2]
            if (
                not self.armed
                or self.mode != GUIDED
                or not self.landed
                or self.takeoff_alt is not None
                or math.isnan(alt)
                or alt <= self.alt_rel_est()
            ):
                return failed, []
            b = self.belief()
            self.guided_wp_active = False
            self.takeoff_alt = alt + self.home[2] - self.origin[2]
            self.target = (b[0], b[1], -self.takeoff_alt)
            self.landed = False
            self.leg = None
            return acc, []
        if cmd == mav.MAV_CMD_NAV_LAND:
            return (acc if self.set_mode(LAND) else failed), []
        if cmd == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return (acc if self.set_mode(RTL) else failed), []
        if cmd == mav.MAV_CMD_DO_REPOSITION:
            lat, lon, d = self._cmd_location(msg, is_int)
            if self.mode != GUIDED and not self.set_mode(GUIDED):
                return failed, []
            b = self.belief()
            n, e = b[0], b[1]
            if lat is not None and lon is not None:
                n, e = latlon_to_local(self.origin[0], self.origin[1], lat, lon)
            if d is None:
                d = self.target[2] if not self.landed else b[2]
            if not self.landed or self.takeoff_alt is not None:
                self._goto(n, e, d)
            if p1 > 0:
                self.speed_xy_override = p1
            return acc, []
        if cmd == mav.MAV_CMD_DO_CHANGE_SPEED:
            # Only modes with a speed override take it (Mode::set_speed_xy): AUTO, GUIDED, RTL.
            if self.mode not in (AUTO, GUIDED, RTL):
                return failed, []
            return (acc if self._change_speed(p1, p2) else failed), []
        if cmd == mav.MAV_CMD_DO_SET_HOME:
            if p1 >= 0.5:
                en, ee, ed = self.est()
                lat_, lon_ = local_to_latlon(self.origin[0], self.origin[1], en, ee)
                self.home = (lat_, lon_, self.origin[2] - ed)
            else:
                if is_int:
                    lat_, lon_, alt_ = msg.x / 1e7, msg.y / 1e7, msg.z
                else:
                    lat_, lon_, alt_ = msg.param5, msg.param6, msg.param7
                if (lat_ == 0 and lon_ == 0) or math.isnan(alt_):
                    return failed, []
                self.home = (lat_, lon_, alt_)
            if (home := self.msg_home_position()) is not None:
                self.send(home)
            return acc, []
        if cmd == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            mid, us = int(p1), p2
            if mid not in BUILDERS:
                return failed, []
            if us < 0:
                self.link.set_message_interval(mid, None)
            elif us == 0:
                self.link.set_message_interval(mid, 1.0)
            else:
                self.link.set_message_interval(mid, us / 1e6)
            return acc, []
        if cmd == mav.MAV_CMD_REQUEST_MESSAGE:
            return (acc if int(p1) in BUILDERS else failed), []
        if cmd == mav.MAV_CMD_GET_HOME_POSITION:
            return acc, []
        if cmd == mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return acc, []
        if cmd == mav.MAV_CMD_MISSION_START:
            if len(self.mission.mission_items()) <= 1:
                return failed, []
            if self.mode != AUTO and not self.set_mode(AUTO):
                return failed, []
            if int(p1) > 0:
                self._set_mission_current(int(p1))
            return acc, []
        if cmd == mav.MAV_CMD_DO_SET_MISSION_CURRENT:
            return (acc if self._set_mission_current(int(p1)) else failed), []
        if cmd == mav.MAV_CMD_CONDITION_YAW:
            return acc, []
        return mav.MAV_RESULT_UNSUPPORTED, []

    # ------------------------------------------------------------------ outgoing messages
    def time_boot_ms(self) -> int:
        """Sim milliseconds since boot (wraps like the uint32 field)."""
        return int(self.t * 1000) & 0xFFFFFFFF

    def landed_state(self) -> int:
        """MAV_LANDED_STATE as ArduCopter reports it."""
        if self.landed and self.takeoff_alt is None:
            return mav.MAV_LANDED_STATE_ON_GROUND
        if self.takeoff_alt is not None:
            return mav.MAV_LANDED_STATE_TAKEOFF
        landing = (
            self.mode == LAND
            or (self.mode == RTL and self.rtl_state == RTL_FINAL)
            or (self.mode == AUTO and self.mis_land and self.mis_reached)
            or (self.mode == AUTO and self.mis_rtl and self.rtl_state == RTL_FINAL)
        )
        return mav.MAV_LANDED_STATE_LANDING if landing else mav.MAV_LANDED_STATE_IN_AIR

    def msg_heartbeat(self) -> mav.MAVLink_message:
        """HEARTBEAT: quadrotor, ArduPilot, custom mode + armed flag."""
        base = (
            mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            | mav.MAV_MODE_FLAG_STABILIZE_ENABLED
            | mav.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        )
        if self.mode in (AUTO, GUIDED, RTL, LAND, LOITER, POSHOLD, BRAKE):
            base |= mav.MAV_MODE_FLAG_GUIDED_ENABLED
        if self.mode == AUTO:
            base |= mav.MAV_MODE_FLAG_AUTO_ENABLED
        if self.armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        if self.batt_failsafe or self.ekf_failsafe or self.gcs_failsafe:
            status = mav.MAV_STATE_CRITICAL
        else:
            status = mav.MAV_STATE_ACTIVE if self.armed else mav.MAV_STATE_STANDBY
        return mav.MAVLink_heartbeat_message(
            mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, base, self.mode, status, 3
        )

    def msg_sys_status(self) -> mav.MAVLink_message:
        """SYS_STATUS with sensor health (GPS, battery, fence, pre-arm) and battery figures."""
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
        if self._fence_enabled() or self.fence_zones:
            present |= s.MAV_SYS_STATUS_GEOFENCE
        enabled = present
        if not self._fence_enabled():
            enabled &= ~s.MAV_SYS_STATUS_GEOFENCE
        health = present
        if not self.gps_ok:
            health &= ~s.MAV_SYS_STATUS_SENSOR_GPS
        if self.batt_failsafe:
            health &= ~s.MAV_SYS_STATUS_SENSOR_BATTERY
        if self.breaches:
            health &= ~s.MAV_SYS_STATUS_GEOFENCE
        if self._prearm_failure() is not None:
            health &= ~s.MAV_SYS_STATUS_PREARM_CHECK
        bat = self.battery
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
        if self.booting:
            return mav.MAVLink_global_position_int_message(self.time_boot_ms(), 0, 0, 0, 0, 0, 0, 0, 65535)
        en, ee, ed = self.est()
        lat, lon = local_to_latlon(self.origin[0], self.origin[1], en, ee)
        alt = self.origin[2] - ed
        gvn, gve = self.ground_velocity()
        return mav.MAVLink_global_position_int_message(
            self.time_boot_ms(),
            round(lat * 1e7),
            round(lon * 1e7),
            round(alt * 1000),
            round((alt - self.home[2]) * 1000),
            round(gvn * 100),
            round(gve * 100),
            round(self.kin.vd * 100 if not self.landed else 0),
            round(math.degrees(self.heading) % 360 * 100) % 36000,
        )

    def msg_local_position_ned(self) -> mav.MAVLink_message:
        """LOCAL_POSITION_NED relative to the EKF origin."""
        en, ee, ed = self.est()
        gvn, gve = self.ground_velocity()
        return mav.MAVLink_local_position_ned_message(
            self.time_boot_ms(), en, ee, ed, gvn, gve, self.kin.vd if not self.landed else 0.0
        )

    def msg_gps_raw_int(self) -> mav.MAVLink_message:
        """GPS_RAW_INT: 3D fix with 10 satellites, or fix 0 / frozen position while GPS is lost."""
        gvn, gve = self.ground_velocity()
        if self.gps_ok:
            en, ee, ed = self.est()
            lat, lon = local_to_latlon(self.origin[0], self.origin[1], en, ee)
            alt = self.origin[2] - ed
            fix, sats, eph, epv = 3, 10, 121, 200
            vel = round(math.hypot(gvn, gve) * 100)
            cog = round(math.degrees(math.atan2(gve, gvn)) % 360 * 100) % 36000 if vel > 0 else 0
        else:
            lat, lon, alt = self.gps_fix_lat, self.gps_fix_lon, self.origin[2] - self.est()[2]
            if self.booting:
                lat = lon = alt = 0.0
            fix, sats, eph, epv, vel, cog = 0, 0, 9999, 9999, 0, 0
        return mav.MAVLink_gps_raw_int_message(
            int(self.t * 1e6),
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
        k = self.kin
        c, s = math.cos(self.heading), math.sin(self.heading)
        a_fwd = k.an * c + k.ae * s
        a_right = -k.an * s + k.ae * c
        pitch = -math.atan2(a_fwd, 9.81)
        roll = math.atan2(a_right, 9.81)
        yaw = (self.heading + math.pi) % (2 * math.pi) - math.pi
        return mav.MAVLink_attitude_message(self.time_boot_ms(), roll, pitch, yaw, 0.0, 0.0, 0.0)

    def msg_vfr_hud(self) -> mav.MAVLink_message:
        """VFR_HUD: air/ground speed, heading, throttle %, AMSL altitude, climb rate."""
        gvn, gve = self.ground_velocity()
        gs = math.hypot(gvn, gve)
        airspeed = math.hypot(gvn - self.wind.north - self.gust[0], gve - self.wind.east - self.gust[1])
        p = self.power.power_w(not self.landed, self.armed, airspeed, -self.kin.vd)
        thr = 0 if not self.armed else min(100, round(50 * math.sqrt(p / self.power.p_hover)))
        alt = self.origin[2] - self.est()[2]
        return mav.MAVLink_vfr_hud_message(
            airspeed if not self.landed else 0.0,
            gs,
            round(math.degrees(self.heading)) % 360,
            thr,
            alt,
            -self.kin.vd if not self.landed else 0.0,
        )

    def msg_battery_status(self) -> mav.MAVLink_message:
        """BATTERY_STATUS: pack voltage in cell 0 (as ArduPilot without cell monitoring), charge state."""
        bat = self.battery
        volts = [min(65534, int(bat.voltage_v * 1000))] + [65535] * 9
        charge_state = mav.MAV_BATTERY_CHARGE_STATE_OK
        if self.batt_failsafe:
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
        if self.booting:
            return None
        hn, he, hd = self.home_ned
        return mav.MAVLink_home_position_message(
            round(self.home[0] * 1e7),
            round(self.home[1] * 1e7),
            round(self.home[2] * 1000),
            hn,
            he,
            hd,
            [1.0, 0.0, 0.0, 0.0],
            0.0,
            0.0,
            0.0,
            int(self.t * 1e6),
        )

    def msg_extended_sys_state(self) -> mav.MAVLink_message:
        """EXTENDED_SYS_STATE with the landed state."""
        return mav.MAVLink_extended_sys_state_message(mav.MAV_VTOL_STATE_UNDEFINED, self.landed_state())

    def msg_mission_current(self) -> mav.MAVLink_message:
        """MISSION_CURRENT: seq, total (home excluded) and mission state."""
        n = len(self.mission.mission_items())
        if n <= 1:
            state = mav.MISSION_STATE_NO_MISSION
        elif self.mis_complete:
            state = mav.MISSION_STATE_COMPLETE
        elif self.mode == AUTO and self.armed:
            state = mav.MISSION_STATE_ACTIVE
        elif self.mis_started:
            state = mav.MISSION_STATE_PAUSED
        else:
            state = mav.MISSION_STATE_NOT_STARTED
        seq = min(self.mis_idx, max(0, n - 1))
        return mav.MAVLink_mission_current_message(seq, max(0, n - 1), state, 1 if self.mode == AUTO else 0)

    def msg_nav_controller_output(self) -> mav.MAVLink_message:
        """NAV_CONTROLLER_OUTPUT: bearing and distance to the current position target."""
        b = self.belief()
        tn, te, td = self.target
        bearing = round(math.degrees(math.atan2(te - b[1], tn - b[0]))) if self.armed else 0
        wp_dist = min(65535, round(math.hypot(tn - b[0], te - b[1]))) if self.armed else 0
        return mav.MAVLink_nav_controller_output_message(
            0.0, 0.0, bearing, bearing, wp_dist, float(b[2] - td) if self.armed else 0.0, 0.0, 0.0
        )

    def msg_fence_status(self) -> mav.MAVLink_message | None:
        """FENCE_STATUS, only while the fence is enabled (as ArduPilot)."""
        if not self._fence_enabled():
            return None
        return mav.MAVLink_fence_status_message(
            1 if self.breaches else 0, self.breach_count, self.breach_type, self.breach_time_ms, 0
        )

    def msg_system_time(self) -> mav.MAVLink_message:
        """SYSTEM_TIME: Unix time unknown (0), sim boot time."""
        return mav.MAVLink_system_time_message(0, self.time_boot_ms())

    def msg_autopilot_version(self) -> mav.MAVLink_message:
        """AUTOPILOT_VERSION with the capabilities a GCS checks (MISSION_INT, COMMAND_INT, FENCE...)."""
        c = mav
        caps = (
            c.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
            | c.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
            | c.MAV_PROTOCOL_CAPABILITY_MISSION_INT
            | c.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | c.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
            | c.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
            | c.MAV_PROTOCOL_CAPABILITY_MAVLINK2
            | c.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
            | c.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
        )
        version = (4 << 24) | (5 << 16) | (0 << 8) | c.FIRMWARE_VERSION_TYPE_OFFICIAL
        return mav.MAVLink_autopilot_version_message(
            caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, self.sysid, [0] * 18
        )

    def build(self, msgid: int) -> mav.MAVLink_message | None:
        """The message ``msgid`` as it would be sent now, or None if not available."""
        fn = BUILDERS.get(msgid)
        return fn(self) if fn is not None else None


def _pname(raw: str | bytes) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode(errors="replace")
    return raw.split("\x00", 1)[0].strip().upper()


# methodcaller: a personality's override (sitl/px4.py msg_heartbeat) is the one streamed.
BUILDERS: dict[int, Callable[[SimVehicle], mav.MAVLink_message | None]] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: methodcaller("msg_heartbeat"),
    mav.MAVLINK_MSG_ID_SYS_STATUS: methodcaller("msg_sys_status"),
    mav.MAVLINK_MSG_ID_SYSTEM_TIME: methodcaller("msg_system_time"),
    mav.MAVLINK_MSG_ID_GPS_RAW_INT: methodcaller("msg_gps_raw_int"),
    mav.MAVLINK_MSG_ID_ATTITUDE: methodcaller("msg_attitude"),
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: methodcaller("msg_local_position_ned"),
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: methodcaller("msg_global_position_int"),
    mav.MAVLINK_MSG_ID_MISSION_CURRENT: methodcaller("msg_mission_current"),
    mav.MAVLINK_MSG_ID_NAV_CONTROLLER_OUTPUT: methodcaller("msg_nav_controller_output"),
    mav.MAVLINK_MSG_ID_VFR_HUD: methodcaller("msg_vfr_hud"),
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: methodcaller("msg_battery_status"),
    mav.MAVLINK_MSG_ID_HOME_POSITION: methodcaller("msg_home_position"),
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: methodcaller("msg_extended_sys_state"),
    mav.MAVLINK_MSG_ID_FENCE_STATUS: methodcaller("msg_fence_status"),
    mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION: methodcaller("msg_autopilot_version"),
}

DEFAULT_STREAMS: dict[int, float] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
}
