"""Fleet state shared by daemons through NATS JetStream (key-value buckets and two streams).

What lives where (docs/cluster.md):

==================  ===================================  =====================================
bucket / stream     key                                  value / rule
==================  ===================================  =====================================
fleet_agents        identity                             {cid, daemon}: registry, who holds the link;
                                                         its revision orders the link's holders
fleet_cids          c<CID>                               identity; ``create``: a CID is assigned once
fleet_missions      mission id                           accepted mission (task, state, paused)
fleet_progress      <mission>.<agent>                    {completed, excluded}
fleet_barriers      <mission>.<step>.arrived.<agent>     an arrival (written by the link's daemon)
                    <mission>.<step>.released            ``create``: a barrier is released once
fleet_holds         <agent>.<owner>                      {agent, owner, reason}: operator holds
fleet_leases        <mission>                            daemon id; bucket TTL: the leader's lease
                                                         (fencing token: the create's revision)
FLEET_EVENTS        fleet.events.<daemon>                the event log (limits: count, age)
FLEET_TELEMETRY     fleet.status.<identity>              live status (plain subject) kept with limits
==================  ===================================  =====================================

Reads come from in-memory mirrors kept current by one KV watcher per bucket, so the daemon's
synchronous code (the mission runner, the store interface) never waits on the network. Writes go
through one ordered queue (retried, bounded); the few writes that must not race (a CID, a barrier
release, a lease) are awaited compare-and-set calls.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any
from urllib.parse import urlsplit

import nats
import nats.errors
import nats.js.errors
from nats.aio.client import Client
from nats.js.client import JetStreamContext
from nats.js.kv import KV_DEL, KV_PURGE, KeyValue

from gcs.cluster.fencing import Leases

log = logging.getLogger("gcs.cluster")

BUCKETS = ("agents", "cids", "missions", "progress", "barriers", "holds", "leases")
EVENTS_STREAM = "FLEET_EVENTS"
TELEMETRY_STREAM = "FLEET_TELEMETRY"
EVENT_LIMIT = 200_000
EVENT_MAX_AGE_S = 7 * 86_400.0
TELEMETRY_MAX_AGE_S = 3_600.0
TELEMETRY_MAX_BYTES = 256 << 20
WRITE_ATTEMPTS = 20
SEND_ATTEMPTS = 10
CID_ATTEMPTS = 64
MIRROR_LOAD_TIMEOUT_S = 10.0
SETUP_TIMEOUT_S = 20.0
CONNECT_TIMEOUT_S = 5.0
CAS_TIMEOUT_S = 10.0
FOLLOWER_CHECK_PERIOD_S = 1.0
FOLLOWER_CHECK_TIMEOUT_S = 2.0

Write = Callable[[], Awaitable[object]]


class ClusterUnavailable(ConnectionError):
    """NATS could not be reached or JetStream is not enabled there."""


async def _stop_followers(
    followers: list[tuple[Any, asyncio.Task[None]]], tasks: list[asyncio.Task[None]]
) -> None:
    """Stop the KV watchers, then cancel their tasks and ``tasks``. Unsubscribing a watcher ends
    nats-py's heartbeat and flow-control tasks of its consumer, which closing the connection does
    not: they would keep a stopping daemon's event loop alive for 5 s more."""
    for watcher, _ in followers:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(watcher.stop(), 1.0)
    tasks = tasks + [task for _, task in followers]
    for task in tasks:
        task.cancel()
    for task in tasks:
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task


class ClusterState:
    """One daemon's connection to the shared fleet state."""

    def __init__(self, servers: list[str], daemon_id: str, replicas: int, lease_ttl_s: float) -> None:
        self.servers = servers
        self.daemon_id = daemon_id
        self.replicas = replicas
        self.lease_ttl_s = lease_ttl_s
        self.nc: Client | None = None
        self.js: JetStreamContext | None = None
        self.kv: dict[str, KeyValue] = {}
        self.mirror: dict[str, dict[str, bytes]] = {name: {} for name in BUCKETS}
        self.on_change: list[Callable[[str, str, bytes | None], None]] = []
        self._followers: dict[str, tuple[Any, asyncio.Task[None]]] = {}
        self._tasks: list[asyncio.Task[None]] = []
        self._writes: asyncio.Queue[Write] = asyncio.Queue()
        self._sends: asyncio.Queue[tuple[str, bytes, str, dict[str, str] | None]] = asyncio.Queue()
        self.write_failures = 0
        self._serial = itertools.count()
        self._seen: dict[str, int] = {}  # bucket -> newest revision applied to its mirror
        self.revisions: dict[str, int] = {}  # agent -> revision of its fleet_agents record in the mirror
        self._behind: dict[str, int] = {}  # bucket -> stream sequence it lagged at the last check
        self.leases = Leases(self)  # held leases by our own clock; fenced writes
        self.disconnected_at: float | None = None  # time.monotonic() the connection dropped

    # --- connection ------------------------------------------------------------------------------

    async def connect(self) -> None:
        try:
            await self._probe()  # nats-py retries refused servers forever: fail fast when all refuse
            self.nc = await asyncio.wait_for(self._connect(), CONNECT_TIMEOUT_S)
        except Exception as exc:
            raise ClusterUnavailable(
                f"cannot reach NATS at {','.join(self.servers)} within {CONNECT_TIMEOUT_S:.0f} s: {exc!r}"
            ) from exc
        self.js = self.nc.jetstream(timeout=5.0)
        deadline = time.monotonic() + SETUP_TIMEOUT_S
        while True:  # a NATS cluster just started elects its JetStream leader first: retry, bounded
            try:
                await self._setup()
                break
            except (nats.errors.Error, nats.js.errors.Error, TimeoutError) as exc:
                if time.monotonic() > deadline:
                    await self.close()
                    raise ClusterUnavailable(
                        f"JetStream not usable at {','.join(self.servers)}: {exc!r}"
                    ) from exc
                await asyncio.sleep(0.5)
        for name in BUCKETS:
            if name != "leases":  # leases expire without a marker on 2.9: always read them fresh
                await self._follow(name)
        self._tasks.append(asyncio.create_task(self._writer(), name="cluster-writer"))
        self._tasks.append(asyncio.create_task(self._sender(), name="cluster-sender"))
        self._tasks.append(asyncio.create_task(self._watch_followers(), name="cluster-mirror-check"))

    async def _probe(self) -> None:
        """Raise when no server accepts a TCP connection within CONNECT_TIMEOUT_S (all at once)."""

        async def reachable(url: str) -> bool:
            parsed = urlsplit(url)
            try:
                _, writer = await asyncio.wait_for(
                    asyncio.open_connection(parsed.hostname, parsed.port or 4222), CONNECT_TIMEOUT_S
                )
            except (OSError, TimeoutError):
                return False
            writer.close()
            return True

        if not any(await asyncio.gather(*(reachable(url) for url in self.servers))):
            raise ConnectionRefusedError("no server accepts connections")

    async def _connect(self) -> Client:
        """Connect; the first connection tries every server in turn, reconnects never give up."""
        return await nats.connect(
            servers=self.servers,
            name=self.daemon_id,
            connect_timeout=2,
            reconnect_time_wait=0.25,
            max_reconnect_attempts=-1,
            allow_reconnect=True,
            reconnected_cb=self._reconnected,
            disconnected_cb=self._disconnected,
            error_cb=self._nats_error,
        )

    async def _nats_error(self, exc: Exception) -> None:
        """One line per client error (nats-py would log a traceback); quiet until first connected."""
        level = logging.WARNING if self.js is not None else logging.DEBUG
        log.log(level, "NATS: %r", exc)

    async def _setup(self) -> None:
        for name in BUCKETS:
            if name not in self.kv:
                self.kv[name] = await self._bucket(name)
        await self._stream(EVENTS_STREAM, ["fleet.events.>"], max_msgs=EVENT_LIMIT, max_age=EVENT_MAX_AGE_S)
        await self._stream(
            TELEMETRY_STREAM,
            ["fleet.status.>"],
            max_age=TELEMETRY_MAX_AGE_S,
            max_bytes=TELEMETRY_MAX_BYTES,
            storage="memory",
        )

    async def _bucket(self, name: str) -> KeyValue:
        assert self.js is not None
        bucket = f"fleet_{name}"
        with contextlib.suppress(nats.js.errors.BucketNotFoundError):
            return await self.js.key_value(bucket)
        ttl = self.lease_ttl_s if name == "leases" else None
        return await self.js.create_key_value(bucket=bucket, history=1, replicas=self.replicas, ttl=ttl)

    async def _stream(self, name: str, subjects: list[str], storage: str = "file", **limits: Any) -> None:
        from nats.js.api import StorageType, StreamConfig

        assert self.js is not None
        config = StreamConfig(
            name=name,
            subjects=subjects,
            num_replicas=self.replicas,
            storage=StorageType.MEMORY if storage == "memory" else StorageType.FILE,
            **limits,
        )
        try:
            await self.js.stream_info(name)
        except nats.js.errors.NotFoundError:
            with contextlib.suppress(nats.js.errors.BadRequestError):  # another daemon made it first
                await self.js.add_stream(config)

    async def _follow(self, name: str) -> None:
        """Load the bucket into its mirror, then keep the mirror current in the background."""
        watcher = await self.kv[name].watchall()
        snapshot: dict[str, bytes] = {}
        deadline = time.monotonic() + MIRROR_LOAD_TIMEOUT_S
        while time.monotonic() < deadline:
            entry = await watcher.updates(timeout=max(0.1, deadline - time.monotonic()))
            if entry is None:
                break
            self._apply(name, snapshot, entry)
        mirror = self.mirror[name]
        mirror.clear()
        mirror.update(snapshot)
        old = self._followers.pop(name, None)
        self._followers[name] = (
            watcher,
            asyncio.create_task(self._run(name, watcher), name=f"cluster-{name}"),
        )
        if old is not None:
            old[1].cancel()
            with contextlib.suppress(Exception):
                await old[0].stop()

    async def _run(self, name: str, watcher: Any) -> None:
        async for entry in watcher:
            if entry is not None:
                self._apply(name, self.mirror[name], entry)

    async def resync(self, names: tuple[str, ...] = ("missions", "progress", "barriers", "holds")) -> None:
        """Reload mirrors from a fresh snapshot (after a reconnect, before taking over a mission):
        a watcher whose consumer sat on a NATS node that died is silent until it resets itself."""
        for name in names:
            await self._follow(name)

    async def refresh(self, bucket: str, keys: list[str]) -> None:
        """Read ``keys`` straight from the bucket into its mirror, all at once (bounded). A direct
        get needs only the stream's leader, not a new consumer: it works while NATS re-elects
        its metadata leader (a node died), when reloading a whole bucket would not."""

        async def one(key: str) -> None:
            with contextlib.suppress(nats.js.errors.KeyNotFoundError, nats.js.errors.KeyDeletedError):
                entry = await self.kv[bucket].get(key)
                if entry.value is not None:
                    self.mirror[bucket][key] = entry.value

        await asyncio.wait_for(asyncio.gather(*(one(k) for k in keys)), CAS_TIMEOUT_S)

    def resync_soon(self) -> None:
        """Reload every mirror in the background (:meth:`resync`, errors left to the mirror check)."""
        task = asyncio.create_task(self._resync_quietly(), name="cluster-resync")
        self._tasks.append(task)
        task.add_done_callback(self._forget_task)

    async def check_followers(self) -> None:
        """Reload a mirror still behind what its bucket held at the previous check.

        An ordered consumer whose NATS server died (without our connection moving) is silent
        until its heartbeat check resets it; the bucket's last sequence shows the lag. Each bucket
        is checked on its own with a short timeout: JetStream re-electing a leader after a node
        died must not stop the other buckets' checks.
        """
        assert self.js is not None
        for name in list(self._followers):
            try:
                info = await asyncio.wait_for(
                    self.js.stream_info(f"KV_fleet_{name}"), FOLLOWER_CHECK_TIMEOUT_S
                )
            except (nats.errors.Error, nats.js.errors.Error, TimeoutError) as exc:
                log.debug("mirror check of %s: %r", name, exc)
                continue
            last = int(info.state.last_seq or 0)
            before = self._behind.pop(name, None)
            if before is not None and self._seen.get(name, 0) < before:
                seen = self._seen.get(name, 0)
                log.warning("mirror of %s stalled at %d (bucket at %d); reloading", name, seen, last)
                try:
                    await self._follow(name)
                except (nats.errors.Error, nats.js.errors.Error, TimeoutError) as exc:
                    log.warning("reloading the mirror of %s failed (%r); next check retries", name, exc)
                    self._behind[name] = last
            elif last > self._seen.get(name, 0):
                self._behind[name] = last

    async def _watch_followers(self) -> None:
        """Check the mirrors every FOLLOWER_CHECK_PERIOD_S, apart from the lease round (which a slow
        JetStream answer must never delay past the lease's TTL)."""
        while True:
            await asyncio.sleep(FOLLOWER_CHECK_PERIOD_S)
            if self.nc is None or not self.nc.is_connected:
                continue
            try:
                await self.check_followers()
            except Exception:
                log.warning("mirror check failed", exc_info=True)

    async def _disconnected(self) -> None:
        if self.disconnected_at is None:
            self.disconnected_at = time.monotonic()

    def cut_off_s(self) -> float:
        """How long this daemon has been without NATS (0 while connected)."""
        nc = self.nc
        if nc is None or nc.is_connected or self.disconnected_at is None:
            return 0.0
        return time.monotonic() - self.disconnected_at

    async def _reconnected(self) -> None:
        """Reload the mirrors beside the client (nats-py awaits this inside its reconnect: a
        reload waiting on a stream that re-elects its leader must not hold that up)."""
        self.disconnected_at = None
        url = self.nc.connected_url if self.nc else None
        log.info("NATS reconnected to %s; reloading the shared state", url.netloc if url else "?")
        self.resync_soon()

    def _forget_task(self, task: asyncio.Task[None]) -> None:
        if task in self._tasks:
            self._tasks.remove(task)

    async def _resync_quietly(self) -> None:
        with contextlib.suppress(Exception):
            await self.resync(tuple(n for n in BUCKETS if n != "leases"))

    def _apply(self, name: str, mirror: dict[str, bytes], entry: Any) -> None:
        self._seen[name] = max(self._seen.get(name, 0), int(entry.revision or 0))
        value = None if entry.operation in (KV_DEL, KV_PURGE) else entry.value
        if value is None:
            mirror.pop(entry.key, None)
        else:
            mirror[entry.key] = value
        if name == "agents":
            self.revisions[entry.key] = int(entry.revision or 0)
        for callback in self.on_change:
            try:
                callback(name, entry.key, value)
            except Exception:
                log.exception("cluster change callback failed")

    async def close(self) -> None:
        if self.nc is not None and self.nc.is_connected:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.flush_writes(), 5.0)
        followers, tasks = list(self._followers.values()), list(self._tasks)
        self._followers.clear()
        self._tasks.clear()
        await _stop_followers(followers, tasks)
        if self.nc is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self.nc.close(), 5.0)

    # --- ordered writes --------------------------------------------------------------------------

    def enqueue(self, write: Write) -> None:
        """Run ``write`` after every write queued before it (retried; never blocks the caller)."""
        self._writes.put_nowait(write)

    def put_json(self, bucket: str, key: str, value: dict[str, Any]) -> None:
        data = json.dumps(value, separators=(",", ":")).encode()
        self.mirror[bucket][key] = data
        self.enqueue(lambda: self.kv[bucket].put(key, data))

    def delete(self, bucket: str, key: str) -> None:
        self.mirror[bucket].pop(key, None)
        self.enqueue(lambda: self.kv[bucket].delete(key))

    def publish(self, subject: str, payload: bytes) -> None:
        """Core publish (no ack): the stream on that subject keeps it within its limits."""
        self.send(subject, payload)

    def send(
        self, subject: str, payload: bytes, reply: str = "", headers: dict[str, str] | None = None
    ) -> None:
        """Core publish, in order with the others but never behind a JetStream write: a write
        waiting out a stream's leader election (seconds) must not hold up a barrier arrival, a
        release or a collision order on its way to another daemon."""
        if self.nc is not None and not self.nc.is_closed:
            self._sends.put_nowait((subject, payload, reply, headers))

    async def _sender(self) -> None:
        while True:
            subject, payload, reply, headers = await self._sends.get()
            try:
                for _ in range(SEND_ATTEMPTS):
                    try:
                        assert self.nc is not None
                        await self.nc.publish(subject, payload, reply=reply, headers=headers)
                        break
                    except (nats.errors.Error, OSError) as exc:  # buffer full while reconnecting
                        log.debug("publish on %s: %r", subject, exc)
                        await asyncio.sleep(0.2)
            finally:
                self._sends.task_done()

    async def flush_writes(self) -> None:
        await self._writes.join()
        await self._sends.join()

    async def _writer(self) -> None:
        while True:
            write = await self._writes.get()
            try:
                for attempt in range(WRITE_ATTEMPTS):
                    try:
                        await write()
                        break
                    except (nats.errors.Error, nats.js.errors.Error, TimeoutError) as exc:
                        if isinstance(exc, nats.js.errors.KeyWrongLastSequenceError):
                            break  # a compare-and-set lost: someone else wrote first, which is fine
                        await asyncio.sleep(min(2.0, 0.1 * (attempt + 1)))
                else:
                    self.write_failures += 1
                    log.error("cluster write failed %d times; dropped", WRITE_ATTEMPTS)
            finally:
                self._writes.task_done()

    # --- pruning (gcs/cluster/housekeeping.py) ------------------------------------------------------

    async def purge_key(self, bucket: str, key: str) -> None:
        """Remove ``key`` and its history; the purge marker tells every mirror (awaited, bounded)."""
        self.mirror[bucket].pop(key, None)
        await asyncio.wait_for(self.kv[bucket].purge(key), CAS_TIMEOUT_S)

    async def purge_subject(self, bucket: str, keys: str) -> None:
        """Remove every message of the keys matching ``keys`` (a key or ``prefix.>``), markers too."""
        assert self.js is not None
        await asyncio.wait_for(
            self.js.purge_stream(f"KV_fleet_{bucket}", subject=f"$KV.fleet_{bucket}.{keys}"), CAS_TIMEOUT_S
        )

    # --- compare-and-set -------------------------------------------------------------------------

    async def create(self, bucket: str, key: str, value: bytes) -> bool:
        """Write ``key`` only if it does not exist; False if someone else holds it (see
        :meth:`create_revision`)."""
        return bool(await self.create_revision(bucket, key, value))

    async def create_revision(self, bucket: str, key: str, value: bytes) -> int:
        """Write ``key`` only if it does not exist; its revision, or 0 if someone else holds it.

        Retried (bounded) while NATS fails over; a retry that finds our own value there means the
        earlier try went through and only its answer was lost, so it counts as won. Callers make
        ``value`` unique to them (daemon id, time) for that reason.
        """
        deadline = time.monotonic() + CAS_TIMEOUT_S
        while True:
            try:
                revision = int(await self.kv[bucket].create(key, value))
                break
            except nats.js.errors.KeyWrongLastSequenceError:
                try:
                    entry = await self.kv[bucket].get(key)
                except (nats.js.errors.KeyNotFoundError, nats.js.errors.KeyDeletedError):
                    if time.monotonic() > deadline:
                        raise
                    continue  # deleted again between the two calls (a lost CID race): try again
                if entry.value == value:
                    revision = int(entry.revision or 0)
                    break
                if entry.value is not None and bucket != "leases":
                    self.mirror[bucket][key] = entry.value
                return 0
            except (nats.errors.Error, nats.js.errors.Error, TimeoutError):
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.2)
        if bucket != "leases":
            self.mirror[bucket][key] = value
        return max(1, revision)

    def unique(self) -> bytes:
        """A value only this daemon writes, now (see :meth:`create`)."""
        return f"{self.daemon_id} {time.time():.6f} {next(self._serial)}".encode()

    async def assign_cid(self, identity: str) -> int:
        """The agent's CID: its registered one, else the lowest free one (claimed with create)."""
        known = self.agent_record(identity)
        if known is not None:
            return int(known["cid"])
        for _ in range(CID_ATTEMPTS):
            used = [int(k[1:]) for k in self.mirror["cids"] if k[1:].isdigit()]
            cid = max(used, default=0) + 1
            if await self.create("cids", f"c{cid}", identity.encode() + b" " + self.unique()):
                record = {"cid": cid, "daemon": self.daemon_id, "since": time.time()}
                if await self.create("agents", identity, json.dumps(record).encode()):
                    return cid
                self.delete("cids", f"c{cid}")  # registered meanwhile by another daemon: use theirs
                theirs = self.agent_record(identity)
                if theirs is not None:
                    return int(theirs["cid"])
        raise RuntimeError(f"could not assign a connection ID to {identity} after {CID_ATTEMPTS} tries")

    async def claim_agent(self, identity: str, cid: int) -> int:
        """Record that this daemon holds ``identity``'s link now; returns the record's revision.

        The revision is the link's epoch: every daemon's messages about the agent carry it, and
        a message from an older epoch (a daemon the agent has left) is ignored everywhere. The
        read-modify-write is a compare-and-set on the revision read, retried (bounded) when
        another write came first; 0 when NATS is away or did not answer in time (the record is then
        queued, and the join hooks are not held up by a NATS outage).
        """
        record = {"cid": cid, "daemon": self.daemon_id, "since": time.time()}
        data = json.dumps(record, separators=(",", ":")).encode()
        deadline = time.monotonic() + CAS_TIMEOUT_S
        while time.monotonic() < deadline and self.nc is not None and self.nc.is_connected:
            try:
                try:
                    entry = await self.kv["agents"].get(identity)
                    revision = int(await self.kv["agents"].update(identity, data, last=entry.revision))
                except (nats.js.errors.KeyNotFoundError, nats.js.errors.KeyDeletedError):
                    revision = int(await self.kv["agents"].create(identity, data))
            except nats.js.errors.KeyWrongLastSequenceError:
                continue  # written meanwhile: read again
            except (nats.errors.Error, nats.js.errors.Error, TimeoutError):
                await asyncio.sleep(0.2)
                continue
            self.mirror["agents"][identity] = data
            self.revisions[identity] = max(self.revisions.get(identity, 0), revision)
            return revision
        self.put_json("agents", identity, record)
        return 0

    def agent_record(self, identity: str) -> dict[str, Any] | None:
        raw = self.mirror["agents"].get(identity)
        return None if raw is None else json.loads(raw)

    def json_values(self, bucket: str, prefix: str = "") -> dict[str, dict[str, Any]]:
        return {k: json.loads(v) for k, v in list(self.mirror[bucket].items()) if k.startswith(prefix)}

    # --- leases ----------------------------------------------------------------------------------

    async def lease_holder(self, mission_id: str) -> tuple[str | None, int]:
        """(daemon holding the mission's lease, revision); (None, 0) when it expired or never was."""
        return await self.leases.holder(mission_id)

    async def take_lease(self, mission_id: str) -> bool:
        return await self.leases.take(mission_id)

    async def renew_lease(self, mission_id: str) -> bool:
        """Extend our lease; False if it is no longer ours (expired and taken by another daemon)."""
        return await self.leases.renew(mission_id)

    async def drop_lease(self, mission_id: str) -> None:
        await self.leases.drop(mission_id)

    # --- fenced writes (gcs/cluster/fencing.py) ------------------------------------------------------

    def put_fenced(self, bucket: str, key: str, value: dict[str, Any], mission_id: str) -> None:
        """Queue a leader's write of a record of ``mission_id`` under its lease token (taken now,
        at the decision): the mission record itself by compare-and-set, other records after a
        check that no newer leader stamped the mission record. A refused write is dropped."""
        token = self.leases.decision_token(mission_id)
        data = json.dumps(value, separators=(",", ":")).encode()
        if bucket == "missions":
            self.mirror[bucket][key] = data
            self.enqueue(lambda: self.leases.write_record(mission_id, value, token))
            return
        self.mirror[bucket][key] = data

        async def write() -> None:
            if await self.leases.allowed(mission_id, token, f"write of {bucket} {key}"):
                await self.kv[bucket].put(key, data)
            else:
                with contextlib.suppress(nats.js.errors.KeyNotFoundError, nats.js.errors.KeyDeletedError):
                    entry = await self.kv[bucket].get(key)
                    if entry.value is not None:
                        self.mirror[bucket][key] = entry.value  # the stored value, not our refused one

        self.enqueue(write)
