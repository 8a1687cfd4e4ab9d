"""Detection work spread over threads, with results that do not depend on it.

The sub-pixel stages (:mod:`tasks.vision.detection.subpixel`, :mod:`tasks.vision.detection.edge_fit`)
work on all dots of a plate at once, and each dot's numbers come from that dot's rows alone
(every sum runs along a dot's own rays or pixels, random draws are made for all dots beforehand).
Cutting the dots into contiguous chunks, one per thread, therefore gives bit for bit the batch's
result. numpy's array loops and the compiled loops (``nogil``) release the GIL, so the chunks
run on separate cores. :func:`resize_area` does the same for the area-averaged copies of the image
(the coarse search's downsampling, the pass-2 crops of blurry rims), in blocks of rows.

Two settings. :func:`set_threads` spreads whole stages (:func:`over_dots`); it is off by default
(one thread, the caller's): on the 2-CPU bench host, idle, two threads gave RRHT no wall time
(28.6 ms per full-size image against 28.2 ms with one) for 30 % more CPU time
(``bench/bench_detection.py`` and ``--threads 1``, commit 5dc2319): per dot those stages are many
small array operations, and their Python between them holds the GIL. :func:`set_kernel_threads`
spreads the parts whose time is compiled loops, OpenCV or large array operations, all of which
release the GIL (:func:`over_dots_compiled`, :func:`over_ranges`, :func:`resize_area`,
:func:`map_kernel`: the pixel edge fit's normal equations, pass 2's step fits, the area-averaged
copies, the region-contour candidates' threshold windows); by default on 2
threads while the host has a free CPU, else on the caller's (:func:`kernel_threads`;
docs/detector-comparison.md, "Speed", for what it gains and costs). One caller at a time spreads
its work; others run theirs whole.

SYNOPSIS

    >>> import numpy as np
    >>> from tasks.vision.detection.parallel import over_dots
    >>> float(over_dots(lambda a, b: (a + b,), 12, np.arange(12.0), np.ones(12))[0][-1])
    12.0
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from itertools import pairwise
from typing import TypeVar

import cv2
import numpy as np
import scipy.linalg.cython_blas  # noqa: F401 - the BLAS the compiled kernels call, loaded before the controller
from threadpoolctl import ThreadpoolController

T = TypeVar("T")
MIN_DOTS_PER_CHUNK = 4  # fewer dots than this per thread are not worth a thread's start-up

_state: dict = {"threads": None, "kernel_threads": None, "pool": None, "pid": None, "workers": 0,
                "load_read": -1e9, "free_core": False}
_spreading = threading.Lock()  # held by the one caller whose work is on the helper threads
_blas: dict = {"controller": None, "limiter": None, "users": 0}
_blas_lock = threading.Lock()


def set_threads(n: int | None) -> None:
    """Spread the detection stages over ``n`` threads (1: none besides the caller's); None: the
    default, one."""
    if n is not None and n < 1:
        raise ValueError(f"threads must be at least 1, got {n}")
    _state["threads"] = n


def threads() -> int:
    """Threads the detection stages are spread over (:func:`set_threads`; default 1)."""
    return _state["threads"] or 1


def set_kernel_threads(n: int | None) -> None:
    """Share the compiled kernels' dots among ``n`` threads (1: the caller's only); None: the
    default, :func:`kernel_threads`."""
    if n is not None and n < 1:
        raise ValueError(f"threads must be at least 1, got {n}")
    _state["kernel_threads"] = n


def kernel_threads() -> int:
    """Threads the compiled kernels (which release the GIL) share their dots among
    (:func:`set_kernel_threads`). Default: 2 while the host is not busy (its 1-minute load average
    below the number of CPUs this process may run on, read at most once a second; a lone detection
    with OpenCV's threads keeps it about 1–1.5 on 2 CPUs), else 1: a helper thread that has to wait
    for a core costs CPU time and gains no wall time (docs/detector-comparison.md, "Speed"). The
    results are the same either way."""
    if _state["kernel_threads"]:
        return _state["kernel_threads"]
    now = time.monotonic()
    if now - _state["load_read"] >= 1.0:
        cpus = len(os.sched_getaffinity(0))
        _state["free_core"] = cpus >= 2 and os.getloadavg()[0] < cpus
        _state["load_read"] = now
    return 2 if _state["free_core"] else 1


def _pool(workers: int) -> ThreadPoolExecutor:
    """The helper threads (created once per process: a forked child makes its own)."""
    pool = _state["pool"]
    if pool is None or _state["pid"] != os.getpid() or _state["workers"] < workers:
        if pool is not None and _state["pid"] == os.getpid():
            pool.shutdown(wait=False)  # too few helpers: replaced by a larger pool
        pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="fivecal-dots")
        _state.update(pool=pool, pid=os.getpid(), workers=workers)
    return pool


def chunk_bounds(n: int, n_threads: int, min_chunk: int = MIN_DOTS_PER_CHUNK) -> list[tuple[int, int]]:
    """Contiguous (start, stop) ranges covering 0…n, at most ``n_threads`` of them and each at least
    ``min_chunk`` long (one range when n is small)."""
    k = max(1, min(n_threads, n // min_chunk))
    edges = np.linspace(0, n, k + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in pairwise(edges)]


def _spread(run: Callable[[tuple[int, int]], object], bounds: list[tuple[int, int]]) -> list | None:
    """[run(b) for b in bounds], the first on the calling thread and the others on the helpers; None
    (nothing run) when another caller's work is on the helpers (or this is a helper thread)."""
    if not _spreading.acquire(blocking=False):
        return None
    try:
        futures = [_pool(len(bounds) - 1).submit(run, b) for b in bounds[1:]]
        return [run(bounds[0])] + [f.result() for f in futures]
    finally:
        _spreading.release()


def over_dots(fn: Callable[..., tuple], n: int, *per_dot: np.ndarray | None, **shared) -> tuple:
    """``fn(*per_dot, **shared)`` with the per-dot arrays (first axis: the n dots; None passes
    through) cut into chunks run on :func:`threads` threads; fn returns a tuple of arrays whose
    first axis is the chunk's dots, and the chunks' tuples are joined along it."""
    return _over_dots(fn, n, threads(), per_dot, shared)


def over_dots_compiled(fn: Callable[..., tuple], n: int, *per_dot: np.ndarray | None, **shared) -> tuple:
    """:func:`over_dots` on :func:`kernel_threads` threads, for a ``fn`` whose time goes to compiled
    loops and large array operations that release the GIL."""
    return _over_dots(fn, n, kernel_threads(), per_dot, shared)


def _over_dots(fn: Callable[..., tuple], n: int, n_threads: int, per_dot: tuple, shared: dict) -> tuple:
    bounds = chunk_bounds(n, n_threads)

    def run(lo_hi: tuple[int, int]) -> tuple:
        lo, hi = lo_hi
        return fn(*(None if a is None else a[lo:hi] for a in per_dot), **shared)

    parts = _spread(run, bounds) if len(bounds) > 1 else None
    if parts is None:
        return fn(*per_dot, **shared)
    return tuple(np.concatenate(arrays, axis=0) for arrays in zip(*parts, strict=True))


def over_ranges(run: Callable[[int, int], None], n: int) -> None:
    """``run(lo, hi)`` over contiguous ranges covering 0…n, on :func:`kernel_threads` threads
    (the first range on the calling thread); ``run`` writes its range's results into arrays it
    shares with the other ranges. For compiled loops that release the GIL."""
    bounds = chunk_bounds(n, kernel_threads())
    if len(bounds) == 1 or _spread(lambda lo_hi: run(*lo_hi), bounds) is None:
        run(0, n)


def map_kernel(fn: Callable[[object], T], items: list) -> list[T]:
    """``[fn(x) for x in items]`` with the items cut into contiguous groups, one per
    :func:`kernel_threads` thread (the first on the calling thread), for a ``fn`` whose time goes to
    OpenCV and compiled loops that release the GIL; each result is its item's, whatever the split."""
    bounds = chunk_bounds(len(items), kernel_threads(), min_chunk=1)

    def run(lo_hi: tuple[int, int]) -> list[T]:
        return [fn(x) for x in items[lo_hi[0] : lo_hi[1]]]

    parts = _spread(run, bounds) if len(bounds) > 1 else None
    return [fn(x) for x in items] if parts is None else [r for part in parts for r in part]


def resize_area(image: np.ndarray, factor: int) -> np.ndarray:
    """``cv2.resize(image, (W // factor, H // factor), interpolation=cv2.INTER_AREA)`` of an (H, W)
    image. When factor divides H and W, each output row is the mean of its own ``factor`` input
    rows (OpenCV's integer-scale path), so blocks of rows are resized on :func:`kernel_threads`
    threads (OpenCV releases the GIL) and give the same bits."""
    h, w = image.shape[:2]
    size = (w // factor, h // factor)
    bounds = chunk_bounds(size[1], kernel_threads() if h % factor == 0 and w % factor == 0 else 1)
    out = np.empty((size[1], size[0], *image.shape[2:]), image.dtype)

    def run(lo_hi: tuple[int, int]) -> None:
        lo, hi = lo_hi
        out[lo:hi] = cv2.resize(image[lo * factor : hi * factor], (size[0], hi - lo), interpolation=cv2.INTER_AREA)

    if len(bounds) == 1 or _spread(run, bounds) is None:
        return cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    return out


@contextmanager
def one_blas_thread():
    """Within this context the BLAS libraries run each product on the calling thread alone (all
    threads of the process; the first caller in sets it, the last one out restores the libraries'
    own settings). For kernels that call BLAS on many small products (the pixel edge fit's 10 × M
    Jacobian times its transpose, once per dot and iteration), already spread over
    :func:`kernel_threads`: OpenBLAS's own threads, spinning while they wait for the next product,
    made the fit of 12 dots of 400 px (10–18 thousand rim pixels each) take 0.3–1.5 s of CPU against
    0.1 s, and the more so the busier the host (docs/detector-comparison.md, "Speed"). It also
    makes the results independent of the BLAS threads the host offers: compared with two threads
    on 273 images, one dot's minor axis differed by 7e-15 px, every centre the same bits."""
    with _blas_lock:
        if _blas["users"] == 0:
            if _blas["controller"] is None:
                _blas["controller"] = ThreadpoolController()
            _blas["limiter"] = _blas["controller"].limit(limits=1, user_api="blas")
        _blas["users"] += 1
    try:
        yield
    finally:
        with _blas_lock:
            _blas["users"] -= 1
            if _blas["users"] == 0:
                _blas["limiter"].restore_original_limits()
                _blas["limiter"] = None
