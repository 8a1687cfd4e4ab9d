"""What limits the dispensing test's tip constant, at pose level (no images): for calibrated simulated
campaigns, the true constant tool-frame tip error over the validation poses after compensation
against what the tip fit finds from exact dot offsets (the simulator's landing points) and from
offsets with Gaussian measurement noise, for three workpiece designs:

* ``flat 63``: one flat surface 19.8 mm above plate a (Z command set by the surface and A), 63 rings,
  the compensated phase only (the design before the pads);
* ``flat 480``: the rings of ``pads`` (same X, Y, A, C), all on that flat surface;
* ``pads 480``: the flow's design (tasks.dispensing.workpiece): rings over X, Y, Z, A, C on pads,
  two plates of 240, the nominal phase on one and the compensated on the other.

Beside them ``floor``: the best constant from exact horizontal offsets taken at the validation poses
themselves: what dots on a horizontal surface cannot see (the tip's vertical error that a constant
tool-frame offset does not follow) even there.

    .venv/bin/python bench/dispense_design.py --results R CAMPAIGN_FOLDER...
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from tasks.analysis.compensation import compensate, desired_tip_poses
from tasks.campaign.ingest import load_campaign_metadata
from tasks.core.units import UM
from tasks.dispensing.tip import constant_tool_frame_error, fit_tip_offset, landing_points
from tasks.dispensing.workpiece import Workpiece, dispensing_commands, ring_layout
from tasks.identification.calibration import calibrate
from tasks.identification.measurements import assemble_measurements
from tasks.lake.store import read_table
from tasks.machine.kinematics import forward
from tasks.simulation.simulate import read_truth
from tasks.vision.pipeline import nominal_machine

FLAT_SURFACE_MM = 19.8


def on_flat_surface(machine, layout):
    """The layout's commands with the tip held above one flat surface instead of its pads."""
    n = len(layout.centres)
    return dispensing_commands(machine, Workpiece(), layout.centres, np.full(n, FLAT_SURFACE_MM), layout.commands)


def fit_error(machine, model, truth, commands, rings, target, noise_um, rng, draws):
    """|target − fitted constant| (µm): exact offsets, then ``draws`` noisy ones."""
    exact = landing_points(machine, truth, commands) - rings
    out = [np.linalg.norm(target - fit_tip_offset(machine, model, commands, rings, exact).offset_um)]
    for _ in range(draws):
        noisy = exact + rng.normal(0, noise_um * UM, exact.shape)
        out.append(np.linalg.norm(target - fit_tip_offset(machine, model, commands, rings, noisy,
                                                          iterations=1).offset_um))
    return out[0], np.array(out[1:])


def horizontal_floor(machine, truth, desired, commands, target) -> float:
    """|target − t| (µm) for the constant t that best explains the exact horizontal tip errors at the
    validation poses (least squares on P R t)."""
    tip = forward(machine, commands, truth).tool_in_workpiece()
    horizontal = (tip[:, :2, 3] - desired[:, :2, 3]) / UM
    t = np.linalg.lstsq(tip[:, :2, :3].reshape(-1, 3), horizontal.ravel(), rcond=None)[0]
    return float(np.linalg.norm(target - t))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--results", type=Path, required=True)
    p.add_argument("--noise-um", type=float, default=1.2, help="per-axis dot offset noise (µm)")
    p.add_argument("--draws", type=int, default=100)
    p.add_argument("campaigns", nargs="+", type=Path)
    a = p.parse_args()
    print("|const − fitted constant| (µm): exact offsets, then median, 95th percentile and max over the noisy draws")
    head = " | ".join(f"{name:<23}" for name in ("flat 63", "flat 480", "pads 480"))
    print(f"{'campaign':>9} {'const µm':>9} {'floor':>6} | {head} | identify s")
    print(f"{'':>26} | " + " | ".join(["exact   med   p95   max"] * 3))
    for folder in a.campaigns:
        metadata = load_campaign_metadata(folder)
        cid, machine = metadata["campaign_id"], nominal_machine(metadata)
        doc, truth = read_truth(folder)
        meas = assemble_measurements(read_table("images", a.results, cid), read_table("poses", a.results, cid))
        t0 = time.perf_counter()
        model = calibrate(machine, meas, truth).model
        took = time.perf_counter() - t0
        five, val = meas.stage("pige").commands, meas.stage("validation", camera="camera1").commands
        desired, compensated = desired_tip_poses(machine, val), compensate(machine, model, val).commands
        target = constant_tool_frame_error(machine, truth, desired, compensated)
        ranges, seed = np.column_stack([five.min(axis=0), five.max(axis=0)]), int(doc["seed"])
        rng = np.random.default_rng(seed)
        old = ring_layout(machine, Workpiece(rings=63), ranges, seed)
        old_exact, old_noisy = fit_error(machine, model, truth,
                                         compensate(machine, model, on_flat_surface(machine, old)).commands,
                                         old.centres, target, a.noise_um, rng, a.draws)
        first, second = (ring_layout(machine, Workpiece(), ranges, seed + k) for k in (0, 1))
        rings = np.vstack([first.centres, second.centres])
        results = [(old_exact, old_noisy)]
        for plates in ((on_flat_surface(machine, first), on_flat_surface(machine, second)),
                       (first.commands, second.commands)):
            commands = np.vstack([plates[0], compensate(machine, model, plates[1]).commands])
            results.append(fit_error(machine, model, truth, commands, rings, target, a.noise_um, rng, a.draws))
        floor = horizontal_floor(machine, truth, desired, compensated, target)
        cells = " | ".join(f"{exact:5.2f} {np.median(noisy):5.2f} {np.percentile(noisy, 95):5.2f} {noisy.max():5.2f}"
                           for exact, noisy in results)
        print(f"{cid:>9} {np.linalg.norm(target):9.2f} {floor:6.2f} | {cells} | {took:.0f}", flush=True)


if __name__ == "__main__":
    main()
