"""Token buckets: the frame budgets of a served connection and the allowances counted before one is known.

Why a module of its own: the connection (live and replayed frame budgets), the session (exception
events per minute) and the pre-auth limits (enrollments per source) all count with it.
"""

from __future__ import annotations

import time


class RateLimited(Exception):
    """An authenticated peer sent frames faster than its allowance."""


class TokenBucket:
    """``rate`` tokens per second, at most ``burst`` saved up; one token per frame."""

    __slots__ = ("burst", "rate", "stamp", "tokens")

    def __init__(self, rate: float, burst: int) -> None:
        self.rate, self.burst = rate, float(burst)
        self.tokens = float(burst)
        self.stamp = time.monotonic()

    def take(self, now: float) -> bool:
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True

    def wait(self, now: float) -> float:
        """Seconds until the next token (0 if one is there)."""
        tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        return max(0.0, (1.0 - tokens) / self.rate)

    def refilled(self, now: float) -> bool:
        """Full again: nothing spent that still counts (the bucket can be forgotten)."""
        return self.tokens + (now - self.stamp) * self.rate >= self.burst
