"""When this daemon decided, and under which lease term: the evidence for "one decider at a time".

The airspace decider (the holder of the ``airspace`` lease) and each mission's leader decide only
while their lease is good by their own clock (gcs/cluster/fencing.py). To check that two daemons
never decided at once, each one records its decisions as spans: the kind (``airspace``, or
``mission:<id>``), the scope (``fleet``, or ``local`` when cut off from NATS), the lease term (the
lease's fencing token), the first and last decision of the span by ``time.monotonic()`` (one clock
for every process of a host, so two daemons' spans on one host compare directly) and by wall
time. A span closes when the term or scope changes, after a gap, or after ``SPAN_S``; it is
appended to ``cluster-decisions.jsonl`` in the data directory (kept under ``MAX_BYTES``, the
previous file as ``.1``). tests/cluster/test_one_decider.py reads both daemons' files.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger("gcs.cluster")

FILE_NAME = "cluster-decisions.jsonl"
SPAN_S = 1.0  # a span is written at least this often while decisions go on
GAP_S = 1.0  # decisions further apart than this are separate spans
MAX_BYTES = 8 << 20


@dataclass
class Span:
    scope: str
    term: int
    first: float  # time.monotonic()
    last: float


class DecisionLog:
    """Spans of decisions of one daemon, appended to ``path`` (None: kept nowhere)."""

    def __init__(self, path: Path | None, daemon_id: str) -> None:
        self.path = path
        self.daemon_id = daemon_id
        self._open: dict[str, Span] = {}

    def note(self, kind: str, scope: str, term: int) -> None:
        """One decision of ``kind`` now, in ``scope``, under lease term ``term``."""
        now = time.monotonic()
        span = self._open.get(kind)
        same = span is not None and (span.scope, span.term) == (scope, term)
        if span is not None and same and now - span.last <= GAP_S and now - span.first < SPAN_S:
            span.last = now
            return
        if span is not None:
            self._write(kind, span)
        self._open[kind] = Span(scope, term, now, now)

    def close(self) -> None:
        for kind, span in list(self._open.items()):
            self._write(kind, span)
        self._open.clear()

    def _write(self, kind: str, span: Span) -> None:
        if self.path is None:
            return
        offset = time.time() - time.monotonic()
        line = {
            "daemon": self.daemon_id,
            "kind": kind,
            "scope": span.scope,
            "term": span.term,
            "first": round(span.first, 6),
            "last": round(span.last, 6),
            "first_wall": round(span.first + offset, 6),
            "last_wall": round(span.last + offset, 6),
        }
        try:
            with contextlib.suppress(FileNotFoundError):
                if self.path.stat().st_size > MAX_BYTES:
                    self.path.replace(self.path.with_suffix(".jsonl.1"))
            with self.path.open("a") as out:
                out.write(json.dumps(line, separators=(",", ":")) + "\n")
        except OSError as exc:  # a full disk must not stop the decider
            log.warning("decision log %s: %r", self.path, exc)


def read_spans(path: Path) -> list[dict[str, Any]]:
    """The spans a daemon wrote (its older file first), for tests and the bench."""
    spans: list[dict[str, Any]] = []
    for file in (path.with_suffix(".jsonl.1"), path):
        if file.exists():
            spans += [json.loads(line) for line in file.read_text().splitlines() if line.strip()]
    return spans


def overlaps(
    spans: list[dict[str, Any]], prefix: str = "airspace"
) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """Pairs of spans of one kind (starting with ``prefix``: "airspace", "mission:") written by
    different daemons that overlap in time: none, if one daemon decided at a time."""
    chosen = [s for s in spans if str(s["kind"]).startswith(prefix)]
    found = []
    for i, a in enumerate(chosen):
        for b in chosen[i + 1 :]:
            if (
                a["daemon"] != b["daemon"]
                and a["kind"] == b["kind"]
                and a["first"] <= b["last"]
                and b["first"] <= a["last"]
            ):
                found.append((a, b))
    return found
