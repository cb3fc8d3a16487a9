"""Pure models of the simulated copter: kinematics, position controller, wind, GPS, path error, battery.

Nothing here knows about MAVLink or sockets, so the models can be unit-tested and reused (e.g. by an
energy model fitted offline). Units are SI throughout (metres, seconds, m/s, watts, joules); the local
frame is NED in metres relative to the vehicle's EKF origin (its boot position), ``d`` positive down.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass

from protocol.geo import ARDUPILOT_EARTH_RADIUS_M, ned_offset_m, offset_latlon

GRAVITY = 9.80665

# Seed 000 eq. 9: path error (m) = a*sin(v - pi) + b*(v - 10)^2 + c, v in m/s.
PATH_ERR_A = 0.1356
PATH_ERR_B = -0.008092
PATH_ERR_C = 1.051


def path_error_m(speed_mps: float) -> float:
    """Seed 000 eq. 9: expected deviation (m) of the flown path from the planned line at ``speed_mps``.

    Clamped at 0 because the quadratic term goes negative far outside the fitted 0..10 m/s range.
    """
    v = speed_mps
    return max(0.0, PATH_ERR_A * math.sin(v - math.pi) + PATH_ERR_B * (v - 10.0) ** 2 + PATH_ERR_C)


def local_to_latlon(lat0: float, lon0: float, north: float, east: float) -> tuple[float, float]:
    """Flat-earth offset from an origin with ArduPilot's radius, as ArduPilot does over short ranges
    (``protocol.geo.offset_latlon``), so local offsets match a real ArduCopter's for the same lat/lon."""
    return offset_latlon(lat0, lon0, north, east, ARDUPILOT_EARTH_RADIUS_M)


def latlon_to_local(lat0: float, lon0: float, lat: float, lon: float) -> tuple[float, float]:
    """Inverse of :func:`local_to_latlon`: north/east metres of ``lat``/``lon`` from the origin."""
    return ned_offset_m(lat0, lon0, lat, lon, ARDUPILOT_EARTH_RADIUS_M)


def sqrt_controller(error: float, kp: float, accel: float) -> float:
    """ArduPilot's sqrt controller: speed to command for a distance ``error`` so we can stop at ``accel``.

    Linear (``kp*error``) close to the target, ``sqrt(2*a*d)``-shaped further out: this is what makes a
    copter decelerate smoothly into a waypoint instead of overshooting it (seed 001 section 7.1).
    """
    if error <= 0.0:
        return 0.0
    linear_dist = accel / (kp * kp)
    if error > linear_dist:
        return math.sqrt(2.0 * accel * (error - linear_dist / 2.0))
    return kp * error


@dataclass(slots=True)
class Limits:
    """Controller limits, from WPNAV_* parameters converted to SI."""

    speed_xy: float = 5.0  # m/s  (WPNAV_SPEED)
    accel_xy: float = 2.5  # m/s^2 (WPNAV_ACCEL)
    speed_up: float = 2.5  # m/s  (WPNAV_SPEED_UP)
    speed_dn: float = 1.5  # m/s  (WPNAV_SPEED_DN)
    accel_z: float = 1.0  # m/s^2 (WPNAV_ACCEL_Z)
    kp_xy: float = 1.0  # 1/s (PSC_POSXY_P)
    kp_z: float = 1.0  # 1/s (PSC_POSZ_P)


@dataclass(slots=True)
class Kinematics:
    """Point-mass state: controller-believed position (NED m) and commanded ground velocity (m/s)."""

    n: float = 0.0
    e: float = 0.0
    d: float = 0.0
    vn: float = 0.0
    ve: float = 0.0
    vd: float = 0.0
    an: float = 0.0  # last horizontal acceleration, for the attitude report
    ae: float = 0.0

    def step_velocity(self, want_vn: float, want_ve: float, want_vd: float, lim: Limits, dt: float) -> None:
        """Move the velocity toward a wanted velocity with the acceleration limits (jerk ignored)."""
        dvn, dve = want_vn - self.vn, want_ve - self.ve
        dv = math.hypot(dvn, dve)
        max_dv = lim.accel_xy * dt
        if dv > max_dv:
            scale = max_dv / dv
            dvn, dve = dvn * scale, dve * scale
        self.an, self.ae = dvn / dt, dve / dt
        self.vn += dvn
        self.ve += dve
        dvd = want_vd - self.vd
        max_dz = lim.accel_z * dt
        self.vd += max(-max_dz, min(max_dz, dvd))

    def position_step(
        self,
        tn: float,
        te: float,
        td: float,
        lim: Limits,
        dt: float,
        pos_n: float | None = None,
        pos_e: float | None = None,
        pos_d: float | None = None,
    ) -> None:
        """One step of the position controller toward target ``(tn, te, td)``.

        The wanted velocity comes from the sqrt controller on the distance left, capped at the speed
        limit, so the copter accelerates, cruises and decelerates into the target. ``pos_*`` is the
        position the controller believes (GPS-noisy); it defaults to the kinematic position.
        """
        pn = self.n if pos_n is None else pos_n
        pe = self.e if pos_e is None else pos_e
        pd = self.d if pos_d is None else pos_d
        en, ee = tn - pn, te - pe
        dist = math.hypot(en, ee)
        if dist > 1e-6:
            speed = min(lim.speed_xy, sqrt_controller(dist, lim.kp_xy, lim.accel_xy))
            wvn, wve = en / dist * speed, ee / dist * speed
        else:
            wvn = wve = 0.0
        ed = td - pd
        if ed > 0:  # target below: descend
            wvd = min(lim.speed_dn, sqrt_controller(ed, lim.kp_z, lim.accel_z))
        else:
            wvd = -min(lim.speed_up, sqrt_controller(-ed, lim.kp_z, lim.accel_z))
        self.step_velocity(wvn, wve, wvd, lim, dt)

    def integrate(self, dt: float, drift_n: float = 0.0, drift_e: float = 0.0) -> None:
        """Advance the position with the commanded velocity plus the uncorrected wind drift."""
        self.n += (self.vn + drift_n) * dt
        self.e += (self.ve + drift_e) * dt
        self.d += self.vd * dt


class OrnsteinUhlenbeck:
    """Seeded first-order Gauss-Markov process: correlated noise for gusts and GPS error."""

    __slots__ = ("_k", "rng", "sigma", "tau", "x")

    def __init__(self, rng: random.Random, sigma: float, tau: float) -> None:
        self.rng = rng
        self.sigma = sigma
        self.tau = tau
        self.x = 0.0
        self._k = (0.0, 0.0)

    def step(self, dt: float) -> float:
        """Advance by ``dt``; exact discretisation so the statistics do not depend on the step size."""
        if self.sigma <= 0.0:
            self.x = 0.0
            return 0.0
        if self._k[0] != dt:
            phi = math.exp(-dt / self.tau)
            self._k = (dt, phi)
        phi = self._k[1]
        self.x = phi * self.x + self.sigma * math.sqrt(1.0 - phi * phi) * self.rng.gauss(0.0, 1.0)
        return self.x


class Wind:
    """Steady wind vector plus seeded gusts (one OU process per horizontal axis, tau 3 s)."""

    def __init__(self, rng: random.Random, north: float = 0.0, east: float = 0.0, gust: float = 0.0) -> None:
        self.north = north
        self.east = east
        self.gust_n = OrnsteinUhlenbeck(rng, gust, 3.0)
        self.gust_e = OrnsteinUhlenbeck(rng, gust, 3.0)

    def set_gust(self, gust: float) -> None:
        """Change the gust standard deviation (m/s)."""
        self.gust_n.sigma = gust
        self.gust_e.sigma = gust

    def step(self, dt: float) -> tuple[float, float]:
        """Wind (north, east) in m/s at the next step."""
        return self.north + self.gust_n.step(dt), self.east + self.gust_e.step(dt)


class GpsError:
    """GPS position error: slow correlated wander (sigma 0.3 m horizontal, 0.5 m vertical, tau 30 s).

    Seed 001 section 7: short-term GPS variation is below 1 m with an open sky, which this matches.
    """

    def __init__(self, rng: random.Random, sigma_h: float = 0.3, sigma_v: float = 0.5) -> None:
        self.n = OrnsteinUhlenbeck(rng, sigma_h, 30.0)
        self.e = OrnsteinUhlenbeck(rng, sigma_h, 30.0)
        self.d = OrnsteinUhlenbeck(rng, sigma_v, 30.0)

    def step(self, dt: float) -> tuple[float, float, float]:
        """The error (north, east, down) in metres at the next step."""
        return self.n.step(dt), self.e.step(dt), self.d.step(dt)


class PathWobble:
    """Cross-track deviation of the flown path whose amplitude follows seed 000 eq. 9.

    The offset is perpendicular to the direction of travel, oscillates with distance flown (wavelength
    ``wavelength_m``) and is low-passed so turns do not make it jump. Its amplitude is eq. 9 at the
    current ground speed, faded in below ``fade_speed`` so a hovering copter does not wobble. The
    position controller does not see it: it stands for regulator/mechanical imprecision.
    """

    def __init__(self, phase: float, wavelength_m: float = 40.0, fade_speed: float = 1.0) -> None:
        self.phase = phase
        self.wavelength_m = wavelength_m
        self.fade_speed = fade_speed
        self.on = 0.0
        self.oe = 0.0

    def step(self, vn: float, ve: float, dt: float) -> tuple[float, float]:
        """Advance with the horizontal ground velocity; returns the (north, east) offset in metres."""
        speed = math.hypot(vn, ve)
        self.phase += 2.0 * math.pi * speed * dt / self.wavelength_m
        if speed > 1e-3:
            amp = path_error_m(speed) * min(1.0, speed / self.fade_speed) * math.sin(self.phase)
            tn, te = -ve / speed * amp, vn / speed * amp
        else:
            tn = te = 0.0
        k = min(1.0, dt / 0.5)
        self.on += (tn - self.on) * k
        self.oe += (te - self.oe) * k
        return self.on, self.oe


@dataclass(slots=True)
class PowerModel:
    """Electrical power drawn by the simulated copter (documented in docs/simulator.md).

    P = P_hover + k2*v_air^2 + k3*v_air^3 + m*g*max(climb, 0)/eta_climb - r_desc*m*g*max(-climb, 0),
    floored at ``min_fraction*P_hover`` while flying; ``p_spin`` when armed on the ground and
    ``p_avionics`` when disarmed. ``v_air`` is the speed relative to the air mass (wind matters).
    """

    p_hover: float = 180.0  # W
    k2: float = 0.5  # W/(m/s)^2
    k3: float = 0.05  # W/(m/s)^3
    mass_kg: float = 1.5
    eta_climb: float = 0.6
    r_desc: float = 0.3
    min_fraction: float = 0.6
    p_spin: float = 30.0
    p_avionics: float = 2.0

    def power_w(self, flying: bool, armed: bool, v_air: float, climb: float) -> float:
        """Electrical power (W) for the given state."""
        if not armed:
            return self.p_avionics
        if not flying:
            return self.p_spin
        mg = self.mass_kg * GRAVITY
        p = self.p_hover + self.k2 * v_air * v_air + self.k3 * v_air**3
        if climb > 0:
            p += mg * climb / self.eta_climb
        else:
            p += self.r_desc * mg * climb
        return max(p, self.min_fraction * self.p_hover)


class Battery:
    """LiPo pack: linear open-circuit voltage in state of charge plus internal-resistance sag.

    V_oc = cells*(v_empty + (v_full - v_empty)*soc); V = V_oc - I*R; I solves P = V*I.
    """

    def __init__(self, capacity_mah: float = 5000.0, cells: int = 3, r_int: float = 0.05) -> None:
        self.capacity_mah = capacity_mah
        self.cells = cells
        self.r_int = r_int
        self.v_full = 4.2
        self.v_empty = 3.5
        self.consumed_mah = 0.0
        self.energy_j = 0.0
        self.current_a = 0.0
        self.voltage_v = self.ocv()

    @property
    def soc(self) -> float:
        """State of charge 0..1."""
        return max(0.0, 1.0 - self.consumed_mah / self.capacity_mah)

    @property
    def remaining_pct(self) -> float:
        """Remaining charge in percent."""
        return 100.0 * self.soc

    def ocv(self) -> float:
        """Open-circuit pack voltage at the current charge."""
        return self.cells * (self.v_empty + (self.v_full - self.v_empty) * self.soc)

    def set_pct(self, pct: float) -> None:
        """Set the remaining charge (failure injection / tests)."""
        pct = max(0.0, min(100.0, pct))
        self.consumed_mah = (1.0 - pct / 100.0) * self.capacity_mah
        self.voltage_v = self.ocv()

    def draw(self, power_w: float, dt: float) -> None:
        """Draw ``power_w`` for ``dt`` seconds: updates current, voltage, charge and energy."""
        v_oc = self.ocv()
        disc = v_oc * v_oc - 4.0 * self.r_int * power_w
        current = (v_oc - math.sqrt(disc)) / (2.0 * self.r_int) if disc > 0 else v_oc / (2.0 * self.r_int)
        self.current_a = current
        self.voltage_v = v_oc - current * self.r_int
        self.consumed_mah += current * dt / 3.6
        self.energy_j += power_w * dt
