"""The airspace in a cluster: which drones this daemon's collision check decides for.

Why apart from the service: one daemon at a time runs the collision check over the whole fleet
(docs/cluster.md); the scope follows the cluster node's airspace lease (:class:`ClusterView`),
and when it changes the collision holds in force are handed over or adopted. Embedded (no
cluster) the scope is always every fresh drone.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Literal, Protocol

from gcs.control.authority import PRIORITY
from gcs.cooperation.collision_monitor import CollisionMonitor
from gcs.cooperation.tracking import TrackedAgent
from gcs.core.context import ServiceContext

log = logging.getLogger("gcs.cooperation")

Airspace = Literal["fleet", "local", "none"]
"""Which drones this daemon's collision check decides for: every drone of the cluster, only its
own (cut off from the cluster), or none (another daemon decides)."""


class ClusterView(Protocol):
    """What the service needs of the cluster node (gcs/cluster/node.py)."""

    def airspace(self) -> Airspace: ...

    def remote_level(self, ident: str) -> int:
        """Authority level of a drone at the daemon holding its link (0 if unknown)."""
        ...

    def remote_collision_hold(self, ident: str) -> bool:
        """True while the daemon holding the drone's link has it under a collision hold."""
        ...


class ClusterAirspace:
    """The collision check's scope and the authority level of drones linked to other daemons."""

    def __init__(
        self,
        cluster: ClusterView | None,
        collision: CollisionMonitor,
        agents: Mapping[str, TrackedAgent],
        remote: set[str],
        ctx: Callable[[], ServiceContext],
    ) -> None:
        self.cluster = cluster  # the cluster node, plugged in by the daemon (None: embedded)
        self.current: Airspace = "fleet"
        self._collision = collision
        self._agents = agents  # the service's tracked agents
        self._remote = remote  # the service's drones linked to other daemons
        self._ctx = ctx

    def outranked(self, ident: str, owner: str) -> bool:
        """Whether a source above ``owner`` controls the drone, here or (linked elsewhere) at its daemon."""
        level = self._ctx().authority.level(ident)
        if self.cluster is not None and ident in self._remote:  # what its own daemon has ordered
            level = max(level, self.cluster.remote_level(ident))
        return level > PRIORITY[owner]

    def scope(self, fresh: list[TrackedAgent], now: float) -> list[TrackedAgent]:
        """Of the ``fresh`` drones, those this daemon's collision check decides for (all, embedded)."""
        if self.cluster is None:
            return fresh
        airspace = self.cluster.airspace()
        if airspace != self.current:
            self._change(airspace, now)
        if airspace == "none":
            return []
        return fresh if airspace == "fleet" else [a for a in fresh if a.ident not in self._remote]

    def _change(self, airspace: Airspace, now: float) -> None:
        """Another daemon decides now, or we do: hand over or adopt the collision holds in force.

        Handing over forgets our collision picture (the holds stay with the drones' own daemons,
        whose status reports say so); taking over adopts every collision hold in force in the new
        scope, so the new decider releases them once clear. Escapes under way finish on the drones.
        """
        log.info("airspace: %s -> %s", self.current, airspace)
        self.current = airspace
        avoider, authority = self._collision.avoider, self._ctx().authority
        for ident in list(avoider.holds) + list(avoider.escaping):
            avoider.forget(ident)
        for ident in self._remote:
            authority.drop_holds(ident, ("collision",), f"airspace scope now {airspace}")
        if airspace == "none" or self.cluster is None:
            return
        for ident in list(self._agents):
            remote = ident in self._remote
            if remote and airspace != "fleet":
                continue
            held = (
                self.cluster.remote_collision_hold(ident) if remote else authority.is_held(ident, "collision")
            )
            if held:
                avoider.adopt(ident, now)
                if remote:  # our authority sends the release when it is clear
                    authority.restore_hold(ident, "collision", "adopted from the previous decider")


__all__ = ["Airspace", "ClusterAirspace", "ClusterView"]
