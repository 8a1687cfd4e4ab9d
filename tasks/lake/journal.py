"""A step's partitions swapped in together, even across a kill: a roll-forward journal.

:func:`tasks.lake.store.write_partitions` stages every partition of a step, then swaps them in one
after the other. Before the first swap it writes a journal into ``<root>/.staging/``: the write's
id (also stamped into each staged file's metadata) and each (staging folder, partition folder)
pair. After the last swap the journal is deleted. A writer killed between two swaps leaves the
journal behind; the next write to the lake on the same host finds it (:func:`complete_interrupted`)
and finishes the swaps whose staged partition is still waiting — so a step's tables end all new,
never some new and some old. Between the kill and that next write a reader can see the mix.
"""

from __future__ import annotations

import fcntl
import json
import os
from pathlib import Path

import pyarrow.parquet as pq

from tasks.core.atomic_io import atomic_write_text, fsync_path, swap_in_folder

WRITE_ID_KEY = "write_id"
_SUFFIX = ".journal"


def journal_path(staging_root: Path, prefix: str, write_id: str) -> Path:
    """The journal's file: ``<staging_root>/<prefix>journal_<write_id>`` (``prefix`` names the
    writer as the staging folders do, so a dead writer's journal is recognised as such)."""
    return staging_root / f"{prefix}journal_{write_id}{_SUFFIX}"


def write_journal(path: Path, root: Path, write_id: str, swaps: list[tuple[Path, Path]]) -> None:
    """Record (staging folder, partition folder) pairs, both under ``root``, atomically and durably."""
    pairs = [[str(staging.relative_to(root)), str(dest.relative_to(root))] for staging, dest in swaps]
    atomic_write_text(path, json.dumps({WRITE_ID_KEY: write_id, "swaps": pairs}))


def file_write_id(part_file: Path) -> str | None:
    """The write id stamped in a partition file's ``fivecal`` metadata (None if absent or unreadable)."""
    try:
        meta = pq.read_schema(part_file).metadata or {}
        return json.loads(meta.get(b"fivecal", b"{}")).get(WRITE_ID_KEY)
    except (OSError, ValueError):
        return None


def complete_interrupted(root: Path, staging_root: Path, part_file: str, is_dead_writer) -> list[Path]:
    """Finish the swaps of every journal in ``staging_root`` whose writer is dead
    (``is_dead_writer(name)``); returns the partition folders swapped in now.

    A pair is done when its partition file already carries the journal's write id; otherwise the
    staged folder, if it still holds that write's file, is swapped in. The journal is then deleted
    (the dead writer's staging folders are left to the caller's clean-up). A journal another
    process is completing (locked) is skipped.
    """
    completed = []
    for journal in sorted(staging_root.glob(f"*{_SUFFIX}")):
        if not is_dead_writer(journal.name[: -len(_SUFFIX)]):
            continue
        try:
            handle = open(journal, "rb")
        except FileNotFoundError:  # completed by another process since the glob
            continue
        with handle:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue
            if not journal.exists():  # completed by another process between the glob and the lock
                continue
            try:
                record = json.loads(handle.read())
                write_id, swaps = record[WRITE_ID_KEY], record["swaps"]
            except (ValueError, KeyError, TypeError):
                continue  # not a journal of ours: left alone
            for staging_name, dest_name in swaps:
                staging, dest = root / staging_name, root / dest_name
                if file_write_id(dest / part_file) == write_id:
                    continue
                if file_write_id(staging / part_file) == write_id:
                    dest.parent.mkdir(parents=True, exist_ok=True)
                    swap_in_folder(staging, dest)
                    fsync_path(dest.parent)
                    completed.append(dest)
            os.unlink(journal)
            fsync_path(staging_root)
    return completed
