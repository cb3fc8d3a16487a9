"""Which key each agent identity must prove it holds (shared fleet key and/or per-agent keys)."""

from __future__ import annotations

import json
import os
import secrets
from pathlib import Path

from protocol.auth import parse_key


def load_or_create_key_file(path: Path) -> bytes:
    """Read a hex key file, creating it (mode 0600, 32 random bytes) when absent."""
    if not path.exists():
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as handle:
            handle.write(secrets.token_hex(32) + "\n")
    return parse_key(path.read_text())


class KeyRing:
    """Looks up the key for an identity: its own key if listed, else the fleet key (if allowed)."""

    def __init__(self, fleet_key: bytes | None, agent_keys: dict[str, bytes], allow_unlisted: bool) -> None:
        self._fleet_key = fleet_key
        self._agent_keys = agent_keys
        self._allow_unlisted = allow_unlisted

    @classmethod
    def from_files(
        cls, fleet_key: bytes | None, agent_keys_file: Path | None, allow_unlisted: bool
    ) -> KeyRing:
        agent_keys: dict[str, bytes] = {}
        if agent_keys_file is not None:
            document = json.loads(agent_keys_file.read_text())
            if not isinstance(document, dict):
                raise ValueError(f"{agent_keys_file}: expected a JSON object {{identity: hex key}}")
            for identity, text in document.items():
                try:
                    agent_keys[str(identity)] = parse_key(str(text))
                except ValueError as exc:
                    raise ValueError(f"{agent_keys_file}: key of {identity!r}: {exc}") from None
        return cls(fleet_key, agent_keys, allow_unlisted)

    def key_for(self, identity: str) -> bytes | None:
        """The key ``identity`` must prove, or None when it may not join at all."""
        if identity in self._agent_keys:
            return self._agent_keys[identity]
        if self._allow_unlisted or not self._agent_keys:
            return self._fleet_key
        return None
