"""Which key each agent identity must prove it holds (shared fleet key and/or per-agent keys)."""

from __future__ import annotations

import json
import os
import secrets
from pathlib import Path

from protocol.auth import parse_key


class KeyFileError(ValueError):
    """A key file cannot be used (unreadable, not hex, too short): one line naming the file and why."""


def load_or_create_key_file(path: Path) -> bytes:
    """Read a hex key file, creating it (mode 0600, 32 random bytes) when absent."""
    try:
        if not path.exists():
            path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "w") as handle:
                handle.write(secrets.token_hex(32) + "\n")
        text = path.read_bytes()
    except OSError as exc:
        raise KeyFileError(f"cannot read the key file {path}: {exc.strerror or exc}") from None
    try:
        return parse_key(text.decode("ascii"))
    except (UnicodeDecodeError, ValueError) as exc:
        why = "not ASCII hex digits" if isinstance(exc, UnicodeDecodeError) else str(exc)
        raise KeyFileError(
            f"the key file {path} is unusable: {why}; restore it (every agent holds the same key), "
            "or move it aside to have a new one made (every agent then needs the new key)"
        ) from None


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
            try:
                document = json.loads(agent_keys_file.read_bytes())
            except (OSError, ValueError, RecursionError) as exc:
                raise KeyFileError(f"cannot read the agent keys file {agent_keys_file}: {exc}") from None
            if not isinstance(document, dict):
                raise KeyFileError(f"{agent_keys_file}: expected a JSON object {{identity: hex key}}")
            for identity, text in document.items():
                try:
                    agent_keys[str(identity)] = parse_key(str(text))
                except ValueError as exc:
                    raise KeyFileError(f"{agent_keys_file}: key of {identity!r}: {exc}") from None
        return cls(fleet_key, agent_keys, allow_unlisted)

    def key_for(self, identity: str) -> bytes | None:
        """The key ``identity`` must prove, or None when it may not join at all."""
        if identity in self._agent_keys:
            return self._agent_keys[identity]
        if self._allow_unlisted or not self._agent_keys:
            return self._fleet_key
        return None
