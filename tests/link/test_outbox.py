"""Per-agent outbound queues over real TCP: a peer that stops reading stalls only itself."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

from protocol.actions import Hold
from protocol.packets import AgentParameters, PacketType, PerformActions, SetParameters, SyncSignal
from protocol.wire import Frame
from tests.backbone.helpers import new_key, running_daemon, start_agent, stop_agents
from tests.link.common import record_actions, stall_outbox
from tests.support.polling import wait_for
from tests.support.raw_client import RawClient, build_status_report

HOLD_BOUND_S = 0.1


async def test_a_peer_that_stops_reading_does_not_delay_another_agents_pause(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key, send_timeout_s=3.0) as daemon:
        fast = start_agent("fast", daemon.listen_port, key)
        received = record_actions(fast)
        deaf = await RawClient.connect(daemon.listen_port)
        talking: asyncio.Task[None] | None = None
        try:
            await deaf.handshake("deaf", key)
            talking = asyncio.create_task(_keep_reporting(deaf))  # alive, just not reading
            await wait_for(lambda: daemon.agents.session("fast") is not None, 10, "fast agent joins")
            await stall_outbox(daemon, "deaf")
            # A caller waiting on the stuck peer, as a fan-out or a service would.
            stuck = asyncio.create_task(
                daemon.agents.send("deaf", PerformActions(mission_id="m", mode="pause", reason="x"))
            )
            delays = []
            for attempt in range(5):
                sent_at = time.monotonic()
                mode = "pause" if attempt % 2 == 0 else "resume"
                assert daemon.agents.post(
                    "fast", PerformActions(mission_id="none", mode=mode, reason="test"), urgent=True
                )
                await wait_for(lambda n=attempt: len(received) > n, 2.0, f"command {attempt} at fast")
                delays.append(received[attempt][0] - sent_at)
                await asyncio.sleep(0.05)
            print(
                "\nurgent command to 'fast' while 'deaf' is stuck, delays (ms):",
                [round(d * 1000, 1) for d in delays],
            )
            assert max(delays) < HOLD_BOUND_S, delays
            assert not stuck.done(), "the stuck peer's send resolved although it never read"
            # The stuck peer is cut off after the send timeout; the other agent never noticed.
            assert await asyncio.wait_for(stuck, 10.0) is False
            assert daemon.agents.session("deaf") is None
            assert [e.agent for e in daemon.events.history(kind="agent_cut_off")] == ["deaf"]
            fast_session = daemon.agents.session("fast")
            assert fast_session is not None and "fast" not in daemon.agents.lost
            before = fast_session.status_count
            await wait_for(lambda: fast_session.status_count > before + 3, 5, "fast keeps reporting")
        finally:
            if talking is not None:
                talking.cancel()
            deaf.close()
            await stop_agents([fast])


async def test_urgent_frames_overtake_queued_normal_traffic(tmp_path: Path) -> None:
    key = new_key()
    # The raw peer sends no status: a long liveness limit keeps a loaded machine from losing it.
    async with running_daemon(tmp_path, key, send_timeout_s=20.0, lost_after_periods=400.0) as daemon:
        slow = await RawClient.connect(daemon.listen_port)
        try:
            await slow.handshake("slow", key)
            await stall_outbox(daemon, "slow", frames_waiting=3)
            agents = daemon.agents
            urgent_params = SetParameters(parameters=AgentParameters(battery_low_pct=42.0))
            replace = PerformActions(mission_id="m", mode="replace", actions=[Hold(step=0, seconds=1.0)])
            pause = PerformActions(mission_id="m", mode="pause", reason="hold now")
            assert agents.post("slow", urgent_params, urgent=True)
            assert agents.post("slow", replace)  # normal lane
            for step in (1, 2, 3):
                assert agents.post("slow", SyncSignal(mission_id="m", step=step, kind="release"))
            assert agents.post("slow", pause)  # urgent by default: a pause
            frames = await _read_until(slow, lambda f: isinstance(f.body, SyncSignal) and f.body.step == 3)
        finally:
            slow.close()

    seqs = [f.seq for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "sequence numbers follow the wire order"
    kinds = [_label(f) for f in frames]
    fences_after_params = kinds[kinds.index("params") :].count("fence")
    assert fences_after_params >= 1, f"the urgent frame did not overtake queued fences: {kinds}"
    tail = [k for k in kinds if k not in ("fence", "keepalive")]
    # A pause keeps its place after a type-4 frame queued before it (a replace cancels a pause),
    # and jumps ahead of the normal releases; the releases keep their own order.
    assert tail == ["params", "replace", "pause", "release-1", "release-2", "release-3"], kinds


async def _keep_reporting(client: RawClient, period_s: float = 0.1, limit: int = 600) -> None:
    """Send a status every period (bounded), ignoring a closed connection."""
    for _ in range(limit):
        try:
            await client.send(build_status_report())
        except (ConnectionError, OSError):
            return
        await asyncio.sleep(period_s)


async def _read_until(client: RawClient, last: object, limit: int = 5000) -> list[Frame]:
    frames = []
    for _ in range(limit):
        frame = await client.receive(timeout=10.0)
        assert frame is not None, "the daemon closed the connection"
        if frame.packet_type == PacketType.RESPONSE_CID:
            continue
        frames.append(frame)
        if last(frame):  # type: ignore[operator]
            return frames
    raise AssertionError(f"no final frame in {limit} frames")


def _label(frame: Frame) -> str:
    body = frame.body
    if isinstance(body, SetParameters):
        if body.geofence is not None:
            return "fence"
        return "params" if body.parameters is not None else "keepalive"
    if isinstance(body, PerformActions):
        return body.mode
    if isinstance(body, SyncSignal):
        return f"release-{body.step}"
    return type(body).__name__


async def test_a_burst_is_written_in_one_pass_in_order_with_fresh_seqs(tmp_path: Path) -> None:
    """AgentManager.burst (barrier releases): one encoding, every socket written at once, behind
    whatever the agent's outbox still holds, and numbered in the session's own sequence."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        clients = [await RawClient.connect(daemon.listen_port) for _ in range(3)]
        try:
            for i, client in enumerate(clients):
                await client.handshake(f"b-{i}", key)
            first = daemon.agents.session("b-0")
            assert first is not None
            first.post(SetParameters(parameters=AgentParameters(link_range_m=500.0)))  # queued ahead
            release = SyncSignal(mission_id="m", step=4, kind="release")
            assert daemon.agents.burst(["b-0", "b-1", "b-2", "nobody"], release) == 3
            for i, client in enumerate(clients):
                frames = [await client.receive(5.0) for _ in range(2 if i == 0 else 1)]
                bodies = [f.body for f in frames if f is not None]
                assert bodies[-1] == release, bodies
                if i == 0:
                    assert isinstance(bodies[0], SetParameters)  # the queued frame went first
                seqs = [f.seq for f in frames if f is not None]
                assert seqs == sorted(seqs) and seqs[0] == 3  # challenge 1, accepted 2, then ours
        finally:
            for client in clients:
                client.close()
