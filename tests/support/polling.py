"""Waiting for a condition in a test: one bounded poll for a plain predicate, one for an awaitable one.

Every wait has a deadline and fails the test naming what it waited for (issue 24: this was written
six times with small differences)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable


async def wait_for(predicate: Callable[[], object], timeout: float, what: str, poll: float = 0.02) -> None:
    """Poll ``predicate`` until true; fail with ``what`` after ``timeout`` seconds (bounded loop)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        await asyncio.sleep(poll)
    raise AssertionError(f"timed out after {timeout:.1f} s waiting for {what}")


async def wait_until(
    predicate: Callable[[], Awaitable[object]], timeout: float, what: str, poll: float = 0.1
) -> None:
    """``wait_for`` for a predicate that must be awaited (a page query, an HTTP read)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if await predicate():
            return
        await asyncio.sleep(poll)
    raise AssertionError(f"timed out after {timeout:.1f} s waiting for {what}")
