"""`gcs serve`: run the daemon (agent TCP listener + HTTP API) until SIGINT/SIGTERM."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import errno
import logging
import signal
import socket
import sys
from collections.abc import Coroutine
from pathlib import Path
from typing import Any

from gcs.core.config import DaemonConfig, default_data_dir
from gcs.core.config_file import ConfigFileError, load_daemon_config
from gcs.core.daemon import serve_forever
from gcs.link.keys import KeyFileError
from gcs.storage.store import StoreError
from protocol.settings_file import LoggingConfig, configure_logging


def split_host_port(text: str, default_port: int) -> tuple[str, int]:
    """'HOST:PORT', 'HOST' or ':PORT' -> (host, port); IPv6 as [::1]:PORT."""
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, default_port
    host = host.strip("[]") or "127.0.0.1"
    try:
        return host, int(port)
    except ValueError:
        raise argparse.ArgumentTypeError(f"bad port in {text!r}") from None


def add_daemon_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--listen", default="127.0.0.1:4396", help="agent listener HOST:PORT (default %(default)s)"
    )
    parser.add_argument(
        "--http", default="127.0.0.1:8080", help="HTTP API HOST:PORT, or 'none' (default %(default)s)"
    )
    parser.add_argument("--data-dir", type=Path, default=default_data_dir(), help="database, keys, API token")
    parser.add_argument("--agent-keys", type=Path, help="JSON file {identity: hex key} of per-agent keys")
    parser.add_argument("--status-period", type=float, default=0.5, help="agent status period, s")
    parser.add_argument("--lost-after", type=float, default=6.0, help="status periods of silence = lost")
    parser.add_argument("--tls-cert", type=Path, help="PEM certificate: serve the agent link over TLS")
    parser.add_argument("--tls-key", type=Path, help="PEM private key of --tls-cert")
    parser.add_argument(
        "--tls-client-ca", type=Path, help="PEM CA: require agent certificates it signed (mTLS)"
    )
    parser.add_argument(
        "--cluster",
        default="",
        metavar="nats://HOST:PORT[,...]",
        help="share the fleet with other daemons through these NATS JetStream servers (docs/cluster.md)",
    )
    parser.add_argument("--daemon-id", help="this daemon's name in the cluster (default: hostname-pid)")


def config_from_args(args: argparse.Namespace) -> DaemonConfig:
    host, port = split_host_port(args.listen, 4396)
    http_host: str | None
    if args.http.lower() == "none":
        http_host, http_port = None, 0
    else:
        http_host, http_port = split_host_port(args.http, 8080)
    return DaemonConfig(
        listen_host=host,
        listen_port=port,
        http_host=http_host,
        http_port=http_port,
        data_dir=args.data_dir,
        agent_keys_file=args.agent_keys,
        status_period_s=args.status_period,
        lost_after_periods=args.lost_after,
        tls_cert=args.tls_cert,
        tls_key=args.tls_key,
        tls_client_ca=args.tls_client_ca,
        cluster=[url.strip() for url in (getattr(args, "cluster", "") or "").split(",") if url.strip()],
        daemon_id=getattr(args, "daemon_id", None),
    )


def run(args: argparse.Namespace) -> int:
    try:
        config, log = resolve_config(args)
    except (ConfigFileError, ValueError) as exc:
        print(f"gcs serve: {exc}", file=sys.stderr)
        return 2
    configure_logging(log, verbose=logging.getLogger().level == logging.DEBUG)
    busy = [
        f"{what} {host}:{port}"
        for what, host, port in (
            ("agent listener", config.listen_host, config.listen_port),
            ("HTTP API", config.http_host, config.http_port),
        )
        if host is not None and port and not port_free(host, port)
    ]
    if busy:
        print(
            f"gcs serve: {' and '.join(busy)}: address already in use "
            "(another `gcs serve` running? choose other ports with --listen / --http)",
            file=sys.stderr,
        )
        return 2
    try:
        return run_until_signalled(serve_forever(config, args.ready_file))
    except (StoreError, KeyFileError) as exc:
        print(f"gcs serve: cannot start: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"gcs serve: cannot start: {exc}", file=sys.stderr)
        return 2


def port_free(host: str, port: int) -> bool:
    """Whether a server could bind ``host:port`` now (checked first so the operator gets one line)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except OSError:
        return True  # let the server report the bad address itself
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as exc:
            return exc.errno != errno.EADDRINUSE
    return True


def resolve_config(args: argparse.Namespace) -> tuple[DaemonConfig, LoggingConfig]:
    """Defaults < --config file < FLEETGCS_* environment < flags given on the command line."""
    cli, defaults = config_from_args(args), config_from_args(args.parser_defaults)
    explicit = {
        name: getattr(cli, name)
        for name in cli.model_fields_set
        if getattr(cli, name) != getattr(defaults, name)
    }
    config, log = load_daemon_config(args.config, explicit)
    changes: dict[str, object] = {}
    if getattr(args, "new_database", False):
        changes["new_database"] = True
    if getattr(args, "no_enrollment", False):
        changes["enroll_new_agents"] = False
    if changes:
        config = config.model_copy(update=changes)
    updates = {"json_format": True} if args.log_json else {}
    if args.log_file is not None:
        updates["file"] = args.log_file
    return config, log.model_copy(update=updates)


SHUTDOWN_DRAIN_S = 5.0


def run_until_signalled(coroutine: Coroutine[Any, Any, None]) -> int:
    """Run ``coroutine`` until SIGINT/SIGTERM, then cancel it (its cleanup runs) and let the tasks
    it leaves (agent connections being closed) end by themselves, bounded.

    Cancelling everything at once, as ``asyncio.run`` does on Ctrl-C, cancels the connection
    handlers while the daemon is still closing them, and asyncio logs a traceback for each.
    """

    async def main() -> None:
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        work = asyncio.ensure_future(coroutine)
        stopper = asyncio.ensure_future(stop.wait())
        await asyncio.wait([work, stopper], return_when=asyncio.FIRST_COMPLETED)
        stopper.cancel()
        if work.done():
            work.result()  # the daemon ended by itself: raise what ended it
        work.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await work
        others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        if others:
            await asyncio.wait(others, timeout=SHUTDOWN_DRAIN_S)

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(main())
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("serve", help="run the ground station daemon")
    add_daemon_arguments(parser)
    parser.add_argument("--ready-file", type=Path, help="write 'AGENT_PORT HTTP_PORT' here once listening")
    parser.add_argument("--config", type=Path, help="TOML configuration file (docs/configuration.md)")
    parser.add_argument("--log-json", action="store_true", help="log one JSON object per line")
    parser.add_argument("--log-file", type=Path, help="log to this file, rotated at 10 MiB (5 kept)")
    parser.add_argument(
        "--new-fleet",
        "--new-database",
        dest="new_database",
        action="store_true",
        help="begin a new fleet where the database went missing or is empty (zero bytes); "
        "connection IDs are assigned anew",
    )
    parser.add_argument(
        "--no-enrollment",
        action="store_true",
        help="only identities the database already knows may join (with per-agent keys: see gcs keygen)",
    )
    parser.set_defaults(run=run, parser_defaults=parser.parse_args([]))
