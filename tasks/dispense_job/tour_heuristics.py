"""Tour heuristics over a distance matrix (mm): nearest neighbour, the paper's simulated annealing,
and local search (2-opt and Or-opt) iterated with double-bridge kicks.

Tours are arrays of node indices, a closed cycle that starts at node 0 (the home position). All
compiled loops run on the dense distance matrix; none allocates per move beyond one tour copy.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numba import njit

_COMPILED = {"cache": True, "nogil": True}
_EPS = 1e-10  # mm; a move must gain more than this to count as an improvement
KICK_WINDOW = 100  # positions spanned by one double-bridge kick


@dataclass(frozen=True)
class AnnealingSchedule:
    """The paper's simulated-annealing settings (its Table 3): initial temperature t0 (mm of tour
    length), geometric cooling factor, and proposals per temperature level (its "iterations N").
    The paper's final value (eps −11.28) is not a temperature; the annealing stops at
    ``final_temperature`` instead, the usual setting of the MATLAB formulation it follows."""

    initial_temperature: float = 1000.0
    cooling: float = 0.98
    proposals_per_level: int = 500
    final_temperature: float = 1e-3

    @property
    def levels(self) -> int:
        """Number of temperature levels from t0 down to the final temperature."""
        ratio = self.final_temperature / self.initial_temperature
        return int(np.ceil(np.log(ratio) / np.log(self.cooling)))


PAPER_SCHEDULE = AnnealingSchedule()


@njit(**_COMPILED)
def tour_length(dist: np.ndarray, tour: np.ndarray) -> float:
    """Length (mm) of the closed tour."""
    total = 0.0
    n = tour.shape[0]
    for i in range(n):
        total += dist[tour[i], tour[(i + 1) % n]]
    return total


@njit(**_COMPILED)
def nearest_neighbour(dist: np.ndarray, first: int = 0) -> np.ndarray:
    """From node ``first``, always go to the nearest node not yet visited (ties: the lowest index);
    the cycle is returned starting at node 0."""
    n = dist.shape[0]
    tour = np.empty(n, np.int64)
    visited = np.zeros(n, np.bool_)
    tour[0], visited[first] = first, True
    for k in range(1, n):
        here, best, nxt = tour[k - 1], np.inf, -1
        for v in range(n):
            if not visited[v] and dist[here, v] < best:
                best, nxt = dist[here, v], v
        tour[k], visited[nxt] = nxt, True
    zero = np.argmin(tour)
    return np.concatenate((tour[zero:], tour[:zero]))


@njit(**_COMPILED)
def simulated_annealing(
    dist: np.ndarray, start: np.ndarray, t0: float, cooling: float, per_level: int, levels: int, seed: int
) -> np.ndarray:
    """Simulated annealing with the Metropolis rule: a proposal reverses a random stretch of the tour
    (a 2-opt move, node 0 kept first), accepted when shorter, or when longer with probability
    exp(−Δ/T); T starts at t0 and is multiplied by ``cooling`` after every ``per_level`` proposals,
    for ``levels`` levels. Returns the shortest tour met."""
    np.random.seed(seed)  # noqa: NPY002 (numba's own generator, seeded inside the compiled function)
    n = start.shape[0]
    tour = start.copy()
    best = tour.copy()
    length = tour_length(dist, tour)
    best_length = length
    temperature = t0
    if n < 4:
        return best
    for _ in range(levels):
        for _ in range(per_level):
            i = np.random.randint(1, n - 1)  # noqa: NPY002
            j = np.random.randint(i + 1, n)  # noqa: NPY002
            a, b = tour[i - 1], tour[i]
            c, d = tour[j], tour[(j + 1) % n]
            delta = dist[a, c] + dist[b, d] - dist[a, b] - dist[c, d]
            if delta < 0.0 or np.random.random() < np.exp(-delta / temperature):  # noqa: NPY002
                tour[i : j + 1] = tour[i : j + 1][::-1].copy()
                length += delta
                if length < best_length - _EPS:
                    best_length = length
                    best[:] = tour
        temperature *= cooling
    return best


@njit(**_COMPILED)
def _reverse(tour: np.ndarray, pos: np.ndarray, i: int, j: int) -> None:
    """Reverse the cyclic stretch of positions i…j (forward from i to j), or equivalently its
    complement, whichever is shorter (both give the same cycle)."""
    n = tour.shape[0]
    inner = (j - i) % n + 1
    if 2 * inner > n:  # reverse the complement j+1 … i−1 instead
        i, j = (j + 1) % n, (i - 1) % n
        inner = n - inner
    for _ in range(inner // 2):
        a, b = tour[i], tour[j]
        tour[i], pos[b] = b, i
        tour[j], pos[a] = a, j
        i = (i + 1) % n
        j = (j - 1) % n


@njit(**_COMPILED)
def _move_segment(tour: np.ndarray, pos: np.ndarray, first: int, length: int, after: int, flip: bool) -> None:
    """Cut the ``length`` nodes starting at position ``first`` and put them back right after node
    ``after`` (not in the segment), reversed when ``flip``. Shifts whichever side between the
    segment and its new place is shorter, so a move between nearby positions costs little."""
    n = tour.shape[0]
    seg = np.empty(length, np.int64)
    for k in range(length):
        seg[k] = tour[(first + k) % n]
    if flip:
        seg = seg[::-1].copy()
    last = first + length - 1
    ahead = (pos[after] - last) % n  # nodes from the segment's successor up to ``after``
    behind = n - length - ahead  # nodes from after's successor up to the segment's predecessor
    if ahead <= behind:  # pull the nodes ahead back over the segment, then write it behind them
        for k in range(1, ahead + 1):
            dst = (first + k - 1) % n
            tour[dst] = tour[(last + k) % n]
            pos[tour[dst]] = dst
        start = first + ahead
    else:  # push the nodes behind forward over the segment, then write it before them
        for k in range(1, behind + 1):
            dst = (last - k + 1) % n
            tour[dst] = tour[(first - k) % n]
            pos[tour[dst]] = dst
        start = first - behind
    for k in range(length):
        p = (start + k) % n
        tour[p] = seg[k]
        pos[seg[k]] = p


@njit(**_COMPILED)
def _improve_node(dist: np.ndarray, near: np.ndarray, tour: np.ndarray, pos: np.ndarray, a: int) -> int:
    """Apply the first improving 2-opt or Or-opt move that makes node ``a`` adjacent to one of its
    near neighbours. Returns a node whose surroundings changed (to re-examine), or −1 if none."""
    n = tour.shape[0]
    pa = pos[a]
    succ_a, pred_a = tour[(pa + 1) % n], tour[(pa - 1) % n]
    for k in range(near.shape[1]):
        c = near[a, k]
        pc = pos[c]
        # 2-opt, a–succ(a) and c–succ(c) become a–c and succ(a)–succ(c)
        d_ac = dist[a, c]
        if d_ac >= dist[a, succ_a] and d_ac >= dist[pred_a, a]:
            break  # neighbours are sorted: no nearer node can gain with a as the new end
        succ_c = tour[(pc + 1) % n]
        if c != succ_a and succ_c != a:
            delta = d_ac + dist[succ_a, succ_c] - dist[a, succ_a] - dist[c, succ_c]
            if delta < -_EPS:
                _reverse(tour, pos, (pa + 1) % n, pc)
                return c
        pred_c = tour[(pc - 1) % n]
        if c != pred_a and pred_c != a:
            delta = d_ac + dist[pred_a, pred_c] - dist[pred_a, a] - dist[pred_c, c]
            if delta < -_EPS:
                _reverse(tour, pos, pc, (pa - 1) % n)
                return c
        # Or-opt: move a segment of 1–3 nodes starting or ending at a next to c
        for length in range(1, 4):
            if length + 2 >= n:
                break
            for ends_at_a in (False, True):
                first = (pa - length + 1) % n if ends_at_a else pa
                last = (first + length - 1) % n
                s1, s2 = tour[first], tour[last]
                p, q = tour[(first - 1) % n], tour[(last + 1) % n]
                inside = (pc - first) % n < length
                if inside or c == p or c == q:
                    continue
                removed = dist[p, s1] + dist[s2, q] - dist[p, q]
                # a ends up adjacent to c: place the segment after c or before c
                for before in (False, True):
                    if before:
                        u, v = tour[(pc - 1) % n], c
                    else:
                        u, v = c, tour[(pc + 1) % n]
                    if (pos[u] - first) % n < length or (pos[v] - first) % n < length:
                        continue
                    # orientation that puts a next to c
                    flip = (a == s1) == before
                    x, y = (s2, s1) if flip else (s1, s2)
                    added = dist[u, x] + dist[y, v] - dist[u, v]
                    if added - removed < -_EPS:
                        _move_segment(tour, pos, first, length, u, flip)
                        return c
    return -1


LK_DEPTH = 12  # 2-opt steps in one chain of the Lin–Kernighan move


@njit(**_COMPILED)
def _step_reversal(tour: np.ndarray, pos: np.ndarray, t1: int, t2: int, t3: int) -> tuple[int, int, int]:
    """One step of the chain: t2 is t1's tour neighbour (the open end of the Hamiltonian path t2 … t1);
    add t2–t3 and remove the edge from t3 to its neighbour t4 on t2's side, by reversing the stretch
    t2 … t4. Returns (t4, the reversed positions i, j) so that ``_reverse(tour, pos, i, j)`` undoes it."""
    n = tour.shape[0]
    if tour[(pos[t1] + 1) % n] == t2:  # the path runs forward from t2: t4 precedes t3
        t4 = tour[(pos[t3] - 1) % n]
        i, j = pos[t2], pos[t4]
    else:  # the path runs backward from t2: t4 follows t3
        t4 = tour[(pos[t3] + 1) % n]
        i, j = pos[t4], pos[t2]
    _reverse(tour, pos, i, j)
    return t4, i, j


@njit(**_COMPILED)
def _lin_kernighan(dist: np.ndarray, near: np.ndarray, tour: np.ndarray, pos: np.ndarray, t1: int,
                   touched: np.ndarray) -> int:
    """A Lin–Kernighan move from node t1 built of sequential 2-opt steps (Lin & Kernighan 1973):
    remove t1–t2 (either tour neighbour), then repeatedly join the path's open end t2 to a near node t3
    and drop t3's edge toward it, while the partial gain stays positive and no edge added in the chain
    is removed again; every candidate t3 is tried at the first step, the best one at deeper steps, up to
    ``LK_DEPTH`` steps. The chain is cut back to the step whose closed tour is shortest; it is kept
    when that is shorter than the start. Returns the number of nodes written to ``touched`` (the
    chain's end points, to re-examine), 0 when the tour is unchanged."""
    n = tour.shape[0]
    if n < 8:
        return 0
    undo = np.empty((LK_DEPTH, 2), np.int64)
    added = np.empty((LK_DEPTH, 2), np.int64)
    ends = np.empty(LK_DEPTH + 1, np.int64)
    for side in (1, -1):
        t2_first = tour[(pos[t1] + side) % n]
        for first in range(near.shape[1]):
            t2 = t2_first
            if tour[(pos[t1] + 1) % n] != t2 and tour[(pos[t1] - 1) % n] != t2:
                break  # the tour changed under a rolled-back chain: t2_first is stale
            gain = dist[t1, t2]  # length removed minus length added so far along the path
            best_gain, best_step, steps = 0.0, 0, 0
            ends[0] = t2
            while steps < LK_DEPTH:
                forward = tour[(pos[t1] + 1) % n] == t2
                pick, pick_value = -1, -np.inf
                lo = first if steps == 0 else 0
                hi = first + 1 if steps == 0 else near.shape[1]
                for k in range(lo, hi):
                    t3 = near[t2, k]
                    g1 = gain - dist[t2, t3]
                    if g1 <= _EPS:
                        break  # neighbours are sorted: the rest cost more
                    if t3 == t1 or t3 == tour[(pos[t2] + 1) % n] or t3 == tour[(pos[t2] - 1) % n]:
                        continue
                    t4 = tour[(pos[t3] - 1) % n] if forward else tour[(pos[t3] + 1) % n]
                    tabu = False
                    for e in range(steps):
                        if (added[e, 0] == t3 and added[e, 1] == t4) or (added[e, 0] == t4 and added[e, 1] == t3):
                            tabu = True
                    if tabu:
                        continue
                    value = dist[t3, t4] - dist[t2, t3]
                    if value > pick_value:
                        pick, pick_value = t3, value
                if pick < 0:
                    break
                gain -= dist[t2, pick]
                added[steps, 0], added[steps, 1] = t2, pick
                t4, i, j = _step_reversal(tour, pos, t1, t2, pick)
                undo[steps, 0], undo[steps, 1] = i, j
                gain += dist[pick, t4]
                steps += 1
                ends[steps] = t4
                t2 = t4
                closed = gain - dist[t4, t1]
                if closed > best_gain + _EPS:
                    best_gain, best_step = closed, steps
            for s in range(steps - 1, best_step - 1, -1):  # roll back past the best step
                _reverse(tour, pos, undo[s, 0], undo[s, 1])
            if best_step > 0:
                touched[0] = t1
                for s in range(best_step + 1):
                    touched[s + 1] = ends[s]
                for s in range(best_step):
                    touched[best_step + 2 + s] = added[s, 1]
                return 2 * best_step + 2
    return 0


@njit(**_COMPILED)
def local_search(dist: np.ndarray, near: np.ndarray, tour: np.ndarray, dirty: np.ndarray) -> np.ndarray:
    """2-opt + Or-opt, then the Lin–Kernighan chain move where neither gains, with neighbour lists and
    don't-look bits, from the nodes flagged in ``dirty`` until no move gains. Works in place on ``tour``
    (node 0 is rotated back to the front at the end)."""
    n = tour.shape[0]
    pos = np.empty(n, np.int64)
    for k in range(n):
        pos[tour[k]] = k
    queue = np.empty(n, np.int64)
    queued = np.zeros(n, np.bool_)
    touched = np.empty(2 * LK_DEPTH + 2, np.int64)
    head, size = 0, 0
    for v in range(n):
        if dirty[v]:
            queue[(head + size) % n] = v
            queued[v] = True
            size += 1
    while size > 0:
        a = queue[head]
        head = (head + 1) % n
        size -= 1
        queued[a] = False
        while True:
            changed = _improve_node(dist, near, tour, pos, a)
            if changed < 0:
                count = _lin_kernighan(dist, near, tour, pos, a, touched)
                for t in range(count):
                    for v in (touched[t], tour[(pos[touched[t]] + 1) % n], tour[(pos[touched[t]] - 1) % n]):
                        if not queued[v]:
                            queue[(head + size) % n] = v
                            queued[v] = True
                            size += 1
                break
            for v in (
                changed,
                tour[(pos[a] + 1) % n],
                tour[(pos[a] - 1) % n],
                tour[(pos[changed] + 1) % n],
                tour[(pos[changed] - 1) % n],
            ):
                if not queued[v] and v != a:
                    queue[(head + size) % n] = v
                    queued[v] = True
                    size += 1
    start = pos[0]
    return np.concatenate((tour[start:], tour[:start]))


@njit(**_COMPILED)
def _double_bridge(tour: np.ndarray, window: int, dirty: np.ndarray) -> np.ndarray:
    """A segment double-bridge kick: three random cuts within ``window`` consecutive positions swap
    the two middle stretches (A B C D → A C B D); flags the eight end nodes in ``dirty``."""
    n = tour.shape[0]
    w = min(window, n - 1)
    start = np.random.randint(0, n)  # noqa: NPY002
    cuts = np.sort(np.random.choice(w - 1, 3, replace=False) + 1)  # noqa: NPY002
    rolled = np.concatenate((tour[start:], tour[:start]))
    i, j, k = cuts[0], cuts[1], cuts[2]
    out = np.concatenate((rolled[:i], rolled[j:k], rolled[i:j], rolled[k:]))
    for p in (0, i - 1, i, j - 1, j, k - 1, k % n, n - 1):
        dirty[rolled[p]] = True
    return out


@njit(**_COMPILED)
def _kick_rounds(dist: np.ndarray, near: np.ndarray, tour: np.ndarray, kicks: int, seed: int) -> np.ndarray:
    """``kicks`` double-bridge kicks on a locally optimal tour, each followed by local search around
    the kick and kept if the tour got shorter."""
    np.random.seed(seed)  # noqa: NPY002 (numba's own generator, seeded inside the compiled function)
    n = dist.shape[0]
    length = tour_length(dist, tour)
    window = min(n - 1, KICK_WINDOW)
    dirty = np.zeros(n, np.bool_)
    for _ in range(kicks):
        dirty[:] = False
        trial = local_search(dist, near, _double_bridge(tour, window, dirty), dirty)
        trial_length = tour_length(dist, trial)
        if trial_length < length - _EPS:
            tour, length = trial, trial_length
    return tour


def iterated_local_search(
    dist: np.ndarray, near: np.ndarray, start: np.ndarray, kicks: int, seconds: float, seed: int
) -> np.ndarray:
    """Local search (2-opt + Or-opt) from ``start``, then up to ``kicks`` double-bridge kicks in
    rounds of 256, stopping after the round that passes ``seconds`` of wall time. Deterministic for
    a given seed whenever the kick count, not the clock, ends the search."""
    n = dist.shape[0]
    tour = local_search(dist, near, np.asarray(start, np.int64).copy(), np.ones(n, np.bool_))
    if n < 8:
        return tour
    t0 = time.perf_counter()
    done, round_no = 0, 0
    while done < kicks and time.perf_counter() - t0 < seconds:
        batch = min(256, kicks - done)
        tour = _kick_rounds(dist, near, tour, batch, seed * 100003 + round_no)
        done += batch
        round_no += 1
    return tour


def near_neighbours(dist: np.ndarray, count: int) -> np.ndarray:
    """(n, k) the ``count`` nearest other nodes of each node, nearest first."""
    n = dist.shape[0]
    k = min(count, n - 1)
    masked = dist + np.diag(np.full(n, np.inf))
    idx = np.argpartition(masked, k - 1, axis=1)[:, :k]
    order = np.argsort(np.take_along_axis(masked, idx, axis=1), axis=1)
    return np.ascontiguousarray(np.take_along_axis(idx, order, axis=1))
