"""ASGI guard in front of the HTTP API: Host/Origin, token before body, body size while reading.

* **Host and Origin** (HTTP and WebSocket): a web page the operator visits must not read the
  fleet. A request whose ``Host`` is not an allowed name (DNS rebinding), or that carries an
  ``Origin`` of another site, is refused with 403 before it reaches the API.
* **Token first**: every call that is not a read (POST, PUT, PATCH, DELETE) must carry the
  bearer token, checked from the headers before one body byte is read.
* **Reads beyond loopback**: when the API listens on anything but a loopback address (or
  ``http_reads_need_token = "always"``), every read too (GET, HEAD, OPTIONS, the WebSocket
  stream) must carry the API token or the read-only token (``api_read_token``); only the
  dashboard's static files, the API description and map tiles stay open (:data:`OPEN_READS`),
  since they hold no fleet data and the page is where the operator enters the token. A browser
  cannot set headers on a WebSocket, so the stream also takes the token as a subprotocol
  ``bearer.<token>`` offered beside ``fleetgcs``.
* **Body size**: ``Content-Length`` above the limit is refused at once (413); a body without
  one (chunked) is counted while it is read and cut off at the limit, before any parsing.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any
from urllib.parse import urlsplit

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

READ_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})
WILDCARDS = frozenset({"0.0.0.0", "::", ""})
OPEN_READS = ("/ui/", "/docs-assets/", "/api/v1/tiles/")
"""Path prefixes readable without a token even beyond loopback (no fleet data in them)."""
OPEN_PATHS = frozenset({"/", "/ui", "/docs", "/openapi.json"})
BEARER_SUBPROTOCOL = "bearer."
"""A WebSocket subprotocol ``bearer.<token>`` carries the token where a browser cannot set headers."""
NEEDS_TOKEN = "this call needs 'Authorization: Bearer <token>' (see api.token)"
NEEDS_READ_TOKEN = (
    "reads need 'Authorization: Bearer <token>' (the API token or the read-only token) "
    "because the API listens beyond loopback"
)


def is_loopback_bind(host: str | None) -> bool:
    """Whether an HTTP listen address reaches this machine only (``localhost``, 127.0.0.0/8, ::1).

    A wildcard (``0.0.0.0``, ``::``) or a DNS name other than ``localhost`` counts as beyond loopback.
    """
    if host is None:
        return True  # no HTTP listener at all
    name = host.strip("[]").lower()
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def _bearer(headers: dict[str, str], websocket: bool) -> str:
    """The token a request carries: its Authorization header or, on a WebSocket, a bearer subprotocol."""
    given = headers.get("authorization", "")
    if given or not websocket:
        return given
    for offered in headers.get("sec-websocket-protocol", "").split(","):
        offered = offered.strip()
        if offered.startswith(BEARER_SUBPROTOCOL):
            return "Bearer " + offered[len(BEARER_SUBPROTOCOL) :]
    return ""


def _matches(given: str, token: str | None) -> bool:
    if not token:
        return False
    return hmac.compare_digest(given.encode("utf-8", "replace"), f"Bearer {token}".encode())


def allowed_host(host: str, listen_host: str | None, extra: frozenset[str]) -> bool:
    """Whether a ``Host``/``Origin`` host name may address this API.

    Loopback names always; the listen address; names in ``extra``; and, when listening on every
    address, any IP literal (a DNS name must then be listed: that is what rebinding uses).
    """
    name = host.strip("[]").lower()
    if name in LOOPBACK_NAMES or name in extra or (listen_host and name == listen_host.lower()):
        return True
    if listen_host in WILDCARDS or listen_host is None:
        try:
            ipaddress.ip_address(name)
        except ValueError:
            return False
        return True
    return False


def _host_of(value: str) -> str:
    """The host part of a ``Host`` header (``name:port``, ``[v6]:port``)."""
    return urlsplit(f"//{value}").hostname or ""


class HttpGuard:
    """Pure ASGI middleware (``app.add_middleware(HttpGuard, ...)``)."""

    def __init__(
        self,
        app: ASGIApp,
        token: Callable[[], str],
        max_body_bytes: int,
        listen_host: str | None,
        allowed_hosts: list[str] | None = None,
        read_token: Callable[[], str | None] | None = None,
        reads_need_token: bool | None = None,
    ) -> None:
        self.app = app
        self.token = token
        self.read_token = read_token or (lambda: None)
        self.max_body_bytes = max_body_bytes
        self.listen_host = listen_host
        self.extra = frozenset(h.lower() for h in allowed_hosts or ())
        # None: decided by the listen address (loopback: reads open, as before)
        self.reads_need_token = (
            not is_loopback_bind(listen_host) if reads_need_token is None else reads_need_token
        )

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        problem = self._check(scope, headers)
        if problem is not None:
            status, title, detail = problem
            if scope["type"] == "websocket":
                if "websocket.http.response" in scope.get("extensions", {}):  # a real 401/403 answer
                    await _respond(send, status, title, detail, "websocket.http.response")
                else:  # closed before the upgrade: the server answers 403
                    await send({"type": "websocket.close", "code": 1008, "reason": detail[:120]})
            else:
                await _respond(send, status, title, detail)
            return
        if scope["type"] == "websocket" or scope.get("method", "GET") in READ_METHODS:
            await self.app(scope, receive, send)
            return
        started = rejected = False
        received = 0

        async def counted_receive() -> Message:
            nonlocal received, rejected
            if rejected:
                return {"type": "http.disconnect"}
            message = await receive()
            if message.get("type") == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_body_bytes:
                    # Answer now and tell the app the client left: it never sees the rest.
                    rejected = True
                    if not started:
                        await _respond(send, 413, "request too large", self._too_large())
                    return {"type": "http.disconnect"}
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if rejected:
                return  # the app's answer to a body we cut off is dropped: ours went out
            if message.get("type") == "http.response.start":
                started = True
            await send(message)

        await self.app(scope, counted_receive, guarded_send)

    def _too_large(self) -> str:
        return f"the request body exceeds {self.max_body_bytes} bytes"

    def _check(self, scope: Scope, headers: dict[str, str]) -> tuple[int, str, str] | None:
        host = _host_of(headers.get("host", ""))
        if host and not allowed_host(host, self.listen_host, self.extra):
            return 403, "forbidden host", f"Host {host!r} is not an address of this daemon"
        origin = headers.get("origin")
        if origin and origin != "null":
            origin_host = urlsplit(origin).hostname or ""
            if not allowed_host(origin_host, self.listen_host, self.extra):
                return 403, "forbidden origin", f"requests from {origin!r} are not allowed"
        elif origin == "null":
            return 403, "forbidden origin", "requests from an opaque origin are not allowed"
        websocket = scope["type"] == "websocket"
        if not websocket and scope.get("method", "GET") not in READ_METHODS:
            if not _matches(headers.get("authorization", ""), self.token()):
                return 401, "unauthorized", NEEDS_TOKEN
            length = headers.get("content-length")
            if length is not None and (not length.isdigit() or int(length) > self.max_body_bytes):
                return 413, "request too large", self._too_large()
        elif self.reads_need_token and not self._open_read(scope.get("path", "/")):
            given = _bearer(headers, websocket)
            if not (_matches(given, self.token()) or _matches(given, self.read_token())):
                return 401, "unauthorized", NEEDS_READ_TOKEN
        return None

    @staticmethod
    def _open_read(path: str) -> bool:
        return path in OPEN_PATHS or path.startswith(OPEN_READS)


async def _respond(send: Send, status: int, title: str, detail: str, prefix: str = "http.response") -> None:
    body = json.dumps({"type": "about:blank", "title": title, "status": status, "detail": detail}).encode()
    await send(
        {
            "type": f"{prefix}.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/problem+json"),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": f"{prefix}.body", "body": body})


__all__ = ["BEARER_SUBPROTOCOL", "HttpGuard", "allowed_host", "is_loopback_bind"]
