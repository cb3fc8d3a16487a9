"""Flight guidance: what each flight mode flies, step by step (position/velocity control, take-off climb,
RTL and landing profiles, the speed limits in force)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from sitl.mission import GLOBAL_FRAMES_AMSL
from sitl.physics import Limits
from sitl.vehicle.constants import (
    ALT_HOLD,
    AUTO,
    BRAKE,
    BRAKE_DECEL,
    GUIDED,
    LAND,
    LAND_DETECT_S,
    LOITER,
    POSHOLD,
    RTL,
    RTL_CLIMB,
    RTL_DESCEND,
    RTL_FINAL,
    RTL_LOITER,
    RTL_RETURN,
    TAKEOFF_DONE_M,
    VEL_TIMEOUT_S,
)

if TYPE_CHECKING:
    from sitl.vehicle.core import SimVehicle


class Guidance:
    """Runs the current mode's controller on the vehicle's kinematics; owns nothing but the limits cache."""

    def __init__(self, v: SimVehicle) -> None:
        self.v = v
        self.lim_cache: Limits | None = None
        self.rtl_state = RTL_CLIMB
        self.rtl_alt = 15.0  # metres above the origin
        self.rtl_loiter_until = 0.0
        self.land_target: tuple[float, float] = (0.0, 0.0)  # n, e of LAND and the final descent

    def limits(self) -> Limits:
        """The speed/acceleration limits in force: WPNAV_*, RTL_SPEED in RTL, DO_CHANGE_SPEED overrides."""
        v = self.v
        if self.lim_cache is None:
            p = v.params
            self.lim_cache = Limits(
                speed_xy=max(0.2, p["WPNAV_SPEED"] / 100.0),
                accel_xy=max(0.5, p["WPNAV_ACCEL"] / 100.0),
                speed_up=max(0.1, p["WPNAV_SPEED_UP"] / 100.0),
                speed_dn=max(0.1, p["WPNAV_SPEED_DN"] / 100.0),
                accel_z=max(0.5, p["WPNAV_ACCEL_Z"] / 100.0),
            )
        base = self.lim_cache
        overrides = (v.speed_xy_override, v.speed_up_override, v.speed_dn_override)
        no_override = all(o is None for o in overrides)
        if no_override:
            if v.mode == RTL and v.params["RTL_SPEED"] > 0:
                return Limits(
                    v.params["RTL_SPEED"] / 100.0,
                    base.accel_xy,
                    base.speed_up,
                    base.speed_dn,
                    base.accel_z,
                )
            return base
        return Limits(
            v.speed_xy_override if v.speed_xy_override is not None else base.speed_xy,
            base.accel_xy,
            v.speed_up_override if v.speed_up_override is not None else base.speed_up,
            v.speed_dn_override if v.speed_dn_override is not None else base.speed_dn,
            base.accel_z,
        )

    def stopping_point(self, decel: float | None = None) -> tuple[float, float, float]:
        """Where the vehicle would stop from its current (believed) position and velocity."""
        v = self.v
        b = v.belief()
        k = v.kin
        a = decel if decel is not None else self.limits().accel_xy
        sp = math.hypot(k.vn, k.ve)
        if sp > 1e-3:
            dist = sp * sp / (2.0 * a)
            n, e = b[0] + k.vn / sp * dist, b[1] + k.ve / sp * dist
        else:
            n, e = b[0], b[1]
        d = b[2] + (k.vd * abs(k.vd) / (2.0 * self.limits().accel_z))
        return n, e, min(d, -0.5) if not v.landed else b[2]

    def set_leg(self, tn: float, te: float) -> None:
        """Start a straight leg (for the path-error statistic) from the true position to (tn, te)."""
        v = self.v
        v.leg = (v.true_prev[0], v.true_prev[1], tn, te)

    def goto(self, n: float, e: float, d: float) -> None:
        """Fly to (n, e, d); the first target in GUIDED starts the waypoint controller at WPNAV_SPEED."""
        v = self.v
        if v.mode == GUIDED and not v.guided_wp_active:
            v.guided_wp_active = True
            v.speed_xy_override = v.speed_up_override = v.speed_dn_override = None
        v.takeoff_alt = None  # a new destination ends a GUIDED takeoff, as in ArduCopter
        v.target = (n, e, d)
        v.vel_target = None
        self.set_leg(n, e)

    def alt_to_d(self, frame: int, alt: float) -> float:
        """Altitude of a command/mission item in ``frame`` to local down."""
        v = self.v
        if frame in GLOBAL_FRAMES_AMSL:
            return -(alt - v.origin[2])
        return -(alt + v.home[2] - v.origin[2])

    def control(self, dt: float) -> None:
        """Run the current flight mode's controller for one step."""
        v = self.v
        if not v.armed:
            if not v.landed:  # motors stopped in the air (forced disarm): fall
                v.kin.vn *= 0.98
                v.kin.ve *= 0.98
                v.kin.vd = min(v.kin.vd + 9.8 * dt, 15.0)
            return
        if v.landed and v.takeoff_alt is None:
            if v.mode in (LAND, RTL) or (v.mode == AUTO and (v.auto.landing or v.auto.returning)):
                if v.t - v.landed_since >= LAND_DETECT_S:
                    if v.mode == AUTO and not v.auto.complete:
                        v.auto.advance()
                    v.disarm("Land complete")
                return
            if v.mode == AUTO and not v.auto.complete and v.auto.ground_start():
                v.auto.step(self.limits(), dt, v.belief())
                if v.takeoff_alt is not None:
                    return
            if v.t - max(v.arm_time, v.landed_since) >= v.params["DISARM_DELAY"] > 0:
                v.disarm("Auto disarm")
            return
        lim = self.limits()
        k = v.kin
        b = v.belief()
        if v.takeoff_alt is not None:
            v.landed = False
            tn, te, _ = v.target
            k.position_step(tn, te, -v.takeoff_alt, lim, dt, b[0], b[1], b[2])
            if -b[2] >= v.takeoff_alt - TAKEOFF_DONE_M:
                v.target = (tn, te, -v.takeoff_alt)
                v.takeoff_alt = None
            return
        m = v.mode
        if m == GUIDED:
            if v.vel_target is not None:
                if v.t - v.vel_target_t > VEL_TIMEOUT_S:
                    v.vel_target = None
                    v.target = self.stopping_point()
                else:
                    vn, ve, vd = v.vel_target
                    k.step_velocity(vn, ve, vd, lim, dt)
                    return
            tn, te, td = v.target
            k.position_step(tn, te, td, lim, dt, b[0], b[1], b[2])
        elif m in (LOITER, POSHOLD):
            tn, te, td = v.target
            k.position_step(tn, te, td, lim, dt, b[0], b[1], b[2])
        elif m == BRAKE:
            tn, te, td = v.target
            blim = Limits(lim.speed_xy * 4, BRAKE_DECEL, lim.speed_up, lim.speed_dn, lim.accel_z)
            k.position_step(tn, te, td, blim, dt, b[0], b[1], b[2])
        elif m == LAND:
            self.land_step(lim, dt, b)
        elif m == RTL:
            self.rtl_step(lim, dt, b)
        elif m == AUTO:
            v.auto.step(lim, dt, b)
        elif m == ALT_HOLD:
            # no RC: sticks centred, altitude held, no position hold -> drifts with the air mass
            k.step_velocity(v.wind.north + v.gust[0], v.wind.east + v.gust[1], 0.0, lim, dt)
        else:  # STABILIZE / ACRO with no RC: throttle low -> sinks at 2.5 m/s, drifts with the air mass
            k.step_velocity(v.wind.north + v.gust[0], v.wind.east + v.gust[1], 2.5, lim, dt)

    def land_descent_speed(self, b: tuple[float, float, float]) -> float:
        """LAND_SPEED_HIGH above LAND_ALT_LOW, LAND_SPEED below."""
        v = self.v
        alt = -b[2]
        if alt > v.params["LAND_ALT_LOW"] / 100.0:
            high = v.params["LAND_SPEED_HIGH"]
            return high / 100.0 if high > 0 else self.limits().speed_dn
        return max(0.1, v.params["LAND_SPEED"] / 100.0)

    def land_step(self, lim: Limits, dt: float, b: tuple[float, float, float]) -> None:
        """Descend at the landing speed over the land target."""
        v = self.v
        ln, le = self.land_target
        llim = Limits(lim.speed_xy, lim.accel_xy, lim.speed_up, self.land_descent_speed(b), lim.accel_z)
        v.kin.position_step(ln, le, 1000.0, llim, dt, b[0], b[1], b[2])

    def start_rtl(self) -> None:
        """Return altitude: RTL_ALT (at least RTL_CLIMB_MIN up), capped by an altitude fence."""
        v = self.v
        b = v.belief()
        alt = -b[2]
        rtl_alt = v.params["RTL_ALT"] / 100.0
        target = max(rtl_alt, alt + v.params["RTL_CLIMB_MIN"] / 100.0) if rtl_alt > 0 else alt
        if v.fence.enabled() and int(v.params["FENCE_TYPE"]) & 1:
            target = min(target, v.params["FENCE_ALT_MAX"] - v.params["FENCE_MARGIN"])
        _hn, _he, hd = v.home_ned
        self.rtl_alt = target - hd  # relative to home -> above origin
        self.rtl_alt = max(self.rtl_alt, -hd + 2.0)
        self.rtl_state = RTL_CLIMB
        v.target = (b[0], b[1], -self.rtl_alt)
        v.leg = None

    def rtl_step(self, lim: Limits, dt: float, b: tuple[float, float, float]) -> None:
        """RTL: climb, return, loiter RTL_LOIT_TIME, then descend to RTL_ALT_FINAL or land."""
        v = self.v
        k = v.kin
        hn, he, hd = v.home_ned
        if self.rtl_state == RTL_CLIMB:
            tn, te, _ = v.target
            k.position_step(tn, te, -self.rtl_alt, lim, dt, b[0], b[1], b[2])
            if abs(-b[2] - self.rtl_alt) < 0.5:
                self.rtl_state = RTL_RETURN
                v.target = (hn, he, -self.rtl_alt)
                self.set_leg(hn, he)
        elif self.rtl_state == RTL_RETURN:
            k.position_step(hn, he, -self.rtl_alt, lim, dt, b[0], b[1], b[2])
            if (
                math.hypot(hn - b[0], he - b[1]) < max(0.5, v.params["WPNAV_RADIUS"] / 100.0 * 0.25)
                and math.hypot(k.vn, k.ve) < 0.5
            ):
                self.rtl_state = RTL_LOITER
                self.rtl_loiter_until = v.t + v.params["RTL_LOIT_TIME"] / 1000.0
                v.leg = None
        elif self.rtl_state == RTL_LOITER:
            k.position_step(hn, he, -self.rtl_alt, lim, dt, b[0], b[1], b[2])
            if v.t >= self.rtl_loiter_until:
                final = v.params["RTL_ALT_FINAL"] / 100.0
                self.rtl_state = RTL_DESCEND if final > 0 else RTL_FINAL
                self.land_target = (hn, he)
        elif self.rtl_state == RTL_DESCEND:
            final = v.params["RTL_ALT_FINAL"] / 100.0
            k.position_step(hn, he, hd - final, lim, dt, b[0], b[1], b[2])
        else:
            self.land_step(lim, dt, b)
