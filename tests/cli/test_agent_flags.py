"""`agent run`: every flag merges with --config FILE and the FLEETGCS_AGENT_* environment.

Order, lowest first: built-in defaults < the file < the environment < flags given on the command
line (issue 23: with --config, seven flags were silently dropped, and the environment only applied
with --config). No daemon or autopilot is contacted: the backends are built without I/O.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from agent.cli import agent_from_args, build_parser
from agent.config import AgentConfig

KEY = "ab" * 32


def _load(argv: list[str]) -> tuple[AgentConfig, Any]:
    config, autopilot, _ = agent_from_args(build_parser().parse_args(["run", *argv]))
    return config, autopilot


@pytest.fixture
def config_file(tmp_path: Path) -> Path:
    """A file that sets every option to something no flag below uses."""
    (tmp_path / "file.tlog").write_text("")
    (tmp_path / "file.sign").write_text("file-passphrase")
    path = tmp_path / "agent.toml"
    path.write_text(
        f"""
[agent]
identity = "from-file"
gcs_host = "10.1.1.1"
gcs_port = 4000
key_hex = "{"cd" * 32}"
release_beacon = "10.1.1.255:1000"
tls_server_name = "file-name"
[agent.capabilities]
max_speed_mps = 7
endurance_s = 700
[agent.settings]
battery_low_pct = 33
lost_link_timeout_s = 33
lost_link_action = "land"
[autopilot]
backend = "memory"
connection = "1.0,2.0,3.0"
speedup = 3.0
"""
    )
    return path


# (flags, how to read the value from (config, autopilot), value) for every option of `agent run`.
def _options(tmp: Path) -> list[tuple[list[str], Any, object]]:
    for name in ("ca.pem", "cert.pem", "key.pem"):
        (tmp / name).write_text("")
    (tmp / "flag.sign").write_text("flag-passphrase")
    return [
        (["--id", "from-flag"], lambda c, a: c.identity, "from-flag"),
        (["--gcs", "10.2.2.2:4111"], lambda c, a: (c.gcs_host, c.gcs_port), ("10.2.2.2", 4111)),
        (["--key", "ef" * 32], lambda c, a: c.key_hex, "ef" * 32),
        (["--max-speed", "12.5"], lambda c, a: c.capabilities.max_speed_mps, 12.5),
        (["--endurance", "900"], lambda c, a: c.capabilities.endurance_s, 900.0),
        (["--lost-link-timeout", "7"], lambda c, a: c.settings.lost_link_timeout_s, 7.0),
        (["--lost-link-action", "rtl"], lambda c, a: c.settings.lost_link_action, "rtl"),
        (["--release-beacon", "10.2.2.255:2000"], lambda c, a: c.release_beacon, "10.2.2.255:2000"),
        (["--tls-ca", str(tmp / "ca.pem")], lambda c, a: c.tls_ca, tmp / "ca.pem"),
        (["--tls-cert", str(tmp / "cert.pem")], lambda c, a: c.tls_cert, tmp / "cert.pem"),
        (["--tls-key", str(tmp / "key.pem")], lambda c, a: c.tls_key, tmp / "key.pem"),
        (["--tls-server-name", "flag-name"], lambda c, a: c.tls_server_name, "flag-name"),
        (["--autopilot", "4.0,5.0,6.0"], lambda c, a: a.telemetry().lat, 4.0),
        (["--speedup", "9"], lambda c, a: a.speedup, 9.0),
        (
            ["--autopilot-backend", "mavlink", "--autopilot", "udpin:127.0.0.1:1"],
            lambda c, a: (type(a).__name__, c.capabilities.autopilot),
            ("MavlinkAutopilot", "mavlink"),
        ),
        (
            ["--autopilot-backend", "mavlink", "--tlog", str(tmp / "flag.tlog")],
            lambda c, a: a.link._tlog_path,
            str(tmp / "flag.tlog"),
        ),
        (
            ["--autopilot-backend", "mavlink", "--mavlink-signing-key-file", str(tmp / "flag.sign")],
            lambda c, a: a.link._signing_key is not None,
            True,
        ),
        (
            [
                "--autopilot-backend",
                "mavlink",
                "--mavlink-out",
                "udp:127.0.0.1:14550",
                "--mavlink-out",
                "tcpin::5790",
            ],
            lambda c, a: [str(spec) for spec in a.link.router.specs],
            ["udp:127.0.0.1:14550", "tcpin:0.0.0.0:5790"],
        ),
    ]


def test_every_flag_wins_over_the_file(config_file: Path, tmp_path: Path) -> None:
    for flags, read, value in _options(tmp_path):
        config, autopilot = _load(["--config", str(config_file), *flags])
        assert read(config, autopilot) == value, flags
        assert config.settings.battery_low_pct == 33  # the rest of the file still applies


def test_every_flag_works_without_a_file(tmp_path: Path) -> None:
    base = ["--id", "d1", "--key", KEY, "--autopilot-backend", "memory", "--autopilot", "1.0,2.0,3.0"]
    for flags, read, value in _options(tmp_path):
        config, autopilot = _load([*base, *flags])
        assert read(config, autopilot) == value, flags


def test_the_issue_example_and_a_flag_equal_to_the_default(config_file: Path) -> None:
    config, _ = _load(["--config", str(config_file), "--lost-link-action", "rtl", "--lost-link-timeout", "7"])
    assert (config.settings.lost_link_action, config.settings.lost_link_timeout_s) == ("rtl", 7.0)
    # "continue" and 15 are the built-in defaults: given on the command line they still beat the file.
    config, _ = _load(
        ["--config", str(config_file), "--lost-link-action", "continue", "--lost-link-timeout", "15"]
    )
    assert (config.settings.lost_link_action, config.settings.lost_link_timeout_s) == ("continue", 15.0)
    config, autopilot = _load(["--config", str(config_file), "--max-speed", "10", "--speedup", "1"])
    assert config.capabilities.max_speed_mps == 10.0 and autopilot.speedup == 1.0


def test_file_values_apply_when_no_flag_is_given(config_file: Path) -> None:
    config, autopilot = _load(["--config", str(config_file)])
    assert (config.identity, config.gcs_host, config.gcs_port) == ("from-file", "10.1.1.1", 4000)
    assert (config.capabilities.max_speed_mps, config.capabilities.endurance_s) == (7.0, 700.0)
    assert (config.settings.lost_link_action, config.settings.lost_link_timeout_s) == ("land", 33.0)
    assert (config.release_beacon, config.tls_server_name) == ("10.1.1.255:1000", "file-name")
    assert autopilot.speedup == 3.0 and config.capabilities.autopilot == "memory"


def test_environment_applies_with_and_without_a_file(
    config_file: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("FLEETGCS_AGENT_SETTINGS__LOST_LINK_ACTION", "hold")
    monkeypatch.setenv("FLEETGCS_AGENT_CAPABILITIES__MAX_SPEED_MPS", "6")
    monkeypatch.setenv("FLEETGCS_AUTOPILOT_SPEEDUP", "4")
    plain = ["--id", "d1", "--key", KEY, "--autopilot-backend", "memory"]
    for argv in (plain, ["--config", str(config_file)]):
        config, autopilot = _load(argv)
        assert config.settings.lost_link_action == "hold", argv
        assert config.capabilities.max_speed_mps == 6.0 and autopilot.speedup == 4.0, argv
    # ... and flags beat the environment.
    config, autopilot = _load([*plain, "--lost-link-action", "rtl", "--max-speed", "8", "--speedup", "2"])
    assert config.settings.lost_link_action == "rtl" and config.capabilities.max_speed_mps == 8.0
    assert autopilot.speedup == 2.0
    monkeypatch.setenv("FLEETGCS_AGENT_IDENTITY", "env-id")
    assert _load(["--key", KEY, "--autopilot-backend", "memory"])[0].identity == "env-id"


def test_missing_identity_or_key_is_one_clear_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("FLEETGCS_KEY", raising=False)
    with pytest.raises(SystemExit, match="give --id"):
        _load(["--key", KEY, "--autopilot-backend", "memory"])
    with pytest.raises(SystemExit, match="give the key"):
        _load(["--id", "d1", "--autopilot-backend", "memory"])
    with pytest.raises(SystemExit, match=r"agent run: agent\.capabilities\.max_speed_mps"):
        _load(["--id", "d1", "--key", KEY, "--autopilot-backend", "memory", "--max-speed", "-1"])


def test_mavlink_out_from_the_environment_and_a_bad_one_is_one_clear_line(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("FLEETGCS_AUTOPILOT_MAVLINK_OUT", "udp:10.0.0.9:14550,udpin:0.0.0.0:14551")
    _, autopilot = _load(["--id", "d1", "--key", KEY, "--autopilot-backend", "mavlink"])
    assert [str(spec) for spec in autopilot.link.router.specs] == [
        "udp:10.0.0.9:14550",
        "udpin:0.0.0.0:14551",
    ]
    with pytest.raises(SystemExit, match=r"autopilot\.mavlink_out.*mavlink-out '10\.0\.0\.9:14550'"):
        _load(
            ["--id", "d1", "--key", KEY, "--autopilot-backend", "mavlink", "--mavlink-out", "10.0.0.9:14550"]
        )
    monkeypatch.delenv("FLEETGCS_AUTOPILOT_MAVLINK_OUT")
    with pytest.raises(SystemExit, match="need --autopilot-backend mavlink"):
        _load(["--id", "d1", "--key", KEY, "--autopilot-backend", "memory", "--mavlink-out", "udp:1.2.3.4:1"])
