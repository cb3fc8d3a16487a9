"""The sessions registry: who is on the fleet list, who is connected, lost, or linked elsewhere.

Why a class of its own: admission adds sessions, the liveness watch marks them lost, the sender
looks them up, the API retires them, the cluster node registers the drones linked to other
daemons; none of these jobs needs the others to read the fleet list.
"""

from __future__ import annotations

from collections.abc import Callable

from gcs.link.outbox import Outbox
from gcs.link.session import AgentSession
from gcs.observe.events import EventBus


class RetireRefused(Exception):
    """Why an agent cannot leave the fleet list now: ``status`` 404 (not on it) or 409 (in use)."""

    def __init__(self, status: int, title: str, detail: str) -> None:
        super().__init__(detail)
        self.status, self.title, self.detail = status, title, detail


class SessionRegistry:
    """Every agent session this daemon holds (open or not), the lost ones, and the remote ones."""

    def __init__(self, events: EventBus) -> None:
        self._events = events
        self.sessions: dict[str, AgentSession] = {}
        self.lost: set[str] = set()
        # Cluster mode (gcs/cluster): agents linked to other daemons (their sessions forward).
        self.remote: dict[str, AgentSession] = {}
        # Cluster mode: which daemon holds an agent's link (``ClusterNode.holder``: the newest
        # epoch of its registry record); None on a single daemon.
        self.holder_of: Callable[[str], str | None] | None = None

    def session(self, identity: str) -> AgentSession | None:
        session = self.sessions.get(identity)
        if session is not None and session.open:
            return session
        return self.remote.get(identity)  # linked to another daemon of the cluster (or None)

    def connected(self) -> list[AgentSession]:
        return [s for s in self.sessions.values() if s.open]

    # --- where each agent's link is: the one answer every view gives (API, stream, cluster, CLI) ---

    def link(self, identity: str) -> AgentSession | None:
        """The session that stands for ``identity`` in every view: our open session, else (cluster
        mode) the mirror of the daemon holding its link now, else our last, closed session. An
        agent that moved to another daemon is shown there, never also as our disconnected one."""
        own = self.sessions.get(identity)
        if own is not None and own.open:
            return own
        remote = self.remote.get(identity)
        return remote if remote is not None and remote.open else own

    def holder(self, identity: str) -> str | None:
        """The daemon holding ``identity``'s link (cluster mode), from the cluster's one source of
        truth, the registry record's epoch; None on a single daemon."""
        return None if self.holder_of is None else self.holder_of(identity)

    def fleet(self) -> list[AgentSession]:
        """Every agent on the fleet list once, as :meth:`link` shows it: this daemon's sessions and,
        in cluster mode, the agents linked to other daemons."""
        names = dict.fromkeys([*self.sessions, *(i for i, s in self.remote.items() if s.open)])
        return [s for s in (self.link(i) for i in names) if s is not None]

    def retire(self, identity: str, mission: str | None = None) -> AgentSession:
        """Take a disconnected agent off the fleet list (a ghost, a drone gone for good).

        ``mission`` is the mission it still flies, if any: then it stays. Its CID stays reserved in
        the store, so if it ever comes back it re-joins as before. Raises :class:`RetireRefused`.
        """
        session = self.sessions.get(identity)
        if session is None:
            raise RetireRefused(404, "no such agent", f"agent {identity!r} is not on the fleet list")
        if session.open:
            raise RetireRefused(409, "agent connected", f"{identity} is connected: stop its agent first")
        if mission is not None:
            raise RetireRefused(
                409, "agent in a mission", f"{identity} flies mission {mission}: abort it first"
            )
        del self.sessions[identity]
        self.lost.discard(identity)
        return session

    def cut_off(self, outbox: Outbox, reason: str) -> None:
        """A session's outbox gave up on the peer (overflow or no drain): the session ends."""
        session = self.sessions.get(outbox.identity)
        if session is None or session.outbox is not outbox or not session.open:
            return
        session.open = False
        self._events.publish("agent_cut_off", f"{reason}; cut off", severity="error", agent=session.identity)


__all__ = ["RetireRefused", "SessionRegistry"]
