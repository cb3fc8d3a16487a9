"""The link's send side: one packet to one agent (``post``, ``send``) or one to many (``burst``).

Why apart: only the vehicle authority and the command port (gcs/control/) hold it, through the
agent manager (tests/architecture/test_imports.py checks who calls ``post``/``burst``). A session
linked to another daemon of the cluster forwards what it is given there.
"""

from __future__ import annotations

import time

from gcs.link.outbox import Outbox
from gcs.link.send_pool import SendPool
from gcs.link.sessions import SessionRegistry
from protocol.packets import Body, packet_type_of
from protocol.wire import encode


class LinkSender:
    """Puts frames on agents' outboxes (and sockets), found through the sessions registry."""

    def __init__(self, registry: SessionRegistry) -> None:
        self._registry = registry
        self._send_pool = SendPool()  # a large burst's sends on two threads (its thread starts then)

    async def send(self, identity: str, body: Body, *, urgent: bool | None = None) -> bool:
        """Queue ``body`` for ``identity`` and wait until it is written and drained.

        True once the frame is on its way; False if the agent is not connected or was cut off
        (it overflowed its queue or did not drain within ``send_timeout_s``). ``urgent`` puts the
        frame ahead of queued mission traffic; ``None`` picks the lane from the packet.
        """
        session = self._registry.session(identity)
        if session is None:
            return False
        return await session.send(body, urgent=urgent)

    def post(self, identity: str, body: Body, *, urgent: bool | None = None) -> bool:
        """Queue ``body`` for ``identity`` without waiting; False if it is not connected (or overflowed)."""
        session = self._registry.session(identity)
        if session is None:
            return False
        return session.post(body, urgent=urgent)

    def burst(self, identities: list[str], body: Body) -> int:
        """Send ``body`` to every connected agent of ``identities`` in one pass; how many got it.

        Encoded once per protocol version; each agent's socket is written right away (behind
        what its outbox still holds), with no task switch per agent: a barrier release reaches
        1,000 agents in one go.
        """
        frames: dict[int, bytes] = {}
        ptype = packet_type_of(body)
        sent = 0
        now = time.monotonic()
        registry = self._registry
        remote = registry.remote
        local = registry.sessions
        targets: list[tuple[Outbox, bytes]] = []
        for identity in identities:
            session = local.get(identity)
            if session is None or not session.open:
                session = remote.get(identity)  # (registry.session's lookup, inline: one per agent)
                if session is None:
                    continue
            if identity in remote:  # linked to another daemon of the cluster: forwarded there
                sent += session.post(body)
                continue
            frame = frames.get(session.version)
            if frame is None:
                frame = frames[session.version] = encode(body, 0, session.version)
            targets.append((session.outbox, frame))
        if not targets:
            return sent
        # Plain sockets with nothing waiting are stamped and sent by the thread that sends them, a
        # large burst on two threads (gcs/link/send_pool.py); the others go through write_now.
        taken, results = self._send_pool.take_and_send(targets, Outbox.take_direct)
        for (outbox, frame), job, result in zip(targets, taken, results, strict=True):
            if job is None:
                sent += outbox.write_now(frame, ptype, now)
            else:
                assert result is not None  # a job taken was sent: bytes taken or the error
                sent += outbox.finish_direct(job[1], result, now)
        return sent

    def close(self) -> None:
        """The send pool's threads end (the daemon is stopping)."""
        self._send_pool.close()


__all__ = ["LinkSender"]
