"""The command port: the one object that puts anything on an agent's link that changes what it does.

A type-4 order (through :class:`gcs.control.authority.VehicleAuthority`, which arbitrates it by priority),
a type-3 geofence or parameter set, a type-5 barrier release and the telemetry's replay
acknowledgement all leave the daemon here. Services, extensions, the mission runner and the
cluster get this port (or its authority) and a read-only view of the agents
(:class:`gcs.core.context.AgentsView`), never the agent manager's ``post``/``send``/``burst``: a path
around the authority cannot be written without reaching into the composition root.

Why one port: a geofence sent beside it left ``geofences`` (what the emergency monitor checks)
stale, and a forwarded ``append`` reached a drone an operator held. Here the fence view is
updated by the same call that sends the fence, and every type-4 body is arbitrated.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Protocol

from gcs.control.authority import PRIORITY, VehicleAuthority, Verdict
from gcs.cooperation.returns import RETURN_PREFIX
from protocol.packets import (
    AgentParameters,
    Body,
    Geofence,
    PerformActions,
    SetParameters,
    SyncSignal,
)

GeofenceNotice = Callable[[list[str]], None]
"""Told who got a geofence (or its removal): the daemon publishes the event."""


class AgentLink(Protocol):
    """What the port needs of the agent manager: its send side, held by nothing else."""

    def post(self, identity: str, body: Body, *, urgent: bool | None = None) -> bool: ...

    def burst(self, identities: list[str], body: Body) -> int: ...


class CommandPort:
    """Orders (arbitrated), geofences, parameters, barrier releases and replay acks to agents."""

    def __init__(
        self, link: AgentLink, authority: VehicleAuthority, on_geofence: GeofenceNotice | None = None
    ) -> None:
        self._link = link
        self.authority = authority
        self._on_geofence = on_geofence
        self._geofences: dict[str, Geofence] = {}  # the fence each agent was last sent

    @property
    def geofences(self) -> Mapping[str, Geofence]:
        """The fence each agent was last sent (the emergency monitor checks positions against it)."""
        return self._geofences

    # --- type 3 -----------------------------------------------------------------------------------

    def configure(self, identity: str, body: SetParameters) -> bool:
        """Send one type-3 body to one agent; a fence in it updates :attr:`geofences` when it went out."""
        if not self._link.post(identity, body):
            return False
        if body.geofence is not None:
            self._geofences[identity] = body.geofence
        elif body.clear_geofence:
            self._geofences.pop(identity, None)
        return True

    def set_geofence(self, geofence: Geofence | None, agents: list[str]) -> list[str]:
        """Install (None: remove) a geofence on each agent; returns who got it (event published)."""
        body = SetParameters(geofence=geofence, clear_geofence=geofence is None)
        delivered = [a for a in agents if self.configure(a, body)]  # each agent's own outbox
        if self._on_geofence is not None:
            self._on_geofence(delivered)
        return delivered

    def set_parameters(self, parameters: AgentParameters, agents: list[str]) -> list[str]:
        """Push agent parameters (link range, lost-link action...); returns who got them."""
        body = SetParameters(parameters=parameters)
        return [a for a in agents if self.configure(a, body)]

    def acknowledge_replay(self, identity: str, until: float) -> bool:
        """Tell an agent its replayed reports up to ``until`` are stored (it may forget them)."""
        return self._link.post(identity, SetParameters(replay_stored=until))

    # --- type 5 -----------------------------------------------------------------------------------

    def release_barrier(self, members: list[str], mission_id: str, step: int, *, urgent: bool = False) -> int:
        """The one release path: ``step`` of ``mission_id`` released to ``members``; how many got it.

        Several members get one burst (encoded once, written in one pass); a single member (a
        repeated arrival, a lost release re-sent, a return's wait point) gets it on its outbox.
        """
        body = SyncSignal(mission_id=mission_id, step=step, kind="release")
        if len(members) == 1:
            return int(self._link.post(members[0], body, urgent=urgent or None))
        return self._link.burst(members, body)

    # --- bodies another daemon of the cluster forwards --------------------------------------------

    def forwarded(self, identity: str, body: Body, sender: str, urgent: bool = False) -> Verdict:
        """A body another daemon sent our agent: type 4 through the authority at its source's
        priority (refusals recorded here), type 3 through :meth:`configure`, a release through
        :meth:`release_barrier`; anything else is refused (no other body travels that way)."""
        if isinstance(body, PerformActions):
            return self._order(identity, body, sender)
        if isinstance(body, SetParameters):
            return self.configure(identity, body), "parameters"
        if isinstance(body, SyncSignal) and body.kind == "release":
            sent = self.release_barrier([identity], body.mission_id, body.step, urgent=urgent)
            return bool(sent), "release"
        return False, f"{type(body).__name__} is not forwarded to agents"

    def _order(self, identity: str, body: PerformActions, sender: str) -> Verdict:
        authority = self.authority
        owner = body.source or "mission"
        reason = f"{body.reason or body.mode} (via {sender})"
        planned = PRIORITY[owner] <= PRIORITY["mission"]
        if body.mode == "pause":
            if planned:  # a plan-level pause re-sends the sender's holds: ours re-sends our own
                return True, "plan pause: our own holds stand"
            return authority.hold(identity, owner, reason, body.mission_id)
        if body.mode == "resume":
            return authority.release(identity, owner, reason, body.mission_id)
        if body.mode == "replace":
            return authority.replace(
                identity,
                owner,
                body.mission_id,
                list(body.actions),
                reason,
                order=_order_kind(owner, body.mission_id),
                await_release=body.await_release,
                keep_holds=planned,  # a plan queues behind any hold, as the leader's did
            )
        return authority.append(identity, owner, body.mission_id, list(body.actions), reason)


def _order_kind(owner: str, mission_id: str) -> str | None:
    """The order a forwarded replace gives, as the sending authority recorded it: a return program
    (its mission id says rtl or land) above the mission's level; nothing else is an order."""
    if PRIORITY[owner] > PRIORITY["mission"] and mission_id.startswith(RETURN_PREFIX):
        return mission_id[len(RETURN_PREFIX) :].split("-", 1)[0]
    return None


__all__ = ["AgentLink", "CommandPort"]
