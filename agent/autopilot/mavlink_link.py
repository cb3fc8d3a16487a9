"""Private transport under :class:`agent.autopilot.mavlink_backend.MavlinkAutopilot`.

One :class:`MavlinkLink` owns one pymavlink connection and one daemon *reader thread*. Why a thread
and not an asyncio task polling a non-blocking socket: pymavlink's serial port (the usual link on a
companion computer, ``/dev/ttyAMA0``) has blocking reads and a reconnect that sleeps, TCP reconnects
sleep too, and a thread keeps the 1 Hz heartbeat going even while the event loop is busy. The thread
only parses bytes and updates plain state; everything the event loop waits on is handed over with
``loop.call_soon_threadsafe`` into per-waiter :class:`asyncio.Queue` objects (see :meth:`subscribe`).
Writes come from both the thread (heartbeat, stream re-asserts) and the loop (commands), so every
write takes ``_send_lock``; each write is a single small frame, so the loop never blocks for long.

Error mapping for every request/answer exchange here (COMMAND_LONG/COMMAND_INT → COMMAND_ACK,
PARAM_SET/PARAM_REQUEST_READ → PARAM_VALUE): answer refused → :class:`CommandRefused` with the
MAV_RESULT name and the latest STATUSTEXT; no answer after ``retries`` sends of ``timeout_s`` each
→ :class:`CommandTimeout`; heartbeat silent longer than ``heartbeat_timeout_s`` (checked before the
first send and every 0.1 s while waiting) → :class:`LinkLost`.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import hashlib
import logging
import math
import os
import re
import struct
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

# MAVLink 2 is needed for mission_type (fences) and STATUSTEXT chunks. pymavlink picks the wire
# protocol from the environment when a dialect is loaded, so set it before importing mavutil.
os.environ["MAVLINK20"] = "1"
os.environ.setdefault("MAVLINK_DIALECT", "ardupilotmega")

from agent.autopilot.lean_mavutil import kept_out

with kept_out():  # mavutil without the v1 "all" dialect and NumPy (agent/autopilot/lean_mavutil.py)
    from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from agent.autopilot.base import CommandRefused, CommandTimeout, LinkLost
from agent.autopilot.mavlink_router import MavlinkRouter, RouterConfigError

log = logging.getLogger(__name__)

DEFAULT_SERIAL_BAUD = 57600  # ArduPilot's default SERIALn_BAUD for TELEM ports; pass 921600 explicitly
WAIT_SLICE_S = 0.1  # how often a waiting command re-checks the heartbeat
STATUSTEXT_KEEP = 20

# Heartbeats from these are never "the vehicle" (ground stations, companions, peripherals).
_NOT_VEHICLE_TYPES = frozenset(
    {
        mavlink.MAV_TYPE_GCS,
        mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
        mavlink.MAV_TYPE_GIMBAL,
        mavlink.MAV_TYPE_ADSB,
        mavlink.MAV_TYPE_CAMERA,
        mavlink.MAV_TYPE_CHARGING_STATION,
        mavlink.MAV_TYPE_FLARM,
        mavlink.MAV_TYPE_SERVO,
        mavlink.MAV_TYPE_ODID,
        mavlink.MAV_TYPE_ANTENNA_TRACKER,
        mavlink.MAV_TYPE_BATTERY,
        mavlink.MAV_TYPE_PARACHUTE,
        mavlink.MAV_TYPE_LOG,
        mavlink.MAV_TYPE_OSD,
        mavlink.MAV_TYPE_IMU,
        mavlink.MAV_TYPE_GPS,
        mavlink.MAV_TYPE_WINCH,
    }
)


class ParamCodec(Protocol):
    """How parameter values travel (:class:`agent.autopilot.flavours.Flavour` implements it)."""

    params_bytewise: bool

    def decode_param(self, raw: float, param_type: int) -> float: ...

    def encode_param(self, value: float, param_type: int) -> float: ...


INT32_MAX = 0x7FFFFFFF  # COMMAND_INT x/y: "no position" (PX4 reads it as NaN lat/lon)


def _int_degrees(degrees: float) -> int:
    """COMMAND_INT x/y for a latitude/longitude in degrees; NaN (no position) as INT32_MAX."""
    return round(degrees * 1e7) if math.isfinite(degrees) else INT32_MAX


def mav_result_name(result: int) -> str:
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else f"MAV_RESULT({result})"


def mission_result_name(result: int) -> str:
    entry = mavlink.enums["MAV_MISSION_RESULT"].get(result)
    return entry.name if entry is not None else f"MAV_MISSION_RESULT({result})"


def signing_key_bytes(key: bytes | str) -> bytes:
    """A MAVLink 2 signing secret: 32 raw bytes, 64 hex digits, or a passphrase (SHA-256, as MAVProxy)."""
    if isinstance(key, bytes):
        if len(key) != 32:
            raise ValueError("a MAVLink signing key is 32 bytes")
        return key
    text = key.strip()
    if len(text) == 64:
        with contextlib.suppress(ValueError):
            return bytes.fromhex(text)
    return hashlib.sha256(text.encode()).digest()


BARE_DEVICE = re.compile(r"^(tty[A-Za-z]+\d*|serial\d+|cu\.[\w.-]+)([:,]\d+)?$")


def parse_connection(connection: str) -> tuple[str, int | None]:
    """Split a connection string into (pymavlink device, serial baud or None for network links).

    Network strings (``udpin:``, ``udpout:``, ``tcp:``, ...) pass through unchanged. Serial strings
    are ``/dev/ttyAMA0:921600``, ``/dev/serial0,921600``, ``serial:/dev/ttyUSB0:57600`` or a bare
    device; pymavlink itself would mistake ``/dev/ttyAMA0:921600`` for a UDP address.
    """
    conn = connection.strip()
    serial = False
    for prefix in ("serial://", "serial:"):
        if conn.startswith(prefix):
            conn, serial = conn[len(prefix) :], True
            break
    if BARE_DEVICE.match(conn):  # ttyUSB0:57600 means /dev/ttyUSB0, not a UDP host named ttyUSB0
        conn = "/dev/" + conn
    if serial or conn.startswith("/dev/") or conn.upper().startswith("COM"):
        for sep in (",", ":"):
            if sep in conn:
                device, baud = conn.rsplit(sep, 1)
                if baud.strip().isdigit():
                    return device, int(baud)
        return conn, DEFAULT_SERIAL_BAUD
    return conn, None


@dataclass(eq=False)
class Subscription:
    """Messages of some types (optionally filtered) copied from the reader thread to the loop."""

    loop: asyncio.AbstractEventLoop
    types: frozenset[str]
    predicate: Callable[[Any], bool] | None
    queue: asyncio.Queue[Any] = field(default_factory=asyncio.Queue)

    async def get(self, timeout: float) -> Any | None:
        """The next message, or None after ``timeout`` seconds."""
        try:
            return await asyncio.wait_for(self.queue.get(), max(0.0, timeout))
        except TimeoutError:
            return None


@dataclass(slots=True, frozen=True)
class StatusText:
    monotonic: float
    severity: int
    text: str


@dataclass(slots=True)
class VehicleIdentity:
    system: int
    component: int
    autopilot: int
    mav_type: int


class MavlinkLink:
    """A pymavlink connection with a reader thread, subscriptions and acknowledged commands."""

    def __init__(
        self,
        connection: str,
        *,
        target_system: int | None,
        source_system: int | None,
        source_component: int,
        heartbeat_timeout_s: float,
        command_timeout_s: float,
        command_retries: int,
        on_message: Callable[[Any], None],
        on_tick: Callable[[], None],
        on_link_restored: Callable[[], None],
        signing_key: bytes | str | None = None,
        allow_unsigned: bool = False,
        tlog_path: str | None = None,
    ) -> None:
        self.connection = connection
        self._tlog_path = tlog_path
        self._signing_key = None if signing_key is None else signing_key_bytes(signing_key)
        self._allow_unsigned = allow_unsigned
        self._wanted_system = target_system
        self._source_system = source_system
        self.source_component = source_component
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.command_timeout_s = command_timeout_s
        self.command_retries = max(1, command_retries)
        self._on_message = on_message
        self._on_tick = on_tick
        self._on_link_restored = on_link_restored

        self.vehicle: VehicleIdentity | None = None
        self.vehicle_found = threading.Event()
        self.last_heartbeat_monotonic = 0.0
        self.last_heartbeat: Any = None
        self.last_seen: dict[str, float] = {}
        self._link_was_lost = False

        self._conn: Any = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._send_lock = threading.Lock()
        self._subs_lock = threading.Lock()
        self._subs: list[Subscription] = []
        self._texts: collections.deque[StatusText] = collections.deque(maxlen=STATUSTEXT_KEEP)
        self._text_chunks: dict[int, list[str]] = {}
        self._param_types: dict[str, int] = {}
        # Set by the backend from the vehicle's flavour: PX4 sends integer values byte-wise.
        self.param_codec: ParamCodec | None = None
        self._command_locks: dict[int, asyncio.Lock] = {}
        self._t0 = time.monotonic()
        # Extra ground stations sharing this link (agent/autopilot/mavlink_router.py), or None.
        self.router: MavlinkRouter | None = None

    # ------------------------------------------------------------------ lifecycle

    def open(self) -> None:
        """Open the pymavlink connection (blocking: TCP connect retries, serial open)."""
        device, baud = parse_connection(self.connection)
        src = self._source_system or self._wanted_system or 254
        kwargs: dict[str, Any] = {
            "source_system": src,
            "source_component": self.source_component,
            "autoreconnect": True,
        }
        if mavutil.mavlink is not mavlink:  # set_dialect imports the XML parser (issue 29): only if needed
            kwargs["dialect"] = "ardupilotmega"
        if baud is not None:
            kwargs["baud"] = baud
        if device.startswith("tcp:"):
            kwargs["retries"] = 3
            kwargs["reconnect_delay"] = 0.5
        try:
            self._conn = mavutil.mavlink_connection(device, **kwargs)
        except OSError as exc:
            raise LinkLost(f"cannot open {self.connection!r}: {exc}") from exc
        if self._tlog_path:
            # Telemetry log in the .tlog format MAVProxy and Mission Planner read: a big-endian
            # 8-byte microsecond timestamp before each message; received here, sent in send().
            self._conn.setup_logfile(self._tlog_path, mode="ab")
        # Make sure we speak MAVLink 2 even if another module loaded the v1 dialect first.
        if not isinstance(self._conn.mav, mavlink.MAVLink):
            self._conn.mav = mavlink.MAVLink(self._conn, srcSystem=src, srcComponent=self.source_component)
            self._conn.mav.robust_parsing = True
        if self._signing_key is not None:
            allow = self._allow_unsigned

            def allow_unsigned(_mav: Any, msg_id: int) -> bool:
                # SiK radios inject unsigned RADIO_STATUS even on signed links (MAVProxy accepts it too).
                return allow or msg_id == mavlink.MAVLINK_MSG_ID_RADIO_STATUS

            self._conn.setup_signing(
                self._signing_key, sign_outgoing=True, allow_unsigned_callback=allow_unsigned
            )
        if self.router is not None:
            try:
                self.router.open()
            except RouterConfigError as exc:
                self.stop()
                raise LinkLost(str(exc)) from exc

    def start(self) -> None:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"mavlink-{self.connection}", daemon=True)
        self._thread.start()
        if self.router is not None:
            self.router.start()

    def stop(self) -> None:
        """Stop the reader thread and close the port (blocking up to ~1 s). Idempotent."""
        self._stop.set()
        if self.router is not None:
            self.router.stop()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        conn, self._conn = self._conn, None
        if conn is not None:
            with contextlib.suppress(Exception):
                conn.close()

    # ------------------------------------------------------------------ state

    @property
    def target_system(self) -> int:
        return self.vehicle.system if self.vehicle else (self._wanted_system or 1)

    @property
    def target_component(self) -> int:
        return self.vehicle.component if self.vehicle else 1

    def heartbeat_age(self) -> float:
        if self.last_heartbeat_monotonic == 0.0:
            return math.inf
        return time.monotonic() - self.last_heartbeat_monotonic

    def link_ok(self) -> bool:
        return self.heartbeat_age() <= self.heartbeat_timeout_s

    def ensure_link(self, what: str) -> None:
        if self._conn is None:
            raise LinkLost(f"{what}: link is closed")
        if not self.link_ok():
            age = self.heartbeat_age()
            since = "ever" if math.isinf(age) else f"{age:.1f} s"
            raise LinkLost(f"{what}: no heartbeat from the vehicle for {since}")

    def status_texts(self) -> list[StatusText]:
        return list(self._texts)

    def time_boot_ms(self) -> int:
        return int((time.monotonic() - self._t0) * 1000) & 0xFFFFFFFF

    # ------------------------------------------------------------------ sending

    def send(self, msg: Any) -> None:
        conn = self._conn
        if conn is None:
            raise LinkLost("link is closed")
        with self._send_lock:
            conn.mav.send(msg)
            if conn.logfile is not None:
                conn.logfile.write(struct.pack(">Q", int(time.time() * 1e6) & ~3) + msg.get_msgbuf())

    def send_raw(self, frame: bytes) -> None:
        """Write a whole MAVLink frame from another ground station (the router), unchanged."""
        conn = self._conn
        if conn is None:
            raise LinkLost("link is closed")
        with self._send_lock:
            conn.write(frame)

    def own_ids(self) -> tuple[int, int]:
        """The (system, component) the agent sends as."""
        conn = self._conn
        system = conn.mav.srcSystem if conn is not None else (self._source_system or 0)
        return system, self.source_component

    def send_command_long(self, command: int, params: Iterable[float], confirmation: int = 0) -> None:
        p = [float(x) for x in params]
        p += [0.0] * (7 - len(p))
        self.send(
            mavlink.MAVLink_command_long_message(
                self.target_system, self.target_component, command, confirmation, *p
            )
        )

    def _send_heartbeat(self) -> None:
        self.send(
            mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                mavlink.MAV_AUTOPILOT_INVALID,
                0,
                0,
                mavlink.MAV_STATE_ACTIVE,
                3,
            )
        )

    # ------------------------------------------------------------------ subscriptions

    def subscribe(self, types: Iterable[str], predicate: Callable[[Any], bool] | None = None) -> Subscription:
        """Start copying matching messages from the vehicle's system into a queue (call on the loop)."""
        sub = Subscription(asyncio.get_running_loop(), frozenset(types), predicate)
        with self._subs_lock:
            self._subs.append(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        with self._subs_lock, contextlib.suppress(ValueError):
            self._subs.remove(sub)

    # ------------------------------------------------------------------ reader thread

    def _run(self) -> None:
        next_heartbeat = 0.0
        next_tick = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_heartbeat:
                next_heartbeat = now + 1.0
                with contextlib.suppress(Exception):
                    self._send_heartbeat()
            if now >= next_tick:
                next_tick = now + 0.5
                try:
                    self._on_tick()
                except Exception:
                    log.exception("mavlink periodic task failed")
            conn = self._conn
            if conn is None:
                break
            try:
                msg = conn.recv_match(blocking=True, timeout=0.1)
            except Exception as exc:  # port vanished, TCP reset while reconnecting, ...
                if self._stop.is_set():
                    break
                log.debug("mavlink read error on %s: %s", self.connection, exc)
                self._stop.wait(0.2)
                continue
            if msg is None:
                continue
            try:
                self._dispatch(msg)
            except Exception:
                log.exception("mavlink message handling failed for %s", msg.get_type())

    def _dispatch(self, msg: Any) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            return
        if self.router is not None:
            self.router.from_autopilot(msg)
        if mtype == "HEARTBEAT":
            self._on_heartbeat(msg)
        vehicle = self.vehicle
        if vehicle is None or msg.get_srcSystem() != vehicle.system:
            return
        now = time.monotonic()
        from_autopilot = msg.get_srcComponent() == vehicle.component
        if mtype == "STATUSTEXT":
            self._on_statustext(msg, now)
        if from_autopilot:
            self.last_seen[mtype] = now
            if mtype == "PARAM_VALUE":
                self._param_types[msg.param_id] = msg.param_type
            self._on_message(msg)
        with self._subs_lock:
            subs = [s for s in self._subs if mtype in s.types]
        for sub in subs:
            if sub.predicate is not None and not sub.predicate(msg):
                continue
            with contextlib.suppress(RuntimeError):  # loop already closed
                sub.loop.call_soon_threadsafe(sub.queue.put_nowait, msg)

    def _is_vehicle_heartbeat(self, msg: Any) -> bool:
        if msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID or msg.type in _NOT_VEHICLE_TYPES:
            return False
        return self._wanted_system is None or msg.get_srcSystem() == self._wanted_system

    def _on_heartbeat(self, msg: Any) -> None:
        if not self._is_vehicle_heartbeat(msg):
            return
        src, comp = msg.get_srcSystem(), msg.get_srcComponent()
        if self.vehicle is None:
            self.vehicle = VehicleIdentity(src, comp, msg.autopilot, msg.type)
            if self._source_system is None and self._conn is not None:
                # Companion-computer identity: the vehicle's own system id, component 191.
                self._conn.mav.srcSystem = src
            log.info("vehicle sysid %d compid %d autopilot %d type %d", src, comp, msg.autopilot, msg.type)
        elif (src, comp) != (self.vehicle.system, self.vehicle.component):
            return
        now = time.monotonic()
        restored = self.last_heartbeat_monotonic != 0.0 and (
            now - self.last_heartbeat_monotonic > self.heartbeat_timeout_s
        )
        self.vehicle.autopilot, self.vehicle.mav_type = msg.autopilot, msg.type
        self.last_heartbeat = msg
        self.last_heartbeat_monotonic = now
        self.vehicle_found.set()
        if restored:
            log.warning("vehicle heartbeat back after a gap on %s", self.connection)
            try:
                self._on_link_restored()
            except Exception:
                log.exception("link-restored handler failed")

    def _on_statustext(self, msg: Any, now: float) -> None:
        text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("utf-8", "replace")
        text = text.rstrip("\x00")
        chunk_id = getattr(msg, "id", 0) or 0
        if chunk_id:
            parts = self._text_chunks.setdefault(chunk_id, [])
            parts.append(text)
            if len(text) >= 50 and len(parts) < 8:
                return  # more chunks follow
            text = "".join(self._text_chunks.pop(chunk_id))
            if len(self._text_chunks) > 16:
                self._text_chunks.clear()
        self._texts.append(StatusText(now, msg.severity, text))

    # ------------------------------------------------------------------ commands

    def refusal_text(self, since: float) -> str | None:
        """The most relevant STATUSTEXT received after ``since``: warnings and worse first."""
        recent = [t for t in self._texts if t.monotonic >= since]
        serious = [t for t in recent if t.severity <= mavlink.MAV_SEVERITY_WARNING]
        pick = serious or recent
        return pick[-1].text if pick else None

    async def refusal_reason(self, result_name: str, since: float) -> str:
        text = self.refusal_text(since)
        if text is None:  # the STATUSTEXT may trail the COMMAND_ACK by a few milliseconds
            await asyncio.sleep(0.25)
            text = self.refusal_text(since)
        return f"{text} [{result_name}]" if text else result_name

    async def command(
        self,
        name: str,
        command: int,
        params: Iterable[float] = (),
        *,
        int_frame: int | None = None,
        timeout_s: float | None = None,
        retries: int | None = None,
        already: Callable[[], bool] | None = None,
    ) -> None:
        """Send COMMAND_LONG (or COMMAND_INT when ``int_frame`` is given) and wait for its ACK.

        For COMMAND_INT, params 5 and 6 are lat/lon in degrees (sent x1e7; NaN as INT32_MAX, "no
        position") and 7 is the altitude.
        Returns on MAV_RESULT_ACCEPTED; IN_PROGRESS keeps waiting. Each re-send of a COMMAND_LONG
        counts up its ``confirmation`` field (0 first), as the MAVLink command protocol asks.

        ``already``: for a command the vehicle refuses to carry out twice (ArduCopter answers a
        second NAV_TAKEOFF while climbing with FAILED). On a lossy link the first send may have
        been carried out and its ACK lost; a refusal of a *re-send* is then taken as success when
        ``already()`` says the vehicle is doing what was asked.
        """
        timeout = self.command_timeout_s if timeout_s is None else timeout_s
        attempts = self.command_retries if retries is None else max(1, retries)
        p = [float(x) for x in params]
        p += [0.0] * (7 - len(p))
        lock = self._command_locks.setdefault(command, asyncio.Lock())
        async with lock:
            self.ensure_link(name)
            our_sys = self._conn.mav.srcSystem if self._conn is not None else 0
            sub = self.subscribe(
                ["COMMAND_ACK"],
                lambda m: (
                    m.command == command
                    and m.get_srcComponent() == self.target_component
                    and (getattr(m, "target_system", 0) or our_sys) == our_sys
                    and (getattr(m, "target_component", 0) or self.source_component) == self.source_component
                ),
            )
            try:
                first_sent = time.monotonic()
                for attempt in range(attempts):
                    sent_at = time.monotonic()
                    if int_frame is None:
                        self.send_command_long(command, p, confirmation=min(attempt, 255))
                    else:
                        self.send(
                            mavlink.MAVLink_command_int_message(
                                self.target_system,
                                self.target_component,
                                int_frame,
                                command,
                                0,
                                0,
                                p[0],
                                p[1],
                                p[2],
                                p[3],
                                _int_degrees(p[4]),
                                _int_degrees(p[5]),
                                p[6],
                            )
                        )
                    deadline = sent_at + timeout
                    while (remaining := deadline - time.monotonic()) > 0:
                        ack = await sub.get(min(remaining, WAIT_SLICE_S))
                        if ack is None:
                            self.ensure_link(name)
                            continue
                        if ack.result == mavlink.MAV_RESULT_ACCEPTED:
                            return
                        if ack.result == mavlink.MAV_RESULT_IN_PROGRESS:
                            deadline = time.monotonic() + max(timeout, 5.0)
                            continue
                        if attempt > 0 and already is not None and already():
                            log.info("%s: re-send refused, the first send was carried out (ACK lost)", name)
                            return
                        reason = await self.refusal_reason(mav_result_name(ack.result), first_sent - 0.5)
                        raise CommandRefused(name, reason)
                    log.debug("%s: no COMMAND_ACK (attempt %d/%d)", name, attempt + 1, attempts)
                raise CommandTimeout(name, timeout * attempts)
            finally:
                self.unsubscribe(sub)

    # ------------------------------------------------------------------ parameters

    async def get_param(
        self, name: str, *, timeout_s: float | None = None, retries: int | None = None
    ) -> float:
        """Read a parameter (PARAM_REQUEST_READ → PARAM_VALUE)."""
        return await self._param_exchange(name, None, timeout_s, retries)

    async def set_param(
        self, name: str, value: float, *, timeout_s: float | None = None, retries: int | None = None
    ) -> float:
        """Write a parameter (PARAM_SET → PARAM_VALUE echo); returns the value the vehicle reports.

        Raises :class:`CommandRefused` when the echoed value differs from the one asked for (the
        autopilot kept its old value) and :class:`CommandTimeout` when there is no echo at all
        (typically: no such parameter).
        """
        got = await self._param_exchange(name, float(value), timeout_s, retries)
        if not math.isclose(got, float(value), rel_tol=1e-5, abs_tol=1e-5):
            raise CommandRefused(f"set {name}", f"vehicle kept {name}={got:g} (asked for {value:g})")
        return got

    async def _param_exchange(
        self, name: str, value: float | None, timeout_s: float | None, retries: int | None
    ) -> float:
        what = f"param {name}"
        timeout = self.command_timeout_s if timeout_s is None else timeout_s
        attempts = self.command_retries if retries is None else max(1, retries)
        self.ensure_link(what)
        codec = self.param_codec
        if (
            value is not None
            and codec is not None
            and codec.params_bytewise
            and name not in self._param_types
        ):
            # The bytes of an integer value depend on the parameter's type: read it first.
            await self._param_exchange(name, None, timeout_s, retries)
        sub = self.subscribe(["PARAM_VALUE"], lambda m: m.param_id == name)
        seen: float | None = None  # the last echo that differed from the value asked for
        try:
            for _ in range(attempts):
                if value is None:
                    msg: Any = mavlink.MAVLink_param_request_read_message(
                        self.target_system, self.target_component, name.encode(), -1
                    )
                else:
                    ptype = self._param_types.get(name, mavlink.MAV_PARAM_TYPE_REAL32)
                    wire = value if codec is None else codec.encode_param(value, ptype)
                    msg = mavlink.MAVLink_param_set_message(
                        self.target_system, self.target_component, name.encode(), wire, ptype
                    )
                self.send(msg)
                deadline = time.monotonic() + timeout
                while (remaining := deadline - time.monotonic()) > 0:
                    reply = await sub.get(min(remaining, WAIT_SLICE_S))
                    if reply is None:
                        self.ensure_link(what)
                        continue
                    got = float(reply.param_value)
                    if codec is not None:
                        got = codec.decode_param(got, reply.param_type)
                    if value is None or math.isclose(got, value, rel_tol=1e-5, abs_tol=1e-5):
                        return got
                    # Another link's read (a GCS, a test) is answered to every link: an echo of
                    # the old value may precede ours. Wait for ours; only the end decides "refused".
                    seen = got
            if seen is not None:
                return seen
            raise CommandTimeout(what, timeout * attempts)
        finally:
            self.unsubscribe(sub)
