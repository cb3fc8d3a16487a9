"""`gcs keygen`: a new random key (hex) for the fleet, or per-agent keys added to an agent-keys file.

Per-agent keys are what a real fleet should use (docs/security.md): a key stolen from one
companion computer then opens one identity, not the fleet. ``gcs keygen --agent drone-1 --agent
drone-2 --agent-keys agents.json`` adds a key for each to the file (created 0600; identities
already in it keep their keys unless ``--rotate``) and prints ``identity key`` lines to copy to
each drone; start the daemon with ``--agent-keys agents.json --no-enrollment``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import secrets
import sys
from pathlib import Path

IDENTITY = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")


def _agent_keys(args: argparse.Namespace) -> int:
    path: Path | None = args.agent_keys
    keys: dict[str, str] = {}
    if path is not None and path.exists():
        try:
            document = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            print(f"gcs keygen: cannot read {path}: {exc}", file=sys.stderr)
            return 2
        if not isinstance(document, dict):
            print(f"gcs keygen: {path}: expected a JSON object {{identity: hex key}}", file=sys.stderr)
            return 2
        keys = {str(k): str(v) for k, v in document.items()}
    for identity in args.agent:
        if not IDENTITY.match(identity):
            print(
                f"gcs keygen: {identity!r} is not a valid identity (letters, digits, _ . -)", file=sys.stderr
            )
            return 2
        if identity not in keys or args.rotate:
            keys[identity] = secrets.token_hex(args.bytes)
        print(f"{identity} {keys[identity]}")
    if path is not None:
        temporary = path.with_name(path.name + ".tmp")
        fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as handle:
            json.dump(keys, handle, indent=2, sort_keys=True)
            handle.write("\n")
        temporary.replace(path)
    return 0


def run(args: argparse.Namespace) -> int:
    if args.agent:
        return _agent_keys(args)
    print(secrets.token_hex(args.bytes))
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("keygen", help="print a new fleet key, or issue per-agent keys")
    parser.add_argument(
        "--bytes", type=int, default=32, choices=range(16, 65), metavar="16..64", help="key length (32)"
    )
    parser.add_argument("--agent", action="append", default=[], help="issue a key for this identity (repeat)")
    parser.add_argument("--agent-keys", type=Path, help="add the keys to this JSON file (created 0600)")
    parser.add_argument("--rotate", action="store_true", help="replace the keys of identities already listed")
    parser.set_defaults(run=run)
