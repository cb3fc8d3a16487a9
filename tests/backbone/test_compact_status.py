"""Negotiating the compact status body (a v2 capability) over real TCP; JSON-only agents keep working."""

from __future__ import annotations

import time
from pathlib import Path

from gcs.core.daemon import Daemon
from protocol.packets import Close, CloseReason, Position, StatusReport
from protocol.session import Accepted, ClientHandshake
from protocol.stream import client_handshake
from protocol.wire import encode
from tests.backbone.helpers import new_key, running_daemon, start_agent, stop_agents
from tests.support.polling import wait_for
from tests.support.raw_client import RawClient


async def _joined(
    daemon: Daemon, identity: str, key_hex: str, offer: bool, versions: tuple[int, ...] = (1, 2)
) -> tuple[RawClient, Accepted]:
    """A raw client through the shared client handshake (session layer), offering compact or not."""
    client = await RawClient.connect(daemon.listen_port)
    handshake = ClientHandshake(identity, bytes.fromhex(key_hex), versions=versions, compact_status=offer)
    accepted = await client_handshake(client.stream, handshake, timeout=5.0)
    return client, accepted


T0 = time.time()  # report times near the daemon's clock (it refuses others)


def _report(t: float) -> StatusReport:
    return StatusReport(
        time=T0 + t, position=Position(lat=47.3, lon=8.5, alt_rel=10.0, alt_amsl=500.0), mode="GUIDED"
    )


async def test_json_only_sessions_are_served_and_an_unnegotiated_compact_body_is_an_error(
    tmp_path: Path,
) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        # A version-1 session never gets the capability, even when the agent would like it.
        old, accepted = await _joined(daemon, "old-1", key, True, versions=(1,))
        assert accepted.version == 1 and not accepted.compact_status
        await old.send(_report(1.0))
        await wait_for(lambda: (s := daemon.agents.session("old-1")) and s.status, 5.0, "v1 status")
        session = daemon.agents.session("old-1")
        assert session is not None and session.status == _report(1.0) and not session.compact_status
        old.close()
        # A v2 agent that did not offer it: sending one is a protocol error for it alone.
        plain, accepted = await _joined(daemon, "plain-1", key, False)
        assert accepted.version == 2 and not accepted.compact_status
        await plain.send_raw(encode(_report(2.0), plain.stream.seq + 1, 2, compact=True))
        bodies = await plain.receive_all_until_closed()
        assert any(isinstance(b, Close) and b.reason is CloseReason.PROTOCOL_ERROR for b in bodies)
        plain.close()


async def test_offered_compact_body_is_accepted_and_ingested(tmp_path: Path) -> None:
    key = new_key()
    async with running_daemon(tmp_path, key) as daemon:
        client, accepted = await _joined(daemon, "new-1", key, True)
        assert accepted.version == 2 and accepted.compact_status and client.stream.compact_status
        await client.send(_report(3.0))  # the stream now writes status as 0x82
        await wait_for(lambda: (s := daemon.agents.session("new-1")) and s.status, 5.0, "compact status")
        session = daemon.agents.session("new-1")
        assert session is not None and session.compact_status and session.status == _report(3.0)
        client.stream.compact_status = False
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
