"""Aggregates repeated identical events so that a persistent condition cannot bury the event log.

The first event of a key is published; repeats within ``window_s`` are counted, and the next one
after the window is published with the count ("... (37 similar in 10 s)").
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

Publish = Callable[[str, str, str, str | None, dict[str, Any]], None]  # kind, message, severity, agent, data


@dataclass
class _Seen:
    first: float
    suppressed: int = 0


class EventThrottle:
    def __init__(self, publish: Publish, window_s: float = 10.0, clock: Callable[[], float] = time.monotonic):
        self._publish = publish
        self.window_s = window_s
        self._clock = clock
        self._seen: dict[tuple[str, str | None, str], _Seen] = {}
        self.suppressed_total = 0

    def publish(
        self,
        kind: str,
        message: str,
        severity: str = "info",
        agent: str | None = None,
        data: dict[str, Any] | None = None,
        key: str | None = None,
    ) -> bool:
        """Publish unless an identical event (same kind, agent and key/message) went out recently."""
        now = self._clock()
        ident = (kind, agent, key if key is not None else message)
        seen = self._seen.get(ident)
        if seen is not None and now - seen.first < self.window_s:
            seen.suppressed += 1
            self.suppressed_total += 1
            return False
        payload = dict(data or {})
        if seen is not None and seen.suppressed:
            message = f"{message} ({seen.suppressed} similar in the last {now - seen.first:.0f} s)"
            payload["repeated"] = seen.suppressed
        self._seen[ident] = _Seen(now)
        if len(self._seen) > 4096:  # bounded: forget the oldest keys
            for old in sorted(self._seen, key=lambda k: self._seen[k].first)[:1024]:
                del self._seen[old]
        self._publish(kind, message, severity, agent, payload)
        return True
