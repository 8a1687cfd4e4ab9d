"""``fivecal recalibrate`` (one tick by hand) and ``fivecal serve-recalibration`` (the deployment on
a cron schedule): scheduled recalibration from the command line (docs/recalibration.md).

Plain functions with typer annotations, registered in fivecal/cli.py.
"""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path
from typing import Annotated, Any

import typer

from fivecal.options import RESULTS_HELP as BASE_RESULTS_HELP
from fivecal.options import DetectorOption, OrientationOption, VerificationRepeatsOption, check_orientation

RESULTS_HELP = f"{BASE_RESULTS_HELP}; the ledger is in <results>/.recalibration"
REPORTS_HELP = "reports root: calibration reports in <reports>/<campaign_id>/, the drift report in <reports>/drift/"
TOLERANCE_HELP = ("drift tolerance KEY=VALUE (repeatable): abs_um, abs_arcsec, k, require (both|abs|sig|either), "
                  "after_position_um, after_orientation_arcsec")
WatchOption = Annotated[Path, typer.Option("--watch", help="the watched directory labs drop campaign folders into")]
ResultsOption = Annotated[Path | None, typer.Option("--results", help=RESULTS_HELP)]
ReportsOption = Annotated[Path, typer.Option("--reports", help=REPORTS_HELP)]
ToleranceOption = Annotated[list[str] | None, typer.Option("--tolerance", help=TOLERANCE_HELP)]
ReferenceOption = Annotated[str | None, typer.Option(help="campaign_id drift is measured from (default: earliest)")]
SettleOption = Annotated[float, typer.Option(help="seconds a folder must be unchanged before it is calibrated")]


def parse_tolerance(specs: list[str] | None):
    """A :class:`tasks.analysis.drift.DriftTolerance` from ``KEY=VALUE`` strings over the defaults (µm,
    arcsec, coverage factor k); typer.BadParameter naming the bad spec otherwise."""
    from tasks.analysis.drift import DriftTolerance

    known = {f.name: f.type for f in fields(DriftTolerance)}
    values: dict[str, Any] = {}
    for spec in specs or []:
        key, sep, raw = spec.partition("=")
        key = key.strip()
        if not sep or key not in known:
            raise typer.BadParameter(f"{spec!r}: expected KEY=VALUE with KEY one of {', '.join(known)}",
                                     param_hint="--tolerance")
        try:
            values[key] = raw.strip() if key == "require" else float(raw)
        except ValueError:
            raise typer.BadParameter(f"{spec!r}: {raw!r} is not a number", param_hint="--tolerance") from None
    try:
        return DriftTolerance(**values)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--tolerance") from None


def _parameters(watch: Path, results: Path | None, reports: Path, tolerance: list[str] | None,
                reference: str | None, settle_seconds: float, detector: str, orientation: str,
                verification_repeats: int = 1) -> dict[str, Any]:
    """The flow's parameters with absolute paths (a served run may start in another folder)."""
    from tasks.lake.store import results_root

    if not watch.is_dir():
        raise typer.BadParameter(f"{watch} is not a folder", param_hint="--watch")
    return {"watch_dir": str(watch.resolve()), "results_root": str(results_root(results).resolve()),
            "reports_root": str(reports.resolve()), "tolerance": parse_tolerance(tolerance).to_dict(),
            "reference": reference, "settle_seconds": settle_seconds, "detector": detector,
            "orientation": check_orientation(orientation), "verification_repeats": int(verification_repeats)}


def recalibrate(
    watch: WatchOption,
    results: ResultsOption = None,
    reports: ReportsOption = Path("reports"),
    tolerance: ToleranceOption = None,
    reference: ReferenceOption = None,
    settle_seconds: SettleOption = 120.0,
    detector: DetectorOption = "rrht",
    orientation: OrientationOption = "full",
    verification_repeats: VerificationRepeatsOption = 1,
    always_report: Annotated[bool, typer.Option(help="write the drift report even if nothing new was calibrated")]
    = False,
) -> None:
    """Run one recalibration tick now: calibrate every new campaign under --watch, then the drift report."""
    params = _parameters(watch, results, reports, tolerance, reference, settle_seconds, detector, orientation,
                         verification_repeats)
    from flows.recalibrate import recalibrate_new_campaigns

    state = recalibrate_new_campaigns(**params, always_report=always_report, return_state=True)
    if state.is_failed():
        typer.echo(f"error: {state.message}", err=True)
        raise typer.Exit(1)
    summary = state.result()
    typer.echo(f"calibrated now: {', '.join(summary['calibrated']) or 'none'}")
    typer.echo(f"already calibrated: {', '.join(summary['already_calibrated']) or 'none'}")
    if summary.get("awaiting_capture"):
        typer.echo(f"awaiting the lab's verification capture (captures/<id>/capture_plan.csv): "
                   f"{', '.join(summary['awaiting_capture'])}")
    for folder in summary["waiting"]:
        typer.echo(f"waiting (changed less than {settle_seconds:g} s ago): {folder}")
    for s in summary["skipped"]:
        typer.echo(f"skipped {s['folder']}: {s['reason']}")
    drift = summary["drift"]
    if drift is None:
        typer.echo("drift report: not written (nothing new; --always-report writes one)")
        return
    typer.echo(f"drift report: {drift['report']}\nmarkdown: {drift['markdown']}\n{drift['flagged']} flagged "
               f"quantity(ies) over {len(drift['campaigns'])} campaign(s)\n\n{drift['verdict']}")


def serve_recalibration(
    watch: WatchOption,
    cron: Annotated[str, typer.Option(help="cron schedule of the ticks, e.g. \"0 2 * * *\" (02:00 every day)")],
    results: ResultsOption = None,
    reports: ReportsOption = Path("reports"),
    tolerance: ToleranceOption = None,
    reference: ReferenceOption = None,
    settle_seconds: SettleOption = 120.0,
    detector: DetectorOption = "rrht",
    orientation: OrientationOption = "full",
    verification_repeats: VerificationRepeatsOption = 1,
    name: Annotated[str, typer.Option(help="deployment name")] = "scheduled-recalibration",
    timezone: Annotated[str, typer.Option(help="IANA time zone of the cron schedule")] = "UTC",
) -> None:
    """Serve the recalibration flow as a Prefect deployment on a cron schedule (runs until stopped)."""
    from prefect.client.schemas.schedules import CronSchedule
    from prefect.deployments.runner import EntrypointType
    from prefect.settings import get_current_settings

    if not get_current_settings().api.url:
        typer.echo("error: Prefect's temporary server cannot run schedules. Start a Prefect server (`prefect server "
                   "start`, e.g. as a service) and point fivecal at it: `prefect config set "
                   "PREFECT_API_URL=http://127.0.0.1:4200/api` (docs/recalibration.md).", err=True)
        raise typer.Exit(2)

    params = _parameters(watch, results, reports, tolerance, reference, settle_seconds, detector, orientation,
                         verification_repeats)
    try:
        schedule = CronSchedule(cron=cron, timezone=timezone)
    except ValueError:
        raise typer.BadParameter(f"{cron!r} with time zone {timezone!r} is not a valid cron schedule",
                                 param_hint="--cron") from None
    from flows.recalibrate import recalibrate_new_campaigns

    typer.echo(f"serving deployment recalibrate-new-campaigns/{name} on {cron!r} ({timezone}) with {params}")
    recalibrate_new_campaigns.serve(name=name, schedules=[schedule], parameters=params, limit=1,
                                    entrypoint_type=EntrypointType.MODULE_PATH)
