"""Leases judged by this daemon's own clock, and writes fenced by the lease's token.

A daemon that was paused (SIGSTOP, a frozen VM, a long GC) wakes with timers that fired while it
slept and a belief that it still leads. NATS expired its lease meanwhile and another daemon took
it. Two rules keep the sleeper from acting on that stale state (docs/cluster.md, "Fencing"):

* **The lease is judged by the local monotonic clock.** A lease written (taken or renewed) at
  ``T`` is good until ``T + ttl - margin`` here, whatever NATS says later; ``T`` is read before
  the write is sent, so the server's own expiry is never earlier. Past that instant a decision
  first renews once, by compare-and-set on the revision this daemon last wrote (so it succeeds
  only if nobody touched the key since); if that fails the daemon steps down first.
* **Every leader write carries the lease's token**, the revision of the ``create`` that took the
  lease (a later leader's create always has a higher one). The mission record holds the token
  of the leader that wrote it; a new leader stamps it on takeover, and a write whose token is
  older than the record's is refused (the record is a compare-and-set on its revision, other
  records of the mission are checked against it first). Forwarded orders carry it too and the
  receiving daemon refuses an older one.

Lease calls ride through a NATS node failing: each KV call waits at most ``op_timeout`` (a
request to a stream re-electing its leader gets no answer at all; nats-py's 5 s wait would
outlast the lease), the round retries next period. A call that timed out is no verdict: only
NATS saying another daemon holds the key, or that it lapsed, makes the holder let go.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import nats.errors
import nats.js.errors

if TYPE_CHECKING:
    from gcs.cluster.state import ClusterState

log = logging.getLogger("gcs.cluster")

MARGIN_FRACTION = 0.25  # of the TTL: a lease is trusted locally until ttl - margin after its write
FENCE_ATTEMPTS = 10  # compare-and-set rounds of one fenced mission-record write
STAMP_TIMEOUT_S = 10.0
LEASE_ERRORS = (nats.errors.Error, nats.js.errors.Error, TimeoutError)
LOST = (nats.js.errors.KeyWrongLastSequenceError, nats.js.errors.KeyNotFoundError)


class LeaseUncertain(RuntimeError):
    """NATS did not answer in time whether we may still decide: decide nothing now."""


@dataclass
class HeldLease:
    token: int  # revision of the create that took the lease: the fencing token
    revision: int  # revision of our newest write of the key (a renewal compares-and-sets on it)
    valid_until: float  # time.monotonic(): when this daemon stops trusting it


class Leases:
    """The leases this daemon holds, by its own clock; fenced writes of the shared records."""

    def __init__(self, state: ClusterState) -> None:
        self.state = state
        self.ttl = state.lease_ttl_s
        self.margin = state.lease_ttl_s * MARGIN_FRACTION
        # one KV call of a lease round: short, so a round that got no answer retries in time
        self.op_timeout = min(1.0, max(0.2, state.lease_ttl_s / 6))
        self.held: dict[str, HeldLease] = {}
        # missions submitted here whose lease is being taken (queued behind earlier writes)
        self.pending: dict[str, asyncio.Event] = {}
        self.refused = 0  # writes refused: a newer leader's token was on the record
        self.stamped_over: dict[str, int] = {}  # mission -> the token our last stamp replaced
        self._locks: dict[str, asyncio.Lock] = {}

    def _lock(self, name: str) -> asyncio.Lock:
        return self._locks.setdefault(name, asyncio.Lock())

    def valid(self, name: str) -> bool:
        """True while this daemon may act on the lease ``name`` by its own clock."""
        held = self.held.get(name)
        return held is not None and time.monotonic() < held.valid_until

    def token(self, name: str) -> int | None:
        """The fencing token of a lease we hold (expired by our clock or not), else None."""
        held = self.held.get(name)
        return None if held is None else held.token

    def _wrote(self, name: str, token: int, revision: int, sent: float) -> None:
        self.held[name] = HeldLease(token, revision, sent + self.ttl - self.margin)

    async def holder(self, name: str) -> tuple[str | None, int]:
        """(daemon holding the lease, revision); (None, 0) when it expired or never was."""
        try:
            entry = await asyncio.wait_for(self.state.kv["leases"].get(name), self.op_timeout)
        except (nats.js.errors.KeyNotFoundError, nats.js.errors.KeyDeletedError):
            return None, 0
        holder = (entry.value or b"").decode().split(" ", 1)[0]
        return holder or None, int(entry.revision or 0)

    async def take(self, name: str) -> bool:
        async with self._lock(name):
            return await self._take(name)

    async def _take(self, name: str) -> bool:
        """Create the key (bounded); a create whose answer was lost counts if our value is there."""
        sent, value = time.monotonic(), self.state.unique()
        kv = self.state.kv["leases"]
        try:
            revision = int(await asyncio.wait_for(kv.create(name, value), self.op_timeout))
        except nats.js.errors.KeyWrongLastSequenceError:
            try:
                entry = await asyncio.wait_for(kv.get(name), self.op_timeout)
            except (nats.js.errors.KeyNotFoundError, nats.js.errors.KeyDeletedError):
                return False
            if (entry.value or b"").split(b" ", 1)[0] != self.state.daemon_id.encode():
                return False  # another daemon's (ours: an earlier try whose answer was lost)
            revision = int(entry.revision or 0)
        self._wrote(name, revision, revision, sent)
        return True

    async def renew(self, name: str, take_if_free: bool = True) -> bool:
        """Extend our lease; False if another daemon holds it now, or if it lapsed and
        ``take_if_free`` is off (a mission's leader whose lease lapsed may have missed another
        leader's whole term: it lets go, and takes the mission over afresh). Raises on no answer
        (the caller keeps what it holds: its clock decides). Read and write under the lease's
        lock, so a confirmation running meanwhile (which moves the revision) never makes a
        renewal look lost."""
        async with self._lock(name):
            holder, revision = await self.holder(name)
            if holder != self.state.daemon_id:
                self.held.pop(name, None)
                return holder is None and take_if_free and await self._take(name)
            sent = time.monotonic()
            try:
                new = await asyncio.wait_for(
                    self.state.kv["leases"].update(name, self.state.unique(), last=revision), self.op_timeout
                )
            except nats.js.errors.KeyWrongLastSequenceError:
                self.held.pop(name, None)
                return False
            held = self.held.get(name)
            self._wrote(name, held.token if held is not None else revision, int(new), sent)
            return True

    async def confirm(self, name: str) -> bool | None:
        """True if we may act on lease ``name`` now. Past its local validity (a pause, missed
        rounds) one renewal decides: a compare-and-set on the revision we last wrote, which
        fails if the key expired or anyone wrote it since. False when it failed: the lease is
        dropped here and the caller steps down before deciding anything. None when NATS gave no
        answer in time (a node failing over): decide nothing now, let go of nothing."""
        if self.valid(name):
            return True
        taking = self.pending.get(name)
        if taking is not None:  # just submitted here: its take is queued, wait for it (bounded)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(taking.wait(), self.ttl)
        async with self._lock(name):
            held = self.held.get(name)
            if held is None:
                return False
            if time.monotonic() < held.valid_until:  # renewed while we waited for the lock
                return True
            sent = time.monotonic()
            try:
                new = await asyncio.wait_for(
                    self.state.kv["leases"].update(name, self.state.unique(), last=held.revision),
                    self.op_timeout,  # it only succeeds if nobody wrote the key since
                )
            except LOST as exc:
                log.warning("lease %s ran out by our clock, not renewed (%r): stepping down", name, exc)
                self.held.pop(name, None)
                return False
            except LEASE_ERRORS as exc:
                log.info("lease %s ran out by our clock; NATS did not answer (%r): waiting", name, exc)
                return None
            self._wrote(name, held.token, int(new), sent)
            return True

    def step_down(self, name: str) -> None:
        self.held.pop(name, None)

    async def drop(self, name: str) -> None:
        """Hand the lease back at once, only if the key is still our last write (a delete
        conditional on our revision: never another daemon's lease that replaced ours)."""
        held = self.held.pop(name, None)
        if held is None:
            return
        try:
            await asyncio.wait_for(self.state.kv["leases"].delete(name, last=held.revision), self.op_timeout)
        except LEASE_ERRORS as exc:
            log.debug("dropping lease %s: %r", name, exc)

    # --- fenced writes -------------------------------------------------------------------------------

    def decision_token(self, mission_id: str) -> int | None:
        """The token a decision about ``mission_id`` is made under, now: ours if we hold the
        lease, -1 for a mission submitted here whose lease is still being taken (resolved when
        the write runs, after the take queued before it), else None (the write will be refused)."""
        token = self.token(mission_id)
        if token is None and mission_id in self.pending:
            return -1
        return token

    async def _record(self, mission_id: str) -> tuple[dict[str, Any] | None, int]:
        """The mission record as stored now (not the mirror) and its revision."""
        try:
            entry = await self.state.kv["missions"].get(mission_id)
        except (nats.js.errors.KeyNotFoundError, nats.js.errors.KeyDeletedError):
            return None, 0
        return (json.loads(entry.value) if entry.value else None), int(entry.revision or 0)

    def _refuse(self, what: str, mission_id: str, token: int | None, record: dict[str, Any] | None) -> None:
        self.refused += 1
        theirs = None if record is None else record.get("lease")
        log.warning(
            "fenced: %s of %s refused (our lease token %s, the record's %s from %s)",
            what,
            mission_id,
            token,
            theirs,
            None if record is None else record.get("leader"),
        )
        if record is not None:  # our mirror may hold our refused copy: put the stored one back
            self.state.mirror["missions"][mission_id] = json.dumps(record, separators=(",", ":")).encode()

    def _resolve(self, mission_id: str, token: int | None) -> int | None:
        return self.token(mission_id) if token == -1 else token

    async def allowed(self, mission_id: str, token: int | None, what: str) -> bool:
        """True if a write under ``token`` may still go: no newer leader stamped the record."""
        token = self._resolve(mission_id, token)
        record, _ = await self._record(mission_id)
        if token is None or (record is not None and int(record.get("lease", 0)) > token):
            self._refuse(what, mission_id, token, record)
            return False
        return True

    async def write_record(self, mission_id: str, record: dict[str, Any], token: int | None) -> bool:
        """Write the mission record under ``token``: compare-and-set on the stored revision,
        refused if the stored record carries a newer leader's token."""
        token = self._resolve(mission_id, token)
        for _ in range(FENCE_ATTEMPTS):
            stored, revision = await self._record(mission_id)
            if token is None or (stored is not None and int(stored.get("lease", 0)) > token):
                self._refuse(f"write ({record.get('state')})", mission_id, token, stored)
                return False
            data = json.dumps({**record, "lease": token}, separators=(",", ":")).encode()
            try:
                if revision:
                    await self.state.kv["missions"].update(mission_id, data, last=revision)
                else:
                    await self.state.kv["missions"].create(mission_id, data)
            except nats.js.errors.KeyWrongLastSequenceError:
                continue  # written meanwhile (a takeover's stamp): read again
            self.state.mirror["missions"][mission_id] = data
            return True
        log.warning("fenced write of %s gave up after %d compare-and-set rounds", mission_id, FENCE_ATTEMPTS)
        return False

    async def stamp(self, mission_id: str) -> bool:
        """A new leader writes its token and name into the mission record before it acts: every
        write still queued by the previous leader is refused from then on."""
        token = self.token(mission_id)
        deadline = time.monotonic() + STAMP_TIMEOUT_S
        while time.monotonic() < deadline:
            try:
                record, _ = await self._record(mission_id)
                if record is None:
                    return False
                self.stamped_over[mission_id] = int(record.get("lease", 0))
                record["leader"] = self.state.daemon_id
                return await self.write_record(mission_id, record, token)
            except (nats.errors.Error, nats.js.errors.Error, TimeoutError):
                await asyncio.sleep(0.2)
        return False
