"""A strict protocol-version-1 agent: standard library only, written from the v1 text of docs/protocol.md.

It speaks version 1 (a hello without ``versions``), checks every body it receives with the strict
version-1 decoder (:mod:`tests.support.v1_schema`: an unknown field anywhere is an error), and
"flies" a point-mass vehicle towards each target at a plausible speed, reporting its progress in
status reports (position, step, completed step, queue, sync wait) until each action is finished.
On a body it rejects it does what a version-1 agent does (type-6 ``protocol_error`` close, drop
the connection), records the violation and makes :meth:`StrictV1Agent.run` raise, so a daemon
that sends a version-1 agent anything outside version 1 fails the test.

Use it from a thread (``asyncio.to_thread(agent.run, seconds)``): it uses blocking sockets.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import json
import math
import secrets
import socket
import struct
import threading
import time
import zlib
from typing import Any

from tests.support.v1_schema import V1Violation, check_v1_body

HEADER = struct.Struct(">2sBBIII")
EARTH_M = 6_371_000.0
CLIMB_MPS, DESCENT_MPS = 3.0, 2.0


class StrictV1Agent:
    """One version-1 agent on its own socket; ``speedup`` scales simulated time (motion and holds)."""

    def __init__(
        self,
        port: int,
        identity: str,
        key_hex: str,
        home: tuple[float, float, float] = (47.397742, 8.545594, 488.0),
        speed_mps: float = 8.0,
        speedup: float = 4.0,
    ) -> None:
        self.port, self.identity, self.key = port, identity, bytes.fromhex(key_hex)
        self.home = home
        self.speed, self.cruise, self.speedup = speed_mps, speed_mps, speedup
        self.north = self.east = self.up = 0.0
        self.armed, self.landed = False, True
        self.violations: list[str] = []
        self.closes: list[dict[str, Any]] = []
        self.log: list[tuple[str, int]] = []  # ("start"|"done"|"finished"|"release"|"restart", step)
        self.gates: dict[int, threading.Event] = {}  # step -> event the action waits for (tests)
        self.stop = threading.Event()
        self.restart_wanted = threading.Event()
        self.reconnects = 0
        self.sock: socket.socket | None = None
        self._forget()

    # --- state the companion computer loses on a restart ------------------------------------------

    def _forget(self) -> None:
        self.mission: str | None = None
        self.queue: list[dict[str, Any]] = []
        self.current: dict[str, Any] | None = None
        self.target: tuple[float, float, float] | None = None
        self.hold_left = 0.0
        self.points: list[dict[str, Any]] = []
        self.completed, self.waiting = -1, None
        self.paused = False
        self.released: set[int] = set()
        self.period = 0.5
        self.seq = 0
        self.buffer = b""

    # --- link --------------------------------------------------------------------------------------

    def connect(self) -> dict[str, Any]:
        """Connect and run the version-1 handshake; the ``accepted`` body."""
        self.sock = socket.create_connection(("127.0.0.1", self.port), timeout=5)
        nonce = secrets.token_hex(16)
        hello: dict[str, Any] = {
            "identity": self.identity,
            "protocol_version": 1,
            "client_nonce": nonce,
            "capabilities": {"vehicle_kind": "multicopter", "max_speed_mps": self.speed},
            "home": {"lat": self.home[0], "lon": self.home[1], "alt_amsl": self.home[2]},
        }
        if self.mission is not None:  # what it still holds, so the daemon resumes it (v1 ``resume``)
            resume: dict[str, Any] = {
                "mission_id": self.mission,
                "completed_step": self.completed,
                "queue_depth": len(self.queue),
            }
            if self.waiting is not None:
                resume["waiting_step"] = self.waiting
            hello["resume"] = resume
        self._send(0, hello)
        challenge = self._receive(5.0)
        assert challenge is not None and challenge[1]["outcome"] == "challenge", challenge
        server_nonce = challenge[1]["server_nonce"]
        self._send(0, {**hello, "proof": self._mac("fleetgcs-agent-v1", server_nonce, nonce)})
        answer = self._receive(5.0)
        assert answer is not None and answer[1]["outcome"] == "accepted", answer
        accepted = answer[1]
        assert accepted["server_proof"] == self._mac("fleetgcs-daemon-v1", nonce, server_nonce)
        self.period = accepted.get("parameters", {}).get("status_period_s", 0.5)
        return accepted

    def restart(self) -> None:
        """Ask for a reboot of the companion computer, done by :meth:`run` between two reports:
        the connection drops without a close, the queue is lost, the vehicle keeps its state, and
        it joins again (no ``resume``: it holds nothing)."""
        self.restart_wanted.set()

    def _restart(self) -> None:
        self.restart_wanted.clear()
        if self.sock is not None:
            self.sock.close()
        self._forget()
        self.log.append(("restart", -1))
        self.connect()

    def close(self) -> None:
        self.stop.set()
        if self.sock is not None:
            self.sock.close()

    def _mac(self, label: str, a: str, b: str) -> str:
        return hmac.new(self.key, f"{label}|{self.identity}|{a}|{b}".encode(), hashlib.sha256).hexdigest()

    def _send(self, ptype: int, body: dict[str, Any]) -> None:
        assert self.sock is not None
        payload = json.dumps(body).encode()
        self.seq += 1
        header = HEADER.pack(b"FG", 1, ptype, self.seq, len(payload), zlib.crc32(payload))
        self.sock.sendall(header + payload)

    def _receive(self, timeout: float) -> tuple[int, dict[str, Any]] | None:
        """The next frame within ``timeout``, strictly checked as version 1; None on timeout."""
        assert self.sock is not None
        deadline = time.monotonic() + timeout
        while True:
            if len(self.buffer) >= 16:
                magic, version, ptype, _, length, crc = HEADER.unpack_from(self.buffer)
                if magic != b"FG" or version != 1:
                    raise V1Violation(f"bad frame header {self.buffer[:4]!r}")
                if len(self.buffer) >= 16 + length:
                    payload, self.buffer = self.buffer[16 : 16 + length], self.buffer[16 + length :]
                    if zlib.crc32(payload) != crc:
                        raise V1Violation(f"type {ptype}: CRC mismatch")
                    return ptype, check_v1_body(ptype, payload)
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self.sock.settimeout(left)
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                return None
            if not data:
                raise ConnectionError("the daemon closed the connection")
            self.buffer += data

    # --- the loop ----------------------------------------------------------------------------------

    def run(self, seconds: float) -> None:
        """Fly for at most ``seconds`` (or until :attr:`stop`): a status every period, packets between.

        Raises :class:`V1Violation` when the daemon sent something a version-1 agent rejects.
        """
        deadline = time.monotonic() + seconds
        last = time.monotonic()
        while time.monotonic() < deadline and not self.stop.is_set():
            if self.restart_wanted.is_set():
                self._restart()
            now = time.monotonic()
            self._advance((now - last) * self.speedup)
            last = now
            try:
                self._send(2, self._status())
                end = time.monotonic() + self.period
                while (left := end - time.monotonic()) > 0:
                    frame = self._receive(left)
                    if frame is not None:
                        self._handle(*frame)
            except V1Violation as exc:
                self.violations.append(str(exc))
                self._reject(str(exc))
                raise
            except OSError:  # the daemon dropped us (lost under load, restarted): reconnect
                if self.stop.is_set():
                    return
                self.reconnects += 1
                time.sleep(0.2)
                with contextlib.suppress(OSError, AssertionError):
                    if self.sock is not None:
                        self.sock.close()
                    self.seq, self.buffer = 0, b""
                    self.connect()

    def _reject(self, why: str) -> None:
        """What a version-1 agent does with a body it cannot parse: close with protocol_error."""
        with contextlib.suppress(OSError):
            self._send(6, {"reason": "protocol_error", "message": why[:512]})
        if self.sock is not None:
            self.sock.close()

    def _handle(self, ptype: int, body: dict[str, Any]) -> None:
        if ptype == 4:
            self._orders(body)
        elif ptype == 5 and body["kind"] == "release":
            self.log.append(("release", body["step"]))
            if body["mission_id"] == self.mission and self.waiting == body["step"]:
                self.released.add(body["step"])
        elif ptype == 3:
            self.period = body.get("parameters", {}).get("status_period_s", self.period)
        elif ptype == 6:
            self.closes.append(body)

    def _orders(self, body: dict[str, Any]) -> None:
        mode = body.get("mode", "append")
        if mode == "pause":
            self.paused = True
            return
        if mode == "resume":
            self.paused = False
            return
        if mode == "replace" or body["mission_id"] != self.mission:
            self.queue, self.current, self.waiting, self.paused = [], None, None, False
        self.mission = body["mission_id"]
        self.queue += body.get("actions", [])

    # --- the vehicle -------------------------------------------------------------------------------

    def _latlon(self) -> tuple[float, float]:
        lat = self.home[0] + math.degrees(self.north / EARTH_M)
        lon = self.home[1] + math.degrees(self.east / (EARTH_M * math.cos(math.radians(self.home[0]))))
        return lat, lon

    def _local(self, lat: float, lon: float) -> tuple[float, float]:
        north = math.radians(lat - self.home[0]) * EARTH_M
        east = math.radians(lon - self.home[1]) * EARTH_M * math.cos(math.radians(self.home[0]))
        return north, east

    def _status(self) -> dict[str, Any]:
        lat, lon = self._latlon()
        status: dict[str, Any] = {
            "time": time.time(),
            "position": {"lat": lat, "lon": lon, "alt_rel": self.up, "alt_amsl": self.home[2] + self.up},
            "velocity": {"vn": 0.0, "ve": 0.0, "vd": 0.0},
            "heading_deg": 0.0,
            "battery": {"pct": 90.0, "voltage_v": 16.0},
            "mode": "GUIDED" if self.armed else "LOITER",
            "armed": self.armed,
            "landed": self.landed,
            "gps": {"fix": 3, "satellites": 12},
            "step": self.current["step"] if self.current else -1,
            "completed_step": self.completed,
            "queue_depth": len(self.queue),
            "paused": self.paused,
            "exceptions": [],
            "autopilot_link": True,
            "buffered": False,
        }
        if self.mission is not None:
            status["mission_id"] = self.mission
        if self.waiting is not None:
            status["waiting_sync"] = self.waiting
        return status

    def _advance(self, dt: float) -> None:
        """Move the vehicle by ``dt`` simulated seconds; finish and start actions."""
        if self.paused:
            return
        if self.waiting is not None:
            if self.waiting not in self.released:
                return
            self.waiting = None
        if self.current is None:
            if not self.queue:
                return
            gate = self.gates.get(self.queue[0]["step"])
            if gate is not None and not gate.is_set():
                return
            self._start(self.queue.pop(0))
        if self.current is not None and self._fly(self.current, dt):
            done, self.current = self.current, None
            self.completed = done["step"]
            self.log.append(("done", done["step"]))
            if done.get("sync"):
                self.waiting = done["step"]
                self.log.append(("finished", done["step"]))
                self._send(5, {"mission_id": self.mission, "step": done["step"], "kind": "finished"})

    def _start(self, act: dict[str, Any]) -> None:
        self.current = act
        self.log.append(("start", act["step"]))
        kind = act["kind"]
        if kind == "go_by":
            self.target = (self.north + act["north"], self.east + act["east"], self.up + act["up"])
        elif kind == "goto":
            self.target = (*self._local(act["lat"], act["lon"]), act["alt"])
        elif kind == "hold":
            self.hold_left = act["seconds"]
        elif kind == "waypoints":
            self.points = list(act["points"])
        if "speed" in act:
            self.speed = act["speed"]

    def _fly(self, act: dict[str, Any], dt: float) -> bool:
        """One step of ``act``; True once it is complete."""
        kind = act["kind"]
        if kind == "takeoff":
            self.armed, self.landed = True, False
            self.up = min(act["alt"], self.up + CLIMB_MPS * dt)
            return self.up >= 0.95 * act["alt"]
        if kind in ("goto", "go_by"):
            assert self.target is not None
            return self._towards(self.target, dt)
        if kind == "waypoints":
            while self.points:
                point = self.points[0]
                if not self._towards((*self._local(point["lat"], point["lon"]), point["alt"]), dt):
                    return False
                self.points.pop(0)
            return True
        if kind == "hold":
            self.hold_left -= dt
            return self.hold_left <= 0
        if kind == "set_speed":
            self.cruise = self.speed = act["speed"]
            return True
        if kind in ("land", "rtl"):
            where = (0.0, 0.0) if kind == "rtl" else None
            if "lat" in act:
                where = self._local(act["lat"], act["lon"])
            if where is not None and not self._towards((*where, self.up), dt):
                return False
            self.up = max(0.0, self.up - DESCENT_MPS * dt)
            if self.up <= 0.0:
                self.armed, self.landed = False, True
            return self.landed
        raise V1Violation(f"unknown action kind {kind!r}")

    def _towards(self, target: tuple[float, float, float], dt: float) -> bool:
        dn, de, du = target[0] - self.north, target[1] - self.east, target[2] - self.up
        gap = math.sqrt(dn * dn + de * de + du * du)
        step = self.speed * dt
        if gap <= max(step, 0.5):
            self.north, self.east, self.up = target
            return True
        self.north += dn / gap * step
        self.east += de / gap * step
        self.up += du / gap * step
        return False


__all__ = ["StrictV1Agent", "V1Violation"]
