"""Flight logs: one CSV per drone-flight, written from status reports and read for energy training.

Format (the same as ``gcs log export``): a header line
``time,lat,lon,alt_rel,alt_amsl,vn,ve,vd,heading_deg,battery_pct,voltage_v,current_a,mode,armed,landed,step,mission_id``
then one row per status report. ``time`` is seconds on the vehicle's clock, anchored at the
first report's UNIX time (:class:`VehicleClock`); empty cells mean "not reported";
``armed``/``landed`` are 0/1. Energy is the integral of voltage x current over time.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from gcs.planning.geodesy import distance_m_array
from protocol.packets import StatusReport

COLUMNS = [
    "time", "lat", "lon", "alt_rel", "alt_amsl", "vn", "ve", "vd", "heading_deg",
    "battery_pct", "voltage_v", "current_a", "mode", "armed", "landed", "step", "mission_id",
]  # fmt: skip
JITTER_FLOOR_M = 0.05


class FlightLogError(ValueError):
    """A file that is not a flight log in the documented format."""


@dataclass(frozen=True)
class FlightSummary:
    """What the energy model learns from: one drone-flight (armed period)."""

    path: str
    time_s: float
    distance_m: float
    energy_wh: float
    samples: int
    complete: bool  # ends landed and disarmed (a whole flight, not a cut-off one)


def _cell(value: float | None, digits: int = 7) -> str:
    return "" if value is None or not math.isfinite(value) else f"{value:.{digits}f}".rstrip("0").rstrip(".")


def flight_log_row(status: StatusReport, time_s: float) -> list[str]:
    """One flight-log CSV row (``COLUMNS``); the caller writes only reports with a position.

    Not ``gcs.observe.telemetry.status_row``, which makes the telemetry database's row."""
    p, v, b = status.position, status.velocity, status.battery
    assert p is not None, "flight logs record positioned reports only"
    return [
        f"{time_s:.3f}", _cell(p.lat, 8), _cell(p.lon, 8), _cell(p.alt_rel, 3), _cell(p.alt_amsl, 3),
        _cell(v.vn, 3), _cell(v.ve, 3), _cell(v.vd, 3), _cell(status.heading_deg, 1),
        _cell(b.pct, 2), _cell(b.voltage_v, 3), _cell(b.current_a, 3), status.mode,
        "1" if status.armed else "0", "1" if status.landed else "0", str(status.step),
        status.mission_id or "",
    ]  # fmt: skip


class VehicleClock:
    """Record time for status reports: the vehicle's own clock whenever the agent reports it.

    Times are anchored at the first report's wall time and advance with ``vehicle_time`` (the
    autopilot's clock; a simulator's sim time), so a log stays right when a simulator runs
    faster than real time or falls behind its speed-up. Without a vehicle clock, wall time
    is stretched by ``time_scale`` (the nominal speed-up), which is only right if it was kept.
    A vehicle clock that goes backwards (autopilot reboot) is re-anchored.
    """

    def __init__(self, time_scale: float = 1.0) -> None:
        self.time_scale = time_scale
        self._anchor: tuple[float, float, bool] | None = None  # (record time, source time, vehicle?)
        self.last: float | None = None

    def __call__(self, status: StatusReport) -> float:
        vehicle = status.vehicle_time is not None
        source = status.vehicle_time if status.vehicle_time is not None else status.time
        anchor = self._anchor
        if anchor is None or anchor[2] != vehicle or (vehicle and source < anchor[1] - 1e-6):
            start = status.time if self.last is None else self.last
            anchor = self._anchor = (start, source, vehicle)
        scale = 1.0 if vehicle else self.time_scale
        t = anchor[0] + (source - anchor[1]) * scale
        self.last = t
        return t


class FlightLogWriter:
    """Appends status rows to one CSV, timed by the vehicle's clock (see :class:`VehicleClock`)."""

    def __init__(self, path: Path, time_scale: float = 1.0) -> None:
        self.path = path
        self.clock = VehicleClock(time_scale)
        path.parent.mkdir(parents=True, exist_ok=True)
        self._file: TextIO = path.open("w", newline="")
        self._writer = csv.writer(self._file)
        self._writer.writerow(COLUMNS)

    @property
    def time_scale(self) -> float:
        return self.clock.time_scale

    def add(self, status: StatusReport) -> None:
        if status.position is not None:  # no fix yet: no row
            self._writer.writerow(flight_log_row(status, self.clock(status)))

    def close(self) -> None:
        self._file.close()


def _float(row: dict[str, str], key: str) -> float:
    text = row.get(key, "")
    return float(text) if text not in ("", None) else math.nan


def read_flight_log(path: Path) -> dict[str, np.ndarray]:
    """Columns of a flight log as arrays (NaN for empty cells); strict about the header."""
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or [h.strip() for h in reader.fieldnames] != COLUMNS:
            raise FlightLogError(f"{path}: header is not {','.join(COLUMNS)}")
        rows = list(reader)
    if not rows:
        raise FlightLogError(f"{path}: no samples")
    numeric = [c for c in COLUMNS if c not in ("mode", "mission_id")]
    out: dict[str, np.ndarray] = {c: np.array([_float(r, c) for r in rows]) for c in numeric}
    out["mode"] = np.array([r["mode"] for r in rows])
    out["mission_id"] = np.array([r["mission_id"] for r in rows])
    order = np.argsort(out["time"], kind="stable")
    return {k: v[order] for k, v in out.items()}


def summarize(path: Path) -> FlightSummary:
    """Flight time, 3D distance and energy over the armed period of one log."""
    log = read_flight_log(path)
    armed = log["armed"] == 1
    if armed.sum() < 2:
        raise FlightLogError(f"{path}: fewer than two armed samples")
    first, last = np.flatnonzero(armed)[[0, -1]]
    sl = slice(first, last + 1)
    t = log["time"][sl]
    lat, lon, alt = log["lat"][sl], log["lon"][sl], log["alt_rel"][sl]
    across = distance_m_array(lat[:-1], lon[:-1], lat[1:], lon[1:])
    step = np.sqrt(across**2 + np.diff(alt) ** 2)
    step = np.where(np.isfinite(step) & (step > JITTER_FLOOR_M), step, 0.0)
    power = log["voltage_v"][sl] * np.clip(log["current_a"][sl], 0.0, None)
    if not np.isfinite(power).any():
        raise FlightLogError(f"{path}: no voltage/current samples, energy cannot be integrated")
    power = np.where(np.isfinite(power), power, 0.0)
    energy_j = float(np.sum(0.5 * (power[1:] + power[:-1]) * np.diff(t)))
    complete = bool(log["landed"][-1] == 1 and log["armed"][-1] == 0)
    return FlightSummary(
        str(path), float(t[-1] - t[0]), float(step.sum()), energy_j / 3600.0, len(t), complete
    )
