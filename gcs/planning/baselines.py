"""Reference planners for PSA, without the connectivity constraint (so usually shorter routes).

* :func:`minmax_routes` - min-max multi-vehicle routing with OR-Tools (open routes from a
  common start, global span cost = the longest route), hard time limit per instance;
* :func:`tsp_split_routes` - one TSP tour from the start, cut optimally into ``m`` consecutive
  pieces (each drone flies from the start to its piece): the classic tour-splitting heuristic.

Both return one (k, 2) polyline per drone starting at ``start``; :func:`route_lengths` measures
them. Used by tests and bench/bench_fleet_planners.py on the same instances as PSA.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
SCALE = 100.0  # OR-Tools wants integer arc costs: centimetres


def route_lengths(routes: list[FloatArray]) -> FloatArray:
    """Length of each polyline (metres)."""
    return np.array([float(np.hypot(*np.diff(r, axis=0).T).sum()) if len(r) > 1 else 0.0 for r in routes])


def _distance_matrix(nodes: FloatArray) -> NDArray[np.int64]:
    diff = nodes[:, None, :] - nodes[None, :, :]
    return np.rint(np.hypot(diff[..., 0], diff[..., 1]) * SCALE).astype(np.int64)


def _solve(
    points: FloatArray, start: FloatArray, vehicles: int, time_limit_s: float, span_cost: int
) -> list[list[int]]:
    """Open routes (end anywhere) from node 0 = start over targets 1..n; returns target indices."""
    from ortools.constraint_solver import pywrapcp, routing_enums_pb2

    nodes = np.vstack([start.reshape(1, 2), points])
    dist = _distance_matrix(nodes)
    dist[:, 0] = 0  # returning to the depot is free: routes are open paths
    manager = pywrapcp.RoutingIndexManager(len(nodes), vehicles, 0)
    routing = pywrapcp.RoutingModel(manager)

    def arc(i: int, j: int) -> int:
        return int(dist[manager.IndexToNode(i), manager.IndexToNode(j)])

    cb = routing.RegisterTransitCallback(arc)
    routing.SetArcCostEvaluatorOfAllVehicles(cb)
    if vehicles > 1:
        routing.AddDimension(cb, 0, int(dist.max()) * len(nodes) + 1, True, "distance")
        routing.GetDimensionOrDie("distance").SetGlobalSpanCostCoefficient(span_cost)
    params = pywrapcp.DefaultRoutingSearchParameters()
    params.first_solution_strategy = routing_enums_pb2.FirstSolutionStrategy.PATH_CHEAPEST_ARC
    params.local_search_metaheuristic = routing_enums_pb2.LocalSearchMetaheuristic.GUIDED_LOCAL_SEARCH
    params.time_limit.FromMilliseconds(max(1, int(time_limit_s * 1000)))
    solution = routing.SolveWithParameters(params)
    if solution is None:
        raise RuntimeError("OR-Tools found no routing solution within the time limit")
    routes = []
    for v in range(vehicles):
        idx = routing.Start(v)
        route = []
        while not routing.IsEnd(idx):
            node = manager.IndexToNode(idx)
            if node:
                route.append(node - 1)
            idx = solution.Value(routing.NextVar(idx))
        routes.append(route)
    return routes


def minmax_routes(
    points: FloatArray, start: FloatArray, vehicles: int, time_limit_s: float = 1.0
) -> list[FloatArray]:
    """Min-max open multi-vehicle routes (OR-Tools, guided local search, ``time_limit_s`` cap)."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    s = np.asarray(start, dtype=float).reshape(2)
    order = _solve(pts, s, vehicles, time_limit_s, span_cost=100)
    return [np.vstack([s.reshape(1, 2), pts[r]]) for r in order]


def _nearest_neighbour_tour(points: FloatArray, start: FloatArray) -> list[int]:
    left = np.ones(len(points), dtype=bool)
    here, tour = start, []
    for _ in range(len(points)):
        d = np.hypot(*(points - here).T)
        d[~left] = np.inf
        i = int(np.argmin(d))
        tour.append(i)
        left[i] = False
        here = points[i]
    return tour


def tsp_tour(
    points: FloatArray, start: FloatArray, time_limit_s: float = 1.0, ortools_max: int = 1500
) -> list[int]:
    """Open TSP path from ``start`` through all points (OR-Tools when small, nearest neighbour else)."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(pts) <= ortools_max:
        return _solve(pts, np.asarray(start, dtype=float).reshape(2), 1, time_limit_s, span_cost=0)[0]
    return _nearest_neighbour_tour(pts, np.asarray(start, dtype=float).reshape(2))


def split_tour(points: FloatArray, start: FloatArray, tour: list[int], vehicles: int) -> list[list[int]]:
    """Cut ``tour`` into ``vehicles`` consecutive pieces minimising the longest start-to-piece route (DP)."""
    p = np.asarray(points, dtype=float)[tour]
    n = len(p)
    if n == 0:
        return [[] for _ in range(vehicles)]
    cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))])  # cum[i] = path to i
    reach = np.hypot(*(p - np.asarray(start).reshape(1, 2)).T)
    # best[k][j]: min over splits of targets 0..j-1 into k pieces of the longest route; piece i..j-1
    inf = np.inf
    best = np.full((vehicles + 1, n + 1), inf)
    arg = np.zeros((vehicles + 1, n + 1), dtype=np.int64)
    best[0, 0] = 0.0
    for k in range(1, vehicles + 1):
        best[k, 0] = 0.0
        for j in range(1, n + 1):
            firsts = np.arange(j)  # piece firsts[x]..j-1
            cost = np.maximum(best[k - 1, firsts], reach[firsts] + cum[j - 1] - cum[firsts])
            stay = best[k - 1, j]  # this vehicle idle
            b = int(np.argmin(cost))
            if stay <= cost[b]:
                best[k, j], arg[k, j] = stay, j
            else:
                best[k, j], arg[k, j] = cost[b], b
    pieces: list[list[int]] = []
    j = n
    for k in range(vehicles, 0, -1):
        i = int(arg[k, j])
        pieces.append([tour[x] for x in range(i, j)])
        j = i
    return pieces[::-1]


def tsp_split_routes(
    points: FloatArray, start: FloatArray, vehicles: int, time_limit_s: float = 1.0
) -> list[FloatArray]:
    """Single-tour TSP split into ``vehicles`` routes from ``start``."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    s = np.asarray(start, dtype=float).reshape(2)
    tour = tsp_tour(pts, s, time_limit_s)
    return [np.vstack([s.reshape(1, 2), pts[piece]]) for piece in split_tour(pts, s, tour, vehicles)]
