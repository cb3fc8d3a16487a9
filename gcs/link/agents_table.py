"""The fleet status table: every connected agent's latest status in preallocated arrays.

Why: at 10 Hz from thousands of agents, building a validated ``StatusReport`` (and a hook call
per service) for every report costs the event loop ~50 us a report. Here the ingest of a compact
status body (gcs/link/ingest.py, in the connection's ``buffer_updated``) checks the body's layout
(``status_binary.check_layout``: a few byte reads) and copies its bytes into the agent's row and
marks the row dirty; no Python object is made per report, and a row's variable part (mode,
mission) is always sound. Once per
status tick the agent manager takes the dirty rows, reads their fixed fields as NumPy columns
(:data:`ROW_DTYPE`, the little-endian layout of ``protocol.status_binary``) and turns only the
rows that are needed into reports (:meth:`report`).

Layout: one row of :data:`ROW_BYTES` bytes per agent slot; bytes ``[0, n)`` are the newest body
and the row's last byte is ``n`` (a body longer than :data:`MAX_BODY` takes the slow path). The
buffers are allocated for ``capacity`` rows and doubled when the fleet outgrows them; a slot is
reused after its agent leaves.
"""

from __future__ import annotations

import array
from typing import Any

import numpy as np

from gcs.link.status_limits import ImplausibleStatus, StatusLimits, plausible, refusal
from protocol import status_binary
from protocol.packets import StatusReport
from protocol.status_binary import StatusBodyError

ROW_BYTES = 256
MAX_BODY = ROW_BYTES - 1  # the last byte of a row holds the body length
_NUMPY_CODES = {"B": "u1", "i": "<i4", "I": "<u4", "d": "<f8"}
_FIELDS: list[tuple[str, str]] = [(name, _NUMPY_CODES[code]) for name, code in status_binary.FIXED_FIELDS]
FIXED_DTYPE: np.dtype[Any] = np.dtype(_FIELDS)
ROW_DTYPE: np.dtype[Any] = np.dtype(
    {  # type: ignore[call-overload]
        "names": [name for name, _ in status_binary.FIXED_FIELDS],
        "formats": [FIXED_DTYPE[name] for name, _ in status_binary.FIXED_FIELDS],
        "offsets": [FIXED_DTYPE.fields[name][1] for name, _ in status_binary.FIXED_FIELDS],  # type: ignore[index]
        "itemsize": ROW_BYTES,
    }
)
"""One table row read as the compact body's fixed fields (the rest of the row is skipped)."""
_OFFSET = {name: FIXED_DTYPE.fields[name][1] for name, _ in status_binary.FIXED_FIELDS}  # type: ignore[index]
STATE_BYTES: tuple[int, ...] = (
    _OFFSET["flags"],
    *range(_OFFSET["step"], _OFFSET["queue_depth"]),
    *range(_OFFSET["waiting_sync"], ROW_BYTES),
)
"""The row bytes whose change a state hook cares about: flags (armed, landed, paused, position,
link), step, completed step, waiting sync, then mode, mission and the body length."""
_STATE_INDEX = np.array(STATE_BYTES, dtype=np.intp)
assert FIXED_DTYPE.itemsize == status_binary.FIXED_SIZE


class StatusTable:
    """Rows of raw compact status bodies, one per agent slot, with a dirty mark and arrival time.

    The hot path writes ``buf``, ``dirty`` and ``rx`` directly (gcs/link/ingest.py ``FrameIngest.ingest``);
    everything else goes through the methods.
    """

    __slots__ = ("_free", "_used", "buf", "capacity", "dirty", "limits", "objects", "owners", "rx", "seen")

    def __init__(self, capacity: int = 64, limits: StatusLimits | None = None) -> None:
        self.capacity = max(1, capacity)
        self.limits = limits or StatusLimits()  # what a report must keep to be plausible
        self.buf = bytearray(self.capacity * ROW_BYTES)
        self.dirty = bytearray(self.capacity)  # 1: a report came since the last tick
        self.rx = array.array("d", bytes(8 * self.capacity))  # wall time the newest report arrived
        self.objects: list[StatusReport | None] = [None] * self.capacity  # decoded already (JSON, rare path)
        self.owners: list[Any] = [None] * self.capacity  # the session of each used row
        self.seen = bytearray(self.capacity * len(STATE_BYTES))  # state bytes of the last tick's report
        self._free: list[int] = []
        self._used = 0  # rows handed out so far (slots below it are used or on the free list)

    def __len__(self) -> int:
        return self._used - len(self._free)

    def attach(self, owner: object) -> int:
        """A row for a new session (cleared)."""
        if self._free:
            row = self._free.pop()
        else:
            if self._used == self.capacity:
                self._grow()
            row = self._used
            self._used += 1
        self.owners[row] = owner
        self.objects[row] = None
        self.dirty[row] = 0
        self.rx[row] = 0.0
        self.buf[row * ROW_BYTES + MAX_BODY] = 0
        width = len(STATE_BYTES)
        self.seen[row * width : (row + 1) * width] = bytes(width)  # its first report counts as a change
        return row

    def release(self, row: int) -> None:
        """The session of ``row`` ended: the slot is free for the next one."""
        if self.owners[row] is None:
            return
        self.owners[row] = None
        self.objects[row] = None
        self.dirty[row] = 0
        self._free.append(row)

    def _grow(self) -> None:
        """Double every buffer (new objects: views taken before stay valid on the old ones)."""
        old = self.capacity
        self.capacity = old * 2
        self.buf = self.buf + bytes(old * ROW_BYTES)
        self.dirty = self.dirty + bytes(old)
        self.rx = self.rx + array.array("d", bytes(8 * old))
        self.objects += [None] * old
        self.owners += [None] * old
        self.seen = self.seen + bytes(old * len(STATE_BYTES))

    def put(self, row: int, body: bytes, now: float) -> None:
        """Store a compact body (at most :data:`MAX_BODY` bytes, no tail) as the row's newest report;
        ``StatusBodyError`` if its layout is not sound (``status_binary.check_layout``, as the
        daemon's ingest checks it), so a row's variable part is always sound."""
        status_binary.check_layout(body)
        start = row * ROW_BYTES
        self.buf[start : start + len(body)] = body
        self.buf[start + MAX_BODY] = len(body)
        self.objects[row] = None
        self.dirty[row] = 1
        self.rx[row] = now

    def put_report(self, row: int, report: StatusReport, now: float) -> None:
        """Store a report that was decoded already (a JSON body): its object is kept, its fields too."""
        body = status_binary.encode(report)
        if len(body) > MAX_BODY or body[1] & status_binary.HAS_TAIL:
            cut = status_binary.FIXED_SIZE  # the columns only need the fixed part
            body = bytes((body[0], body[1] & ~status_binary.HAS_TAIL)) + body[2:cut] + b"\x00\x00"
        self.put(row, body, now)
        self.objects[row] = report

    def take_dirty(self) -> np.ndarray[Any, np.dtype[np.intp]]:
        """The rows with a report since the last call (ascending), their marks cleared."""
        marks = np.frombuffer(self.dirty, dtype=np.uint8)
        rows = np.flatnonzero(marks)
        marks[rows] = 0
        return rows

    def clean(self, row: int) -> None:
        """The row's newest report was handed over already (a rare packet flushed it)."""
        self.dirty[row] = 0

    def columns(self, rows: np.ndarray[Any, np.dtype[np.intp]] | None = None) -> np.ndarray[Any, Any]:
        """The fixed fields of ``rows`` (default: every row handed out) as a structured array: a copy
        of the whole rows (fancy indexing of a structured array would drop the bytes after the
        fixed fields, which hold mode and mission)."""
        raw = np.frombuffer(self.buf, dtype=np.uint8, count=self._used * ROW_BYTES).reshape(-1, ROW_BYTES)
        picked = raw.copy() if rows is None else raw[rows]
        return picked.view(ROW_DTYPE).reshape(-1)

    @staticmethod
    def pick(cols: np.ndarray[Any, Any], keep: list[int]) -> np.ndarray[Any, Any]:
        """Rows ``keep`` of ``cols`` (``ROW_DTYPE``), whole: indexing the structured array itself
        would copy only its fields and drop the bytes after them (mode, mission, body length)."""
        raw = cols.view(np.uint8).reshape(-1, ROW_BYTES)
        return raw[keep].view(ROW_DTYPE).reshape(-1)

    def arrivals(self, rows: np.ndarray[Any, np.dtype[np.intp]]) -> np.ndarray[Any, np.dtype[np.float64]]:
        """Wall time the newest report of each of ``rows`` arrived."""
        return np.frombuffer(self.rx, dtype=np.float64)[rows]

    def body(self, row: int) -> bytes:
        """The newest body stored in ``row``."""
        start = row * ROW_BYTES
        return bytes(self.buf[start : start + self.buf[start + MAX_BODY]])

    def changed(self, rows: np.ndarray[Any, np.dtype[np.intp]]) -> np.ndarray[Any, np.dtype[np.bool_]]:
        """Which of ``rows`` changed state (:data:`STATE_BYTES`: flags, steps, mode, mission) since the
        last call for them; one vectorised compare, the remembered state updated."""
        width = len(STATE_BYTES)
        table = np.frombuffer(self.buf, dtype=np.uint8, count=self._used * ROW_BYTES).reshape(-1, ROW_BYTES)
        now = table[rows[:, None], _STATE_INDEX]
        seen = np.frombuffer(self.seen, dtype=np.uint8, count=self._used * width).reshape(-1, width)
        diff: np.ndarray[Any, np.dtype[np.bool_]] = (now != seen[rows]).any(axis=1)
        seen[rows] = now
        return diff

    def unsee(self, row: int) -> None:
        """The row's report went to the hooks outside a tick: its next report counts as a change
        (a state that came back, say a failsafe that cleared, must not look unchanged)."""
        width = len(STATE_BYTES)
        self.seen[row * width : (row + 1) * width] = bytes(width)

    @staticmethod
    def check(cols: np.ndarray[Any, Any]) -> np.ndarray[Any, np.dtype[np.bool_]]:
        """Which rows of ``cols`` (``ROW_DTYPE``) keep the protocol's ranges, as one vectorised check."""
        flags = cols["flags"]
        vt, pct, volts, amps = cols["vehicle_time"], cols["battery_pct"], cols["voltage_v"], cols["current_a"]
        lat, lon, heading = cols["lat"], cols["lon"], cols["heading_deg"]
        isfinite, isnan = np.isfinite, np.isnan
        with np.errstate(invalid="ignore"):
            ok: np.ndarray[Any, np.dtype[np.bool_]] = (
                (cols["layout"] == status_binary.LAYOUT_VERSION)
                & (flags < 0x80)
                & ((flags & status_binary.HAS_TAIL) == 0)
                & isfinite(cols["time"])
                & isfinite(cols["vn"])
                & isfinite(cols["ve"])
                & isfinite(cols["vd"])
                & (heading >= 0.0)
                & (heading <= 360.0)
                & (isnan(vt) | (isfinite(vt) & (vt >= 0.0)))
                & (isnan(pct) | ((pct >= 0.0) & (pct <= 100.0)))
                & (isnan(volts) | ((volts >= 0.0) & (volts <= 1000.0)))
                & (isnan(amps) | ((amps >= -1000.0) & (amps <= 1000.0)))
                & (cols["fix"] <= 8)
                & (cols["step"] >= -1)
                & (cols["completed_step"] >= -1)
                & (cols["waiting_sync"] >= -1)
                & (
                    ((flags & status_binary.HAS_POSITION) == 0)
                    | (
                        (lat >= -90.0)
                        & (lat <= 90.0)
                        & (lon >= -180.0)
                        & (lon <= 180.0)
                        & isfinite(cols["alt_rel"])
                        & isfinite(cols["alt_amsl"])
                    )
                )
            )
        return ok

    def plausible(
        self, cols: np.ndarray[Any, Any], rows: np.ndarray[Any, np.dtype[np.intp]]
    ) -> np.ndarray[Any, np.dtype[np.bool_]]:
        """Which rows of ``cols`` (the columns of ``rows``) keep the plausibility bounds
        (gcs/link/status_limits.py), against the time each report arrived; one vectorised check."""
        return plausible(cols, self.arrivals(rows), self.limits)

    def reports(
        self, rows: np.ndarray[Any, np.dtype[np.intp]]
    ) -> list[StatusReport | StatusBodyError | ImplausibleStatus]:
        """The newest report of each of ``rows``, or why it is refused (what a tick does, as objects).

        The fixed fields of all rows are checked at once on NumPy columns (ranges and
        plausibility); a row that passes is assembled without a second check
        (``status_binary.from_checked``: its variable part was checked when it was stored), a row
        that does not goes through :meth:`report`, which names the problem.
        """
        cols = self.columns(rows)
        ok = self.check(cols) & self.plausible(cols, rows)
        out: list[StatusReport | StatusBodyError | ImplausibleStatus] = []
        for i, (row, passed) in enumerate(zip(rows.tolist(), ok.tolist(), strict=True)):
            try:
                if self.objects[row] is None and passed:
                    self.objects[row] = row_report(cols[i : i + 1].tobytes())
                out.append(self.report(row))
            except (StatusBodyError, ImplausibleStatus) as exc:
                out.append(exc)
        return out

    def report(self, row: int) -> StatusReport:
        """The newest report of ``row`` as a ``StatusReport`` (decoded now unless it came decoded).

        Raises ``protocol.status_binary.StatusBodyError`` for a body that breaks the protocol's
        ranges and :class:`~gcs.link.status_limits.ImplausibleStatus` for one beyond the plausibility
        bounds (the ingest only copies bytes; the checks happen here or in the tick).
        """
        report = self.objects[row]
        if report is None:
            report = status_binary.decode(self.body(row))
            reason = refusal(report, self.rx[row], self.limits)
            if reason is not None:
                raise ImplausibleStatus(reason)
            self.objects[row] = report
        return report


def row_report(raw: bytes) -> StatusReport:
    """The report of one raw table row (:data:`ROW_BYTES`) whose fixed fields passed
    :meth:`StatusTable.check`: assembled without a second check when mode and mission are sound,
    else decoded by ``status_binary.decode``, which names the problem (``StatusBodyError``)."""
    fixed, size = status_binary.FIXED_SIZE, raw[MAX_BODY]
    mode_end = fixed + 1 + raw[fixed]
    if fixed + 2 <= size and mode_end < size and mode_end + 1 + raw[mode_end] == size:
        try:
            mode = raw[fixed + 1 : mode_end].decode()
            mission = raw[mode_end + 1 : size].decode() or None
        except UnicodeDecodeError:
            mode, mission = "", ""
        if len(mode) <= 32 and (mission is None or 0 < len(mission) <= 64):
            return status_binary.from_checked(status_binary.FIXED.unpack_from(raw), mode, mission)
    return status_binary.decode(raw[:size])


class StatusTick:
    """One status tick as columns: the rows handed over, their owners (sessions) and arrival times.

    Why: services that work on the whole fleet (telemetry rows, the bench) read the columns and
    never need a ``StatusReport`` per row; :meth:`report` builds one on demand (cached). ``cols``
    is a copy (``ROW_DTYPE``, each item the whole raw row), so later reports do not change it.
    """

    __slots__ = ("_reports", "cols", "owners", "received")

    def __init__(
        self,
        owners: list[Any],
        cols: np.ndarray[Any, Any],
        received: np.ndarray[Any, np.dtype[np.float64]],
        reports: list[StatusReport | None],
    ) -> None:
        self.owners = owners
        self.cols = cols
        self.received = received  # wall time each row's report arrived
        self._reports = reports

    def __len__(self) -> int:
        return len(self.owners)

    @classmethod
    def of_reports(cls, pairs: list[tuple[Any, StatusReport]], received: float) -> StatusTick:
        """A tick of reports decoded already (rare packets handed over at once)."""
        rows = bytearray(len(pairs) * ROW_BYTES)
        for i, (_, report) in enumerate(pairs):
            body = status_binary.encode(report)[: status_binary.FIXED_SIZE]
            rows[i * ROW_BYTES : i * ROW_BYTES + len(body)] = body
        cols = np.frombuffer(bytes(rows), dtype=ROW_DTYPE)
        stamps = np.full(len(pairs), received, dtype=np.float64)
        return cls([owner for owner, _ in pairs], cols, stamps, [report for _, report in pairs])

    def slice(self, start: int, stop: int) -> StatusTick:
        """Rows ``start`` to ``stop`` (the whole tick when it has no more)."""
        if start == 0 and stop >= len(self.owners):
            return self
        return StatusTick(
            self.owners[start:stop],
            self.cols[start:stop],
            self.received[start:stop],
            self._reports[start:stop],
        )

    def report(self, i: int) -> StatusReport:
        """Row ``i`` as a ``StatusReport`` (built now unless it came decoded)."""
        report = self._reports[i]
        if report is None:
            report = self._reports[i] = row_report(self.cols[i : i + 1].tobytes())
        return report

    def whole_rows(
        self, rows: np.ndarray[Any, np.dtype[np.intp]]
    ) -> tuple[np.ndarray[Any, np.dtype[np.uint8]], np.ndarray[Any, Any]]:
        """Rows ``rows`` whole: their bytes (one row each, for a copy kept elsewhere) and their
        columns with mode and mission still in them (fancy indexing ``cols`` would drop the bytes
        outside the named fields), so a consumer needs no row layout of its own."""
        raw = self.cols.view(np.uint8).reshape(-1, ROW_BYTES)[rows]
        return raw, raw.view(ROW_DTYPE).reshape(-1)

    def decoded(self, i: int) -> StatusReport | None:
        """Row ``i``'s report if it exists already (it came decoded, or was built), else None."""
        return self._reports[i]

    def built(self) -> list[int]:
        """The rows whose report exists already (it came decoded, or a hook built it)."""
        return [i for i, report in enumerate(self._reports) if report is not None]

    def mode_mission(self, i: int) -> tuple[str, str | None]:
        """Mode and mission id of row ``i`` (no report built for a compact row)."""
        report = self._reports[i]
        if report is not None:
            return report.mode, report.mission_id
        raw = self.cols[i : i + 1].tobytes()
        key = raw[status_binary.FIXED_SIZE : raw[MAX_BODY]]
        found = _MODES.get(key)
        if found is None:
            built = self.report(i)
            found = (built.mode, built.mission_id)
            if len(_MODES) > 4096:
                _MODES.clear()
            _MODES[key] = found
        return found


_MODES: dict[bytes, tuple[str, str | None]] = {}  # the variable part of a body -> its mode, mission


__all__ = [
    "FIXED_DTYPE",
    "MAX_BODY",
    "ROW_BYTES",
    "ROW_DTYPE",
    "STATE_BYTES",
    "StatusTable",
    "StatusTick",
    "row_report",
]
