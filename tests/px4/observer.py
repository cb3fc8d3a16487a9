"""An independent observer of one PX4 instance on its GCS link (UDP 18570+i), as a ground station would be.

The agent under test talks to PX4's API link; the observer checks what PX4 really does, in PX4's own
clock (``time_boot_ms``, which runs ``PX4_SIM_SPEED_FACTOR`` times faster than the wall), and reads
parameters decoded the PX4 way (integers arrive byte-wise in PARAM_VALUE's float). Its reader thread
is bounded by :meth:`Observer.close`.
"""

from __future__ import annotations

import math
import os
import struct
import threading
import time
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

    def __init__(self, instance: int) -> None:
        self.sysid = instance + 1
        self.conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{GCS_PORT_BASE + instance}",
            source_system=OBSERVER_SYSID,
            source_component=mavutil.mavlink.MAV_COMP_ID_MISSIONPLANNER,
            dialect="common",
        )
        self.fixes: list[Fix] = []
        self.params: dict[str, tuple[float, float]] = {}  # name -> (value, wall time)
        self.custom_mode = 0
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
                elif kind == "PARAM_VALUE":
                    value = msg.param_value
                    if msg.param_type in INT_TYPES:
                        value = float(struct.unpack("<i", struct.pack("<f", value))[0])
                    self.params[msg.param_id] = (value, time.monotonic())

    def latest(self) -> Fix | None:
        with self._lock:
            return self.fixes[-1] if self.fixes else None

    def since(self, t: float) -> list[Fix]:
        """Fixes at or after vehicle time ``t``."""
        with self._lock:
            return [f for f in self.fixes if f.t >= t]

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

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.conn.close()
