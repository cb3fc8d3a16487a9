"""Run-time cooperation services of the daemon (seed 004 section 2.2.1, seed 000 section IV).

Pure algorithms (``collision``, ``divergence``, ``connectivity``, ``emergency``, ``energy``,
``legs``) are separate from the glue that listens to status reports and sends packets
(``service``). ``cooperation_services(config)`` builds what the daemon runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from gcs.cooperation.config import CooperationConfig

if TYPE_CHECKING:
    from gcs.cooperation.airspace import ClusterView

__all__ = ["CooperationConfig", "cooperation_services"]


def cooperation_services(config: CooperationConfig, cluster: ClusterView | None = None) -> list[Any]:
    """The services the daemon runs (imported lazily: the daemon imports this module); ``cluster``
    is the cluster node in cluster mode (the airspace lease, remote drones' levels)."""
    from gcs.cooperation.service import CooperationService

    return [CooperationService(config, cluster)]
