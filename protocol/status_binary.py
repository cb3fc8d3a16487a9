"""The compact binary type-2 (status) body: a fixed little-endian layout, no JSON on the hot path.

Why: at 10 Hz from thousands of agents the daemon spends most of its time turning JSON into a
validated :class:`~protocol.packets.StatusReport` (~25 µs a report). This layout unpacks with
one ``struct`` call and is range-checked by hand, then the report is assembled without a second
validation pass; it decodes to *the same* ``StatusReport`` the JSON body gives (tests/protocol/
test_status_binary.py checks that for random reports). Pure: no sockets, no asyncio.

Layout (docs/protocol.md "Compact binary status body" documents it byte by byte)::

    offset size type  field
    0      1    u8    layout version (1)
    1      1    u8    flags: bit0 armed, bit1 landed, bit2 paused, bit3 autopilot_link,
                      bit4 buffered, bit5 position present, bit6 JSON tail present
    2      1    u8    gps.fix
    3      1    u8    gps.satellites
    4      8    f64   time
    12     8    f64   vehicle_time            (NaN = none)
    20     8    f64   position.lat            (0 when bit5 is clear)
    28     8    f64   position.lon
    36     8    f64   position.alt_rel
    44     8    f64   position.alt_amsl
    52     8    f64   velocity.vn
    60     8    f64   velocity.ve
    68     8    f64   velocity.vd
    76     8    f64   heading_deg
    84     8    f64   battery.pct             (NaN = none)
    92     8    f64   battery.voltage_v       (NaN = none)
    100    8    f64   battery.current_a       (NaN = none)
    108    4    i32   step
    112    4    i32   completed_step
    116    4    u32   queue_depth
    120    4    i32   waiting_sync            (-1 = none)
    124    1    u8    mode length M (bytes)
    125    M    utf-8 mode
    125+M  1    u8    mission_id length N     (0 = none)
    126+M  N    utf-8 mission_id
    126+M+N ... utf-8 JSON tail: an object with the fields that have no slot (exceptions,
                      failure, failsafe, pilot) or did not fit theirs; present only when bit6 is set

The protocol forbids NaN in every float field, so NaN is free to mean "none". A tail field
overrides the fixed slot of the same name; a report with a tail is validated by pydantic in
full (the rare path).
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Callable
from typing import Any

from pydantic import ValidationError

from protocol.packets import Battery, Gps, Position, StatusReport, VelocityNed

LAYOUT_VERSION = 1
FIXED_FIELDS: tuple[tuple[str, str], ...] = (
    ("layout", "B"),
    ("flags", "B"),
    ("fix", "B"),
    ("satellites", "B"),
    ("time", "d"),
    ("vehicle_time", "d"),
    ("lat", "d"),
    ("lon", "d"),
    ("alt_rel", "d"),
    ("alt_amsl", "d"),
    ("vn", "d"),
    ("ve", "d"),
    ("vd", "d"),
    ("heading_deg", "d"),
    ("battery_pct", "d"),
    ("voltage_v", "d"),
    ("current_a", "d"),
    ("step", "i"),
    ("completed_step", "i"),
    ("queue_depth", "I"),
    ("waiting_sync", "i"),
)
"""The fixed part, field by field (``struct`` codes, little-endian, no padding): the daemon's fleet
table reads the same layout as a NumPy structured dtype built from this list."""
FIXED = struct.Struct("<" + "".join(code for _, code in FIXED_FIELDS))
FIXED_SIZE = FIXED.size  # 124
assert FIXED_SIZE == 124

ARMED, LANDED, PAUSED, AUTOPILOT_LINK, BUFFERED, HAS_POSITION, HAS_TAIL = (1 << i for i in range(7))
_UNKNOWN_OR_TAIL = 0x80 | HAS_TAIL
_I32_MIN, _I32_MAX, _U32_MAX = -(1 << 31), (1 << 31) - 1, (1 << 32) - 1
_NAN = math.nan


class StatusBodyError(ValueError):
    """A compact status body that is malformed or out of the protocol's ranges (one line)."""


# --- encode ----------------------------------------------------------------------------------------


def _opt(value: float | None) -> float:
    return _NAN if value is None else value


def encode(status: StatusReport) -> bytes:
    """The compact body of ``status`` (without the frame header)."""
    tail: dict[str, Any] = {}
    if status.exceptions:
        tail["exceptions"] = status.exceptions
    if status.failure is not None:
        tail["failure"] = status.failure.model_dump()
    if status.failsafe is not None:
        tail["failsafe"] = status.failsafe
    if status.pilot is not None:
        tail["pilot"] = status.pilot
    ints = {
        "step": status.step,
        "completed_step": status.completed_step,
        "waiting_sync": -1 if status.waiting_sync is None else status.waiting_sync,
    }
    for name, value in ints.items():  # pydantic bounds these from below only: big ones ride the tail
        if value > _I32_MAX:
            tail[name] = value
            ints[name] = -1
    queue_depth = status.queue_depth
    if queue_depth > _U32_MAX:
        tail["queue_depth"] = queue_depth
        queue_depth = 0
    mode = status.mode.encode()
    mission = (status.mission_id or "").encode()
    if len(mode) > 255:
        tail["mode"] = status.mode
        mode = b""
    if len(mission) > 255:
        tail["mission_id"] = status.mission_id
        mission = b""
    p, v, b = status.position, status.velocity, status.battery
    flags = (
        (ARMED if status.armed else 0)
        | (LANDED if status.landed else 0)
        | (PAUSED if status.paused else 0)
        | (AUTOPILOT_LINK if status.autopilot_link else 0)
        | (BUFFERED if status.buffered else 0)
        | (HAS_POSITION if p is not None else 0)
        | (HAS_TAIL if tail else 0)
    )
    fixed = FIXED.pack(
        LAYOUT_VERSION,
        flags,
        status.gps.fix,
        status.gps.satellites,
        status.time,
        _opt(status.vehicle_time),
        p.lat if p else 0.0,
        p.lon if p else 0.0,
        p.alt_rel if p else 0.0,
        p.alt_amsl if p else 0.0,
        v.vn,
        v.ve,
        v.vd,
        status.heading_deg,
        _opt(b.pct),
        _opt(b.voltage_v),
        _opt(b.current_a),
        ints["step"],
        ints["completed_step"],
        queue_depth,
        ints["waiting_sync"],
    )
    out = fixed + bytes((len(mode),)) + mode + bytes((len(mission),)) + mission
    if tail:
        out += json.dumps(tail, separators=(",", ":"), allow_nan=False).encode()
    return out


# --- decode ----------------------------------------------------------------------------------------

_new = object.__new__
_set = object.__setattr__


def _model(cls: type[Any], values: dict[str, Any]) -> Any:
    """A model instance from values already checked against its field constraints (no validation).

    Equal to what ``cls.model_validate(values)`` gives for those values (every field given), in
    well under 1 µs instead of 5-25. The fields-set is shared per class: these models are frozen,
    and pydantic copies it before changing it (``model_copy``).
    """
    model = _new(cls)
    _set(model, "__dict__", values)
    _set(model, "__pydantic_fields_set__", _FIELDS_SET[cls])
    _set(model, "__pydantic_extra__", None)
    _set(model, "__pydantic_private__", None)
    return model


_FIELDS_SET: dict[type[Any], set[str]] = {
    cls: set(cls.model_fields) for cls in (StatusReport, Position, VelocityNed, Battery, Gps)
}
_GPS: dict[tuple[int, int], Gps] = {}  # at most 9 x 256 distinct values, and frozen: shared


def _gps(fix: int, satellites: int) -> Gps:
    gps = _GPS.get((fix, satellites))
    if gps is None:
        gps = _GPS[(fix, satellites)] = _model(Gps, {"fix": fix, "satellites": satellites})
    return gps


def _bad(field: str, value: object) -> StatusBodyError:
    return StatusBodyError(f"compact status body: {field} {value!r} out of range")


MODE_MAX_CHARS = 32  # StatusReport.mode max_length
MISSION_MAX_CHARS = 64  # MissionId max_length


def check_layout(payload: bytes) -> None:
    """Everything about a body but its fixed fields' ranges; :class:`StatusBodyError` (one line) if bad.

    Length at least the fixed part and both length bytes, layout version, flag bits, ``mode`` and
    ``mission_id`` inside the body, UTF-8 and within the schema's lengths (32 and 64 characters),
    and bytes after ``mission_id`` exactly when the tail flag is set. The daemon runs this on every
    compact body before it copies it into its fleet table (gcs/link/agents.py), so a row only ever holds
    a body whose variable part is sound; cheap (byte checks, no decode for ASCII, well under 1 us).
    """
    size = len(payload)
    if size >= FIXED_SIZE + 2:  # the daemon's hot path: a sound tail-less ASCII body, in a few byte reads
        mode_len = payload[FIXED_SIZE]
        mode_end = FIXED_SIZE + 1 + mode_len
        if (
            mode_end < size
            and mode_end + 1 + payload[mode_end] == size
            and payload[0] == LAYOUT_VERSION
            and not payload[1] & _UNKNOWN_OR_TAIL
            and mode_len <= MODE_MAX_CHARS
            and payload[mode_end] <= MISSION_MAX_CHARS
            and payload[FIXED_SIZE + 1 : size].isascii()
        ):
            return
    else:
        raise StatusBodyError(f"compact status body of {size} bytes is shorter than {FIXED_SIZE + 2}")
    if payload[0] != LAYOUT_VERSION:
        raise StatusBodyError(f"compact status layout {payload[0]} not supported (this side reads 1)")
    flags = payload[1]
    if flags >> 7:
        raise StatusBodyError(f"compact status body: unknown flag bits {flags:#04x}")
    mode_end = FIXED_SIZE + 1 + payload[FIXED_SIZE]
    if mode_end >= size:
        raise StatusBodyError(
            f"compact status body truncated in mode ({payload[FIXED_SIZE]} bytes from offset "
            f"{FIXED_SIZE + 1} in a body of {size})"
        )
    mission_end = mode_end + 1 + payload[mode_end]
    if mission_end > size:
        raise StatusBodyError(
            f"compact status body truncated in mission_id ({payload[mode_end]} bytes from offset "
            f"{mode_end + 1} in a body of {size})"
        )
    has_tail = bool(flags & HAS_TAIL)
    if has_tail != (mission_end < size):
        raise StatusBodyError(
            f"compact status body: {size - mission_end} bytes after mission_id, tail flag {has_tail}"
        )
    if payload[FIXED_SIZE + 1 : mission_end].isascii():  # the usual case: bytes are characters
        mode_chars, mission_chars = mode_end - FIXED_SIZE - 1, payload[mode_end]
    else:
        try:
            mode_chars = len(payload[FIXED_SIZE + 1 : mode_end].decode())
            mission_chars = len(payload[mode_end + 1 : mission_end].decode())
        except UnicodeDecodeError:
            raise StatusBodyError("compact status body: mode or mission_id is not UTF-8") from None
    if mode_chars > MODE_MAX_CHARS:
        raise StatusBodyError(
            f"compact status body: mode of {mode_chars} characters (at most {MODE_MAX_CHARS})"
        )
    if mission_chars > MISSION_MAX_CHARS:
        raise StatusBodyError(
            f"compact status body: mission_id of {mission_chars} characters (at most {MISSION_MAX_CHARS})"
        )


def decode(payload: bytes) -> StatusReport:
    """The :class:`StatusReport` of a compact body; :class:`StatusBodyError` (one line) if malformed."""
    check_layout(payload)
    (
        _version,
        flags,
        fix,
        _sats,
        t,
        vt,
        lat,
        lon,
        alt_rel,
        alt_amsl,
        vn,
        ve,
        vd,
        heading,
        pct,
        volts,
        amps,
        step,
        completed,
        _queue_depth,
        waiting,
    ) = fields = FIXED.unpack_from(payload)
    mode_end = FIXED_SIZE + 1 + payload[FIXED_SIZE]
    mission_end = mode_end + 1 + payload[mode_end]
    mode = payload[FIXED_SIZE + 1 : mode_end].decode()
    mission = payload[mode_end + 1 : mission_end].decode() or None
    has_tail = bool(flags & HAS_TAIL)
    isfinite = math.isfinite
    # The fast path: the same constraints pydantic would check (protocol/packets.py), by hand.
    checked = (
        not has_tail
        and isfinite(t)
        and isfinite(vn)
        and isfinite(ve)
        and isfinite(vd)
        and 0.0 <= heading <= 360.0
        and (vt != vt or (isfinite(vt) and vt >= 0.0))
        and (pct != pct or 0.0 <= pct <= 100.0)
        and (volts != volts or 0.0 <= volts <= 1000.0)
        and (amps != amps or -1000.0 <= amps <= 1000.0)
        and fix <= 8
        and step >= -1
        and completed >= -1
        and waiting >= -1
        and (
            not flags & HAS_POSITION
            or (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and isfinite(alt_rel) and isfinite(alt_amsl))
        )
    )
    if checked:
        return from_checked(fields, mode, mission)
    # The tail merged, or pydantic names the offending field.
    return _with_tail(_values(fields, mode, mission, _plain), payload[mission_end:])


def _plain(_: type[Any], values: dict[str, Any]) -> dict[str, Any]:
    return values


def _values(
    fields: tuple[Any, ...], mode: str, mission: str | None, nest: Callable[[type[Any], dict[str, Any]], Any]
) -> dict[str, Any]:
    """The report's fields from the fixed part (in :data:`FIXED_FIELDS` order), mode and mission;
    ``nest`` makes the nested parts (models, or plain dicts for pydantic to validate)."""
    (_, flags, fix, sats, t, vt, lat, lon, alt_rel, alt_amsl, vn, ve, vd, heading, pct, volts, amps) = fields[
        :17
    ]
    step, completed, queue_depth, waiting = fields[17:]
    return {
        "time": t,
        "vehicle_time": None if vt != vt else vt,
        "position": nest(Position, {"lat": lat, "lon": lon, "alt_rel": alt_rel, "alt_amsl": alt_amsl})
        if flags & HAS_POSITION
        else None,
        "velocity": nest(VelocityNed, {"vn": vn, "ve": ve, "vd": vd}),
        "heading_deg": heading,
        "battery": nest(
            Battery,
            {
                "pct": None if pct != pct else pct,
                "voltage_v": None if volts != volts else volts,
                "current_a": None if amps != amps else amps,
            },
        ),
        "mode": mode,
        "armed": bool(flags & ARMED),
        "landed": bool(flags & LANDED),
        "gps": _gps(fix, sats) if nest is _model else {"fix": fix, "satellites": sats},
        "mission_id": mission,
        "step": step,
        "completed_step": completed,
        "queue_depth": queue_depth,
        "waiting_sync": None if waiting == -1 else waiting,
        "paused": bool(flags & PAUSED),
        "exceptions": [],
        "autopilot_link": bool(flags & AUTOPILOT_LINK),
        "buffered": bool(flags & BUFFERED),
        "failure": None,
        "failsafe": None,
        "pilot": None,
    }


def from_checked(fields: tuple[Any, ...], mode: str, mission: str | None) -> StatusReport:
    """The report of a tail-less body whose fixed ``fields`` (in :data:`FIXED_FIELDS` order),
    ``mode`` and ``mission`` were checked against the protocol's ranges already (the daemon's fleet
    table checks whole columns at once, gcs/link/agents_table.py): what :func:`decode` gives for it."""
    report: StatusReport = _model(StatusReport, _values(fields, mode, mission, _model))
    return report


def _with_tail(values: dict[str, Any], tail: bytes) -> StatusReport:
    """The slow path: merge the JSON tail and let pydantic validate the whole report."""
    if tail:
        try:
            extra = json.loads(tail.decode())
        except (ValueError, RecursionError) as exc:
            raise StatusBodyError(f"compact status body: JSON tail is not UTF-8 JSON: {exc}") from None
        if not isinstance(extra, dict):
            raise StatusBodyError("compact status body: JSON tail must be an object")
        values.update(extra)
    try:
        return StatusReport.model_validate(values)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ())) or "body"
        raise StatusBodyError(f"compact status body: invalid {where}: {first.get('msg')}") from None
    except RecursionError:
        raise StatusBodyError("compact status body: JSON tail nests too deeply") from None


__all__ = [
    "FIXED_FIELDS",
    "FIXED_SIZE",
    "LAYOUT_VERSION",
    "MISSION_MAX_CHARS",
    "MODE_MAX_CHARS",
    "StatusBodyError",
    "check_layout",
    "decode",
    "encode",
    "from_checked",
]
