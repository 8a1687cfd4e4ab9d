"""SQL over the whole results lake: every table folder is a DuckDB view (``fivecal query``).

SYNOPSIS::

    from tasks.lake_query import run_query, format_result
    df = run_query("select campaign_id, name, value from pige order by name, campaign_id")
    print(format_result(df, "table"))

Each table folder ``<root>/<table>/`` with at least one partition file becomes the view
``<table>``: ``campaign_id`` (VARCHAR, from the hive partition) first, then the columns
(``union_by_name``: a column missing from older partitions reads as null). The view
``lake_partitions`` lists every partition file with its table, campaign_id, schema_version,
fivecal_version, row count and path, read from the files' ``fivecal`` metadata.
Folders whose names start with "." (the staging area) are never read.
Columns, units and frames: docs/results-schema.md; example questions: docs/queries.md.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import duckdb
import pandas as pd

from tasks.results_lake import (
    PARTITION_COLUMN,
    arrow_to_pandas,
    results_root,
    scan_sql,
    table_glob,
)

FORMATS = ("table", "csv", "json")
PARTITIONS_VIEW = "lake_partitions"
_VIEW_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


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


def _literal(text: str) -> str:
    return "'" + text.replace("'", "''") + "'"


def connect(root: str | Path | None = None) -> duckdb.DuckDBPyConnection:
    """An in-memory DuckDB connection (time zone UTC) with one view per table folder and the
    ``lake_partitions`` view. Close it when done."""
    con = duckdb.connect()
    con.execute("SET TimeZone = 'UTC'")
    folders = table_folders(root)
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
    return con


def run_query(sql: str, root: str | Path | None = None) -> pd.DataFrame | None:
    """Run ``sql`` over the lake at ``root`` (default: $FIVECAL_RESULTS_DIR, else data/results).

    Returns the result (integers as nullable Int64, timestamps in UTC), or None for a statement
    without one. Raises LakeQueryError for SQL DuckDB rejects, naming the views available when a
    table is unknown."""
    con = connect(root)
    try:
        rel = con.sql(sql)
        return None if rel is None else arrow_to_pandas(rel.to_arrow_table())
    except duckdb.Error as e:
        msg = str(e).strip()
        if isinstance(e, duckdb.CatalogException):
            views = ", ".join([*table_folders(root), PARTITIONS_VIEW])
            msg += f"\ntables in the lake at {results_root(root)}: {views}"
        raise LakeQueryError(msg) from None
    finally:
        con.close()


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
