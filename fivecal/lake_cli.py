"""``fivecal query`` and ``fivecal reproduce``: the results lake from the command line.

Plain functions with typer annotations, registered in fivecal/cli.py.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from fivecal.options import ResultsOption


def query(
    sql: Annotated[str, typer.Argument(help="SQL over the lake; every table is a view, plus lake_partitions")],
    results: ResultsOption = None,
    format: Annotated[str, typer.Option("--format", help="table, csv or json")] = "table",
    max_rows: Annotated[int, typer.Option(help="rows printed by --format table (0: all)")] = 100,
    memory_limit: Annotated[str, typer.Option(help="DuckDB's memory limit for the query, e.g. 1GB, 500MB")] = "1GB",
) -> None:
    """Run one read-only SQL query (SELECT) over every table of the results lake (DuckDB; docs/queries.md)
    and print the result as it streams."""
    from tasks.lake.query import FORMATS, LakeQueryError, print_result, query_batches

    if format not in FORMATS:
        typer.echo(f"error: --format {format!r}: choose one of {', '.join(FORMATS)}", err=True)
        raise typer.Exit(2)
    batches = query_batches(sql, results, memory_limit)
    try:
        print_result(batches, typer.echo, format, max_rows)
    except LakeQueryError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from None
    finally:
        batches.close()


def reproduce(
    report_dir: Annotated[Path, typer.Argument(help="a report folder written by fivecal calibrate")],
    campaign: Annotated[Path | None, typer.Option(help="the campaign folder, if it moved (default: the recorded "
                                                       "path)")] = None,
    workdir: Annotated[Path | None, typer.Option(help="keep the reproduction's results and report here (default: "
                                                      "a temporary folder)")] = None,
) -> None:
    """Re-run a report's calibration with its recorded parameters and Prefect's cache refreshed; print
    every number that differs (exit 1), or "all N numbers reproduced"."""
    from flows.reproduce import reproduce_report

    code = reproduce_report(report_dir, campaign, workdir, echo=typer.echo, error=lambda m: typer.echo(m, err=True))
    raise typer.Exit(code)
