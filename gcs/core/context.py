"""The contracts between the daemon's composition root and what runs inside it.

* :class:`Service`: a fleet service (cooperation, telemetry, the live hub, an extension);
* :class:`ServiceContext`: what a service gets at ``start`` instead of the whole daemon;
* :class:`AgentsView`: the agents as a service sees them: sessions to read and the status bus to
  subscribe to (gcs/link/status_bus.py), no ``post``/``send``/``burst``. What reaches an agent's
  link goes through ``commands`` (the command port, gcs/control/command_port.py) and its
  ``authority``, which arbitrates every type-4 order;
* :class:`DaemonParts`: the daemon's parts the edge modules read (HTTP API, live hub, metrics,
  cluster node), so none of them imports ``gcs.core.daemon`` (only the entry points do).

Why here and not in ``gcs/core/daemon.py``: the extensions need ``Service`` and the services need the
context, and importing them from the composition root made a circle of seven modules.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from collections.abc import Set as AbstractSet
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from gcs.cluster.node import ClusterNode
    from gcs.control.authority import VehicleAuthority
    from gcs.control.bring_down import BringDown
    from gcs.control.command_port import CommandPort
    from gcs.control.operator import OperatorCommands
    from gcs.cooperation.return_coordinator import ReturnCoordinator
    from gcs.core.config import DaemonConfig
    from gcs.link.agents import AgentManager
    from gcs.link.dispatch import ConsumerStats, HookList
    from gcs.link.session import JoinHook, LostHook, StatusHook, SyncHook, TickHook
    from gcs.link.status_bus import Subscriptions
    from gcs.missions.runner import MissionRunner
    from gcs.observe.events import EventBus
    from gcs.observe.live import LiveHub
    from gcs.observe.telemetry import TelemetryRecorder
    from gcs.storage.store import Store
    from protocol.packets import Capabilities, Geofence, GeoPoint, StatusReport


class Service(Protocol):
    """A fleet service running inside the daemon (collision avoidance, an extension...).

    ``start`` is called after the agent listener is up, ``stop`` before it closes. A service gets
    a :class:`ServiceContext` (not the daemon): it hooks into ``ctx.agents.on_status`` /
    ``on_join`` / ``on_lost``, ``ctx.events`` and ``ctx.missions.preflight_checks``, and reaches
    drones only through ``ctx.authority`` and ``ctx.commands``.
    """

    name: str

    async def start(self, ctx: ServiceContext) -> None: ...

    async def stop(self) -> None: ...


class AgentRecord(Protocol):
    """One agent's session as a service reads it: who, where it started, what it last said.

    No ``post``/``send``: what reaches the agent goes through the command port.
    """

    @property
    def identity(self) -> str: ...
    @property
    def cid(self) -> int: ...
    @property
    def home(self) -> GeoPoint | None: ...
    @property
    def status(self) -> StatusReport | None: ...
    @property
    def open(self) -> bool: ...
    @property
    def version(self) -> int: ...
    @property
    def capabilities(self) -> Capabilities: ...
    @property
    def release_beacon(self) -> bool: ...
    @property
    def last_rx(self) -> float: ...


class AgentsView:
    """The agent manager as services see it: read the fleet, register hooks; nothing to send with.

    The hook lists are the manager's own (a service appends and removes its hooks as before).
    """

    __slots__ = (
        "_agents",
        "on_join",
        "on_lost",
        "on_status",
        "on_status_changes",
        "on_status_tick",
        "on_sync",
    )

    def __init__(self, agents: AgentManager) -> None:
        self._agents = agents
        self.on_join: HookList[JoinHook] = agents.on_join
        self.on_status: HookList[StatusHook] = agents.on_status
        self.on_status_changes: HookList[StatusHook] = agents.on_status_changes
        self.on_status_tick: HookList[TickHook] = agents.on_status_tick
        self.on_sync: HookList[SyncHook] = agents.on_sync
        self.on_lost: HookList[LostHook] = agents.on_lost

    def subscriptions(self) -> Subscriptions:
        """A scope of subscriptions to the status bus that end together (a service's ``stop``):
        ``subscribe(kind, hook, capacity)`` gives a handle carrying its queue's limit."""
        return self._agents.bus.subscriptions()

    def session(self, identity: str) -> AgentRecord | None:
        """The agent's session (this daemon's, else a cluster peer's), None if unknown."""
        return self._agents.session(identity)

    def connected(self) -> list[AgentRecord]:
        """This daemon's open sessions."""
        return list(self._agents.connected())

    @property
    def lost(self) -> AbstractSet[str]:
        return frozenset(self._agents.lost)

    def hook_stats(self) -> list[ConsumerStats]:
        return self._agents.hook_stats()


@dataclass(frozen=True)
class ServiceContext:
    """What a daemon service may touch: a narrow view instead of the whole daemon."""

    config: DaemonConfig
    store: Store
    agents: AgentsView
    events: EventBus
    missions: MissionRunner
    authority: VehicleAuthority
    commands: CommandPort
    bring_down: BringDown
    returns: ReturnCoordinator
    services: Sequence[Any]

    @property
    def geofences(self) -> Mapping[str, Geofence]:
        """The fence each agent was last sent (kept by the command port that sent it)."""
        return self.commands.geofences

    def service(self, name: str) -> Any | None:
        """Another running service by name (e.g. ``live-hub``), or None."""
        return next((s for s in self.services if getattr(s, "name", None) == name), None)


class DaemonParts(Protocol):
    """The running daemon's parts, for the edge modules built around it (HTTP API, live hub,
    metrics, cluster node). The composition root (gcs/core/daemon.py) satisfies it; mypy checks that
    where it passes itself."""

    config: DaemonConfig
    store: Store
    agents: AgentManager
    events: EventBus
    missions: MissionRunner
    authority: VehicleAuthority
    commands: CommandPort
    returns: ReturnCoordinator
    operator: OperatorCommands
    telemetry: TelemetryRecorder
    cluster: ClusterNode | None
    services: list[Service]
    api_token: str

    @property
    def geofences(self) -> Mapping[str, Geofence]: ...

    def live_hub(self) -> LiveHub: ...

    async def set_geofence(self, geofence: Geofence | None, agents: list[str] | None = None) -> list[str]: ...


__all__ = ["AgentRecord", "AgentsView", "DaemonParts", "Service", "ServiceContext"]
