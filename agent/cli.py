"""`agent` command line: run the companion-computer agent beside one autopilot."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from agent.autopilot.base import Autopilot, LinkLost
from agent.config import AgentConfig
from agent.runtime import Agent
from protocol.settings_file import LoggingConfig, configure_logging, package_version


def split_host_port(text: str, default_port: int) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, default_port
    return host.strip("[]") or "127.0.0.1", int(port)


def make_autopilot(
    backend: str,
    connection: str,
    speedup: float,
    tlog: str | None = None,
    signing_key_file: str | None = None,
    mavlink_out: Sequence[str] = (),
) -> Autopilot:
    """The backend named on the command line. ``memory`` takes 'LAT,LON[,ALT]' as its connection."""
    if backend != "mavlink" and (tlog or signing_key_file or mavlink_out):
        raise SystemExit(
            "agent: --tlog, --mavlink-signing-key-file and --mavlink-out need --autopilot-backend mavlink"
        )
    if backend == "memory":
        from agent.autopilot.memory import MemoryAutopilot
        from agent.config_file import AutopilotSection

        default = AutopilotSection.model_fields["connection"].default
        given = connection if connection not in ("", "memory", default) else ""
        try:
            parts = [float(p) for p in given.split(",")] if given else []
        except ValueError:
            raise SystemExit(
                f"agent: the memory backend takes LAT,LON[,ALT] as its connection, not {connection!r}"
            ) from None
        home = (parts[0], parts[1], parts[2] if len(parts) > 2 else 0.0) if len(parts) >= 2 else None
        return MemoryAutopilot(home, speedup=speedup) if home else MemoryAutopilot(speedup=speedup)
    from agent.autopilot.factory import create_autopilot

    options: dict[str, object] = {}
    if backend == "mavlink":
        if tlog:
            options["tlog_path"] = tlog
        if signing_key_file:
            options["signing_key"] = Path(signing_key_file).read_text().strip()
        if mavlink_out:
            options["mavlink_out"] = list(mavlink_out)
    return create_autopilot(backend, connection, **options)


def read_key(args: argparse.Namespace) -> str:
    if args.key:
        return str(args.key)
    if os.environ.get("FLEETGCS_KEY"):
        return os.environ["FLEETGCS_KEY"]
    if args.key_file:
        return Path(args.key_file).read_text().strip()
    raise SystemExit("agent: give the key with --key-file, --key or FLEETGCS_KEY (see `gcs keygen`)")


def _flag(args: argparse.Namespace, name: str) -> object | None:
    """A flag's value when given on the command line, else None (`doctor` lacks some of them)."""
    return getattr(args, name, None)


def flag_overrides(args: argparse.Namespace) -> tuple[dict[str, object], dict[str, object]]:
    """The ([agent], [autopilot]) values set by command-line flags; only flags actually given.

    Flags default to None so that a flag equal to the built-in default still beats the file.
    """
    agent: dict[str, object] = {}
    autopilot: dict[str, object] = {}
    if args.id:
        agent["identity"] = args.id
    if args.gcs is not None:
        agent["gcs_host"], agent["gcs_port"] = split_host_port(args.gcs, 4396)
    if args.key or args.key_file:
        agent["key_hex"] = read_key(args)
    for flag, field in (
        ("release_beacon", "release_beacon"),
        ("tls_ca", "tls_ca"),
        ("tls_cert", "tls_cert"),
        ("tls_key", "tls_key"),
        ("tls_server_name", "tls_server_name"),
    ):
        if _flag(args, flag) is not None:
            agent[field] = _flag(args, flag)
    capabilities = {
        field: _flag(args, flag)
        for flag, field in (("max_speed", "max_speed_mps"), ("endurance", "endurance_s"))
        if _flag(args, flag) is not None
    }
    if capabilities:
        agent["capabilities"] = capabilities
    settings = {
        field: _flag(args, flag)
        for flag, field in (
            ("lost_link_timeout", "lost_link_timeout_s"),
            ("lost_link_action", "lost_link_action"),
        )
        if _flag(args, flag) is not None
    }
    if settings:
        agent["settings"] = settings
    for flag, field in (
        ("autopilot", "connection"),
        ("autopilot_backend", "backend"),
        ("speedup", "speedup"),
        ("tlog", "tlog"),
        ("mavlink_signing_key_file", "mavlink_signing_key_file"),
        ("mavlink_out", "mavlink_out"),
    ):
        if _flag(args, flag) is not None:
            autopilot[field] = _flag(args, flag)
    return agent, autopilot


def agent_from_args(args: argparse.Namespace) -> tuple[AgentConfig, Autopilot, LoggingConfig | None]:
    """The agent's configuration and autopilot: built-in defaults < --config FILE < FLEETGCS_AGENT_*
    / FLEETGCS_AUTOPILOT_* environment < command-line flags (docs/configuration.md)."""
    from agent.config_file import LOG_PREFIX, load_agent_config

    agent, autopilot = flag_overrides(args)
    try:
        loaded = load_agent_config(args.config, agent, autopilot)
    except ValueError as exc:
        text = str(exc)
        if args.config is None and "agent.identity" in text:
            raise SystemExit(
                f"agent {args.command}: give --id (or --config FILE with [agent] identity)"
            ) from None
        if args.config is None and "agent.key_hex" in text:
            read_key(args)  # raises the "give the key" message
        raise SystemExit(f"agent {args.command}: {text}") from None
    config = loaded.agent
    a = loaded.autopilot
    if "autopilot" not in config.capabilities.model_fields_set:
        capabilities = config.capabilities.model_copy(update={"autopilot": a.backend})
        config = config.model_copy(update={"capabilities": capabilities})
    pilot = make_autopilot(
        a.backend,
        a.connection,
        a.speedup,
        str(a.tlog) if a.tlog else None,
        str(a.mavlink_signing_key_file) if a.mavlink_signing_key_file else None,
        a.mavlink_out,
    )
    logging_set = args.config is not None or any(k.startswith(LOG_PREFIX) for k in os.environ)
    return config, pilot, loaded.log if logging_set else None


def run(args: argparse.Namespace) -> int:
    config, autopilot, log = agent_from_args(args)
    if log is not None:
        configure_logging(log, verbose=args.verbose)
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM stops like Ctrl-C
    try:
        with contextlib.suppress(KeyboardInterrupt):
            asyncio.run(Agent(config, autopilot).run())
    except LinkLost as exc:  # the autopilot could not be opened at all: say why in one line
        from agent.doctor import serial_hint

        hint = serial_hint(str(exc)) or "check it with `agent doctor`"
        print(f"agent run: {exc} ({hint})", file=sys.stderr)
        return 1
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="agent", description="fleetgcs companion-computer agent")
    parser.add_argument("-v", "--verbose", action="store_true")
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("run", help="connect an autopilot to the daemon")
    # Flags default to None: a flag given wins over --config and the environment, one left out does
    # not; the built-in defaults (in brackets) live in AgentConfig / AutopilotSection.
    p.add_argument("--gcs", help="daemon HOST:PORT [127.0.0.1:4396]")
    p.add_argument("--autopilot", help="MAVLink connection string [tcp:127.0.0.1:5760]")
    p.add_argument(
        "--autopilot-backend", choices=["mavlink", "mavsdk", "memory"], help="autopilot backend [mavlink]"
    )
    p.add_argument("--id", help="agent identity (unique in the fleet; required without --config)")
    p.add_argument("--key-file", help="file holding the hex key (fleet key or this agent's key)")
    p.add_argument("--key", help="hex key (prefer --key-file or FLEETGCS_KEY: argv is visible to all users)")
    p.add_argument("--max-speed", type=float, help="capability: max speed m/s [10]")
    p.add_argument("--endurance", type=float, help="capability: endurance s [1200]")
    p.add_argument("--lost-link-timeout", type=float, help="s without the daemon before the action [15]")
    p.add_argument("--lost-link-action", choices=["continue", "hold", "rtl", "land"], help="[continue]")
    p.add_argument("--speedup", type=float, help="memory backend only: time speed-up [1]")
    p.add_argument("--tlog", help="append the MAVLink traffic to this .tlog file (replay with MAVProxy)")
    p.add_argument("--mavlink-signing-key-file", help="MAVLink 2 signing key (64 hex digits or a passphrase)")
    p.add_argument(
        "--mavlink-out",
        action="append",
        metavar="SCHEME:HOST:PORT",
        help="another ground station sharing the autopilot link (repeatable): udp:HOST:PORT sends to a "
        "QGroundControl there, udpin:/tcpin:HOST:PORT listen; its commands count as the pilot's",
    )
    p.add_argument("--tls-ca", type=Path, help="PEM CA: connect to the daemon over TLS and verify it")
    p.add_argument("--tls-cert", type=Path, help="PEM client certificate (mutual TLS)")
    p.add_argument("--tls-key", type=Path, help="PEM private key of --tls-cert")
    p.add_argument("--tls-server-name", help="name in the daemon's certificate (default: the --gcs host)")
    p.add_argument(
        "--release-beacon",
        metavar="IPV4:PORT",
        help="listen for barrier releases broadcast by the daemon (e.g. 127.255.255.255:14650 on one "
        "host, the LAN's broadcast address on a field network); the TCP release still counts",
    )
    p.add_argument("--config", type=Path, help="TOML configuration file (docs/configuration.md)")
    p.set_defaults(run=run)
    d = sub.add_parser(
        "doctor",
        help="check the autopilot link, the daemon link (handshake with the key), time sync and clock drift",
        parents=[_shared(p)],
        conflict_handler="resolve",
    )
    d.add_argument("--skip-autopilot", action="store_true", help="check only the key and the daemon link")
    d.add_argument("--probe-identity", help="identity for the test handshake (default: the agent's own)")
    d.add_argument("--timeout", type=float, default=10.0, help="per-check timeout, s")
    d.add_argument("--drift-interval", type=float, default=3.0, help="s between two offset samples; 0 = skip")
    d.set_defaults(run=doctor)
    return parser


def _shared(run_parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """The connection options of `run`, reused by `doctor`."""
    shared = argparse.ArgumentParser(add_help=False)
    names: tuple[str, ...] = (
        "--gcs",
        "--autopilot",
        "--autopilot-backend",
        "--id",
        "--key-file",
        "--key",
        "--config",
        "--speedup",
    )
    names += (
        "--tls-ca",
        "--tls-cert",
        "--tls-key",
        "--tls-server-name",
        "--tlog",
        "--mavlink-signing-key-file",
        "--release-beacon",
    )
    for action in run_parser._actions:
        if action.option_strings and action.option_strings[0] in names:
            shared._add_action(action)
    return shared


def doctor(args: argparse.Namespace) -> int:
    """Run the checks of agent/doctor.py and print what is wrong."""
    from agent.doctor import diagnose

    # doctor checks links, not capabilities or failsafes: the file's or built-in values serve
    config, autopilot, _ = agent_from_args(args)
    report = asyncio.run(
        diagnose(
            config,
            None if args.skip_autopilot else autopilot,
            Path(args.key_file) if args.key_file else None,
            args.probe_identity,
            args.timeout,
            args.drift_interval,
        )
    )
    print(report.render())
    return 0 if report.ok else 1


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        return int(args.run(args))
    except KeyboardInterrupt:
        print(f"\nagent {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
