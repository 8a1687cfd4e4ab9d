"""``fivecal dispense-job``, ``fivecal locate`` and ``fivecal simulate-tray``: the dispensing job
(docs/dispense-job.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from fivecal.options import ResultsOption, on_valid_campaign


def dispense_job(
    images: Annotated[list[Path], typer.Argument(help="tray images (each with its NAME.json sidecar)")],
    campaign: Annotated[Path, typer.Option(help="the calibrated campaign whose machine runs the job")],
    results: ResultsOption = None,
    reports: Annotated[Path, typer.Option(help="reports root; the report goes to "
                                               "<reports>/<campaign_id>/<run>/dispense-job/")] = Path("reports"),
    phase: Annotated[list[str] | None, typer.Option(
        help="compensated | nominal | planar (repeatable; default: all three for simulated trays, compensated "
             "otherwise)")] = None,
    effect_module: Annotated[list[str] | None, typer.Option(
        help="import a module that registers the user-written effect families the calibration added "
             "(repeatable; default: the modules the calibration recorded)")] = None,
) -> None:
    """Locate the dispensing areas on every tray, map them to the machine, plan beads and the tour, write the
    dispensing program; on simulated trays the virtual machine dispenses and the beads are inspected."""
    from tasks.dispense_job.tray_job import PHASES
    from tasks.machine.effects import load_effect_modules

    bad = [p for p in phase or [] if p not in PHASES]
    if bad:
        raise typer.BadParameter(f"unknown phase(s) {bad}: choose from {', '.join(PHASES)}", param_hint="--phase")
    try:
        load_effect_modules(effect_module or [], entry_point_group=None)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--effect-module") from None

    def run():
        from flows.dispense_job import dispense_job as flow

        return flow([str(i) for i in images], str(campaign), None if results is None else str(results), str(reports),
                    None, tuple(phase) if phase else None, effect_modules=list(effect_module or []))

    try:
        summary = on_valid_campaign(campaign, run)
    except ValueError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from None
    for tray, s in summary["trays"].items():
        if "error" in s:
            typer.echo(f"tray {tray}: failed: {s['error']}")
        else:
            truth = (f"; against the truth: {s['recognised']} of {s['true_boards']} boards handled correctly"
                     if "recognised" in s else "")
            typer.echo(f"tray {tray}: {s['boards']} boards, {s['accepted']} accepted{truth}"
                       + "".join(f"\n  rejected: {r}" for r in s["rejected"]))
    beads = summary["beads"]
    if len(beads):
        for ph, b in beads.groupby("phase", sort=False):
            off = (b.true_offset_along_mm ** 2 + b.true_offset_across_mm ** 2) ** 0.5 * 1e3
            typer.echo(f"{ph}: true bead offset median {off.median():.0f} µm, max {off.max():.0f} µm; "
                       f"{int(b.true_within_tolerance.sum())}/{len(b)} within ±0.5 mm")
    for name, path in summary["tables"].items():
        typer.echo(f"{name} table: {path}")
    typer.echo(f"report: {summary['report']}")


def locate(
    image: Annotated[Path, typer.Argument(help="a colour tray image")],
    mm_per_px: Annotated[float, typer.Option(help="image scale on the tray (mm per pixel)")] = 0.045,
    overlay: Annotated[Path | None, typer.Option(help="write the image with boards and areas drawn on it")] = None,
) -> None:
    """Find the boards and their dispensing areas in one image (the paper's §2 pipeline) and print them."""
    import cv2

    from tasks.dispense_job.locate import locate as run_locate
    from tasks.dispense_job.overlay import draw_overlay

    bgr = cv2.imread(str(image), cv2.IMREAD_COLOR)
    if bgr is None:
        typer.echo(f"error: {image}: not a readable image", err=True)
        raise typer.Exit(2)
    found = run_locate(bgr[..., ::-1].copy(), mm_per_px=mm_per_px)
    if not found.boards:
        typer.echo(f"{image}: no board found (a blank tray, or not a tray image)")
    typer.echo(f"{'board':>5} {'u_px':>9} {'v_px':>9} {'angle':>7} {'length':>7} {'width':>6} {'area_px':>7}  verdict")
    for i, b in enumerate(found.boards):
        if b.area is not None:
            r = b.area.rect
            typer.echo(f"{f'b{i:02d}':>5} {r.u:9.2f} {r.v:9.2f} {r.angle_deg:7.2f} {r.length_px * mm_per_px:7.3f} "
                       f"{r.width_px * mm_per_px:6.3f} {b.area.area_px:7d}  accepted")
        else:
            typer.echo(f"{f'b{i:02d}':>5} {'':>9} {'':>9} {'':>7} {'':>7} {'':>6} {'':>7}  {b.reason}")
    stray = [a for a in found.areas if a.board < 0 and a.accepted]
    if stray:
        typer.echo(f"{len(stray)} accepted area(s) on no board (ignored)")
    if overlay is not None:
        cv2.imwrite(str(overlay), draw_overlay(bgr, found))
        typer.echo(f"overlay: {overlay}")


def simulate_tray(
    out: Annotated[Path, typer.Argument(help="the tray image to write (PNG; NAME.json and NAME.truth.csv beside it)")],
    campaign: Annotated[Path, typer.Option(help="a simulated campaign: its true machine images the tray")],
    seed: Annotated[int, typer.Option(help="places the boards")] = 0,
    boards: Annotated[int, typer.Option(min=0, max=20, help="boards on the tray (0: a blank tray)")] = 20,
    defect_rate: Annotated[float, typer.Option(min=0.0, max=1.0, help="share of defective boards")] = 0.1,
) -> None:
    """Render a tray of boards as camera 1 of a simulated campaign's machine sees it (with truth)."""
    from tasks.dispense_job.boards import TraySpec
    from tasks.dispense_job.tray_io import simulate_tray as simulate
    from tasks.simulation.verification_capture import is_simulated

    if not is_simulated(campaign):
        typer.echo(f"error: {campaign}: not a simulated campaign (no truth): a real tray is photographed", err=True)
        raise typer.Exit(2)
    path = simulate(out, campaign, seed, boards, TraySpec(defect_rate=defect_rate))
    typer.echo(f"tray: {path} (sidecar {path.with_suffix('.json').name}, truth {path.with_suffix('.truth.csv').name})")
