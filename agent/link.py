"""The agent's side of the daemon link: connect, authenticate, reconnect with backoff, buffer, replay.

The handshake is :class:`protocol.session.ClientHandshake` over a :class:`protocol.stream.FramedStream`
(the one implementation every client uses). The agent offers protocol versions 1 and 2; a
version-1 daemon refuses the v2 hello without a code, and the link then speaks version 1.

While the link is down, status reports go into a bounded buffer (oldest dropped first) and
control packets (sync "finished") into an unbounded one. After the next ``accepted`` the agent
sends, in this order (docs/protocol.md section 2): the buffered reports oldest first, thinned to
``replay_max_reports`` (state changes kept), the control packets in order, then a fresh status
report, all before its first status period. The daemon counts replayed reports apart from live
frames (its replay allowance has a burst of 400), so a long outage never trips the rate limit.

On a version-2 session a replayed report stays buffered after it is sent, until the daemon
acknowledges that it is stored (a type 3 with ``replay_stored``: every replayed report up to
that agent time): a daemon killed between receiving the replay and committing it to its
database would otherwise lose the whole outage. What is not acknowledged when the link drops
is replayed again after the next ``accepted`` (the daemon ignores a report it already stored).
The buffer keeps its bound (``status_buffer``). A version-1 session forgets a report once sent.

Refusal and close codes decide what happens next (:data:`protocol.session.ACTIONS`): ``retry``
waits the daemon's ``retry_after_s`` (``REFUSED_BACKOFF_S`` when it names none; an unproved wait
is capped at ``UNPROVED_RETRY_MAX_S``), ``reconnect`` uses the normal backoff (``replaced`` waits
``REPLACED_BACKOFF_S`` so two agents with one identity do not take turns kicking each other off).
``stop`` (wrong key, banned...) ends the link until restart only when the daemon proved the
refusal with our key (``refusal_proof``, :attr:`protocol.session.Refused.final`): anything else
before ``accepted`` may have been forged by an on-path party without the key, so it is logged
as an error and retried with a backoff doubling to ``UNPROVED_STOP_MAX_S``. A stopped agent keeps
flying its queue and applies its lost-link failsafe.

Version fallback: a code-less refusal of the v2 hello that names the versions (what a version-1
daemon answers) is unproved too; the agent falls back to version 1 only after
``V1_FALLBACK_AFTER`` such answers in a row (a WARNING), and offers version 2 again at its first
connection ``V2_RETRY_S`` later. A bad frame from the daemon is answered with a type-6 close
(code ``protocol_error``) before the connection is dropped.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import ssl
import time
from collections import deque
from collections.abc import Awaitable, Callable, Sequence

from agent.config import AgentConfig
from protocol.packets import (
    SUPPORTED_VERSIONS,
    Body,
    Close,
    CloseReason,
    GeoPoint,
    PerformActions,
    Resume,
    SetParameters,
    StatusReport,
    SyncSignal,
)
from protocol.session import V1_DAEMON, ClientHandshake, Code, Refused, close_for
from protocol.stream import FramedStream, client_handshake
from protocol.wire import Frame, ProtocolError

log = logging.getLogger("agent.link")

REPLACED_BACKOFF_S = 30.0
REFUSED_BACKOFF_S = 10.0  # a retry code without retry_after_s, or a code-less (v1) refusal
UNPROVED_RETRY_MAX_S = 30.0  # the longest retry_after_s an unproved refusal may impose
PROVED_RETRY_MAX_S = 600.0  # ... and a refusal the daemon proved with our key
UNPROVED_STOP_MAX_S = 10.0  # the backoff after unproved stop codes doubles up to this
V1_FALLBACK_AFTER = 3  # v1-daemon answers in a row before the agent speaks version 1
V2_RETRY_S = 300.0  # on version 1 this long: offer version 2 again at the next connection


def client_tls_context(config: AgentConfig) -> ssl.SSLContext | None:
    """TLS towards the daemon when a CA is configured; with tls_cert, mutual TLS."""
    if config.tls_ca is None:
        return None
    context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH, cafile=str(config.tls_ca))
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    if config.tls_cert is not None:
        context.load_cert_chain(config.tls_cert, config.tls_key)
    return context


def _milestone(report: StatusReport) -> tuple[object, ...]:
    failure = report.failure.time if report.failure else None
    return (
        report.mission_id,
        report.step,
        report.completed_step,
        report.waiting_sync,
        report.mode,
        report.armed,
        report.landed,
        report.paused,
        failure,
        tuple(report.exceptions),
        report.failsafe,
        report.pilot,
    )


def thin_replay(reports: Sequence[StatusReport], limit: int) -> list[StatusReport]:
    """At most ``limit`` of ``reports``, in order: every state change first, then evenly spaced.

    A state change (step, completed step, mode, armed, exceptions...) is what the daemon must
    not miss; the reports between two changes differ only in position and battery.
    """
    if len(reports) <= limit:
        return list(reports)
    keep: set[int] = {len(reports) - 1}
    previous: tuple[object, ...] | None = None
    changes = []
    for index, report in enumerate(reports):
        mark = _milestone(report)
        if mark != previous:
            changes.append(index)
        previous = mark
    if len(changes) >= limit - 1:
        stride = len(changes) / (limit - 1)
        keep.update(changes[int(k * stride)] for k in range(limit - 1))
    else:
        keep.update(changes)
    spare = limit - len(keep)
    if spare > 0:  # evenly spaced among the rest (stride >= 1, so the picks are distinct)
        rest = [i for i in range(len(reports)) if i not in keep]
        stride = len(rest) / spare
        keep.update(rest[int(k * stride)] for k in range(spare))
    return [reports[i] for i in sorted(keep)][:limit]


class DaemonLink:
    """Keeps one authenticated session to the daemon and routes what arrives to handlers."""

    def __init__(
        self,
        config: AgentConfig,
        key: bytes,
        on_actions: Callable[[PerformActions], Awaitable[None]],
        on_release: Callable[[SyncSignal], Awaitable[None]],
        on_parameters: Callable[[SetParameters], Awaitable[None]],
        home: Callable[[], GeoPoint | None],
        resume: Callable[[], Resume | None],
        current_status: Callable[[], StatusReport] | None = None,
    ) -> None:
        self.config = config
        self._key = key
        self._on_actions = on_actions
        self._on_release = on_release
        self._on_parameters = on_parameters
        self._home = home
        self._resume = resume
        self._current_status = current_status
        self.cid: int | None = None
        self.version: int | None = None  # negotiated protocol version of the current session
        self.versions: list[int] = list(SUPPORTED_VERSIONS)  # what we offer; [1] after a v1 daemon
        self.connected = False
        self.last_contact = time.monotonic()
        self.sessions = 0
        self.last_error: str | None = None
        self.last_code: str | None = None  # code of the last refusal or close the daemon sent
        self.stopped: str | None = None  # why the link gave up for good (a proved `stop` code)
        self.unproved_refusals = 0  # stop codes the daemon did not prove with our key (retried)
        self.v1_fallback_after = V1_FALLBACK_AFTER
        self.v2_retry_s = V2_RETRY_S
        self._v1_answers = 0  # v1-daemon answers to our v2 hello in a row
        self._v1_since: float | None = None  # when the link fell back to version 1
        self._unproved_delay = config.reconnect_min_s
        self.was_lost = False  # the daemon said it had marked us lost (v2 `accepted.lost`)
        self.compact_status = False  # the daemon accepted the compact binary status body (v2)
        self.offer_release_beacon = False  # the agent listens for release beacons (agent/beacon.py)
        self.replayed = 0  # buffered status reports sent after outages
        self.thinned = 0  # buffered status reports left out of a replay
        self._stream: FramedStream | None = None
        self._status_backlog: deque[StatusReport] = deque(maxlen=config.status_buffer)
        self._sent_unacked = 0  # the backlog's first reports: replayed, not yet acknowledged (v2)
        self.acknowledged = 0  # replayed reports the daemon said it stored (v2 `replay_stored`)
        self._control_backlog: list[Body] = []
        self._send_lock = asyncio.Lock()
        self._stopping = False
        self._addresses = config.daemon_addresses()
        self._address = 0  # index of the daemon tried next; moves on after each failure

    # --- sending --------------------------------------------------------------------------------

    async def send_status(self, status: StatusReport) -> None:
        if not self.connected or not await self._send(status):
            backlog = self._status_backlog
            if self._sent_unacked and len(backlog) == backlog.maxlen:
                self._sent_unacked -= 1  # the bound pushes out the oldest, a sent one
            backlog.append(status.model_copy(update={"buffered": True}))

    async def send_control(self, body: Body) -> None:
        if not self.connected or not await self._send(body):
            self._control_backlog.append(body)

    async def _send(self, body: Body) -> bool:
        stream = self._stream
        if stream is None:
            return False
        async with self._send_lock:
            try:
                await stream.send(body, timeout=5.0)
            except (OSError, TimeoutError, ConnectionError):
                self._drop()
                return False
        return True

    def _drop(self) -> None:
        self.connected = False
        if self._stream is not None:
            with contextlib.suppress(Exception):
                self._stream.writer.close()
        self._stream = None

    # --- session loop ---------------------------------------------------------------------------

    async def run(self) -> None:
        """Connect, serve, reconnect with jittered exponential backoff; until cancelled or told to stop."""
        delay = self.config.reconnect_min_s
        while not self._stopping:
            backoff: float | None = None
            self._maybe_offer_v2()
            host, port = self._addresses[self._address % len(self._addresses)]
            self._address += 1  # a cluster: the next attempt goes to the next daemon
            try:
                tls = client_tls_context(self.config)
                server_name = (self.config.tls_server_name or host) if tls else None
                async with asyncio.timeout(self.config.handshake_timeout_s):
                    reader, writer = await asyncio.open_connection(
                        host, port, ssl=tls, server_hostname=server_name
                    )
            except (OSError, TimeoutError) as exc:  # ssl.SSLError is an OSError
                self.last_error = f"cannot reach daemon {host}:{port}: {exc!r}"
            else:
                stream = FramedStream(reader, writer)
                try:
                    await self._session(stream)
                    delay = self.config.reconnect_min_s
                except Refused as exc:
                    backoff = self._refused(exc)
                    if self.stopped is not None:
                        return
                except ProtocolError as exc:  # the daemon broke the protocol: say so, then drop it
                    self.last_error = f"link error: {exc}"
                    log.warning("daemon link lost: %s", exc)
                    await stream.close(close_for(Code.PROTOCOL_ERROR, f"bad frame from the daemon: {exc}"))
                except (
                    ConnectionError,
                    OSError,
                    TimeoutError,
                    asyncio.IncompleteReadError,
                ) as exc:
                    self.last_error = f"link error: {exc}"
                    log.warning("daemon link lost: %s", exc)
                except Exception as exc:  # whatever a peer sends, the agent must live on and reconnect
                    self.last_error = f"unexpected link failure: {exc!r}"
                    log.exception("daemon link failed unexpectedly")
                finally:
                    self._drop()
            if self._stopping:
                return
            wait = backoff if backoff is not None else delay * (0.75 + 0.5 * random.random())
            if backoff is None and self._address % len(self._addresses):
                wait = self.config.reconnect_min_s  # other daemons left to try in this round
            await asyncio.sleep(wait)
            if self._address % len(self._addresses) == 0:
                delay = min(self.config.reconnect_max_s, delay * 2)

    def _refused(self, exc: Refused) -> float | None:
        """Act on a refusal or coded close; returns the backoff (None: the usual one)."""
        self.last_error = str(exc)
        self.last_code = exc.code
        if exc.code == V1_DAEMON and self.versions != [1]:
            return self._v1_answer(exc)
        action = exc.action
        if exc.code is None:  # a version-1 daemon: no codes, retry later as before
            log.error("%s", exc)
            return REFUSED_BACKOFF_S
        if exc.final:
            self.stopped = f"{exc.code}: {exc.message}"
            log.error(
                "daemon refused us for good, proved with our key (%s); not reconnecting until restarted",
                self.stopped,
            )
            return None
        if action == "stop":  # unproved: a forged answer looks the same, so never final
            self.unproved_refusals += 1
            wait = self._unproved_delay * (0.75 + 0.5 * random.random())
            self._unproved_delay = min(UNPROVED_STOP_MAX_S, self._unproved_delay * 2)
            log.error(
                "%s (code %s, not proved with our key: check the key and the daemon's configuration, "
                "or someone on the path forged it); retrying in %.1f s",
                exc,
                exc.code,
                wait,
            )
            return wait
        if action == "retry":
            cap = PROVED_RETRY_MAX_S if exc.authenticated else UNPROVED_RETRY_MAX_S
            wanted = REFUSED_BACKOFF_S if exc.retry_after_s is None else exc.retry_after_s
            wait = min(cap, max(self.config.reconnect_min_s, wanted)) * (0.75 + 0.5 * random.random())
            log.warning("%s; retrying in %.1f s", exc, wait)
            return wait
        if exc.code == Code.REPLACED:
            log.error("%s", exc)
            return REPLACED_BACKOFF_S
        log.warning("%s; reconnecting", exc)
        return None

    def _v1_answer(self, exc: Refused) -> float | None:
        """A version-1 daemon's answer to our v2 hello: unproved, so fall back only if it repeats."""
        self._v1_answers += 1
        if self._v1_answers < self.v1_fallback_after:
            log.warning(
                "the daemon answered our version-2 hello as a version-1 daemon would (%d of %d before "
                "falling back; unproved, it may be forged): %s",
                self._v1_answers,
                self.v1_fallback_after,
                exc,
            )
            return None
        log.warning(
            "FALLING BACK to protocol version 1: %d version-1 answers in a row to our version-2 hello; "
            "version 2 is offered again in %g s",
            self._v1_answers,
            self.v2_retry_s,
        )
        self.versions = [1]
        self._v1_since = time.monotonic()
        return self.config.reconnect_min_s

    def _maybe_offer_v2(self) -> None:
        """After ``v2_retry_s`` on a fallback to version 1, the next connection offers version 2 again."""
        since = self._v1_since
        if since is None or time.monotonic() - since < self.v2_retry_s:
            return
        log.warning("offering protocol version 2 again (on version 1 for %.0f s)", time.monotonic() - since)
        self.versions = list(SUPPORTED_VERSIONS)
        self._v1_since = None
        self._v1_answers = 0

    async def stop(self, reason: CloseReason = CloseReason.NORMAL) -> None:
        self._stopping = True
        if self.connected:
            await self._send(Close(reason=reason, message="agent stopping"))
        self._drop()

    async def _session(self, stream: FramedStream) -> None:
        self._stream = stream
        self.compact_status = False
        accepted = await client_handshake(
            stream,
            self.handshake(),
            home=self._home(),
            resume=self._resume(),
            timeout=self.config.handshake_timeout_s,
        )
        self.cid, self.version, self.was_lost = accepted.cid, accepted.version, accepted.lost
        self._unproved_delay = self.config.reconnect_min_s
        if accepted.version >= 2:
            self._v1_answers = 0
        self.compact_status = accepted.compact_status  # client_handshake set the stream to match
        if accepted.parameters is not None:
            await self._on_parameters(SetParameters(parameters=accepted.parameters))
        self.connected = True
        self.sessions += 1
        self.last_contact = time.monotonic()
        log.info(
            "connected to daemon as %s, cid %s, protocol v%d%s",
            self.config.identity,
            self.cid,
            self.version,
            " (the daemon had marked us lost)" if accepted.lost else "",
        )
        # Right after accepted, in time order: the buffered reports (thinned), the buffered
        # control packets, then the current state, before the first period has passed.
        await self._replay()
        await self._flush_control()
        if self._current_status is not None and self.connected:
            await self._send(self._current_status())
        try:
            async for frame in stream.frames(idle_timeout=self.config.daemon_silence_s):
                self.last_contact = time.monotonic()
                await self._dispatch(frame)
                if not self.connected:
                    return
        except TimeoutError:  # a silent partition: TCP open, nothing flowing (the daemon keeps alive)
            raise ConnectionError(f"nothing from the daemon for {self.config.daemon_silence_s:g} s") from None

    def handshake(self) -> ClientHandshake:
        """This session's handshake: our versions, the compact status offer, the release beacon offer."""
        return ClientHandshake(
            self.config.identity,
            self._key,
            versions=self.versions,
            capabilities=self.config.capabilities,
            compact_status=True,
            release_beacon=self.offer_release_beacon,
        )

    async def _flush_control(self) -> None:
        while self._control_backlog and self.connected:
            if not await self._send(self._control_backlog[0]):
                return
            self._control_backlog.pop(0)

    async def _replay(self) -> None:
        """Send the buffered reports, thinned to ``replay_max_reports``, oldest first.

        The thinned replay fits the daemon's separate replay allowance (docs/protocol.md), so it
        goes out at once; what cannot be sent stays buffered for the next session.
        """
        self._sent_unacked = 0  # what the last session did not get acknowledged goes again
        if not self._status_backlog:
            return
        reports = thin_replay(list(self._status_backlog), self.config.replay_max_reports)
        self.thinned += len(self._status_backlog) - len(reports)
        self._status_backlog.clear()
        self._status_backlog.extend(reports)
        keep = self.version is not None and self.version >= 2  # until the daemon acknowledges them
        while len(self._status_backlog) > self._sent_unacked and self.connected:
            if not await self._send(self._status_backlog[self._sent_unacked]):
                return
            if keep:
                self._sent_unacked += 1
            else:
                self._status_backlog.popleft()
            self.replayed += 1

    def _stored(self, until: float) -> None:
        """The daemon stored our replayed reports up to agent time ``until``: forget those (v2)."""
        backlog = self._status_backlog
        while self._sent_unacked and backlog[0].time <= until:
            backlog.popleft()
            self._sent_unacked -= 1
            self.acknowledged += 1

    async def _dispatch(self, frame: Frame) -> None:
        body = frame.body
        if isinstance(body, PerformActions):
            await self._on_actions(body)
        elif isinstance(body, SyncSignal) and body.kind == "release":
            await self._on_release(body)
        elif isinstance(body, SetParameters):
            if body.replay_stored is not None:
                self._stored(body.replay_stored)
            await self._on_parameters(body)
        elif isinstance(body, Close):
            self._drop()
            code = body.code or (Code.REPLACED if body.reason == CloseReason.REPLACED else None)
            if code is not None:
                raise Refused(code, f"daemon closed the session: {body.reason.value} {body.message}".strip())
            raise ConnectionError(f"daemon closed the session: {body.reason.value} {body.message}")
        else:
            raise ProtocolError(f"type {frame.packet_type.value} is not valid from the daemon")

    @property
    def buffered(self) -> tuple[int, int]:
        """(status reports, control packets) waiting for the link (not yet sent)."""
        return len(self._status_backlog) - self._sent_unacked, len(self._control_backlog)

    @property
    def unacknowledged(self) -> int:
        """Replayed status reports kept until the daemon says it stored them (v2)."""
        return self._sent_unacked
