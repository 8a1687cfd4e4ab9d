"""A writer killed (SIGKILL) mid-write leaves the previous partition whole, and its staging leftovers are
never read as data."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import duckdb
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from tasks.lake.query import run_query
from tasks.lake.store import STAGING_DIR, partition_path, read_provenance, read_table, write_partition

REPO = Path(__file__).resolve().parents[2]
CHILD = """
import sys
import numpy as np, pandas as pd
from tasks.lake.store import write_partition
root, n, versions = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
i = np.arange(n)
for v in range(1, versions + 1):
    df = pd.DataFrame({"image_id": pd.Series(i % 997).astype(str), "camera": "camera1", "row": i % 7, "col": v,
                       "u_px": np.random.default_rng(v).random(n), "v_px": float(v), "residual_rms_px": 0.01,
                       "support_ratio": 1.0, "detector": "rrht"})
    print("writing", v, flush=True)
    write_partition("dots", "c1", df, {"run": v}, root)
    print("written", v, flush=True)
"""


def start_writer(root: Path, rows: int, versions: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", CHILD, str(root), str(rows), str(versions)], cwd=REPO,
                            stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})


def previous_partition(root: Path) -> tuple[pd.DataFrame, dict, bytes]:
    rng = np.random.default_rng(0)
    old = pd.DataFrame({"image_id": [f"img{k:05d}" for k in range(2000)], "camera": "camera2", "row": 3, "col": 4,
                        "u_px": rng.random(2000), "v_px": rng.random(2000), "residual_rms_px": 0.02,
                        "support_ratio": 0.9, "detector": "blob"})
    path = write_partition("dots", "c1", old, {"run": 0}, root)
    return read_table("dots", root), read_provenance("dots", "c1", root), path.read_bytes()


def test_killed_mid_write_leaves_the_previous_partition_whole_and_leftovers_unread(tmp_path):
    root = tmp_path / "results"
    before, provenance, file_bytes = previous_partition(root)
    child = start_writer(root, rows=4_000_000, versions=1)
    try:
        assert child.stdout.readline().split() == ["writing", "1"]
        staging = root / STAGING_DIR
        deadline = time.monotonic() + 60
        partial = []
        while not partial and time.monotonic() < deadline and child.poll() is None:
            partial = [p for p in root.rglob(".part-0.parquet.*.tmp") if p.stat().st_size > 0]
            time.sleep(0.002)
        assert partial, "the replacement finished (or never started) before it could be killed: make it bigger"
        child.send_signal(signal.SIGKILL)
    finally:
        child.kill()
        child.wait()
    assert child.returncode == -signal.SIGKILL
    assert child.stdout.read() == ""  # it never got past the write

    # the previous partition: the same bytes, the same rows and provenance, through every reader
    assert (partition_path("dots", "c1", root) / "part-0.parquet").read_bytes() == file_bytes
    assert sorted(p.name for p in (root / "dots").rglob("*") if p.is_file()) == ["part-0.parquet"]
    pd.testing.assert_frame_equal(read_table("dots", root), before)
    assert read_provenance("dots", "c1", root) == provenance
    assert run_query("select count(*) as n, min(detector) as d from dots", root).values.tolist() == [[2000, "blob"]]
    n = duckdb.sql(f"select count(*) from read_parquet('{root}/dots/**/*.parquet', hive_partitioning = true)")
    assert n.fetchall() == [(2000,)]

    # killed mid-write: the staging file is a Parquet file without its footer, outside the table
    assert partial[0].exists() and partial[0].parent.parent == staging and f".pid{child.pid}." in partial[0].parent.name
    with pytest.raises(Exception, match=r"(?i)parquet|footer|magic|size"):
        pq.read_metadata(partial[0])

    # the next write removes the dead writer's staging folder, and the partition is replaced whole
    write_partition("dots", "c1", before.iloc[:10], {"run": 2}, root)
    assert not partial[0].exists() and list(staging.iterdir()) == []
    assert len(read_table("dots", root)) == 10 and read_provenance("dots", "c1", root)["run"] == 2


def test_a_writer_killed_among_repeated_replacements_leaves_one_whole_version(tmp_path):
    """Killed at an arbitrary moment while replacing the partition again and again: the partition is
    exactly one version (all its rows, its own provenance), never a mix or a half."""
    root = tmp_path / "results"
    previous_partition(root)
    rows = 200_000
    child = start_writer(root, rows=rows, versions=1000)
    try:
        assert child.stdout.readline().split() == ["writing", "1"]
        assert child.stdout.readline().split() == ["written", "1"]
        time.sleep(0.7 + 0.5 * np.random.default_rng().random())
        child.send_signal(signal.SIGKILL)
    finally:
        child.kill()
        child.wait()
    df = read_table("dots", root)
    version = read_provenance("dots", "c1", root)["run"]
    assert version >= 1 and len(df) == rows
    assert (df["v_px"] == version).all() and (df["col"] == version).all()
    assert df["u_px"].to_numpy() == pytest.approx(np.random.default_rng(version).random(rows), rel=0, abs=0)


STEP_CHILD = """
import os, sys
import pandas as pd
import tasks.lake.store as store
root = sys.argv[1]
swaps = []
real_swap = store.swap_in_folder
def swap_then_die(new, dest):
    if swaps:
        os._exit(9)  # killed between the step's first and second swap
    swaps.append(dest)
    real_swap(new, dest)
store.swap_in_folder = swap_then_die
dots = pd.DataFrame({"image_id": ["a", "b"], "camera": "camera1", "row": [0, 1], "col": 2, "u_px": 1.0,
                     "v_px": 2.0, "residual_rms_px": 0.01, "support_ratio": 1.0, "detector": "rrht"})
cal = pd.DataFrame({"camera": ["camera1"], "trial": ["joint"], "status": ["ok"], "message": [""]})
store.write_partitions({"dots": dots, "camera_calibration": cal}, "c1", {"run": "new"}, root)
"""


def test_a_writer_killed_between_a_steps_swaps_is_completed_by_the_next_write(tmp_path):
    """A step writes two tables; its writer dies after the first swap. Its tables are a mix (dots new,
    camera_calibration old) until the next write to the lake, which finishes the step from the
    journal: both new, the staging area empty. A second recovery changes nothing."""
    root = tmp_path / "results"
    write_partition("dots", "c1", pd.DataFrame({"image_id": ["x"], "camera": "camera2", "row": 5, "col": 5,
                                                "u_px": 0.0, "v_px": 0.0, "residual_rms_px": 0.0,
                                                "support_ratio": 1.0, "detector": "blob"}), {"run": "old"}, root)
    old_calibration = pd.DataFrame({"camera": ["camera2"], "trial": ["t0"], "status": ["old"], "message": [""]})
    write_partition("camera_calibration", "c1", old_calibration, {"run": "old"}, root)
    child = subprocess.run([sys.executable, "-c", STEP_CHILD, str(root)], cwd=REPO, capture_output=True, text=True,
                           env={**os.environ, "PYTHONPATH": str(REPO)})
    assert child.returncode == 9, child.stderr
    staging = root / STAGING_DIR
    assert read_provenance("dots", "c1", root)["run"] == "new"
    assert read_provenance("camera_calibration", "c1", root)["run"] == "old"  # the mix a kill leaves
    assert len(list(staging.glob("*.journal"))) == 1

    write_partition("images", "other", pd.DataFrame({"image_id": ["i"]}), {"run": "unrelated"}, root)
    assert read_provenance("camera_calibration", "c1", root)["run"] == "new"
    assert read_table("camera_calibration", root).status.tolist() == ["ok"]
    assert read_table("dots", root).image_id.tolist() == ["a", "b"]
    assert list(staging.iterdir()) == []

    write_partition("images", "other", pd.DataFrame({"image_id": ["j"]}), {"run": "again"}, root)
    assert read_table("dots", root).image_id.tolist() == ["a", "b"]
    assert read_provenance("camera_calibration", "c1", root)["run"] == "new"
