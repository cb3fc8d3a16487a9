"""The operator's fleet commands (API, CLI, dashboard): RTL, land, hold, resume.

They run at ``operator`` priority in the vehicle authority, so nothing else may undo them: RTL and
land take the drones out of their missions and start a deconflicted return (distinct altitude
layers, landing in sequence); hold is an operator hold on each drone (and a pause of any mission
wholly held), resume drops the operator's hold only.
"""

from __future__ import annotations

import contextlib
from typing import Literal

from gcs.control.authority import VehicleAuthority
from gcs.control.bring_down import BringDown
from gcs.core.context import AgentsView
from gcs.missions.runner import MissionRejected, MissionRunner
from gcs.observe.events import EventBus


class OperatorCommands:
    """The operator's fleet commands, at ``operator`` priority (see the module doc)."""

    def __init__(
        self,
        agents: AgentsView,
        missions: MissionRunner,
        authority: VehicleAuthority,
        bring_down: BringDown,
        events: EventBus,
    ) -> None:
        self._agents = agents
        self._missions = missions
        self._authority = authority
        self._bring_down = bring_down
        self._events = events

    def _airborne(self, identity: str) -> bool:
        """Armed and not landed, by its latest status (a grounded drone only stands down)."""
        session = self._agents.session(identity)
        status = session.status if session else None
        return bool(status and status.armed and not status.landed)

    def targets(self, agents: list[str] | None) -> list[str]:
        """The connected agents among ``agents`` (default: every connected agent)."""
        connected = [s.identity for s in self._agents.connected()]
        return connected if agents is None else [a for a in agents if a in connected]

    def _members(self, mission_id: str) -> list[str]:
        mission = self._missions.active.get(mission_id)
        return self._missions.members(mission) if mission else []

    async def bring_down(
        self, kind: Literal["rtl", "land"], agents: list[str] | None, reason: str
    ) -> tuple[list[str], list[str]]:
        """RTL or land (deconflicted); returns (airborne agents given the order, aborted missions).

        The one bring-down use case (gcs/control/bring_down.py) at operator priority; a mission all of
        whose flying members are targets is aborted rather than emptied one drone at a time.
        """
        targets = self.targets(agents)
        why = f"fleet {kind} ({reason})"
        descent = await self._bring_down(targets, kind, "operator", why, abort_emptied=True)
        airborne = [a for a in descent.delivered if self._airborne(a)]
        grounded = len(descent.delivered) - len(airborne)
        self._events.publish(
            f"fleet_{kind}",
            f"{kind} sent to {len(airborne)} airborne agents"
            + (f" and {grounded} on the ground (they stand down)" if grounded else "")
            + f" ({reason})",
            data={"agents": descent.delivered, "airborne": airborne},
        )
        return descent.delivered, descent.aborted

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
        # Missions resumed above already dropped their members' operator holds; drop the rest. A
        # drone a pilot flies is asked to come back (the agent takes it only where it may).
        for t in targets:
            if self._authority.is_held(t, "operator") or self._authority.pilot(t) is not None:
                self._authority.release(t, "operator", why)
        return [t for t in targets if not self._authority.is_held(t, "operator")]
