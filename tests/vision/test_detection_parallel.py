"""The detector's work spread over threads gives the same bits as one thread (tasks/vision/detection/parallel.py)."""

from __future__ import annotations

import dataclasses
import itertools
import threading
from itertools import pairwise

import cv2
import numpy as np
import pytest
import threadpoolctl

from tasks.machine.camera_model import CameraModel
from tasks.machine.plate import DotPlate, facing_camera_pose
from tasks.simulation.render import ImagingConditions, render_plate_image
from tasks.vision.detection import blobs, framework, parallel, perspective
from tasks.vision.detection.edges import canny_edges, gradient_magnitude, pixels_where

DIST = (-0.062, 0.115, 0.00012, -0.00018, -0.041)
PLATE_A = DotPlate(7, 7, 5.0, 2.5, dark_dots=True, margin_mm=5.0, name="a")
PLATE_B = DotPlate(7, 7, 2.0, 1.0, dark_dots=True, margin_mm=2.0, name="b")


def camera(focus_mm: float) -> CameraModel:
    return CameraModel(3072, 2048, 0.0024, 16.0, 1541.3, 1019.8, DIST, focus_distance_mm=focus_mm, f_number=8.0)


# the three regimes of the sub-pixel stage: sharp rims (pixel edge fit), blurry rims (rays on an
# area-averaged crop), a near plate under lens distortion (local homographies for the bias)
CASES = {
    "sharp": (camera(300.0), PLATE_A, facing_camera_pose([3.0, -2.0, 300.0], 0.4, 0.3, spin_deg=-5.0), -5.0),
    "blurry": (camera(80.0), PLATE_B, facing_camera_pose([1.0, 1.0, 76.0], 20.0, 10.0, spin_deg=-120.0), -120.0),
    "near": (camera(130.0), PLATE_A, facing_camera_pose([0.0, 0.0, 140.0], 5.0, -4.0, spin_deg=30.0), 30.0),
}


@pytest.fixture
def restore_threads():
    yield
    parallel.set_threads(None)
    parallel.set_kernel_threads(None)


def detection_arrays(det) -> dict[str, np.ndarray]:
    values = {f.name: getattr(det, f.name) for f in dataclasses.fields(det)}
    return {name: v for name, v in values.items() if isinstance(v, np.ndarray)}


@pytest.mark.parametrize("case", list(CASES))
def test_detections_are_bit_identical_with_one_two_and_three_threads(case, restore_threads, monkeypatch):
    cam, plate, T, angle = CASES[case]
    local = []
    one_per_neighbourhood = perspective.correct_bias_local
    monkeypatch.setattr(perspective, "correct_bias_local",
                        lambda *a, **k: local.append(1) or one_per_neighbourhood(*a, **k))
    img = render_plate_image(cam, plate, T, ImagingConditions(), seed=5)
    runs = []
    for n in (1, 2, 3):  # the stages and the compiled kernels on n threads
        parallel.set_threads(n)
        parallel.set_kernel_threads(n)
        det = framework.detect_rrht(img, plate, expected_rotation_deg=angle)
        assert det.ok, det.reason
        runs.append(detection_arrays(det))
    sigma = np.median(runs[0]["edge_sigma_px"])
    assert (sigma <= 1.5) if case == "sharp" else (sigma > 1.5)  # the regime the case is meant to cover
    assert bool(local) == (case == "near")
    for other in runs[1:]:
        assert other.keys() == runs[0].keys()
        for name, value in runs[0].items():
            assert value.tobytes() == other[name].tobytes(), name


def test_over_dots_runs_the_chunks_on_separate_threads_and_joins_them_in_order(restore_threads):
    seen = set()

    def double(a, b, *, offset):
        seen.add(threading.get_ident())
        return a * 2 + offset, b[:, ::-1]

    a, b = np.arange(20.0), np.arange(40).reshape(20, 2)
    parallel.set_threads(2)
    got = parallel.over_dots(double, 20, a, b, offset=1.0)
    assert len(seen) == 2
    assert np.array_equal(got[0], a * 2 + 1.0) and np.array_equal(got[1], b[:, ::-1])
    seen.clear()
    parallel.set_threads(1)
    parallel.over_dots(double, 20, a, b, offset=1.0)
    assert len(seen) == 1


def test_over_ranges_covers_every_dot_once_on_the_kernel_threads(restore_threads):
    seen, out = set(), np.zeros(30)

    def add_one(lo, hi):
        seen.add(threading.get_ident())
        out[lo:hi] += 1

    parallel.set_kernel_threads(2)
    parallel.over_ranges(add_one, 30)
    assert len(seen) == 2 and np.array_equal(out, np.ones(30))
    seen.clear()
    parallel.set_kernel_threads(1)
    parallel.over_ranges(add_one, 30)
    assert len(seen) == 1 and np.array_equal(out, np.full(30, 2.0))
    with pytest.raises(ValueError, match="at least 1"):
        parallel.set_kernel_threads(0)


def test_kernel_threads_are_two_on_a_quiet_host_and_one_on_a_busy_one(monkeypatch, restore_threads):
    clock = itertools.count(1e6, 10.0)  # every reading 10 s after the last: the load is read again
    monkeypatch.setattr(parallel.time, "monotonic", lambda: next(clock))
    monkeypatch.setattr(parallel.os, "sched_getaffinity", lambda pid: {0, 1})
    parallel.set_kernel_threads(None)
    for load, want in ((0.3, 2), (1.6, 2), (2.1, 1), (9.5, 1)):
        monkeypatch.setattr(parallel.os, "getloadavg", lambda load=load: (load, load, load))
        assert parallel.kernel_threads() == want, load
    monkeypatch.setattr(parallel.os, "getloadavg", lambda: (0.0, 0.0, 0.0))
    monkeypatch.setattr(parallel.os, "sched_getaffinity", lambda pid: {0})
    assert parallel.kernel_threads() == 1
    parallel.set_kernel_threads(3)
    assert parallel.kernel_threads() == 3


def test_chunks_cover_every_dot_once_and_small_batches_stay_whole():
    for n in (0, 1, 7, 8, 49, 50):
        for k in (1, 2, 3, 4):
            bounds = parallel.chunk_bounds(n, k)
            assert bounds[0][0] == 0 and bounds[-1][1] == n
            assert all(b0 == a1 for (_, a1), (b0, _) in pairwise(bounds))
            assert len(bounds) == 1 or min(b - a for a, b in bounds) >= parallel.MIN_DOTS_PER_CHUNK
    assert len(parallel.chunk_bounds(7, 2)) == 1 and len(parallel.chunk_bounds(49, 2)) == 2
    with pytest.raises(ValueError, match="at least 1"):
        parallel.set_threads(0)


@pytest.mark.parametrize("shape", [(2048, 3072), (1001, 1203), (960, 1280)])
def test_resize_area_matches_opencv_with_any_thread_count(shape, restore_threads):
    img = np.random.default_rng(sum(shape)).integers(0, 256, shape).astype(np.uint8)
    for factor in (2, 3, 4, 5):
        want = cv2.resize(img, (shape[1] // factor, shape[0] // factor), interpolation=cv2.INTER_AREA)
        for n in (1, 2, 3):
            parallel.set_kernel_threads(n)
            got = parallel.resize_area(img, factor)
            assert got.shape == want.shape and np.array_equal(got, want), (factor, n)


def test_pixels_where_is_numpys_nonzero():
    m = np.random.default_rng(3).random((37, 53)) < 0.2
    for mask in (m, m.astype(np.uint8) * 255):
        got, want = pixels_where(mask), np.nonzero(mask)
        assert all(np.array_equal(g, w) and g.dtype == w.dtype for g, w in zip(got, want, strict=True))


def test_by_default_the_stages_run_on_the_callers_thread(restore_threads):
    parallel.set_threads(None)
    assert parallel.threads() == 1 and parallel.chunk_bounds(49, parallel.threads()) == [(0, 49)]
    parallel.set_threads(3)
    assert parallel.threads() == 3
    with pytest.raises(ValueError, match="at least 1"):
        parallel.set_threads(0)


def test_nested_and_concurrent_callers_run_their_work_whole_without_waiting(restore_threads):
    parallel.set_threads(2)
    a = np.arange(40.0)

    def inner(x):  # a chunk that spreads its own work: the helpers are taken, it runs whole
        return parallel.over_dots(lambda y: (y + 1,), len(x), x)

    assert np.array_equal(parallel.over_dots(inner, 40, a)[0], a + 1)
    results = {}

    def caller(k):
        results[k] = parallel.over_dots(lambda y: (y * k,), 40, a)[0]

    workers = [threading.Thread(target=caller, args=(k,)) for k in range(4)]
    for t in workers:
        t.start()
    for t in workers:
        t.join(timeout=30)
    assert all(np.array_equal(results[k], a * k) for k in range(4))


def test_map_kernel_keeps_the_items_order_on_any_number_of_threads(restore_threads):
    items = list(range(7))
    for n in (1, 2, 3):
        seen = set()
        parallel.set_kernel_threads(n)
        got = parallel.map_kernel(lambda x, seen=seen: seen.add(threading.get_ident()) or x * x, items)
        # the calling thread takes the first group, the helpers the rest (a helper may take two)
        assert got == [x * x for x in items] and min(n, 2) <= len(seen) <= n


def test_contour_candidates_are_the_same_bits_with_one_and_two_kernel_threads(restore_threads):
    rng = np.random.default_rng(3)
    img = cv2.GaussianBlur(rng.integers(0, 256, (300, 400)).astype(np.uint8), (0, 0), 3.0)  # blobs of all sizes
    runs = []
    for n in (1, 2):
        parallel.set_kernel_threads(n)
        c = blobs.contour_candidates(img, True, 6.0, 30.0)
        runs.append(np.column_stack([c.centres, c.axes, c.theta, c.votes]))
    assert len(runs[0]) > 20 and runs[0].tobytes() == runs[1].tobytes()


def test_one_blas_thread_limits_every_blas_while_inside_and_restores_it():
    def blas_threads():
        return [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]

    before = blas_threads()
    with parallel.one_blas_thread():
        with parallel.one_blas_thread():  # nested (or another thread's) use keeps the limit
            assert blas_threads() == [1] * len(before)
        assert blas_threads() == [1] * len(before)
    assert blas_threads() == before


def copy_at(a: np.ndarray, offset: int) -> np.ndarray:
    """A copy of ``a`` starting ``offset`` bytes past a 64-byte boundary."""
    buf = np.empty(a.nbytes + 128, np.uint8)
    start = (-buf.ctypes.data) % 64 + offset
    out = buf[start : start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


def test_canny_thresholds_and_edges_do_not_depend_on_where_the_image_lies_in_memory():
    # which arrays a detection allocates where depends on the threads that ran before it; the
    # thresholds' gradient magnitudes once changed by an ulp with the alignment, and a seed pixel
    # exactly at the threshold changed the candidates (the garden's distant render 18 of seed 200)
    cam = CameraModel(640, 480, 0.0048, 8.0, 321.0, 238.0, DIST)
    plate = DotPlate(4, 3, 6.0, 4.0, dark_dots=True, margin_mm=5.0, name="small")
    img = render_plate_image(cam, plate, facing_camera_pose([2.0, -1.0, 250.0], 25.0, 10.0, spin_deg=-80.0),
                             ImagingConditions(), seed=7)
    dx, dy = cv2.spatialGradient(img, ksize=3)
    exact = np.sqrt(dx.astype(np.float64) ** 2 + dy.astype(np.float64) ** 2).astype(np.float32)  # rounded once
    runs = set()
    for offset in range(0, 64, 4):
        gx, gy = copy_at(dx, offset), copy_at(dy, offset)
        assert gradient_magnitude(gx, gy).tobytes() == exact.tobytes(), offset
        em = canny_edges(copy_at(img, offset))
        runs.add((em.low, em.high, em.edges.tobytes()))
    assert len(runs) == 1
    # on a busy image the median sets the high threshold: it is the correctly rounded magnitudes'
    busy = cv2.GaussianBlur(np.random.default_rng(0).integers(0, 256, (120, 160)).astype(np.uint8), (0, 0), 1.5)
    dx, dy = cv2.spatialGradient(busy, ksize=3)
    rounded = np.sqrt(dx[::2, ::2].astype(np.float64) ** 2 + dy[::2, ::2].astype(np.float64) ** 2).astype(np.float32)
    assert canny_edges(busy).high == 6.0 * float(np.median(rounded)) > 24.0
