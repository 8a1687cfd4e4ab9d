"""A calibrated campaign as the lake holds it, for the flows that run after ``calibrate``
(``dispense-test``, ``dispense-job``): its tables, the effects it fitted and calibrate's cached
identification."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from tasks.campaign.ingest import load_campaign_metadata
from tasks.dispensing.measure import full_resolution
from tasks.identification.measurements import Measurements, assemble_measurements
from tasks.identification.pige_identification import CalibrationResult
from tasks.lake.store import read_provenance, read_table
from tasks.machine.camera_model import CameraModel
from tasks.machine.description import Machine, load_machine
from tasks.machine.effects import recorded_effects
from tasks.machine.error_model import ErrorModel
from tasks.simulation.simulate import read_truth
from tasks.simulation.verification_capture import is_simulated
from tasks.steps.calibration import identify_task
from tasks.vision.detector_comparison import intrinsics_from_table
from tasks.vision.pipeline import nominal_machine


@dataclass(frozen=True)
class LakeCalibration:
    """campaign_id, the ``pige`` table's provenance (``effects``, ``effect_modules``,
    ``orientation_objective``, ...), the nominal machine, the measurements (mm, rad; camera frames),
    the calibrated intrinsics per camera, calibrate's identification result (its model, and what
    its uncertainty is propagated for), and for a simulated campaign its truth.json and true error
    model (None for a lab's campaign)."""

    campaign_id: str
    provenance: dict
    machine: Machine
    measurements: Measurements
    cameras: dict[str, CameraModel]
    result: CalibrationResult
    truth_doc: dict | None
    truth: ErrorModel | None

    @property
    def model(self) -> ErrorModel:
        """The identified error model."""
        return self.result.model

    @property
    def simulated(self) -> bool:
        return self.truth is not None

    def full_resolution_camera(self, camera: str) -> CameraModel:
        """``camera``'s calibrated model on the unbinned sensor (the campaign's images may be binned,
        ``--size small``): what the full-resolution dispensing crops are measured with."""
        model = self.cameras[camera]
        return full_resolution(model, round(load_machine("prototype").cameras[camera].width_px / model.width_px))


def calibration_from_lake(campaign: Path, root: Path | None, effect_modules: list[str] | None = None
                          ) -> LakeCalibration:
    """The calibration of the campaign folder ``campaign`` in the lake at ``root``. The model is
    calibrate's identification (a cached Prefect task: call this inside a flow) of the effects it
    recorded, their user families imported from ``effect_modules`` when given (``--effect-module``),
    else from the modules the calibration recorded. ValueError when the campaign has no calibration
    or its effects cannot be read."""
    campaign = Path(campaign)
    metadata = load_campaign_metadata(campaign)
    campaign_id = metadata["campaign_id"]
    try:
        provenance = read_provenance("pige", campaign_id, root)
    except (FileNotFoundError, OSError) as e:
        raise ValueError(f"campaign {campaign_id} has no calibration in the lake ({e}): run fivecal calibrate "
                         f"first") from None
    machine = nominal_machine(metadata)
    measurements = assemble_measurements(read_table("images", root, campaign_id),
                                         read_table("poses", root, campaign_id))
    cameras = intrinsics_from_table(read_table("camera_calibration", root, campaign_id), metadata)
    # the truth, with the user effect modules recorded beside it, read only to report against it
    truth_doc, truth = read_truth(campaign) if is_simulated(campaign) else (None, None)
    base = ErrorModel(effects=recorded_effects(provenance.get("effects", []), provenance.get("effect_modules", []),
                                               effect_modules))
    result = identify_task.submit(machine, measurements, truth, base).result()
    return LakeCalibration(campaign_id, provenance, machine, measurements, cameras, result, truth_doc, truth)
