"""Handshake, refusal paths and malformed input over real TCP: the daemon keeps serving others."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import secrets
from pathlib import Path

import pytest

from agent.config import AgentConfig
from agent.link import DaemonLink
from protocol import auth
from protocol.packets import (
    PROTOCOL_VERSION,
    Close,
    CloseReason,
    FenceVertex,
    Geofence,
    PerformActions,
    RequestCid,
    ResponseCid,
    StatusReport,
)
from protocol.wire import FRAME_VERSION, HEADER, MAGIC, FrameDecoder, encode
from tests.backbone.helpers import new_key, running_daemon, start_agent, stop_agents, survey_mission
from tests.support.polling import wait_for
from tests.support.raw_client import RawClient, build_status_report


async def test_handshake_gives_stable_cid_and_server_proof(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        first = await RawClient.connect(daemon.listen_port)
        answer, server_nonce, client_nonce = await first.handshake("drone-7", key)
        assert isinstance(answer, ResponseCid) and answer.outcome == "accepted" and answer.cid == 1
        expected = auth.daemon_proof(bytes.fromhex(key), "drone-7", client_nonce, server_nonce)
        assert answer.server_proof == expected
        assert answer.parameters is not None and answer.parameters.status_period_s == pytest.approx(0.1)
        other = await RawClient.connect(daemon.listen_port)
        answer_other, _, _ = await other.handshake("drone-8", key)
        assert isinstance(answer_other, ResponseCid) and answer_other.cid == 2
        first.close()
        again = await RawClient.connect(daemon.listen_port)
        answer_again, _, _ = await again.handshake("drone-7", key)
        assert isinstance(answer_again, ResponseCid) and answer_again.cid == 1
        other.close()
        again.close()


async def test_wrong_key_is_refused_and_logged(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        client = await RawClient.connect(daemon.listen_port)
        answer, _, _ = await client.handshake("intruder", new_key())
        assert isinstance(answer, ResponseCid) and answer.outcome == "refused"
        assert "wrong key" in (answer.reason or "")
        rest = await client.receive_all_until_closed()
        assert rest == [Close(reason=CloseReason.REFUSED, message=answer.reason or "", code="wrong_key")]
        assert daemon.events.history(kind="agent_refused")
        assert daemon.agents.session("intruder") is None


async def test_recorded_handshake_cannot_be_replayed(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        honest = await RawClient.connect(daemon.listen_port)
        _, server_nonce, client_nonce = await honest.handshake("drone-1", key)
        recorded_proof = auth.agent_proof(bytes.fromhex(key), "drone-1", server_nonce, client_nonce)
        attacker = await RawClient.connect(daemon.listen_port)
        hello = RequestCid(identity="drone-1", protocol_version=PROTOCOL_VERSION, client_nonce=client_nonce)
        await attacker.send(hello)
        challenge = await attacker.receive()
        assert challenge is not None and isinstance(challenge.body, ResponseCid)
        assert challenge.body.server_nonce != server_nonce
        await attacker.send(hello.model_copy(update={"proof": recorded_proof}))
        answer = await attacker.receive()
        assert (
            answer is not None and isinstance(answer.body, ResponseCid) and answer.body.outcome == "refused"
        )
        honest.close()


async def test_per_agent_keys_refuse_unknown_identities(tmp_path: Path) -> None:
    fleet_key, own_key = new_key(), new_key()
    keys_file = tmp_path / "agent-keys.json"
    keys_file.write_text(json.dumps({"listed": own_key}))
    async with running_daemon(
        tmp_path, fleet_key, agent_keys_file=keys_file, allow_unlisted_agents=False
    ) as daemon:
        listed = await RawClient.connect(daemon.listen_port)
        answer, _, _ = await listed.handshake("listed", own_key)
        assert isinstance(answer, ResponseCid) and answer.outcome == "accepted"
        stranger = await RawClient.connect(daemon.listen_port)
        await stranger.send(
            RequestCid(identity="stranger", protocol_version=PROTOCOL_VERSION, client_nonce=auth.new_nonce())
        )
        refusal = await stranger.receive()
        assert refusal is not None and isinstance(refusal.body, ResponseCid)
        assert refusal.body.outcome == "refused" and "unknown agent 'stranger'" in (refusal.body.reason or "")
        wrong_key = await RawClient.connect(daemon.listen_port)
        answer, _, _ = await wrong_key.handshake("listed", fleet_key)  # the fleet key is not listed's key
        assert isinstance(answer, ResponseCid) and answer.outcome == "refused"
        listed.close()


async def test_wrong_protocol_version_is_refused(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        client = await RawClient.connect(daemon.listen_port)
        answer, _, _ = await client.handshake("future", key, version=9)
        assert isinstance(answer, ResponseCid) and answer.outcome == "refused"
        assert "protocol version(s) [9] not supported" in (answer.reason or "")
        assert answer.code == "version_unsupported"


async def test_silent_connection_is_cut_after_handshake_timeout(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key, handshake_timeout_s=0.5) as daemon:
        client = await RawClient.connect(daemon.listen_port)
        await client.send_raw(MAGIC)  # a slow-loris: two bytes, then nothing
        bodies = await client.receive_all_until_closed(timeout=3.0)
        assert bodies == [
            Close(reason=CloseReason.PROTOCOL_ERROR, message="handshake timeout", code="handshake_timeout")
        ]
        assert daemon.events.history(kind="handshake_timeout")


async def test_second_session_replaces_the_first(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        first = await RawClient.connect(daemon.listen_port)
        await first.handshake("twin", key)
        second = await RawClient.connect(daemon.listen_port)
        answer, _, _ = await second.handshake("twin", key)
        assert isinstance(answer, ResponseCid) and answer.outcome == "accepted" and answer.cid == 1
        bodies = await first.receive_all_until_closed()
        assert isinstance(bodies[-1], Close) and bodies[-1].reason == CloseReason.REPLACED
        assert daemon.agents.session("twin") is not None
        assert daemon.events.history(kind="agent_replaced")


async def test_agent_refuses_a_daemon_that_cannot_prove_the_key(tmp_path: Path) -> None:
    """Mutual authentication: an impostor daemon that accepts anyone is not trusted."""

    async def impostor(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        decoder = FrameDecoder()
        for seq, outcome in enumerate(("challenge", "accepted"), start=1):
            data = await reader.read(65_536)
            if not data:
                return
            list(decoder.feed(data))
            reply = ResponseCid(
                outcome=outcome,  # type: ignore[arg-type]
                server_nonce=auth.new_nonce(),
                cid=1,
                server_proof=secrets.token_hex(32),
            )
            writer.write(encode(reply, seq))
            await writer.drain()
        await asyncio.sleep(1)
        writer.close()

    server = await asyncio.start_server(impostor, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    config = AgentConfig(identity="careful", gcs_port=port, key_hex=new_key(), reconnect_min_s=0.05)

    async def noop(_: object) -> None:
        return None

    link = DaemonLink(config, bytes.fromhex(config.key_hex), noop, noop, noop, lambda: None, lambda: None)
    task = asyncio.create_task(link.run())
    try:
        await wait_for(lambda: link.last_error is not None, 5, "the agent to reject the impostor")
        assert "could not prove it holds our key" in (link.last_error or "")
        assert not link.connected
    finally:
        task.cancel()
        server.close()


async def test_malformed_input_never_disturbs_a_running_mission(tmp_path: Path) -> None:
    key = new_key()
    names = ["steady-1", "steady-2"]
    async with running_daemon(tmp_path, key) as daemon:
        agents = [start_agent(name, daemon.listen_port, key, i) for i, name in enumerate(names)]
        try:
            await wait_for(lambda: len(daemon.agents.connected()) == 2, 10, "two agents")
            mission_id = await daemon.missions.submit(survey_mission(names, sync_legs=3))

            abusers: list[tuple[str, bytes]] = [
                ("garbage", secrets.token_bytes(4096)),
                ("http", b"GET / HTTP/1.1\r\nHost: x\r\n\r\n"),
                ("oversized", HEADER.pack(MAGIC, FRAME_VERSION, 2, 1, 512 << 20, 0)),
                ("wrong version", HEADER.pack(MAGIC, 99, 0, 1, 2, 0) + b"{}"),
                ("invalid body", encode(Close(reason=CloseReason.NORMAL), 1)[:16] + b"{nope}"),
                ("truncated", encode(Close(reason=CloseReason.NORMAL), 1)[:10]),
            ]
            for label, data in abusers:
                client = await RawClient.connect(daemon.listen_port)
                await client.send_raw(data)
                if label == "truncated":
                    client.close()
                    continue
                bodies = await client.receive_all_until_closed()
                assert bodies and isinstance(bodies[-1], Close), label
                assert bodies[-1].reason == CloseReason.PROTOCOL_ERROR, (label, bodies)

            # An authenticated peer that sends a packet only the daemon may send is cut off too.
            rogue = await RawClient.connect(daemon.listen_port)
            await rogue.handshake("rogue", key)
            await rogue.send(PerformActions(mission_id="x", actions=[]))
            bodies = await rogue.receive_all_until_closed()
            assert isinstance(bodies[-1], Close) and "not valid from an agent" in bodies[-1].message

            await wait_for(lambda: mission_id not in daemon.missions.active, 60, "mission completion")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed"
            assert all(daemon.agents.session(n) is not None for n in names)
            assert not daemon.events.history(kind="agent_lost")
            assert len(daemon.events.history(kind="protocol_error")) >= 5
        finally:
            await stop_agents(agents)


async def test_flooding_agent_is_cut_off_and_others_keep_flying(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key, max_frames_per_s=50.0, frame_burst=100) as daemon:
        steady = start_agent("steady", daemon.listen_port, key)
        try:
            await wait_for(lambda: daemon.agents.session("steady") is not None, 10, "steady agent")
            flooder = await RawClient.connect(daemon.listen_port)
            await flooder.handshake("flooder", key)
            status = build_status_report()
            burst = b"".join(encode(status, seq) for seq in range(3, 1003))
            with contextlib.suppress(ConnectionError):
                await flooder.send_raw(burst)
            bodies = await flooder.receive_all_until_closed()
            # The close may be lost to a TCP reset (the flooder's unread frames); the event is not.
            assert all(isinstance(b, ResponseCid | StatusReport) for b in bodies[:-1])
            if bodies and isinstance(bodies[-1], Close):
                assert "frames/s" in bodies[-1].message and bodies[-1].code == "rate_limited"
            cut = daemon.events.history(kind="agent_cut_off")
            assert [e.agent for e in cut] == ["flooder"]
            before = daemon.agents.session("steady").status_count  # type: ignore[union-attr]
            await wait_for(
                lambda: daemon.agents.session("steady").status_count > before + 5,  # type: ignore[union-attr]
                5,
                "the well-behaved agent still reporting",
            )
        finally:
            await stop_agents([steady])


async def test_peer_that_never_reads_is_cut_off(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key, max_pending_bytes=64 << 10) as daemon:
        deaf = await RawClient.connect(daemon.listen_port)
        await deaf.handshake("deaf", key)
        ring = [
            FenceVertex(lat=47.0 + 0.001 * math.sin(i / 80), lon=8.0 + 0.001 * math.cos(i / 80))
            for i in range(500)
        ]
        fence = Geofence(polygon=ring)
        delivered: list[str] = ["deaf"]
        for _ in range(2000):  # ~25 KB each: socket buffers fill long before this bound
            delivered = await daemon.set_geofence(fence, ["deaf"])
            if not delivered:
                break
        assert delivered == []
        assert daemon.agents.session("deaf") is None
        deaf.close()
