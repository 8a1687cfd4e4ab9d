"""The results lake's files follow the umask, are fsync'd (file and folders) around the rename
and swap, and a step's tables are replaced together or not at all (tasks/lake/store.py)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pandas as pd
import pytest

from tasks.core import atomic_io
from tasks.lake import store as results_lake
from tasks.lake.store import read_table, write_partition, write_partitions


def rows(value: float) -> pd.DataFrame:
    return pd.DataFrame({"image_id": ["a", "b"], "value": [value, value + 1]})


@pytest.fixture
def umask():
    """Set the process umask for a test (restored after)."""
    previous = os.umask(0o022)
    os.umask(previous)
    yield lambda mask: os.umask(mask)
    os.umask(previous)


@pytest.mark.parametrize(("mask", "file_mode", "dir_mode"), [(0o022, 0o644, 0o755), (0o002, 0o664, 0o775),
                                                             (0o077, 0o600, 0o700)])
def test_lake_files_and_folders_follow_the_umask(tmp_path, umask, mask, file_mode, dir_mode):
    umask(mask)
    assert atomic_io.current_umask() == mask
    path = write_partition("extra", "c1", rows(1.0), {}, tmp_path)
    path = write_partition("extra", "c1", rows(2.0), {}, tmp_path)  # a replacement, through the swap
    assert stat.S_IMODE(path.stat().st_mode) == file_mode
    for folder in (path.parent, path.parent.parent, tmp_path / results_lake.STAGING_DIR):
        assert stat.S_IMODE(folder.stat().st_mode) == dir_mode, folder
    assert read_table("extra", tmp_path)["value"].tolist() == [2.0, 3.0]


def test_the_file_and_the_folders_are_fsynced_before_the_swap_and_after(tmp_path, monkeypatch):
    write_partition("extra", "c1", rows(1.0), {}, tmp_path)
    events: list[tuple[str, str]] = []
    real_fsync, real_swap = os.fsync, results_lake.swap_in_folder

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def swap(new, dest):
        events.append(("swap", str(dest)))
        real_swap(new, dest)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(results_lake, "swap_in_folder", swap)
    write_partition("extra", "c1", rows(2.0), {}, tmp_path)
    kinds = [(k, Path(p).name if k == "fsync" else "") for k, p in events]
    swap_at = kinds.index(("swap", ""))
    before, after = events[:swap_at], events[swap_at + 1:]
    # before the swap: the temporary Parquet file, then the staging folder that holds it after its rename
    assert before[0][1].endswith(".tmp") and ".part-0.parquet." in before[0][1]
    assert ".staging" in before[1][1] and Path(before[1][1]).parent.name == ".staging"
    # after: the table folder (the swap) and the staging area
    assert [p for _, p in after] == [str((tmp_path / "extra").resolve()),
                                     str((tmp_path / results_lake.STAGING_DIR).resolve())]


def test_tables_written_together_are_all_replaced_or_none(tmp_path):
    write_partitions({"extra": rows(1.0), "more": rows(10.0)}, "c1", {}, tmp_path)
    bad = rows(2.0).assign(campaign_id="another")  # refused while staging: nothing swapped
    with pytest.raises(ValueError, match="rows of campaign"):
        write_partitions({"extra": rows(2.0), "more": bad}, "c1", {}, tmp_path)
    assert read_table("extra", tmp_path)["value"].tolist() == [1.0, 2.0]
    assert read_table("more", tmp_path)["value"].tolist() == [10.0, 11.0]
    assert list((tmp_path / results_lake.STAGING_DIR).iterdir()) == []  # nothing left behind
    paths = write_partitions({"extra": rows(3.0), "more": rows(30.0)}, "c1", {}, tmp_path)
    assert set(paths) == {"extra", "more"}
    assert read_table("more", tmp_path)["value"].tolist() == [30.0, 31.0]
