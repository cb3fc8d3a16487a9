"""Connectivity maintenance: a disk-model link graph of the base station and the drones.

Node 0 is the base (the daemon's radio), nodes 1..N the drones. Two nodes are linked when they
are within the link range w (the agent parameter ``link_range_m``). With ``multihop`` drones
relay for each other (a mesh such as OLSR, seed 004 2.2.4); without it each drone needs the
base directly (a star, seed 000's single access point). A drone is *connected* when it is in
the base's component. Pure numpy/scipy; a cKDTree keeps the graph near O(N log N).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from gcs.cooperation.legs import planned_targets
from gcs.planning.geodesy import FloatArray, LocalFrame
from protocol.actions import Action


def connected_to_base(
    base_en: tuple[float, float], drones_en: FloatArray, range_m: float, multihop: bool
) -> np.ndarray:
    """Boolean per drone: reachable from the base over links no longer than ``range_m``."""
    n = len(drones_en)
    if n == 0:
        return np.zeros(0, dtype=bool)
    nodes = np.vstack([np.asarray(base_en, dtype=float)[None, :], drones_en])
    if not multihop:
        return np.linalg.norm(drones_en - nodes[0], axis=1) <= range_m
    pairs = cKDTree(nodes).query_pairs(range_m, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n + 1, n + 1))
    _, labels = connected_components(graph, directed=False)
    return np.asarray(labels[1:] == labels[0])


def nearest_connected(
    base_en: tuple[float, float], drones_en: FloatArray, connected: np.ndarray, k: int
) -> tuple[float, float]:
    """The base or a connected drone nearest to drone ``k`` (where a disconnected drone should head)."""
    candidates = [np.asarray(base_en, dtype=float)] + [
        drones_en[m] for m in range(len(drones_en)) if connected[m] and m != k
    ]
    points = np.vstack(candidates)
    best = int(np.argmin(np.linalg.norm(points - drones_en[k], axis=1)))
    return float(points[best, 0]), float(points[best, 1])


def preflight_disconnections(
    plans: dict[str, list[Action]],
    homes: dict[str, tuple[float, float, float]],
    frame: LocalFrame,
    base_en: tuple[float, float],
    range_m: float,
    multihop: bool,
) -> list[tuple[int, str]]:
    """(step, agent) pairs where the plan leaves a drone without a link to the base.

    Sync points make every plan reach step k together, so the fleet's shape at step k is each
    drone's planned position after its last action up to k; each step's shape is checked.
    """
    agents = sorted(plans)
    per_agent: dict[str, list[tuple[int, tuple[float, float] | None]]] = {}
    steps: set[int] = set()
    for agent in agents:
        actions = plans[agent]
        targets = planned_targets(actions, homes[agent])
        per_agent[agent] = [
            (a.step, frame.local_point(t[0], t[1]) if t is not None else None)
            for a, t in zip(actions, targets, strict=True)
        ]
        steps |= {a.step for a in actions}
    found: list[tuple[int, str]] = []
    for step in sorted(steps):
        names: list[str] = []
        points: list[tuple[float, float]] = []
        for agent in agents:
            where: tuple[float, float] | None = frame.local_point(homes[agent][0], homes[agent][1])
            for s, p in per_agent[agent]:
                if s > step:
                    break
                where = p  # None after rtl/land: back at home, on the ground
            if where is not None:
                names.append(agent)
                points.append(where)
        if not points:
            continue
        ok = connected_to_base(base_en, np.array(points), range_m, multihop)
        found += [(step, names[m]) for m in range(len(names)) if not ok[m]]
    return found
