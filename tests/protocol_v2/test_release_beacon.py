"""Release beacons from a real daemon to agents written from docs/protocol.md alone.

The agents are the stdlib agent (tests/protocol_v2/stdlib_agent.py); the beacon is read by a
plain UDP socket bound to the loopback broadcast address and checked with the chain rule as the
spec states it (SHA-256 with the domain tag, cut to 16 bytes), not with protocol/beacon.py: if
the daemon and the spec disagree, this test fails.
"""

from __future__ import annotations

import asyncio
import hashlib
import socket
import sqlite3
import struct
from pathlib import Path

import pytest

from gcs.core.config import DaemonConfig
from gcs.link.beacon import LOOPBACK_BROADCAST, free_udp_port
from gcs.observe.metrics import DaemonMetrics
from tests.backbone.helpers import new_key, running_daemon, survey_mission
from tests.protocol_v2.stdlib_agent import StdlibAgent
from tests.support.polling import wait_for

pytestmark = pytest.mark.timeout(90)

BROADCAST = LOOPBACK_BROADCAST


def _listener(port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind((BROADCAST, port))
    sock.settimeout(0.1)
    return sock


def _spec_hash(value: bytes) -> bytes:
    return hashlib.sha256(b"fleetgcs-release-beacon-v1|" + value).digest()[:16]


def _parse(datagram: bytes) -> tuple[str, int, bytes]:
    assert datagram[:4] == b"FGRB" and datagram[4] == 1, datagram
    size = datagram[5]
    assert len(datagram) == 6 + size + 4 + 16
    (step,) = struct.unpack_from("<I", datagram, 6 + size)
    return datagram[6 : 6 + size].decode(), step, datagram[10 + size :]


def _plan_of(agent: StdlibAgent, mission_id: str) -> dict:
    """The agent's type-4 batch of ``mission_id`` (read within 10 s)."""
    for _ in range(400):
        try:
            ptype, body = agent.receive()
        except TimeoutError:
            continue
        if ptype == 4 and body.get("mission_id") == mission_id and body.get("actions"):
            return body
    raise AssertionError(f"{agent.identity} got no plan")


def _release_of(agent: StdlibAgent, mission_id: str, step: int) -> None:
    for _ in range(400):
        try:
            ptype, body = agent.receive()
        except TimeoutError:
            continue
        if ptype == 5 and body == {"mission_id": mission_id, "step": step, "kind": "release"}:
            return
    raise AssertionError(f"{agent.identity} got no TCP release of step {step}")


def _released_in_db(db_path: str, mission_id: str, step: int) -> bool:
    db = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True, timeout=10)
    try:
        query = "SELECT 1 FROM releases WHERE mission_id=? AND step=?"
        return db.execute(query, (mission_id, step)).fetchone() is not None
    finally:
        db.close()


def _receive_beacon(sock: socket.socket, seconds: float) -> bytes | None:
    for _ in range(int(seconds / 0.1)):
        try:
            return sock.recv(256)
        except TimeoutError:
            continue
    return None


async def _joined(daemon: object, agents: list[StdlibAgent]) -> None:
    for agent in agents:
        await asyncio.to_thread(agent.handshake)
        agent.status()
    sessions = daemon.agents  # type: ignore[attr-defined]
    await wait_for(lambda: all((s := sessions.session(a.identity)) and s.status for a in agents), 10, "fix")


async def test_a_release_is_announced_by_one_stored_verifiable_beacon_then_sent_over_tcp(
    tmp_path: Path,
) -> None:
    key, port = new_key(), free_udp_port()
    listener = _listener(port)
    async with running_daemon(tmp_path, key, release_beacon=f"{BROADCAST}:{port}") as daemon:
        listening = [
            StdlibAgent(daemon.listen_port, f"beacon-{i}", key, release_beacon=True) for i in range(3)
        ]
        deaf = StdlibAgent(daemon.listen_port, "beacon-9", key)  # v2, no offer
        old = StdlibAgent(daemon.listen_port, "beacon-8", key, version=1, release_beacon=True)  # v1: never
        agents = [*listening, deaf, old]
        try:
            await _joined(daemon, agents)
            mission_id = await daemon.missions.submit(
                survey_mission([a.identity for a in agents], sync_legs=2)
            )
            plans = {a.identity: await asyncio.to_thread(_plan_of, a, mission_id) for a in agents}
            anchors = {plans[a.identity].get("release_anchor") for a in listening}
            assert len(anchors) == 1 and None not in anchors, plans  # one chain per mission
            anchor = bytes.fromhex(anchors.pop())  # type: ignore[arg-type]
            assert "release_anchor" not in plans[deaf.identity]
            assert "release_anchor" not in plans[old.identity]  # (the v1 agent asserts no v2 field)

            known_step, known_value = -1, anchor
            for step in (0, 1):
                for agent in agents:
                    agent.send(5, {"mission_id": mission_id, "step": step, "kind": "finished"})
                datagram = await asyncio.to_thread(_receive_beacon, listener, 10.0)
                assert datagram is not None, f"no beacon for step {step}"
                assert _released_in_db(str(daemon.store.path), mission_id, step), "beacon before storing"
                named, beacon_step, value = _parse(datagram)
                assert (named, beacon_step) == (mission_id, step)
                link = value
                for _ in range(step - known_step):
                    link = _spec_hash(link)
                assert link == known_value, "the beacon does not hash back to the anchor"
                known_step, known_value = step, value
                for agent in agents:  # the TCP release follows, for everyone
                    await asyncio.to_thread(_release_of, agent, mission_id, step)
            assert daemon.missions.beacon is not None and daemon.missions.beacon.sent == 2
            scrape = DaemonMetrics(daemon).render().decode()
            assert 'fleetgcs_release_beacons_total{outcome="sent"} 2.0' in scrape
            # A repeated 'finished' at a released step is answered over TCP, with no second beacon.
            listening[0].send(5, {"mission_id": mission_id, "step": 1, "kind": "finished"})
            await asyncio.to_thread(_release_of, listening[0], mission_id, 1)
            assert await asyncio.to_thread(_receive_beacon, listener, 0.5) is None
        finally:
            listener.close()
            for agent in agents:
                agent.close()
            await asyncio.sleep(0.2)


async def test_no_beacon_when_no_member_listens(tmp_path: Path) -> None:
    key, port = new_key(), free_udp_port()
    listener = _listener(port)
    async with running_daemon(tmp_path, key, release_beacon=f"{BROADCAST}:{port}") as daemon:
        agents = [StdlibAgent(daemon.listen_port, f"deaf-{i}", key) for i in range(2)]
        try:
            await _joined(daemon, agents)
            mission_id = await daemon.missions.submit(
                survey_mission([a.identity for a in agents], sync_legs=1)
            )
            for agent in agents:
                assert "release_anchor" not in await asyncio.to_thread(_plan_of, agent, mission_id)
                agent.send(5, {"mission_id": mission_id, "step": 0, "kind": "finished"})
            for agent in agents:
                await asyncio.to_thread(_release_of, agent, mission_id, 0)
            assert await asyncio.to_thread(_receive_beacon, listener, 0.5) is None
            assert daemon.missions.active[mission_id].chain is None
        finally:
            listener.close()
            for agent in agents:
                agent.close()
            await asyncio.sleep(0.2)


def test_a_beacon_target_must_be_ipv4_and_port(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="not an IPv4 address"):
        DaemonConfig(data_dir=tmp_path, release_beacon="broadcast.local:14650")
    with pytest.raises(ValueError, match="expected IPv4:PORT"):
        DaemonConfig(data_dir=tmp_path, release_beacon="127.255.255.255")
