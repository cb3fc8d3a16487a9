"""Composition root of the daemon: wires store, events, agent manager, missions, servers."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import math
import secrets
import ssl
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from gcs.control.authority import Owner, VehicleAuthority
from gcs.control.bring_down import BringDown
from gcs.control.command_port import CommandPort
from gcs.control.operator import OperatorCommands
from gcs.cooperation import cooperation_services
from gcs.cooperation.event_throttle import EventThrottle
from gcs.cooperation.return_coordinator import ReturnCoordinator, ReturnSettings, VehicleView
from gcs.core.config import DaemonConfig
from gcs.core.context import AgentsView, Service, ServiceContext
from gcs.extensions import load_extensions
from gcs.link.agents import AgentManager
from gcs.link.agents_table import StatusTick
from gcs.link.beacon import BeaconSender
from gcs.link.keys import KeyFileError, KeyRing, load_or_create_key_file
from gcs.link.session import AgentSession
from gcs.missions.retask import Retasking
from gcs.missions.runner import MissionRunner
from gcs.observe.events import EventBus, Severity
from gcs.observe.live import LiveHub
from gcs.observe.telemetry import TelemetryRecorder
from gcs.storage.store import Store
from protocol.auth import parse_key
from protocol.packets import (
    AgentParameters,
    CloseReason,
    Geofence,
    GeoPoint,
    StatusReport,
)

if TYPE_CHECKING:
    from gcs.cluster.node import ClusterNode

log = logging.getLogger("gcs.core.daemon")
RETURNS_TICK_S = 0.1
"""The return coordinator's tick (wait points cleared to descend) runs at most this often."""
_heap_frozen = False


def _freeze_startup_heap() -> None:
    """Move what is loaded at start-up (modules, pydantic schemas, services) out of the collector's sight.

    It lives as long as the process, so a full collection need not scan it: that took full
    collections from 60-130 ms to a few ms (docs/performance.md). Once per process, so tests
    that start many daemons do not freeze each other's garbage.
    """
    global _heap_frozen
    if not _heap_frozen:
        _heap_frozen = True
        gc.freeze()


SERVICE_STOP_TIMEOUT_S = 5.0


def server_tls_context(config: DaemonConfig) -> ssl.SSLContext | None:
    """TLS for the agent listener when a certificate is configured; mutual TLS with a client CA."""
    if config.tls_cert is None:
        return None
    if config.tls_key is None:
        raise ValueError("tls_cert needs tls_key")
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.load_cert_chain(config.tls_cert, config.tls_key)
    if config.tls_client_ca is not None:
        context.load_verify_locations(config.tls_client_ca)
        context.verify_mode = ssl.CERT_REQUIRED
    return context


def load_api_token(config: DaemonConfig) -> str:
    """The token mutating API calls need: configured, or kept in DATA_DIR/api.token (0600)."""
    if config.api_token:
        return config.api_token
    path = config.data_dir / "api.token"
    try:
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch(mode=0o600)
            path.write_text(secrets.token_urlsafe(24) + "\n")
        token = path.read_text().strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise KeyFileError(f"cannot read the API token file {path}: {exc}") from None
    if not token:  # an empty token would let an empty 'Bearer ' through
        raise KeyFileError(
            f"the API token file {path} is empty: write a token into it, or move it aside to have a new "
            "one made (clients read it from there)"
        )
    return token


def _quiet_server_class() -> type:
    import uvicorn

    class QuietServer(uvicorn.Server):
        """uvicorn without its own signal handlers: the daemon's CLI owns SIGINT/SIGTERM."""

        @contextlib.contextmanager
        def capture_signals(self) -> Iterator[None]:
            yield

    return QuietServer


class Daemon:
    """The running ground station: ``await start()``, then ``await stop()``."""

    def __init__(self, config: DaemonConfig) -> None:
        self.config = config
        self.cluster: ClusterNode | None = None
        if config.cluster:  # NATS is imported only when asked for (the embedded default needs none)
            from gcs.cluster.node import ClusterNode

            self.cluster = ClusterNode(config)
            self.store: Store = self.cluster.store
        else:
            self.store = Store(config.database_path, allow_new=config.new_database)
        self.events = EventBus(self.store)
        fleet_key = (
            parse_key(config.fleet_key_hex)
            if config.fleet_key_hex
            else load_or_create_key_file(config.data_dir / "fleet.key")
        )
        self.keys = KeyRing.from_files(fleet_key, config.agent_keys_file, config.allow_unlisted_agents)
        cluster = self.cluster  # plugged in through the parts' ports, none reassigned later
        self.agents = AgentManager(
            config,
            self.store,
            self.events,
            self.keys,
            assign_cid=cluster.state.assign_cid if cluster is not None else None,
        )
        self._decision_events = EventThrottle(self._publish_decision, window_s=5.0)
        # The agent manager's send side goes to the authority and the command port only; every
        # other part gets the read-only view (gcs/core/context.py) and the port.
        self.authority = VehicleAuthority(self.agents, self._on_decision, self._persist_hold)
        self.commands = CommandPort(self.agents, self.authority, self._geofence_sent)
        self.agents_view = AgentsView(self.agents)
        collision = config.cooperation.collision
        self.returns = ReturnCoordinator(
            self.authority,
            self._fleet_view if cluster is None else cluster.fleet_view(self._fleet_view),
            self._release_return,
            self._publish_return,
            ReturnSettings(
                horizontal_margin_m=collision.horizontal_margin_m,
                layer_step_m=collision.vertical_margin_m + 1.0,
            ),
        )
        self.missions = MissionRunner(
            self.agents,
            self.store,
            self.events,
            self.commands,
            return_home=self.returns.start,
            beacon=BeaconSender(config.release_beacon) if config.release_beacon is not None else None,
            cluster=cluster,
        )
        self.bring_down = BringDown(self.authority, self.missions, self.returns, self.events.deferred)
        self.operator = OperatorCommands(
            self.agents_view, self.missions, self.authority, self.bring_down, self.events
        )
        # The synchronous observers of every changed report, run inside the status tick in the order
        # the status bus declares (gcs/link/status_bus.py OBSERVERS), before any service's consumer.
        self.agents.bus.observe("authority", self._observe_authority)
        self.agents.bus.observe("home", self._latch_home)
        # The returns tick (gcs/cooperation/return_coordinator.py) runs off the status tick; built
        # before any service starts, its subscription is the first of the tick kind.
        self.agents.bus.subscribe("tick", self._on_status_tick)
        self._returns_tick_due = False
        self._returns_ticked = -math.inf  # loop time of the last returns tick
        self.api_token = load_api_token(config)
        self._server: asyncio.base_events.Server | None = None
        self._http_task: asyncio.Task[None] | None = None
        self._http_server: object | None = None
        self._liveness: asyncio.Task[None] | None = None
        self.listen_port = config.listen_port
        self.http_port: int | None = None
        self.telemetry = TelemetryRecorder(config.telemetry)
        self.services: list[Service] = [self.telemetry]
        self._live_hub: LiveHub | None = None  # built by live_hub(), for the HTTP API
        self.services += load_extensions(config)  # user modules listed in the configuration
        self.services.extend(cooperation_services(config.cooperation, self.cluster))
        self.services.append(Retasking(config.cooperation.energy))  # a dropped drone's share (issue 27)

    def context(self) -> ServiceContext:
        """The narrow view of the daemon that services get."""
        return ServiceContext(
            config=self.config,
            store=self.store,
            agents=self.agents_view,
            events=self.events,
            missions=self.missions,
            authority=self.authority,
            commands=self.commands,
            bring_down=self.bring_down,
            returns=self.returns,
            services=self.services,
        )

    # --- vehicle authority plumbing -------------------------------------------------------------

    def _publish_decision(
        self, kind: str, message: str, severity: str, agent: str | None, data: dict[str, object]
    ) -> None:
        level: Severity = "warning" if severity == "warning" else "info"
        self.events.publish(kind, message, severity=level, agent=agent, data=data)

    def _on_decision(self, agent: str, source: str, command: str, accepted: bool, message: str) -> None:
        self._decision_events.publish(
            "command" if accepted else "command_refused",
            message,
            "info" if accepted else "warning",
            agent,
            {"source": source, "command": command, "accepted": accepted},
            key=f"{source}/{command}/{accepted}",
        )

    def _publish_return(self, kind: str, message: str, agent: str | None, data: dict[str, object]) -> None:
        self.events.publish(kind, message, agent=agent, data=data)

    def _persist_hold(self, agent: str, owner: str, reason: str | None) -> None:
        if reason is None:
            self.store.drop_hold(agent, owner)
        else:
            self.store.save_hold(agent, owner, reason)

    def _fleet_view(self) -> dict[str, VehicleView]:
        views = {}
        for session in self.agents.connected():
            status = session.status  # decoded from the status table once, not once per field
            if status is not None and status.position is not None:
                views[session.identity] = VehicleView(status, status.position, session.home)
        return views

    def _release_return(self, ident: str, mission_id: str, step: int) -> None:
        self.commands.release_barrier([ident], mission_id, step, urgent=True)

    def _geofence_sent(self, delivered: list[str]) -> None:
        self.events.publish("geofence_sent", f"geofence sent to {delivered}", data={"agents": delivered})

    @property
    def geofences(self) -> Mapping[str, Geofence]:
        """The fence each agent was last sent (the command port's record)."""
        return self.commands.geofences

    def _observe_authority(self, session: AgentSession, status: StatusReport) -> None:
        """The authority follows the pilot, the vehicle's failsafe and its landing (live reports only)."""
        if not status.buffered:
            self.authority.observe(session.identity, status)

    @staticmethod
    def _latch_home(session: AgentSession, status: StatusReport) -> None:
        """An agent that joined before its autopilot had a home: where it stands landed is its home."""
        p = status.position
        if (
            session.home is None
            and p is not None
            and status.landed
            and not status.armed
            and not status.buffered
        ):
            session.home = GeoPoint(lat=p.lat, lon=p.lon, alt_amsl=p.alt_amsl)

    async def _on_status_tick(self, tick: StatusTick) -> None:
        if self.returns.active and not self._returns_tick_due:  # O(fleet): once per batch, not per report
            self._returns_tick_due = True
            loop = asyncio.get_running_loop()
            # At most every RETURNS_TICK_S: a tick decodes every drone's status (~20 ms at 1,000
            # drones); run after each 10 ms status tick it held the loop after a fleet RTL.
            wait = self._returns_ticked + RETURNS_TICK_S - loop.time()
            loop.call_later(max(0.0, wait), self._returns_tick)

    def _returns_tick(self) -> None:
        self._returns_tick_due = False
        self._returns_ticked = asyncio.get_running_loop().time()
        self.returns.tick()

    async def start(self) -> None:
        if self.cluster is not None:
            await self.cluster.start(self)  # shared state loaded; takes over leaderless missions
        else:
            self.missions.restore()
        for agent, owner, reason in self.store.holds():
            self.authority.restore_hold(agent, owner, reason)
        tls = server_tls_context(self.config)
        self._server = await asyncio.get_running_loop().create_server(
            self.agents.connection,  # one protocol object per agent connection (gcs/link/connection.py)
            self.config.listen_host,
            self.config.listen_port,
            ssl=tls,
            ssl_handshake_timeout=self.config.handshake_timeout_s if tls else None,
        )
        self.listen_port = self._server.sockets[0].getsockname()[1]
        self._liveness = asyncio.create_task(self.agents.watch_liveness(), name="liveness")
        context = self.context()
        for service in self.services:
            await service.start(context)
        if self.config.http_host:
            await self._start_http()
        _freeze_startup_heap()
        self.events.publish(
            "daemon_started",
            f"agents on {self.config.listen_host}:{self.listen_port}"
            + (f", API on http://{self.config.http_host}:{self.http_port}" if self.http_port else ""),
        )

    async def _start_http(self) -> None:
        import uvicorn

        from gcs.http.app import create_app

        _QuietServer = _quiet_server_class()

        assert self.config.http_host is not None
        hub = self.live_hub()
        await hub.start()
        server_config = uvicorn.Config(
            create_app(self, hub),
            host=self.config.http_host,
            port=self.config.http_port,
            log_level="warning",
            lifespan="off",
            # WebSocket input: the stream takes none, so a client's message is tiny or it is cut off
            # from its frame header (no 16 MiB default, no queue of them, no decompression bombs)
            ws_max_size=self.config.ws_max_message_bytes,
            ws_max_queue=1,
            ws_per_message_deflate=False,
        )
        server = _QuietServer(server_config)
        self._http_server = server
        self._http_task = asyncio.create_task(server.serve(), name="http")
        for _ in range(200):
            if server.started or self._http_task.done():
                break
            await asyncio.sleep(0.02)
        if self._http_task.done():
            self._http_task.result()
        if not server.started:
            raise RuntimeError("HTTP API did not start")
        sockets = [s for srv in server.servers for s in srv.sockets]
        self.http_port = sockets[0].getsockname()[1] if sockets else self.config.http_port

    async def stop(self) -> None:
        self.events.publish("daemon_stopping", "shutting down")
        for service in reversed(self.services):
            try:
                await asyncio.wait_for(service.stop(), SERVICE_STOP_TIMEOUT_S)
            except Exception:  # one faulty or stuck service must not keep the others from stopping
                log.exception("service %s failed to stop", service.name)
        if self._server is not None:
            self._server.close()
        await self.agents.close_all(CloseReason.SHUTDOWN, "daemon shutting down")
        if self._liveness is not None:
            self._liveness.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._liveness
        if self._http_server is not None and self._http_task is not None:
            self._http_server.should_exit = True  # type: ignore[attr-defined]
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._http_task, 5)
        if self._server is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2)
        if self.cluster is not None:
            await self.cluster.stop()
        if self.missions.beacon is not None:
            self.missions.beacon.close()
        self.store.close()

    def live_hub(self) -> LiveHub:
        """The live hub the HTTP API serves (status rings, stream, metrics), built once on first call.

        Registered as a service so :meth:`stop` stops it; started at once if the loop runs (else by
        the caller, or on first use). Built after the services, so its hooks run after theirs.
        """
        if self._live_hub is None:
            self._live_hub = LiveHub(self)
            self.services.append(self._live_hub)
            with contextlib.suppress(RuntimeError):  # no running loop yet: started on first use
                asyncio.get_running_loop().create_task(self._live_hub.start())
        return self._live_hub

    async def set_geofence(self, geofence: Geofence | None, agents: list[str] | None = None) -> list[str]:
        """Send a type-3 geofence to the given (default: all connected) agents; returns who got it."""
        return self.commands.set_geofence(geofence, self._targets(agents))

    async def set_parameters(self, parameters: AgentParameters, agents: list[str] | None = None) -> list[str]:
        return self.commands.set_parameters(parameters, self._targets(agents))

    def _targets(self, agents: list[str] | None) -> list[str]:
        return agents if agents is not None else [s.identity for s in self.agents.connected()]

    async def pause_agent(self, identity: str, reason: str, owner: Owner = "operator") -> bool:
        """Hold one agent where it is (its queue is kept), through the authority; True if accepted."""
        if self.agents.session(identity) is None:
            return False
        return self.authority.hold(identity, owner, reason)[0]

    async def resume_agent(self, identity: str, reason: str, owner: Owner = "operator") -> bool:
        """Drop ``owner``'s hold; the agent resumes once nothing else holds it."""
        if self.agents.session(identity) is None:
            return False
        return self.authority.release(identity, owner, reason)[0]


async def serve_forever(config: DaemonConfig, ready_file: Path | None = None) -> None:
    """Run until cancelled (SIGINT/SIGTERM are turned into cancellation by the CLI)."""
    daemon = Daemon(config)
    await daemon.start()
    if ready_file is not None:
        ready_file.write_text(f"{daemon.listen_port} {daemon.http_port or 0}\n")
    try:
        await asyncio.Event().wait()
    finally:
        await daemon.stop()
