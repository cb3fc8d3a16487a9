"""What one source address may hold or do before its agent is known: handshake slots and enrollments.

Why apart from admission: these limits are counted before the key is checked (a flood of silent
connections, a host minting identities), so they must stay cheap and self-contained.
"""

from __future__ import annotations

import time

from gcs.core.config import DaemonConfig
from gcs.link.rates import TokenBucket
from protocol.session import Code, Refused

BUSY_RETRY_S = 1.0
"""The wait a ``busy`` (handshake slots full) answer names: slots free up within a handshake."""
ENROLLMENT_SOURCES = 4096
"""Source addresses whose enrollment allowance is remembered; refilled ones are forgotten first."""


class PreAuthLimits:
    """What one source address may hold or do before it is known: handshake slots and enrollments.

    At most ``max_handshakes_per_source`` of the ``max_handshakes`` slots go to one source (an
    IPv6 /64), so one host holding silent connections cannot keep agents from other addresses
    out; its extra connections are answered ``busy`` with a short wait. New identities (a new
    CID) are limited to ``enroll_per_s`` per source with a burst of ``enroll_burst``.
    """

    def __init__(self, config: DaemonConfig) -> None:
        self.config = config
        self.pending = 0  # handshakes in progress, every source
        self.busy_refusals = 0
        self._held: dict[str, int] = {}  # handshakes in progress per source
        self._enrollments: dict[str, TokenBucket] = {}  # enrollment allowance per source

    def take_slot(self, source: str) -> None:
        """A handshake slot for a connection from ``source``, or Refused ``busy``."""
        per_source = self.config.max_handshakes_per_source
        held = self._held.get(source, 0)
        if held >= per_source:
            self.busy_refusals += 1
            raise Refused(
                Code.BUSY, f"{per_source} handshakes in progress from {source}; retry later", BUSY_RETRY_S
            )
        if self.pending >= self.config.max_handshakes:
            self.busy_refusals += 1
            raise Refused(
                Code.BUSY, f"{self.config.max_handshakes} handshakes in progress; retry later", BUSY_RETRY_S
            )
        self.pending += 1
        self._held[source] = held + 1

    def release_slot(self, source: str) -> None:
        self.pending -= 1
        held = self._held.get(source, 0) - 1
        if held > 0:
            self._held[source] = held
        else:
            self._held.pop(source, None)

    def enroll(self, source: str) -> None:
        """One new identity from ``source`` within the enrollment rate, or Refused ``busy`` with the wait."""
        now = time.monotonic()
        bucket = self._enrollments.get(source)
        if bucket is None:
            if len(self._enrollments) >= ENROLLMENT_SOURCES:  # forget sources whose allowance refilled
                for key in [k for k, b in self._enrollments.items() if b.refilled(now)]:
                    del self._enrollments[key]
                if len(self._enrollments) >= ENROLLMENT_SOURCES:
                    self._enrollments.clear()
            bucket = self._enrollments[source] = TokenBucket(
                self.config.enroll_per_s, self.config.enroll_burst
            )
        if not bucket.take(now):
            self.busy_refusals += 1
            raise Refused(
                Code.BUSY,
                f"more than {self.config.enroll_per_s:g} new identities/s (burst {self.config.enroll_burst}) "
                f"enrolled from {source}; retry later",
                round(bucket.wait(now) + 0.05, 2),
            )


__all__ = ["PreAuthLimits"]
