"""Barrier releases in a cluster: claimed once in shared state, or decided by the lease alone.

A leader releases a barrier after a compare-and-set create of ``<mission>.<step>.released``
(carrying its lease token): a barrier is released once, by a leader whose lease is good by its
own clock and whose token is the mission record's. When the barriers stream does not answer
within ``CLAIM_S`` (a NATS node died and the stream re-elects its leader: 5-6.5 s), a leader
whose lease is still good by its clock releases at once: no other daemon can lead before that
lease runs out (docs/cluster.md, "Losing a NATS node"), and the claim lands when the stream
answers. Without a good lease it raises :class:`LeaseUncertain` and releases nothing; the
complete barrier is released by a later try (an agent's next report, the lease renewed).
"""

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING

from gcs.cluster.fencing import LeaseUncertain

if TYPE_CHECKING:
    from gcs.cluster.node import ClusterNode

log = logging.getLogger("gcs.cluster")

CLAIM_S = 0.5  # a release claim's wait for NATS, before the lease alone decides


class ReleaseClaims:
    """One daemon's release claims (``ClusterNode.releases``)."""

    def __init__(self, node: ClusterNode) -> None:
        self.node = node
        self._under_way: dict[str, asyncio.Future[bool]] = {}  # claims being decided, by key
        self._landing: set[asyncio.Future[bool]] = set()  # released; their record not yet written

    async def claim(self, mission_id: str, step: int) -> bool:
        """Claim a release (once, by compare-and-set, carrying our token) only while we lead by
        our clock. Concurrent claims of one barrier share one try: only the first caller sends.
        Raises :class:`LeaseUncertain` when NATS does not answer and our lease is not good by
        our clock: nothing is released, the complete barrier is released by a later try."""
        key = f"{mission_id}.{step}.released"
        claim = self._under_way.get(key)
        if claim is not None:
            await asyncio.shield(claim)
            return False  # the first caller releases (or it raised: so do we)
        claim = asyncio.ensure_future(self._claim(mission_id, step, key))
        self._under_way[key] = claim
        claim.add_done_callback(lambda _c: self._under_way.pop(key, None))
        return await asyncio.shield(claim)

    async def _claim(self, mission_id: str, step: int, key: str) -> bool:
        """The fence check and the compare-and-set, awaited CLAIM_S at most: past that, with our
        lease good by our clock, we release at once (no other daemon can lead before it runs
        out; the claim lands when the stream answers again: a JetStream leader election)."""
        leases = self.node.state.leases
        token = leases.token(mission_id)
        if not await self.node.may_decide(mission_id):
            if mission_id in self.node.daemon.missions.active:
                raise LeaseUncertain(f"{mission_id}: lease out by our clock, NATS silent")
            return False
        mine = f" lease {token}".encode()
        value = self.node.state.unique() + mine

        async def claim() -> bool:
            if not await leases.allowed(mission_id, token, f"release of step {step}"):
                return False
            return await self.node.state.create("barriers", key, value)

        trying = asyncio.ensure_future(claim())
        done, _ = await asyncio.wait({trying}, timeout=CLAIM_S)
        if not done:
            if not leases.valid(mission_id):
                trying.add_done_callback(_retrieve)  # it may land: a later try finds it ours
                raise LeaseUncertain(f"{mission_id}: release of step {step} got no answer in {CLAIM_S:g} s")
            log.info(
                "release of %s step %d: NATS slow, released under our lease (claim pending)", mission_id, step
            )
            self._landing.add(trying)
            trying.add_done_callback(self._landed)
            return True
        if trying.result():
            return True
        found = self.node.state.mirror["barriers"].get(key, b"")  # ours: an earlier try's answer was lost
        return found.startswith(self.node.daemon_id.encode() + b" ") and found.endswith(mine)

    def _landed(self, claim: asyncio.Future[bool]) -> None:
        self._landing.discard(claim)
        if claim.cancelled():
            return
        if claim.exception() is not None or not claim.result():
            log.warning(
                "a release made under our lease was not recorded: %r", claim.exception() or "claimed first"
            )


def _retrieve(claim: asyncio.Future[bool]) -> None:
    if not claim.cancelled() and claim.exception() is not None:
        log.debug("release claim: %r", claim.exception())
