"""Endpoint I/O: one non-blocking loopback socket per vehicle, served by the fleet's single selector loop.

TCP (default) mirrors ArduPilot SITL's SERIAL0: a server port taking one client at a time; a new
connection replaces the old one (so a client that reconnects after a half-open drop is never locked
out). UDP binds a port and answers whoever sent the last datagram (the client must speak first, e.g.
its HEARTBEAT). Stream intervals live here because ArduPilot keeps them per link; they reset to the
defaults (HEARTBEAT + SYS_STATUS at 1 Hz) whenever a new TCP client connects.
"""

from __future__ import annotations

import contextlib
import logging
import math
import socket
from typing import TYPE_CHECKING

from sitl.dialect import mavlink as mav
from sitl.vehicle import BUILDERS

if TYPE_CHECKING:
    from sitl.vehicle import SimVehicle

log = logging.getLogger(__name__)

OUTBUF_LIMIT = 1 << 20  # bytes queued for a slow client before new messages are dropped
LOGGED = frozenset(  # what a ground station asks of the vehicle: kept in SimVehicle.command_log
    {
        "COMMAND_LONG",
        "COMMAND_INT",
        "SET_POSITION_TARGET_GLOBAL_INT",
        "SET_POSITION_TARGET_LOCAL_NED",
        "SET_MODE",
    }
)


class Endpoint:
    """A vehicle's MAVLink endpoint: socket(s), MAVLink framing and per-link stream scheduling."""

    def __init__(
        self,
        vehicle: SimVehicle,
        transport: str,
        host: str,
        port: int,
        min_interval: float,
        remote: tuple[str, int] | None = None,
        name: str = "gcs",
    ) -> None:
        """``name`` "gcs" is the vehicle's own link (SERIAL0); any other (the "pilot" link, as a
        second ground station on SERIAL1) is an extra one: it gets its own streams and the answers
        to what it sends, the vehicle's other messages go to the "gcs" link."""
        if remote is not None and transport != "udp":
            raise ValueError("a remote address needs the udp transport")
        self.vehicle = vehicle
        # PX4 layout: send to a fixed remote port from the start (the client binds it, ``udpin:``)
        # and keep the stream settings when the client's address changes.
        self.remote = remote
        self.transport = transport
        self.host = host
        self.min_interval = min_interval
        self.listener: socket.socket | None = None
        self.conn: socket.socket | None = None
        self.peer: tuple[str, int] | None = remote
        if transport == "tcp":
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, port))
            s.listen(4)
            s.setblocking(False)
            self.listener = s
        elif transport == "udp":
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind((host, port))
            s.setblocking(False)
            self.conn = s
        else:
            raise ValueError(f"unknown transport {transport!r} (tcp or udp)")
        self.port: int = s.getsockname()[1]
        self.mav = self._new_mav()
        self.outbuf = bytearray()
        self.want_write = False
        self.streams: dict[int, list[float]] = {}
        self.next_due = math.inf
        self.dropped_msgs = 0
        self.handler_errors = 0
        self.sent_msgs = 0
        self.name = name
        self.reset_streams()
        if name == "gcs":
            vehicle.link = self

    @property
    def url(self) -> str:
        """pymavlink connection string a client uses for this endpoint."""
        if self.transport == "tcp":
            return f"tcp:{self.host}:{self.port}"
        if self.remote is not None:
            return f"udpin:{self.remote[0]}:{self.remote[1]}"
        return f"udpout:{self.host}:{self.port}"

    @property
    def connected(self) -> bool:
        """True when a client is there to talk to."""
        return self.peer is not None

    def _new_mav(self) -> mav.MAVLink:
        m = mav.MAVLink(None, srcSystem=self.vehicle.sysid, srcComponent=1)
        m.robust_parsing = True
        return m

    # ---------------------------------------------------------------- streams
    def reset_streams(self) -> None:
        """Back to ArduPilot's defaults for a fresh link."""
        t = self.vehicle.t
        self.streams = {mid: [iv, t] for mid, iv in self.vehicle.default_streams().items()}
        self.next_due = t

    def set_message_interval(self, msgid: int, interval_s: float | None) -> None:
        """Stream ``msgid`` every ``interval_s`` sim seconds (clamped to the physics step); None stops it."""
        if interval_s is None:
            self.streams.pop(msgid, None)
            return
        interval = max(self.min_interval, interval_s)
        self.streams[msgid] = [interval, self.vehicle.t]
        self.next_due = min(self.next_due, self.vehicle.t)

    def pump(self, t: float) -> None:
        """Send every stream message that is due at sim time ``t``."""
        if t < self.next_due:
            return
        nxt = math.inf
        if self.peer is None or self.vehicle.link_down:
            for st in self.streams.values():
                if st[1] <= t:
                    st[1] = t + st[0]
                nxt = min(nxt, st[1])
            self.next_due = nxt
            return
        v = self.vehicle
        for mid, st in list(self.streams.items()):
            if st[1] <= t + 1e-9:
                msg = BUILDERS[mid](v)
                if msg is not None:
                    self.send(msg)
                st[1] += st[0]
                if st[1] <= t:
                    st[1] = t + st[0]
            nxt = min(nxt, st[1])
        self.next_due = nxt

    # ---------------------------------------------------------------- output
    def send(self, msg: mav.MAVLink_message) -> None:
        """Frame ``msg`` as MAVLink 2 and queue it (dropped with no client, link down or full buffer)."""
        if self.peer is None or self.vehicle.link_down:
            return
        m = self.mav
        buf = msg.pack(m)
        m.seq = (m.seq + 1) % 256
        if self.transport == "udp":
            try:
                assert self.conn is not None
                self.conn.sendto(buf, self.peer)
                self.sent_msgs += 1
            except OSError:
                self.dropped_msgs += 1
            return
        if len(self.outbuf) > OUTBUF_LIMIT:
            self.dropped_msgs += 1
            return
        self.outbuf += buf
        self.sent_msgs += 1

    def flush(self) -> bool:
        """Write queued bytes; returns True if some remain (caller then waits for writability)."""
        if not self.outbuf or self.conn is None or self.transport != "tcp":
            return False
        try:
            n = self.conn.send(self.outbuf)
            del self.outbuf[:n]
        except BlockingIOError:
            pass
        except OSError:
            self.close_client()
            return False
        return bool(self.outbuf)

    # ---------------------------------------------------------------- input
    def accept(self) -> socket.socket | None:
        """Accept a pending TCP client, replacing the current one.

        Returns the replaced socket (still open: the caller unregisters it from its selector, then closes
        it), or None. Raises BlockingIOError when no client was actually pending.
        """
        assert self.listener is not None
        conn, addr = self.listener.accept()
        old = self.conn
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.conn = conn
        self.peer = addr
        self.outbuf.clear()
        self.mav = self._new_mav()
        self.reset_streams()
        return old

    def close_client(self) -> None:
        """Forget the TCP client (it disconnected or broke); the port keeps listening."""
        if self.transport != "tcp":
            return
        if self.conn is not None:
            with contextlib.suppress(OSError):
                self.conn.close()
        self.conn = None
        self.peer = None
        self.outbuf.clear()

    def read(self, wall_now: float) -> bool:
        """Read what is available and dispatch it to the vehicle; False if the TCP client went away."""
        assert self.conn is not None
        try:
            if self.transport == "udp":
                data, addr = self.conn.recvfrom(65536)
                if self.vehicle.link_down:
                    return True
                if addr != self.peer:
                    self.peer = addr
                    if self.remote is None:
                        self.reset_streams()
            else:
                data = self.conn.recv(65536)
                if not data:
                    return False
        except BlockingIOError:
            return True
        except OSError:
            return self.transport == "udp"
        if self.vehicle.link_down:
            return True  # radio silent: input is lost too
        try:
            msgs = self.mav.parse_buffer(data)
        except Exception:  # pymavlink raises on unrecoverable framing errors; drop the chunk
            return True
        for msg in msgs or ():
            if msg.get_type() == "BAD_DATA":
                continue
            mtype = msg.get_type()
            if mtype in LOGGED:
                entry = (self.vehicle.t, self.name, mtype, getattr(msg, "command", None), msg.get_srcSystem())
                self.vehicle.command_log.append(entry)
            self.vehicle.reply_link = self  # answers (ACKs, parameters) go back where asked
            try:
                self.vehicle.handle(msg, wall_now)
            except Exception:  # one odd message must not take the whole fleet down
                self.handler_errors += 1
                log.exception("vehicle %d failed to handle %s", self.vehicle.sysid, msg.get_type())
            finally:
                self.vehicle.reply_link = None
        return True

    def tick(self, wall_now: float) -> None:
        """Wall-clock protocol timers (mission transfer resends)."""
        if self.vehicle.mission.upload is not None:
            self.vehicle.mission.tick(wall_now)

    def close(self) -> None:
        """Close every socket."""
        for s in (self.conn, self.listener):
            if s is not None:
                with contextlib.suppress(OSError):
                    s.close()
        self.conn = None
        self.listener = None
        self.peer = None
