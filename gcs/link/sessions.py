"""The sessions registry: who is on the fleet list, who is connected, lost, or linked elsewhere.

Why a class of its own: admission adds sessions, the liveness watch marks them lost, the sender
looks them up, the API retires them, the cluster node registers the drones linked to other
daemons; none of these jobs needs the others to read the fleet list.
"""

from __future__ import annotations

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

    def session(self, identity: str) -> AgentSession | None:
        session = self.sessions.get(identity)
        if session is not None and session.open:
            return session
        return self.remote.get(identity)  # linked to another daemon of the cluster (or None)

    def connected(self) -> list[AgentSession]:
        return [s for s in self.sessions.values() if s.open]

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
