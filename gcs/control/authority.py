"""The vehicle authority: the one place every type-4 command to a drone passes through.

Every source that wants to move, stop or resume a drone (operator API/CLI/dashboard, mission
runner, collision avoidance, connectivity, divergence, the daemon's emergency monitor,
extensions) asks the authority, which decides by a fixed priority (highest first):

    pilot (RC or another ground station, reported by the agent) > operator (land, RTL, hold)
    > vehicle failsafe (reported by the agent) > daemon emergency > collision avoidance
    > connectivity / divergence > mission

* **The pilot has the last word.** While the agent reports ``pilot`` (a mode it did not command)
  nothing is sent to the drone, not even the operator's orders: each is refused and recorded. The
  pilot hands back by selecting the agent's mode; the operator's ``resume`` asks the agent to take
  the drone back (a release it accepts only where the pilot can take it again: docs/cooperation.md).

Rules, per vehicle:
* **Holds are counted per owner.** The first hold sends ``pause``; ``resume`` goes out only when
  the last owner releases. A source can only release its own hold.
* **A lower source never undoes a higher one.** A hold or a new plan is refused while a source of
  higher priority holds the drone or has given it an order (RTL, land, an escape), and while the
  agent reports its own failsafe (only the operator overrides that).
* **Orders expire** when the vehicle is landed and disarmed, so the next mission can start.
* **Every decision is recorded** (accepted or refused, with source and reason): the event log and
  ``GET /api/v1/agents/{id}/authority`` answer "who commanded drone X last and why".

The authority is not a service with its own task: it is called synchronously and posts packets to
the agent's own outbound queue (``AgentManager.post``), so a slow agent delays only itself.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal, Protocol, cast

from pydantic import BaseModel

from protocol.actions import Action
from protocol.packets import Body, CommandSource, PerformActions, StatusReport

Owner = CommandSource
"""Who asks: the same names travel in the type-4 ``source`` field."""

PRIORITY: dict[str, int] = {
    "mission": 10,
    "returns": 10,  # mission-end returns; operator/emergency returns run at their initiator's level
    "divergence": 20,
    "connectivity": 20,
    "extension": 20,
    "collision": 30,
    "daemon_emergency": 40,
    "vehicle_failsafe": 50,
    "operator": 60,
    "pilot": 70,  # reported by the agent: never a source of orders, nothing outranks it
}
HISTORY = 50
PERSISTED_OWNERS = frozenset({"operator"})
AUTOMATIC_HOLDS = ("collision", "connectivity", "divergence")
"""Holds that exist for an airborne conflict: they end when the drone is down."""


class Link(Protocol):
    """What the authority needs of the agent manager."""

    def post(self, identity: str, body: Body, *, urgent: bool = False) -> bool: ...


class Decision(BaseModel):
    """One command decision, as the API shows it."""

    time: float
    source: str
    command: str
    reason: str
    accepted: bool
    detail: str = ""


class VehicleControl(BaseModel):
    """Who controls a drone right now."""

    agent: str
    level: str
    holds: dict[str, str]
    order: str | None
    order_source: str | None
    failsafe: str | None
    pilot: str | None = None
    decisions: list[Decision]


@dataclass
class _Order:
    owner: str
    kind: str
    reason: str


@dataclass(slots=True)
class _Vehicle:
    holds: dict[str, str] = field(default_factory=dict)  # owner -> reason
    order: _Order | None = None
    failsafe: str | None = None
    pilot: str | None = None  # the pilot's mode while a pilot flies the drone
    mission_id: str | None = None
    history: deque[Decision] | None = None  # made at the first decision (~0.7 KiB even empty)
    held_since: dict[str, float] = field(default_factory=dict)  # owner -> monotonic start


Verdict = tuple[bool, str]
"""(accepted, why refused or what was done)."""

EventSink = Callable[[str, str, str, bool, str], None]
"""(agent, source, command, accepted, message) -> publish."""

PersistHook = Callable[[str, str, str | None], None]
"""(agent, owner, reason or None to drop)."""


class VehicleAuthority:
    """Per-vehicle arbiter with an explicit priority; see the module docstring."""

    def __init__(self, link: Link, on_decision: EventSink, persist: PersistHook | None = None) -> None:
        self._link = link
        self._on_decision = on_decision
        self._persist = persist
        self._vehicles: dict[str, _Vehicle] = {}
        self.hold_durations: deque[tuple[str, str, float]] = deque(maxlen=10_000)  # agent, owner, s

    def longest_hold(self, owner: str | None = None, now: float | None = None) -> float:
        """Longest hold (seconds) so far, ended or still running, of ``owner`` (default: any)."""
        now = time.monotonic() if now is None else now
        ended = [d for _, o, d in self.hold_durations if owner is None or o == owner]
        running = [
            now - since
            for v in self._vehicles.values()
            for o, since in v.held_since.items()
            if owner is None or o == owner
        ]
        return max(ended + running, default=0.0)

    def _hold_ended(self, ident: str, vehicle: _Vehicle, owner: str) -> None:
        since = vehicle.held_since.pop(owner, None)
        if since is not None:
            self.hold_durations.append((ident, owner, time.monotonic() - since))

    # --- queries --------------------------------------------------------------------------------

    def _vehicle(self, ident: str) -> _Vehicle:
        return self._vehicles.setdefault(ident, _Vehicle())

    def level(self, ident: str) -> int:
        """Priority of whatever controls the drone now (0: nothing above its plan)."""
        vehicle = self._vehicles.get(ident)
        if vehicle is None:
            return 0
        levels = [PRIORITY[o] for o in vehicle.holds]
        if vehicle.order is not None:
            levels.append(PRIORITY[vehicle.order.owner])
        if vehicle.failsafe is not None:
            levels.append(PRIORITY["vehicle_failsafe"])
        if vehicle.pilot is not None:
            levels.append(PRIORITY["pilot"])
        return max(levels, default=0)

    def held_by(self, ident: str) -> dict[str, str]:
        vehicle = self._vehicles.get(ident)
        return dict(vehicle.holds) if vehicle else {}

    def is_held(self, ident: str, owner: str | None = None) -> bool:
        holds = self.held_by(ident)
        return bool(holds) if owner is None else owner in holds

    def order_owner(self, ident: str) -> str | None:
        vehicle = self._vehicles.get(ident)
        return vehicle.order.owner if vehicle and vehicle.order else None

    def failsafe(self, ident: str) -> str | None:
        vehicle = self._vehicles.get(ident)
        return vehicle.failsafe if vehicle else None

    def pilot(self, ident: str) -> str | None:
        """The pilot's mode while a pilot flies the drone (the agent reports it), else None."""
        vehicle = self._vehicles.get(ident)
        return vehicle.pilot if vehicle else None

    def may_command(self, ident: str, owner: str) -> bool:
        """True when ``owner`` is not outranked by anything controlling the drone now."""
        return self._blocker(ident, owner) is None

    def request(self, ident: str, owner: Owner, command: str, reason: str) -> Verdict:
        """Ask before acting outside the authority (a withdrawal): recorded when refused."""
        blocker = self._blocker(ident, owner)
        if blocker is not None:
            return self._refuse(ident, owner, command, reason, blocker)
        return True, "allowed"

    def control(self, ident: str) -> VehicleControl:
        vehicle = self._vehicles.get(ident) or _Vehicle()
        level = self.level(ident)
        name = next((o for o, p in PRIORITY.items() if p == level and level), "plan")
        if vehicle.failsafe and level == PRIORITY["vehicle_failsafe"]:
            name = "vehicle_failsafe"
        return VehicleControl(
            agent=ident,
            level=name,
            holds=dict(vehicle.holds),
            order=vehicle.order.kind if vehicle.order else None,
            order_source=vehicle.order.owner if vehicle.order else None,
            failsafe=vehicle.failsafe,
            pilot=vehicle.pilot,
            decisions=list(vehicle.history or ()),
        )

    # --- commands -------------------------------------------------------------------------------

    def hold(self, ident: str, owner: Owner, reason: str, mission_id: str | None = None) -> Verdict:
        """Stop the drone where it is (its queue is kept) on behalf of ``owner``."""
        blocker = self._blocker(ident, owner)
        if blocker is not None:
            return self._refuse(ident, owner, "hold", reason, blocker)
        vehicle = self._vehicle(ident)
        first = not vehicle.holds
        fresh = owner not in vehicle.holds
        vehicle.holds[owner] = reason
        vehicle.held_since.setdefault(owner, time.monotonic())
        if owner in PERSISTED_OWNERS and self._persist is not None and fresh:
            self._persist(ident, owner, reason)
        if not first:
            if fresh:
                self._record(ident, owner, "hold", reason, True, "already paused by another source")
            return True, "already paused"
        self._post(ident, owner, "pause", reason, mission_id)
        self._record(ident, owner, "hold", reason, True, "pause sent")
        return True, "pause sent"

    def release(self, ident: str, owner: Owner, reason: str, mission_id: str | None = None) -> Verdict:
        """Drop ``owner``'s hold; the drone resumes only when no owner holds it any more."""
        vehicle = self._vehicles.get(ident)
        if vehicle is not None and vehicle.pilot is not None and owner == "operator":
            # The operator's release of the pilot's control: the agent decides (docs/cooperation.md).
            self._post(ident, owner, "resume", reason, mission_id)
            self._record(ident, owner, "release pilot", reason, True, f"asked of the agent ({vehicle.pilot})")
            return True, f"release asked of the agent (pilot in {vehicle.pilot})"
        if vehicle is None or owner not in vehicle.holds:
            return False, f"{owner} holds nothing on {ident}"
        del vehicle.holds[owner]
        self._hold_ended(ident, vehicle, owner)
        if owner in PERSISTED_OWNERS and self._persist is not None:
            self._persist(ident, owner, None)
        if vehicle.holds:
            still = ", ".join(sorted(vehicle.holds))
            self._record(ident, owner, "release", reason, True, f"still held by {still}")
            return True, f"still held by {still}"
        if vehicle.pilot is not None:
            detail = f"no resume: pilot in control ({vehicle.pilot})"
            self._record(ident, owner, "release", reason, True, detail)
            return True, "pilot in control"
        if vehicle.failsafe is not None and owner != "operator":
            self._record(ident, owner, "release", reason, True, "no resume: vehicle failsafe in force")
            return True, "vehicle failsafe in force"
        self._post(ident, owner, "resume", reason, mission_id)
        self._record(ident, owner, "release", reason, True, "resume sent")
        return True, "resume sent"

    def replace(
        self,
        ident: str,
        owner: Owner,
        mission_id: str,
        actions: list[Action],
        reason: str,
        *,
        order: str | None = None,
        await_release: int | None = None,
        keep_holds: bool = False,
        release_anchor: str | None = None,
    ) -> Verdict:
        """Give the drone a new action list on behalf of ``owner``.

        ``order`` names what it is (``rtl``, ``land``, ``escape``...) for anything above the
        mission: it stays in force, refusing lower sources, until the vehicle is down or a source
        of at least the same priority replaces it. Holds of lower priority are superseded (the
        agent's replace ends its pause) unless ``keep_holds`` (a mission re-sent to a rejoining
        agent under a hold): then the pause is re-sent right behind the plan. ``release_anchor``
        travels with the plan (a mission's release-beacon chain, protocol/beacon.py).
        """
        blocker = self._blocker(ident, owner, ignore_holds=keep_holds)
        if blocker is not None:
            return self._refuse(ident, owner, order or "plan", reason, blocker)
        vehicle = self._vehicle(ident)
        rank = PRIORITY[owner]
        if owner == "operator" and vehicle.failsafe is not None:
            vehicle.failsafe = None  # the agent drops its latch on an operator command too
        if not keep_holds:
            for other in [o for o in vehicle.holds if PRIORITY[o] <= rank]:
                del vehicle.holds[other]
                self._hold_ended(ident, vehicle, other)
                if other in PERSISTED_OWNERS and self._persist is not None:
                    self._persist(ident, other, None)
        if order is not None and rank > PRIORITY["mission"]:
            vehicle.order = _Order(owner, order, reason)
        elif vehicle.order is not None and PRIORITY[vehicle.order.owner] <= rank:
            vehicle.order = None
        vehicle.mission_id = mission_id
        body = PerformActions(
            mission_id=mission_id,
            mode="replace",
            actions=actions,
            reason=reason[:200],
            source=owner,
            await_release=await_release,
            release_anchor=release_anchor,
        )
        urgent = rank > PRIORITY["mission"] or bool(vehicle.holds)
        self._link.post(ident, body, urgent=urgent)
        if vehicle.holds:
            self._post(ident, owner, "pause", next(iter(vehicle.holds.values())), mission_id, urgent=urgent)
        self._record(ident, owner, order or "plan", reason, True, f"{len(actions)} actions")
        return True, f"{len(actions)} actions sent"

    def append(
        self, ident: str, owner: Owner, mission_id: str, actions: list[Action], reason: str
    ) -> Verdict:
        """Add actions behind the drone's queue on behalf of ``owner`` (a cluster-forwarded
        ``append``): refused while a higher source holds or orders the drone, like a replace."""
        blocker = self._blocker(ident, owner)
        if blocker is not None:
            return self._refuse(ident, owner, "append", reason, blocker)
        body = PerformActions(
            mission_id=mission_id, mode="append", actions=actions, reason=reason[:200], source=owner
        )
        self._link.post(ident, body)
        self._record(ident, owner, "append", reason, True, f"{len(actions)} actions")
        return True, f"{len(actions)} actions appended"

    def end_order(self, ident: str, owner: Owner, reason: str) -> None:
        """``owner``'s order is done (an escape reached its altitude): lower sources may act again."""
        vehicle = self._vehicles.get(ident)
        if vehicle is not None and vehicle.order is not None and vehicle.order.owner == owner:
            self._record(ident, owner, f"end {vehicle.order.kind}", reason, True)
            vehicle.order = None

    def refused_where_linked(self, ident: str, owner: str, mode: str, holder: str, why: str) -> None:
        """A command we forwarded (cluster) was refused by the vehicle authority of the daemon
        holding the link: what we recorded as given is taken back, so our record says what the
        drone was actually told (a refused hold is no hold of ours; a refused order no order)."""
        vehicle = self._vehicles.get(ident)
        if vehicle is not None:
            if mode == "pause" and owner in vehicle.holds:
                del vehicle.holds[owner]
                self._hold_ended(ident, vehicle, owner)
                if owner in PERSISTED_OWNERS and self._persist is not None:
                    self._persist(ident, owner, None)
            elif mode == "replace" and vehicle.order is not None and vehicle.order.owner == owner:
                vehicle.order = None
        command = {"pause": "hold", "resume": "release"}.get(mode, mode)
        self._record(ident, owner, command, f"forwarded to {holder}", False, f"refused by {holder}: {why}")

    def restore_hold(self, ident: str, owner: str, reason: str) -> None:
        """A persisted hold found at daemon start: in force again, sent when the agent joins."""
        vehicle = self._vehicle(ident)
        vehicle.holds[owner] = reason
        vehicle.held_since.setdefault(owner, time.monotonic())

    def drop_holds(self, ident: str, owners: tuple[str, ...], reason: str) -> None:
        """Forget ``owners``' holds without a resume (the drone landed or left the picture)."""
        vehicle = self._vehicles.get(ident)
        if vehicle is None:
            return
        for owner in [o for o in owners if o in vehicle.holds]:
            del vehicle.holds[owner]
            self._hold_ended(ident, vehicle, owner)
            self._record(ident, owner, "drop hold", reason, True)

    def reassert(self, ident: str) -> None:
        """Re-send the pause of a held drone (a rejoin, or the periodic safety re-send)."""
        vehicle = self._vehicles.get(ident)
        if vehicle is not None and vehicle.holds and vehicle.pilot is None:
            owner, reason = max(vehicle.holds.items(), key=lambda item: PRIORITY[item[0]])
            self._post(ident, owner, "pause", reason, vehicle.mission_id)

    # --- vehicle state --------------------------------------------------------------------------

    def observe(self, ident: str, status: StatusReport) -> None:
        """Follow the pilot and the agent's own failsafe; end orders once the vehicle is down."""
        vehicle = self._vehicle(ident)
        if status.pilot != vehicle.pilot:
            if status.pilot is not None and vehicle.pilot is None:
                self._record(ident, "pilot", "pilot", f"mode {status.pilot}", True, "reported by agent")
            elif status.pilot is None:
                back = f"vehicle in {status.mode}"
                self._record(ident, "pilot", "hand back", back, True, "reported by agent")
            vehicle.pilot = status.pilot
        if status.mission_id:
            vehicle.mission_id = status.mission_id
        if status.failsafe != vehicle.failsafe:
            if status.failsafe is not None:
                self._record(
                    ident, "vehicle_failsafe", "failsafe", status.failsafe, True, "reported by agent"
                )
            vehicle.failsafe = status.failsafe
        if status.landed and not status.armed:
            if vehicle.order is not None:
                self._record(ident, vehicle.order.owner, f"end {vehicle.order.kind}", "vehicle landed", True)
                vehicle.order = None
            self.drop_holds(ident, AUTOMATIC_HOLDS, "vehicle landed")

    # --- internals ------------------------------------------------------------------------------

    def _blocker(self, ident: str, owner: str, ignore_holds: bool = False) -> str | None:
        vehicle = self._vehicles.get(ident)
        if vehicle is None:
            return None
        rank = PRIORITY[owner]
        if vehicle.pilot is not None:
            return f"pilot in control ({vehicle.pilot})"
        if vehicle.failsafe is not None and rank < PRIORITY["vehicle_failsafe"]:
            return f"vehicle failsafe {vehicle.failsafe}"
        if vehicle.order is not None and PRIORITY[vehicle.order.owner] > rank:
            return f"{vehicle.order.owner} {vehicle.order.kind} ({vehicle.order.reason})"
        if not ignore_holds:
            higher = [o for o in vehicle.holds if PRIORITY[o] > rank]
            if higher:
                top = max(higher, key=PRIORITY.__getitem__)
                return f"{top} hold ({vehicle.holds[top]})"
        return None

    def _post(
        self,
        ident: str,
        owner: str,
        mode: Literal["pause", "resume"],
        reason: str,
        mission_id: str | None,
        urgent: bool = True,
    ) -> None:
        vehicle = self._vehicle(ident)
        body = PerformActions(
            mission_id=mission_id or vehicle.mission_id or "authority",
            mode=mode,
            reason=reason[:200],
            source=cast(Owner, owner),
        )
        self._link.post(ident, body, urgent=urgent)

    def _refuse(self, ident: str, owner: str, command: str, reason: str, blocker: str) -> Verdict:
        self._record(ident, owner, command, reason, False, f"refused: outranked by {blocker}")
        return False, f"outranked by {blocker}"

    def _record(
        self, ident: str, owner: str, command: str, reason: str, accepted: bool, detail: str = ""
    ) -> None:
        decision = Decision(
            time=time.time(),
            source=owner,
            command=command,
            reason=reason[:200],
            accepted=accepted,
            detail=detail,
        )
        vehicle = self._vehicle(ident)
        if vehicle.history is None:
            vehicle.history = deque(maxlen=HISTORY)
        vehicle.history.append(decision)
        message = f"{command} by {owner}: {reason[:160]}" + (f" ({detail})" if detail else "")
        self._on_decision(ident, owner, command, accepted, message)


__all__ = ["PRIORITY", "Decision", "Owner", "VehicleAuthority", "VehicleControl"]
