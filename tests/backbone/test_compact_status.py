"""Negotiating the compact status body over real TCP; v1 (JSON-only) agents keep working."""

from __future__ import annotations

from pathlib import Path

from gcs.daemon import Daemon
from protocol import auth
from protocol.packets import (
    PROTOCOL_VERSION,
    Close,
    CloseReason,
    Position,
    RequestCid,
    ResponseCid,
    StatusReport,
)
from protocol.wire import encode
from tests.backbone.helpers import new_key, running_daemon, start_agent, stop_agents, wait_for
from tests.backbone.test_handshake_and_abuse import RawClient


async def _handshake(client: RawClient, identity: str, key_hex: str, offer: bool | None) -> ResponseCid:
    nonce = auth.new_nonce()
    await client.send(RequestCid(identity=identity, protocol_version=PROTOCOL_VERSION, client_nonce=nonce))
    challenge = await client.receive()
    assert challenge is not None and isinstance(challenge.body, ResponseCid)
    proof = auth.agent_proof(bytes.fromhex(key_hex), identity, challenge.body.server_nonce or "", nonce)
    await client.send(
        RequestCid(
            identity=identity,
            protocol_version=PROTOCOL_VERSION,
            client_nonce=nonce,
            proof=proof,
            compact_status=offer,
        )
    )
    answer = await client.receive()
    assert answer is not None and isinstance(answer.body, ResponseCid)
    assert answer.body.outcome == "accepted"
    return answer.body


async def _joined(daemon: Daemon, identity: str, key_hex: str, offer: bool | None) -> tuple[RawClient, bool]:
    """A raw client through the handshake; and whether the daemon accepted the compact body."""
    client = await RawClient.connect(daemon.listen_port)
    accepted = await _handshake(client, identity, key_hex, offer)
    if not offer:  # a v1 agent never sees the new field
        assert accepted.compact_status is None and b"compact_status" not in encode(accepted, 1)
    return client, accepted.compact_status is True


def _report(t: float) -> StatusReport:
    return StatusReport(
        time=t, position=Position(lat=47.3, lon=8.5, alt_rel=10.0, alt_amsl=500.0), mode="GUIDED"
    )


async def test_v1_agent_without_the_offer_gets_json_only_and_is_served(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        client, compact = await _joined(daemon, "old-1", key, None)
        assert not compact
        await client.send(_report(1.0))
        await wait_for(lambda: (s := daemon.agents.session("old-1")) and s.status, 5.0, "v1 status")
        session = daemon.agents.session("old-1")
        assert session is not None and session.status == _report(1.0) and not session.compact_status
        # It did not negotiate the compact body, so sending one is a protocol error for it alone.
        client.seq += 1
        await client.send_raw(encode(_report(2.0), client.seq, compact=True))
        bodies = await client.receive_all_until_closed()
        assert any(isinstance(b, Close) and b.reason is CloseReason.PROTOCOL_ERROR for b in bodies)
        client.close()


async def test_offered_compact_body_is_accepted_and_ingested(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        client, compact = await _joined(daemon, "new-1", key, True)
        assert compact
        client.seq += 1
        await client.send_raw(encode(_report(3.0), client.seq, compact=True))
        await wait_for(lambda: (s := daemon.agents.session("new-1")) and s.status, 5.0, "compact status")
        session = daemon.agents.session("new-1")
        assert session is not None and session.compact_status and session.status == _report(3.0)
        await client.send(_report(4.0))  # JSON stays valid on a compact session
        await wait_for(lambda: session.status == _report(4.0), 5.0, "JSON status on a compact session")
        client.close()


async def test_the_agent_negotiates_the_compact_body(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        agent = start_agent("drone-1", daemon.listen_port, key)
        try:
            await wait_for(lambda: agent.agent.link.compact_status, 10.0, "agent link negotiated")
            await wait_for(
                lambda: (s := daemon.agents.session("drone-1")) is not None and s.status_count >= 2,
                10.0,
                "compact status reports",
            )
            session = daemon.agents.session("drone-1")
            assert session is not None and session.compact_status
        finally:
            await stop_agents([agent])
