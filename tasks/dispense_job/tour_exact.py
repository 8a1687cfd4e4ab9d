"""The dispensing tour over many boards: the shortest closed tour from the home position through every
dispensing point, proven optimal by integer programming up to ``EXACT_MAX_POINTS`` points, and beside
it the paper's simulated annealing, nearest neighbour and the return-to-origin path on the same points.

The exact method is the Dantzig–Fulkerson–Johnson formulation on the complete graph of home + points
(one binary per edge, every node of degree 2) solved by HiGHS (``scipy.optimize.linprog``/``milp``):
the LP relaxation is tightened with subtour cuts (components of the support graph, the global minimum
cut) and blossom inequalities, edges whose reduced cost rules them out of any tour shorter than a
known one are dropped, and the integer program on the rest takes the subtours of its solutions as
further cuts until the solution is one cycle. That cycle is optimal for the full problem because
every subtour constraint left out is satisfied by it. Beyond the exact range, iterated local search
with tour merging gives the tour, and the larger of the Held–Karp bound (tour_bound.py) and the LP
bound with subtour and blossom cuts (tour_lp_bound.py) states how far from the optimum it can be.
docs/dispense-job-paths.md has the details."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.optimize import Bounds, LinearConstraint, linprog, milp

from tasks.dispense_job import tour_heuristics as heur
from tasks.dispense_job.tour_bound import components, distance_matrix, fast_blossoms, global_min_cut, held_karp_bound
from tasks.dispense_job.tour_lp_bound import lp_tour_bound

EXACT_MAX_POINTS = 60  # the integer program is run up to this many points (home not counted)
EXACT_SECONDS = 30.0  # beyond this the integer program gives up and the search's tour and bound stand
METHODS = ("optimal", "annealing", "nearest", "return_to_origin", "given_order")
NEAR_COUNT = 8  # neighbour-list length of the local search
LARGE_SEARCH_SECONDS = 10.0  # wall-time cap of the local searches beyond the exact range (a safety net:
# the kick count ends them first on an unloaded core, and then the tour depends on the seed alone)
MERGED_RUNS = 8  # independent local searches recombined by tour merging
KICKS_PER_NODE = 10  # double-bridge kicks of each local search, per node
SEARCH_THREADS = 2  # the machine's cores: the independent searches run side by side
MERGE_SECONDS = 2.0  # wall-time cap of the merging integer program; past it the best single run stands
LP_NEAR_COUNT = 5  # candidate edges per node of the LP bound (tour_lp_bound.py), before pricing
LP_ROUNDS = 40  # most LPs of its cut loop (it converges in 22–36 on 500 uniform points)
LP_SECONDS = 5.0  # wall-time cap of the cut loop (a safety net, as LARGE_SEARCH_SECONDS)


@dataclass(frozen=True)
class Tour:
    """A closed dispensing tour home → points[order[0]] → … → points[order[-1]] → home.

    ``length_mm`` is its length (for ``return_to_origin``: home → each point → home, in ``order``);
    ``lower_bound_mm`` a proven lower bound on the shortest closed tour through home and the points;
    ``proven_optimal`` says the length equals that bound (to 1e-9 relative); ``seconds`` is the
    planning wall time."""

    order: np.ndarray
    length_mm: float
    lower_bound_mm: float
    proven_optimal: bool
    method: str
    seconds: float

    @property
    def gap(self) -> float:
        """Relative excess of the tour over the lower bound (0 for a proven optimum)."""
        return self.length_mm / self.lower_bound_mm - 1.0 if self.lower_bound_mm > 0 else 0.0


def plan_tour(
    points_mm: np.ndarray,
    home_mm: tuple[float, float] | np.ndarray = (0.0, 0.0),
    method: str = "optimal",
    seed: int = 0,
    *,
    exact_max_points: int = EXACT_MAX_POINTS,
    search_seconds: float = LARGE_SEARCH_SECONDS,
) -> Tour:
    """Plan the visiting order of ``points_mm`` (n, 2) machine XY (mm), starting and ending at
    ``home_mm``.

    method: ``optimal`` (proven optimum up to ``exact_max_points`` points, else iterated local search
    for up to ``search_seconds`` with its Held–Karp bound), ``annealing`` (the paper's simulated
    annealing, Table 3), ``nearest`` (nearest neighbour), ``return_to_origin`` (the paper's traditional
    path: back home after every point, points in the given order), ``given_order`` (the points in the
    given order, one closed tour). ``seed`` drives the random choices of annealing and local search."""
    if method not in METHODS:
        raise ValueError(f"unknown tour method {method!r}; expected one of {', '.join(METHODS)}")
    pts = _checked_points(points_mm)
    home = np.asarray(home_mm, dtype=float).reshape(2)
    t0 = time.perf_counter()
    n = pts.shape[0]
    if n == 0:
        return Tour(np.zeros(0, np.int64), 0.0, 0.0, True, method, time.perf_counter() - t0)
    dist = distance_matrix(np.vstack([home, pts]))
    exact = None
    if method == "optimal" and n <= exact_max_points:
        try:
            exact = _exact(dist, seed)
        except TimeoutError:  # a pathological layout: fall back to the search and its bound
            exact = None
    if exact is not None:
        order, length, bound = exact
    else:
        order, length, bound = _by_heuristic(dist, method, seed, search_seconds)
    proven = length <= bound * (1.0 + 1e-9)
    return Tour(order, float(length), float(min(bound, length)), bool(proven), method, time.perf_counter() - t0)


def tour_path_mm(points_mm: np.ndarray, tour: Tour, home_mm=(0.0, 0.0)) -> np.ndarray:
    """(k, 2) machine XY waypoints (mm) the head passes through, home first and last: for the
    return-to-origin tour home sits between every two points."""
    pts = _checked_points(points_mm)
    home = np.asarray(home_mm, dtype=float).reshape(1, 2)
    visits = pts[tour.order]
    if tour.method == "return_to_origin":
        stops = np.empty((2 * len(visits), 2))
        stops[0::2] = visits
        stops[1::2] = home
        return np.vstack([home, stops])
    return np.vstack([home, visits, home])


def _checked_points(points_mm: np.ndarray) -> np.ndarray:
    pts = np.asarray(points_mm, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"points_mm must be an (n, 2) array of machine XY in mm, got shape {pts.shape}")
    bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))
    if bad.size:
        raise ValueError(f"points_mm row {bad[0]} is not finite: {pts[bad[0]].tolist()}")
    return pts


def _as_order(node_tour: np.ndarray) -> np.ndarray:
    """Point indices in visiting order from a node cycle that starts at node 0 (home)."""
    return np.asarray(node_tour[1:], np.int64) - 1


def _good_tour(dist: np.ndarray, seed: int, seconds: float) -> tuple[np.ndarray, float]:
    """A short tour and a lower bound (mm). Local search from nearest neighbour gives the upper bound
    for the Held–Karp ascent; ``MERGED_RUNS`` iterated local searches (2-opt, Or-opt and the
    Lin–Kernighan chain move; ``seconds`` shared between them, ``SEARCH_THREADS`` at a time) on
    neighbour lists ranked by the penalised costs c_ij + π_i + π_j (closer to the optimal tour's edges
    than plain distance), from nearest-neighbour tours begun at home and at random nodes (different
    good tours share most edges but not all), are then recombined by the integer program on the union
    of their edges (tour merging), which is never longer than the best of them. The bound is the larger
    of Held–Karp's and the LP bound with subtour and blossom cuts (tour_lp_bound.py) around the tour.
    With ``seconds`` ≤ 0: the first local search and the Held–Karp bound only."""
    n = dist.shape[0]
    start = heur.local_search(dist, heur.near_neighbours(dist, NEAR_COUNT), heur.nearest_neighbour(dist),
                              np.ones(n, np.bool_))
    bound = held_karp_bound(dist, float(heur.tour_length(dist, start)))
    if seconds <= 0.0:
        return start, bound.bound_mm
    pi = bound.penalties_mm
    near = heur.near_neighbours(dist + pi[:, None] + pi[None, :], NEAR_COUNT)
    firsts = np.random.default_rng(seed).integers(1, n, MERGED_RUNS - 1)
    starts = [start] + [heur.nearest_neighbour(dist, int(first)) for first in firsts]
    with ThreadPoolExecutor(SEARCH_THREADS) as pool:  # the compiled search releases the GIL
        tours = list(pool.map(
            lambda run: heur.iterated_local_search(dist, near, starts[run], kicks=KICKS_PER_NODE * n,
                                                   seconds=seconds * SEARCH_THREADS / MERGED_RUNS,
                                                   seed=seed * MERGED_RUNS + run),
            range(MERGED_RUNS)))
    best = min(tours, key=lambda t: heur.tour_length(dist, t))
    edges = np.sort(np.concatenate([np.stack([t, np.roll(t, -1)], axis=1) for t in tours]), axis=1)
    ei, ej = np.unique(edges, axis=0).T
    try:
        merged, _ = shortest_cycle_on_edges(dist, ei, ej, seconds=MERGE_SECONDS)
        if heur.tour_length(dist, merged) < heur.tour_length(dist, best):
            best = merged
    except TimeoutError:  # the merge ran out of time: keep the best single run
        pass
    tightened = lp_tour_bound(dist, best, near[:, :LP_NEAR_COUNT], rounds=LP_ROUNDS, seconds=LP_SECONDS)
    return best, max(bound.bound_mm, tightened.bound_mm)


def _by_heuristic(dist: np.ndarray, method: str, seed: int, seconds: float) -> tuple[np.ndarray, float, float]:
    m = dist.shape[0]
    identity = np.arange(m, dtype=np.int64)
    if m <= 3:
        reference, bound = identity, float(heur.tour_length(dist, identity))
    else:
        reference, bound = _good_tour(dist, seed, seconds if method == "optimal" else 0.0)
    if method == "optimal":
        tour = reference
    elif method == "annealing":
        s = heur.PAPER_SCHEDULE
        tour = heur.simulated_annealing(dist, identity, s.initial_temperature, s.cooling,
                                        s.proposals_per_level, s.levels, seed)
    elif method == "nearest":
        tour = heur.nearest_neighbour(dist)
    else:
        tour = identity
    if method == "return_to_origin":
        length = 2.0 * float(dist[0, 1:].sum())
    else:
        length = float(heur.tour_length(dist, tour))
    return _as_order(tour), length, bound


def _cut_row(nodes: np.ndarray, ei: np.ndarray, ej: np.ndarray, m: int) -> np.ndarray:
    """0/1 row over the edges with exactly one end in ``nodes``: the edges crossing the cut."""
    inside = np.zeros(m, bool)
    inside[nodes] = True
    return (inside[ei] != inside[ej]).astype(float)


def _exact(dist: np.ndarray, seed: int) -> tuple[np.ndarray, float, float]:
    """Shortest closed tour over all nodes of ``dist``: (point order, length, lower bound), mm."""
    m = dist.shape[0]
    if m <= 3:
        tour = np.arange(m)
        length = float(heur.tour_length(dist, tour))
        return _as_order(tour), length, length
    upper = heur.iterated_local_search(dist, heur.near_neighbours(dist, NEAR_COUNT), heur.nearest_neighbour(dist),
                                       kicks=50 * m, seconds=0.1, seed=seed)
    ei, ej = np.triu_indices(m, k=1)
    tour, bound = shortest_cycle_on_edges(dist, ei, ej, upper_tour=upper, seconds=EXACT_SECONDS)
    length = float(heur.tour_length(dist, tour))
    return _as_order(tour), length, min(bound, length)


def shortest_cycle_on_edges(
    dist: np.ndarray, ei: np.ndarray, ej: np.ndarray, upper_tour: np.ndarray | None = None, seconds: float = np.inf
) -> tuple[np.ndarray, float]:
    """Shortest cycle through all nodes using only the edges (ei[k], ej[k]), by integer programming
    with subtour cuts: (node order from node 0, the solver's lower bound in mm). On the complete
    graph this is the optimal tour; on the union of a few good tours it is their best recombination
    (tour merging).

    With ``upper_tour`` (a cycle on these edges), the LP relaxation is first tightened with subtour
    cuts (components, then the global minimum cut) and blossom inequalities, and every edge whose
    reduced cost r_e exceeds U − z_LP is dropped (U the upper tour's length): a tour using it costs at
    least z_LP + r_e > U, so the optimum is among the remaining edges plus those of the upper tour."""
    m = dist.shape[0]
    subtours: list[np.ndarray] = []  # node sets S with x(δ(S)) ≥ 2
    blossoms: list[tuple[np.ndarray, np.ndarray]] = []  # (handle, teeth) from tour_bound.fast_blossoms

    def add_subtour(nodes: np.ndarray) -> None:
        subtours.append(nodes if 2 * len(nodes) <= m else np.setdiff1d(np.arange(m), nodes))

    def incidence_of(ei: np.ndarray, ej: np.ndarray) -> sparse.csr_array:
        k = ei.size
        return sparse.csr_array((np.ones(2 * k), (np.concatenate([ei, ej]), np.tile(np.arange(k), 2))), shape=(m, k))

    def cut_rows(ei: np.ndarray, ej: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rows over the edges (ei, ej) and their bounds: lower ≤ row · x ≤ upper."""
        rows = [_cut_row(side, ei, ej, m) for side in subtours]
        lower = [2.0] * len(subtours)
        upper = [np.inf] * len(subtours)
        for handle, teeth in blossoms:
            inside = np.zeros(m, bool)
            inside[handle] = True
            tooth = np.zeros((m, m), bool)
            tooth[teeth[:, 0], teeth[:, 1]] = True
            tooth |= tooth.T
            rows.append((inside[ei] & inside[ej]).astype(float) + tooth[ei, ej])
            lower.append(-np.inf)
            upper.append(len(handle) + (len(teeth) - 1) / 2)
        return np.vstack(rows), np.array(lower), np.array(upper)

    if upper_tour is not None:
        upper_length = float(heur.tour_length(dist, upper_tour))
        on_upper = np.zeros((m, m), bool)
        on_upper[upper_tour, np.roll(upper_tour, -1)] = True
        on_upper |= on_upper.T
        for _ in range(10 * m):
            cost = dist[ei, ej]
            a_ub = b_ub = None
            if subtours or blossoms:
                rows, lower, upper = cut_rows(ei, ej)
                flip = np.isfinite(lower)  # lower ≤ row·x becomes −row·x ≤ −lower
                a_ub = sparse.csr_array(np.where(flip[:, None], -rows, rows))
                b_ub = np.where(flip, -lower, upper)
            lp = linprog(cost, A_ub=a_ub, b_ub=b_ub, A_eq=incidence_of(ei, ej), b_eq=2.0 * np.ones(m),
                         bounds=(0.0, 1.0), method="highs")
            if lp.status != 0:
                raise RuntimeError(f"tour LP failed: {lp.message}")
            # reduced-cost fixing, valid after any round: z_LP bounds every tour from below
            keep = lp.lower.marginals <= upper_length - lp.fun + 1e-9 * max(lp.fun, 1.0)
            keep |= on_upper[ei, ej]
            x, ei, ej = lp.x[keep], ei[keep], ej[keep]
            weights = np.zeros((m, m))
            weights[ei, ej] = x
            weights += weights.T
            parts = components(weights > 1e-9)
            if len(parts) > 1:
                for part in parts:
                    add_subtour(part)
                continue
            value, side = global_min_cut(weights)
            if value < 2.0 - 1e-6:
                add_subtour(side)
                continue
            found = fast_blossoms(x, ei, ej, m)
            if found:
                blossoms.extend(found)
                continue
            break
    cost = dist[ei, ej]
    incidence = incidence_of(ei, ej)
    # integer program: add the subtours of each integer solution until it is one cycle
    t0 = time.perf_counter()
    while True:
        constraints = [LinearConstraint(incidence, 2.0, 2.0)]
        if subtours or blossoms:
            constraints.append(LinearConstraint(*cut_rows(ei, ej)))
        left = seconds - (time.perf_counter() - t0)
        options = {"mip_rel_gap": 1e-9} | ({"time_limit": max(left, 0.01)} if np.isfinite(left) else {})
        res = milp(cost, integrality=np.ones(cost.size), bounds=Bounds(0.0, 1.0), constraints=constraints,
                   options=options)
        if res.status == 1:
            raise TimeoutError(f"tour integer program stopped at its {seconds:g} s limit")
        if res.status != 0 or res.x is None:
            raise RuntimeError(f"tour integer program failed: {res.message}")
        chosen = res.x > 0.5
        adjacency = np.zeros((m, m), bool)
        adjacency[ei[chosen], ej[chosen]] = True
        adjacency |= adjacency.T
        parts = components(adjacency)
        if len(parts) == 1:
            break
        for part in parts:
            add_subtour(part)
    return _cycle_from_adjacency(adjacency), float(getattr(res, "mip_dual_bound", res.fun))


def _cycle_from_adjacency(adjacency: np.ndarray) -> np.ndarray:
    """Node order of the single cycle in a 0/1 adjacency matrix, from node 0 toward its lower-index
    neighbour."""
    m = adjacency.shape[0]
    tour = np.empty(m, np.int64)
    prev, here = -1, 0
    for k in range(m):
        tour[k] = here
        nxt = [v for v in np.flatnonzero(adjacency[here]) if v != prev]
        prev, here = here, nxt[0]
    return tour
