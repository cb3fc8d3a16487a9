"""The state every part of the mission runner shares, and the few steps they all take.

Why one object: the runner's parts (admission, releases, the barrier watchdog, the failure
policies, rejoins, records) act on the same running missions through the same ports; this holds
them once, with what the cluster says (lease, claims, remote drones), instead of each part
keeping a copy that could drift. Holds no decision of its own.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING

from gcs.missions.model import (
    ActiveMission,
    MissionAgents,
    MissionCluster,
    MissionRejected,
    MissionState,
    ReturnHome,
)
from gcs.observe.events import EventBus
from gcs.storage.store import Store
from protocol.actions import Action

if TYPE_CHECKING:
    from gcs.control.command_port import CommandPort
    from gcs.link.beacon import BeaconSender


class MissionCore:
    """The ports, the running missions, the paused ones, and the cluster's say over them."""

    def __init__(
        self,
        agents: MissionAgents,
        store: Store,
        events: EventBus,
        commands: CommandPort,
        *,
        return_home: ReturnHome | None = None,
        beacon: BeaconSender | None = None,
        cluster: MissionCluster | None = None,
    ) -> None:
        self.agents = agents  # read and hooks only: what reaches an agent goes through commands
        self.store = store
        self.events = events
        self.commands = commands
        self.authority = commands.authority
        self.active: dict[str, ActiveMission] = {}
        self.paused: set[str] = set()  # changed in place only: every part holds this set
        self.return_home = return_home  # the daemon's return coordinator (deconflicted returns)
        self.beacon = beacon  # the release beacon's sender, when release_beacon is configured
        self.watchdogs: dict[str, asyncio.TimerHandle] = {}  # mission id -> next barrier's watchdog
        # Cluster mode (gcs/cluster, MissionCluster): a release is claimed in shared state first
        # (exactly once), missions another daemon leads are not ours to judge, an agent withdrawn
        # here whose mission another daemon leads is reported to that daemon, and what controls a
        # drone linked to another daemon there ("operator rtl at gcs-b") refuses it a mission.
        self.claim_release: Callable[[str, int], Awaitable[bool]] | None = None
        self.led_elsewhere: Callable[[str], bool] = lambda _mission_id: False
        self.withdraw_elsewhere: Callable[[str, str], Awaitable[None]] | None = None
        self.remote_blocker: Callable[[str], str | None] = lambda _identity: None
        # Fencing: before any decision about a mission the cluster confirms our lease by our own
        # clock; False means we stepped down (the mission was forgotten here): decide nothing.
        self.may_decide: Callable[[str], Awaitable[bool]] | None = None
        if cluster is not None:
            self.may_decide = cluster.may_decide
            self.claim_release = cluster.claim_release
            self.led_elsewhere = cluster.led_elsewhere
            self.withdraw_elsewhere = cluster.withdraw_elsewhere
            self.remote_blocker = cluster.remote_blocker

    async def leading(self, mission: ActiveMission) -> bool:
        """True if this runner may still decide for ``mission`` (always, without a cluster); a
        forgotten mission's late timer (another object since a takeover) decides nothing."""
        if self.active.get(mission.id) is not mission:
            return False
        return self.may_decide is None or await self.may_decide(mission.id)

    def forget(self, mission_id: str) -> None:
        """Stop running a mission here without ending it (another daemon of the cluster leads it)."""
        mission = self.active.pop(mission_id, None)
        if mission is not None:
            for timer in mission.timers.values():
                timer.cancel()
        self.disarm_watchdog(mission_id)
        self.paused.discard(mission_id)

    def send_plan(
        self,
        mission: ActiveMission,
        identity: str,
        actions: list[Action],
        reason: str,
        *,
        await_release: int | None = None,
        keep_holds: bool = False,
    ) -> None:
        """Give a member (part of) its plan, through the authority, with the release anchor if it listens."""
        session = self.agents.session(identity)
        anchor = None
        if mission.chain is not None and session is not None and session.release_beacon:
            anchor = mission.chain.anchor.hex()
        self.authority.replace(
            identity,
            "mission",
            mission.id,
            actions,
            reason,
            await_release=await_release,
            keep_holds=keep_holds,
            release_anchor=anchor,
        )

    def members(self, mission: ActiveMission) -> list[str]:
        return [a for a in mission.plans if a not in mission.excluded]

    def require(self, mission_id: str) -> ActiveMission:
        mission = self.active.get(mission_id)
        if mission is None:
            raise MissionRejected(f"mission {mission_id} is not running")
        return mission

    async def require_led(self, mission_id: str) -> ActiveMission:
        mission = self.require(mission_id)
        if not await self.leading(mission):
            raise MissionRejected(f"mission {mission_id} is not led by this daemon any more")
        return mission

    def finish(self, mission: ActiveMission, state: MissionState, result: str) -> None:
        mission.state = state
        if mission.id in self.paused:
            self.paused.discard(mission.id)
            self.store.set_paused(mission.id, False)
        for timer in mission.timers.values():
            timer.cancel()
        self.disarm_watchdog(mission.id)
        self.store.finish_mission(mission.id, state, result)
        self.active.pop(mission.id, None)
        self.events.publish(
            f"mission_{state}",
            f"{mission.task.name}: {result}",
            severity="info" if state == "completed" else "warning",
            mission_id=mission.id,
        )

    def mission_of(self, identity: str, mission_id: str | None = None) -> ActiveMission | None:
        for mission in self.active.values():
            if identity in mission.plans and (mission_id is None or mission.id == mission_id):
                return mission
        return None

    def disarm_watchdog(self, mission_id: str) -> None:
        timer = self.watchdogs.pop(mission_id, None)
        if timer is not None:
            timer.cancel()


class MissionPart:
    """A part of the runner: the shared core and its ports under the names the parts use."""

    def __init__(self, core: MissionCore) -> None:
        self._core = core
        self._agents = core.agents
        self._store = core.store
        self._events = core.events
        self._commands = core.commands
        self._authority = core.authority
        self.active = core.active
