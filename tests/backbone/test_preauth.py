"""Before the handshake completes, nobody without the key can stop an agent or keep it out.

A real daemon on loopback; an on-path forger is the fault proxy answering in the daemon's place
(tests/faults/proxy.py ``impersonate``). The pre-authentication flood comes from 127.0.0.2 (Linux
routes all of 127/8 to lo) while the genuine agent connects from 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets
import time
from pathlib import Path

import pytest

from agent.config import AgentConfig
from agent.doctor import diagnose, handshake
from agent.link import DaemonLink
from gcs.link.admission import source_of
from protocol import auth
from protocol.packets import Close, CloseReason, RequestCid, ResponseCid
from protocol.session import ClientHandshake, Code, Refused, ServerHandshake, refusal
from protocol.stream import FramedStream, open_client
from tests.backbone.helpers import new_key, running_daemon, start_agent
from tests.faults.proxy import FaultProxy, Script
from tests.support.polling import wait_for

pytestmark = pytest.mark.timeout(120)

V1_ANSWER: Script = [
    [
        Close(
            reason=CloseReason.PROTOCOL_ERROR,
            message="invalid type 0 (REQUEST_CID) body at versions: Extra inputs are not permitted",
        )
    ]
]
"""What a version-1 daemon answers a v2 hello: a code-less close naming the field."""


def forged_refusal(code: Code, **fields: object) -> Script:
    """A refusal of the hello as the daemon would send it (type 1 + type 6), by someone without the key."""
    answer = refusal(code, f"forged {code.value}")
    answer[0] = answer[0].model_copy(update=fields)
    return [answer]


def forged_bad_proof() -> Script:
    """A challenge, then ``accepted`` with a server proof made without the key."""
    challenge = ResponseCid(outcome="challenge", server_nonce=auth.new_nonce(), protocol_version=2)
    accepted = ResponseCid(
        outcome="accepted", cid=1, server_nonce=challenge.server_nonce, server_proof=secrets.token_hex(32)
    )
    return [[challenge], [accepted]]


async def test_forged_unproved_refusals_leave_the_agent_reconnecting_on_v2(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon, FaultProxy(daemon.listen_port) as proxy:
        proxy.impersonate(
            forged_refusal(Code.BANNED),
            forged_refusal(Code.WRONG_KEY),
            forged_bad_proof(),
            # a stop code with a made-up proof of the refusal
            forged_refusal(Code.BANNED, server_nonce=auth.new_nonce(), refusal_proof=secrets.token_hex(32)),
            V1_ANSWER,  # one code-less "version 2 not supported"
        )
        running = start_agent("drone-1", proxy.port, key)
        try:
            link = running.agent.link
            await wait_for(
                lambda: daemon.agents.session("drone-1") is not None and link.connected,
                15,
                "the agent through",
            )
            assert proxy.forging == 0 and proxy.stats["forged"] == 5
            assert link.stopped is None and link.unproved_refusals == 4
            assert link.version == 2 and link.versions == [1, 2]
            session = daemon.agents.session("drone-1")
            assert session is not None and session.version == 2
        finally:
            await running.kill()


async def test_repeated_v1_answers_fall_back_loudly_and_v2_is_offered_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    key = new_key()
    caplog.set_level(logging.WARNING, logger="agent.link")
    async with running_daemon(tmp_path, key) as daemon, FaultProxy(daemon.listen_port) as proxy:
        proxy.impersonate(V1_ANSWER, V1_ANSWER, V1_ANSWER)
        running = start_agent("drone-1", proxy.port, key)
        running.agent.link.v2_retry_s = 1.0  # before its task first runs
        try:
            await wait_for(lambda: running.agent.link.connected, 15, "the agent to connect")
            assert running.agent.link.version == 1  # three answers in a row: it fell back
            assert any(
                r.levelno == logging.WARNING and "FALLING BACK to protocol version 1" in r.getMessage()
                for r in caplog.records
            )
            await asyncio.sleep(1.1)
            proxy.reset_all()  # the next connection comes after v2_retry_s: it offers version 2 again
            await wait_for(
                lambda: (s := daemon.agents.session("drone-1")) is not None and s.version == 2,
                15,
                "the agent back on version 2",
            )
            assert running.agent.link.stopped is None
        finally:
            await running.kill()


async def test_a_proved_refusal_stops_the_agent_through_the_proxy(tmp_path: Path) -> None:
    key = new_key()
    async with (
        running_daemon(tmp_path, key, banned_agents=["rogue"]) as daemon,
        FaultProxy(daemon.listen_port) as proxy,
    ):
        running = start_agent("rogue", proxy.port, key)
        try:
            await wait_for(lambda: running.agent.link.stopped is not None, 10, "the link to stop")
            assert running.agent.link.last_code == Code.BANNED and running.agent.link.unproved_refusals == 0
            attempts = proxy.stats["connections"]
            await asyncio.sleep(0.5)
            assert proxy.stats["connections"] == attempts  # no further connection
        finally:
            await running.kill()


async def _hold_slots(port: int, stop_at: float, answers: list[ResponseCid]) -> None:
    """One attacker socket from 127.0.0.2: silent, re-opened as soon as the daemon drops it."""
    for _ in range(2000):
        if time.monotonic() >= stop_at:
            return
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", port, local_addr=("127.0.0.2", 0))
        except OSError:
            await asyncio.sleep(0.05)
            continue
        stream = FramedStream(reader, writer)
        try:
            for _ in range(3):
                frame = await stream.read_frame(timeout=max(0.01, stop_at - time.monotonic()))
                if isinstance(frame.body, ResponseCid):
                    answers.append(frame.body)
        except (ConnectionError, TimeoutError, OSError):
            pass
        finally:
            writer.close()
        await asyncio.sleep(0.02)


async def test_pre_auth_flood_from_one_source_lets_a_genuine_agent_join(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key, handshake_timeout_s=5.0) as daemon:
        answers: list[ResponseCid] = []
        stop_at = time.monotonic() + 12.0
        flood = [asyncio.create_task(_hold_slots(daemon.listen_port, stop_at, answers)) for _ in range(64)]
        running = None
        try:
            await wait_for(lambda: daemon.agents.pre_auth.pending >= 16, 5, "the flood to hold slots")
            await asyncio.sleep(0.5)  # the flood has settled
            running = start_agent("genuine", daemon.listen_port, key)
            await wait_for(lambda: daemon.agents.session("genuine") is not None, 5, "the genuine agent")
            assert answers and all(a.code == Code.BUSY and a.retry_after_s for a in answers)
            assert daemon.agents.pre_auth.busy_refusals > 0
        finally:
            if running is not None:
                await running.kill()
            for task in flood:
                task.cancel()
            await asyncio.gather(*flood, return_exceptions=True)


async def test_enrollment_above_the_rate_is_answered_busy(tmp_path: Path) -> None:
    key = bytes.fromhex(k := new_key())
    async with running_daemon(tmp_path, k, enroll_per_s=2.0, enroll_burst=3) as daemon:
        port = daemon.listen_port
        for i in range(3):
            stream, _ = await open_client("127.0.0.1", port, ClientHandshake(f"new-{i}", key))
            await stream.close()
        with pytest.raises(Refused) as caught:
            await open_client("127.0.0.1", port, ClientHandshake("new-3", key))
        busy = caught.value
        assert busy.code == Code.BUSY and busy.authenticated and busy.action == "retry"
        assert busy.retry_after_s is not None and 0.0 < busy.retry_after_s <= 1.0
        assert "new identities/s" in busy.message
        assert daemon.store.cid_of("new-3") is None
        # known identities are not enrollments: they rejoin at once
        stream, accepted = await open_client("127.0.0.1", port, ClientHandshake("new-0", key))
        assert accepted.cid == 1
        await stream.close()
        await asyncio.sleep(busy.retry_after_s)
        stream, accepted = await open_client("127.0.0.1", port, ClientHandshake("new-3", key))
        assert accepted.cid == 4
        await stream.close()


async def test_agent_sends_a_coded_close_before_dropping_a_daemon_that_sent_a_bad_frame() -> None:
    key = new_key()
    received: list[Close] = []

    async def bad_daemon(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        stream = FramedStream(reader, writer)
        with contextlib.suppress(Exception):
            server = ServerHandshake(lambda _: bytes.fromhex(key))
            await stream.send(server.on_hello((await stream.read_frame(5.0)).body))
            server.on_proof((await stream.read_frame(5.0)).body)
            stream.version = server.version
            await stream.send(server.accept(1, None, None))
            # a packet only an agent may send
            await stream.send(RequestCid(identity="x", protocol_version=2, client_nonce=auth.new_nonce()))
            for _ in range(20):
                frame = await stream.read_frame(5.0)
                if isinstance(frame.body, Close):
                    received.append(frame.body)
                    break
        writer.close()

    server = await asyncio.start_server(bad_daemon, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    config = AgentConfig(identity="careful", gcs_port=port, key_hex=key, reconnect_min_s=0.05)

    async def noop(_: object) -> None:
        return None

    link = DaemonLink(config, bytes.fromhex(key), noop, noop, noop, lambda: None, lambda: None)
    task = asyncio.create_task(link.run())
    try:
        await wait_for(lambda: received, 10, "the agent's close")
        assert received[0].code == Code.PROTOCOL_ERROR and received[0].reason == CloseReason.PROTOCOL_ERROR
        assert "bad frame from the daemon" in received[0].message
        assert link.stopped is None
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        server.close()


def test_only_a_refusal_after_the_proof_is_proved_and_it_covers_code_wait_and_text() -> None:
    key = bytes.fromhex(new_key())
    for after_proof in (False, True):
        server = ServerHandshake(lambda _: key)
        client = ClientHandshake("d", key)
        challenge = server.on_hello(client.hello())
        proof = client.on_challenge(challenge)
        if after_proof:
            server.on_proof(proof)
        answer = server.refusal(Code.BANNED, "banned by the operator")[0]
        assert isinstance(answer, ResponseCid)
        assert (answer.refusal_proof is not None) is after_proof
        if not after_proof:
            continue
        for tampered in (
            answer,
            answer.model_copy(update={"retry_after_s": 86_400.0}),
            answer.model_copy(update={"reason": "something else"}),
            answer.model_copy(update={"code": "unknown_identity"}),
        ):
            checker = ClientHandshake("d", key, nonce=client.client_nonce)
            checker.hello()
            checker.on_challenge(challenge)
            with pytest.raises(Refused) as caught:
                checker.on_answer(tampered)
            assert caught.value.authenticated is (tampered is answer)


def test_sources_are_addresses_and_ipv6_counts_per_64() -> None:
    assert source_of(("127.0.0.2", 5000)) == "127.0.0.2"
    assert source_of(("::ffff:10.0.0.7", 5000, 0, 0)) == "10.0.0.7"
    assert source_of(("2001:db8:1:2:aaaa::1", 1, 0, 0)) == source_of(("2001:db8:1:2:bbbb::9", 2, 0, 0))
    assert source_of(("2001:db8:1:2::1", 1, 0, 0)) == "2001:db8:1:2::/64"
    assert source_of(("2001:db8:1:3::1", 1, 0, 0)) != source_of(("2001:db8:1:2::1", 1, 0, 0))
    assert source_of(("fe80::1%eth0", 1, 0, 2)) == "fe80::/64"


async def test_agent_doctor_does_not_fall_back_to_v1_on_one_forged_answer(tmp_path: Path) -> None:
    """`agent doctor` treats a code-less version answer as the link does: unauthenticated, so v1 only
    after three in a row; one forged answer leaves the probe on v2 (and the report says which)."""
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon, FaultProxy(daemon.listen_port) as proxy:
        proxy.impersonate(V1_ANSWER)
        config = AgentConfig(identity="doctor-probe", gcs_port=proxy.port, key_hex=key)
        report = await diagnose(config, None, drift_interval_s=0, timeout=5)
        assert proxy.stats["forged"] == 1
        assert report.ok and "protocol v2," in report.render(), report.render()
        proxy.impersonate(V1_ANSWER, V1_ANSWER, V1_ANSWER)  # a v1 daemon answers every v2 hello so
        old = await handshake(config, "doctor-probe", 5.0)
        assert old.version == 1 and proxy.stats["forged"] == 4
