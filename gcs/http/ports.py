"""What the HTTP routes may read and do, as narrow typed contracts (Protocols) over the daemon's parts.

A route asks for one port through a FastAPI dependency (gcs/http/deps.py), never for the whole
daemon: the agent directory, the mission control, the stored archive, the operator's fleet commands,
the vehicle authority's view, the event log, the live hub. :class:`ApiPorts` is built once per app
(gcs/http/app.py) from a running daemon; the daemon's own classes satisfy these contracts, which
mypy checks where the ports are built.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping
from collections.abc import Set as AbstractSet
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol

if TYPE_CHECKING:
    from gcs.control.authority import VehicleControl
    from gcs.core.config import DaemonConfig
    from gcs.core.context import DaemonParts
    from gcs.http.planning_requests import EnergySettings
    from gcs.link.session import AgentSession
    from gcs.missions.retask import Decision, SurveyRecord
    from gcs.missions.runner import ActiveMission, MissionProgress
    from gcs.observe.events import Event, Severity
    from gcs.observe.live import LiveHub
    from gcs.storage.store import StoredMission
    from protocol.packets import Geofence
    from protocol.taskfile import TaskFile


class AgentDirectory(Protocol):
    """The fleet list: this daemon's sessions, the cluster's remote ones, and retiring a ghost."""

    @property
    def sessions(self) -> Mapping[str, AgentSession]: ...
    @property
    def remote(self) -> Mapping[str, AgentSession]: ...
    @property
    def lost(self) -> AbstractSet[str]: ...
    def connected(self) -> list[AgentSession]: ...
    def link(self, identity: str) -> AgentSession | None: ...
    def holder(self, identity: str) -> str | None: ...
    def fleet(self) -> list[AgentSession]: ...
    def retire(self, identity: str, mission: str | None = None) -> AgentSession: ...


class MissionControl(Protocol):
    """Running missions: submit, progress, and the operator's abort/pause/resume."""

    @property
    def active(self) -> Mapping[str, ActiveMission]: ...
    def members(self, mission: ActiveMission) -> list[str]: ...
    def progress(self, mission_id: str) -> MissionProgress | None: ...
    async def submit(self, task: TaskFile) -> str: ...
    async def abort(
        self, mission_id: str, reason: str, owner: Any = ..., then: Literal["rtl", "land", "hold"] = ...
    ) -> list[str]: ...
    async def pause(self, mission_id: str, reason: str = ...) -> None: ...
    async def resume(self, mission_id: str, reason: str = ...) -> None: ...


class MissionArchive(Protocol):
    """The stored missions and the agents ever enrolled (read only)."""

    def missions(self, state: str | None = None) -> list[StoredMission]: ...
    def mission(self, mission_id: str) -> StoredMission | None: ...
    def known_agents(self) -> dict[str, int]: ...


class FleetOperator(Protocol):
    """The operator's whole-fleet commands, arbitrated by the vehicle authority (gcs/control/operator.py)."""

    async def bring_down(
        self, kind: Literal["rtl", "land"], agents: list[str] | None, reason: str
    ) -> tuple[list[str], list[str]]: ...
    async def hold(self, agents: list[str] | None, reason: str) -> list[str]: ...
    async def resume(self, agents: list[str] | None, reason: str) -> list[str]: ...


class ControlView(Protocol):
    """Who controls a drone now and why (the vehicle authority, read only)."""

    def control(self, ident: str) -> VehicleControl: ...


class EventLog(Protocol):
    def publish(
        self,
        kind: str,
        message: str,
        *,
        severity: Severity = ...,
        agent: str | None = ...,
        mission_id: str | None = ...,
        data: dict[str, Any] | None = ...,
    ) -> Event: ...
    def history(
        self, since_id: int = 0, kind: str | None = None, agent: str | None = None, limit: int = 500
    ) -> list[Event]: ...


class RetaskDesk(Protocol):
    """Re-tasking a dropped drone's share and the survey records (gcs/missions/retask.py)."""

    def record(self, mission_id: str) -> SurveyRecord | None: ...
    async def find(self, mission_id: str) -> SurveyRecord | None: ...
    def proposals(self, mission_id: str) -> list[dict[str, Any]]: ...
    def decide(self, mission_id: str, decision_id: str | None, accept: bool, by: str = ...) -> Decision: ...


@dataclass(frozen=True)
class ApiPorts:
    """Everything the routes may touch; ``config`` and ``token`` are read per request (they may change)."""

    config: Callable[[], DaemonConfig]
    token: Callable[[], str]
    agents: AgentDirectory
    missions: MissionControl
    archive: MissionArchive
    operator: FleetOperator
    authority: ControlView
    events: EventLog
    hub: LiveHub
    set_geofence: Callable[[Geofence | None, list[str] | None], Awaitable[list[str]]]
    energy: Callable[[], EnergySettings]
    retask: RetaskDesk | None = None  # None: the daemon runs no retask service

    @classmethod
    def of(cls, daemon: DaemonParts, hub: LiveHub) -> ApiPorts:
        return cls(
            config=lambda: daemon.config,
            token=lambda: daemon.api_token,
            agents=daemon.agents,
            missions=daemon.missions,
            archive=daemon.store,
            operator=daemon.operator,
            authority=daemon.authority,
            events=daemon.events,
            hub=hub,
            set_geofence=daemon.set_geofence,
            energy=lambda: _energy_settings(daemon),
            retask=_retask_desk(daemon),
        )


def _retask_desk(daemon: DaemonParts) -> RetaskDesk | None:
    from gcs.missions.retask import Retasking

    return next((s for s in daemon.services if isinstance(s, Retasking)), None)


def _energy_settings(daemon: DaemonParts) -> EnergySettings:
    """The pre-flight check's estimator, so a preview predicts what the daemon will check."""
    from gcs.http.planning_requests import EnergySettings

    coop = next((s for s in daemon.services if getattr(s, "name", "") == "cooperation"), None)
    model = getattr(coop, "energy_model", None)
    return EnergySettings(daemon.config.cooperation.energy, model if model and model.trained_on else None)
