"""An in-process vehicle behind the Autopilot contract, for daemon load tests and protocol tests.

Point-mass kinematics (speed and climb limits, no wind), a linear battery, instant GPS fix.
It is not a simulator of ArduCopter: the MAVLink simulator in ``sitl`` is. Its value is being
cheap enough to run hundreds of agents in one process.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time

from agent.autopilot.base import Autopilot, CommandRefused, FenceSpec, Telemetry
from protocol.geo import ned_offset_m, offset_latlon


class MemoryAutopilot(Autopilot):
    def __init__(
        self,
        home: tuple[float, float, float] = (47.397742, 8.545594, 488.0),
        *,
        speed_mps: float = 5.0,
        climb_mps: float = 2.5,
        speedup: float = 1.0,
        step_s: float = 0.05,
        battery_drain_pct_per_s: float = 0.05,
    ) -> None:
        self.speedup = speedup
        self.step_s = step_s
        self.cruise_mps = speed_mps
        self.climb_mps = climb_mps
        self.drain = battery_drain_pct_per_s
        self._t = Telemetry(
            lat=home[0],
            lon=home[1],
            alt_rel=0.0,
            alt_amsl=home[2],
            mode="STABILIZE",
            gps_fix=3,
            satellites=12,
            position_known=True,
            home_lat=home[0],
            home_lon=home[1],
            home_alt_amsl=home[2],
            battery_pct=100.0,
            voltage_v=16.8,
        )
        self._target: tuple[float, float, float] | None = None
        self._landing = False
        self._task: asyncio.Task[None] | None = None
        self.fence: FenceSpec | None = None
        self.refuse_arming = False
        self.rtl_alt_m = 15.0  # ArduCopter's RTL_ALT default

    async def connect(self, timeout: float = 30.0) -> None:
        self._task = asyncio.create_task(self._run(), name="memory-autopilot")

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None

    def telemetry(self) -> Telemetry:
        return self._t

    async def arm(self, deadline_s: float = 60.0) -> None:
        if self.refuse_arming:
            raise CommandRefused("arm", "PreArm: refused by test setting")
        self._t.mode = "GUIDED"
        self._t.armed = True

    async def disarm(self) -> None:
        if not self._t.landed:
            raise CommandRefused("disarm", "vehicle is flying")
        self._t.armed = False

    async def takeoff(self, alt_rel_m: float) -> None:
        if not self._t.armed or not self._t.landed or self._t.mode != "GUIDED":
            raise CommandRefused("takeoff", "needs armed, landed, GUIDED")
        self._t.landed = False
        self._landing = False
        self._target = (self._t.lat, self._t.lon, alt_rel_m)

    async def goto(self, lat: float, lon: float, alt_rel_m: float, speed_mps: float | None = None) -> None:
        self._require_flying("goto")
        if speed_mps:
            self.cruise_mps = speed_mps
        self._t.mode = "GUIDED"
        self._target = (lat, lon, alt_rel_m)

    async def land(self, lat: float | None = None, lon: float | None = None) -> None:
        self._require_flying("land")
        self._t.mode = "LAND"
        if lat is not None and lon is not None:
            self._target = (lat, lon, self._t.alt_rel)
        else:
            self._target = None
        self._landing = True

    async def return_to_launch(self, alt_rel_m: float | None = None) -> None:
        self._require_flying("rtl")
        self._t.mode = "RTL"
        assert self._t.home_lat is not None and self._t.home_lon is not None
        if alt_rel_m is not None:
            self.rtl_alt_m = alt_rel_m
        # Like ArduCopter: return at the RTL altitude, or higher if already higher.
        self._target = (self._t.home_lat, self._t.home_lon, max(self._t.alt_rel, self.rtl_alt_m))
        self._landing = False

    async def hold(self) -> None:
        self._t.mode = "BRAKE"
        self._target = (self._t.lat, self._t.lon, self._t.alt_rel)
        self._landing = False

    async def set_speed(self, speed_mps: float) -> None:
        self.cruise_mps = speed_mps

    async def upload_fence(self, fence: FenceSpec) -> bool:
        self.fence = fence
        return True

    def _require_flying(self, command: str) -> None:
        if not self._t.armed or self._t.landed:
            raise CommandRefused(command, "vehicle is not flying")

    async def _run(self) -> None:
        last = time.monotonic()
        while True:
            await asyncio.sleep(self.step_s)
            now = time.monotonic()
            self._advance((now - last) * self.speedup)
            self._t.last_heartbeat_monotonic = now
            last = now

    def _advance(self, dt: float) -> None:
        t = self._t
        if t.armed and t.battery_pct is not None:
            t.battery_pct = max(0.0, t.battery_pct - self.drain * dt)
            t.voltage_v = 13.2 + 3.6 * t.battery_pct / 100.0
        t.vn = t.ve = t.vd = 0.0
        if t.landed:
            return
        if t.mode == "RTL" and self._target is not None:
            north, east = ned_offset_m(t.lat, t.lon, self._target[0], self._target[1])
            if math.hypot(north, east) < 0.5:
                self._landing = True
                self._target = None
        if self._target is not None:
            north, east = ned_offset_m(t.lat, t.lon, self._target[0], self._target[1])
            dist = math.hypot(north, east)
            move = min(dist, self.cruise_mps * dt)
            if dist > 1e-6:
                t.lat, t.lon = offset_latlon(t.lat, t.lon, north * move / dist, east * move / dist)
                t.vn, t.ve = north / dist * self.cruise_mps, east / dist * self.cruise_mps
                t.heading_deg = math.degrees(math.atan2(east, north)) % 360.0
            if not self._landing:
                # A land at a position flies there at its altitude, then descends: the target's
                # altitude must not pull it back up (that held it at the land point for good).
                dz = self._target[2] - t.alt_rel
                climb = max(-self.climb_mps * dt, min(self.climb_mps * dt, dz))
                t.alt_rel += climb
                t.vd = -climb / dt if dt > 0 else 0.0
        if self._landing and (self._target is None or (t.vn == 0.0 and t.ve == 0.0)):
            t.alt_rel = max(0.0, t.alt_rel - self.climb_mps * dt)
            t.vd = self.climb_mps
            if t.alt_rel <= 0.0:
                t.landed, t.armed, t.vd, self._landing = True, False, 0.0, False
                t.mode = "LAND" if t.mode != "RTL" else "RTL"
        if t.home_alt_amsl is not None:
            t.alt_amsl = t.home_alt_amsl + t.alt_rel
