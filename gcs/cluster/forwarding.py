"""Orders between daemons: ours for drones linked elsewhere, theirs for drones linked here.

What a daemon sends a drone linked to another daemon goes out on ``fleet.down.<identity>`` (the
type-4 packet, with its source); the holding daemon passes it through its own command port (its
vehicle authority decides) and answers a command on ``fleet.result.<sender>``; a refusal comes
back to the sender's authority. An order sent under an older lease token than the mission
record's (a stale leader's), or an older airspace token than one already seen, is refused here
(docs/cluster.md, "Fencing").
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections import deque
from typing import TYPE_CHECKING, Any

from gcs.control.authority import PRIORITY
from protocol.packets import Body, PerformActions
from protocol.wire import FrameDecoder, encode

if TYPE_CHECKING:
    from nats.aio.msg import Msg

    from gcs.cluster.node import ClusterNode

log = logging.getLogger("gcs.cluster")

PENDING_LIMIT = 2000  # forwarded commands awaiting the holder's answer (oldest dropped beyond)
PENDING_TTL_S = 30.0  # an answer later than this is logged without its command
AIRSPACE_LEASE = "airspace"  # its holder decides collisions for the whole fleet and prunes


def frame(body: Body) -> bytes:
    return encode(body, 0)


def unframe(data: bytes) -> Body | None:
    frames = list(FrameDecoder().feed(data))
    return frames[0].body if frames else None


class Forwarder:
    """Forwarded orders of one daemon (``ClusterNode.forwarder``)."""

    def __init__(self, node: ClusterNode) -> None:
        self.node = node
        self._pending: dict[int, tuple[str, str, float]] = {}  # seq -> (agent, command, sent at)
        self._seq = 0
        self.refusals: deque[dict[str, Any]] = deque(maxlen=200)  # holders' refusals of our commands
        self.fenced_orders = 0  # forwarded orders refused: sent under an older lease token
        self._airspace_token = 0  # newest airspace lease token seen on a forwarded collision order

    def forward(self, identity: str, body: Body, urgent: bool) -> None:
        """Post ``body`` through the daemon holding the link; a command's answer (delivered or
        refused by that daemon's vehicle authority) comes back on ``fleet.result.<us>``."""
        nc = self.node.state.nc
        if nc is None or nc.is_closed:
            return
        data, headers = frame(body), {"daemon": self.node.daemon_id, "urgent": "1" if urgent else ""}
        mission_id = getattr(body, "mission_id", None)
        token = self.node.state.leases.token(mission_id) if isinstance(mission_id, str) else None
        if token is not None:  # a leader's order: the holder refuses it once a newer leader stamped
            headers["mission"], headers["lease"] = str(mission_id), str(token)
        airspace = self.node.state.leases.token(AIRSPACE_LEASE)
        if isinstance(body, PerformActions) and body.source == "collision" and airspace is not None:
            headers["airspace"] = str(airspace)
        reply = ""
        if isinstance(body, PerformActions):
            self._seq += 1
            headers["seq"] = str(self._seq)
            reply = f"fleet.result.{self.node.daemon_id}"
            self._remember(self._seq, identity, f"{body.source or 'mission'} {body.mode}")
        subject = f"fleet.down.{identity}"
        self.node.state.send(subject, data, reply=reply, headers=headers)

    def _remember(self, seq: int, identity: str, command: str) -> None:
        now = time.monotonic()
        self._pending[seq] = (identity, command, now)
        if len(self._pending) > PENDING_LIMIT or next(iter(self._pending.values()))[2] < now - PENDING_TTL_S:
            for old in [k for k, (_, _, at) in self._pending.items() if at < now - PENDING_TTL_S]:
                del self._pending[old]
            while len(self._pending) > PENDING_LIMIT:
                del self._pending[next(iter(self._pending))]

    async def down(self, msg: Msg) -> None:
        identity = msg.subject.split(".", 2)[2]
        session = self.node.daemon.agents.sessions.get(identity)
        if session is None or not session.open or (msg.headers or {}).get("daemon") == self.node.daemon_id:
            return
        body = unframe(msg.data)
        if body is None:
            return
        headers = msg.headers or {}
        stale = self.stale_order(headers)
        if stale is not None:
            self.fenced_orders += 1
            log.warning("refused %s for %s: %s", type(body).__name__, identity, stale)
            delivered, why = False, stale
        else:
            # Whatever another daemon sends our agent passes our command port: orders through our
            # vehicle authority at their source's priority (refusals recorded here), fences kept.
            delivered, why = self.node.daemon.commands.forwarded(
                identity, body, headers.get("daemon", "?"), bool(headers.get("urgent"))
            )
        if isinstance(body, PerformActions) and msg.reply:
            answer = {
                "agent": identity,
                "seq": headers.get("seq", ""),
                "daemon": self.node.daemon_id,
                "delivered": delivered,
                "reason": why,
                "level": self.node.daemon.authority.level(identity),
            }
            with contextlib.suppress(Exception):
                await msg.respond(json.dumps(answer).encode())

    def stale_order(self, headers: dict[str, str]) -> str | None:
        """Why a forwarded order is refused as a stale leader's (its lease token is older than the
        one on the mission record, or than an airspace token already seen), else None."""
        try:
            lease, airspace = int(headers.get("lease") or 0), int(headers.get("airspace") or 0)
        except ValueError:
            return "bad lease header"
        mission_id = headers.get("mission")
        if lease and mission_id:
            raw = self.node.state.mirror["missions"].get(mission_id)
            current = int(json.loads(raw).get("lease", 0)) if raw else 0
            if current > lease:
                return f"stale leader: lease token {lease} of {mission_id} is older than {current}"
        if airspace:
            if airspace < self._airspace_token:
                return f"stale airspace decider: token {airspace} older than {self._airspace_token}"
            self._airspace_token = airspace
        return None

    async def result(self, msg: Msg) -> None:
        """The holder's answer to a command we forwarded: a refusal is recorded (event, the
        drone's level raised so the airspace decider treats it as outranked right away)."""
        try:
            answer = json.loads(msg.data)
            identity, delivered = str(answer["agent"]), bool(answer["delivered"])
            seq, holder, why = int(answer.get("seq") or 0), str(answer["daemon"]), str(answer["reason"])
            level = int(answer.get("level", 0))
        except (ValueError, KeyError, TypeError):
            log.warning("bad command answer on %s: %r", msg.subject, msg.data[:200])
            return
        _, command, _ = self._pending.pop(seq, (identity, "command", 0.0))
        if delivered:
            return
        from gcs.cluster.node import RemoteSession  # the node module imports this one

        remote = self.node.daemon.agents.remote.get(identity)
        if isinstance(remote, RemoteSession) and remote.daemon == holder:
            remote.level = max(remote.level, level)
        source, _, mode = command.partition(" ")
        if mode == "resume" or source not in PRIORITY:
            return  # nothing of ours to release there: not a refusal worth recording
        self.refusals.append({"agent": identity, "daemon": holder, "command": command, "reason": why})
        # Our authority takes back what it recorded as given; its decision event says who refused
        # and why (throttled per drone, source and command like every decision event).
        self.node.daemon.authority.refused_where_linked(identity, source, mode, holder, why)
