"""The agent's daemon list: a dead first address is skipped, a dying daemon is left for the next one."""

from __future__ import annotations

from pathlib import Path

from gcs.cluster.natsrun import free_port
from gcs.core.daemon import Daemon
from tests.backbone.helpers import daemon_config, new_key, running_daemon, start_agent, stop_agents
from tests.support.polling import wait_for


async def test_link_moves_to_the_next_daemon(tmp_path: Path) -> None:
    key = new_key()
    dead = free_port()  # nothing listens there
    first = Daemon(daemon_config(tmp_path / "one", key))
    await first.start()
    stopped = False
    try:
        async with running_daemon(tmp_path / "two", key) as second:
            addresses = [f"127.0.0.1:{first.listen_port}", f"127.0.0.1:{second.listen_port}"]
            agent = start_agent("r0", dead, key, 0, daemons=addresses)
            try:
                await wait_for(lambda: first.agents.session("r0") is not None, 10, "join via the 2nd address")
                await wait_for(lambda: agent.agent.link.sessions == 1, 10, "the agent counts its session")
                sessions = agent.agent.link.sessions
                await first.stop()  # the daemon it is linked to goes away
                stopped = True
                await wait_for(lambda: second.agents.session("r0") is not None, 10, "move to the 3rd")
                # the daemon registers the session before the agent has read its acceptance
                await wait_for(lambda: agent.agent.link.sessions == sessions + 1, 10, "the agent's count")
            finally:
                await stop_agents([agent])
    finally:
        if not stopped:
            await first.stop()
