"""The release journal: a barrier release made durable with one ``write`` before anyone hears of it.

Why: a release must be stored before it is sent (an agent released by a daemon that then dies
must not be told to wait at that barrier again after the restart). Stored in SQLite, that meant
waiting for the write lock (the telemetry writer's row and commit) and a transaction on the
event loop before the first datagram went out: 0.4-1.7 ms at the median, several ms at p99 with
1,000 agents (docs/performance.md, round 7). The journal is one append of one line to a file
beside the database (``<database>-releases``): no lock, no transaction, durable across a
``kill -9`` like SQLite's own WAL at ``synchronous=NORMAL`` (the page cache survives the
process; a power cut may lose the newest lines of either). The release row and its event go into
SQLite right after the burst; a release journaled but not yet in the database is recovered when
the store opens (:meth:`gcs.storage.store.Store.recover_releases`), and only if the database agrees.

Line format, exactly as :meth:`ReleaseJournal.append` writes it (JSON without spaces)::

    {"m":"<mission id>","s":<step>,"t":<unix time>}

The journal is read as untrusted input (docs/security.md): a line is matched against that shape
with a regular expression of bounded length, never handed to a JSON parser, so a line nested
100,000 deep or a step of ``1e999`` is only a line that does not match. A line that does not
match (a torn last line after a power cut, a foreign or damaged one) is skipped with a warning
naming its line number; after :data:`WARN_LINES` such warnings the rest are counted into one
summary.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

TRUNCATE_AT_BYTES = 64 << 10
"""The journal is emptied once it is this long and every line in it is in the database."""

MAX_LINE_BYTES = 256
"""Longer lines are not parsed (the daemon's own lines are under 100 bytes)."""

MAX_JOURNAL_BYTES = 64 << 20
"""A journal longer than this is refused: the daemon's own stays near :data:`TRUNCATE_AT_BYTES`."""

MAX_STEP = 1_000_000
"""The largest step an action may have (``protocol/actions.py``)."""

MAX_TIME = 1e10
"""Release times past this (the year 2286) are not ones this daemon wrote."""

WARN_LINES = 10
"""Skipped lines warned about one by one; the rest are summed up in one warning."""

_LINE = re.compile(
    rb'\{"m":"(?P<m>[A-Za-z0-9_.:-]{1,128})",'
    rb'"s":(?P<s>0|[1-9][0-9]{0,6}),'
    rb'"t":(?P<t>[0-9]{1,11}(?:\.[0-9]{1,20})?(?:[eE][+-]?[0-9]{1,2})?)\}'
)


class JournalError(ValueError):
    """One journal line is not a release this daemon could have written (the reason is the text)."""


@dataclass(frozen=True, slots=True)
class JournalEntry:
    """One well-formed journal line: where it is (1-based) and the release it records."""

    line: int
    mission_id: str
    step: int
    at: float


_LINES = re.compile(rb"^" + _LINE.pattern + rb"\r?$", re.MULTILINE)
"""Every well-formed line of a whole journal, found in one pass of the regular expression engine."""


def parse_line(raw: bytes) -> tuple[str, int, float]:
    """(mission_id, step, time) of one journal line, or :class:`JournalError` saying why not.

    Bounded work whatever the input: a length check, then one anchored regular expression whose
    parts are all of bounded length; numbers are checked for range after conversion.
    """
    if len(raw) > MAX_LINE_BYTES:
        raise JournalError(f"{len(raw)} bytes, longer than any release line ({MAX_LINE_BYTES})")
    match = _LINE.fullmatch(raw.strip(b"\r"))
    if match is None:
        raise JournalError('not {"m":"<mission id>","s":<step>,"t":<time>}')
    step, at = _numbers(match)
    return match["m"].decode("ascii"), step, at


def _numbers(match: re.Match[bytes]) -> tuple[int, float]:
    """The step and time of a matched line, range-checked."""
    step = int(match["s"])
    if step > MAX_STEP:
        raise JournalError(f"step {step} is beyond the largest step {MAX_STEP}")
    at = float(match["t"])
    if not math.isfinite(at) or not 0.0 < at <= MAX_TIME:
        raise JournalError(f"time {match['t'].decode()} is not a plausible UNIX time")
    return step, at


class SkipLog:
    """Warnings about skipped lines: the first :data:`WARN_LINES` one by one, then one summary."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.skipped = 0

    def skip(self, line: int, why: str) -> None:
        self.skipped += 1
        if self.skipped <= WARN_LINES:
            log.warning("release journal %s line %d skipped: %s", self.path, line, why)

    @property
    def full(self) -> bool:
        """No more lines will be named one by one (callers may just :meth:`count` them)."""
        return self.skipped >= WARN_LINES

    def count(self, lines: int) -> None:
        self.skipped += lines

    def summary(self) -> None:
        """One warning for the lines not warned about one by one (call once, at the end)."""
        if self.skipped > WARN_LINES:
            log.warning(
                "release journal %s: %d more lines skipped (%d in all; only the first %d are named)",
                self.path,
                self.skipped - WARN_LINES,
                self.skipped,
                WARN_LINES,
            )


def _scan(text: bytes, skips: SkipLog, missions: set[bytes] | None) -> list[JournalEntry]:
    """The well-formed lines of ``text`` (of ``missions``, when given); the others to ``skips``.

    The well-formed lines are found by one regular expression over the whole text (C speed:
    400,000 lines in well under a second), the lines between them are the malformed ones, parsed
    one by one only while they are still named in a warning.
    """
    out: list[JournalEntry] = []
    line, at = 1, 0  # ``at`` is the start of line number ``line``
    for match in _LINES.finditer(text):
        start = match.start()
        if start > at:
            _skip_malformed(text[at:start], line, skips)
            line += text.count(b"\n", at, start)
        at, number = match.end() + 1, line
        line += 1
        mission = match["m"]
        if missions is not None and mission not in missions:
            if skips.full:
                skips.count(1)  # the common case of a flood: no message built
            else:
                skips.skip(number, f"mission {mission.decode()} is not in the database")
            continue
        try:
            step, when = _numbers(match)
        except JournalError as exc:
            skips.skip(number, str(exc))
            continue
        out.append(JournalEntry(number, mission.decode("ascii"), step, when))
    if at < len(text):
        _skip_malformed(text[at:], line, skips)
    return out


def _skip_malformed(lines: bytes, first: int, skips: SkipLog) -> None:
    """Report every non-empty line of ``lines`` (line ``first`` onwards) as skipped."""
    split = lines.split(b"\n")
    for offset, raw in enumerate(split):
        if not raw:
            continue
        if skips.full:
            skips.count(sum(1 for rest in split[offset:] if rest))
            return
        try:
            parse_line(raw)
            why = "not a release line"  # unreachable: _LINES would have matched it
        except JournalError as exc:
            why = str(exc)
        skips.skip(first + offset, why)


class ReleaseJournal:
    """Append-only file of releases not yet known to be in the database."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
        self._size = os.fstat(self._fd).st_size
        self.unrecorded = 0  # lines appended whose database row has not been written yet

    def append(self, mission_id: str, step: int, at: float) -> None:
        """Make the release of ``step`` durable: one ``write`` of one line (atomic for an append)."""
        line = f'{{"m":{json.dumps(mission_id)},"s":{int(step)},"t":{float(at)!r}}}\n'.encode()
        os.write(self._fd, line)
        self._size += len(line)
        self.unrecorded += 1

    def recorded(self) -> None:
        """The newest appended release is in the database; empty the file once it is long and all are."""
        self.unrecorded = max(0, self.unrecorded - 1)
        if self.unrecorded == 0 and self._size >= TRUNCATE_AT_BYTES:
            self.clear()

    def entries(
        self, skips: SkipLog | None = None, missions: Collection[str] | None = None
    ) -> list[JournalEntry]:
        """Every well-formed line (of one of ``missions``, when given), in order; each other line is
        skipped and reported to ``skips`` (a fresh :class:`SkipLog`, its summary logged here, when
        none is given).

        Raises OSError when the file cannot be read, and :class:`JournalError` when it is longer
        than :data:`MAX_JOURNAL_BYTES` (not a journal this daemon wrote; refusing to start beats
        spending minutes on it or forgetting a release in it).
        """
        own = skips is None
        skipped = SkipLog(self.path) if skips is None else skips
        out: list[JournalEntry] = []
        try:
            handle = open(self.path, "rb")  # noqa: SIM115 - closed below, size checked first
        except FileNotFoundError:
            return out
        with handle:
            size = os.fstat(handle.fileno()).st_size
            if size > MAX_JOURNAL_BYTES:
                raise JournalError(
                    f"{size} bytes, far more than the daemon writes (it is emptied at {TRUNCATE_AT_BYTES}); "
                    "move it aside after checking the missions it names"
                )
            text = handle.read()
        out = _scan(text, skipped, None if missions is None else {m.encode() for m in missions})
        if own:
            skipped.summary()
        return out

    def clear(self) -> None:
        os.ftruncate(self._fd, 0)
        self._size = 0
        self.unrecorded = 0

    def set_aside(self) -> Path:
        """Copy the file to ``<journal>.rejected`` (replacing an older copy), then empty it: lines
        skipped at start-up stay there for the operator, but are not warned about again. Copied,
        not renamed, so a process appending to this file keeps appending to the journal."""
        aside = self.path.with_name(self.path.name + ".rejected")
        shutil.copyfile(self.path, aside)
        os.chmod(aside, 0o600)
        self.clear()
        return aside

    def close(self) -> None:
        os.close(self._fd)
