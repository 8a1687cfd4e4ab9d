"""The diagnosis on the joint step's solution vs on the alternation's (docs/diagnosis.md, "Limits").

Usage: .venv/bin/python bench/bench_diagnosis_estimators.py "thermal_drift:axis=Y,driver=time,um_per_hour=30"

The campaign of tests/analysis/test_diagnosis.py (its plan, pose covariance and noise draw) with the hidden
effects given; prints, for the calibration's joint solution and for the alternation's converged
one, the cross-validated RMS of the residual and the diagnosis' top candidates (fitted spec).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path[:0] = [str(Path(__file__).resolve().parents[1]), str(Path(__file__).resolve().parents[1] / "tests")]

from test_diagnosis import COV, PLAN, simulate  # noqa: E402

from tasks.analysis.diagnosis import diagnose, linearised_cross_validated_rms  # noqa: E402
from tasks.analysis.diagnosis.linearisation import alternation_of  # noqa: E402
from tasks.identification.calibration import calibrate  # noqa: E402
from tasks.identification.measurements import planned_measurements  # noqa: E402
from tasks.identification.pige_identification import CalibrationResult  # noqa: E402
from tasks.machine.description import load_machine  # noqa: E402
from tasks.machine.effects import parse_effect  # noqa: E402
from tasks.simulation.campaign_plan import plan_campaign  # noqa: E402


def main(specs: list[str]) -> None:
    machine = load_machine("prototype")
    plan, _ = plan_campaign(machine, PLAN, 5)
    meas = simulate(machine, planned_measurements(plan, COV), [parse_effect(s) for s in specs])
    joint = calibrate(machine, meas)
    alternation = alternation_of(machine, meas, joint)
    # the joint solution as the diagnosis would see it were it linearised there
    as_is = CalibrationResult(joint.pdge, joint.pige, extraction_model=joint.extraction_model)
    for name, result in (("joint", as_is), ("alternation", alternation)):
        d = diagnose(machine, meas, result, max_effects=1)
        print(f"{name}: cv_rms {linearised_cross_validated_rms(machine, meas, result):.3f}, best {d.best}")
        print(d.table.head(3)[["family", "axis", "spec", "p_value", "delta_bic", "cv_rms", "accepted"]].to_string())


if __name__ == "__main__":
    main(sys.argv[1:])
