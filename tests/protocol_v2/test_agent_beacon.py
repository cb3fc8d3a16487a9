"""The agent's release-beacon listener (agent/beacon.py) on real loopback UDP beside a real daemon.

A valid beacon releases a barrier with no TCP release at all; garbage, forgeries, replays, other
missions' beacons and steps not reached are counted and change nothing; two agents of one
machine hear one broadcast; without the option, or on a version-1 session, nothing listens.
The daemon here sends no beacons (the test sends them), so every release seen is the beacon's.
"""

from __future__ import annotations

import contextlib
import secrets
import socket
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest

from agent.beacon import MAX_MISSIONS, MAX_REJECTS_PER_STEP, BeaconListener
from agent.cli import agent_from_args, build_parser
from agent.config import AgentConfig
from agent.config_file import load_agent_config
from gcs.core.daemon import Daemon
from gcs.link.beacon import LOOPBACK_BROADCAST, free_udp_port
from protocol.actions import Action, Hold
from protocol.beacon import VALUE_BYTES, ReleaseChain, encode_beacon
from protocol.packets import PerformActions, RequestCid, SyncSignal
from protocol.session import ServerHandshake
from tests.backbone.helpers import (
    RunningAgent,
    new_key,
    running_daemon,
    start_agent,
    stop_agents,
    survey_mission,
)
from tests.support.polling import wait_for

BROADCAST = LOOPBACK_BROADCAST


def broadcast(port: int, *datagrams: bytes) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        sender.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        for data in datagrams:
            sender.sendto(data, (BROADCAST, port))


def barriers(count: int) -> list[Action]:
    """``count`` short holds, each a barrier, then one more hold."""
    return [Hold(step=i, seconds=0.2, sync=i < count) for i in range(count + 1)]


def beacon(chain: ReleaseChain, step: int, mission_id: str = "m") -> bytes:
    value = chain.value(step)
    assert value is not None
    return encode_beacon(mission_id, step, value)


def listener_of(running: RunningAgent) -> BeaconListener:
    assert running.agent.beacon is not None
    return running.agent.beacon


async def processed(listener: BeaconListener, received: int) -> None:
    await wait_for(lambda: listener.stats.received >= received, 5, f"{received} datagrams received")


async def until(predicate: Callable[[], object], what: str) -> None:
    await wait_for(predicate, 10, what)


def plan(chain: ReleaseChain, actions: list[Action], **fields: object) -> PerformActions:
    """Mission "m" with ``chain``'s anchor, as the daemon sends it to a listening agent."""
    values: dict[str, object] = {"mode": "replace", **fields}
    return PerformActions(mission_id="m", actions=actions, release_anchor=chain.anchor.hex(), **values)


@contextlib.asynccontextmanager
async def one_listener(
    tmp_path: Path, name: str, versions: list[int] | None = None
) -> AsyncIterator[tuple[Daemon, RunningAgent, int]]:
    """A daemon (sending no beacons) and one joined agent listening on a free port; stopped after."""
    key, port = new_key(), free_udp_port()
    async with running_daemon(tmp_path, key) as daemon:
        running = start_agent(name, daemon.listen_port, key, release_beacon=f"{BROADCAST}:{port}")
        if versions is not None:
            running.agent.link.versions = versions  # before its first connection (its task has not run)
        try:
            # both ends: the daemon registers the session before the agent has read `accepted`
            await until(
                lambda: daemon.agents.session(name) is not None and running.agent.link.connected, "joined"
            )
            yield daemon, running, port
        finally:
            await running.kill()


async def test_a_beacon_releases_a_barrier_and_nothing_else_does(tmp_path: Path) -> None:
    chain, other = ReleaseChain(6), ReleaseChain(6)
    async with one_listener(tmp_path, "listener") as (daemon, running, port):
        queue, listener = running.agent.queue, listener_of(running)
        assert not listener.listening  # no anchor yet: no socket
        daemon.agents.post("listener", plan(chain, barriers(3)))
        await until(lambda: queue.waiting_sync == 0, "waiting at barrier 0")
        assert listener.listening
        held = listener.verifier("m")
        broadcast(
            port,
            b"not a beacon",
            encode_beacon("m", 0, secrets.token_bytes(VALUE_BYTES)),  # forged value
            beacon(other, 0),  # another chain's valid value
            beacon(chain, 0, mission_id="other"),  # a mission without an anchor here
            beacon(chain, 1),  # the right value, for a barrier not reached
        )
        await processed(listener, 5)
        stats = listener.stats
        assert (stats.malformed, stats.rejected, stats.ignored, stats.accepted) == (1, 2, 2, 0)
        assert queue.awaits_release("m", 0) and queue.waiting_sync == 0  # still held at barrier 0

        broadcast(port, beacon(chain, 0))
        await until(lambda: queue.waiting_sync == 1, "released by the beacon, waiting at barrier 1")
        assert stats.accepted == 1
        broadcast(port, beacon(chain, 0))  # a replay: that step is released already
        await processed(listener, 7)
        assert stats.late == 1 and stats.accepted == 1

        # More of the mission, without its anchor and with it: the verifier (and what it
        # accepted) stays.
        daemon.agents.post("listener", PerformActions(mission_id="m", actions=[Hold(step=4, seconds=0.2)]))
        more = [Hold(step=5, seconds=0.2)]
        daemon.agents.post("listener", plan(chain, more, mode="append"))
        await until(lambda: queue.depth == 4, "steps 4 and 5 queued behind 2 and 3")
        assert listener.verifier("m") is held
        broadcast(port, beacon(chain, 1))
        await until(lambda: queue.waiting_sync == 2, "released by the second beacon")
        assert stats.accepted == 2
        assert daemon.agents.session("listener") is not None  # the daemon saw nothing amiss
    # The agent stopped: its socket is closed (a socket without SO_REUSEADDR can take the address).
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind((BROADCAST, port))
    assert not listener.listening


async def test_forgeries_use_up_a_steps_budget_and_the_tcp_release_still_counts(tmp_path: Path) -> None:
    chain = ReleaseChain(2)
    async with one_listener(tmp_path, "flooded") as (daemon, running, port):
        queue, listener = running.agent.queue, listener_of(running)
        daemon.agents.post("flooded", plan(chain, barriers(1)))
        await until(lambda: queue.waiting_sync == 0, "waiting at barrier 0")
        forged = [encode_beacon("m", 0, secrets.token_bytes(VALUE_BYTES)) for _ in range(20)]
        broadcast(port, *forged, beacon(chain, 0))
        await processed(listener, 21)
        # Only MAX_REJECTS_PER_STEP forgeries were hashed; then the step stopped listening,
        # the true beacon included, and waits for its TCP release.
        assert listener.stats.rejected == MAX_REJECTS_PER_STEP
        assert listener.stats.ignored == 21 - MAX_REJECTS_PER_STEP
        assert listener.stats.accepted == 0 and queue.waiting_sync == 0
        daemon.agents.post("flooded", SyncSignal(mission_id="m", step=0, kind="release"))
        await until(lambda: queue.waiting_sync is None and queue.completed_step == 1, "released by TCP")


async def test_a_rejoining_agents_barrier_is_released_by_a_beacon(tmp_path: Path) -> None:
    """A rejoin (``await_release``) waits at a barrier finished before; the beacon for it counts."""
    chain = ReleaseChain(4)
    async with one_listener(tmp_path, "rejoiner") as (daemon, running, port):
        queue, listener = running.agent.queue, listener_of(running)
        daemon.agents.post("rejoiner", plan(chain, [Hold(step=3, seconds=0.2)], await_release=2))
        await until(lambda: queue.waiting_sync == 2, "waiting at the rejoin barrier")
        broadcast(port, beacon(chain, 1), beacon(chain, 2))  # step 1 was released long ago
        await until(lambda: queue.completed_step == 3, "released by the beacon, step 3 flown")
        assert (listener.stats.accepted, listener.stats.ignored) == (1, 1)


async def test_a_mission_flown_with_a_beacon_daemon(tmp_path: Path) -> None:
    """The daemon's beacons (gcs/link/beacon.py) and the agents' listeners agree: every barrier is
    announced once, each beacon verifies (or comes after its TCP release), the mission completes."""
    key, port = new_key(), free_udp_port()
    names = ["lead-a", "lead-b"]
    address = f"{BROADCAST}:{port}"
    async with running_daemon(tmp_path, key, release_beacon=address) as daemon:
        agents = [
            start_agent(name, daemon.listen_port, key, index=i, release_beacon=address)
            for i, name in enumerate(names)
        ]
        try:
            await until(lambda: len(daemon.agents.connected()) == 2, "both joined")
            mission_id = await daemon.missions.submit(survey_mission(names, sync_legs=2))
            await wait_for(lambda: mission_id not in daemon.missions.active, 60, "mission completion")
            progress = daemon.missions.progress(mission_id)
            assert progress is not None and progress.state == "completed", progress
            assert progress.released_steps == [0, 1, 2]
            for running in agents:
                stats = listener_of(running).stats
                await wait_for(lambda s=stats: s.received == 3, 5, "three beacons")
                assert stats.accepted + stats.late == 3, stats
                assert (stats.rejected, stats.ignored, stats.malformed) == (0, 0, 0), stats
        finally:
            await stop_agents(agents)


async def test_two_agents_of_one_machine_hear_one_broadcast(tmp_path: Path) -> None:
    key, port = new_key(), free_udp_port()
    chain = ReleaseChain(2)
    names = ["twin-a", "twin-b"]
    async with running_daemon(tmp_path, key) as daemon:
        agents = [
            start_agent(name, daemon.listen_port, key, index=i, release_beacon=f"{BROADCAST}:{port}")
            for i, name in enumerate(names)
        ]
        try:
            await until(lambda: all(daemon.agents.session(n) is not None for n in names), "both joined")
            for name in names:
                daemon.agents.post(
                    name,
                    PerformActions(
                        mission_id="m", mode="replace", actions=barriers(1), release_anchor=chain.anchor.hex()
                    ),
                )
            await until(lambda: all(a.agent.queue.waiting_sync == 0 for a in agents), "both at barrier 0")
            broadcast(port, beacon(chain, 0))  # one datagram
            await until(
                lambda: all(
                    a.agent.queue.waiting_sync is None and a.agent.queue.completed_step == 1 for a in agents
                ),
                "both released",
            )
            assert [listener_of(a).stats.accepted for a in agents] == [1, 1]
        finally:
            for running in agents:
                await running.kill()


async def test_a_version_1_session_never_gets_an_anchor_so_nothing_listens(tmp_path: Path) -> None:
    async with one_listener(tmp_path, "old-school", versions=[1]) as (daemon, running, _port):
        assert running.agent.link.version == 1
        daemon.agents.post("old-school", plan(ReleaseChain(2), barriers(1)))
        await until(lambda: running.agent.queue.waiting_sync == 0, "waiting at barrier 0")
        listener = listener_of(running)
        assert listener.verifier("m") is None and not listener.listening  # v1 drops the v2 field


def _offer(config: AgentConfig, versions: list[int] | None = None) -> RequestCid:
    from agent.autopilot.memory import MemoryAutopilot
    from agent.runtime import Agent

    agent = Agent(config, MemoryAutopilot())
    if versions is not None:
        agent.link.versions = versions
    handshake = agent.link.handshake()
    server = ServerHandshake(lambda _identity: bytes.fromhex(config.key_hex))
    return handshake.on_challenge(server.on_hello(handshake.hello()))


def test_the_handshake_offers_beacons_only_when_configured() -> None:
    config = AgentConfig(identity="a", key_hex=new_key())
    assert _offer(config).release_beacon is None
    configured = config.model_copy(update={"release_beacon": f"{BROADCAST}:14650"})
    assert _offer(configured).release_beacon is True
    assert _offer(configured, versions=[1]).release_beacon is None


async def test_anchors_are_kept_for_a_few_missions_only() -> None:
    from agent.autopilot.memory import MemoryAutopilot
    from agent.runtime import Agent

    agent = Agent(
        AgentConfig(identity="a", key_hex=new_key(), release_beacon=f"{BROADCAST}:{free_udp_port()}"),
        MemoryAutopilot(),
    )
    listener = agent.beacon
    assert listener is not None
    try:
        chains = [ReleaseChain(1) for _ in range(MAX_MISSIONS + 2)]
        for number, chain in enumerate(chains):
            await listener.arm(f"m{number}", chain.anchor.hex())
        held = [n for n in range(len(chains)) if listener.verifier(f"m{n}") is not None]
        assert held == list(range(2, MAX_MISSIONS + 2))
        first = listener.verifier("m5")
        await listener.arm("m5", chains[5].anchor.hex())
        assert listener.verifier("m5") is first  # the same anchor keeps its verifier
        await listener.arm("m5", ReleaseChain(1).anchor.hex())
        assert listener.verifier("m5") is not first  # a new chain for the mission
    finally:
        await listener.close()
    assert not listener.listening


async def test_an_address_that_cannot_be_bound_leaves_tcp_releases_working() -> None:
    from agent.autopilot.memory import MemoryAutopilot
    from agent.runtime import Agent

    # 192.0.2.1 (TEST-NET-1) is on no interface of this machine: bind fails with EADDRNOTAVAIL.
    agent = Agent(
        AgentConfig(identity="a", key_hex=new_key(), release_beacon="192.0.2.1:14650"), MemoryAutopilot()
    )
    assert agent.beacon is not None
    await agent.beacon.arm("m", ReleaseChain(1).anchor.hex())
    assert not agent.beacon.listening
    assert agent.beacon.last_error is not None and "192.0.2.1:14650" in agent.beacon.last_error


def test_release_beacon_from_file_environment_and_flag(tmp_path: Path) -> None:
    path = tmp_path / "agent.toml"
    path.write_text(
        f'[agent]\nidentity = "d1"\nkey_hex = "{new_key()}"\nrelease_beacon = "127.255.255.255:14650"\n'
    )
    assert load_agent_config(path, environ={}).agent.release_beacon == "127.255.255.255:14650"
    from_env = load_agent_config(path, environ={"FLEETGCS_AGENT_RELEASE_BEACON": "192.168.1.255:14650"})
    assert from_env.agent.release_beacon == "192.168.1.255:14650"
    memory = ["--autopilot-backend", "memory", "--autopilot", "memory"]
    args = build_parser().parse_args(
        ["run", "--config", str(path), *memory, "--release-beacon", "10.0.0.255:1"]
    )
    assert agent_from_args(args)[0].release_beacon == "10.0.0.255:1"
    flags = ["run", "--id", "d2", "--key", new_key(), *memory]
    assert agent_from_args(build_parser().parse_args(flags))[0].release_beacon is None
    for bad, why in (
        ("nohost:1", "not an IPv4 address"),
        ("10.0.0.255", "IPv4:PORT"),
        ("1.2.3.4:0", "1..65535"),
    ):
        with pytest.raises(SystemExit, match=why) as exc:
            agent_from_args(build_parser().parse_args([*flags, "--release-beacon", bad]))
        assert "\n" not in str(exc.value) and "agent.release_beacon" in str(exc.value)
    with pytest.raises(SystemExit, match="release_beacon"):
        agent_from_args(build_parser().parse_args(["run", "--config", str(path), "--release-beacon", "x:1"]))


async def test_no_option_no_listener(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        running = start_agent("plain", daemon.listen_port, key)
        try:
            await until(lambda: daemon.agents.session("plain") is not None, "joined")
            assert running.agent.beacon is None
            daemon.agents.post(
                "plain",
                PerformActions(
                    mission_id="m",
                    mode="replace",
                    actions=barriers(1),
                    release_anchor=ReleaseChain(1).anchor.hex(),
                ),
            )
            queue = running.agent.queue
            await until(lambda: queue.waiting_sync == 0, "waiting at barrier 0")  # the anchor did no harm
            daemon.agents.post("plain", SyncSignal(mission_id="m", step=0, kind="release"))
            await until(lambda: queue.waiting_sync is None and queue.completed_step == 1, "released by TCP")
        finally:
            await running.kill()


def test_doctor_says_whether_the_beacon_address_can_be_bound() -> None:
    from agent.beacon import beacon_socket
    from agent.doctor import Report, check_release_beacon

    config = AgentConfig(identity="a", key_hex=new_key())
    unset = Report()
    check_release_beacon(unset, config)
    assert unset.checks == []
    port = free_udp_port()
    with beacon_socket((BROADCAST, port)):  # a running agent holds it: the doctor's check still binds
        good = Report()
        check_release_beacon(good, config.model_copy(update={"release_beacon": f"{BROADCAST}:{port}"}))
    assert [(c.name, c.verdict) for c in good.checks] == [("release beacon", "ok")]
    bad = Report()
    check_release_beacon(bad, config.model_copy(update={"release_beacon": "192.0.2.1:14650"}))
    assert bad.ok and "[WARN] release beacon: cannot listen on 192.0.2.1:14650" in bad.render()
