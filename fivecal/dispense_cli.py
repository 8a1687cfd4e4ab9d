"""``fivecal dispense-test`` and ``fivecal inspect``: the dispensing test (docs/dispensing-test.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from fivecal.options import ResultsOption, on_valid_campaign

ConfigOption = Annotated[Path | None, typer.Option(help="TOML file overriding the inspection thresholds "
                                                        "([inspection] section; defaults: "
                                                        "tasks/dispensing/inspection_defaults.toml)")]


def dispense_test(
    campaign: Annotated[Path, typer.Argument(help="a calibrated campaign folder")],
    results: ResultsOption = None,
    reports: Annotated[Path, typer.Option(help="reports root; the report goes to "
                                               "<reports>/<campaign_id>/<run>/dispensing/")] = Path("reports"),
    inspection_config: ConfigOption = None,
    effect_module: Annotated[list[str] | None, typer.Option(
        help="import a module that registers the user-written effect families the calibration added "
             "(repeatable; default: the modules the calibration recorded)")] = None,
) -> None:
    """Dispense dots in ring targets (nominal, compensated), inspect them (§4.3), fit the tip's offset,
    fold it into the compensation and check it on a fresh workpiece."""
    from tasks.dispensing.inspection import load_config
    from tasks.machine.effects import load_effect_modules

    try:
        load_config(inspection_config)
    except (ValueError, OSError) as e:
        raise typer.BadParameter(str(e), param_hint="--inspection-config") from None
    try:
        load_effect_modules(effect_module or [], entry_point_group=None)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--effect-module") from None

    def run():
        from flows.dispense import dispense_test as flow

        return flow(str(campaign), None if results is None else str(results), str(reports), None,
                    None if inspection_config is None else str(inspection_config),
                    effect_modules=list(effect_module or []))

    try:
        summary = on_valid_campaign(campaign, run)
    except ValueError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from None
    typer.echo(f"campaign {summary['campaign_id']}: captures {summary['captures']}")
    if "tip_offset_um" in summary:
        typer.echo("tip offset (tool frame, µm): " + ", ".join(
            f"{a} {v:+.2f} ± {u:.2f}" for a, v, u in zip("xyz", summary["tip_offset_um"],
                                                         summary["tip_offset_uncertainty_um"], strict=True))
                   + f" from {summary['tip_fit_dots']} dots (residual rms {summary['tip_fit_residual_rms_um']:.2f} µm)")
        typer.echo("model uncertainty of the tip after the tip fit: "
                   f"{summary['model_uncertainty_after_tip_um']:.2f} µm (mean over the validation poses)")
    if "truth" in summary:
        t = summary["truth"]
        typer.echo(f"truth: constant tool-frame tip error {_norm(t['constant_before_um']):.2f} µm after compensation, "
                   f"{_norm(t['constant_after_tip_um']):.2f} µm after the tip fit; mean tip position error "
                   f"{t['position_after_um']:.2f} → {t['position_after_tip_um']:.2f} µm")
    for name, path in summary["tables"].items():
        typer.echo(f"{name} table: {path}")
    if "report" in summary:
        typer.echo(f"report: {summary['report']}")


def _norm(v) -> float:
    return float(sum(x * x for x in v) ** 0.5)


def inspect(
    image: Annotated[Path, typer.Argument(help="a grey or colour image (PNG, TIFF, ...)")],
    config: ConfigOption = None,
) -> None:
    """Run the §4.3 inspection on one image and print the dots found (with a ring target: its centre too)."""
    import cv2

    from tasks.dispensing.inspection import inspect_regions, inspect_ring_image, load_config

    try:
        cfg = load_config(config)
    except (ValueError, OSError) as e:
        raise typer.BadParameter(str(e), param_hint="--config") from None
    gray = cv2.imread(str(image), cv2.IMREAD_GRAYSCALE)
    if gray is None:
        typer.echo(f"error: {image}: not a readable image", err=True)
        raise typer.Exit(2)
    ring = inspect_ring_image(gray, cfg)
    if ring.ring is not None:
        typer.echo(f"ring: centre ({ring.ring.x_px:.3f}, {ring.ring.y_px:.3f}) px, radii {ring.ring.inner_px:.2f} / "
                   f"{ring.ring.outer_px:.2f} px; verdict: {'qualified' if ring.qualified else ring.reason}")
        regions, polarity = ring.regions, ring.polarity
    else:
        typer.echo("no ring target: the whole image inspected")
        regions, polarity, _ = inspect_regions(gray, cfg)
    typer.echo(f"polarity: {polarity}; {len(regions)} dot(s)")
    typer.echo(f"{'x_px':>9} {'y_px':>9} {'A_px2':>8} {'P_px':>7} {'d_px':>7} {'C':>6} {'NSD_r':>6} "
               f"{'CoV_I':>6}  verdict")
    for r in regions:
        typer.echo(f"{r.x_px:9.3f} {r.y_px:9.3f} {r.area_px2:8.1f} {r.perimeter_px:7.2f} {r.diameter_px:7.2f} "
                   f"{r.circularity:6.3f} {r.nsd_r:6.3f} {r.cov_i:6.3f}  {'qualified' if r.qualified else r.reason}")
