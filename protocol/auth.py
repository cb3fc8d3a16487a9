"""HMAC-SHA256 challenge-response used in the type 0/1 handshake (both directions).

The daemon's challenge nonce is fresh per connection, so a recorded handshake proves nothing
on a later connection; the agent's own nonce makes the daemon prove it holds the key too.
Keys are raw bytes; on disk they are hex strings (see ``docs/protocol.md``).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets

NONCE_BYTES = 16


def new_nonce() -> str:
    """A fresh random nonce as lowercase hex (32 characters)."""
    return secrets.token_hex(NONCE_BYTES)


def _mac(key: bytes, *parts: str) -> str:
    return hmac.new(key, "|".join(parts).encode("utf-8"), hashlib.sha256).hexdigest()


def agent_proof(key: bytes, identity: str, server_nonce: str, client_nonce: str) -> str:
    """What the agent sends in its second type-0 packet."""
    return _mac(key, "fleetgcs-agent-v1", identity, server_nonce, client_nonce)


def daemon_proof(key: bytes, identity: str, client_nonce: str, server_nonce: str) -> str:
    """What the daemon sends in its accepting type-1 packet."""
    return _mac(key, "fleetgcs-daemon-v1", identity, client_nonce, server_nonce)


def refusal_proof(
    key: bytes,
    identity: str,
    client_nonce: str,
    server_nonce: str,
    code: str,
    retry_after_s: float | None,
    reason: str,
) -> str:
    """What a version-2 daemon adds to a refusal once the agent proved its key (``refusal_proof``).

    It covers both nonces (fresh, this connection only), the code, the wait and the text, so an
    on-path party without the key can neither forge a final refusal nor stretch a genuine one's wait.
    """
    wait = "" if retry_after_s is None else f"{retry_after_s:.3f}"
    return _mac(key, "fleetgcs-refusal-v2", identity, client_nonce, server_nonce, code, wait, reason)


def proofs_equal(a: str, b: str) -> bool:
    """Constant-time comparison of two hex proofs."""
    return hmac.compare_digest(a.encode("ascii", "replace"), b.encode("ascii", "replace"))


def parse_key(text: str) -> bytes:
    """A key from its hex form; at least 16 bytes so it cannot be guessed."""
    try:
        key = bytes.fromhex(text.strip())
    except ValueError:
        raise ValueError("a key must be hex digits (generate one with `gcs keygen`)") from None
    if len(key) < 16:
        raise ValueError(f"a key must be at least 16 bytes (32 hex digits), got {len(key)} bytes")
    return key
