"""Admission of a mission: its plans resolved to agents, checked against the live fleet, sent.

Why apart: everything that may refuse a mission (an agent not connected, busy, under another
controller, without a fix, a pre-flight check) happens here, before anything is stored or sent;
the layered mission-end returns and the release-beacon chain are decided here once per mission.
"""

from __future__ import annotations

import asyncio
import secrets
import time

from gcs.cooperation.returns import Returner, assign_layers
from gcs.missions.core import MissionCore, MissionPart
from gcs.missions.model import ActiveMission, MissionRejected, PreflightCheck
from gcs.missions.sync import BarrierSet
from gcs.missions.watchdog import BarrierWatchdog
from gcs.planning.geodesy import LocalFrame
from protocol.actions import Action, ReturnToLaunch
from protocol.beacon import MAX_CHAIN_STEPS, ReleaseChain
from protocol.taskfile import TaskFile

FIX_POLL_S = 0.25
RETURN_BASE_ALT_M = 15.0
RETURN_LAYER_STEP_M = 3.0
RETURN_SPACING_M = 6.0


class MissionAdmission(MissionPart):
    """Validates, persists and starts a mission (``submit``); maps plans to agents."""

    def __init__(self, core: MissionCore, watchdog: BarrierWatchdog) -> None:
        super().__init__(core)
        self._watchdog = watchdog
        self.preflight_checks: list[PreflightCheck] = []

    async def submit(self, task: TaskFile) -> str:
        """Validate against the live fleet, persist, and send every agent its actions."""
        plans = self.resolve(task)
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
            blocked = self._core.remote_blocker(identity)
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
        mission = self.build(mission_id, task, plans)
        mission.chain = self._release_chain(mission)
        self._store.add_mission(mission_id, task.name, task.model_dump_json(), list(plans))
        self.active[mission_id] = mission
        self._events.publish(
            "mission_started",
            f"{task.name}: {len(plans)} agents, sync steps {mission.barriers.sync_steps}",
            mission_id=mission_id,
        )
        for identity, actions in plans.items():
            self._core.send_plan(mission, identity, actions, f"mission {task.name}")
        self._watchdog.arm(mission)
        return mission_id

    def _release_chain(self, mission: ActiveMission) -> ReleaseChain | None:
        """A release-beacon chain for a new mission, when beacons are configured and a member listens.

        Not in a cluster (a release is claimed in shared state and may be sent by another daemon,
        which does not hold the chain) nor for a mission restored after a restart (the seed is not
        persisted): those release over TCP only, and the agents' beacon listeners stay idle.
        """
        steps = mission.barriers.sync_steps
        if self._core.beacon is None or self._core.claim_release is not None or not steps:
            return None
        length = max(steps) + 1
        if length > MAX_CHAIN_STEPS:
            return None
        listening = (self._agents.session(identity) for identity in mission.plans)
        if not any(session is not None and session.release_beacon for session in listening):
            return None
        return ReleaseChain(length)

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
                Returner(
                    identity,
                    frame.local_point(last[0], last[1]),
                    last[2],
                    frame.local_point(home.lat, home.lon),
                )
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

    def resolve(self, task: TaskFile) -> dict[str, list[Action]]:
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

    def build(self, mission_id: str, task: TaskFile, plans: dict[str, list[Action]]) -> ActiveMission:
        sync_steps = task.plans[0].sync_steps()
        return ActiveMission(
            id=mission_id,
            task=task,
            plans=plans,
            barriers=BarrierSet(members=set(plans), sync_steps=sync_steps),
            completed=dict.fromkeys(plans, -1),
        )

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

    def resolve_stored(self, task: TaskFile) -> dict[str, list[Action]]:
        try:
            return self.resolve(task)
        except MissionRejected:
            return {p.label: list(p.actions) for p in task.plans}
