"""Closed-loop coverage (issue 27): a drone that leaves a survey has its unseen share re-tasked.

A daemon service beside the mission runner (whose class may only shrink), wired by hooks only:

* **tracks**: every status tick of a drone flying a survey mission (a task file with ``survey``)
  adds its (lat, lon, alt_rel) to the mission's record, thinned to one per metre moved. They are
  what the fleet has seen (:mod:`gcs.planning.seen`), for the proposal and the report.
* **a drone leaves**: the runner publishes ``agent_excluded`` for every way out (battery
  failsafe or low-battery RTL, lost link, pilot takeover, an emergency withdrawal). The service
  gathers the remaining members (position, end of their own survey, energy margin from the
  shared estimator, :func:`gcs.cooperation.energy.predict_plan_energy`) and asks the pure
  decision (:func:`gcs.planning.retask.propose_retask`).
* **policy** (the task file's ``survey.retask``): ``automatic`` applies a proposal at once;
  ``ask`` publishes it (``retask_proposed``) and keeps it for the operator (HTTP ``POST
  /api/v1/missions/{id}/retask/{rid}/accept|reject``, ``gcs mission retask``); ``off`` does
  nothing.
* **applying** edits each receiver's plan in the runner (:mod:`gcs.missions.plan_edit`: the
  legs after its own survey, before its return, so completion waits for them) and sends the new
  legs and the return through the vehicle authority at mission priority once the receiver has
  flown its own survey (at once if it has). The dropped drone left the barriers when it was
  excluded, so nobody waits for it.
* **kept**: a record is saved in the daemon's store (:mod:`gcs.missions.record_codec`, table
  ``survey_records``, the last :data:`MAX_RECORDS`) after each decision, when its mission ends and
  when the daemon stops; :meth:`Retasking.find` reads it back, so the report outlives a restart,
  and a survey resumed after a restart goes on from the tracks it had.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

from gcs.cooperation.config import EnergyConfig
from gcs.cooperation.energy import capability_power_w, predict_plan_energy
from gcs.missions.plan_edit import extend_plan, survey_alt, survey_points
from gcs.missions.record_codec import RecordDecodeError, decode_record, encode_record
from gcs.planning.retask import Candidate, RetaskProposal, propose_retask
from protocol.actions import Action, Goto, ReturnToLaunch, Waypoints
from protocol.geo import distance_m
from protocol.taskfile import SurveyArea

if TYPE_CHECKING:
    from gcs.core.context import ServiceContext
    from gcs.link.agents_table import StatusTick
    from gcs.link.session import AgentSession
    from gcs.link.status_bus import Subscriptions
    from gcs.missions.runner import ActiveMission
    from gcs.observe.events import Event, Severity
    from protocol.packets import StatusReport

log = logging.getLogger("gcs.missions.retask")

TRACK_STEP_M = 1.0  # a new track point once the drone moved this far (or changed height by it)
MAX_RECORDS = 64  # survey missions remembered for reports, in memory and in the store (oldest first out)
ENDED = frozenset({"mission_completed", "mission_aborted"})  # the runner's events of a mission's end
MAX_TRACK_POINTS = 200_000  # per drone and mission: hours of flight at one point per metre

State = Literal["pending", "applied", "rejected", "none"]


class RetaskError(ValueError):
    """A decision that cannot be taken (no such proposal, already decided, mission over)."""


@dataclass
class Decision:
    """One re-task decision of a mission: the proposal and what became of it."""

    id: str
    dropped: str
    why: str
    proposal: RetaskProposal
    state: State
    at: float = field(default_factory=time.time)
    by: str = ""  # who decided: automatic, operator

    def summary(self, gap: bool = False) -> dict[str, Any]:
        p = self.proposal
        out: dict[str, Any] = {
            "id": self.id,
            "dropped": self.dropped,
            "why": self.why,
            "verdict": p.verdict,
            "reason": p.reason,
            "state": self.state,
            "by": self.by,
            "at": self.at,
            "gap_m2": p.gap_m2,
            "share_m2": p.share_m2,
            "pieces": p.pieces,
            "legs": [
                {k: v for k, v in leg.__dict__.items() if k != "points"} | {"points": len(leg.points)}
                for leg in p.legs
            ],
        }
        if gap:
            out["gap"] = p.gap
        return out


@dataclass
class SurveyRecord:
    """What the service keeps of one survey mission."""

    mission_id: str
    survey: SurveyArea
    planned: dict[str, list[Action]]  # each member's plan as submitted (the report's "planned")
    tracks: dict[str, list[tuple[float, float, float]]] = field(default_factory=dict)
    decisions: list[Decision] = field(default_factory=list)
    waiting: dict[str, tuple[int, list[Action]]] = field(default_factory=dict)  # agent -> (ready, send)

    def snapshot(self) -> SurveyRecord:
        """A copy a worker thread may read while the status ticks go on appending to this one."""
        return SurveyRecord(
            self.mission_id,
            self.survey,
            dict(self.planned),
            {a: list(t) for a, t in self.tracks.items()},
            list(self.decisions),
            dict(self.waiting),
        )

    def track(self, ident: str, point: tuple[float, float, float]) -> None:
        track = self.tracks.setdefault(ident, [])
        if track:
            lat, lon, alt = track[-1]
            moved = distance_m(lat, lon, point[0], point[1])
            if moved < TRACK_STEP_M and abs(point[2] - alt) < TRACK_STEP_M:
                return
            if len(track) >= MAX_TRACK_POINTS:
                return
        track.append(point)


class Retasking:
    """The service (``name = "retask"``): tracks, proposals on a drone's exit, their application."""

    name = "retask"

    def __init__(self, energy: EnergyConfig) -> None:
        self._energy = energy
        self._ctx: ServiceContext | None = None
        self._subscriptions: Subscriptions | None = None  # its hooks on the status bus, from start()
        self.records: OrderedDict[str, SurveyRecord] = OrderedDict()
        self._plain: OrderedDict[str, None] = OrderedDict()  # missions seen that are no survey
        self._events: asyncio.Queue[Event] | None = None
        self._task: asyncio.Task[None] | None = None
        self._saving: set[asyncio.Task[None]] = set()
        self._last_saved: dict[str, tuple[int, tuple[str, ...]]] = {}  # mission -> _mark() of its last save

    # --- lifecycle ------------------------------------------------------------------------------

    async def start(self, ctx: ServiceContext) -> None:
        self._ctx = ctx
        self._subscriptions = subscriptions = ctx.agents.subscriptions()  # ended together in stop()
        subscriptions.subscribe("tick", self._on_tick)
        subscriptions.subscribe("changes", self._on_status)
        self._events = ctx.events.subscribe()
        self._task = asyncio.create_task(self._consume(), name="retask")

    async def stop(self) -> None:
        if self._subscriptions is not None:
            self._subscriptions.close()
        if self._ctx is not None and self._events is not None:
            self._ctx.events.unsubscribe(self._events)
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        if self._saving:
            await asyncio.wait(list(self._saving), timeout=5.0)
        # What changed since it was last saved (a survey still flying, or one whose end event was
        # still queued) keeps its tracks so far across the restart.
        for mission_id in [m for m, rec in self.records.items() if self._last_saved.get(m) != _mark(rec)]:
            await self.save(mission_id)

    @property
    def ctx(self) -> ServiceContext:
        assert self._ctx is not None, "the retask service is not started"
        return self._ctx

    def record(self, mission_id: str) -> SurveyRecord | None:
        """The mission's record (created on first sight of a running survey mission)."""
        found = self.records.get(mission_id)
        if found is not None or mission_id in self._plain or self._ctx is None:
            return found
        mission = self._ctx.missions.active.get(mission_id)
        if mission is None:
            return None
        if mission.task.survey is None:
            self._plain[mission_id] = None
            while len(self._plain) > MAX_RECORDS:
                self._plain.popitem(last=False)
            return None
        found = self.records[mission_id] = self._stored(mission_id) or SurveyRecord(
            mission_id, mission.task.survey, {a: list(p) for a, p in mission.plans.items()}
        )
        while len(self.records) > MAX_RECORDS:
            self.records.popitem(last=False)
        return found

    async def find(self, mission_id: str) -> SurveyRecord | None:
        """A snapshot of the mission's record: the one in memory, else the store's (a survey this
        daemon flew before a restart, or one forgotten in memory); None if there is neither."""
        found = self.record(mission_id)
        if found is not None:
            return found.snapshot()
        blob = self.ctx.store.survey_record(mission_id)
        if blob is None:
            return None
        try:
            return await asyncio.to_thread(decode_record, blob)
        except RecordDecodeError as exc:
            log.warning("survey record of %s not read: %s", mission_id, exc)
            return None

    def _stored(self, mission_id: str) -> SurveyRecord | None:
        """The store's copy of a survey resumed after a restart (read once, on the loop)."""
        blob = self.ctx.store.survey_record(mission_id)
        if blob is None:
            return None
        try:
            return decode_record(blob)
        except RecordDecodeError as exc:
            log.warning("survey record of %s not read: %s", mission_id, exc)
            return None

    async def save(self, mission_id: str) -> None:
        """Write the mission's record to the store (encoded in a worker thread)."""
        rec = self.records.get(mission_id)
        if rec is None or self._ctx is None:
            return
        snapshot = rec.snapshot()
        blob = await asyncio.to_thread(encode_record, snapshot)
        self._ctx.store.save_survey_record(mission_id, blob, MAX_RECORDS)
        self._last_saved[mission_id] = _mark(snapshot)
        while len(self._last_saved) > MAX_RECORDS:
            del self._last_saved[next(iter(self._last_saved))]

    def _save_soon(self, mission_id: str) -> None:
        task = asyncio.create_task(self.save(mission_id), name=f"retask-save-{mission_id}")
        self._saving.add(task)
        task.add_done_callback(self._saved)

    def _saved(self, task: asyncio.Task[None]) -> None:
        self._saving.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("survey record not saved", exc_info=task.exception())

    # --- hooks ----------------------------------------------------------------------------------

    async def _on_tick(self, tick: StatusTick) -> None:
        if not any(m.task.survey is not None for m in self.ctx.missions.active.values()):
            return  # no survey flies: a fleet's tick costs one look at the running missions
        for i, session in enumerate(tick.owners):
            mission_id = tick.mode_mission(i)[1]
            if mission_id is None:
                continue
            rec = self.record(mission_id)
            if rec is None:
                continue
            p = tick.report(i).position
            if p is not None:
                rec.track(session.identity, (p.lat, p.lon, p.alt_rel))

    async def _on_status(self, session: AgentSession, status: StatusReport) -> None:
        """A receiver that has flown its own survey gets the legs waiting for it."""
        rec = self.records.get(status.mission_id or "")
        if rec is None or session.identity not in rec.waiting:
            return
        ready, send = rec.waiting[session.identity]
        if status.completed_step >= ready:
            del rec.waiting[session.identity]
            self._send(rec.mission_id, session.identity, send)

    async def _consume(self) -> None:
        assert self._events is not None
        while True:
            event = await self._events.get()
            if event.kind in ENDED and event.mission_id is not None and event.mission_id in self.records:
                self._save_soon(event.mission_id)
                continue
            if event.kind != "agent_excluded" or event.agent is None or event.mission_id is None:
                continue
            try:
                await self.on_left(event.mission_id, event.agent, event.message)
            except Exception:  # one bad proposal must not end re-tasking for the daemon's life
                log.exception("re-tasking %s's share in %s failed", event.agent, event.mission_id)

    # --- the use case ---------------------------------------------------------------------------

    async def on_left(self, mission_id: str, dropped: str, why: str) -> Decision | None:
        """``dropped`` left the survey: propose its unseen share to the others (then by policy)."""
        mission = self.ctx.missions.active.get(mission_id)
        rec = self.record(mission_id)
        if mission is None or rec is None or rec.survey.retask == "off" or mission.state != "running":
            return None
        candidates = [c for a in mission.plans if (c := self._candidate(mission, a, dropped)) is not None]
        survey, tracks = rec.survey, list(rec.snapshot().tracks.values())  # the ticks append meanwhile
        share = survey_points(mission.plans[dropped])
        proposal = await asyncio.to_thread(_propose, survey, tracks, dropped, share, candidates)
        decision = Decision(
            f"r{len(rec.decisions) + 1}",
            dropped,
            why,
            proposal,
            "pending" if proposal.verdict == "proposed" else "none",
        )
        rec.decisions.append(decision)
        self._publish(
            rec,
            decision,
            "retask_proposed" if proposal.verdict == "proposed" else f"retask_{proposal.verdict}",
            f"{dropped} left ({why}): {proposal.reason}",
        )
        if decision.state == "pending" and survey.retask == "automatic":
            try:
                self.decide(mission_id, decision.id, accept=True, by="automatic")
            except RetaskError as exc:  # the mission ended while the proposal was computed
                log.info("re-task %s not applied: %s", decision.id, exc)
        return decision

    def _candidate(self, mission: ActiveMission, ident: str, dropped: str) -> Candidate | None:
        """A member still flying, with where its new legs would start and its energy margin."""
        if ident == dropped or ident in mission.excluded:
            return None
        session = self.ctx.agents.session(ident)
        status = session.status if session is not None else None
        if session is None or status is None or status.position is None:
            return None
        plan = mission.plans[ident]
        done = mission.completed.get(ident, -1)
        if done >= plan[-1].step:
            return None  # home already: not asked to start again
        pos = status.position
        own = survey_points([a for a in plan if a.step > done])
        start = own[-1] if own else (pos.lat, pos.lon)
        home = (session.home.lat, session.home.lon) if session.home is not None else (pos.lat, pos.lon)
        cfg = self._energy
        power = capability_power_w(session.capabilities.battery_wh, session.capabilities.endurance_s, cfg)
        remaining = [a for a in plan if a.step > done]
        here = {ident: (pos.lat, pos.lon, max(pos.alt_rel, 0.0))}
        need = predict_plan_energy({ident: remaining}, here, cfg, None, {ident: power})[ident].energy_wh
        capacity = session.capabilities.battery_wh or cfg.default_battery_wh
        pct = status.battery.pct if status.battery.pct is not None else 100.0
        margin = capacity * (pct - cfg.reserve_pct) / 100.0 - need
        speeds = [a.speed for a in plan if isinstance(a, Waypoints) and a.speed]
        return Candidate(ident, start, home, margin, speeds[-1] if speeds else cfg.speed_mps, power)

    def decide(
        self, mission_id: str, decision_id: str | None, accept: bool, by: str = "operator"
    ) -> Decision:
        """Accept (apply) or reject a pending proposal; ``decision_id`` None: the newest pending one."""
        rec = self.records.get(mission_id)
        pending = [d for d in rec.decisions if d.state == "pending"] if rec is not None else []
        if decision_id is None:
            decision = pending[-1] if pending else None
        else:
            decision = next((d for d in pending if d.id == decision_id), None)
        if rec is None or decision is None:
            what = f"proposal {decision_id}" if decision_id else "proposal"
            raise RetaskError(f"no pending re-task {what} in mission {mission_id}")
        if not accept:
            decision.state, decision.by = "rejected", by
            self._publish(
                rec,
                decision,
                "retask_rejected",
                f"{decision.proposal.gap_m2:.0f} m2 of "
                f"{decision.dropped}'s share stays unseen (rejected by the {by})",
                "warning",
            )
            return decision
        mission = self.ctx.missions.active.get(mission_id)
        if mission is None or mission.state != "running":
            raise RetaskError(f"mission {mission_id} is not running any more")
        self._apply(rec, mission, decision)
        decision.state, decision.by = "applied", by
        self._publish(
            rec, decision, "retask_applied", f"{decision.dropped}'s share: {decision.proposal.reason}"
        )
        return decision

    def _apply(self, rec: SurveyRecord, mission: ActiveMission, decision: Decision) -> None:
        for leg in decision.proposal.legs:
            plan = mission.plans.get(leg.ident)
            if plan is None or leg.ident in mission.excluded:
                continue
            alt = survey_alt(plan, rec.survey.altitude_m or 10.0)
            new_plan, send, ready = extend_plan(plan, leg.points, alt, _speed(plan))
            mission.plans[leg.ident] = rec.planned[leg.ident] = new_plan
            session = self.ctx.agents.session(leg.ident)
            status = session.status if session is not None else None
            reported = status.completed_step if status is not None and status.mission_id == mission.id else -1
            if max(mission.completed.get(leg.ident, -1), reported) >= ready:  # the runner may lag
                self._send(mission.id, leg.ident, send)
            else:
                rec.waiting[leg.ident] = (ready, send)

    def _send(self, mission_id: str, ident: str, send: list[Action]) -> None:
        """The new legs and the return, through the authority at mission priority."""
        ok, why = self.ctx.authority.replace(
            ident, "mission", mission_id, send, "re-task: a dropped drone's share"
        )
        if not ok:
            self.ctx.events.publish(
                "retask_refused",
                f"re-task legs refused: {why}",
                severity="warning",
                agent=ident,
                mission_id=mission_id,
            )

    def _publish(
        self, rec: SurveyRecord, decision: Decision, kind: str, message: str, severity: Severity | None = None
    ) -> None:
        """Publish a decision's event and keep the record as it stands now."""
        self._save_soon(rec.mission_id)
        level: Severity = severity or ("warning" if decision.proposal.verdict == "not_feasible" else "info")
        self.ctx.events.publish(
            kind,
            message,
            severity=level,
            agent=decision.dropped,
            mission_id=rec.mission_id,
            data=decision.summary(),
        )

    def proposals(self, mission_id: str) -> list[dict[str, Any]]:
        """The mission's re-task decisions (pending ones included), newest last."""
        rec = self.records.get(mission_id)
        return [d.summary(gap=True) for d in rec.decisions] if rec else []


def _mark(rec: SurveyRecord) -> tuple[int, tuple[str, ...]]:
    """What a save depends on, cheaply: the track points and the decisions' states."""
    return sum(len(t) for t in rec.tracks.values()), tuple(d.state for d in rec.decisions)


def _speed(plan: list[Action]) -> float | None:
    speeds = [a.speed for a in plan if isinstance(a, Waypoints) and a.speed]
    return speeds[-1] if speeds else None


def _propose(
    survey: SurveyArea,
    tracks: list[list[tuple[float, float, float]]],
    dropped: str,
    share: list[tuple[float, float]],
    candidates: list[Candidate],
) -> RetaskProposal:
    """In a worker thread: the seen grid so far, then the pure decision."""
    from gcs.planning.seen import seen_grid

    grid = seen_grid(survey.area, tracks, survey.swath_m, survey.altitude_m)
    return propose_retask(grid, dropped, share, survey.swath_m, candidates)


def flown_m(track: list[tuple[float, float, float]]) -> float:
    """Horizontal metres of a thinned track."""
    return sum(distance_m(a[0], a[1], b[0], b[1]) for a, b in itertools.pairwise(track))


def planned_m(plan: list[Action], home: tuple[float, float]) -> float:
    """Horizontal metres of a plan from home through its gotos and waypoints (home again at a return)."""
    here, total = home, 0.0
    for a in plan:
        targets: list[tuple[float, float]] = []
        if isinstance(a, Waypoints):
            targets = [(p.lat, p.lon) for p in a.points]
        elif isinstance(a, Goto):
            targets = [(a.lat, a.lon)]
        elif isinstance(a, ReturnToLaunch):
            targets = [home]
        for t in targets:
            total += distance_m(here[0], here[1], t[0], t[1])
            here = t
    return total
