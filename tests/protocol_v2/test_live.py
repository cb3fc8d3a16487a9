"""Protocol v2 against a real daemon on loopback: versions both ways, codes, bounds, replay."""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from pathlib import Path

import pytest

from agent.link import DaemonLink
from protocol.packets import Close, CloseReason, Position, RequestCid, StatusReport, SyncSignal
from protocol.session import ClientHandshake, Code, Refused, ServerHandshake
from protocol.stream import FramedStream, open_client
from protocol.wire import FRAME_VERSION, HEADER, MAGIC
from tests.backbone.helpers import new_key, running_daemon, start_agent, survey_mission
from tests.faults.common import hover_mission
from tests.protocol_v2.stdlib_agent import StdlibAgent
from tests.support.polling import wait_for

pytestmark = pytest.mark.timeout(120)


async def _refusal(port: int, identity: str, key: bytes) -> Refused:
    with pytest.raises(Refused) as caught:
        stream, _ = await open_client("127.0.0.1", port, ClientHandshake(identity, key), timeout=5.0)
        await stream.close()
    return caught.value


@pytest.mark.parametrize("version", [1, 2])
async def test_stdlib_agents_fly_a_mission_with_either_version(tmp_path: Path, version: int) -> None:
    """Three agents written from docs/protocol.md alone (stdlib) complete a synced mission."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agents = [StdlibAgent(daemon.listen_port, f"std-{i}", key, version) for i in range(1, 4)]
        try:
            accepted = [await asyncio.to_thread(a.handshake) for a in agents]
            assert all(("protocol_version" in a) == (version == 2) for a in accepted)
            flying = [asyncio.create_task(asyncio.to_thread(a.fly, 25.0)) for a in agents]
            await wait_for(lambda: all(daemon.agents.session(a.identity) for a in agents), 5, "joined")
            await wait_for(
                lambda: all((s := daemon.agents.session(a.identity)) and s.status for a in agents),
                5,
                "status",
            )
            mission_id = await daemon.missions.submit(
                survey_mission([a.identity for a in agents], sync_legs=1)
            )
            await wait_for(lambda: mission_id not in daemon.missions.active, 20, "mission done")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed", progress
            joined = daemon.events.history(kind="agent_joined")
            assert {e.data["version"] for e in joined} == {version}
            for task in flying:
                task.cancel()
        finally:
            for a in agents:
                a.close()
            await asyncio.sleep(0.3)


async def test_v2_agent_falls_back_to_a_v1_daemon(tmp_path: Path) -> None:
    """A v1 daemon (old shapes: it rejects the unknown ``versions`` field, sends no codes) still gets us."""
    key = new_key()
    hellos: list[dict[str, object]] = []

    async def v1_daemon(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        stream = FramedStream(reader, writer, version=1)
        with contextlib.suppress(Exception):
            data = await reader.readexactly(16)
            _, _, _, _, length, _ = HEADER.unpack(data)
            body = json.loads(await reader.readexactly(length))
            hellos.append(body)
            if "versions" in body:  # what v1 code answered: a protocol error naming the field
                await stream.close(
                    Close(
                        reason=CloseReason.PROTOCOL_ERROR,
                        message="invalid type 0 (REQUEST_CID) body at versions: "
                        "Extra inputs are not permitted",
                    )
                )
                return
            server = ServerHandshake(lambda _: bytes.fromhex(key), versions=(1,))
            await stream.send(server.on_hello(RequestCid.model_validate(body)))
            server.on_proof((await stream.read_frame()).body)
            await stream.send(server.accept(7, None, None))
            await asyncio.sleep(5)
        writer.close()

    server = await asyncio.start_server(v1_daemon, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    running = start_agent("new-agent", port, key)
    try:
        await wait_for(lambda: running.agent.link.connected, 10, "connected to the v1 daemon")
        assert running.agent.link.version == 1 and running.agent.link.cid == 7
        assert "versions" in hellos[0] and "versions" not in hellos[-1]
    finally:
        await running.kill()
        server.close()


async def test_refusal_codes_and_what_the_agent_does(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key, banned_agents=["rogue"], max_agents=1) as daemon:
        port = daemon.listen_port
        wrong = await _refusal(port, "someone", bytes.fromhex(new_key()))
        assert wrong.code == Code.WRONG_KEY and not wrong.authenticated and not wrong.final
        banned = await _refusal(port, "rogue", bytes.fromhex(key))  # decided after the proof: proved
        assert banned.code == Code.BANNED and banned.authenticated and banned.final
        daemon.agents.accepting = False
        starting = await _refusal(port, "early", bytes.fromhex(key))
        assert starting.code == Code.STARTING and starting.action == "retry" and starting.retry_after_s
        daemon.agents.accepting = True
        first, accepted = await open_client("127.0.0.1", port, ClientHandshake("one", bytes.fromhex(key)))
        assert accepted.version == 2 and not accepted.lost
        full = await _refusal(port, "two", bytes.fromhex(key))
        assert full.code == Code.FLEET_FULL and full.action == "retry"
        # replaced: a second session of "one" closes the first with code replaced
        second, _ = await open_client("127.0.0.1", port, ClientHandshake("one", bytes.fromhex(key)))
        close = None
        for _ in range(5):
            frame = await first.read_frame(timeout=3.0)
            if frame.packet_type == 6:
                close = frame.body
                break
        assert close is not None and close.code == Code.REPLACED  # type: ignore[attr-defined]
        await first.close()
        await second.close()
        # a wrong key cannot be proved by the daemon: the agent keeps retrying with backoff
        running = start_agent("intruder", port, new_key())
        try:
            await wait_for(lambda: running.agent.link.unproved_refusals >= 3, 10, "unproved refusals")
            assert running.agent.link.last_code == Code.WRONG_KEY and running.agent.link.stopped is None
        finally:
            await running.kill()
        # the project's agent stops for good on a proved stop code, and keeps its process alive
        running = start_agent("rogue", port, key)
        try:
            await wait_for(lambda: running.agent.link.stopped is not None, 10, "link stopped")
            assert running.agent.link.last_code == Code.BANNED and not running.task.done()
        finally:
            await running.kill()


async def test_enrollment_off_and_cid_exhaustion_refuse_new_identities(tmp_path: Path) -> None:
    key = bytes.fromhex(k := new_key())
    async with running_daemon(tmp_path, k) as daemon:
        stream, _ = await open_client("127.0.0.1", daemon.listen_port, ClientHandshake("known", key))
        await stream.close()
        daemon.config.enroll_new_agents = False
        assert (await _refusal(daemon.listen_port, "new", key)).code == Code.ENROLLMENT_CLOSED
        stream, _ = await open_client("127.0.0.1", daemon.listen_port, ClientHandshake("known", key))
        await stream.close()
        daemon.config.enroll_new_agents = True
        daemon.store._db.execute(
            "INSERT INTO agents(identity, cid, first_seen, last_seen, capabilities) "
            "VALUES ('z', 65535, 0, 0, '{}')"
        )
        exhausted = await _refusal(daemon.listen_port, "one-too-many", key)
        assert exhausted.code == Code.CID_EXHAUSTED and exhausted.action == "retry"


async def test_pre_auth_frames_are_small_and_handshakes_are_capped(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key, max_handshakes=2, handshake_timeout_s=3.0) as daemon:
        port = daemon.listen_port
        running = start_agent("flying", port, key)
        try:
            await wait_for(lambda: (s := daemon.agents.session("flying")) and s.status, 10, "agent joined")
            mission_id = await daemon.missions.submit(hover_mission("flying", seconds=60.0))
            # a 2 KiB "hello" is refused from its header before the body is read
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(HEADER.pack(MAGIC, FRAME_VERSION, 0, 1, 2048, 0))
            await writer.drain()
            stream = FramedStream(reader, writer)
            close = (await stream.read_frame(timeout=3.0)).body
            assert close.code == Code.PROTOCOL_ERROR and "exceeds the limit of 1024" in close.message  # type: ignore[union-attr]
            await stream.close()
            # two silent connections hold every handshake slot: the third is refused busy at once
            holders = [await asyncio.open_connection("127.0.0.1", port) for _ in range(2)]
            await asyncio.sleep(0.2)
            busy = await _refusal(port, "late", bytes.fromhex(key))
            assert busy.code == Code.BUSY and busy.action == "retry"
            for _, w in holders:
                w.close()
            before = daemon.agents.session("flying")
            assert before is not None and before.open  # the flying agent was never disturbed
            assert mission_id in daemon.missions.active
            count = before.status_count
            await asyncio.sleep(0.5)
            assert before.status_count > count
        finally:
            await running.kill()


async def test_lost_agent_is_told_when_it_comes_back(tmp_path: Path) -> None:
    key = bytes.fromhex(k := new_key())
    async with running_daemon(tmp_path, k, lost_after_periods=3.0) as daemon:
        stream, accepted = await open_client("127.0.0.1", daemon.listen_port, ClientHandshake("quiet", key))
        assert not accepted.lost
        await wait_for(lambda: "quiet" in daemon.agents.lost, 10, "marked lost")
        await stream.close()
        again, accepted = await open_client("127.0.0.1", daemon.listen_port, ClientHandshake("quiet", key))
        assert accepted.lost
        await again.close()


async def test_sixty_second_outage_at_10_hz_replays_without_cut_off_or_lost_steps(tmp_path: Path) -> None:
    """600 buffered reports (60 s at 10 Hz) and the step completions of the outage reach the daemon.

    The outage is simulated by filling the link's buffers as 60 s offline would (status every
    0.1 s, a finished step every 10 s); the daemon's limits are the defaults.
    """
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        running = start_agent("replayer", daemon.listen_port, key, status_buffer=1200)
        link: DaemonLink = running.agent.link
        try:
            await wait_for(
                lambda: daemon.agents.session("replayer") is not None and link.connected, 10, "joined"
            )
            await running.kill()
            await wait_for(lambda: daemon.agents.session("replayer") is None, 10, "gone")
            start = time.time() - 120.0  # replayed reports of the last two minutes
            for i in range(600):
                report = StatusReport(
                    time=start + i * 0.1,
                    position=Position(lat=47.0, lon=8.0, alt_rel=10.0, alt_amsl=500.0),
                    mission_id="m-outage",
                    completed_step=i // 100,
                    step=i // 100 + 1,
                )
                await link.send_status(report)
            for step in range(6):
                await link.send_control(SyncSignal(mission_id="m-outage", step=step, kind="finished"))
            assert link.buffered == (600, 6)
            held = 600 + link.unacknowledged  # a replay of the first session not yet acknowledged goes again
            replayed_before = link.replayed
            sync_seen: list[int] = []

            async def on_sync(_session: object, signal: SyncSignal) -> None:
                sync_seen.append(signal.step)

            daemon.agents.on_sync.append(on_sync)
            link._stopping = False  # the agent's shutdown stopped its link; run it again on its own
            replay = asyncio.create_task(link.run())
            try:
                await wait_for(lambda: link.buffered == (0, 0) and link.replayed > 0, 30, "replay done")
                await daemon.agents.drain_hooks()
                session = daemon.agents.session("replayer")
                assert session is not None and session.open
                assert not daemon.events.history(kind="agent_cut_off")
                assert sorted(sync_seen) == list(range(6))
                sent = link.replayed - replayed_before
                await wait_for(lambda: session.replayed_count == sent, 5, "replay received")
                assert sent == running.agent.config.replay_max_reports
                assert link.thinned == held - sent
            finally:
                replay.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await replay
        finally:
            await link.stop()
