"""Daemon + in-process agents on real PX4 SITL (SIH), on either agent backend: pymavlink or MAVSDK.

One PX4 boot (3 quadcopters, homes 10 m apart) serves a test module per backend. The agents listen on
PX4's API links (``udpin:127.0.0.1:14540+i``) behind a :class:`tests.faults.proxy.FaultProxy` (to cut
the daemon link); an :class:`Observer` per vehicle watches PX4's GCS link in PX4's own clock.

Instance ids: each xdist worker has its own block (``gw0`` and a run without xdist 0-2, ``gw1`` 5-7;
PX4 sends the API link of every instance from 10 on to one port, so a third worker skips), and a second
process asking for a block (another checkout) waits for it (file lock) instead of colliding.
PX4 runs ``SPEED`` times faster than the wall clock
(``PX4_SIM_SPEED_FACTOR``; override with ``$FLEETGCS_PX4_SPEED``).
"""

from __future__ import annotations

import os
from pathlib import Path

from agent.autopilot.base import Autopilot
from agent.autopilot.factory import create_autopilot
from agent.config import AgentSettings
from gcs.cooperation.config import CollisionConfig, CooperationConfig
from protocol.geo import offset_latlon
from tests.px4.observer import Fix, Observer
from tests.px4.sih import PX4Fleet
from tests.support.rig import FleetRig

HOME = (47.397742, 8.545594, 489.4)  # PX4 SIH's default home (Zurich)
SPACING_M = 10.0
VEHICLES = 3
BACKENDS = ("mavlink", "mavsdk")
BLOCK = 5  # instance ids per xdist worker


def first_instance() -> int | None:
    """This worker's first PX4 instance id (``PYTEST_XDIST_WORKER`` gwN -> 5N), None past id 9."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    index = int(worker[2:]) if worker.startswith("gw") and worker[2:].isdigit() else 0
    first = BLOCK * index
    return first if first + VEHICLES - 1 <= 9 else None


SPEED = float(os.environ.get("FLEETGCS_PX4_SPEED", "2"))
# Stock SIH drains the battery in 60 s (the daemon's energy monitor then sends everyone home within a
# minute); one hour lasts the whole module. No .ulg logs.
PARAMS = {"SIM_BAT_DRAIN": 3600.0}
DEFAULT_SETTINGS = AgentSettings(status_period_s=0.1)


def at(north: float, east: float, index: int = 0) -> tuple[float, float]:
    """Lat/lon ``north``/``east`` metres from vehicle ``index``'s home."""
    lat, lon = offset_latlon(HOME[0], HOME[1], 0.0, SPACING_M * index)
    return offset_latlon(lat, lon, north, east)


class PX4Rig(FleetRig):
    """A running PX4 fleet flown through the daemon by agents on ``backend``."""

    def __init__(
        self, px4: Path, backend: str, data_dir: Path, first: int, collision: CollisionConfig | None = None
    ) -> None:
        super().__init__(f"px4-{backend}", [f"drone-{i + 1}" for i in range(VEHICLES)], data_dir, proxy=True)
        self.backend = backend
        self.fleet = PX4Fleet(px4, data_dir / "px4", first, VEHICLES, HOME, SPACING_M, PARAMS, SPEED)
        self.observers: dict[str, Observer] = {}
        self.origins: list[tuple[float, float]] = [at(0.0, 0.0, i) for i in range(VEHICLES)]
        # Collision avoidance (holds, climbs) would blur what the autopilot does by itself in the
        # mission tests (parallel legs 10 m apart); the safety module turns it on.
        self.collision = collision or CollisionConfig(enabled=False)

    def start(self) -> PX4Rig:
        try:
            self.fleet.start()
            for name, instance in zip(self.names, self.fleet.instances, strict=True):
                self.observers[name] = Observer(instance)
            autopilots: list[Autopilot] = [
                create_autopilot(self.backend, endpoint, telemetry_hz=10.0)
                for endpoint in self.fleet.endpoints
            ]
            cooperation = CooperationConfig(vehicle_time_scale=SPEED, collision=self.collision)
            self.start_agents(autopilots, cooperation, DEFAULT_SETTINGS, arm_deadline_s=30.0)
        except BaseException:
            self.stop()
            raise
        return self

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

    def fixes(self, name: str, start: float, end: float) -> list[Fix]:
        return [f for f in self.observers[name].since(start) if f.t <= end]

    def set_settings(self, **values: object) -> None:
        """Change every agent's settings (on the loop), as a type-3 parameter push would."""

        def apply() -> None:
            for agent in self.agents.values():
                for key, value in values.items():
                    setattr(agent.settings, key, value)

        self.run(apply)
