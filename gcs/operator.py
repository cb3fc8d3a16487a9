"""The operator's fleet commands (API, CLI, dashboard): RTL, land, hold, resume.

They run at ``operator`` priority in the vehicle authority, so nothing else may undo them: RTL and
land take the drones out of their missions and start a deconflicted return (distinct altitude
layers, landing in sequence); hold is an operator hold on each drone (and a pause of any mission
wholly held), resume drops the operator's hold only.
"""

from __future__ import annotations

import contextlib
from typing import Literal

from gcs.agents import AgentManager
from gcs.authority import VehicleAuthority
from gcs.cooperation.return_coordinator import ReturnCoordinator
from gcs.events import EventBus
from gcs.missions import MissionRejected, MissionRunner


class OperatorCommands:
    def __init__(
        self,
        agents: AgentManager,
        missions: MissionRunner,
        authority: VehicleAuthority,
        returns: ReturnCoordinator,
        events: EventBus,
    ) -> None:
        self._agents = agents
        self._missions = missions
        self._authority = authority
        self._returns = returns
        self._events = events

    def targets(self, agents: list[str] | None) -> list[str]:
        """The connected agents among ``agents`` (default: every connected agent)."""
        connected = [s.identity for s in self._agents.connected()]
        return connected if agents is None else [a for a in agents if a in connected]

    def _members(self, mission_id: str) -> list[str]:
        mission = self._missions.active.get(mission_id)
        return self._missions.members(mission) if mission else []

    async def _leave_missions(self, targets: list[str], why: str) -> list[str]:
        """Take the targets out of their missions; a mission left with nobody flying is aborted."""
        aborted = []
        for mission_id in list(self._missions.active):
            members = self._members(mission_id)
            if not set(members) & set(targets):
                continue
            if set(members) <= set(targets):
                with contextlib.suppress(MissionRejected):
                    await self._missions.abort(mission_id, why, "operator", "hold")
                    aborted.append(mission_id)
            else:
                for identity in set(members) & set(targets):
                    await self._missions.withdraw(identity, why)
        return aborted

    async def bring_down(
        self, kind: Literal["rtl", "land"], agents: list[str] | None, reason: str
    ) -> tuple[list[str], list[str]]:
        """RTL or land (deconflicted); returns (airborne agents given the order, aborted missions)."""
        targets = self.targets(agents)
        why = f"fleet {kind} ({reason})"
        aborted = await self._leave_missions(targets, why)
        delivered = self._returns.start(targets, kind, "operator", why)
        self._events.publish(
            f"fleet_{kind}",
            f"{kind} sent to {len(delivered)} airborne agents ({reason})",
            data={"agents": delivered},
        )
        return delivered, aborted

    async def hold(self, agents: list[str] | None, reason: str) -> list[str]:
        targets = self.targets(agents)
        why = f"fleet hold: {reason}"
        for mission_id in list(self._missions.active):
            members = self._members(mission_id)
            if members and set(members) <= set(targets):
                with contextlib.suppress(MissionRejected):
                    await self._missions.pause(mission_id, why)
        return [t for t in targets if self._authority.hold(t, "operator", why)[0]]

    async def resume(self, agents: list[str] | None, reason: str) -> list[str]:
        targets = self.targets(agents)
        why = f"fleet resume: {reason}"
        for mission_id in list(self._missions.paused):
            members = self._members(mission_id)
            if members and set(members) <= set(targets):
                with contextlib.suppress(MissionRejected):
                    await self._missions.resume(mission_id, why)
        # Missions resumed above already dropped their members' operator holds; drop the rest.
        for t in targets:
            if self._authority.is_held(t, "operator"):
                self._authority.release(t, "operator", why)
        return [t for t in targets if not self._authority.is_held(t, "operator")]
