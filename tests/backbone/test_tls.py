"""Optional TLS and mutual TLS on the agent link, with certificates made for the test."""

from __future__ import annotations

import asyncio
from pathlib import Path

from tests.backbone.helpers import new_key, running_daemon, start_agent, stop_agents
from tests.support.pki import make_pki
from tests.support.polling import wait_for


async def test_agent_joins_over_tls_and_plain_tcp_is_refused(tmp_path: Path) -> None:
    pki = make_pki(tmp_path)
    key = new_key()
    async with running_daemon(
        tmp_path, key, tls_cert=pki["server_cert"], tls_key=pki["server_key"]
    ) as daemon:
        running = start_agent("secure", daemon.listen_port, key, tls_ca=pki["ca"])
        plain = start_agent("plain", daemon.listen_port, key)
        try:
            await wait_for(lambda: daemon.agents.session("secure") is not None, 10, "TLS agent joins")
            await asyncio.sleep(0.5)
            assert daemon.agents.session("plain") is None
            assert plain.agent.link.sessions == 0
        finally:
            await stop_agents([running, plain])


async def test_mutual_tls_requires_a_client_certificate_from_the_fleet_ca(tmp_path: Path) -> None:
    pki = make_pki(tmp_path)
    key = new_key()
    overrides = {"tls_cert": pki["server_cert"], "tls_key": pki["server_key"], "tls_client_ca": pki["ca"]}
    async with running_daemon(tmp_path, key, **overrides) as daemon:
        good = start_agent("drone-1", daemon.listen_port, key)
        good.agent.link.config.tls_ca = pki["ca"]
        good.agent.link.config.tls_cert, good.agent.link.config.tls_key = (
            pki["client_cert"],
            pki["client_key"],
        )
        anonymous = start_agent("anonymous", daemon.listen_port, key, index=1)
        anonymous.agent.link.config.tls_ca = pki["ca"]
        impostor = start_agent("impostor", daemon.listen_port, key, index=2)
        impostor.agent.link.config.tls_ca = pki["ca"]
        impostor.agent.link.config.tls_cert = pki["impostor_cert"]
        impostor.agent.link.config.tls_key = pki["impostor_key"]
        try:
            await wait_for(lambda: daemon.agents.session("drone-1") is not None, 10, "certified agent joins")
            await wait_for(lambda: anonymous.agent.link.last_error is not None, 5, "anonymous agent fails")
            await wait_for(lambda: impostor.agent.link.last_error is not None, 5, "impostor fails")
            assert daemon.agents.session("anonymous") is None and daemon.agents.session("impostor") is None
        finally:
            await stop_agents([good, anonymous, impostor])


async def test_a_client_certificate_logs_in_only_as_its_own_identity(tmp_path: Path) -> None:
    """drone-1's certificate, with the fleet key, cannot log in as drone-2 (code certificate_mismatch)."""
    pki = make_pki(tmp_path)
    key = new_key()
    overrides = {"tls_cert": pki["server_cert"], "tls_key": pki["server_key"], "tls_client_ca": pki["ca"]}
    tls = {"tls_ca": pki["ca"], "tls_cert": pki["client_cert"], "tls_key": pki["client_key"]}
    async with running_daemon(tmp_path, key, **overrides) as daemon:
        own = start_agent("drone-1", daemon.listen_port, key, **tls)
        other = start_agent("drone-2", daemon.listen_port, key, index=1, **tls)
        try:
            await wait_for(lambda: daemon.agents.session("drone-1") is not None, 10, "drone-1 joins")
            await wait_for(lambda: other.agent.link.stopped is not None, 10, "drone-2 refused for good")
            assert other.agent.link.last_code == "certificate_mismatch"
            assert daemon.agents.session("drone-2") is None
        finally:
            await stop_agents([own, other])
