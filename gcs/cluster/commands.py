"""Operator commands for any drone of the cluster, run where its link is.

``POST /api/v1/cluster/fleet/{hold,resume,rtl,land}`` on any daemon groups the drones by the
daemon holding their link (``ClusterNode.holder``): its own are commanded here, the others'
daemons get a request on ``fleet.cmd.<daemon>`` and apply it through their vehicle authority
like a local operator command; the answer lists what was delivered and why each other drone
was not (docs/cluster.md).
"""

from __future__ import annotations

import json
import logging
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from nats.aio.msg import Msg

    from gcs.cluster.node import ClusterNode

log = logging.getLogger("gcs.cluster")

COMMAND_TIMEOUT_S = 5.0


class OperatorRoute:
    """Routes operator commands to the daemons holding the drones (``ClusterNode.operator_route``)."""

    def __init__(self, node: ClusterNode) -> None:
        self.node = node

    async def command(
        self, command: str, agents: list[str] | None, reason: str
    ) -> tuple[list[str], dict[str, str]]:
        """Run an operator command on each drone's own daemon (through its vehicle authority);
        returns (delivered, refused: drone -> why, as that daemon answered)."""
        targets = agents if agents is not None else sorted(self.node.fleet_identities())
        by_daemon: dict[str, list[str]] = {}
        refused: dict[str, str] = {}
        for identity in targets:
            holder = self.node.holder(identity)
            if holder is None:
                refused[identity] = "no daemon of the cluster holds its link"
            else:
                by_daemon.setdefault(holder, []).append(identity)
        delivered: list[str] = []
        for daemon, group in sorted(by_daemon.items()):
            if daemon == self.node.daemon_id:
                done, why = await self._apply(command, group, reason)
                delivered += done
                refused.update(why)
                continue
            nc = self.node.state.nc
            assert nc is not None
            request = json.dumps({"command": command, "agents": group, "reason": reason}).encode()
            try:
                reply = await nc.request(f"fleet.cmd.{daemon}", request, timeout=COMMAND_TIMEOUT_S)
                answer = json.loads(reply.data)
            except Exception as exc:
                log.warning("daemon %s did not answer %s for %s: %r", daemon, command, group, exc)
                late = f"{daemon} did not answer within {COMMAND_TIMEOUT_S:.0f} s"
                refused.update(dict.fromkeys(group, late))
                continue
            delivered += answer.get("delivered", [])
            refused.update(answer.get("refused", {}))
            if answer.get("error"):
                refused.update({i: f"{daemon}: {answer['error']}" for i in group if i not in delivered})
        return delivered, refused

    async def _apply(self, command: str, agents: list[str], reason: str) -> tuple[list[str], dict[str, str]]:
        operator = self.node.daemon.operator
        if command == "hold":
            delivered = await operator.hold(agents, reason)
        elif command == "resume":
            delivered = await operator.resume(agents, reason)
        elif command in ("rtl", "land"):  # out of its mission (led here or elsewhere), then down
            delivered, _ = await operator.bring_down(command, agents, reason)  # type: ignore[arg-type]
        else:
            raise ValueError(f"unknown command {command!r}")
        return delivered, {i: self._why_not(i, command) for i in agents if i not in delivered}

    def _why_not(self, identity: str, command: str) -> str:
        """Why ``command`` did not reach a drone linked here (for the cluster API's answer)."""
        session = self.node.daemon.agents.sessions.get(identity)
        if session is None or not session.open:
            return f"not linked to {self.node.daemon_id} any more"
        decisions = self.node.daemon.authority.control(identity).decisions
        last = decisions[-1] if decisions else None
        if last is not None and not last.accepted and last.source == "operator":
            return f"refused by {self.node.daemon_id}'s vehicle authority: {last.detail}"
        if command in ("rtl", "land"):
            return "not airborne: nothing to bring down"
        if command == "resume":
            return "still held by the operator"
        return f"not applied by {self.node.daemon_id}"

    async def answer(self, msg: Msg) -> None:
        try:
            request = json.loads(msg.data)
            delivered, refused = await self._apply(
                request["command"], list(request["agents"]), request["reason"]
            )
            answer: dict[str, Any] = {"delivered": delivered, "refused": refused}
        except Exception as exc:  # a bad request costs its reply, never the subscription
            answer = {"delivered": [], "error": str(exc)}
        await msg.respond(json.dumps(answer).encode())
