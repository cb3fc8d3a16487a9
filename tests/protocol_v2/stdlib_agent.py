"""A third-party agent written from docs/protocol.md alone: standard library only, no fleetgcs imports.

It "flies" by jumping to each target (no autopilot), which is enough to show that the spec is
complete: handshake (v2 with ``versions``, or the v1 shapes), status reports, actions, sync
barriers. ``version=1`` checks every body with the strict version-1 decoder
(tests/support/v1_schema.py, also stdlib only), so a v2 daemon that leaked a v2 field to a v1
peer fails the test. tests/support/v1_agent.py is the stricter v1 agent that flies plausibly.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import secrets
import socket
import struct
import time
import zlib

from tests.support.v1_schema import check_v1_body

HEADER = struct.Struct(">2sBBIII")


class StdlibAgent:
    def __init__(
        self, port: int, identity: str, key_hex: str, version: int = 2, release_beacon: bool = False
    ) -> None:
        self.identity, self.key, self.version = identity, bytes.fromhex(key_hex), version
        self.release_beacon = release_beacon  # v2: offer to listen for release beacons
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.seq = 0
        self.buffer = b""
        self.lat, self.lon, self.alt = 47.397742, 8.545594 + 0.0001 * int(identity[-1]), 0.0
        self.armed, self.landed = False, True
        self.mission: str | None = None
        self.queue: list[dict] = []
        self.completed, self.waiting = -1, None
        self.released: set[int] = set()
        self.accepted: dict = {}

    def send(self, ptype: int, body: dict) -> None:
        payload = json.dumps(body).encode()
        self.seq += 1
        self.sock.sendall(HEADER.pack(b"FG", 1, ptype, self.seq, len(payload), zlib.crc32(payload)) + payload)

    def receive(self) -> tuple[int, dict]:
        while True:
            if len(self.buffer) >= 16:
                magic, _, ptype, _, length, crc = HEADER.unpack_from(self.buffer)
                assert magic == b"FG"
                if len(self.buffer) >= 16 + length:
                    payload = self.buffer[16 : 16 + length]
                    self.buffer = self.buffer[16 + length :]
                    assert zlib.crc32(payload) == crc
                    if self.version == 1:
                        return ptype, check_v1_body(ptype, payload)
                    return ptype, json.loads(payload)
            data = self.sock.recv(65536)
            if not data:
                raise ConnectionError("closed")
            self.buffer += data

    def mac(self, label: str, a: str, b: str) -> str:
        return hmac.new(self.key, f"{label}|{self.identity}|{a}|{b}".encode(), hashlib.sha256).hexdigest()

    def handshake(self) -> dict:
        nonce = secrets.token_hex(16)
        hello = {"identity": self.identity, "protocol_version": self.version, "client_nonce": nonce}
        if self.version >= 2:
            hello["versions"] = [1, 2]
        self.send(0, hello)
        _, challenge = self.receive()
        assert challenge["outcome"] == "challenge", challenge
        server_nonce = challenge["server_nonce"]
        proof = {**hello, "proof": self.mac("fleetgcs-agent-v1", server_nonce, nonce)}
        if self.release_beacon and self.version >= 2:
            proof["release_beacon"] = True
        self.send(0, proof)
        _, accepted = self.receive()
        assert accepted["outcome"] == "accepted", accepted
        assert accepted["server_proof"] == self.mac("fleetgcs-daemon-v1", nonce, server_nonce)
        self.accepted = accepted
        self.sock.settimeout(0.05)
        return accepted

    def status(self) -> None:
        self.send(
            2,
            {
                "time": time.time(),
                "position": {
                    "lat": self.lat,
                    "lon": self.lon,
                    "alt_rel": self.alt,
                    "alt_amsl": 488 + self.alt,
                },
                "mode": "GUIDED",
                "armed": self.armed,
                "landed": self.landed,
                "gps": {"fix": 3, "satellites": 10},
                "mission_id": self.mission,
                "step": self.queue[0]["step"] if self.queue else -1,
                "completed_step": self.completed,
                "queue_depth": len(self.queue),
                "waiting_sync": self.waiting,
            },
        )

    def fly(self, seconds: float) -> None:
        """Serve the link for ``seconds``: one status per period, one action per status."""
        period = self.accepted.get("parameters", {}).get("status_period_s", 0.5)
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.step()
            self.status()
            end = time.monotonic() + period
            while time.monotonic() < end:
                try:
                    ptype, body = self.receive()
                except TimeoutError:
                    continue
                if ptype == 4 and body.get("mode", "append") in ("append", "replace"):
                    if body.get("mode") == "replace" or body["mission_id"] != self.mission:
                        self.queue = []
                    self.mission = body["mission_id"]
                    self.queue += body.get("actions", [])
                elif ptype == 5 and body["kind"] == "release":
                    self.released.add(body["step"])
                elif ptype == 6:
                    raise ConnectionError(f"closed: {body}")

    def step(self) -> None:
        if self.waiting is not None:
            if self.waiting not in self.released:
                return
            self.waiting = None
        if not self.queue:
            return
        action = self.queue.pop(0)
        kind = action["kind"]
        if kind == "takeoff":
            self.armed, self.landed, self.alt = True, False, action["alt"]
        elif kind == "goto":
            self.lat, self.lon, self.alt = action["lat"], action["lon"], action["alt"]
        elif kind in ("land", "rtl"):
            self.armed, self.landed, self.alt = False, True, 0.0
        self.completed = action["step"]
        if action.get("sync"):
            self.waiting = action["step"]
            self.send(5, {"mission_id": self.mission, "step": action["step"], "kind": "finished"})

    def close(self) -> None:
        self.sock.close()
