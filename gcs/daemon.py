"""Composition root of the daemon: wires store, events, agent manager, missions, servers."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import secrets
import ssl
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from gcs.agents import AgentManager, AgentSession
from gcs.agents_table import StatusTick
from gcs.authority import Owner, VehicleAuthority
from gcs.beacon import BeaconSender
from gcs.config import DaemonConfig
from gcs.context import ServiceContext
from gcs.cooperation import cooperation_services
from gcs.cooperation.event_throttle import EventThrottle
from gcs.cooperation.return_coordinator import ReturnCoordinator, ReturnSettings, VehicleView
from gcs.events import EventBus, Severity
from gcs.extensions import load_extensions
from gcs.keys import KeyRing, load_or_create_key_file
from gcs.live import LiveHub
from gcs.missions import MissionRunner
from gcs.operator import OperatorCommands
from gcs.store import Store
from gcs.telemetry import TelemetryRecorder
from protocol.auth import parse_key
from protocol.packets import (
    AgentParameters,
    CloseReason,
    Geofence,
    GeoPoint,
    SetParameters,
    StatusReport,
    SyncSignal,
)

if TYPE_CHECKING:
    from gcs.cluster.node import ClusterNode

log = logging.getLogger("gcs.daemon")
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
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.touch(mode=0o600)
        path.write_text(secrets.token_urlsafe(24) + "\n")
    return path.read_text().strip()


def _quiet_server_class() -> type:
    import uvicorn

    class QuietServer(uvicorn.Server):
        """uvicorn without its own signal handlers: the daemon's CLI owns SIGINT/SIGTERM."""

        @contextlib.contextmanager
        def capture_signals(self) -> Iterator[None]:
            yield

    return QuietServer


class Service(Protocol):
    """A fleet service running inside the daemon (collision avoidance, an extension...).

    ``start`` is called after the agent listener is up, ``stop`` before it closes. A service gets
    a :class:`gcs.context.ServiceContext` (not the daemon): it hooks into ``ctx.agents.on_status``
    / ``on_join`` / ``on_lost``, ``ctx.events`` and ``ctx.missions.preflight_checks``, and commands
    drones only through ``ctx.authority``.
    """

    name: str

    async def start(self, ctx: ServiceContext) -> None: ...

    async def stop(self) -> None: ...


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
        self.agents = AgentManager(config, self.store, self.events, self.keys)
        self._decision_events = EventThrottle(self._publish_decision, window_s=5.0)
        self.authority = VehicleAuthority(self.agents, self._on_decision, self._persist_hold)
        self.missions = MissionRunner(self.agents, self.store, self.events, self.authority)
        collision = config.cooperation.collision
        self.returns = ReturnCoordinator(
            self.authority,
            self._fleet_view,
            self._release_return,
            self._publish_return,
            ReturnSettings(
                horizontal_margin_m=collision.horizontal_margin_m,
                layer_step_m=collision.vertical_margin_m + 1.0,
            ),
        )
        self.missions.return_home = self.returns.start
        self.operator = OperatorCommands(
            self.agents, self.missions, self.authority, self.returns, self.events
        )
        self.agents.on_status_changes.insert(0, self._observe_status)  # mode/armed/landed/step... changed
        self.agents.on_status_tick.insert(0, self._on_status_tick)
        self._returns_tick_due = False
        self.api_token = load_api_token(config)
        self._server: asyncio.base_events.Server | None = None
        self._http_task: asyncio.Task[None] | None = None
        self._http_server: object | None = None
        self._liveness: asyncio.Task[None] | None = None
        self.listen_port = config.listen_port
        self.http_port: int | None = None
        self.geofences: dict[str, Geofence] = {}  # the fence each agent was last sent
        self.telemetry = TelemetryRecorder(config.telemetry)
        self.services: list[Service] = [self.telemetry]
        self._live_hub: LiveHub | None = None  # built by live_hub(), for the HTTP API
        self.services += load_extensions(config)  # user modules listed in the configuration
        self.services.extend(cooperation_services(config.cooperation))

    def context(self) -> ServiceContext:
        """The narrow view of the daemon that services get."""
        return ServiceContext(
            config=self.config,
            store=self.store,
            agents=self.agents,
            events=self.events,
            missions=self.missions,
            authority=self.authority,
            returns=self.returns,
            geofences=self.geofences,
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
        return {
            s.identity: VehicleView(s.status, s.status.position, s.home)
            for s in self.agents.connected()
            if s.status is not None and s.status.position is not None
        }

    def _release_return(self, ident: str, mission_id: str, step: int) -> None:
        self.agents.post(ident, SyncSignal(mission_id=mission_id, step=step, kind="release"), urgent=True)

    async def _observe_status(self, session: AgentSession, status: StatusReport) -> None:
        if status.buffered:
            return
        self.authority.observe(session.identity, status)
        p = status.position
        if session.home is None and p is not None and status.landed and not status.armed:
            # An agent that joined before its autopilot had a home: where it stands is its home.
            session.home = GeoPoint(lat=p.lat, lon=p.lon, alt_amsl=p.alt_amsl)

    async def _on_status_tick(self, tick: StatusTick) -> None:
        if self.returns.active and not self._returns_tick_due:  # O(fleet): once per batch, not per report
            self._returns_tick_due = True
            asyncio.get_running_loop().call_soon(self._returns_tick)

    def _returns_tick(self) -> None:
        self._returns_tick_due = False
        self.returns.tick()

    async def start(self) -> None:
        if self.cluster is not None:
            await self.cluster.start(self)  # shared state loaded; takes over leaderless missions
        else:
            self.missions.restore()
        if self.config.release_beacon is not None:  # a send-only UDP socket: nothing listens
            self.missions.beacon = BeaconSender(self.config.release_beacon)
        for agent, owner, reason in self.store.holds():
            self.authority.restore_hold(agent, owner, reason)
        tls = server_tls_context(self.config)
        self._server = await asyncio.get_running_loop().create_server(
            self.agents.connection,  # one protocol object per agent connection (gcs/agents.py)
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

        from gcs.http import create_app

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
        body = SetParameters(geofence=geofence, clear_geofence=geofence is None)
        return await self._distribute(body, agents)

    async def set_parameters(self, parameters: AgentParameters, agents: list[str] | None = None) -> list[str]:
        return await self._distribute(SetParameters(parameters=parameters), agents)

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

    async def _distribute(self, body: SetParameters, agents: list[str] | None) -> list[str]:
        targets = agents if agents is not None else [s.identity for s in self.agents.connected()]
        delivered = []
        for identity in targets:
            if self.agents.post(identity, body):  # each agent's own outbox: no one waits for the slowest
                delivered.append(identity)
        if body.geofence is not None or body.clear_geofence:
            for identity in delivered:
                if body.geofence is None:
                    self.geofences.pop(identity, None)
                else:
                    self.geofences[identity] = body.geofence
            self.events.publish("geofence_sent", f"geofence sent to {delivered}", data={"agents": delivered})
        return delivered


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
