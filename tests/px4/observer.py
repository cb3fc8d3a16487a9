"""An independent observer of one PX4 instance on its GCS link (UDP 18570+i), as a ground station would be.

The agent under test talks to PX4's API link; the observer checks what PX4 really does, in PX4's own
clock (``time_boot_ms``, which runs ``PX4_SIM_SPEED_FACTOR`` times faster than the wall), and reads
parameters decoded the PX4 way (integers arrive byte-wise in PARAM_VALUE's float). It keeps every mode
change and status text with PX4's time, and can act as a second ground station on that link (a
pilot's QGroundControl: :meth:`Observer.set_mode`, :meth:`Observer.set_param`). Its reader thread is
bounded by :meth:`Observer.close`.
"""

from __future__ import annotations

import bisect
import math
import os
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil

GCS_PORT_BASE = 18570
OBSERVER_SYSID = 245
INT_TYPES = {1, 2, 3, 4, 5, 6}  # MAV_PARAM_TYPE_UINT8 .. INT32: PX4 sends the bytes, not a cast


@dataclass(frozen=True)
class Fix:
    """One GLOBAL_POSITION_INT: vehicle time (s), position, relative altitude, ground speed."""

    t: float
    lat: float
    lon: float
    alt: float
    speed: float


class Observer:
    """Watches instance ``instance`` (system id ``instance + 1``)."""

    def __init__(self, instance: int, on_text: Callable[[float, str], None] | None = None) -> None:
        self.sysid = instance + 1
        self.on_text = on_text  # called (vehicle time, text) for every STATUSTEXT, on the reader thread
        self.conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{GCS_PORT_BASE + instance}",
            source_system=OBSERVER_SYSID,
            source_component=mavutil.mavlink.MAV_COMP_ID_MISSIONPLANNER,
            dialect="common",
        )
        self.fixes: list[Fix] = []
        self.walls: list[float] = []  # when each fix arrived (monotonic): PX4's clock against ours
        self.params: dict[str, tuple[float, float]] = {}  # name -> (value, wall time)
        self.custom_mode = 0
        self.modes: list[tuple[float, int, bool]] = []  # (vehicle time, custom_mode, armed) at each change
        self.texts: list[tuple[float, str]] = []  # (vehicle time, STATUSTEXT)
        self.acks: list[tuple[int, int, float]] = []  # (command, result, wall time)
        self.gps: tuple[float, float, int] | None = None  # the newest GPS_RAW_INT: lat, lon, fix type
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"px4-observer-{instance}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        last_hb = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now - last_hb > 0.5:  # PX4 answers the address it hears from
                self.conn.mav.heartbeat_send(6, 8, 0, 0, 4)  # GCS, INVALID autopilot, ACTIVE
                last_hb = now
            msg = self.conn.recv_match(blocking=True, timeout=0.2)
            if msg is None or msg.get_srcSystem() != self.sysid:
                continue
            kind = msg.get_type()
            with self._lock:
                if kind == "GLOBAL_POSITION_INT":
                    self.walls.append(time.monotonic())
                    self.fixes.append(
                        Fix(
                            msg.time_boot_ms / 1000.0,
                            msg.lat / 1e7,
                            msg.lon / 1e7,
                            msg.relative_alt / 1000.0,
                            math.hypot(msg.vx, msg.vy) / 100.0,
                        )
                    )
                elif kind == "HEARTBEAT" and msg.get_srcComponent() == 1:
                    self.custom_mode = msg.custom_mode
                    armed = bool(msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                    if not self.modes or self.modes[-1][1:] != (msg.custom_mode, armed):
                        self.modes.append((self._now(), msg.custom_mode, armed))
                elif kind == "STATUSTEXT":
                    self.texts.append((self._now(), msg.text))
                    if self.on_text is not None:
                        self.on_text(self._now(), msg.text)
                elif kind == "GPS_RAW_INT":
                    self.gps = (msg.lat / 1e7, msg.lon / 1e7, msg.fix_type)
                elif kind == "COMMAND_ACK" and getattr(msg, "target_system", 0) in (0, OBSERVER_SYSID):
                    # PX4 sends the ACKs of every link's commands on every link: only ours (or untargeted)
                    self.acks.append((msg.command, msg.result, time.monotonic()))
                elif kind == "PARAM_VALUE":
                    value = msg.param_value
                    if msg.param_type in INT_TYPES:
                        value = float(struct.unpack("<i", struct.pack("<f", value))[0])
                    self.params[msg.param_id] = (value, time.monotonic())

    def _now(self) -> float:
        """PX4's clock (s) at the newest fix; the caller holds the lock."""
        return self.fixes[-1].t if self.fixes else 0.0

    def latest(self) -> Fix | None:
        with self._lock:
            return self.fixes[-1] if self.fixes else None

    def since(self, t: float) -> list[Fix]:
        """Fixes at or after vehicle time ``t``."""
        with self._lock:
            i = bisect.bisect_left(self.fixes, t, key=lambda f: f.t)
            return self.fixes[i:]

    def fixes_since_wall(self, wall: float) -> list[tuple[float, Fix]]:
        """(arrival wall time, fix) for the fixes that arrived at or after monotonic ``wall``."""
        with self._lock:
            i = bisect.bisect_left(self.walls, wall)
            return list(zip(self.walls[i:], self.fixes[i:], strict=True))

    def param(self, name: str, timeout: float = 5.0) -> float:
        """Read one parameter from PX4 now (bounded; retried every 0.5 s)."""
        asked = time.monotonic()
        deadline = asked + timeout
        while time.monotonic() < deadline:
            self.conn.mav.param_request_read_send(self.sysid, 1, name.encode(), -1)
            until = min(deadline, time.monotonic() + 0.5)
            while time.monotonic() < until:
                with self._lock:
                    got = self.params.get(name)
                if got is not None and got[1] >= asked:
                    return got[0]
                time.sleep(0.02)
        raise AssertionError(
            f"PX4 system {self.sysid} did not answer PARAM_REQUEST_READ {name} in {timeout:.0f} s"
        )

    def command(self, command: int, *params: float, timeout: float = 5.0) -> int:
        """COMMAND_LONG from this ground station; the first ACK's MAV_RESULT (PX4 may send a second,
        TEMPORARILY_REJECTED, for a mode it cannot enter: :meth:`set_mode` reads both)."""
        sent = time.monotonic()
        self.conn.mav.command_long_send(self.sysid, 1, command, 0, *params, *([0.0] * (7 - len(params))))
        deadline = sent + timeout
        while time.monotonic() < deadline:
            with self._lock:
                got = [r for c, r, t in self.acks if c == command and t >= sent]
            if got:
                return got[0]
            time.sleep(0.02)
        raise AssertionError(f"PX4 system {self.sysid}: no ACK for command {command} in {timeout:.0f} s")

    def set_mode(self, main: int, sub: int = 0, timeout: float = 5.0, tries: int = 1) -> int:
        """MAV_CMD_DO_SET_MODE with PX4's main/sub mode, as a pilot's ground station sends it; with
        ``tries`` > 1 pressed again (as a pilot would) until PX4's heartbeat shows the mode (bounded:
        ``timeout`` per try). The worst MAV_RESULT of the ACKs of the last try (PX4 ACKs ACCEPTED, then
        TEMPORARILY_REJECTED for a mode it cannot enter, e.g. Position without manual control input);
        an ACCEPTED mode the heartbeat never shows (something switched it back) fails."""
        wanted = (main << 16) | (sub << 24)
        result = -1
        for _ in range(tries):
            sent = time.monotonic()
            first = self.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, 1, main, sub, timeout=timeout)
            time.sleep(0.5)
            with self._lock:
                acks = [r for c, r, t in self.acks if c == mavutil.mavlink.MAV_CMD_DO_SET_MODE and t >= sent]
            result = max([first, *acks])
            if result != 0:
                return result
            until = sent + timeout
            while time.monotonic() < until:
                if self.custom_mode == wanted:
                    return result
                time.sleep(0.05)
        raise AssertionError(
            f"PX4 system {self.sysid} ACKed mode {main}.{sub} but its heartbeat never showed it within "
            f"{timeout:.0f} s: something switched it back (modes {self.modes[-3:]})"
        )

    def set_param(self, name: str, value: float, integer: bool = True) -> None:
        """PARAM_SET (integers byte-wise, as PX4 wants them) and wait until PX4 reports the value."""
        raw = struct.unpack("<f", struct.pack("<i", round(value)))[0] if integer else value
        kind = mavutil.mavlink.MAV_PARAM_TYPE_INT32 if integer else mavutil.mavlink.MAV_PARAM_TYPE_REAL32
        for _ in range(5):  # bounded: 5 tries of up to 2 s
            asked = time.monotonic()
            self.conn.mav.param_set_send(self.sysid, 1, name.encode(), raw, kind)
            until = asked + 2.0
            while time.monotonic() < until:
                with self._lock:
                    got = self.params.get(name)
                if got is not None and got[1] >= asked and got[0] == value:
                    return
                time.sleep(0.02)
        raise AssertionError(f"PX4 system {self.sysid} did not take {name} = {value}")

    def modes_since(self, t: float) -> list[tuple[float, int, bool]]:
        """Mode changes at or after vehicle time ``t``, with the mode in force at ``t`` first."""
        with self._lock:
            before = [m for m in self.modes if m[0] < t]
            return before[-1:] + [m for m in self.modes if m[0] >= t]

    def texts_since(self, t: float) -> list[tuple[float, str]]:
        with self._lock:
            return [x for x in self.texts if x[0] >= t]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.conn.close()
