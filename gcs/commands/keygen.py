"""`gcs keygen`: print a new random key (hex) for the fleet key or a per-agent key."""

from __future__ import annotations

import argparse
import secrets


def run(args: argparse.Namespace) -> int:
    print(secrets.token_hex(args.bytes))
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("keygen", help="print a new random agent/fleet key")
    parser.add_argument("--bytes", type=int, default=32, choices=range(16, 65), metavar="16..64")
    parser.set_defaults(run=run)
