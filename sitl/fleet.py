"""A fleet of simulated copters run by one background thread (fixed-step physics + one selector loop).

One thread for all vehicles keeps the cost low (no per-vehicle threads or context switches): each
loop iteration advances every vehicle by as many fixed physics steps as the speed-up calls for, sends
the telemetry that became due (in sim time), then waits on the sockets until the next step is due.

    with SimFleet(FleetConfig(vehicles=3, base_port=0, speedup=10)) as fleet:
        print(fleet.endpoints)   # ["tcp:127.0.0.1:40123", ...]
"""

from __future__ import annotations

import contextlib
import logging
import math
import selectors
import threading
import time
from dataclasses import dataclass, field
from types import TracebackType

from sitl.failures import parse_failures
from sitl.mavlink_link import Endpoint
from sitl.physics import local_to_latlon
from sitl.px4 import Px4Vehicle
from sitl.px4_params import PX4_DEFAULTS
from sitl.vehicle import SEV_WARNING, SimVehicle

log = logging.getLogger("sitl")
OVERRUN_REPORT_S = 5.0  # at most one log line / STATUSTEXT about falling behind per this many wall s

# ArduPilot's default SITL location (Canberra model flying club, "CMAC").
DEFAULT_HOME = (-35.363262, 149.165237, 584.0)
# PX4 SITL's (SIH) default home, Zurich.
PX4_HOME = (47.397742, 8.545594, 489.4)
FLAVOURS = ("ardupilot", "px4")
# PX4 instance i's API link: it sends to PX4_BASE_PORT + i and listens on that + PX4_LOCAL_OFFSET.
PX4_BASE_PORT = 14540
PX4_LOCAL_OFFSET = 40


@dataclass
class FleetConfig:
    """Everything that defines a simulated fleet. ``speedup`` <= 0 or inf runs as fast as possible."""

    vehicles: int = 1
    home: tuple[float, ...] = DEFAULT_HOME
    base_port: int = 5760
    speedup: float = 1.0
    seed: int = 0
    transport: str = "tcp"
    spacing_m: float = 5.0
    prearm_delay_s: float = 3.0
    gps_boot_s: float | None = None  # no fix/position/home before this (None: = prearm_delay_s)
    legacy_mission_request: bool = False
    wind: tuple[float, float] = (0.0, 0.0)
    gust_mps: float = 0.0
    host: str = "127.0.0.1"
    physics_hz: float = 50.0
    params: dict[str, float] = field(default_factory=dict)
    failures: list[str] = field(default_factory=list)
    # "ardupilot" (ArduCopter) or "px4" (PX4 v1.16: sitl/px4.py). PX4 links are always UDP laid out
    # as PX4 SITL's API link (``transport`` is ignored): vehicle i sends to base_port + i (a client
    # binds it: udpin) and listens on base_port + 40 + i; base_port 0 = an ephemeral listening port
    # and no remote until the client speaks (udpout). ``params`` then holds PX4 names.
    flavour: str = "ardupilot"
    # A second MAVLink link per vehicle for a pilot's ground station (ArduPilot SITL's SERIAL1: TCP
    # base_port + 10*i + 2, ephemeral with base_port 0; PX4: UDP, the client speaks first). What
    # it sends counts as a pilot's: a mode set there is a pilot's mode switch (docs/simulator.md).
    pilot_links: bool = False

    def validate(self) -> None:
        """Raise ValueError for settings the simulator cannot honour."""
        if not 1 <= self.vehicles <= 250:
            raise ValueError("vehicles must be 1..250 (system ids 1..250)")
        if len(self.home) not in (2, 3):
            raise ValueError("home must be (lat, lon) or (lat, lon, alt_amsl)")
        if self.transport not in ("tcp", "udp"):
            raise ValueError("transport must be 'tcp' or 'udp'")
        if self.physics_hz <= 0:
            raise ValueError("physics_hz must be positive")
        if self.flavour not in FLAVOURS:
            raise ValueError(f"flavour must be one of {', '.join(FLAVOURS)}, not {self.flavour!r}")
        if self.flavour == "px4":
            unknown = sorted(k for k in self.params if k.upper() not in PX4_DEFAULTS)
            if unknown:
                raise ValueError(f"unknown PX4 parameter(s): {', '.join(unknown)}")
            if self.base_port and self.vehicles > PX4_LOCAL_OFFSET:
                raise ValueError(f"px4 flavour: at most {PX4_LOCAL_OFFSET} vehicles with a fixed base port")
            if self.base_port and self.base_port + PX4_LOCAL_OFFSET + self.vehicles - 1 > 65535:
                raise ValueError("base_port + 40 + vehicles - 1 exceeds 65535")
        elif self.base_port and self.base_port + 10 * (self.vehicles - 1) > 65535:
            raise ValueError("base_port + 10*(vehicles-1) exceeds 65535")


class SimFleet:
    """N simulated copters (ArduCopter or PX4 personality), each a MAVLink 2 endpoint on loopback."""

    def __init__(self, cfg: FleetConfig | None = None) -> None:
        self.cfg = cfg = cfg if cfg is not None else FleetConfig()
        cfg.validate()
        self.lock = threading.RLock()
        lat, lon = cfg.home[0], cfg.home[1]
        alt = cfg.home[2] if len(cfg.home) > 2 else 0.0
        self._vehicles: list[SimVehicle] = []
        vehicle_cls = Px4Vehicle if cfg.flavour == "px4" else SimVehicle
        for i in range(cfg.vehicles):
            vlat, vlon = local_to_latlon(lat, lon, 0.0, i * cfg.spacing_m)
            self._vehicles.append(
                vehicle_cls(
                    i,
                    (vlat, vlon, alt),
                    seed=cfg.seed,
                    prearm_delay_s=cfg.prearm_delay_s,
                    gps_boot_s=cfg.gps_boot_s,
                    legacy_mission_request=cfg.legacy_mission_request,
                    wind=cfg.wind,
                    gust_mps=cfg.gust_mps,
                    params=cfg.params,
                    lock=self.lock,
                )
            )
        for idx, failure in parse_failures(cfg.failures, cfg.vehicles):
            self._vehicles[idx].schedule(failure)
        self.dt = 1.0 / cfg.physics_hz
        self._endpoints: list[Endpoint] = []  # each vehicle's own link (SERIAL0)
        self._pilot_endpoints: list[Endpoint] = []  # cfg.pilot_links: a second link each
        self._all: list[Endpoint] = []
        self._sel: selectors.BaseSelector | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._steps = 0
        self._paused = False
        self._pause_at: float | None = None
        self._paused_evt = threading.Event()
        self._anchor: tuple[float, float] = (0.0, 0.0)
        self.cpu_time_s = 0.0  # CPU time used by the simulation thread
        # Falling behind: when the host cannot step fast enough for the speed-up, the backlog is
        # dropped (sim time runs slower than wall x speed-up). Counted, logged and told to the GCS.
        self.overruns = 0
        self.dropped_sim_s = 0.0
        self._overrun_reported = -math.inf
        self._anchor_wall0 = 0.0
        self.wall_time_s = 0.0  # wall time the simulation thread has been running

    # ------------------------------------------------------------------ public API
    @property
    def endpoints(self) -> list[str]:
        """pymavlink connection strings, one per vehicle (index order)."""
        return [ep.url for ep in self._endpoints]

    @property
    def ports(self) -> list[int]:
        """Bound port of each vehicle."""
        return [ep.port for ep in self._endpoints]

    @property
    def pilot_endpoints(self) -> list[str]:
        """pymavlink connection strings of the pilots' links (``pilot_links``), one per vehicle."""
        return [ep.url for ep in self._pilot_endpoints]

    @property
    def vehicles(self) -> list[SimVehicle]:
        """All vehicles, index order."""
        return list(self._vehicles)

    def vehicle(self, i: int) -> SimVehicle:
        """Vehicle ``i`` (0-based; its system id is i + 1)."""
        return self._vehicles[i]

    @property
    def sim_time(self) -> float:
        """Seconds of simulated time since boot."""
        return self._steps * self.dt

    def start(self) -> SimFleet:
        """Bind every endpoint, then run the simulation in a daemon thread; returns once all listen."""
        if self._thread is not None:
            raise RuntimeError("fleet already started")
        try:
            for i, v in enumerate(self._vehicles):
                self._endpoints.append(self._endpoint(i, v))
                self._all.append(self._endpoints[-1])
                if self.cfg.pilot_links:
                    self._pilot_endpoints.append(self._pilot_endpoint(i, v))
                    self._all.append(self._pilot_endpoints[-1])
        except OSError:
            for ep in self._all:
                ep.close()
            self._endpoints.clear()
            self._pilot_endpoints.clear()
            self._all.clear()
            raise
        sel = selectors.DefaultSelector()
        for ep in self._all:
            if ep.listener is not None:
                sel.register(ep.listener, selectors.EVENT_READ, (ep, "accept"))
            elif ep.conn is not None:
                sel.register(ep.conn, selectors.EVENT_READ, (ep, "read"))
        self._sel = sel
        self._thread = threading.Thread(target=self._run_guarded, name="sitl-fleet", daemon=True)
        self._thread.start()
        if not self._ready.wait(10.0):
            raise RuntimeError("simulation thread did not start")
        if self._error is not None:
            raise RuntimeError("simulation thread failed") from self._error
        return self

    def _endpoint(self, i: int, v: SimVehicle) -> Endpoint:
        cfg = self.cfg
        if cfg.flavour == "px4":
            if not cfg.base_port:
                return Endpoint(v, "udp", cfg.host, 0, self.dt)
            local = cfg.base_port + PX4_LOCAL_OFFSET + i
            return Endpoint(v, "udp", cfg.host, local, self.dt, remote=(cfg.host, cfg.base_port + i))
        port = cfg.base_port + 10 * i if cfg.base_port else 0
        return Endpoint(v, cfg.transport, cfg.host, port, self.dt)

    def _pilot_endpoint(self, i: int, v: SimVehicle) -> Endpoint:
        cfg = self.cfg
        if cfg.flavour == "px4" or cfg.transport == "udp":
            return Endpoint(v, "udp", cfg.host, 0, self.dt, name="pilot")
        port = cfg.base_port + 10 * i + 2 if cfg.base_port else 0
        return Endpoint(v, "tcp", cfg.host, port, self.dt, name="pilot")

    def stop(self) -> None:
        """Stop the simulation thread and close every socket (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        for ep in self._all:
            ep.close()
        if self._sel is not None:
            self._sel.close()
            self._sel = None

    def __enter__(self) -> SimFleet:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        """True while the simulation thread is alive."""
        return self._thread is not None and self._thread.is_alive()

    @property
    def error(self) -> BaseException | None:
        """The exception that stopped the simulation thread, if any."""
        return self._error

    def pause(self) -> None:
        """Freeze sim time now (messages are still received and answered)."""
        with self.lock:
            self._paused = True
            self._paused_evt.set()

    def pause_at(self, sim_t: float) -> None:
        """Freeze sim time exactly when it reaches ``sim_t`` (for deterministic scripted tests)."""
        with self.lock:
            self._pause_at = sim_t
            self._paused_evt.clear()

    def resume(self) -> None:
        """Let sim time run again."""
        with self.lock:
            self._paused = False
            self._paused_evt.clear()
            self._anchor = (time.monotonic(), self.sim_time)

    @property
    def paused(self) -> bool:
        """True while sim time is frozen."""
        return self._paused

    def wait_paused(self, timeout: float) -> bool:
        """Block until the fleet pauses (after :meth:`pause_at`); False on timeout."""
        return self._paused_evt.wait(timeout)

    def wait_sim_time(self, sim_t: float, timeout: float) -> bool:
        """Block until sim time reaches ``sim_t`` (polling, bounded by ``timeout`` wall seconds)."""
        deadline = time.monotonic() + timeout
        while self.sim_time < sim_t:
            if time.monotonic() > deadline or not self.running:
                return False
            time.sleep(0.002)
        return True

    # ------------------------------------------------------------------ the loop
    def _run_guarded(self) -> None:
        try:
            self._run()
        except BaseException as exc:  # surfaced through .error / start()
            self._error = exc
            self._ready.set()
            raise

    def _run(self) -> None:
        cfg = self.cfg
        dt = self.dt
        unlimited = cfg.speedup <= 0 or math.isinf(cfg.speedup)
        speedup = 1.0 if unlimited else cfg.speedup
        max_batch = 200
        sel = self._sel
        assert sel is not None
        vehicles = self._vehicles
        endpoints = self._all
        wall0 = time.monotonic()
        self._anchor_wall0 = wall0
        cpu0 = time.thread_time()
        self._anchor = (wall0, 0.0)
        self._ready.set()
        while not self._stop.is_set():
            now = time.monotonic()
            steps = 0
            with self.lock:
                if self._paused:
                    target = -1.0
                elif unlimited:
                    target = (self._steps + 10) * dt
                else:
                    aw, asim = self._anchor
                    target = asim + (now - aw) * speedup
                while (self._steps + 1) * dt <= target + 1e-9 and steps < max_batch:
                    if self._pause_at is not None and (self._steps + 1) * dt > self._pause_at + 1e-9:
                        self._pause_at = None
                        self._paused = True
                        self._paused_evt.set()
                        break
                    for v in vehicles:
                        v.step(dt)
                    self._steps += 1
                    t = self._steps * dt
                    for ep in endpoints:
                        ep.pump(t)
                    steps += 1
                if not unlimited and not self._paused and target - self.sim_time > 0.25 * speedup:
                    self._overrun(target - self.sim_time, now, speedup)
                    self._anchor = (now, self.sim_time)  # cannot keep up: drop the backlog
                for ep in endpoints:
                    ep.tick(now)
                self._flush_all(sel)
            if self._paused:
                timeout = 0.02
            elif unlimited:
                timeout = 0.0
            else:
                aw, asim = self._anchor
                due = aw + ((self._steps + 1) * dt - asim) / speedup
                timeout = max(0.0, min(0.05, due - time.monotonic()))
            events = sel.select(timeout)
            if events:
                wall = time.monotonic()
                with self.lock:
                    for key, mask in events:
                        ep, kind = key.data
                        if kind == "accept":
                            self._accept(sel, ep)
                        elif mask & selectors.EVENT_READ and ep.conn is not None and not ep.read(wall):
                            self._drop_client(sel, ep)
                    self._flush_all(sel)
            self.cpu_time_s = time.thread_time() - cpu0
            self.wall_time_s = time.monotonic() - wall0

    def _overrun(self, behind_s: float, now: float, speedup: float) -> None:
        """Count a dropped backlog; say so (log line, STATUSTEXT) at most every OVERRUN_REPORT_S."""
        self.overruns += 1
        self.dropped_sim_s += behind_s
        if now - self._overrun_reported < OVERRUN_REPORT_S:
            return
        self._overrun_reported = now
        kept = self.sim_time / max(now - self._anchor_wall0, 1e-9)
        log.warning(
            "simulator behind: %.2f sim s dropped (%d times, %.1f s in all); speed-up %.2fx of %.2fx",
            behind_s,
            self.overruns,
            self.dropped_sim_s,
            kept,
            speedup,
        )
        for v in self._vehicles:
            v.statustext(SEV_WARNING, f"SIM: speedup not kept, {self.dropped_sim_s:.1f}s lost")

    @property
    def speedup_kept(self) -> float:
        """Sim seconds per wall second since start (the speed-up actually achieved)."""
        return self.sim_time / max(self.wall_time_s, 1e-9)

    def _accept(self, sel: selectors.BaseSelector, ep: Endpoint) -> None:
        try:
            old = ep.accept()
        except OSError:
            return
        if old is not None:
            with contextlib.suppress(KeyError, ValueError):
                sel.unregister(old)
            with contextlib.suppress(OSError):
                old.close()
        assert ep.conn is not None
        sel.register(ep.conn, selectors.EVENT_READ, (ep, "read"))
        ep.want_write = False

    def _drop_client(self, sel: selectors.BaseSelector, ep: Endpoint) -> None:
        if ep.conn is not None:
            with contextlib.suppress(KeyError, ValueError):
                sel.unregister(ep.conn)
        ep.close_client()
        ep.want_write = False

    def _flush_all(self, sel: selectors.BaseSelector) -> None:
        for ep in self._all:
            if not ep.outbuf:
                continue
            conn = ep.conn
            pending = ep.flush()
            if ep.conn is None:  # send failed: client gone
                if conn is not None:
                    with contextlib.suppress(KeyError, ValueError):
                        sel.unregister(conn)
                ep.want_write = False
                continue
            if pending != ep.want_write:
                ep.want_write = pending
                events = selectors.EVENT_READ | (selectors.EVENT_WRITE if pending else 0)
                sel.modify(ep.conn, events, (ep, "read"))
