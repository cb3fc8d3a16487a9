"""A survey mission's re-task record as bytes for the daemon's store (issue 27), and back.

The retask service (gcs/missions/retask.py) keeps each survey's record (area, plans as they ended
up, flown tracks, re-task decisions) in memory while it flies; the store keeps its last saved
copy (table ``survey_records``), so ``GET /missions/{id}/report`` and ``gcs mission report``
answer after a daemon restart too. Pure: no I/O, no clock; the encoding is zlib-compressed JSON
(a track of 10,000 points is ~100 kB compressed), versioned by ``"v"``.
"""

from __future__ import annotations

import json
import zlib
from typing import TYPE_CHECKING, Any

from pydantic import TypeAdapter

from gcs.planning.retask import NewLeg, RetaskProposal
from protocol.actions import Action
from protocol.taskfile import SurveyArea

if TYPE_CHECKING:
    from gcs.missions.retask import SurveyRecord

VERSION = 1
_ACTIONS: TypeAdapter[list[Action]] = TypeAdapter(list[Action])


class RecordDecodeError(ValueError):
    """Stored bytes that are not a record this version reads (damaged, or a newer version's)."""


def encode_record(rec: SurveyRecord) -> bytes:
    """``rec`` (a snapshot: call it in a worker thread for a long survey) as stored bytes."""
    doc = {
        "v": VERSION,
        "mission_id": rec.mission_id,
        "survey": rec.survey.model_dump(mode="json"),
        "planned": {a: _ACTIONS.dump_python(p, mode="json") for a, p in rec.planned.items()},
        "tracks": {a: [list(p) for p in t] for a, t in rec.tracks.items()},
        "decisions": [
            {
                "id": d.id,
                "dropped": d.dropped,
                "why": d.why,
                "state": d.state,
                "at": d.at,
                "by": d.by,
                "proposal": d.proposal.as_dict(),
            }
            for d in rec.decisions
        ],
    }
    return zlib.compress(json.dumps(doc, separators=(",", ":")).encode(), 6)


def decode_record(blob: bytes) -> SurveyRecord:
    """The record stored as ``blob`` (a decided proposal's legs as they were; nothing waits to be
    sent any more: the mission that would send them is not this daemon's to resume)."""
    from gcs.missions.retask import Decision, SurveyRecord

    try:
        doc = json.loads(zlib.decompress(blob))
        if doc.get("v") != VERSION:
            raise RecordDecodeError(f"survey record version {doc.get('v')!r}, this daemon reads {VERSION}")
        decisions = [
            Decision(
                id=d["id"],
                dropped=d["dropped"],
                why=d["why"],
                proposal=_proposal(d["proposal"]),
                state=d["state"],
                at=float(d["at"]),
                by=d["by"],
            )
            for d in doc["decisions"]
        ]
        return SurveyRecord(
            mission_id=doc["mission_id"],
            survey=SurveyArea.model_validate(doc["survey"]),
            planned={a: _ACTIONS.validate_python(p) for a, p in doc["planned"].items()},
            tracks={
                a: [(float(p[0]), float(p[1]), float(p[2])) for p in t] for a, t in doc["tracks"].items()
            },
            decisions=decisions,
        )
    except RecordDecodeError:
        raise
    except (zlib.error, ValueError, KeyError, TypeError, IndexError) as exc:
        raise RecordDecodeError(f"stored survey record unreadable: {exc}") from None


def _proposal(d: dict[str, Any]) -> RetaskProposal:
    legs = [NewLeg(**{**g, "points": [(float(p[0]), float(p[1])) for p in g["points"]]}) for g in d["legs"]]
    return RetaskProposal(
        verdict=d["verdict"],
        reason=d["reason"],
        dropped=d["dropped"],
        gap_m2=float(d["gap_m2"]),
        share_m2=float(d["share_m2"]),
        legs=legs,
        gap=d["gap"],
        pieces=int(d.get("pieces", 1)),
    )
