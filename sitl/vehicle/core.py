"""One simulated ArduCopter: the vehicle state, the physics step and the Python API; the behaviour
lives in the parts it composes (see sitl/vehicle/__init__.py for the map).

The vehicle is driven by the fleet loop: :meth:`SimVehicle.step` advances it by one fixed physics step
(sim time), :meth:`SimVehicle.handle` processes one decoded MAVLink message from its link. Everything
it says goes through the :class:`LinkAPI` the endpoint attaches, so this package never touches sockets.
Public methods meant for other threads (``state``, ``inject_*``, ``set_*``) take the fleet lock.
"""

from __future__ import annotations

import math
import random
import threading
from collections import deque
from collections.abc import Mapping

from sitl.dialect import mavlink as mav
from sitl.mission import MissionProtocol
from sitl.params import ParamStore
from sitl.physics import (
    Battery,
    GpsError,
    Kinematics,
    PathWobble,
    PowerModel,
    Wind,
    latlon_to_local,
    local_to_latlon,
)
from sitl.vehicle.arming import Arming
from sitl.vehicle.auto import AutoMission
from sitl.vehicle.commands import Commands
from sitl.vehicle.constants import (
    ACRO,
    ALT_HOLD,
    ARMABLE_MODES,
    AUTO,
    GUST_LEAK,
    MODE_NAMES,
    SEV_CRITICAL,
    SEV_INFO,
    STABILIZE,
    WIND_LEAK,
)
from sitl.vehicle.failsafes import Failsafes, ekf_failsafe, ekf_failsafe_delay
from sitl.vehicle.fence import Fence
from sitl.vehicle.guidance import Guidance
from sitl.vehicle.inbound import Inbound
from sitl.vehicle.modes import ModeSwitch
from sitl.vehicle.setpoints import Setpoints
from sitl.vehicle.state import Failure, LinkAPI, NullLink, VehicleState
from sitl.vehicle.telemetry import BUILDERS, DEFAULT_STREAMS, Telemetry


class SimVehicle:
    """ArduCopter behaviour toward a ground station for one simulated quadrotor.

    It holds the vehicle state and composes the parts that act on it. Other autopilots' personalities
    (sitl/px4.py) subclass it and keep this engine for flight; what they may change is
    :attr:`armable_modes`, their own :class:`Telemetry` and :class:`MissionProtocol`, and the hooks in
    the "personality hooks" section below, through which the parts call each other.
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
        self.params = self._engine_params(params or {})
        self.kin = Kinematics()
        self.wind = Wind(self.rng, wind[0], wind[1], gust_mps)
        self.wind_n = wind[0]
        self.wind_e = wind[1]
        self.gps = GpsError(self.rng, 0.3, 0.1)
        self.wobble = PathWobble(self.rng.uniform(0, 2 * math.pi))
        self.power = PowerModel()
        self.battery = Battery(capacity_mah=self.params["BATT_CAPACITY"])
        self.link: LinkAPI = NullLink()
        self.reply_link: LinkAPI | None = None  # the link whose message is being handled
        # Commands and targets received (sim t, link name, message, command id, source system): what
        # each ground station (the agent's link "gcs", a second one "pilot") asked of the vehicle.
        self.command_log: deque[tuple[float, str, str, int | None, int]] = deque(maxlen=5000)
        # The parts, each with one job (see the package docstring); they read and change this state.
        self.guidance = Guidance(self)
        self.modes = ModeSwitch(self)
        self.auto = AutoMission(self)
        self.arming = Arming(self)
        self.failsafes = Failsafes(self)
        self.fence = Fence(self)
        self.inbound = Inbound(self)
        self.setpoints = Setpoints(self)
        self.commands = Commands(self)
        self.telemetry = Telemetry(self)
        self.mission = MissionProtocol(
            self.sysid,
            self.send,
            self.auto.home_item,
            self.auto.can_clear,
            self.mission_stored,
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
        # failsafes
        self.batt_failsafe = False
        self.gcs_failsafe = False
        self.ekf_failsafe = False
        # statistics
        self.distance_flown_m = 0.0
        self.max_path_error_m = 0.0
        self.leg: tuple[float, float, float, float] | None = None  # start n,e -> end n,e (true frame)
        self.true_prev = (0.0, 0.0, 0.0)
        self.failures: list[Failure] = []

    def _engine_params(self, given: Mapping[str, float]) -> ParamStore:
        """ArduCopter's table with ``given`` applied (unknown names are added)."""
        store = ParamStore()
        store.define("SYSID_THISMAV", self.sysid)
        for k, v in given.items():
            if k.upper() in store:
                store.set(k.upper(), float(v))
            else:
                store.define(k, float(v))
        store.on_change = self._param_changed
        return store

    # ------------------------------------------------------------------ shared helpers
    def send(self, msg: mav.MAVLink_message) -> None:
        """Send to the link being answered, else the vehicle's own (which drops it when nobody listens
        or the link is down)."""
        (self.reply_link or self.link).send(msg)

    def statustext(self, severity: int, text: str) -> None:
        """STATUSTEXT to the GCS (ArduPilot sends the words operators see)."""
        self.send(mav.MAVLink_statustext_message(severity, text.encode()[:50], 0, 0))

    @property
    def link_down(self) -> bool:
        """True while an injected link drop lasts."""
        return self.t < self.link_down_until

    @property
    def gps_ok(self) -> bool:
        """True when GPS has a fix (booted, no injected loss, SIM_GPS_DISABLE off, SIM_GPS1_ENABLE on)."""
        return (
            self.t >= self.gps_lost_until
            and self.t >= self.gps_boot_s
            and self.params.get("SIM_GPS_DISABLE") == 0
            and self.params.get("SIM_GPS1_ENABLE", 1.0) != 0
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

    def _param_changed(self, name: str, value: float) -> None:
        """Apply a PARAM_SET to the models (limits cache, wind, gusts, battery capacity)."""
        if name.startswith("WPNAV_"):
            self.guidance.lim_cache = None
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
        """Steady wind (m/s toward north/east), mirrored in SIM_WIND_SPD/DIR."""
        self.wind.north, self.wind.east = north, east
        if update_params:
            spd = math.hypot(north, east)
            frm = (math.degrees(math.atan2(-east, -north)) + 360.0) % 360.0 if spd > 0 else 0.0
            self.params.define("SIM_WIND_SPD", spd)
            self.params.define("SIM_WIND_DIR", frm)

    def mode_name(self) -> str:
        """The flight mode's name as this autopilot calls it (VehicleState.mode)."""
        return MODE_NAMES.get(self.mode, str(self.mode))

    def wire_custom_mode(self) -> int:
        """HEARTBEAT.custom_mode of the current mode."""
        return self.mode

    def default_streams(self) -> dict[int, float]:
        """Messages (id -> interval, sim s) a fresh link gets unasked: ArduPilot's HEARTBEAT + SYS_STATUS."""
        return DEFAULT_STREAMS

    # ------------------------------------------------------------------ personality hooks
    # The parts call each other through these, so a personality's override applies everywhere.
    def set_mode(self, mode: int, reason: str = "") -> bool:
        """ArduCopter's mode change rules; returns False (and says why) when refused."""
        return self.modes.set_mode(mode, reason)

    def arm(self, force: bool = False) -> tuple[bool, str]:
        """Try to arm; returns (ok, reason)."""
        return self.arming.arm(force)

    def disarm(self, reason: str = "") -> None:
        """Stop the motors, saying ``reason`` (ArduCopter's words) if given."""
        self.arming.disarm(reason)

    def control(self, dt: float) -> None:
        """Run the current flight mode's controller for one step."""
        self.guidance.control(dt)

    def start_rtl(self) -> None:
        """Set up a return: the return altitude and the climb to it."""
        self.guidance.start_rtl()

    def gnss_failsafe_delay(self) -> float | None:
        """Sim seconds from GPS loss to the autopilot's position failsafe (None: disabled)."""
        return ekf_failsafe_delay(self)

    def gnss_failsafe(self) -> None:
        """The autopilot's own reaction to a lost position estimate (ArduCopter: EKF failsafe)."""
        ekf_failsafe(self)

    def gnss_failsafe_cleared(self) -> None:
        """GPS is back after the position failsafe (the mode stays as the failsafe left it)."""
        self.statustext(SEV_CRITICAL, "EKF Failsafe Cleared")

    def item_reached(self, seq: int) -> None:
        """MISSION_ITEM_REACHED for stored item ``seq``."""
        self.auto.item_reached(seq)

    def mission_stored(self, mission_type: int) -> None:
        """A mission/fence/rally upload has replaced the stored list."""
        self.auto.mission_stored(mission_type)

    def set_mission_current(self, seq: int) -> bool:
        """Make stored item ``seq`` the current one; False if there is no such item."""
        return self.auto.set_current(seq)

    def handle(self, msg: mav.MAVLink_message, wall_now: float) -> None:
        """Process one decoded MAVLink message from the GCS."""
        self.inbound.handle(msg, wall_now)

    def command(self, msg: mav.MAVLink_message, is_int: bool) -> None:
        """Execute a COMMAND_LONG/INT and answer it."""
        self.commands.handle(msg, is_int)

    def command_result(self, msg: mav.MAVLink_message, is_int: bool) -> tuple[int | None, list[str]]:
        """Execute a COMMAND_LONG/INT; returns (MAV_RESULT, STATUSTEXTs to send first)."""
        return self.commands.result(msg, is_int)

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
                mission_current=self.auto.idx if self.mode == AUTO else -1,
                mission_count=len(self.mission.mission_items()),
                link_down=self.link_down,
                fence_breached=self.fence.breaches != 0,
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

    def inject_gps_loss(self, seconds: float = math.inf) -> None:
        """No GPS fix for ``seconds`` of sim time (default: for good): GPS_RAW_INT fix 0, no satellites,
        its position frozen; the estimate dead-reckons and the personality's position failsafe follows
        (:meth:`gnss_failsafe_delay`)."""
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
            if (home := self.telemetry.msg_home_position()) is not None:
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
        self.control(dt)
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
        pn, pe, pd = self.true_prev
        if not self.landed:
            self.distance_flown_m += math.sqrt((tn - pn) ** 2 + (te - pe) ** 2 + (td - pd) ** 2)
            if self.leg is not None and math.hypot(gvn, gve) > 0.5:
                self._path_error(tn, te)
        self.true_prev = (tn, te, td)
        # battery
        v_air = math.hypot(gvn - wn, gve - we)
        self.battery.draw(self.power.power_w(not self.landed, self.armed, v_air, -k.vd), dt)
        self.failsafes.check()
        if t >= self.fence.next_check:
            self.fence.next_check = t + 0.1
            self.fence.check()

    def _path_error(self, tn: float, te: float) -> None:
        """Track the largest distance of the true position from the current straight leg."""
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
        """Apply a scheduled failure now."""
        if f.kind == "link_drop":
            self.link_down_until = max(self.link_down_until, f.at + f.duration)
        elif f.kind == "gps_loss":
            self.gps_lost_until = max(self.gps_lost_until, f.at + f.duration)
        elif f.kind == "battery":
            self.battery.set_pct(f.value[0])
        elif f.kind == "wind":
            self._set_wind(f.value[0], f.value[1])

    def _touchdown(self) -> None:
        """On the ground: motion stops, the leg ends."""
        k = self.kin
        k.d = 0.0
        k.vn = k.ve = k.vd = 0.0
        self.landed = True
        self.landed_since = self.t
        self.leg = None
        self.vel_target = None

    def build(self, msgid: int) -> mav.MAVLink_message | None:
        """The message ``msgid`` as it would be sent now, or None if not available."""
        fn = BUILDERS.get(msgid)
        return fn(self) if fn is not None else None
