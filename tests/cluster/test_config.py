"""`--cluster` and the `cluster` settings: parsed from the CLI, TOML and environment; bad ones refused."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from gcs.cli import build_parser
from gcs.cluster.api import public_url
from gcs.cluster.leadership import settings_warnings
from gcs.commands.serve import resolve_config
from gcs.core.config_file import ConfigFileError, load_daemon_config
from tests.support.processes import BIN


def test_cli_flag_splits_servers() -> None:
    args = build_parser().parse_args(
        ["serve", "--cluster", "nats://10.0.0.1:4222,nats://10.0.0.2:4222", "--daemon-id", "base-1"]
    )
    config, _ = resolve_config(args)
    assert config.cluster == ["nats://10.0.0.1:4222", "nats://10.0.0.2:4222"]
    assert config.daemon_id == "base-1"


def test_default_is_embedded() -> None:
    config, _ = resolve_config(build_parser().parse_args(["serve"]))
    assert config.cluster == [] and config.daemon_id is None


def test_toml_and_environment(tmp_path: Path) -> None:
    path = tmp_path / "gcs.toml"
    path.write_text('[daemon]\ncluster = ["nats://127.0.0.1:4222"]\ncluster_replicas = 3\n')
    config, _ = load_daemon_config(path, environ={"FLEETGCS_CLUSTER_LEASE_TTL_S": "2.5"})
    assert config.cluster == ["nats://127.0.0.1:4222"]
    assert config.cluster_replicas == 3 and config.cluster_lease_ttl_s == 2.5


@pytest.mark.parametrize("bad", ['cluster = ["http://x:1"]', 'daemon_id = "has space"'])
def test_bad_settings_refused(tmp_path: Path, bad: str) -> None:
    path = tmp_path / "gcs.toml"
    path.write_text(f"[daemon]\n{bad}\n")
    with pytest.raises(ConfigFileError):
        load_daemon_config(path, environ={})


def test_unreachable_nats_is_one_clear_line(tmp_path: Path) -> None:
    done = subprocess.run(
        [
            str(BIN / "gcs"),
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--http",
            "none",
            "--data-dir",
            str(tmp_path),
            "--cluster",
            "nats://127.0.0.1:1",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2, done.stderr
    assert "cannot reach NATS at nats://127.0.0.1:1" in done.stderr
    assert "Traceback" not in done.stderr


def test_agent_daemon_list() -> None:
    from pydantic import ValidationError

    from agent.config import AgentConfig

    config = AgentConfig(identity="d1", key_hex="00" * 32, gcs_port=4000, daemons=["10.0.0.2:4001", "base3"])
    assert config.daemon_addresses() == [("127.0.0.1", 4000), ("10.0.0.2", 4001), ("base3", 4000)]
    with pytest.raises(ValidationError, match="bad port"):
        AgentConfig(identity="d1", key_hex="00" * 32, daemons=["10.0.0.2:http"])


def test_cluster_lost_timeout_outlasts_the_agents_switch(tmp_path: Path) -> None:
    """Another daemon's agents are dropped only after their own daemon-silence switch plus a
    margin (derived by default); a shorter setting is refused with one line saying why."""
    from gcs.core.config import CLUSTER_LOST_MARGIN_S, DaemonConfig

    config = DaemonConfig(status_period_s=0.5, lost_after_periods=6.0)  # lost_after_s 3 s
    assert config.remote_lost_after_s == 5.0 + CLUSTER_LOST_MARGIN_S
    assert DaemonConfig(agent_daemon_silence_s=2.0, lost_after_periods=20.0).remote_lost_after_s == 10.0
    path = tmp_path / "gcs.toml"
    path.write_text("[daemon]\ncluster_lost_after_s = 3.0\n")
    with pytest.raises(ConfigFileError, match=r"cluster_lost_after_s \(3 s\) must be at least agent_daemon"):
        load_daemon_config(path, environ={})
    config, _ = load_daemon_config(path, environ={"FLEETGCS_AGENT_DAEMON_SILENCE_S": "1.0"})
    assert config.remote_lost_after_s == 3.0


def test_start_up_warns_of_settings_that_do_not_survive_a_node_loss() -> None:
    assert settings_warnings(1, 1, 3.0) == []  # one NATS server: nothing to replicate onto
    assert settings_warnings(3, 3, 8.0) == []  # the production settings (docs/cluster.md)
    (unreplicated,) = settings_warnings(3, 1, 8.0)
    assert "cluster_replicas is 1" in unreplicated and "set cluster_replicas = 3" in unreplicated
    (short,) = settings_warnings(3, 3, 3.0)
    assert "cluster_lease_ttl_s 3 s" in short and "8 s rides through" in short


def test_the_cluster_api_never_shows_nats_credentials() -> None:
    assert public_url("nats://fleet:s3cr@t@base1:4222") == "nats://base1:4222"
    assert public_url("tls://base2:4222") == "tls://base2:4222"
