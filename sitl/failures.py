"""Failure-injection specs shared by the CLI (``--fail``) and :class:`sitl.fleet.FleetConfig`.

Syntax (times in sim seconds since boot; several specs separated by ``;`` or given repeatedly)::

    VEH:KIND@START[+DURATION][=VALUE]

``VEH`` is the vehicle's system id (1-based, vehicle index + 1) or ``*`` for every vehicle. ``KIND``:

* ``link_drop@T+D``  nothing sent and all input ignored from T for D seconds
* ``gps_loss@T+D``   no GPS fix from T for D seconds (position dead-reckoned; the position failsafe follows)
* ``battery@T=PCT``  set the remaining charge to PCT percent at T (alias ``low_battery``)
* ``wind@T=N,E``     set the steady wind to N m/s north, E m/s east at T

Examples: ``1:link_drop@30+10``, ``*:battery@120=15``, ``2:gps_loss@45+8;3:wind@0=3,-1``.
"""

from __future__ import annotations

import re

from sitl.vehicle import Failure

_SPEC = re.compile(
    r"^\s*(?P<veh>\*|\d+)\s*:\s*(?P<kind>[a-z_]+)\s*@\s*(?P<at>[0-9.]+)"
    r"(?:\s*\+\s*(?P<dur>[0-9.]+))?(?:\s*=\s*(?P<val>[-0-9.,\s]+))?\s*$"
)
_KINDS = {
    "link_drop": "link_drop",
    "gps_loss": "gps_loss",
    "battery": "battery",
    "low_battery": "battery",
    "wind": "wind",
}


def parse_failures(specs: str | list[str] | tuple[str, ...], vehicles: int) -> list[tuple[int, Failure]]:
    """Parse ``--fail`` specs into (vehicle index, Failure) pairs; raises ValueError with the bad spec."""
    items = [specs] if isinstance(specs, str) else list(specs)
    out: list[tuple[int, Failure]] = []
    for chunk in items:
        for spec in chunk.split(";"):
            if not spec.strip():
                continue
            m = _SPEC.match(spec)
            if m is None:
                raise ValueError(f"bad failure spec {spec!r}: expected VEH:KIND@START[+DURATION][=VALUE]")
            kind = _KINDS.get(m["kind"])
            if kind is None:
                raise ValueError(f"bad failure spec {spec!r}: unknown kind {m['kind']!r}")
            at = float(m["at"])
            dur = float(m["dur"]) if m["dur"] else 0.0
            vals = tuple(float(x) for x in m["val"].split(",")) if m["val"] else ()
            if kind in ("link_drop", "gps_loss") and dur <= 0:
                raise ValueError(f"bad failure spec {spec!r}: {kind} needs +DURATION")
            if kind == "battery" and len(vals) != 1:
                raise ValueError(f"bad failure spec {spec!r}: battery needs =PCT")
            if kind == "wind" and len(vals) != 2:
                raise ValueError(f"bad failure spec {spec!r}: wind needs =NORTH,EAST")
            if m["veh"] == "*":
                targets = list(range(vehicles))
            else:
                sysid = int(m["veh"])
                if not 1 <= sysid <= vehicles:
                    raise ValueError(f"bad failure spec {spec!r}: vehicle {sysid} not in 1..{vehicles}")
                targets = [sysid - 1]
            for idx in targets:
                out.append((idx, Failure(at=at, kind=kind, duration=dur, value=vals)))
    return out
