"""Daemon + in-process agents on real PX4 SITL (SIH), on either agent backend: pymavlink or MAVSDK.

One PX4 boot (3 quadcopters, homes 10 m apart) serves a test module per backend. The agents listen on
PX4's API links (``udpin:127.0.0.1:14540+i``) behind a :class:`tests.faults.proxy.FaultProxy` (to cut
the daemon link); an :class:`Observer` per vehicle watches PX4's GCS link in PX4's own clock.

Instance ids: each backend has its own block (mavlink 0-2, mavsdk 3-5; ``FLEETGCS_PX4_BLOCK=2`` gives
6-8 to a run beside the suite; PX4 sends the API link of every instance from 10 on to one port), and a
second process asking for a block (another checkout) waits for it (file lock) instead of colliding.
PX4 runs ``SPEED`` times faster than the wall clock
(``PX4_SIM_SPEED_FACTOR``; override with ``$FLEETGCS_PX4_SPEED``). PX4 runs in lockstep: a starved
machine slows PX4's clock instead of dropping physics, so every check reads PX4's own clock and the
rig reports the speed it really got (:meth:`PX4Rig.vehicle_rate`).

The daemon's collision avoidance (escape ``none``: holds, no climbs) is off except inside
:meth:`PX4Rig.collision_avoidance`: parallel legs 10 m apart would otherwise blur what the autopilot
does by itself in the mission scenarios.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from agent.autopilot.base import Autopilot
from agent.autopilot.factory import create_autopilot
from agent.config import AgentSettings
from gcs.cooperation.config import CollisionConfig, CooperationConfig
from gcs.link.beacon import free_udp_port
from protocol.geo import distance_m, offset_latlon
from tests.px4.observer import Fix, Observer
from tests.px4.sih import PX4Fleet
from tests.support.places import at_vehicle
from tests.support.rig import FleetRig

HOME = (47.397742, 8.545594, 489.4)  # PX4 SIH's default home (Zurich)
SPACING_M = 10.0
VEHICLES = 3
BACKENDS = ("mavlink", "mavsdk")
BLOCK = VEHICLES  # instance ids per block: 0-2, 3-5, 6-8


def first_instance(backend: str) -> int | None:
    """The first PX4 instance id of ``backend``'s fleet: each backend has its own block (mavlink 0-2,
    mavsdk 3-5), so the two groups fly side by side on any number of xdist workers; a developer's run
    beside the suite picks another block with ``FLEETGCS_PX4_BLOCK`` (2: ids 6-8). None past id 9."""
    chosen = os.environ.get("FLEETGCS_PX4_BLOCK")
    index = int(chosen) if chosen is not None and chosen.isdigit() else BACKENDS.index(backend)
    first = BLOCK * index
    return first if first + VEHICLES - 1 <= 9 else None


# 2x, not more: PX4's lockstep keeps its clock honest on a starved machine, but its control does not
# stay as tight. Measured under a loaded suite: at 4x (PX4 got 2.8-3.5x) held drones wandered at up
# to 0.87 m/s over 1 s and 2.2 m; at 2x (PX4 got 1.5-1.8x) at most 0.38 m/s and 1.0 m.
SPEED = float(os.environ.get("FLEETGCS_PX4_SPEED", "2"))
# PX4's niceness ($FLEETGCS_PX4_NICE): it runs without real-time threads (no CAP_SYS_NICE), so nice 0
# only makes it an equal of the rest of the machine.
NICE = int(os.environ.get("FLEETGCS_PX4_NICE", "10"))
PARAMS = {
    # Stock SIH drains the battery in 60 s (the daemon's energy monitor then sends everyone home within
    # a minute); one hour lasts the whole run.
    "SIM_BAT_DRAIN": 3600.0,
    # Vertical time is most of a short flight: climb at 3 m/s (stock 1.5), descend at 3 m/s (stock 1.5)
    # down to 6 m (stock 10 m), slowing to the landing speed by 3 m (stock 5 m), and land at 1.2 m/s
    # (stock 0.7). An RTL-all landing from its 15-18 m layers took 21-26 s of PX4 time. Nothing the
    # tests check depends on these.
    "MPC_TKO_SPEED": 3.0,
    "MPC_Z_V_AUTO_DN": 3.0,
    "MPC_Z_VEL_MAX_DN": 3.0,  # the cap of every descent (stock 1.5)
    "MPC_LAND_ALT1": 6.0,
    "MPC_LAND_ALT2": 3.0,
    "MPC_LAND_SPEED": 1.2,
    # A starved PX4 (load 15-20, its clock at 1.3x of 2x) misses its own sensor deadlines ("Accel #0 fail:
    # TIMEOUT", dozens per run) and its estimate's error bounds swell: once it declared the position
    # invalid during RTL-all ("Failsafe activated", then "Switching to Hold is currently not available":
    # Hold needs a valid global position) and never landed. A real vehicle does not lose its IMU to the
    # scheduler, so the bounds are widened (stock 5 m and 1 m/s). A GNSS loss still fails over on time:
    # the estimate turns invalid itself once it dead-reckons past EKF2_NOAID_TOUT (5 s, test_field.py).
    # Which condition fired is printed after each test since (rig.failsafes, PX4's failsafe_flags).
    "COM_POS_FS_EPH": 15.0,
    "COM_VEL_FS_EVH": 2.0,
    # PX4's own link-loss failsafes stay off, as stock (the daemon link and the agent's lost-link action
    # are what the tests check): no GCS-loss action, and no RC in any mode (PX4 ignores RC loss for a
    # vehicle armed without RC; the exceptions say so for Mission, Hold and Offboard as well).
    "NAV_DLL_ACT": 0.0,
    "COM_RCL_EXCEPT": 7.0,
}
DEFAULT_SETTINGS = AgentSettings(status_period_s=0.1)


def at(north: float, east: float, index: int = 0) -> tuple[float, float]:
    """Lat/lon ``north``/``east`` metres from vehicle ``index``'s home."""
    return at_vehicle(HOME, SPACING_M, north, east, index)


class PX4Rig(FleetRig):
    """A running PX4 fleet flown through the daemon by agents on ``backend``."""

    def __init__(
        self, px4: Path, backend: str, data_dir: Path, first: int, collision: CollisionConfig | None = None
    ) -> None:
        super().__init__(f"px4-{backend}", [f"drone-{i + 1}" for i in range(VEHICLES)], data_dir, proxy=True)
        self.backend = backend
        self.fleet = PX4Fleet(px4, data_dir / "px4", first, VEHICLES, HOME, SPACING_M, PARAMS, SPEED, NICE)
        self.observers: dict[str, Observer] = {}
        # (PX4 time, conditions) read from PX4 each time it says "Failsafe activated" (the reason)
        self.failsafes: dict[str, list[tuple[float, list[str]]]] = {n: [] for n in self.names}
        self.origins: list[tuple[float, float]] = [at(0.0, 0.0, i) for i in range(VEHICLES)]
        # Off until collision_avoidance() turns it on: the daemon reads this object on every check.
        self.collision = collision or CollisionConfig(enabled=False, escape="none")
        self.booted_at = 0.0
        self.router_port = 0  # a ground station's UDP port behind drone-3's agent (mavlink backend)

    def start(self) -> PX4Rig:
        try:
            self.booted_at = time.monotonic()
            self.fleet.start()
            for name, instance in zip(self.names, self.fleet.instances, strict=True):
                self.observers[name] = Observer(instance, self._failsafe_reader(name, instance))
            last = len(self.fleet.endpoints) - 1
            autopilots: list[Autopilot] = [
                create_autopilot(self.backend, endpoint, telemetry_hz=10.0, **self._router(i == last))
                for i, endpoint in enumerate(self.fleet.endpoints)
            ]
            cooperation = CooperationConfig(vehicle_time_scale=SPEED, collision=self.collision)
            self.start_agents(autopilots, cooperation, DEFAULT_SETTINGS, arm_deadline_s=30.0)
        except BaseException:
            self.stop()
            raise
        return self

    def _failsafe_reader(self, name: str, instance: int) -> Callable[[float, str], None]:
        """On PX4's "Failsafe activated", read which of its failsafe conditions hold (on a thread of its
        own: the observer's reader must not wait for a process)."""

        def read(at: float) -> None:
            self.failsafes[name].append((at, self.fleet.failsafe_flags(instance)))

        def on_text(at: float, text: str) -> None:
            if "failsafe" in text.lower():
                threading.Thread(target=read, args=(at,), name=f"px4-fs-{instance}", daemon=True).start()

        return on_text

    def _router(self, last: bool) -> dict[str, object]:
        """The last drone's agent routes its MAVLink to a ground station on :attr:`router_port`
        (issue 26; the pymavlink backend's router: MAVSDK owns its link and refuses ``mavlink_out``)."""
        if not last or self.backend != "mavlink":
            return {}
        self.router_port = free_udp_port()
        return {"mavlink_out": [f"udp:127.0.0.1:{self.router_port}"]}

    def stop(self) -> None:
        self.stop_agents()
        for observer in self.observers.values():
            observer.close()
        self.fleet.stop()

    def take_origins(self) -> None:
        """Where each vehicle stands now: PX4 sets its home where it arms, so a drone that landed away
        from its first home returns to its new one. Tests place their points from here (:meth:`at`)."""

        def read() -> list[tuple[float, float]] | None:
            out = []
            for agent in self.agents.values():
                t = agent.autopilot.telemetry()
                if t.home_lat is None or t.home_lon is None or not t.position_known:
                    return None
                out.append((t.lat, t.lon) if t.landed else (t.home_lat, t.home_lon))
            return out

        self.wait(lambda: read() is not None, 30.0, "every vehicle's position and home")
        origins = self.run(read)
        assert origins is not None
        self.origins = origins

    def at(self, north: float, east: float, index: int) -> tuple[float, float]:
        """Lat/lon ``north``/``east`` metres from where vehicle ``index`` stood at the test's start."""
        return offset_latlon(*self.origins[index], north, east)

    def param(self, name: str, param: str) -> float:
        """``param`` as PX4 holds it (read on the GCS link, integers decoded)."""
        return self.observers[name].param(param)

    def estimate_off_gps(self, name: str) -> float:
        """How far PX4's position estimate (GLOBAL_POSITION_INT) lies from its GPS (GPS_RAW_INT), in
        metres; infinite without a 3-D fix. After a GNSS loss the estimate dead-reckons away, and PX4
        resets it to the GPS only some seconds after the fix is back."""
        observer = self.observers[name]
        fix, gps = observer.latest(), observer.gps
        if fix is None or gps is None or gps[2] < 3:
            return float("inf")
        return distance_m(fix.lat, fix.lon, gps[0], gps[1])

    def vehicle_now(self, name: str) -> float:
        fix = self.observers[name].latest()
        assert fix is not None, f"{name}: no GLOBAL_POSITION_INT on PX4's GCS link"
        return fix.t

    def wait_vehicle_time(self, names: list[str], until: dict[str, float], what: str) -> None:
        """Wait until every named vehicle's clock passed ``until[name]`` (bounded in wall time)."""
        span = max(until[n] - self.vehicle_now(n) for n in names)
        self.wait(
            lambda: all(self.vehicle_now(n) >= until[n] for n in names),
            max(10.0, 3.0 * span / SPEED + 10),
            what,
        )

    def vehicle_rate(self, name: str, wall_s: float = 5.0) -> float:
        """PX4's clock over the wall clock for the last ``wall_s`` seconds (SPEED when not starved)."""
        fixes = self.observers[name].fixes_since_wall(time.monotonic() - wall_s)
        if len(fixes) < 2 or fixes[-1][0] <= fixes[0][0]:
            return 0.0
        return (fixes[-1][1].t - fixes[0][1].t) / (fixes[-1][0] - fixes[0][0])

    @contextlib.contextmanager
    def collision_avoidance(self, **settings: float) -> Iterator[None]:
        """The daemon's collision avoidance on (holds only) for the ``with`` block, with ``settings``
        (e.g. ``horizontal_margin_m``) in force; each setting's value before the block comes back."""
        saved = {key: getattr(self.collision, key) for key in settings}

        def apply(values: dict[str, object], enabled: bool) -> None:
            for key, value in values.items():
                setattr(self.collision, key, value)
            self.collision.enabled = enabled

        self.run(lambda: apply(dict(settings), True))
        try:
            yield
        finally:
            self.run(lambda: apply(saved, False))

    def fixes(self, name: str, start: float, end: float) -> list[Fix]:
        return [f for f in self.observers[name].since(start) if f.t <= end]

    def set_settings(self, **values: object) -> None:
        """Change every agent's settings (on the loop), as a type-3 parameter push would."""

        def apply() -> None:
            for agent in self.agents.values():
                for key, value in values.items():
                    setattr(agent.settings, key, value)

        self.run(apply)
