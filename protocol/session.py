"""The session layer without I/O: version negotiation, the type-0/1 handshake, refusal codes.

Both ends of every connection use these state machines (the daemon, the agent, ``agent doctor``,
the benches and the tests), so the handshake exists once. They take decoded bodies and return
the bodies to send, or raise :class:`Refused` (the peer said no, or we say no) or
:class:`~protocol.wire.ProtocolError` (the peer broke the protocol). Sockets live elsewhere
(:mod:`protocol.stream` for asyncio; a blocking client needs only the standard library, see
docs/protocol.md).

Client::

    hs = ClientHandshake(identity, key)
    send(hs.hello())
    send(hs.on_challenge(receive(), home=..., resume=...))
    accepted = hs.on_answer(receive())          # Accepted(cid, version, parameters, ...)

Server::

    hs = ServerHandshake(key_for)
    send(hs.on_hello(receive()))                 # challenge (Refused if unknown identity...)
    auth = hs.on_proof(receive())                # Authenticated(request, version, ...)
    send(hs.accept(cid=..., parameters=...))     # or hs.refusal(code, reason)

Authenticated refusals (version 2): a refusal sent after the agent proved its key carries
``refusal_proof`` (:func:`protocol.auth.refusal_proof`, over both nonces, the code, the wait and
the text); :class:`ClientHandshake` checks it and sets ``Refused.authenticated``. Nothing else a
daemon sends before ``accepted`` is proved, so an agent never stops for good on it.

Capabilities (version 2 only): ``compact_status`` (the binary status body, type byte 0x82) is
offered by ``ClientHandshake(compact_status=True)`` in the packet with the proof, granted by a
``ServerHandshake(compact_status=True)`` in ``accepted``, and in force when ``Accepted.compact_status``
(client) / ``ServerHandshake.compact_status`` (server) is true. ``release_beacon`` (the agent
listens for barrier releases as UDP datagrams, protocol/beacon.py) is offered by
``ClientHandshake(release_beacon=True)`` the same way and needs no grant: the daemon reads it
from ``Authenticated.request`` and sends the chain anchor with each mission's actions.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

from protocol import auth
from protocol.packets import (
    PROTOCOL_VERSION,
    SUPPORTED_VERSIONS,
    AgentParameters,
    Body,
    Capabilities,
    Close,
    CloseReason,
    GeoPoint,
    RequestCid,
    ResponseCid,
    Resume,
)
from protocol.wire import ProtocolError

Action = Literal["retry", "reconnect", "stop"]


class Code(enum.StrEnum):
    """Why a daemon refused or closed a session (type 1 ``code``, type 6 ``code``; v2)."""

    FLEET_FULL = "fleet_full"
    STARTING = "starting"
    BUSY = "busy"
    CID_EXHAUSTED = "cid_exhausted"
    SHUTDOWN = "shutdown"
    HANDSHAKE_TIMEOUT = "handshake_timeout"
    WRONG_KEY = "wrong_key"
    UNKNOWN_IDENTITY = "unknown_identity"
    BANNED = "banned"
    ENROLLMENT_CLOSED = "enrollment_closed"
    CERTIFICATE_MISMATCH = "certificate_mismatch"
    VERSION_UNSUPPORTED = "version_unsupported"
    REPLACED = "replaced"
    LOST = "lost"
    RATE_LIMITED = "rate_limited"
    PROTOCOL_ERROR = "protocol_error"
    NORMAL = "normal"


ACTIONS: dict[str, Action] = {
    Code.FLEET_FULL: "retry",
    Code.STARTING: "retry",
    Code.BUSY: "retry",
    Code.CID_EXHAUSTED: "retry",
    Code.SHUTDOWN: "reconnect",  # a daemon stopping is usually restarting: come back soon
    Code.HANDSHAKE_TIMEOUT: "retry",
    Code.WRONG_KEY: "stop",
    Code.UNKNOWN_IDENTITY: "stop",
    Code.BANNED: "stop",
    Code.ENROLLMENT_CLOSED: "stop",
    Code.CERTIFICATE_MISMATCH: "stop",
    Code.VERSION_UNSUPPORTED: "stop",
    Code.REPLACED: "reconnect",
    Code.LOST: "reconnect",
    Code.RATE_LIMITED: "reconnect",
    Code.PROTOCOL_ERROR: "reconnect",
    Code.NORMAL: "reconnect",
}
"""What an agent does on each code: ``retry`` = reconnect after a longer backoff (the daemon
cannot take it now), ``reconnect`` = reconnect with the usual backoff (``replaced`` waits 30 s),
``stop`` = do not reconnect until an operator fixes the configuration, but only when the daemon
proved the refusal with the agent's key (:attr:`Refused.final`): an unauthenticated ``stop`` code
(a forged one looks the same) is retried with backoff. Unknown codes: ``retry``."""

CLOSE_REASON: dict[str, CloseReason] = {
    Code.REPLACED: CloseReason.REPLACED,
    Code.SHUTDOWN: CloseReason.SHUTDOWN,
    Code.NORMAL: CloseReason.NORMAL,
    Code.HANDSHAKE_TIMEOUT: CloseReason.PROTOCOL_ERROR,
    Code.RATE_LIMITED: CloseReason.PROTOCOL_ERROR,
    Code.PROTOCOL_ERROR: CloseReason.PROTOCOL_ERROR,
    Code.LOST: CloseReason.PROTOCOL_ERROR,
}
"""The v1 ``reason`` sent along with each code; codes not listed close with ``refused``."""


def action_for(code: str | None) -> Action:
    """What to do on ``code`` (``retry`` for codes this side does not know)."""
    return ACTIONS.get(code or "", "retry")


def close_for(code: Code, message: str) -> Close:
    """The type-6 close carrying ``code`` (and the v1 reason that goes with it)."""
    return Close(reason=CLOSE_REASON.get(code, CloseReason.REFUSED), message=message[:500], code=code.value)


class Refused(Exception):
    """A handshake ended in a refusal (either side), or a session was closed with a code.

    ``code`` is None when the peer is a version-1 daemon, which sends no codes.
    ``authenticated`` (client side): the daemon proved this refusal with the agent's key
    (``refusal_proof``, version 2). Only such a refusal may end an agent's link for good; any
    other answer before or after the handshake could have been forged by an on-path party.
    """

    def __init__(
        self,
        code: str | None,
        message: str,
        retry_after_s: float | None = None,
        *,
        authenticated: bool = False,
    ) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.retry_after_s = retry_after_s
        self.authenticated = authenticated

    @property
    def action(self) -> Action:
        return action_for(self.code)

    @property
    def final(self) -> bool:
        """A ``stop`` code the daemon proved with the key: the agent stops until restarted."""
        return self.authenticated and self.action == "stop"


def choose_version(offered: Sequence[int], supported: Sequence[int] = SUPPORTED_VERSIONS) -> int | None:
    """The highest version both sides speak, or None."""
    common = set(offered) & set(supported)
    return max(common) if common else None


def offered_versions(request: RequestCid) -> list[int]:
    """What a hello offers: ``versions`` (v2) or just ``protocol_version`` (a v1 agent)."""
    return list(request.versions) if request.versions else [request.protocol_version]


# --- client ------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Accepted:
    """What the client learned from ``accepted``."""

    cid: int | None  # None: the answer to a probe
    version: int
    parameters: AgentParameters | None
    server_time: float | None
    lost: bool
    compact_status: bool = False  # the agent may send status in the compact binary body (0x82)


class ClientHandshake:
    """The agent's side: hello, proof, check the daemon's proof. One object per connection.

    ``versions`` is what the agent offers; ``[1]`` sends a version-1 hello (the fallback for a
    version-1 daemon, which rejects the v2 ``versions`` field). ``compact_status`` offers the
    compact status body, a version-2 capability (offered only when the challenge names version 2).
    """

    def __init__(
        self,
        identity: str,
        key: bytes,
        *,
        versions: Sequence[int] = SUPPORTED_VERSIONS,
        capabilities: Capabilities | None = None,
        probe: bool = False,
        nonce: str | None = None,
        compact_status: bool = False,
        release_beacon: bool = False,
    ) -> None:
        self.identity = identity
        self.compact_status = compact_status
        self.release_beacon = release_beacon
        self.versions = sorted(set(versions))
        self.capabilities = capabilities or Capabilities()
        self.probe = probe
        self.client_nonce = nonce or auth.new_nonce()
        self.server_nonce: str | None = None
        self.state: Literal["hello", "challenge", "answer", "done"] = "hello"
        self._key = key

    def _request(self, **fields: object) -> RequestCid:
        top = max(self.versions)
        return RequestCid.model_validate(
            {
                "identity": self.identity,
                "protocol_version": top,
                "versions": self.versions if top >= 2 else None,
                "client_nonce": self.client_nonce,
                "probe": self.probe,
                **fields,
            }
        )

    def hello(self) -> RequestCid:
        """The first type-0 packet."""
        if self.state != "hello":
            raise RuntimeError("hello() is the first step")
        self.state = "challenge"
        return self._request()

    def on_challenge(
        self, body: Body, *, home: GeoPoint | None = None, resume: Resume | None = None
    ) -> RequestCid:
        """The daemon's answer to the hello; returns the type-0 packet with the proof."""
        if self.state != "challenge":
            raise RuntimeError("on_challenge() follows hello()")
        self._refusal(body)
        if not isinstance(body, ResponseCid) or body.outcome != "challenge" or body.server_nonce is None:
            raise ProtocolError(f"expected a type 1 challenge, got {_describe(body)}")
        if body.protocol_version is not None and body.protocol_version not in self.versions:
            raise ProtocolError(f"the daemon chose version {body.protocol_version}, not offered")
        self.server_nonce = body.server_nonce
        self.state = "answer"
        return self._request(
            capabilities=self.capabilities,
            home=home,
            resume=resume,
            compact_status=True if self.compact_status and (body.protocol_version or 1) >= 2 else None,
            release_beacon=True if self.release_beacon and (body.protocol_version or 1) >= 2 else None,
            proof=auth.agent_proof(self._key, self.identity, body.server_nonce, self.client_nonce),
        )

    def on_answer(self, body: Body) -> Accepted:
        """The daemon's answer to the proof; checks that the daemon holds the key too."""
        if self.state != "answer" or self.server_nonce is None:
            raise RuntimeError("on_answer() follows on_challenge()")
        self._refusal(body)
        if not isinstance(body, ResponseCid) or body.outcome != "accepted":
            raise ProtocolError(f"expected accepted, got {_describe(body)}")
        expected = auth.daemon_proof(self._key, self.identity, self.client_nonce, self.server_nonce)
        if body.server_proof is None or not auth.proofs_equal(body.server_proof, expected):
            raise Refused(Code.WRONG_KEY, "the daemon could not prove it holds our key; not trusting it")
        if body.cid is None and not self.probe:
            raise ProtocolError("accepted without a cid")
        version = body.protocol_version or 1
        if version not in self.versions:
            raise ProtocolError(f"the daemon accepted with version {version}, not offered")
        self.state = "done"
        compact = version >= 2 and self.compact_status and body.compact_status is True
        return Accepted(body.cid, version, body.parameters, body.server_time, bool(body.lost), compact)

    def _refusal(self, body: Body) -> None:
        if isinstance(body, ResponseCid) and body.outcome == "refused":
            code = body.code
            if code is None and max(self.versions) >= 2 and self.state == "challenge":
                code = _v1_daemon_code(body.reason or "")
            raise Refused(
                code,
                f"daemon refused {self.identity}: {body.reason}",
                body.retry_after_s,
                authenticated=self._proved(body),
            )
        if isinstance(body, Close):
            code = body.code
            if code is None and max(self.versions) >= 2 and self.state == "challenge":
                code = _v1_daemon_code(body.message)
            raise Refused(code, f"daemon closed: {body.reason.value} {body.message}".strip())

    def _proved(self, body: ResponseCid) -> bool:
        """Whether a refusal carries a ``refusal_proof`` made with our key for this connection."""
        server_nonce = self.server_nonce or body.server_nonce
        if body.refusal_proof is None or body.code is None or server_nonce is None:
            return False
        if body.server_nonce is not None and body.server_nonce != server_nonce:
            return False
        expected = auth.refusal_proof(
            self._key,
            self.identity,
            self.client_nonce,
            server_nonce,
            body.code,
            body.retry_after_s,
            body.reason or "",
        )
        return auth.proofs_equal(body.refusal_proof, expected)


V1_DAEMON = "v1_daemon"
"""Pseudo-code of a codeless refusal of a v2 hello: a version-1 daemon; retry with ``versions=[1]``."""


def _v1_daemon_code(text: str) -> str | None:
    """A version-1 daemon refuses a v2 hello without a code: as an unknown field or version."""
    lowered = text.lower()
    if "versions" in lowered or "protocol version" in lowered or "extra" in lowered:
        return V1_DAEMON
    return None


# --- server ------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Authenticated:
    """A proof checked: the daemon now decides (fleet full, enrollment...) and accepts or refuses."""

    request: RequestCid  # the second type-0 packet (capabilities, home, resume)
    version: int
    key: bytes
    probe: bool


class ServerHandshake:
    """The daemon's side. ``key_for(identity)`` is the key to check, None = unknown identity.

    ``compact_status``: the daemon takes the compact status body from a v2 agent that offers it.
    """

    def __init__(
        self,
        key_for: Callable[[str], bytes | None],
        *,
        versions: Sequence[int] = SUPPORTED_VERSIONS,
        nonce: str | None = None,
        compact_status: bool = True,
    ) -> None:
        self._key_for = key_for
        self.compact_supported = compact_status
        self.compact_status = False  # negotiated: set by accept()
        self.supported = tuple(versions)
        self.server_nonce = nonce or auth.new_nonce()
        self.version = 1  # what refusals are shaped for until a hello names a common version
        self.hello: RequestCid | None = None
        self.state: Literal["hello", "proof", "decide", "done"] = "hello"
        self._key: bytes | None = None

    def on_hello(self, body: Body) -> ResponseCid:
        """Check the first packet; returns the challenge, or raises :class:`Refused`."""
        if self.state != "hello":
            raise RuntimeError("on_hello() is the first step")
        if not isinstance(body, RequestCid):
            raise ProtocolError(f"expected a type 0 request first, got {_describe(body)}")
        self.hello = body
        version = choose_version(offered_versions(body), self.supported)
        if version is None:
            self.version = 2 if max(offered_versions(body)) >= 2 else 1  # a newer peer reads codes
            raise Refused(
                Code.VERSION_UNSUPPORTED,
                f"protocol version(s) {offered_versions(body)} not supported "
                f"(daemon speaks {list(self.supported)})",
            )
        self.version = version
        key = self._key_for(body.identity)
        if key is None:
            raise Refused(
                Code.UNKNOWN_IDENTITY, f"unknown agent {body.identity!r}: no key is configured for it"
            )
        self._key = key
        self.state = "proof"
        return ResponseCid(
            outcome="challenge",
            server_nonce=self.server_nonce,
            protocol_version=version if version >= 2 else None,
        )

    def on_proof(self, body: Body) -> Authenticated:
        """Check the second packet's proof; raises :class:`Refused` on a wrong key."""
        if self.state != "proof" or self.hello is None or self._key is None:
            raise RuntimeError("on_proof() follows on_hello()")
        hello = self.hello
        if not isinstance(body, RequestCid) or body.identity != hello.identity:
            raise ProtocolError("expected the type 0 request with proof for the same identity")
        if body.client_nonce != hello.client_nonce or body.proof is None:
            raise Refused(Code.WRONG_KEY, "proof missing or client nonce changed")
        expected = auth.agent_proof(self._key, hello.identity, self.server_nonce, hello.client_nonce)
        if not auth.proofs_equal(body.proof, expected):
            raise Refused(Code.WRONG_KEY, f"authentication failed for {hello.identity!r}: wrong key")
        self.state = "decide"
        self.compact_status = self.compact_supported and self.version >= 2 and body.compact_status is True
        return Authenticated(body, self.version, self._key, hello.probe or body.probe)

    def accept(
        self,
        cid: int | None,
        parameters: AgentParameters | None,
        server_time: float | None,
        lost: bool = False,
    ) -> ResponseCid:
        """The ``accepted`` answer (``cid`` None for a probe)."""
        if self.state != "decide" or self.hello is None or self._key is None:
            raise RuntimeError("accept() follows a successful on_proof()")
        self.state = "done"
        hello = self.hello
        v2 = self.version >= 2
        return ResponseCid(
            outcome="accepted",
            cid=cid,
            server_nonce=self.server_nonce,
            server_proof=auth.daemon_proof(self._key, hello.identity, hello.client_nonce, self.server_nonce),
            parameters=parameters,
            server_time=server_time,
            protocol_version=self.version if v2 else None,
            lost=lost if v2 else None,
            compact_status=True if self.compact_status else None,
        )

    def refusal(self, code: Code, reason: str, retry_after_s: float | None = None) -> list[Body]:
        """The type-1 refusal and type-6 close that end a refused handshake.

        Once the agent has proved its key (version 2), the refusal carries ``refusal_proof``: the
        agent can tell it from one forged by an on-path party, and only then may stop for good.
        """
        signable = self.state == "decide" and self.version >= 2
        self.state = "done"
        bodies = refusal(code, reason, retry_after_s)
        answer = bodies[0]
        if signable and self.hello is not None and self._key is not None and isinstance(answer, ResponseCid):
            proof = auth.refusal_proof(
                self._key,
                self.hello.identity,
                self.hello.client_nonce,
                self.server_nonce,
                code.value,
                answer.retry_after_s,
                answer.reason or "",
            )
            bodies[0] = answer.model_copy(update={"server_nonce": self.server_nonce, "refusal_proof": proof})
        return bodies


def refusal(code: Code, reason: str, retry_after_s: float | None = None) -> list[Body]:
    """Type 1 ``refused`` + type 6 with ``code`` (also before any hello was read)."""
    if retry_after_s is None and action_for(code) == "retry":
        retry_after_s = 10.0
    return [
        ResponseCid(outcome="refused", reason=reason[:500], code=code.value, retry_after_s=retry_after_s),
        Close(reason=CloseReason.REFUSED, message=reason[:500], code=code.value),
    ]


def _describe(body: Body) -> str:
    if isinstance(body, ResponseCid):
        return f"type 1 {body.outcome}"
    if isinstance(body, Close):
        return f"type 6 close ({body.reason.value}: {body.message})"
    return type(body).__name__


__all__ = [
    "ACTIONS",
    "PROTOCOL_VERSION",
    "SUPPORTED_VERSIONS",
    "V1_DAEMON",
    "Accepted",
    "Authenticated",
    "ClientHandshake",
    "Code",
    "Refused",
    "ServerHandshake",
    "action_for",
    "choose_version",
    "close_for",
    "offered_versions",
    "refusal",
]
