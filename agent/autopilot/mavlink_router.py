"""A MAVLink router in the agent: extra endpoints (a pilot's QGroundControl, MAVProxy) share the
one autopilot link the agent owns, as mavlink-router or MAVProxy ``--out`` do on a companion.

* **Autopilot -> endpoints**: every frame the agent's link receives is written, unchanged, to each
  endpoint that should see it, routed by target like mavlink-router: a frame without a target
  (HEARTBEAT, telemetry, STATUSTEXT) or with target system 0 goes to every endpoint; a targeted
  one only to endpoints that sent from that system (and component, unless 0). The autopilot's
  answers to the agent (COMMAND_ACK, PARAM_VALUE, mission items addressed to the agent's system
  and component 191) thus never reach another ground station as if they were its own.
* **Endpoints -> autopilot**: every frame an endpoint sends is written, unchanged, to the
  autopilot link (frames addressed to the agent itself are dropped). What another ground station
  commands is a pilot's command: a mode it sets is not one the agent asked for, so the agent's
  :class:`agent.autopilot.flavours.base.ModeOwner` reports the pilot in control (agent/pilot.py).
* The agent's own frames are not copied to the endpoints: they are the agent's, not the vehicle's.

Endpoints (``--mavlink-out``, ``[autopilot] mavlink_out``, ``FLEETGCS_AUTOPILOT_MAVLINK_OUT``):
``udp:HOST:PORT`` / ``udpout:HOST:PORT`` sends to a ground station listening there (QGC's 14550)
and takes what it sends back; ``udpin:HOST:PORT`` listens and answers the last sender;
``tcpin:HOST:PORT`` listens for TCP ground stations (each connection its own endpoint).

One thread (selectors, bounded waits) reads the endpoints; the link's reader thread writes the
autopilot's frames out. Writes never block: a frame a slow endpoint cannot take is dropped
(counted in :attr:`MavlinkRouter.stats`), as a radio would.
"""

from __future__ import annotations

import contextlib
import logging
import selectors
import socket
import threading
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger(__name__)

SCHEMES = ("udp", "udpout", "udpin", "tcpin")
MAX_TCP_CLIENTS = 8
SELECT_S = 0.2
READ_SIZE = 65_536
TCP_BACKLOG = 256 * 1024  # bytes kept for a TCP ground station that reads slowly


class RouterConfigError(ValueError):
    """An endpoint string the router cannot use (the message says which and why)."""


@dataclass(frozen=True)
class EndpointSpec:
    scheme: str
    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.scheme}:{self.host}:{self.port}"


def parse_endpoint(text: str) -> EndpointSpec:
    """``SCHEME:HOST:PORT`` with SCHEME one of udp, udpout, udpin, tcpin."""
    scheme, sep, rest = text.strip().partition(":")
    host, sep2, port = rest.rpartition(":")
    if not sep or not sep2 or scheme not in SCHEMES:
        raise RouterConfigError(
            f"mavlink-out {text!r}: expected SCHEME:HOST:PORT with SCHEME one of {', '.join(SCHEMES)} "
            "(e.g. udp:192.168.1.20:14550 for QGroundControl on a tablet)"
        )
    if not port.isdigit() or not 0 < int(port) < 65_536:
        raise RouterConfigError(f"mavlink-out {text!r}: the port must be 1..65535")
    return EndpointSpec(scheme, host.strip("[]") or "0.0.0.0", int(port))


@dataclass(eq=False)
class _Peer:
    """One ground station behind the router: where to write, and the ids it sent from."""

    name: str
    sock: socket.socket
    remote: tuple[str, int] | None  # UDP: where to send (None until a udpin sender is heard)
    tcp: bool
    parser: Any = None
    backlog: bytearray = field(default_factory=bytearray)  # TCP: bytes the socket did not take yet
    systems: set[int] = field(default_factory=set)
    components: set[tuple[int, int]] = field(default_factory=set)

    def __post_init__(self) -> None:
        # Imported here: the configuration (agent/config_file.py) parses endpoints without pymavlink.
        from pymavlink.dialects.v20 import ardupilotmega as mavlink

        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True

    def wants(self, msg: Any) -> bool:
        """mavlink-router's rule: broadcasts to everyone, targeted frames to whoever uses the target."""
        target = getattr(msg, "target_system", 0) or 0
        if target == 0:
            return True
        if target not in self.systems:
            return False
        component = getattr(msg, "target_component", 0) or 0
        return component == 0 or (target, component) in self.components


class MavlinkRouter:
    """Extra MAVLink endpoints beside the agent's autopilot link (see the module doc)."""

    def __init__(
        self,
        endpoints: Iterable[str],
        to_autopilot: Callable[[bytes], None],
        own_ids: Callable[[], tuple[int, int]],
    ) -> None:
        self.specs = [parse_endpoint(e) for e in endpoints]
        self._to_autopilot = to_autopilot
        self._own_ids = own_ids
        self.stats: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._peers: list[_Peer] = []
        self._listeners: list[socket.socket] = []
        self._sel: selectors.BaseSelector | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    @property
    def peers(self) -> int:
        with self._lock:
            return len(self._peers)

    # ------------------------------------------------------------------ lifecycle

    def open(self) -> None:
        """Bind/prepare every endpoint (raises :class:`RouterConfigError` naming the one that fails)."""
        sel = selectors.DefaultSelector()
        try:
            for spec in self.specs:
                self._open_one(spec, sel)
        except OSError as exc:
            self._close_all(sel)
            raise RouterConfigError(f"mavlink-out {spec}: {exc.strerror or exc}") from exc
        self._sel = sel

    def _open_one(self, spec: EndpointSpec, sel: selectors.BaseSelector) -> None:
        if spec.scheme == "tcpin":
            listener = socket.create_server((spec.host, spec.port))
            listener.setblocking(False)
            self._listeners.append(listener)
            sel.register(listener, selectors.EVENT_READ, None)
            return
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        if spec.scheme == "udpin":
            sock.bind((spec.host, spec.port))
            remote = None
        else:
            sock.bind(("0.0.0.0" if spec.host not in ("127.0.0.1", "localhost") else spec.host, 0))
            remote = (spec.host, spec.port)
        peer = _Peer(str(spec), sock, remote, tcp=False)
        self._peers.append(peer)
        sel.register(sock, selectors.EVENT_READ, peer)

    def start(self) -> None:
        if self._sel is None:
            self.open()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="mavlink-router", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread and close every socket (idempotent; blocks up to ~1 s)."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        sel, self._sel = self._sel, None
        self._close_all(sel)

    def _close_all(self, sel: selectors.BaseSelector | None) -> None:
        with self._lock:
            socks = [p.sock for p in self._peers] + self._listeners
            self._peers, self._listeners = [], []
        for sock in socks:
            with contextlib.suppress(OSError):
                sock.close()
        if sel is not None:
            sel.close()

    # ------------------------------------------------------------------ autopilot -> endpoints

    def from_autopilot(self, msg: Any) -> None:
        """A frame the agent's link received (called on its reader thread): copy it out."""
        try:
            raw = msg.get_msgbuf()
        except Exception:
            return
        if not raw:
            return
        with self._lock:
            peers = [p for p in self._peers if p.wants(msg)]
            withheld = len(self._peers) - len(peers)
        if withheld:
            self.stats["withheld"] += withheld  # addressed to the agent or to another station
        for peer in peers:
            self._write(peer, bytes(raw))

    def _write(self, peer: _Peer, raw: bytes) -> None:
        try:
            if peer.tcp:
                self._write_stream(peer, raw)
                return
            if peer.remote is None:
                return  # udpin: nobody heard from yet
            peer.sock.sendto(raw, peer.remote)
            self.stats["out"] += 1
        except BlockingIOError:
            self.stats["out_dropped"] += 1
        except OSError:
            self.stats["out_failed"] += 1  # no listener yet (ICMP refused): a GCS not started

    def _write_stream(self, peer: _Peer, raw: bytes) -> None:
        """TCP keeps frames whole: what the socket does not take waits (up to TCP_BACKLOG bytes;
        beyond that whole frames are dropped, never half of one)."""
        if len(peer.backlog) + len(raw) > TCP_BACKLOG:
            self.stats["out_dropped"] += 1
        else:
            peer.backlog += raw
            self.stats["out"] += 1
        try:
            sent = peer.sock.send(peer.backlog)
        except BlockingIOError:
            return
        del peer.backlog[:sent]

    # ------------------------------------------------------------------ endpoints -> autopilot

    def _run(self) -> None:
        while not self._stop.is_set():
            sel = self._sel
            if sel is None:
                return
            try:
                events = sel.select(SELECT_S)
            except (OSError, ValueError):
                return
            for key, _ in events:
                try:
                    if key.data is None:
                        self._accept(key.fileobj, sel)  # type: ignore[arg-type]
                    else:
                        self._read(key.data, sel)
                except Exception:
                    log.exception("mavlink router: endpoint %s failed", getattr(key.data, "name", "listener"))

    def _accept(self, listener: socket.socket, sel: selectors.BaseSelector) -> None:
        conn, addr = listener.accept()
        if self.peers >= MAX_TCP_CLIENTS + len(self.specs):
            conn.close()
            self.stats["refused"] += 1
            return
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        peer = _Peer(f"tcp {addr[0]}:{addr[1]}", conn, None, tcp=True)
        with self._lock:
            self._peers.append(peer)
        sel.register(conn, selectors.EVENT_READ, peer)
        log.info("mavlink router: %s connected", peer.name)

    def _read(self, peer: _Peer, sel: selectors.BaseSelector) -> None:
        try:
            if peer.tcp:
                data = peer.sock.recv(READ_SIZE)
                if not data:
                    self._drop_peer(peer, sel)
                    return
            else:
                data, sender = peer.sock.recvfrom(READ_SIZE)
                if peer.remote is None or peer.name.startswith("udpin"):
                    peer.remote = sender  # udpin: answer whoever spoke last
        except BlockingIOError:
            return
        except OSError:
            if peer.tcp:
                self._drop_peer(peer, sel)
            return  # UDP: an ICMP "port unreachable" from a GCS not running yet
        self._forward(peer, data)

    def _forward(self, peer: _Peer, data: bytes) -> None:
        try:
            msgs = peer.parser.parse_buffer(data) or []
        except Exception:  # unrecoverable framing: drop the chunk, the parser resyncs
            self.stats["in_bad"] += 1
            return
        own = self._own_ids()
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self.stats["in_bad"] += 1
                continue
            src = (msg.get_srcSystem(), msg.get_srcComponent())
            if src == own:
                continue  # our own frame echoed back: never re-sent
            with self._lock:
                peer.systems.add(src[0])
                peer.components.add(src)
            target = (getattr(msg, "target_system", 0) or 0, getattr(msg, "target_component", 0) or 0)
            if target == own:
                self.stats["in_for_agent"] += 1
                continue  # addressed to the agent, not the vehicle
            try:
                self._to_autopilot(bytes(msg.get_msgbuf()))
                self.stats["in"] += 1
            except Exception:
                self.stats["in_failed"] += 1

    def _drop_peer(self, peer: _Peer, sel: selectors.BaseSelector) -> None:
        with contextlib.suppress(KeyError, ValueError):
            sel.unregister(peer.sock)
        with self._lock, contextlib.suppress(ValueError):
            self._peers.remove(peer)
        with contextlib.suppress(OSError):
            peer.sock.close()
        log.info("mavlink router: %s disconnected", peer.name)
