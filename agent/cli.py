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

from pydantic import ValidationError

from agent.autopilot.base import Autopilot, LinkLost
from agent.config import AgentConfig, AgentSettings
from agent.runtime import Agent
from protocol.packets import Capabilities
from protocol.settings_file import LoggingConfig, configure_logging, first_error, package_version


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
) -> Autopilot:
    """The backend named on the command line. ``memory`` takes 'LAT,LON[,ALT]' as its connection."""
    if backend == "memory":
        from agent.autopilot.memory import MemoryAutopilot

        parts = [float(p) for p in connection.split(",")] if connection and connection != "memory" else []
        home = (parts[0], parts[1], parts[2] if len(parts) > 2 else 0.0) if len(parts) >= 2 else None
        return MemoryAutopilot(home, speedup=speedup) if home else MemoryAutopilot(speedup=speedup)
    from agent.autopilot.factory import create_autopilot

    options: dict[str, object] = {}
    if backend == "mavlink":
        if tlog:
            options["tlog_path"] = tlog
        if signing_key_file:
            options["signing_key"] = Path(signing_key_file).read_text().strip()
    elif tlog or signing_key_file:
        raise SystemExit("agent: --tlog and --mavlink-signing-key-file need --autopilot-backend mavlink")
    return create_autopilot(backend, connection, **options)


def read_key(args: argparse.Namespace) -> str:
    if args.key:
        return str(args.key)
    if os.environ.get("FLEETGCS_KEY"):
        return os.environ["FLEETGCS_KEY"]
    if args.key_file:
        return Path(args.key_file).read_text().strip()
    raise SystemExit("agent: give the key with --key-file, --key or FLEETGCS_KEY (see `gcs keygen`)")


def config_from_file(args: argparse.Namespace) -> tuple[AgentConfig, Autopilot, LoggingConfig]:
    """--config FILE (+ FLEETGCS_AGENT_* environment); flags given on the command line win."""
    from agent.config_file import load_agent_config

    defaults = args.parser_defaults
    agent: dict[str, object] = {}
    if args.id:
        agent["identity"] = args.id
    if args.gcs != defaults.gcs:
        agent["gcs_host"], agent["gcs_port"] = split_host_port(args.gcs, 4396)
    if args.key or args.key_file:
        agent["key_hex"] = read_key(args)
    if args.release_beacon:
        agent["release_beacon"] = args.release_beacon
    autopilot: dict[str, object] = {}
    if args.autopilot != defaults.autopilot:
        autopilot["connection"] = args.autopilot
    if args.autopilot_backend != defaults.autopilot_backend:
        autopilot["backend"] = args.autopilot_backend
    try:
        loaded = load_agent_config(args.config, agent, autopilot)
    except ValueError as exc:
        raise SystemExit(f"agent: {exc}") from None
    a = loaded.autopilot
    pilot = make_autopilot(
        a.backend,
        a.connection,
        a.speedup,
        str(a.tlog) if a.tlog else None,
        str(a.mavlink_signing_key_file) if a.mavlink_signing_key_file else None,
    )
    return loaded.agent, pilot, loaded.log


def agent_from_args(args: argparse.Namespace) -> tuple[AgentConfig, Autopilot, LoggingConfig | None]:
    """The agent's configuration and autopilot, from --config FILE or from the flags alone."""
    if args.config is not None:
        return config_from_file(args)
    if not args.id:
        raise SystemExit(f"agent {args.command}: give --id (or --config FILE with [agent] identity)")
    host, port = split_host_port(args.gcs, 4396)
    try:
        config = AgentConfig(
            identity=args.id,
            gcs_host=host,
            gcs_port=port,
            key_hex=read_key(args),
            capabilities=Capabilities(
                max_speed_mps=args.max_speed, endurance_s=args.endurance, autopilot=args.autopilot_backend
            ),
            tls_ca=args.tls_ca,
            tls_cert=args.tls_cert,
            tls_key=args.tls_key,
            tls_server_name=args.tls_server_name,
            settings=AgentSettings(
                lost_link_timeout_s=args.lost_link_timeout, lost_link_action=args.lost_link_action
            ),
            release_beacon=args.release_beacon,
        )
    except ValidationError as exc:
        raise SystemExit(f"agent {args.command}: {first_error(exc, 'agent')}") from None
    autopilot = make_autopilot(
        args.autopilot_backend, args.autopilot, args.speedup, args.tlog, args.mavlink_signing_key_file
    )
    return config, autopilot, None


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
    p.add_argument("--gcs", default="127.0.0.1:4396", help="daemon HOST:PORT (default %(default)s)")
    p.add_argument("--autopilot", default="tcp:127.0.0.1:5760", help="MAVLink connection string")
    p.add_argument("--autopilot-backend", default="mavlink", choices=["mavlink", "mavsdk", "memory"])
    p.add_argument("--id", help="agent identity (unique in the fleet; required without --config)")
    p.add_argument("--key-file", help="file holding the hex key (fleet key or this agent's key)")
    p.add_argument("--key", help="hex key (prefer --key-file or FLEETGCS_KEY: argv is visible to all users)")
    p.add_argument("--max-speed", type=float, default=10.0, help="capability: max speed m/s")
    p.add_argument("--endurance", type=float, default=1200.0, help="capability: endurance s")
    p.add_argument("--lost-link-timeout", type=float, default=15.0)
    p.add_argument("--lost-link-action", default="continue", choices=["continue", "hold", "rtl", "land"])
    p.add_argument("--speedup", type=float, default=1.0, help="memory backend only: time speed-up")
    p.add_argument("--tlog", help="append the MAVLink traffic to this .tlog file (replay with MAVProxy)")
    p.add_argument("--mavlink-signing-key-file", help="MAVLink 2 signing key (64 hex digits or a passphrase)")
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
    p.set_defaults(parser_defaults=argparse.Namespace(**{a.dest: a.default for a in p._actions}))
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
    d.set_defaults(run=doctor, parser_defaults=argparse.Namespace(**{a.dest: a.default for a in p._actions}))
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

    # doctor checks links, not capabilities or failsafes: the run defaults serve
    args.max_speed, args.endurance = 10.0, 1200.0
    args.lost_link_timeout, args.lost_link_action = 15.0, "continue"
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
