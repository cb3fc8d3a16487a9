"""Pruning the shared buckets: a finished mission's keys go ``cluster_prune_after_s`` after it ends.

Without it ``fleet_progress`` and ``fleet_barriers`` grow by a few keys per agent and barrier with
every mission, forever. One daemon prunes (the one holding the ``airspace`` lease, so a round is
never run twice at once), in bounded rounds:

1. ``cluster_prune_after_s`` after a mission ended, its progress and barrier keys are purged (a
   purge marker per key, so every daemon's mirror drops them), at most ``budget`` keys a round;
   when none is left the mission record is marked ``pruned``.
2. One round later the markers themselves go, with the mission's lease key (one subject purge
   per bucket): nothing of the mission is left in those buckets.

The mission record (``fleet_missions``: one key per mission, its task and result) stays: it is
the mission history every daemon's API lists.
"""

from __future__ import annotations

import time

from gcs.cluster.state import ClusterState

PRUNE_KEYS_PER_ROUND = 256
PRUNED_BUCKETS = ("progress", "barriers")


async def prune_round(
    state: ClusterState, after_s: float, now: float | None = None, budget: int = PRUNE_KEYS_PER_ROUND
) -> int:
    """One bounded round over the finished missions (oldest first); returns how many purges it made
    (at most ``budget``: a key, or one mission's step 2)."""
    now = time.time() if now is None else now
    removed = 0
    records = state.json_values("missions")
    finished = [
        (mission_id, record)
        for mission_id, record in records.items()
        if record.get("state") != "running"
        and record.get("finished") is not None
        and now - float(record["finished"]) >= after_s
        and not record.get("tidy")
    ]
    for mission_id, record in sorted(finished, key=lambda item: float(item[1]["finished"])):
        if removed >= budget:
            break
        prefix = f"{mission_id}."
        if record.get("pruned") is not None:  # step 2: the markers and the lease
            for bucket in PRUNED_BUCKETS:
                await state.purge_subject(bucket, prefix + ">")
            await state.purge_subject("leases", mission_id)
            state.put_json("missions", mission_id, {**record, "tidy": True})
            removed += 1
            continue
        keys = [(b, k) for b in PRUNED_BUCKETS for k in list(state.mirror[b]) if k.startswith(prefix)]
        for bucket, key in keys[: budget - removed]:
            await state.purge_key(bucket, key)
            removed += 1
        if all(not k.startswith(prefix) for b in PRUNED_BUCKETS for k in state.mirror[b]):
            state.put_json("missions", mission_id, {**record, "pruned": now})
    return removed
