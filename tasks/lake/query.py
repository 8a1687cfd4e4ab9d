"""SQL over the whole results lake: every table folder is a DuckDB view (``fivecal query``).

SYNOPSIS::

    from tasks.lake.query import run_query, format_result
    df = run_query("select campaign_id, name, value from pige order by name, campaign_id")
    print(format_result(df, "table"))

Each table folder ``<root>/<table>/`` with at least one partition file becomes the view
``<table>``: ``campaign_id`` (VARCHAR, from the hive partition) first, then the columns
(``union_by_name``: a column missing from older partitions reads as null). The view
``lake_partitions`` lists every partition file with its table, campaign_id, schema_version,
fivecal_version, row count and path, read from the files' ``fivecal`` metadata.
Folders whose names start with "." (the staging area) are never read.
Columns, units and frames: docs/results-schema.md; example questions: docs/queries.md.

Read-only and confined to the lake: one SELECT (or EXPLAIN) per query; DuckDB's file access is
limited to the lake folder (``enable_external_access = false`` with the lake as the only
``allowed_directories``), extensions are neither installed nor loaded, the memory is limited
(:data:`MEMORY_LIMIT`, no spilling to disk) and the configuration is locked before the user's SQL
runs, so no SET can undo it. DuckDB checks a path's text against the lake folder, not where a
symbolic link leads, so a lake that holds a link is refused (:func:`symbolic_links`). Results
are streamed in batches (:func:`query_batches`): printing the first rows costs those rows, not
the whole result.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterator
from pathlib import Path

import duckdb
import pandas as pd
import pyarrow as pa

from tasks.lake.store import (
    PARTITION_COLUMN,
    arrow_to_pandas,
    results_root,
    scan_sql,
    table_glob,
)

FORMATS = ("table", "csv", "json")
PARTITIONS_VIEW = "lake_partitions"
_VIEW_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
MEMORY_LIMIT = "1GB"  # DuckDB's memory_limit for fivecal query
BATCH_ROWS = 10_000  # rows per streamed batch
# statements a query may be: they read and return rows, nothing else
READ_ONLY_STATEMENTS = (duckdb.StatementType.SELECT, duckdb.StatementType.EXPLAIN)
FULL_SESSION_HINT = "for a full DuckDB session open one on the lake's files yourself (docs/queries.md)"


class LakeQueryError(Exception):
    """A query that cannot run: its message says why (bad SQL, unknown table, no lake)."""


def table_folders(root: str | Path | None = None) -> dict[str, Path]:
    """{view name: table folder} of every table folder under the lake root that holds a partition
    file; names that are not SQL identifiers and hidden folders (the staging area) are skipped."""
    base = results_root(root)
    if not base.is_dir():
        return {}
    return {d.name: d for d in sorted(base.iterdir())
            if d.is_dir() and _VIEW_NAME.match(d.name) and d.name != PARTITIONS_VIEW
            and any(d.glob(f"{PARTITION_COLUMN}=*/*.parquet"))}


def symbolic_links(base: Path) -> list[Path]:
    """Every symbolic link under the lake folder ``base`` (links are listed, never followed)."""
    links = []
    for folder, dirs, files in os.walk(base):
        links += [Path(folder) / n for n in (*dirs, *files) if (Path(folder) / n).is_symlink()]
    return sorted(links)


def _literal(text: str) -> str:
    return "'" + text.replace("'", "''") + "'"


def connect(root: str | Path | None = None, memory_limit: str = MEMORY_LIMIT) -> duckdb.DuckDBPyConnection:
    """An in-memory DuckDB connection (time zone UTC) with one view per table folder and the
    ``lake_partitions`` view, confined to the lake: file access only inside the lake folder, no
    extension installed or loaded, ``memory_limit`` (e.g. "1GB") without spilling to disk, and the
    configuration locked. Close it when done."""
    base = results_root(root).resolve()
    links = symbolic_links(base)
    if links:
        raise LakeQueryError(f"the lake at {base} holds {len(links)} symbolic link(s), e.g. {links[0]}: fivecal query "
                             f"reads only regular files inside the lake; replace the link by a copy or remove it")
    con = duckdb.connect(config={"autoinstall_known_extensions": False, "autoload_known_extensions": False,
                                 "allow_community_extensions": False, "memory_limit": memory_limit,
                                 "temp_directory": ""})
    try:
        con.execute("SET TimeZone = 'UTC'")
        con.execute(f"SET allowed_directories = [{_literal(str(base) + '/')}]")
        con.execute("SET enable_external_access = false")
        _create_views(con, base)
        con.execute("SET lock_configuration = true")
    except BaseException:
        con.close()
        raise
    return con


def _create_views(con: duckdb.DuckDBPyConnection, base: Path) -> None:
    folders = table_folders(base)
    for name, folder in folders.items():
        con.execute(f'CREATE VIEW "{name}" AS {scan_sql(_literal(table_glob(folder)))}')
    files = [table_glob(f) for f in folders.values()]
    source = f"[{', '.join(_literal(f) for f in files)}]" if files else None
    if source is None:
        con.execute(f"CREATE VIEW {PARTITIONS_VIEW} AS SELECT NULL::VARCHAR AS \"table\", NULL::VARCHAR AS "
                    f"campaign_id, NULL::INTEGER AS schema_version, NULL::VARCHAR AS fivecal_version, "
                    f"NULL::BIGINT AS num_rows, NULL::VARCHAR AS file WHERE false")
    else:
        con.execute(f"""CREATE VIEW {PARTITIONS_VIEW} AS
            WITH meta AS (SELECT file_name, decode(value) AS j FROM parquet_kv_metadata({source})
                          WHERE decode(key) = 'fivecal')
            SELECT json_extract_string(j, '$.table') AS "table", json_extract_string(j, '$.campaign_id') AS campaign_id,
                   TRY_CAST(json_extract(j, '$.schema_version') AS INTEGER) AS schema_version,
                   json_extract_string(j, '$.fivecal_version') AS fivecal_version, f.num_rows, meta.file_name AS file
            FROM meta JOIN parquet_file_metadata({source}) f USING (file_name)""")


def _check_read_only(con: duckdb.DuckDBPyConnection, sql: str) -> None:
    """Raise LakeQueryError unless ``sql`` is exactly one SELECT or EXPLAIN statement."""
    statements = con.extract_statements(sql)
    if len(statements) != 1:
        raise LakeQueryError(f"give one SQL statement per query (got {len(statements)})")
    kind = statements[0].type
    if kind not in READ_ONLY_STATEMENTS:
        raise LakeQueryError(f"{kind.name} statements are not allowed: fivecal query is read-only (SELECT only); "
                             + FULL_SESSION_HINT)


def query_batches(sql: str, root: str | Path | None = None, memory_limit: str = MEMORY_LIMIT,
                  batch_rows: int = BATCH_ROWS) -> Iterator[pd.DataFrame]:
    """Run ``sql`` (one SELECT or EXPLAIN) over the lake at ``root`` and yield its result in
    batches of at most ``batch_rows`` rows as they are computed (integers as nullable Int64,
    timestamps in UTC); at least one batch (empty, with the columns, when there is no row).
    Stopping early (closing the generator) stops the query. Raises LakeQueryError for SQL that is
    not read-only or that DuckDB rejects (naming the views when a table is unknown), and when the
    query runs out of its memory limit."""
    con = None
    try:
        con = connect(root, memory_limit)
        _check_read_only(con, sql)
        with con.sql(sql).to_arrow_reader(batch_rows) as reader:
            empty = True
            for batch in reader:
                empty = False
                yield arrow_to_pandas(pa.Table.from_batches([batch]))
            if empty:
                yield arrow_to_pandas(reader.schema.empty_table())
    except duckdb.Error as e:
        msg = str(e).strip()
        if isinstance(e, duckdb.CatalogException):
            views = ", ".join([*table_folders(root), PARTITIONS_VIEW])
            msg += f"\ntables in the lake at {results_root(root)}: {views}"
        elif isinstance(e, duckdb.PermissionException):
            msg += f"\nfivecal query reads only the lake at {results_root(root)}; {FULL_SESSION_HINT}"
        raise LakeQueryError(msg) from None
    except (MemoryError, pa.ArrowMemoryError) as e:
        raise LakeQueryError(f"out of memory ({e}): narrow the query or raise --memory-limit") from None
    finally:
        if con is not None:
            con.close()


def run_query(sql: str, root: str | Path | None = None, memory_limit: str = MEMORY_LIMIT) -> pd.DataFrame:
    """Run ``sql`` (one SELECT or EXPLAIN) over the lake at ``root`` (default: $FIVECAL_RESULTS_DIR,
    else data/results) and return the whole result (integers as nullable Int64, timestamps in
    UTC). Raises LakeQueryError as :func:`query_batches` does."""
    return pd.concat(list(query_batches(sql, root, memory_limit)), ignore_index=True)


def print_result(batches: Iterator[pd.DataFrame], echo, fmt: str = "table", max_rows: int = 100) -> None:
    """Print streamed ``batches`` with ``echo`` (one call per piece of text) as ``fmt``: ``table``
    reads only the first ``max_rows`` + 1 rows (0 = all) and says when there are more; ``csv`` and
    ``json`` (a list of records) print batch by batch, so memory does not grow with the result."""
    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r}: choose one of {', '.join(FORMATS)}")
    if fmt == "table":
        shown: list[pd.DataFrame] = []
        n = 0
        for df in batches:
            shown.append(df)
            n += len(df)
            if 0 < max_rows < n:
                break
        df = pd.concat(shown, ignore_index=True)
        more = max_rows > 0 and len(df) > max_rows
        text = format_result(df.head(max_rows) if more else df, "table", 0)
        if more:
            text += f"\n… more rows not shown (the first {max_rows} above; --max-rows 0 or --format csv shows all)"
        echo(text)
        return
    if fmt == "csv":
        for i, df in enumerate(batches):
            if i == 0 or len(df):  # the header comes with the first batch, empty or not
                echo(df.to_csv(index=False, header=i == 0).rstrip("\n"))
        return
    echo("[")
    separator = ""
    for df in batches:
        if len(df):
            records = json.loads(df.to_json(orient="records", date_format="iso"))
            echo(separator + ",\n".join(json.dumps(r, ensure_ascii=False) for r in records))
            separator = ","
    echo("]")


def format_result(df: pd.DataFrame | None, fmt: str = "table", max_rows: int = 100) -> str:
    """The result as text: ``table`` (aligned columns, at most ``max_rows`` rows; 0 = all),
    ``csv`` (header, every row) or ``json`` (a list of records; NaN/NA as null, times ISO 8601)."""
    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r}: choose one of {', '.join(FORMATS)}")
    if df is None:
        return "(no result)" if fmt == "table" else ""
    if fmt == "csv":
        return df.to_csv(index=False).rstrip("\n")
    if fmt == "json":
        return json.dumps(json.loads(df.to_json(orient="records", date_format="iso")), indent=1, ensure_ascii=False)
    if df.empty:
        return f"(0 rows; columns: {', '.join(map(str, df.columns))})"
    shown = df if max_rows <= 0 or len(df) <= max_rows else df.head(max_rows)
    text = shown.to_string(index=False, max_colwidth=60)
    if len(shown) < len(df):
        more = len(df) - len(shown)
        text += (f"\n… {more} more row{'s' if more > 1 else ''} ({len(df)} in all; "
                 "--max-rows 0 or --format csv shows all)")
    return text
