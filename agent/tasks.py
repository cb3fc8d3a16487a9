"""Stopping asyncio tasks reliably."""

from __future__ import annotations

import asyncio
import logging

log = logging.getLogger("agent")


async def cancel_and_wait(tasks: list[asyncio.Task[None]], timeout_s: float = 3.0) -> None:
    """Cancel ``tasks`` and wait for them, bounded, cancelling again any that ignored it.

    Python 3.11's ``asyncio.wait_for`` can swallow a cancellation that arrives as its inner
    await completes; a task caught that way would otherwise keep the agent from stopping.
    """
    deadline = asyncio.get_running_loop().time() + timeout_s
    while pending := [t for t in tasks if not t.done()]:
        left = deadline - asyncio.get_running_loop().time()
        if left <= 0:
            log.error("tasks did not stop: %s", ", ".join(t.get_name() for t in pending))
            return
        for task in pending:
            task.cancel()
        await asyncio.wait(pending, timeout=min(0.5, left))
