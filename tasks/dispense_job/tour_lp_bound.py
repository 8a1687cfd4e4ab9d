"""A lower bound on the shortest closed tour beyond the exact range: the LP relaxation of the tour
polytope tightened with subtour and blossom cuts, solved on a sparse candidate graph and made valid
for the complete graph through its dual.

The LP is min Σ c_e x_e over 0 ≤ x ≤ 1 with x(δ(v)) = 2 at every node, x(δ(S)) ≥ 2 for the subtour
sets S found so far and x(E(H)) + x(T) ≤ |H| + (k − 1)/2 for the blossoms (H, T) found so far
(tour_bound.fast_blossoms). It is solved on the candidate edges only (near neighbours and a good
tour's edges). For any multipliers y (nodes), z_S ≥ 0 (subtour rows) and w_B ≥ 0 (blossom rows),
weak duality over all edges of the complete graph gives

    L = 2 Σ y + 2 Σ z_S − Σ w_B (|H_B| + (k_B − 1)/2) + Σ_e min(0, r_e)  ≤  shortest tour,

with r_e = c_e − y_i − y_j − Σ_{S: e ∈ δ(S)} z_S + Σ_{B: e in B's row} w_B the reduced cost of
every edge e = ij (x_e ≤ 1 bounds what a negative one can take away). The LP's own duals are used;
edges of negative reduced cost join the candidate graph for the next round (pricing), so the bound is
valid after any round and the loop may stop on its time limit. Without cuts the LP is the 2-matching
relaxation; with every subtour cut it is the Held–Karp bound (tour_bound.held_karp_bound), and the
blossoms lift it above that.

Subtour cuts come from the components of the LP solution's support, from the stretches of a good
tour whose x(δ(S)) < 2 (all of them at once, by two-dimensional prefix sums of x in tour order:
the optimum's support follows a good tour closely) and, when neither they nor the blossom heuristic
find a cut, from the global minimum cut.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.optimize import linprog
from threadpoolctl import threadpool_limits

from tasks.dispense_job.tour_bound import components, fast_blossoms, global_min_cut

_TOL = 1e-6  # violation (in x units) a cut must exceed to be added
MAX_SEGMENT_CUTS = 100  # most violated tour stretches added per round


@dataclass(frozen=True)
class LpBound:
    """The best dual bound found (mm), the LP rounds solved, and the cuts and edges at the end."""

    bound_mm: float
    rounds: int
    subtour_cuts: int
    blossom_cuts: int
    edges: int


def tour_segment_cuts(weights: np.ndarray, tour: np.ndarray, most: int = MAX_SEGMENT_CUTS) -> list[np.ndarray]:
    """Node sets of the tour's stretches S (2 ≤ |S| ≤ m − 2) with x(δ(S)) < 2, most violated first.

    weights: (m, m) symmetric LP solution x; tour: a cycle of all m nodes. With x(δ(v)) = 2 at every
    node, x(δ(S)) = 2|S| − 2 x(E(S)), and x(E(S)) of every stretch comes from the prefix sums of x
    in tour order."""
    m = tour.shape[0]
    ordered = weights[np.ix_(tour, tour)]
    prefix = np.zeros((m + 1, m + 1))
    prefix[1:, 1:] = ordered.cumsum(0).cumsum(1)
    i, j = np.triu_indices(m + 1, 2)  # the stretch of positions i … j − 1
    inner = (prefix[j, j] - prefix[i, j] - prefix[j, i] + prefix[i, i]) / 2.0
    size = j - i
    cut = 2.0 * size - 2.0 * inner
    violated = np.flatnonzero((size <= m - 2) & (cut < 2.0 - _TOL))
    violated = violated[np.argsort(cut[violated], kind="stable")][:most]
    return [tour[i[k]:j[k]] for k in violated]


def lp_tour_bound(dist: np.ndarray, tour: np.ndarray, near: np.ndarray, rounds: int = 40,
                  seconds: float = np.inf) -> LpBound:
    """Lower bound (mm) on the shortest closed tour through all nodes of the symmetric distance
    matrix ``dist`` (mm): the cut loop of the module docstring on the candidate edges ``near`` (m, k)
    (each node's near nodes) plus the edges of ``tour`` (a good cycle of all nodes), for at most
    ``rounds`` LPs and about ``seconds`` of wall time (the round under way is finished). −inf when
    not even the first LP could be solved."""
    with threadpool_limits(limits=1, user_api="blas"):  # small products: threads only contend
        return _cut_loop(dist, tour, near, rounds, seconds)


def _cut_loop(dist: np.ndarray, tour: np.ndarray, near: np.ndarray, most_rounds: int, seconds: float) -> LpBound:
    m = dist.shape[0]
    candidate = np.zeros((m, m), bool)
    candidate[np.repeat(np.arange(m), near.shape[1]), near.ravel()] = True
    candidate[tour, np.roll(tour, -1)] = True
    candidate |= candidate.T
    np.fill_diagonal(candidate, False)
    subtour_sets = np.zeros((m, 0), bool)  # one column per subtour set S
    handles = np.zeros((m, 0), bool)  # one column per blossom handle H
    teeth: list[np.ndarray] = []  # (k, 2) teeth of each blossom
    upper = np.triu(np.ones((m, m), bool), 1)
    best, rounds, t0 = -np.inf, 0, time.perf_counter()
    while True:
        rounds += 1
        ei, ej = np.nonzero(np.triu(candidate, 1))
        rhs = handles.sum(axis=0) + (np.array([len(t) for t in teeth]) - 1) / 2.0
        try:
            lp = _solve(dist, ei, ej, m, subtour_sets, handles, teeth, rhs)
        except RuntimeError:  # the solver gave up on this round: the bound so far stands
            break
        y = lp.eqlin.marginals
        duals = -np.asarray(lp.ineqlin.marginals) if lp.ineqlin.marginals.size else np.zeros(0)
        z = np.maximum(duals[: subtour_sets.shape[1]], 0.0)  # any z, w ≥ 0 keeps the bound valid
        w = np.maximum(duals[subtour_sets.shape[1]:], 0.0)
        reduced = _reduced_costs(dist, y, subtour_sets, z, handles, teeth, w)
        bound = 2.0 * y.sum() + 2.0 * z.sum() - w @ rhs + np.minimum(reduced[upper], 0.0).sum()
        best = max(best, float(bound))
        priced = (reduced < -1e-9) & ~candidate
        np.fill_diagonal(priced, False)
        candidate |= priced | priced.T
        if rounds >= most_rounds or time.perf_counter() - t0 >= seconds:
            break
        x = np.zeros((m, m))
        x[ei, ej] = lp.x
        x += x.T
        found = _subtour_sets(x, tour)
        if found:
            subtour_sets = np.hstack([subtour_sets, _columns(found, m)])
            continue
        blossoms = fast_blossoms(lp.x, ei, ej, m)
        if blossoms:
            handles = np.hstack([handles, _columns([h for h, _ in blossoms], m)])
            teeth.extend(t for _, t in blossoms)
            continue
        value, side = global_min_cut(x)  # the exact subtour separation, last as it is the dearest
        if value < 2.0 - _TOL:
            subtour_sets = np.hstack([subtour_sets, _columns([side], m)])
            continue
        if not priced.any():
            break
    return LpBound(best, rounds, subtour_sets.shape[1], handles.shape[1], int(np.triu(candidate, 1).sum()))


def _columns(node_sets: list[np.ndarray], m: int) -> np.ndarray:
    """(m, len(node_sets)) membership columns."""
    out = np.zeros((m, len(node_sets)), bool)
    for c, nodes in enumerate(node_sets):
        out[nodes, c] = True
    return out


def _solve(dist, ei, ej, m, subtour_sets, handles, teeth, rhs):
    """The LP on the candidate edges (ei, ej) with the cuts so far, by HiGHS."""
    k = ei.size
    degree = sparse.csr_array((np.ones(2 * k), (np.concatenate([ei, ej]), np.tile(np.arange(k), 2))), shape=(m, k))
    rows = [sparse.csr_array(-(subtour_sets[ei] != subtour_sets[ej]).T.astype(float))]  # −x(δ(S)) ≤ −2
    blossom_rows = (handles[ei] & handles[ej]).T.astype(float)
    keys = ei * m + ej  # ei < ej
    for r, tooth in enumerate(teeth):
        blossom_rows[r] += np.isin(keys, tooth.min(axis=1) * m + tooth.max(axis=1))
    rows.append(sparse.csr_array(blossom_rows))
    a_ub = sparse.vstack(rows).tocsr()
    b_ub = np.concatenate([-2.0 * np.ones(subtour_sets.shape[1]), rhs])
    lp = linprog(dist[ei, ej], A_ub=a_ub if b_ub.size else None, b_ub=b_ub if b_ub.size else None,
                 A_eq=degree, b_eq=2.0 * np.ones(m), bounds=(0.0, 1.0), method="highs")
    if lp.status != 0:
        raise RuntimeError(f"tour LP failed: {lp.message}")
    return lp


def _reduced_costs(dist, y, subtour_sets, z, handles, teeth, w) -> np.ndarray:
    """(m, m) reduced costs of every edge under the multipliers (module docstring); only the cuts with
    a positive multiplier (few) enter."""
    active = np.flatnonzero(z > 0.0)
    s = subtour_sets[:, active].astype(float)
    across = s @ z[active]  # Σ z_S over the sets holding each node
    crossing = across[:, None] + across[None, :] - 2.0 * (s * z[active]) @ s.T  # Σ z_S over S with e ∈ δ(S)
    active = np.flatnonzero(w > 0.0)
    h = handles[:, active].astype(float)
    in_blossom = (h * w[active]) @ h.T
    for r in active:
        a, b = teeth[r].T
        in_blossom[a, b] += w[r]
        in_blossom[b, a] += w[r]
    return dist - y[:, None] - y[None, :] - crossing + in_blossom


def _subtour_sets(x: np.ndarray, tour: np.ndarray) -> list[np.ndarray]:
    """Violated subtour sets of the LP solution x (m, m) found cheaply: the support's components,
    else the tour's stretches."""
    parts = components(x > 1e-9)
    return parts if len(parts) > 1 else tour_segment_cuts(x, tour)
