"""Lower bounds on the shortest closed tour: the Held–Karp 1-tree bound by subgradient ascent, and the
subtour cuts (connected components, global minimum cut) that tighten the LP relaxation of tour_exact.py.

A 1-tree on nodes 0…n−1 is a minimum spanning tree of nodes 1…n−1 plus the two shortest edges at
node 0. Every tour is a 1-tree, so the lightest 1-tree is no longer than the shortest tour. With node
penalties π the edge costs become c_ij + π_i + π_j; each tour's length grows by exactly 2 Σ π, so

    w(π) = (lightest 1-tree under c + π) − 2 Σ π  ≤  shortest tour          (Held & Karp 1971)

for every π. Subgradient ascent on π (g_i = degree_i − 2, Polyak steps toward an upper bound) gives
the Held–Karp bound, the value of the subtour-elimination LP. Any π gives a valid bound: the best w
seen is kept, so stopping early only weakens the bound, never invalidates it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import sparse
from scipy.sparse.csgraph import connected_components

_COMPILED = {"cache": True, "nogil": True}


@dataclass(frozen=True)
class HeldKarpBound:
    """The best 1-tree bound found (mm) and the node penalties π (mm) that give it."""

    bound_mm: float
    penalties_mm: np.ndarray  # (n,)
    iterations: int


def distance_matrix(nodes_mm: np.ndarray) -> np.ndarray:
    """(n, n) Euclidean distances (mm) between the rows of ``nodes_mm`` (n, 2)."""
    diff = nodes_mm[:, None, :] - nodes_mm[None, :, :]
    return np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))


@njit(**_COMPILED)
def one_tree(dist: np.ndarray, pi: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Lightest 1-tree under costs dist_ij + π_i + π_j: (its cost, node degrees, parent of each node
    in the spanning tree of nodes 1…n−1 (−1 at the root, node 1, and at node 0))."""
    n = dist.shape[0]
    degree = np.zeros(n, np.int64)
    parent = np.full(n, -1, np.int64)
    key = np.full(n, np.inf)
    in_tree = np.zeros(n, np.bool_)
    in_tree[0] = True  # node 0 joins through its two shortest edges below
    cost = 0.0
    key[1] = 0.0
    for _ in range(n - 1):
        best, u = np.inf, -1
        for v in range(1, n):
            if not in_tree[v] and key[v] < best:
                best, u = key[v], v
        in_tree[u] = True
        if parent[u] >= 0:
            cost += best
            degree[u] += 1
            degree[parent[u]] += 1
        for v in range(1, n):
            if not in_tree[v]:
                c = dist[u, v] + pi[u] + pi[v]
                if c < key[v]:
                    key[v], parent[v] = c, u
    first, second, a, b = np.inf, np.inf, -1, -1
    for v in range(1, n):
        c = dist[0, v] + pi[0] + pi[v]
        if c < first:
            second, b = first, a
            first, a = c, v
        elif c < second:
            second, b = c, v
    cost += first + second
    degree[0] = 2
    degree[a] += 1
    degree[b] += 1
    return cost, degree, parent


@njit(**_COMPILED)
def _ascent(dist: np.ndarray, upper_mm: float, iterations: int) -> tuple[float, np.ndarray, int]:
    n = dist.shape[0]
    pi = np.zeros(n)
    best_w, best_pi = -np.inf, pi.copy()
    step_scale, stall = 2.0, 0
    patience = max(10, n // 10)
    done = 0
    for it in range(iterations):
        done = it + 1
        cost, degree, _ = one_tree(dist, pi)
        w = cost - 2.0 * pi.sum()
        if w > best_w + 1e-12 * abs(w):
            best_w, best_pi, stall = w, pi.copy(), 0
        else:
            stall += 1
            if stall >= patience:
                step_scale *= 0.5
                stall = 0
                pi = best_pi.copy()  # restart from the best multipliers with a shorter step
        g = degree - 2.0
        norm2 = (g * g).sum()
        if norm2 == 0.0:  # the 1-tree is a tour: the bound is the optimum
            best_w, best_pi = w, pi.copy()
            break
        if step_scale < 1e-4 or upper_mm - best_w <= 1e-9 * upper_mm:
            break
        pi = pi + step_scale * (upper_mm - w) / norm2 * g
    return best_w, best_pi, done


def held_karp_bound(dist: np.ndarray, upper_mm: float, iterations: int = 2000) -> HeldKarpBound:
    """Held–Karp 1-tree lower bound (mm) on the shortest closed tour through all nodes of the
    symmetric distance matrix ``dist`` (mm), by subgradient ascent with Polyak steps toward
    ``upper_mm`` (the length of any known tour). At most ``iterations`` 1-trees of O(n²) each."""
    n = dist.shape[0]
    if n < 3:
        return HeldKarpBound(float(2.0 * dist[0].max()) if n == 2 else 0.0, np.zeros(n), 0)
    w, pi, done = _ascent(np.ascontiguousarray(dist, dtype=np.float64), float(upper_mm), int(iterations))
    return HeldKarpBound(float(w), pi, int(done))


def components(adjacency: np.ndarray) -> list[np.ndarray]:
    """Node sets of the connected components of the graph with boolean (m, m) ``adjacency``."""
    count, labels = connected_components(sparse.csr_array(adjacency), directed=False)
    return [np.flatnonzero(labels == k) for k in range(count)]


@njit(**_COMPILED)
def _stoer_wagner(weights: np.ndarray) -> tuple[float, np.ndarray]:
    m = weights.shape[0]
    w = weights.copy()
    members = np.eye(m, dtype=np.bool_)  # members[v] = original nodes merged into v
    alive = np.ones(m, np.bool_)
    best_value, best_side = np.inf, np.zeros(m, np.bool_)
    for phase in range(m - 1):
        added = np.zeros(m, np.bool_)
        key = np.zeros(m)
        prev, last = -1, -1
        for _ in range(m - phase):
            sel, top = -1, -np.inf
            for v in range(m):
                if alive[v] and not added[v] and key[v] > top:
                    sel, top = v, key[v]
            added[sel] = True
            prev, last = last, sel
            for v in range(m):
                if alive[v] and not added[v]:
                    key[v] += w[sel, v]
        if key[last] < best_value:
            best_value, best_side = key[last], members[last].copy()
        alive[last] = False  # merge the last node into the one before it
        members[prev] |= members[last]
        for v in range(m):
            w[prev, v] += w[last, v]
            w[v, prev] = w[prev, v]
        w[prev, prev] = 0.0
    return best_value, best_side


def global_min_cut(weights: np.ndarray) -> tuple[float, np.ndarray]:
    """Minimum weight cut of the undirected graph with symmetric (m, m) edge ``weights`` (Stoer–Wagner):
    (its weight, the node indices on one side). A cut lighter than 2 is a violated subtour constraint
    of the LP relaxation."""
    value, side = _stoer_wagner(np.ascontiguousarray(weights, dtype=np.float64))
    return float(value), np.flatnonzero(side)


def fast_blossoms(x: np.ndarray, ei: np.ndarray, ej: np.ndarray, m: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Violated 2-matching (blossom) inequalities of an LP solution ``x`` over the edges (ei, ej) of an
    m-node graph, by the fast heuristic of Padberg & Hong: each handle H is a connected component of
    the fractional edges (0 < x < 1), its teeth the edges at x = 1 with one end in H. With an odd
    number k ≥ 3 of disjoint teeth, every tour satisfies

        x(E(H)) + Σ x(teeth) ≤ |H| + (k − 1)/2,

    so a solution above it is cut off. Returns (handle nodes, (k, 2) teeth) of the violated ones."""
    fractional = (x > 1e-6) & (x < 1.0 - 1e-6)
    whole = x >= 1.0 - 1e-6
    adjacency = np.zeros((m, m), bool)
    adjacency[ei[fractional], ej[fractional]] = True
    adjacency |= adjacency.T
    found = []
    for handle in components(adjacency):
        if len(handle) < 2:
            continue
        inside = np.zeros(m, bool)
        inside[handle] = True
        teeth = np.flatnonzero(whole & (inside[ei] != inside[ej]))
        k = teeth.size
        ends = np.concatenate([ei[teeth], ej[teeth]])
        if k < 3 or k % 2 == 0 or np.unique(ends).size != 2 * k:
            continue
        lhs = x[inside[ei] & inside[ej]].sum() + x[teeth].sum()
        if lhs > len(handle) + (k - 1) / 2 + 1e-6:
            found.append((handle, np.column_stack([ei[teeth], ej[teeth]])))
    return found
