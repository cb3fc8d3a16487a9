"""What the commands that talk to a running daemon share: options, the token, one-line errors."""

from __future__ import annotations

import argparse
import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TypeVar

import httpx

from gcs.core.config import default_data_dir
from gcs.http.client import ApiError, FleetClient

T = TypeVar("T")


class CommandError(Exception):
    """A failure the operator can act on: ``gcs`` prints the message on one line and exits ``code``."""

    def __init__(self, message: str, code: int = 2) -> None:
        super().__init__(message)
        self.code = code


def api_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--api", default="http://127.0.0.1:8080", help="daemon HTTP API (default %(default)s)"
    )
    parser.add_argument("--token", help="API token (default: read DATA_DIR/api.token)")
    parser.add_argument(
        "--data-dir",
        type=Path,
        default=default_data_dir(),
        help="where the daemon keeps api.token, read for --token (default %(default)s)",
    )


def api_token(args: argparse.Namespace) -> str:
    if args.token:
        return str(args.token)
    path = Path(args.data_dir) / "api.token"
    try:
        return path.read_text().strip()
    except OSError as exc:
        raise CommandError(f"no API token: cannot read {path}: {exc.strerror} (pass --token)") from None


def optional_token(args: argparse.Namespace) -> str | None:
    """The token when there is one: reads send it too (a daemon beyond loopback requires it)."""
    try:
        return api_token(args)
    except CommandError:
        return None


def unreachable(api: str, exc: Exception) -> CommandError:
    why = str(exc) or type(exc).__name__
    return CommandError(f"cannot reach the daemon at {api} ({why}); is `gcs serve` running?", 3)


def call(args: argparse.Namespace, request: Callable[[FleetClient], Awaitable[T]], token: bool = True) -> T:
    """Run one client call against ``--api``; unreachable daemon and refusals become CommandError."""

    async def go() -> T:
        key = api_token(args) if token else optional_token(args)
        async with FleetClient(args.api, key, timeout=15.0) as client:
            return await request(client)

    try:
        return asyncio.run(go())
    except httpx.TransportError as exc:
        raise unreachable(args.api, exc) from None
    except ApiError as exc:
        raise CommandError(f"{exc.title}: {exc.detail}") from None
