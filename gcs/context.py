"""What a daemon service may touch: a narrow context instead of the whole :class:`gcs.daemon.Daemon`.

Services (cooperation monitors, telemetry, the live hub, extensions) get this at ``start``. Every
command to a drone goes through ``authority`` (docs/cooperation.md: priority order); ``agents``
is for reading the fleet and registering hooks.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from gcs.agents import AgentManager
from gcs.authority import VehicleAuthority
from gcs.config import DaemonConfig
from gcs.events import EventBus
from gcs.missions import MissionRunner
from gcs.store import Store
from protocol.packets import Geofence

if TYPE_CHECKING:
    from gcs.cooperation.return_coordinator import ReturnCoordinator


@dataclass(frozen=True)
class ServiceContext:
    config: DaemonConfig
    store: Store
    agents: AgentManager
    events: EventBus
    missions: MissionRunner
    authority: VehicleAuthority
    returns: ReturnCoordinator
    geofences: Mapping[str, Geofence]
    services: Sequence[Any]

    def service(self, name: str) -> Any | None:
        """Another running service by name (e.g. ``live-hub``), or None."""
        return next((s for s in self.services if getattr(s, "name", None) == name), None)
