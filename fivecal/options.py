"""Command-line options several commands share (typer ``Annotated`` aliases)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

RESULTS_HELP = "results root (default data/results, or $FIVECAL_RESULTS_DIR)"
ResultsOption = Annotated[Path | None, typer.Option(help=RESULTS_HELP)]
DetectorOption = Annotated[str, typer.Option(help="rrht (the paper's framework), blob or hough")]
# Where the image work runs (flows/runners.py); both absent: threads of this process.
DaskAddress = Annotated[str | None, typer.Option(help="scheduler address of an existing Dask cluster for the image "
                                                      "work, e.g. tcp://10.0.0.5:8786")]
DaskWorkers = Annotated[int | None, typer.Option(min=1, help="run the image work on a local Dask cluster of N "
                                                             "worker processes")]
OrientationOption = Annotated[str, typer.Option(
    help="what compensation turns A and C for: 'full' (the whole tip rotation, as the seed counts it) or "
         "'tool-axis' (the tool direction exactly; the rotation about the tool axis, which a round needle does "
         "not see, left free)")]

VerificationRepeatsOption = Annotated[int, typer.Option(
    min=1, help="images of each compensated pose in the simulated verification capture (passes over all the poses "
                "in turn); the after figures as the VBM measures them average them")]


def check_orientation(orientation: str) -> str:
    """``orientation`` if it is a compensation objective (tasks.analysis.compensation.ORIENTATION_OBJECTIVES);
    a usage error naming the choices otherwise."""
    from tasks.analysis.compensation import check_objective

    try:
        return check_objective(orientation)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--orientation") from None


def on_valid_campaign(campaign: Path, run):
    """Run ``run()`` on a campaign whose folder, metadata and manifest pass the campaign-level
    checks (tasks.campaign.ingest.read_checked_manifest); otherwise print the error (it names the file) and
    exit 2, before any Prefect server starts or anything is written."""
    from tasks.campaign.ingest import CampaignError, read_checked_manifest

    try:
        read_checked_manifest(campaign)
        return run()
    except CampaignError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from None
