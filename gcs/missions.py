"""Mission runner: validates a task, sends each agent its actions, runs the sync barriers.

Each agent gets its whole action list in one type-4 ``replace`` packet at start, so it keeps
flying its plan through a daemon restart or a short link loss; the daemon's part is the
barriers (release step k to everyone once everyone finished k), progress, and the lost-agent
policy. Accepted missions, completed steps and released barriers are in the store, so a
restarted daemon picks the mission up where it was.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import secrets
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Literal

from pydantic import BaseModel

from gcs.agents import AgentManager, AgentSession
from gcs.authority import Owner, VehicleAuthority
from gcs.beacon import BeaconSender
from gcs.cooperation.geo import LocalFrame
from gcs.cooperation.returns import RETURN_PREFIX, Returner, assign_layers
from gcs.events import EventBus
from gcs.store import Store
from gcs.sync import BarrierSet
from protocol.actions import Action, ReturnToLaunch
from protocol.beacon import MAX_CHAIN_STEPS, ReleaseChain
from protocol.packets import ActionFailure, Resume, StatusReport, SyncSignal
from protocol.taskfile import TaskFile

log = logging.getLogger("gcs.missions")

FIX_POLL_S = 0.25
STORED_PLAN_RECHECK_S = 1.0

PreflightCheck = Callable[[TaskFile, dict[str, list[Action]]], Awaitable[None]]
"""Runs before a mission is accepted; raises MissionRejected (with the numbers) to refuse it."""

ReturnHome = Callable[[list[str], Literal["rtl", "land"], Owner, str], list[str]]
"""Starts a deconflicted return (``gcs.cooperation.return_coordinator``); returns who got it."""

RETURN_BASE_ALT_M = 15.0
RETURN_LAYER_STEP_M = 3.0
RETURN_SPACING_M = 6.0

MissionState = Literal["running", "completed", "aborted"]


class MissionRejected(ValueError):
    """A mission that cannot start; the message says why."""


class AgentProgress(BaseModel):
    agent: str
    cid: int | None
    connected: bool
    excluded: bool
    step: int
    completed_step: int
    last_step: int
    waiting_sync: int | None
    done: bool


class MissionProgress(BaseModel):
    id: str
    name: str
    state: str
    result: str | None
    sync_steps: list[int]
    released_steps: list[int]
    agents: list[AgentProgress]


@dataclass(eq=False)
class ActiveMission:
    id: str
    task: TaskFile
    plans: dict[str, list[Action]]  # identity -> actions
    barriers: BarrierSet
    completed: dict[str, int]
    excluded: set[str] = field(default_factory=set)
    left_why: dict[str, str] = field(default_factory=dict)  # excluded agent -> why (this daemon's run)
    state: MissionState = "running"
    timers: dict[int, asyncio.TimerHandle] = field(default_factory=dict)
    failures: dict[str, tuple[int, float]] = field(default_factory=dict)  # agent -> last (step, time) seen
    retries: dict[tuple[str, int], int] = field(default_factory=dict)  # (agent, step) -> retries sent
    chain: ReleaseChain | None = None  # release-beacon chain (protocol/beacon.py); None: TCP releases only

    def last_step(self, agent: str) -> int:
        return self.plans[agent][-1].step


def every_agent_left(mission: ActiveMission) -> str:
    """The result of a mission no agent flies any more, saying why each left.

    A battery emergency's withdrawal or a vehicle's own failsafe is not a lost link: the text
    names each agent with its reason ("drone-1: withdrawn: energy: ...; drone-2: vehicle
    failsafe battery_low"). Agents excluded before a daemon restart have no reason kept.
    """
    whys = [f"{a}: {mission.left_why.get(a, 'excluded')}" for a in sorted(mission.plans)]
    if all(mission.left_why.get(a, "").startswith("lost") for a in mission.plans):
        return "every agent was lost"
    return "no agent left flying (" + "; ".join(whys) + ")"


class MissionRunner:
    """Runs missions over the agent manager; one mission per agent at a time."""

    def __init__(
        self, agents: AgentManager, store: Store, events: EventBus, authority: VehicleAuthority
    ) -> None:
        self._agents = agents
        self._store = store
        self._events = events
        self._authority = authority
        self.active: dict[str, ActiveMission] = {}
        self.preflight_checks: list[PreflightCheck] = []
        self.paused: set[str] = set()
        self.return_home: ReturnHome | None = None  # set by the daemon once the coordinator exists
        self.beacon: BeaconSender | None = None  # set by the daemon when release_beacon is configured
        self._watchdogs: dict[str, asyncio.TimerHandle] = {}  # mission id -> next barrier's watchdog
        # Cluster mode (gcs/cluster): a release is claimed in shared state first (exactly once),
        # and missions another daemon leads are not ours to judge.
        self.claim_release: Callable[[str, int], Awaitable[bool]] | None = None
        self.led_elsewhere: Callable[[str], bool] = lambda _mission_id: False
        # Cluster mode: an agent withdrawn here whose mission another daemon leads (that daemon
        # must take it out of its barriers).
        self.withdraw_elsewhere: Callable[[str, str], Awaitable[None]] | None = None
        # Cluster mode: what controls a drone linked to another daemon above the mission's level
        # there ("operator rtl at gcs-b"), None if a mission may command it.
        self.remote_blocker: Callable[[str], str | None] = lambda _identity: None
        # mission id -> (checked at, plans) of running missions led by another daemon
        self._stored_plans: dict[str, tuple[float, dict[str, list[Action]] | None]] = {}
        agents.on_join.append(self._on_join)
        agents.on_status_changes.append(self._on_status)  # completed step, failsafe, failure: state changes
        agents.on_sync.append(self._on_sync)
        agents.on_finished = self._arrive_now  # the direct path: the last arrival releases at once
        self._taken: dict[int, SyncSignal] = {}  # id -> signal the direct path took (its hook skips it)
        agents.on_lost.append(self._on_lost)

    # --- lifecycle ------------------------------------------------------------------------------

    def restore(self) -> None:
        """Reload the missions that were running when the daemon stopped."""
        for stored in self._store.missions("running"):
            self.restore_one(stored.id)
        self.paused = self._store.paused_missions() & set(self.active)

    def restore_one(self, mission_id: str) -> ActiveMission | None:
        """Take over one stored running mission (restart, or a cluster standby taking the lead)."""
        stored = self._store.mission(mission_id)
        if stored is None or stored.state != "running" or mission_id in self.active:
            return self.active.get(mission_id)
        task = TaskFile.model_validate_json(stored.task_json)
        progress = self._store.mission_agents(stored.id)
        mission = self._build(stored.id, task, self._resolve(task))
        mission.barriers.released |= self._store.released_steps(stored.id)
        for agent, (completed, excluded) in progress.items():
            mission.completed[agent] = completed
            if excluded:
                mission.excluded.add(agent)
                mission.barriers.members.discard(agent)
        self.active[stored.id] = mission
        self._arm_watchdog(mission)
        self._events.publish(
            "mission_restored", f"mission {task.name} resumed after restart", mission_id=stored.id
        )
        if mission_id in self._store.paused_missions():
            self.paused.add(mission_id)
        return mission

    def forget(self, mission_id: str) -> None:
        """Stop running a mission here without ending it (another daemon of the cluster leads it)."""
        mission = self.active.pop(mission_id, None)
        if mission is not None:
            for timer in mission.timers.values():
                timer.cancel()
        self._disarm_watchdog(mission_id)
        self.paused.discard(mission_id)

    async def submit(self, task: TaskFile) -> str:
        """Validate against the live fleet, persist, and send every agent its actions."""
        plans = self._resolve(task)
        busy = {a for m in self.active.values() for a in m.plans if a not in m.excluded}
        for identity in plans:
            if self._agents.session(identity) is None:
                raise MissionRejected(f"agent {identity} is not connected")
            if identity in busy:
                raise MissionRejected(f"agent {identity} is already flying another mission")
            verdict = self._authority.control(identity)
            if not self._authority.may_command(identity, "mission"):
                raise MissionRejected(
                    f"agent {identity} is under {verdict.level} control "
                    f"({verdict.order or ', '.join(verdict.holds) or verdict.failsafe}); "
                    "it takes a mission once that ends (landed) or the operator releases it"
                )
            blocked = self.remote_blocker(identity)
            if blocked is not None:
                raise MissionRejected(
                    f"agent {identity} is under {blocked}; "
                    "it takes a mission once that ends (landed) or the operator releases it"
                )
        await self._wait_for_fix(task, plans)
        for check in self.preflight_checks:
            await check(task, plans)
        task, plans = self._layered_returns(task, plans)
        mission_id = f"m-{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(3)}"
        mission = self._build(mission_id, task, plans)
        mission.chain = self._release_chain(mission)
        self._store.add_mission(mission_id, task.name, task.model_dump_json(), list(plans))
        self.active[mission_id] = mission
        self._events.publish(
            "mission_started",
            f"{task.name}: {len(plans)} agents, sync steps {mission.barriers.sync_steps}",
            mission_id=mission_id,
        )
        for identity, actions in plans.items():
            self._send_plan(mission, identity, actions, f"mission {task.name}")
        self._arm_watchdog(mission)
        return mission_id

    def _release_chain(self, mission: ActiveMission) -> ReleaseChain | None:
        """A release-beacon chain for a new mission, when beacons are configured and a member listens.

        Not in a cluster (a release is claimed in shared state and may be sent by another daemon,
        which does not hold the chain) nor for a mission restored after a restart (the seed is not
        persisted): those release over TCP only, and the agents' beacon listeners stay idle.
        """
        steps = mission.barriers.sync_steps
        if self.beacon is None or self.claim_release is not None or not steps:
            return None
        length = max(steps) + 1
        if length > MAX_CHAIN_STEPS:
            return None
        listening = (self._agents.session(identity) for identity in mission.plans)
        if not any(session is not None and session.release_beacon for session in listening):
            return None
        return ReleaseChain(length)

    def _send_plan(
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
        session = self._agents.session(identity)
        anchor = None
        if mission.chain is not None and session is not None and session.release_beacon:
            anchor = mission.chain.anchor.hex()
        self._authority.replace(
            identity,
            "mission",
            mission.id,
            actions,
            reason,
            await_release=await_release,
            keep_holds=keep_holds,
            release_anchor=anchor,
        )

    def _layered_returns(
        self, task: TaskFile, plans: dict[str, list[Action]]
    ) -> tuple[TaskFile, dict[str, list[Action]]]:
        """Plans that end with RTL return at distinct altitudes when their ways home could meet.

        An RTL without an altitude flies home at the autopilot's RTL_ALT, the same for every
        drone; each final RTL gets the layer :func:`assign_layers` gives it (lowest for the drone
        nearest home), from its last planned position to its home.
        """
        from gcs.cooperation.legs import planned_targets

        returners: list[Returner] = []
        frame: LocalFrame | None = None
        for identity, actions in plans.items():
            session = self._agents.session(identity)
            if not actions or not isinstance(actions[-1], ReturnToLaunch) or actions[-1].alt is not None:
                continue
            if session is None or session.home is None:
                continue
            home = session.home
            frame = frame or LocalFrame(home.lat, home.lon)
            targets = [t for t in planned_targets(actions, (home.lat, home.lon, 0.0)) if t is not None]
            last = targets[-1] if targets else (home.lat, home.lon, 0.0)
            returners.append(
                Returner(identity, frame.point(last[0], last[1]), last[2], frame.point(home.lat, home.lon))
            )
        if len(returners) < 2:
            return task, plans
        base = max([RETURN_BASE_ALT_M] + [r.alt for r in returners])  # nobody descends to return
        layers = assign_layers(returners, RETURN_SPACING_M, base, RETURN_LAYER_STEP_M)
        alt = {p.ident: p.alt for p in layers}
        new_plans = {
            identity: [*actions[:-1], actions[-1].model_copy(update={"alt": round(alt[identity], 1)})]
            if identity in alt
            else actions
            for identity, actions in plans.items()
        }
        # _resolve keeps the task's plan order, so plans and task.plans line up one to one.
        updated = [
            plan.model_copy(update={"actions": new_plans[identity]})
            for plan, identity in zip(task.plans, new_plans, strict=True)
        ]
        task = task.model_copy(update={"plans": updated})
        self._events.publish(
            "returns_layered",
            "final RTL altitudes: " + ", ".join(f"{i} {a:.0f} m" for i, a in sorted(alt.items())),
            data={"alt": alt},
        )
        return task, new_plans

    def _resolve(self, task: TaskFile) -> dict[str, list[Action]]:
        """Map each plan to an agent identity (CoUAS files address agents by CID)."""
        plans: dict[str, list[Action]] = {}
        for plan in task.plans:
            identity = plan.agent
            if identity is None:
                assert plan.cid is not None
                identity = self._store.identity_for_cid(plan.cid)
                if identity is None:
                    raise MissionRejected(f"no agent has connection ID {plan.cid}")
            if identity in plans:
                raise MissionRejected(f"agent {identity} appears twice (by name and by CID)")
            plans[identity] = list(plan.actions)
        return plans

    def _build(self, mission_id: str, task: TaskFile, plans: dict[str, list[Action]]) -> ActiveMission:
        sync_steps = task.plans[0].sync_steps()
        return ActiveMission(
            id=mission_id,
            task=task,
            plans=plans,
            barriers=BarrierSet(members=set(plans), sync_steps=sync_steps),
            completed=dict.fromkeys(plans, -1),
        )

    async def abort(
        self,
        mission_id: str,
        reason: str,
        owner: Owner = "mission",
        then: Literal["rtl", "land", "hold"] = "rtl",
    ) -> list[str]:
        """Stop a mission: every agent still in it returns (deconflicted), lands, or holds.

        ``owner`` is who asked (``operator`` from the API): the returns run at that priority.
        Returns the agents that were given the new orders.
        """
        mission = self._require(mission_id)
        members = self.members(mission)
        self._finish(mission, "aborted", reason)
        if then == "hold":
            return [m for m in members if self._authority.hold(m, owner, f"abort: {reason}", mission_id)[0]]
        if self.return_home is None:
            return []
        return self.return_home(members, then, owner, f"abort: {reason}")

    async def withdraw(self, identity: str, reason: str) -> bool:
        """Take one agent out of its mission (emergency): the others go on without it.

        Barriers it blocked are released; what it does next is for the caller to order through
        the authority. False if it flies no active mission here (in a cluster the daemon leading
        its mission is told through ``withdraw_elsewhere``).
        """
        mission = self._mission_of(identity)
        if mission is None and self.withdraw_elsewhere is not None:
            await self.withdraw_elsewhere(identity, reason)
        if mission is None or identity in mission.excluded:
            return False
        await self._exclude(mission, identity, f"withdrawn: {reason}")
        return True

    def members(self, mission: ActiveMission) -> list[str]:
        return [a for a in mission.plans if a not in mission.excluded]

    async def pause(self, mission_id: str, reason: str = "paused by the operator") -> None:
        """Every agent of the mission stops where it is and keeps its queue (an operator hold).

        The pause is stored: agents that rejoin, and a restarted daemon, keep it.
        """
        mission = self._require(mission_id)
        for identity in self.members(mission):
            self._authority.hold(identity, "operator", reason, mission_id)
        self.paused.add(mission_id)
        self._store.set_paused(mission_id, True)
        self._events.publish("mission_paused", reason, mission_id=mission_id)

    async def resume(self, mission_id: str, reason: str = "resumed by the operator") -> None:
        mission = self._require(mission_id)
        for identity in self.members(mission):
            self._authority.release(identity, "operator", reason, mission_id)
        self.paused.discard(mission_id)
        self._store.set_paused(mission_id, False)
        self._events.publish("mission_resumed", reason, mission_id=mission_id)

    def _require(self, mission_id: str) -> ActiveMission:
        mission = self.active.get(mission_id)
        if mission is None:
            raise MissionRejected(f"mission {mission_id} is not running")
        return mission

    def _finish(self, mission: ActiveMission, state: MissionState, result: str) -> None:
        mission.state = state
        if mission.id in self.paused:
            self.paused.discard(mission.id)
            self._store.set_paused(mission.id, False)
        for timer in mission.timers.values():
            timer.cancel()
        self._disarm_watchdog(mission.id)
        self._store.finish_mission(mission.id, state, result)
        self.active.pop(mission.id, None)
        self._events.publish(
            f"mission_{state}",
            f"{mission.task.name}: {result}",
            severity="info" if state == "completed" else "warning",
            mission_id=mission.id,
        )

    # --- what a cluster node feeds in (gcs/cluster: agents linked to other daemons) ---------------

    async def agent_joined(self, session: AgentSession, resume: Resume | None) -> None:
        """An agent joined (here or, in a cluster, another daemon): resume or re-send its plan."""
        await self._on_join(session, resume)

    async def agent_status(self, session: AgentSession, status: StatusReport) -> None:
        """A status report (progress, failsafes, failed actions) from an agent wherever it is linked."""
        await self._on_status(session, status)

    async def agent_finished(self, session: AgentSession, signal: SyncSignal) -> None:
        """An agent finished a barrier step (its 'finished' sync signal, or one inferred from status)."""
        await self._on_sync(session, signal)

    async def agent_lost(self, identity: str) -> None:
        """An agent is gone (its daemon died or dropped it): the mission's lost-agent policy applies."""
        await self._on_lost(identity)

    def count_arrivals(self, mission_id: str, arrivals: dict[int, set[str]]) -> None:
        """Arrivals recorded elsewhere (shared state, a takeover): counted at their barriers."""
        mission = self.active.get(mission_id)
        if mission is None:
            return
        for step, agents in arrivals.items():
            for agent in agents:
                if step in mission.barriers.sync_steps and agent in mission.barriers.members:
                    with contextlib.suppress(ValueError):
                        mission.barriers.arrive(agent, step)

    async def release_ready(self, mission_id: str) -> list[int]:
        """Release every barrier of the mission that all its members reached; returns the steps."""
        mission = self.active.get(mission_id)
        if mission is None:
            return []
        ready = [
            step
            for step in mission.barriers.sync_steps
            if step not in mission.barriers.released and not mission.barriers.missing(step)
        ]
        for step in ready:
            await self._release(mission, step)
        return ready

    def mission_of(self, identity: str) -> ActiveMission | None:
        """The mission run here that ``identity`` flies (excluded or not), or None."""
        return self._mission_of(identity)

    def plan_of(self, mission_id: str, identity: str) -> list[Action] | None:
        """``identity``'s actions in a running mission: run here, or (cluster) led by another daemon,
        from the stored task; None if it has no plan there. The stored state is looked at again
        at most every ``STORED_PLAN_RECHECK_S``."""
        mission = self.active.get(mission_id)
        if mission is not None:
            return mission.plans.get(identity)
        now = time.monotonic()
        cached = self._stored_plans.get(mission_id)
        if cached is None or now - cached[0] > STORED_PLAN_RECHECK_S:
            plans = None
            stored = self._store.mission(mission_id) if self.led_elsewhere(mission_id) else None
            if stored is not None and stored.state == "running":
                plans = cached[1] if cached is not None and cached[1] is not None else {}
                if not plans:
                    try:
                        plans = self._resolve(TaskFile.model_validate_json(stored.task_json))
                    except ValueError:  # MissionRejected included: a CID no longer known
                        plans = {}
            if len(self._stored_plans) > 64:  # bounded: finished missions are not asked for again
                self._stored_plans.clear()
            cached = self._stored_plans[mission_id] = (now, plans)
        return None if cached[1] is None else cached[1].get(identity)

    # --- agent hooks ----------------------------------------------------------------------------

    def _mission_of(self, identity: str, mission_id: str | None = None) -> ActiveMission | None:
        for mission in self.active.values():
            if identity in mission.plans and (mission_id is None or mission.id == mission_id):
                return mission
        return None

    async def _on_join(self, session: AgentSession, resume: Resume | None) -> None:
        identity = session.identity
        mission = self._mission_of(identity)
        if mission is None or identity in mission.excluded:
            self._authority.reassert(identity)
            return
        if resume is not None and resume.mission_id == mission.id:
            # It still holds its queue. A sync wait it reports counts as a (repeated) arrival:
            # the 'finished' it sent before may have died with the previous daemon process.
            self._authority.reassert(identity)
            if resume.waiting_step is not None:
                await self._on_sync(
                    session, SyncSignal(mission_id=mission.id, step=resume.waiting_step, kind="finished")
                )
            return
        completed = max(mission.completed.get(identity, -1), resume.completed_step if resume else -1)
        actions = mission.plans[identity]
        remaining = [a for a in actions if a.step > completed]
        # Finished a barrier step that is not released yet: it must wait there again, not run on.
        barrier = next((a.step for a in actions if a.sync and a.step == completed), None)
        wait = barrier if barrier is not None and barrier not in mission.barriers.released else None
        self._events.publish(
            "mission_resent",
            f"agent lost its queue; re-sending {len(remaining)} actions after step {completed}"
            + (f", waiting at barrier {wait} first" if wait is not None else "")
            + (" (mission paused)" if mission.id in self.paused else ""),
            agent=identity,
            mission_id=mission.id,
        )
        if remaining or wait is not None:
            self._send_plan(
                mission, identity, remaining, "re-sent after rejoin", await_release=wait, keep_holds=True
            )

    async def _on_status(self, session: AgentSession, status: StatusReport) -> None:
        if status.mission_id is None:
            return
        mission = self._mission_of(session.identity, status.mission_id)
        if mission is None:
            return
        if status.failsafe is not None and session.identity not in mission.excluded:
            # The vehicle flies its own failsafe now (RTL, land, hold): the others go on without it.
            await self._exclude(mission, session.identity, f"vehicle failsafe {status.failsafe}")
            return
        previous = mission.completed.get(session.identity, -1)
        if status.completed_step > previous:
            mission.completed[session.identity] = status.completed_step
            self._store.set_completed_step(mission.id, session.identity, status.completed_step)
        if status.failure is not None:
            await self._on_action_failed(mission, session.identity, status.failure)
        if mission.state == "running":
            self._check_complete(mission)

    def _check_complete(self, mission: ActiveMission) -> None:
        flying = [a for a in mission.plans if a not in mission.excluded]
        if not flying:
            self._finish(mission, "aborted", every_agent_left(mission))
            return
        if all(mission.completed[a] >= mission.last_step(a) for a in flying):
            note = f" ({len(mission.excluded)} agents excluded)" if mission.excluded else ""
            self._finish(mission, "completed", f"all {len(flying)} agents finished{note}")

    async def _on_sync(self, session: AgentSession, signal: SyncSignal) -> None:
        if self._taken.pop(id(signal), None) is signal:
            return  # the direct path (_arrive_now) counted it already
        if signal.mission_id.startswith(RETURN_PREFIX):
            return  # a return's wait point: the return coordinator releases it
        mission = self._mission_of(session.identity, signal.mission_id)
        if mission is None and self.led_elsewhere(signal.mission_id):
            return
        if mission is None:
            self._events.publish(
                "sync_ignored",
                f"finished step {signal.step} for unknown mission {signal.mission_id}",
                severity="warning",
                agent=session.identity,
            )
            return
        if self._record_arrival(mission, session, signal):
            await self._release(mission, signal.step)

    def _arrive_now(self, session: AgentSession, signal: SyncSignal) -> bool:
        """A 'finished' straight from the agent's frame (``AgentManager.on_finished``); True if taken.

        Called only while this runner's hook consumer holds no join or lost of the agent. A
        barrier this completes is released in the same call (persisted, then one burst): no hook
        queue, no task switch. Left to the ``on_sync`` hook, in order: an agent whose newest
        report carries a failsafe or a failure (the hook may exclude it first), a cluster (the
        release is claimed in shared state first, which is awaited), returns' wait points, and
        missions not run here.
        """
        if self.claim_release is not None or signal.mission_id.startswith(RETURN_PREFIX):
            return False
        mission = self._mission_of(session.identity, signal.mission_id)
        if mission is None:
            return False
        status = session.status
        if status is not None and (status.failsafe is not None or status.failure is not None):
            return False
        if len(self._taken) >= 4096:  # hooks closed at shutdown never pop theirs: bounded
            self._taken.clear()
        self._taken[id(signal)] = signal
        if self._record_arrival(mission, session, signal):
            self._release_now(mission, signal.step)
        return True

    def _record_arrival(self, mission: ActiveMission, session: AgentSession, signal: SyncSignal) -> bool:
        """Count an arrival at a barrier; True when it completes the barrier (now to be released).

        A repeated arrival at a released step is answered with the release at once; the first
        arrival at a barrier starts its sync timeout.
        """
        try:
            complete = mission.barriers.arrive(session.identity, signal.step)
        except ValueError as exc:
            self._events.publish("sync_ignored", str(exc), severity="warning", agent=session.identity)
            return False
        if signal.step in mission.barriers.released:
            session.post(SyncSignal(mission_id=mission.id, step=signal.step, kind="release"))
            return False
        if not complete and signal.step not in mission.timers:
            timeout = mission.task.sync_timeout_s
            mission.timers[signal.step] = asyncio.get_running_loop().call_later(
                timeout, lambda: asyncio.ensure_future(self._barrier_timeout(mission, signal.step))
            )
        return complete

    async def _release(self, mission: ActiveMission, step: int) -> None:
        if self.claim_release is not None and not await self.claim_release(mission.id, step):
            mission.barriers.mark_released(step)  # another daemon released it; it told the agents
            return
        self._release_now(mission, step)

    def _release_now(self, mission: ActiveMission, step: int) -> None:
        """Make the release of ``step`` durable, announce it, write it to every member's socket in
        one pass, then record it in the database.

        Durable first: one append to the release journal (``Store.journal_release``; no lock, no
        transaction), so an agent never hears of a release a restarted daemon would not know.
        Then the beacon (one datagram for every listening member) and the TCP burst. The release
        row and its event follow as one transaction (a kill -9 between the two lost the event once;
        between the journal and this transaction the store recovers both when it opens).
        ``write_wanted`` is set through the burst: the telemetry writer ends its chunk at the next
        row and waits, instead of competing with this thread for the GIL while the sockets are
        written (each ``send`` lets another thread run, which may then keep the GIL for up to the
        switch interval). The garbage collector is off for the same span.
        """
        mission.barriers.mark_released(step)
        store = self._store
        collecting = gc.isenabled()
        gc.disable()
        store.write_wanted.set()
        try:
            at = store.journal_release(mission.id, step)
            self._announce(mission, step)  # one datagram for every listening member first
            # One burst: encoded once, written to every member's socket in this pass.
            members = sorted(mission.barriers.members)
            self._agents.burst(members, SyncSignal(mission_id=mission.id, step=step, kind="release"))
            with store.atomic():
                store.record_release(mission.id, step, at)
                self._events.publish(
                    "sync_released",
                    f"step {step} released to {len(members)} agents",
                    mission_id=mission.id,
                    data={"step": step, "agents": members},
                )
            store.release_recorded()
        finally:
            store.write_wanted.clear()
            if collecting:
                gc.enable()
        timer = mission.timers.pop(step, None)
        if timer is not None:
            timer.cancel()
        self._arm_watchdog(mission)

    def _announce(self, mission: ActiveMission, step: int) -> None:
        """The release beacon of ``step`` (protocol/beacon.py), when the mission has a chain."""
        if self.beacon is None or mission.chain is None:
            return
        value = mission.chain.value(step)
        if value is not None:
            self.beacon.send(mission.id, step, value)

    async def _barrier_timeout(self, mission: ActiveMission, step: int) -> None:
        if mission.state != "running" or step in mission.barriers.released:
            return
        missing = sorted(mission.barriers.missing(step))
        await self._lost_policy(
            mission,
            step,
            missing,
            f"step {step}: still waiting for {missing} after {mission.task.sync_timeout_s:.0f} s",
            abort_result=f"sync step {step} timed out waiting for {missing}",
            exclude_why=f"did not reach sync step {step} in time",
        )

    async def _lost_policy(
        self,
        mission: ActiveMission,
        step: int,
        missing: list[str],
        what: str,
        abort_result: str,
        exclude_why: str,
    ) -> None:
        """The task's lost-agent policy for agents that did not reach barrier ``step``."""
        policy = mission.task.lost_agent_policy
        self._events.publish(
            "sync_timeout",
            f"{what}; policy {policy}",
            severity="error",
            mission_id=mission.id,
            data={"step": step, "missing": missing},
        )
        if policy == "abort":
            await self.abort(mission.id, abort_result)
            return
        for identity in missing:
            await self._exclude(mission, identity, exclude_why)

    async def _exclude(self, mission: ActiveMission, identity: str, why: str) -> None:
        mission.excluded.add(identity)
        mission.left_why[identity] = why
        self._store.exclude_agent(mission.id, identity)
        self._events.publish("agent_excluded", why, severity="warning", agent=identity, mission_id=mission.id)
        for step in mission.barriers.exclude(identity):
            await self._release(mission, step)
        if mission.state == "running":
            self._check_complete(mission)

    async def _on_lost(self, identity: str) -> None:
        if self._agents.session(identity) is not None:
            return  # back already (here, or linked to another daemon of the cluster)
        mission = self._mission_of(identity)
        if mission is None or identity in mission.excluded:
            return
        if mission.completed.get(identity, -1) >= mission.last_step(identity):
            return  # it had finished its part
        if mission.task.lost_agent_policy == "continue":
            await self._exclude(mission, identity, "lost during the mission; continuing without it")

    # --- pre-flight: wait for every agent's fix -------------------------------------------------

    def _without_fix(self, plans: dict[str, list[Action]]) -> dict[str, str]:
        """Agents of ``plans`` with no position yet, with what their last report says."""
        missing: dict[str, str] = {}
        for identity in plans:
            session = self._agents.session(identity)
            status = session.status if session else None
            if status is None:
                missing[identity] = "no status report yet"
            elif status.position is None or status.gps.fix < 3:
                missing[identity] = f"GPS fix {status.gps.fix}, {status.gps.satellites} satellites"
        return missing

    async def _wait_for_fix(self, task: TaskFile, plans: dict[str, list[Action]]) -> None:
        """Wait (up to ``task.fix_wait_s``) until every agent reports a 3-D fix and a position.

        A vehicle reports no position for a while after boot (ArduCopter: 11-13 s of fix 0 at
        lat/lon 0,0); planning or checking energy from there gives absurd figures, so a mission
        submitted right after the agents connect waits here instead of being refused.
        """
        missing = self._without_fix(plans)
        if not missing:
            return
        started = time.monotonic()
        self._events.publish(
            "preflight_waiting",
            f"{task.name}: waiting up to {task.fix_wait_s:.0f} s for a 3-D fix from "
            + ", ".join(f"{a} ({why})" for a, why in sorted(missing.items())),
            data={"agents": sorted(missing)},
        )
        deadline = started + task.fix_wait_s
        while missing and time.monotonic() < deadline:
            await asyncio.sleep(min(FIX_POLL_S, max(0.0, deadline - time.monotonic())))
            missing = self._without_fix(plans)
        if missing:
            raise MissionRejected(
                f"no 3-D fix after {task.fix_wait_s:.0f} s from "
                + ", ".join(f"{a} ({why})" for a, why in sorted(missing.items()))
            )
        self._events.publish(
            "preflight_fix",
            f"{task.name}: every agent has a 3-D fix after {time.monotonic() - started:.1f} s",
        )

    # --- failed actions -------------------------------------------------------------------------

    async def _on_action_failed(self, mission: ActiveMission, identity: str, failure: ActionFailure) -> None:
        """Apply the task's ``on_action_failed`` policy once per failure an agent reports.

        The agent has emptied its queue and holds; it keeps reporting the failure until it
        starts another action, so each (step, time) is acted on once.
        """
        key = (failure.step, failure.time)
        if (
            mission.state != "running"
            or identity in mission.excluded
            or mission.failures.get(identity) == key
        ):
            return
        mission.failures[identity] = key
        what = f"{identity} step {failure.step} ({failure.kind}): {failure.reason}"
        policy = mission.task.on_action_failed
        self._events.publish(
            "action_failed",
            f"{what}; policy {policy}",
            severity="error",
            agent=identity,
            mission_id=mission.id,
            data={"step": failure.step, "kind": failure.kind, "reason": failure.reason},
        )
        plan = mission.plans[identity]
        if policy == "retry":
            tried = mission.retries.get((identity, failure.step), 0)
            if tried < mission.task.action_retries:
                mission.retries[(identity, failure.step)] = tried + 1
                again = [a for a in plan if a.step >= failure.step]
                self._events.publish(
                    "action_retry",
                    f"{identity}: retry {tried + 1}/{mission.task.action_retries} of step {failure.step}",
                    agent=identity,
                    mission_id=mission.id,
                )
                self._send_plan(mission, identity, again, f"retry step {failure.step}")
                return
        elif policy == "skip":
            await self._skip_step(mission, identity, failure)
            return
        await self.abort(mission.id, f"action failed: {what}")

    async def _skip_step(self, mission: ActiveMission, identity: str, failure: ActionFailure) -> None:
        """Count the failed step as done (a barrier at it counts the agent as arrived), fly on."""
        plan = mission.plans[identity]
        rest = [a for a in plan if a.step > failure.step]
        self._events.publish(
            "action_skipped",
            f"{identity}: step {failure.step} skipped, {len(rest)} actions left",
            severity="warning",
            agent=identity,
            mission_id=mission.id,
        )
        if mission.completed.get(identity, -1) < failure.step:
            mission.completed[identity] = failure.step
            self._store.set_completed_step(mission.id, identity, failure.step)
        if rest:
            self._send_plan(mission, identity, rest, f"step {failure.step} skipped")
        barriers = mission.barriers
        if (
            failure.step in barriers.sync_steps
            and failure.step not in barriers.released
            and barriers.arrive(identity, failure.step)
        ):
            await self._release(mission, failure.step)

    # --- barrier watchdog: agents that never arrive ---------------------------------------------

    def _next_barrier(self, mission: ActiveMission) -> int | None:
        pending = [s for s in mission.barriers.sync_steps if s not in mission.barriers.released]
        return pending[0] if pending else None

    def _arm_watchdog(self, mission: ActiveMission) -> None:
        """Time the next barrier from now (mission start or the previous release).

        The usual sync timeout starts at a barrier's first arrival; this one catches a barrier
        no agent ever reaches (every agent failed, stuck idle or gone).
        """
        self._disarm_watchdog(mission.id)
        step = self._next_barrier(mission)
        if step is None or mission.state != "running":
            return
        self._watchdogs[mission.id] = asyncio.get_running_loop().call_later(
            mission.task.sync_timeout_s, lambda: asyncio.ensure_future(self._watchdog_fired(mission, step))
        )

    def _disarm_watchdog(self, mission_id: str) -> None:
        timer = self._watchdogs.pop(mission_id, None)
        if timer is not None:
            timer.cancel()

    def _working_on(self, mission: ActiveMission, identity: str) -> bool:
        """True while the agent's reports show it flying an action, waiting at a barrier, or held
        by a pause (collision avoidance holds one agent at a time)."""
        session = self._agents.session(identity)
        status = session.status if session else None
        if status is None or status.mission_id != mission.id:
            return False
        return status.step >= 0 or status.waiting_sync is not None or status.paused

    async def _watchdog_fired(self, mission: ActiveMission, step: int) -> None:
        self._watchdogs.pop(mission.id, None)
        if mission.state != "running" or step in mission.barriers.released:
            return
        if mission.barriers.arrivals.get(step) and step in mission.timers:
            return  # someone arrived: the first-arrival sync timeout is running
        idle = sorted(a for a in mission.barriers.missing(step) if not self._working_on(mission, a))
        if not idle or mission.id in self.paused:
            self._arm_watchdog(mission)  # long legs: look again one timeout later
            return
        await self._lost_policy(
            mission,
            step,
            idle,
            f"step {step}: {idle} not working towards it {mission.task.sync_timeout_s:.0f} s after "
            "the mission start or the previous release",
            abort_result=f"sync step {step}: {idle} never arrived",
            exclude_why=f"never reached sync step {step}",
        )
        if mission.state == "running":
            self._arm_watchdog(mission)

    # --- progress -------------------------------------------------------------------------------

    def progress(self, mission_id: str) -> MissionProgress | None:
        stored = self._store.mission(mission_id)
        if stored is None:
            return None
        mission = self.active.get(mission_id)
        task = mission.task if mission else TaskFile.model_validate_json(stored.task_json)
        plans = mission.plans if mission else self._resolve_stored(task)
        agents_state = self._store.mission_agents(mission_id)
        released = self._store.released_steps(mission_id)
        rows = []
        for identity, actions in plans.items():
            session = self._agents.sessions.get(identity)
            status = session.status if session else None
            completed = max(
                agents_state.get(identity, (-1, False))[0], mission.completed[identity] if mission else -1
            )
            rows.append(
                AgentProgress(
                    agent=identity,
                    cid=session.cid if session else None,
                    connected=bool(session and session.open),
                    excluded=agents_state.get(identity, (-1, False))[1],
                    step=status.step if status and status.mission_id == mission_id else -1,
                    completed_step=completed,
                    last_step=actions[-1].step,
                    waiting_sync=status.waiting_sync if status and status.mission_id == mission_id else None,
                    done=completed >= actions[-1].step,
                )
            )
        return MissionProgress(
            id=stored.id,
            name=stored.name,
            state=stored.state,
            result=stored.result,
            sync_steps=task.plans[0].sync_steps(),
            released_steps=sorted(released),
            agents=rows,
        )

    def _resolve_stored(self, task: TaskFile) -> dict[str, list[Action]]:
        try:
            return self._resolve(task)
        except MissionRejected:
            return {p.label: list(p.actions) for p in task.plans}
