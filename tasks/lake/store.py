"""The Parquet results lake: one dataset per table, hive-partitioned by ``campaign_id``.

SYNOPSIS::

    from tasks.lake.store import read_table, write_partition
    write_partition("images", "c2026w02", images_df, {"fivecal_version": "0.1.0", ...})
    images = read_table("images")                       # every campaign
    one = read_table("images", campaign_id="c2026w02")  # one campaign

Layout (design §4)::

    <root>/<table>/campaign_id=<id>/part-0.parquet
    <root>/.staging/                     partitions being written, a step's swap journal (outside every table's glob)

Schemas: ``tasks.lake.schema`` registers every table's columns, keys and schema version
(docs/results-schema.md).

``<root>`` is the ``root`` argument, else the environment variable ``FIVECAL_RESULTS_DIR``, else
``data/results`` (relative to the working directory). The ``campaign_id`` column lives only in
the folder name (hive partitioning); readers get it back from DuckDB's ``hive_partitioning``.

Writes are atomic per partition: the new partition is written completely in a staging folder
(the Parquet file and the folder fsync'd), then swapped with the old one by a single rename
(Linux ``renameat2(RENAME_EXCHANGE)``; where that is unavailable, two renames, so a reader may
briefly find the partition absent but never half of one), and the folders involved are fsync'd
after the swap, so that this holds across a power cut too. A re-run replaces a partition, never
half of one. A writer killed mid-write leaves its staging folder behind, outside every table; the
next write on the same host removes the folders of writers that are no longer running.
:func:`write_partitions` replaces the partitions of several tables together: all are staged
before the first swap, so an error while writing leaves every one of them as it was.

Files and folders of the lake follow the umask, as any file the user creates: with umask 022
partitions are 0644 in 0755 folders (a lab's shared results folder readable by colleagues), with
umask 077 they are private (0600 / 0700).

Each file carries provenance (fivecal version, input content hash, parameters), the ``table``,
``campaign_id`` and the table's ``schema_version`` (from ``tasks.lake.schema``; null for a table
not in the registry) as JSON under the ``fivecal`` key of its Parquet schema metadata; see
:func:`read_provenance`.

Plain DuckDB works as well::

    duckdb.sql("select * from read_parquet('data/results/images/**/*.parquet', hive_partitioning=1, "
               "hive_types={'campaign_id': 'VARCHAR'})")

(``hive_types`` keeps campaign ids such as ``20260105`` strings rather than integers.)
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shutil
import socket
import tempfile
from pathlib import Path
from typing import Any

import duckdb
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from tasks.core.atomic_io import atomic_write_parquet, current_umask, fsync_path, swap_in_folder
from tasks.lake import schema as lake_schema
from tasks.lake.journal import WRITE_ID_KEY, complete_interrupted, journal_path, write_journal

DEFAULT_RESULTS_DIR = Path("data/results")
RESULTS_DIR_ENV = "FIVECAL_RESULTS_DIR"
PARTITION_COLUMN = "campaign_id"
PART_FILE = "part-0.parquet"
STAGING_DIR = ".staging"
# integers read as pandas nullable integers, so that a column with nulls stays integer
_NULLABLE_INTS = {pa.int8(): pd.Int8Dtype(), pa.int16(): pd.Int16Dtype(), pa.int32(): pd.Int32Dtype(),
                  pa.int64(): pd.Int64Dtype(), pa.uint8(): pd.UInt8Dtype(), pa.uint16(): pd.UInt16Dtype(),
                  pa.uint32(): pd.UInt32Dtype(), pa.uint64(): pd.UInt64Dtype()}
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
# a staging folder is <table>.<campaign_id>.pid<pid>.<host tag>.<random>; see _clean_staging
_STAGING = re.compile(r"\.pid(\d+)\.([0-9a-f]{8})\.[A-Za-z0-9_]+$")


def results_root(root: str | Path | None = None) -> Path:
    """The lake's root folder: ``root``, else $FIVECAL_RESULTS_DIR, else data/results."""
    if root is not None:
        return Path(root)
    env = os.environ.get(RESULTS_DIR_ENV)
    return Path(env) if env else DEFAULT_RESULTS_DIR


def partition_path(table_name: str, campaign_id: str, root: str | Path | None = None) -> Path:
    """``<root>/<table>/campaign_id=<id>`` (validated names: letters, digits, ``._-``)."""
    check_name("table name", table_name)
    check_name("campaign_id", campaign_id)
    return results_root(root) / table_name / f"{PARTITION_COLUMN}={campaign_id}"


def write_partition(table_name: str, campaign_id: str, df: pd.DataFrame, provenance: dict[str, Any],
                    root: str | Path | None = None) -> Path:
    """Replace the partition ``campaign_id`` of ``table_name`` with ``df``; returns the Parquet file.

    df: the rows of this campaign. A ``campaign_id`` column, if present, must equal
    ``campaign_id`` everywhere and is dropped (it is the partition). Columns the registry
    declares int64 or string are cast losslessly to it (``tasks.lake.schema.conform``).
    provenance: JSON-able dict stored in the schema metadata together with ``table``,
    ``campaign_id`` and ``schema_version`` (these three are set here and win over the dict's).
    Atomic: on any error the previous partition (if any) is untouched and nothing is left behind;
    a killed writer leaves only its staging folder (outside the tables), removed by a later write.
    """
    return write_partitions({table_name: df}, campaign_id, provenance, root)[table_name]


def write_partitions(tables: dict[str, pd.DataFrame], campaign_id: str, provenance: dict[str, Any],
                     root: str | Path | None = None) -> dict[str, Path]:
    """Replace the partition ``campaign_id`` of every table of ``tables`` ({table: rows}), as
    :func:`write_partition` does for one; returns {table: Parquet file}.

    Every partition is written and fsync'd in the staging area before the first is swapped in,
    so an error while preparing or writing any of them (a bad column, a full disk) leaves all the
    tables as they were; the swaps then follow back to back (renames, microseconds each). A kill
    between two swaps leaves a journal (:mod:`tasks.lake.journal`): the next write to the lake on
    this host completes the swaps first, so the step's tables end all new.
    """
    lake_root = results_root(root)
    staging_root = lake_root / STAGING_DIR
    staging_root.mkdir(parents=True, exist_ok=True)
    complete_interrupted(lake_root, staging_root, PART_FILE, _is_dead_writer)
    _clean_staging(staging_root)
    staged: list[tuple[Path, Path]] = []
    write_id = secrets.token_hex(8) if len(tables) > 1 else None
    journal = None
    try:
        for table_name, df in tables.items():
            meta = provenance if write_id is None else {**provenance, WRITE_ID_KEY: write_id}
            staged.append(_stage(table_name, campaign_id, df, meta, root, staging_root))
        if write_id is not None:
            journal = journal_path(staging_root, _writer_prefix(campaign_id), write_id)
            write_journal(journal, lake_root, write_id, staged)
        for staging, dest in staged:
            dest.parent.mkdir(parents=True, exist_ok=True)
            swap_in_folder(staging, dest)
            fsync_path(dest.parent)  # the swap itself
        if journal is not None:
            journal.unlink()
        fsync_path(staging_root)
    finally:
        for staging, _ in staged:  # the old partitions after the swaps, or the new ones after an error
            shutil.rmtree(staging, ignore_errors=True)
    return {name: dest / PART_FILE for name, (_, dest) in zip(tables, staged, strict=True)}


def _stage(table_name: str, campaign_id: str, df: pd.DataFrame, provenance: dict[str, Any],
           root: str | Path | None, staging_root: Path) -> tuple[Path, Path]:
    """Write the partition into a new staging folder: (staging folder, the partition's folder)."""
    dest = partition_path(table_name, campaign_id, root)
    if PARTITION_COLUMN in df.columns:
        values = df[PARTITION_COLUMN].astype(str)
        if len(df) and not (values == campaign_id).all():
            raise ValueError(f"{table_name}: rows of campaign(s) {sorted(set(values) - {campaign_id})} "
                             f"in the partition of {campaign_id}")
        df = df.drop(columns=PARTITION_COLUMN)
    df = lake_schema.conform(table_name, df)
    prefix = f"{table_name}.{_writer_prefix(campaign_id)}"
    staging = Path(tempfile.mkdtemp(dir=staging_root, prefix=prefix))
    try:
        os.chmod(staging, 0o777 & ~current_umask())  # mkdtemp's folder is private (0700)
        meta = {**provenance, "table": table_name, PARTITION_COLUMN: campaign_id,
                "schema_version": lake_schema.schema_version(table_name)}
        atomic_write_parquet(staging / PART_FILE, df, meta)  # the file and the staging folder fsync'd
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return staging, dest


def _writer_prefix(campaign_id: str) -> str:
    """``<campaign_id>.pid<pid>.<host tag>.``: names what this process leaves in ``.staging``."""
    return f"{campaign_id}.pid{os.getpid()}.{_host_tag()}."


def _is_dead_writer(name: str) -> bool:
    """True for a ``.staging`` entry of a writer on this host that is no longer running."""
    m = _STAGING.search(name)
    return m is not None and m.group(2) == _host_tag() and not _alive(int(m.group(1)))


def _host_tag() -> str:
    return hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


def _clean_staging(staging_root: Path) -> None:
    """Remove the staging folders of writers on this host that are no longer running (killed
    mid-write). Folders of live writers, of other hosts and the ``.old`` folder of the
    two-rename fallback (possibly the only copy of a partition) are left alone."""
    for entry in staging_root.iterdir():
        if entry.is_dir() and _is_dead_writer(entry.name):
            shutil.rmtree(entry, ignore_errors=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def read_table(table_name: str, root: str | Path | None = None, campaign_id: str | None = None) -> pd.DataFrame:
    """Every partition of ``table_name`` (or only ``campaign_id``) through DuckDB, as pandas.

    ``campaign_id`` (str) comes first, from the hive partition; the other columns follow in file
    order (``union_by_name``: a column missing from older partitions reads as null). Integers come
    back as pandas nullable integers (Int64, ...), timestamps tz-aware in UTC. An absent table gives an empty DataFrame.
    """
    check_name("table name", table_name)
    table_dir = results_root(root) / table_name
    if campaign_id is not None:
        check_name("campaign_id", campaign_id)
    if not any(table_dir.glob(f"{PARTITION_COLUMN}=*/*.parquet")):
        return pd.DataFrame()
    sql = scan_sql("$pattern")
    params: dict[str, Any] = {"pattern": table_glob(table_dir)}
    if campaign_id is not None:
        sql += f" WHERE {PARTITION_COLUMN} = $campaign_id"
        params["campaign_id"] = campaign_id
    with duckdb.connect() as con:
        con.execute("SET TimeZone = 'UTC'")
        table = con.sql(sql, params=params).to_arrow_table()
    return arrow_to_pandas(table)


def table_glob(table_dir: Path) -> str:
    """The glob of every partition file of the table folder ``table_dir``."""
    return str(table_dir / "**" / "*.parquet")


def scan_sql(source: str) -> str:
    """DuckDB SELECT over the partition files matched by ``source`` (a ``$parameter`` or a quoted
    SQL string literal of a glob): ``campaign_id`` (VARCHAR, from the hive partition) first, then
    the file's columns; ``union_by_name``, so a column missing from older partitions reads as null."""
    return (f"SELECT {PARTITION_COLUMN}, * EXCLUDE ({PARTITION_COLUMN}) FROM read_parquet({source}, "
            f"hive_partitioning = true, hive_types = {{'{PARTITION_COLUMN}': 'VARCHAR'}}, union_by_name = true)")


def arrow_to_pandas(table: pa.Table) -> pd.DataFrame:
    """An Arrow table as pandas with integers as nullable integers (Int64, ...)."""
    return table.to_pandas(types_mapper=_NULLABLE_INTS.get)


def read_provenance(table_name: str, campaign_id: str, root: str | Path | None = None) -> dict[str, Any]:
    """The provenance dict stored in a partition's Parquet schema metadata (with ``table``,
    ``campaign_id`` and ``schema_version``)."""
    meta = pq.read_schema(partition_path(table_name, campaign_id, root) / PART_FILE).metadata or {}
    return json.loads(meta.get(b"fivecal", b"{}"))


def check_name(what: str, name: str) -> None:
    """Raise ValueError unless ``name`` is a safe lake name (a table or a campaign_id)."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"{what} {name!r} must be 1-128 letters, digits, '.', '_' or '-', not starting with '.'")
