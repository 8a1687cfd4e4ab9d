"""The ``fivecal`` command line: one verb per job."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from fivecal import dispense_cli, dispense_job_cli, lake_cli, recalibrate_cli
from fivecal.command_guard import GuardedTyper
from fivecal.options import (
    DaskAddress,
    DaskWorkers,
    DetectorOption,
    OrientationOption,
    ResultsOption,
    VerificationRepeatsOption,
    check_orientation,
    on_valid_campaign,
)

app = GuardedTyper(add_completion=False, no_args_is_help=True,
                  help="Vision-based calibration of a five-axis precision dispensing machine.")

DEMO_CAMPAIGN = Path("data/campaigns/demo")


def _check_dask(dask_address: str | None, dask_workers: int | None) -> None:
    if dask_address and dask_workers is not None:
        raise typer.BadParameter("give --dask-address (an existing cluster) or --dask-workers (a local one), not both",
                                 param_hint="--dask-address/--dask-workers")


@app.command()
def simulate(
    out: Annotated[Path, typer.Argument(help="campaign folder to create")],
    seed: Annotated[int, typer.Option(help="seed of poses, noise and images")] = 0,
    size: Annotated[str, typer.Option(help="image size: full (3072x2048) or small (768x512)")] = "full",
    effect: Annotated[list[str] | None, typer.Option(help="inject an effect: family:key=value,...")] = None,
    plan: Annotated[str, typer.Option(help="stage sizes: default (the seed's), small (tests) or context "
                                           "(small, in two passes over an hour: docs/effects.md)")] = "default",
    overwrite: Annotated[bool, typer.Option(help="replace an existing campaign folder")] = False,
    dask_address: DaskAddress = None,
    dask_workers: DaskWorkers = None,
    effect_module: Annotated[list[str] | None, typer.Option(
        help="import a module that registers user-written effect families (repeatable); its source is "
             "recorded with the truth, the analysis does not see it")] = None,
) -> None:
    """Simulate a measurement campaign of the prototype and write its folder."""
    from tasks.machine.effects import load_effect_modules, module_source_file, parse_effect

    _check_dask(dask_address, dask_workers)
    try:
        load_effect_modules(effect_module or [], entry_point_group=None)
        for module in effect_module or []:
            module_source_file(module)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--effect-module") from None

    if size not in ("full", "small"):
        raise typer.BadParameter("size must be 'full' or 'small'", param_hint="--size")
    from tasks.simulation.campaign_plan import PLANS

    if plan not in PLANS:
        raise typer.BadParameter(f"plan must be one of {', '.join(PLANS)}", param_hint="--plan")
    for spec in effect or []:
        try:
            parse_effect(spec)
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--effect") from None
    from flows.runners import image_task_runner
    from flows.simulate import simulate_campaign

    flow = simulate_campaign.with_options(task_runner=image_task_runner(dask_address, dask_workers))
    path = flow(str(out), seed=seed, size=size, effects=list(effect or []), plan=plan,
                overwrite=overwrite, effect_modules=list(effect_module or []))
    typer.echo(f"campaign written to {path}")


@app.command()
def ingest(
    campaign: Annotated[Path, typer.Argument(help="campaign folder")],
    results: ResultsOption = None,
    dask_address: DaskAddress = None,
    dask_workers: DaskWorkers = None,
) -> None:
    """Validate a campaign and write its images table (cached by image content)."""
    from tasks.campaign.ingest import format_summary

    _check_dask(dask_address, dask_workers)

    def run():
        from flows.ingest import run_ingest

        return run_ingest(campaign, results, dask_address, dask_workers)

    summary = on_valid_campaign(campaign, run)
    typer.echo(format_summary(summary))
    typer.echo(f"images table: {summary['table']}")


@app.command()
def measure(
    campaign: Annotated[Path, typer.Argument(help="campaign folder")],
    results: ResultsOption = None,
    detector: DetectorOption = "rrht",
    dask_address: DaskAddress = None,
    dask_workers: DaskWorkers = None,
) -> None:
    """Ingest a campaign, detect every dot grid, self-calibrate the cameras and estimate plate poses."""
    _check_dask(dask_address, dask_workers)

    def run():
        from flows.measure import run_measure

        return run_measure(campaign, results, detector, dask_address, dask_workers)

    summary = on_valid_campaign(campaign, run)
    typer.echo(f"campaign {summary['campaign_id']}: {summary['n_images']} images, {summary['n_ingested_ok']} "
               f"ingested ok, {summary['n_detected']} grids found, {summary['n_poses']} poses "
               f"(cached steps: {summary['cached']})")
    _print_table3(Path(summary["tables"]["camera_calibration"]), campaign)
    for name, path in summary["tables"].items():
        typer.echo(f"{name} table: {path}")


def _print_table3(table: Path, campaign: Path) -> None:
    """Table 3 (per-trial reprojection RMS, mean; joint intrinsics), with the truth when simulated."""
    import json

    import pandas as pd

    cal = pd.read_parquet(table)
    truth_file = Path(campaign) / "truth" / "truth.json"
    truth = json.loads(truth_file.read_text())["cameras"] if truth_file.exists() else {}
    typer.echo("\nCamera self-calibration (Table 3): reprojection RMS per trial (px)")
    for camera, g in cal.groupby("camera"):
        trials = g[g["trial"] != "joint"]
        joint = g[g["trial"] == "joint"].iloc[0]
        if joint["status"] != "ok":  # no intrinsics: say why instead of printing NaN
            reasons = "; ".join(f"trial {t.trial}: {t.status}: {t.message}" for t in trials.itertuples()
                                if t.status != "ok")
            typer.echo(f"  {camera}: NOT CALIBRATED ({joint['message']}): its images get no pose. {reasons}")
            continue
        rms = " ".join(f"{v:.4f}" for v in trials["rms_px"])
        typer.echo(f"  {camera}: {rms}  mean {trials['rms_px'].mean():.4f}")
        line = (f"  {camera} joint: fx {joint['fx_px']:.2f} px, cx {joint['cx_px']:.2f}, cy {joint['cy_px']:.2f}, "
                f"k1..k3 {joint['k1']:.4f} {joint['k2']:.4f} {joint['p1']:.5f} {joint['p2']:.5f} {joint['k3']:.4f}")
        if camera in truth:  # simulated campaign: shown, never used by the fit
            t = truth[camera]
            f_true = t["focal_length_mm"] / t["pixel_size_mm"]
            line += (f"; against truth: focal {100 * (joint['fx_px'] - f_true) / f_true:+.4f} %, "
                     f"principal point ({joint['cx_px'] - t['cx_px']:+.2f}, {joint['cy_px'] - t['cy_px']:+.2f}) px")
        typer.echo(line)


@app.command("compare-detectors")
def compare_detectors(
    campaign: Annotated[Path, typer.Argument(help="campaign folder (simulated: errors are scored against its truth)")],
    results: ResultsOption = None,
    detector: Annotated[list[str] | None, typer.Option(help="detectors to compare (repeatable)")] = None,
    max_images_per_camera: Annotated[int, typer.Option(help="images sampled per camera")] = 20,
    repeats: Annotated[int, typer.Option(help="timed runs per image and detector")] = 1,
) -> None:
    """Table 4: runtime, detection rate, centre error, PnP reprojection and pose error of each detector."""
    from tasks.vision.detector_comparison import format_table4, run_comparison

    summary, path = run_comparison(campaign, results, detectors=tuple(detector or ("rrht", "blob", "hough")),
                                   max_images_per_camera=max_images_per_camera, repeats=repeats)
    typer.echo(format_table4(summary))
    typer.echo(f"detector_comparison table: {path}")


@app.command()
def detect(
    image: Annotated[Path, typer.Argument(help="an image file (any format OpenCV reads; converted to 8-bit grey)")],
    rows: Annotated[int, typer.Option(help="dot rows of the plate")] = 7,
    cols: Annotated[int, typer.Option(help="dot columns of the plate")] = 7,
    pitch_mm: Annotated[float | None, typer.Option(
        help="centre-to-centre dot spacing along a row (mm); default: the prototype's plate a (9.0)")] = None,
    row_pitch_mm: Annotated[float | None, typer.Option(
        help="spacing between rows (mm); default: the prototype's plate a (6.0) without --pitch-mm, "
             "else equal to --pitch-mm (a square lattice)")] = None,
    diameter_mm: Annotated[float, typer.Option(help="dot diameter (mm)")] = 2.5,
    light_dots: Annotated[bool, typer.Option(help="light dots on a dark plate")] = False,
    detector: DetectorOption = "rrht",
    rotation_deg: Annotated[float | None, typer.Option(help="expected in-plane rotation of the grid (deg)")] = None,
    json_output: Annotated[bool, typer.Option("--json", help="print JSON instead of a table")] = False,
    debug_image: Annotated[Path | None, typer.Option(
        help="write a PNG with the candidates, the grid found (row 0 red) or the reason it was refused")] = None,
    centres: Annotated[str, typer.Option(
        help="which centre u_px/v_px give: 'ellipse' (the fitted rim ellipse's centre, what a hand fit of the "
             "dot's edge measures) or 'corrected' (where the dot's centre projects: the ellipse centre less "
             "the perspective and lens bias, what fivecal's calibration uses); --json always gives both")] = "ellipse",
) -> None:
    """Run a dot-grid detector on one image and print the ordered centres with their fit quality."""
    import json
    from dataclasses import replace

    import cv2
    import numpy as np

    from tasks.machine.description import load_machine
    from tasks.machine.plate import DotPlate
    from tasks.vision.detection import DETECTORS, detect_grid

    if detector not in DETECTORS:
        raise typer.BadParameter(f"choose one of {sorted(DETECTORS)}", param_hint="--detector")
    if centres not in ("ellipse", "corrected"):
        raise typer.BadParameter("choose 'ellipse' or 'corrected'", param_hint="--centres")
    raw = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    if raw is None:
        typer.echo(f"error: {image}: missing or not an image OpenCV can read", err=True)
        raise typer.Exit(2)
    grey = raw if raw.ndim == 2 else cv2.cvtColor(raw, cv2.COLOR_BGRA2GRAY if raw.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if grey.dtype != np.uint8:
        grey = cv2.normalize(grey, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if pitch_mm is None:  # the default plate: the prototype's plate a, as its machine description gives it
        plate_a = load_machine("prototype").plates["plate_a"]
        pitch_mm = plate_a.pitch_mm
        row_pitch_mm = plate_a.row_pitch_mm if row_pitch_mm is None else row_pitch_mm
    plate = DotPlate(rows, cols, pitch_mm, diameter_mm, dark_dots=not light_dots, row_pitch_mm=row_pitch_mm)
    result = detect_grid(grey, plate, detector, expected_rotation_deg=rotation_deg)
    if not result.ok:  # a grid of the other polarity is refused with a reason about its lattice: say so
        other = detect_grid(grey, replace(plate, dark_dots=light_dots), detector, expected_rotation_deg=rotation_deg)
        if other.ok:
            found_as = "dark dots: run without" if light_dots else "light dots: run with"
            result = replace(result, reason=f"{result.reason}; the grid is found as {found_as} --light-dots")
    if debug_image is not None:
        from tasks.vision.detection.debug_image import draw_detection

        if not cv2.imwrite(str(debug_image), draw_detection(grey, result, plate)):
            typer.echo(f"error: {debug_image}: cannot write the debug image (folder missing or not an image "
                       "extension OpenCV writes)", err=True)
            raise typer.Exit(2)
    rc = plate.row_col()
    ellipse = result.ellipse_centres if result.ellipse_centres is not None else result.centres
    shown = ellipse if centres == "ellipse" else result.centres
    dots = [{"row": int(r), "col": int(c), "u_px": float(u), "v_px": float(v), "ellipse_u_px": float(eu),
             "ellipse_v_px": float(ev), "corrected_u_px": float(cu), "corrected_v_px": float(cv),
             "residual_rms_px": float(q), "support_ratio": float(sr)}
            for (r, c), (u, v), (eu, ev), (cu, cv), q, sr in zip(rc, shown, ellipse, result.centres,
                                                                 result.residual_rms_px, result.support_ratio,
                                                                 strict=True)]
    if result.shadowed is not None:  # the dots refitted under a cast shadow's edge: the less certain centres
        for d, sh in zip(dots, result.shadowed, strict=True):
            d["shadowed"] = bool(sh)
    if json_output:
        typer.echo(json.dumps({"image": str(image), "ok": result.ok, "reason": result.reason,
                               "detector": result.detector, "elapsed_s": result.elapsed_s,
                               "rotation_deg": result.rotation_deg, "n_candidates": result.n_candidates,
                               "orientation_ambiguous": result.orientation_ambiguous,
                               "pixel_origin": "centre of the top-left pixel", "centres": centres,
                               "dots": dots}, indent=1))
    else:
        typer.echo(f"{image}: {result.detector} {'ok' if result.ok else 'FAILED: ' + result.reason} "
                   f"({1e3 * result.elapsed_s:.0f} ms, rotation {result.rotation_deg:.2f} deg)")
        if result.ok:
            typer.echo(f"{'row':>4}{'col':>4}{'u_px':>12}{'v_px':>12}{'fit_rms_px':>12}{'support':>9}")
            for d in dots:
                typer.echo(f"{d['row']:>4}{d['col']:>4}{d['u_px']:>12.3f}{d['v_px']:>12.3f}"
                           f"{d['residual_rms_px']:>12.3f}{d['support_ratio']:>9.2f}")
    if not result.ok:
        raise typer.Exit(1)


def _run_calibrate(campaign: Path, results: Path | None, detector: str, reports: Path,
                   add_effect: list[str] | None, effect_module: list[str] | None,
                   dask_address: str | None = None, dask_workers: int | None = None,
                   orientation: str = "full", verification_repeats: int = 1) -> dict:
    """Check the effect and orientation options (a bad value is a usage error), then run the calibrate
    flow on a campaign that passes the campaign-level checks; returns the flow's summary."""
    from tasks.machine.effects import load_effect_modules, parse_effect

    _check_dask(dask_address, dask_workers)
    check_orientation(orientation)
    try:
        load_effect_modules(effect_module or [])
        for spec in add_effect or []:
            parse_effect(spec)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--add-effect / --effect-module") from None

    def run():
        from flows.calibrate import calibrate_campaign

        return calibrate_campaign(str(campaign), None if results is None else str(results), detector, str(reports),
                                  effects=list(add_effect or []), effect_modules=list(effect_module or []),
                                  dask_address=dask_address, dask_workers=dask_workers, orientation=orientation,
                                  verification_repeats=verification_repeats)

    return on_valid_campaign(campaign, run)


@app.command()
def calibrate(
    campaign: Annotated[Path, typer.Argument(help="campaign folder")],
    results: ResultsOption = None,
    detector: DetectorOption = "rrht",
    reports: Annotated[Path, typer.Option(help="reports root; the report goes to <reports>/<campaign_id>/<run>/")]
    = Path("reports"),
    add_effect: Annotated[list[str] | None, typer.Option(help="add an effect to the model and fit it: "
                                                               "family:key=value,... (repeatable)")] = None,
    effect_module: Annotated[list[str] | None, typer.Option(help="import a module that registers user-written "
                                                                  "effect families (repeatable)")] = None,
    dask_address: DaskAddress = None,
    dask_workers: DaskWorkers = None,
    orientation: OrientationOption = "full",
    verification_repeats: VerificationRepeatsOption = 1,
) -> None:
    """Calibrate a campaign: measure, PDGEs, PIGEs, compensation, verification capture and report."""
    summary = _run_calibrate(campaign, results, detector, reports, add_effect, effect_module, dask_address,
                             dask_workers, orientation, verification_repeats)
    typer.echo(f"campaign {summary['campaign_id']}: fit σ² = {summary['sigma2']:.3g} (1 = as the pose covariances "
               f"predict); cached: {summary['cached']}")
    typer.echo("mean tip errors of the validation poses (position, orientation, tool direction):")
    for r in summary["verification_means"]:
        typer.echo(f"  {r['phase']:>6} {r['source']:>5}: {r['position_um']:8.2f} µm {r['orientation_arcsec']:8.1f}″ "
                   f"{r['tool_direction_arcsec']:8.1f}″")
    for name, path in summary["tables"].items():
        typer.echo(f"{name} table: {path}")
    if summary.get("capture_state") == "requested":
        typer.echo(f"verification capture requested: take the images listed in {summary['capture']}/capture_plan.csv, "
                   f"write them and manifest.csv there, and run calibrate again (docs/campaign-format.md)")
    elif summary.get("capture"):
        typer.echo(f"verification capture: {summary['capture']}")
    typer.echo(f"report: {summary['report']}\nmarkdown: {summary['markdown']}")


@app.command()
def diagnose(
    campaign: Annotated[Path, typer.Argument(help="campaign folder")],
    results: ResultsOption = None,
    reports: Annotated[Path, typer.Option(help="reports root")] = Path("reports"),
    add_effect: Annotated[list[str] | None, typer.Option(help="effects already in the model (repeatable)")] = None,
    effect_module: Annotated[list[str] | None, typer.Option(help="module registering user effects (repeatable)")]
    = None,
) -> None:
    """Which physical effect the model lacks: calibrate (cached), then rank every catalogue effect
    against the residuals and say the verdict in words; writes the `diagnosis` table."""
    summary = _run_calibrate(campaign, results, "rrht", reports, add_effect, effect_module)
    for sentence in summary["diagnosis"]:
        typer.echo(sentence)
    if summary["diagnosis_best"]:
        typer.echo(f"next: fivecal calibrate {campaign} --add-effect '{summary['diagnosis_best']}'")
    typer.echo(f"diagnosis table: {summary['tables']['diagnosis']}")


@app.command()
def effects() -> None:
    """List the catalogue of injectable effects with their parameters and units."""
    from tasks.machine.effects import catalogue_text

    typer.echo(catalogue_text())


@app.command("truth-stats")
def truth_stats(
    effect: Annotated[list[str] | None, typer.Option(help="add an effect to the true machine (repeatable)")] = None,
    poses: Annotated[int, typer.Option(help="number of validation poses")] = 100,
    seed: Annotated[int, typer.Option(help="seed of the validation poses")] = 0,
    effect_module: Annotated[list[str] | None, typer.Option(
        help="import a module that registers user-written effect families (repeatable)")] = None,
) -> None:
    """Print the true tip errors over validation poses and the PDGE magnitudes, beside the seed's.

    Each validation pose is taken in the context it has in the seed's campaign plan (approach per
    axis, time since the start, temperature), so effects that depend on them count."""
    from tasks.machine.description import load_machine
    from tasks.machine.effects import load_effect_modules, parse_effect
    from tasks.simulation.prototype_errors import load_prototype_errors
    from tasks.simulation.truth_stats import (
        SEED_BEFORE,
        effects_change,
        pdge_magnitudes,
        summarise,
        sweep_positions,
        tip_errors,
        validation_poses,
    )

    machine = load_machine("prototype")
    errors = load_prototype_errors()
    try:
        load_effect_modules(effect_module or [], entry_point_group=None)
        errors.effects = [parse_effect(s) for s in effect or []]
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="--effect / --effect-module") from None
    cmds, context = validation_poses(machine, poses, seed)
    err = tip_errors(machine, cmds, errors, context)
    stats = summarise(err)
    typer.echo(f"Tip error over {poses} validation poses (true machine vs nominal model, before compensation)")
    typer.echo(f"{'statistic':<26}{'fivecal':>10}{'seed':>10}{'ratio':>8}")
    for k, v in stats.items():
        typer.echo(f"{k:<26}{v:>10.2f}{SEED_BEFORE[k]:>10.2f}{v / SEED_BEFORE[k]:>8.2f}")
    if errors.effects:
        change = effects_change(machine, cmds, errors, context)
        typer.echo(f"\nThe effects move the tip by {change['position_um'].mean():.2f} µm on average "
                   f"(max {change['position_um'].max():.2f}) and turn it by {change['orientation_arcsec'].mean():.2f}″ "
                   f"(max {change['orientation_arcsec'].max():.2f}), each pose in its campaign context")
    comp = err[["dx_um", "dy_um", "dz_um", "rx_arcsec", "ry_arcsec", "rz_arcsec"]].agg(["mean", "std"]).T
    typer.echo("\nComponents (mean, std):")
    for name, row in comp.iterrows():
        typer.echo(f"  {name:<10}{row['mean']:>10.2f}{row['std']:>10.2f}")
    typer.echo("\nPDGE magnitudes over each axis' sweep (mean of the norm):")
    typer.echo(pdge_magnitudes(machine, errors, sweep_positions()).round(2).to_string(index=False))


@app.command()
def demo(
    fresh: Annotated[bool, typer.Option(help="re-simulate the demo campaign even if it exists")] = False,
) -> None:
    """Run the main job (calibrate, then the dispensing test) on the built-in demo campaign (simulated at
    small image size)."""
    if fresh or not (DEMO_CAMPAIGN / "manifest.csv").exists():
        simulate(DEMO_CAMPAIGN, seed=0, size="small", effect=[], plan="default", overwrite=True)
    else:
        typer.echo(f"using existing demo campaign {DEMO_CAMPAIGN}")
    calibrate(DEMO_CAMPAIGN, None, "rrht", Path("reports"))
    dispense_cli.dispense_test(DEMO_CAMPAIGN, None, Path("reports"), None)


app.command("query")(lake_cli.query)
app.command("reproduce")(lake_cli.reproduce)
app.command("recalibrate")(recalibrate_cli.recalibrate)
app.command("serve-recalibration")(recalibrate_cli.serve_recalibration)
app.command("dispense-test")(dispense_cli.dispense_test)
app.command("inspect")(dispense_cli.inspect)
app.command("dispense-job")(dispense_job_cli.dispense_job)
app.command("locate")(dispense_job_cli.locate)
app.command("simulate-tray")(dispense_job_cli.simulate_tray)


def main() -> None:  # pragma: no cover
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
