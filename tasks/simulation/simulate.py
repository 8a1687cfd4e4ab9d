"""The virtual machine playing a measurement campaign: truth per image, and its rendering.

``simulate_truth`` runs the true machine (description + error model + effects) through the
planned poses in capture order and returns, per image, the true plate pose in the camera frame,
the camera intrinsics of that exposure and the projected dot centres. ``render_image`` turns
one row of that truth into the 8-bit image the camera would record. No Prefect here.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from tasks.campaign.folder import TRUTH_DIR, image_relpath, write_manifest, write_metadata
from tasks.core.atomic_io import atomic_write_bytes, atomic_write_parquet, atomic_write_text
from tasks.core.version import FIVECAL_VERSION
from tasks.machine.camera_model import CameraModel
from tasks.machine.description import AXIS_ORDER, COMMAND_COLUMNS, Machine, load_machine
from tasks.machine.effects import camera_changes, module_source_file, parse_effect, private_families
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward
from tasks.simulation.campaign_plan import CampaignPlan, plan_campaign, plan_context
from tasks.simulation.prototype_errors import load_prototype_errors
from tasks.simulation.render import ImagingConditions, plate_in_view, render_plate_image, true_dot_centres

SIZES = {"full": 1, "small": 4}  # sensor binning factor per image size
CAMPAIGN_EPOCH = pd.Timestamp("2026-01-05T08:00:00Z")


@dataclass
class CampaignTruth:
    """Per-image truth of a simulated campaign (N images, in manifest order).

    T_cam_plate: (N, 4, 4) mm. focal_scale: (N,). centres_px: (N, rows*cols, 2) true projected
    dot centres. in_view: (N,) whole plate inside the image. extra_distortion: {camera: dict|None}.
    cameras: {camera: CameraModel} true intrinsics at the campaign's image size.
    plate_names: (N,) the plate each image shows (``Machine.plate_seen``).
    """

    T_cam_plate: np.ndarray
    focal_scale: np.ndarray
    centres_px: list[np.ndarray]
    in_view: np.ndarray
    extra_distortion: dict[str, dict | None]
    cameras: dict[str, CameraModel]
    plate_names: list[str]


def camera_for_image(camera: CameraModel, focal_scale: float) -> CameraModel:
    """Intrinsics of one exposure: the focal length scaled by a focal-drift effect."""
    if focal_scale == 1.0:
        return camera
    return replace(camera, focal_length_mm=camera.focal_length_mm * float(focal_scale))


def manifest_from_plan(plan: pd.DataFrame) -> pd.DataFrame:
    """Manifest rows (see tasks.campaign.folder.MANIFEST_COLUMNS) from a campaign plan."""
    m = pd.DataFrame({
        "image_id": plan["image_id"],
        "path": [image_relpath(c, i) for c, i in zip(plan["camera"], plan["image_id"], strict=True)],
        "camera": plan["camera"], "stage": plan["stage"], "group": plan["group"], "repeat": plan["repeat"],
    })
    for col, axis in zip(COMMAND_COLUMNS, AXIS_ORDER, strict=True):
        m[col] = plan[axis].round(6)
    stamps = CAMPAIGN_EPOCH + pd.to_timedelta(plan["time_s"], unit="s")
    m["timestamp"] = stamps.dt.strftime("%Y-%m-%dT%H:%M:%S.%fZ")
    m["temperature_c"] = plan["temperature_c"].round(4)
    return m


def simulate_truth(machine: Machine, errors: ErrorModel, plan: pd.DataFrame,
                   fixture: dict[int, np.ndarray], size: str = "full") -> CampaignTruth:
    """Truth of every planned image.

    plan: rows in capture order (tasks.simulation.campaign_plan.plan_campaign). fixture: {row: T_cam_plate}
    for the views on the calibration fixture (the machine does not produce those poses).
    """
    commands = plan[list(AXIS_ORDER)].to_numpy(dtype=float)
    n = commands.shape[0]
    context = plan_context(plan)
    fk = forward(machine, commands, errors, context)
    q = machine.commands_to_internal(commands)
    cameras = {name: cam.scaled(SIZES[size]) for name, cam in machine.cameras.items()}
    T = np.empty((n, 4, 4))
    focal = np.ones(n)
    extra: dict[str, dict | None] = {}
    camera_col = plan["camera"].to_numpy()
    for name in machine.cameras:
        rows = np.flatnonzero(camera_col == name)
        T[rows] = fk.camera_view(name)[rows]
        ch = camera_changes(errors.effects, name, machine, q, context)
        focal[rows] = ch["focal_scale"][rows]
        extra[name] = ch["extra_distortion"]
    for row, pose in fixture.items():
        T[row] = pose
    plate_names = [machine.plate_seen(c, s) for c, s in zip(camera_col, plan["stage"], strict=True)]
    centres, in_view = [], np.zeros(n, dtype=bool)
    for i in range(n):
        name = camera_col[i]
        cam = camera_for_image(cameras[name], focal[i])
        plate = machine.plates[plate_names[i]]
        centres.append(true_dot_centres(cam, plate, T[i], extra_distortion=_extra(extra[name])))
        in_view[i] = plate_in_view(cam, plate, T[i], extra_distortion=_extra(extra[name]))
    return CampaignTruth(T, focal, centres, in_view, extra, cameras, plate_names)


def _extra(d: dict | None):
    return None if not d else tuple(d[k] for k in ("k4", "s1", "s2", "s3", "s4"))


def imaging_conditions(seed: int, index: int) -> ImagingConditions:
    """Photometry of one exposure: small seeded variations of light level and gradient."""
    rng = np.random.default_rng([seed, 7, index])
    return ImagingConditions(
        light_level=float(rng.uniform(185, 215)),
        gradient=float(rng.uniform(0.02, 0.08)),
        gradient_angle_deg=float(rng.uniform(0, 360)),
    )


def render_image(machine: Machine, truth: CampaignTruth, camera: str, index: int, seed: int) -> np.ndarray:
    """The uint8 image of row ``index``, deterministic from (seed, index)."""
    cam = camera_for_image(truth.cameras[camera], truth.focal_scale[index])
    plate = machine.plates[truth.plate_names[index]]
    return render_plate_image(cam, plate, truth.T_cam_plate[index], imaging_conditions(seed, index),
                              seed=int(np.random.default_rng([seed, 11, index]).integers(2**63)),
                              extra_distortion=_extra(truth.extra_distortion[camera]))


def encode_png(image: np.ndarray) -> bytes:
    """Lossless PNG bytes of an 8-bit image (fast compression level)."""
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def truth_tables(plan: pd.DataFrame, truth: CampaignTruth, machine: Machine) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Parquet-ready truth: per image (pose, focal scale, in view) and per dot (u, v px)."""
    n = len(plan)
    images = pd.DataFrame({"image_id": plan["image_id"], "camera": plan["camera"],
                           "focal_scale": truth.focal_scale, "in_view": truth.in_view})
    flat = truth.T_cam_plate[:, :3, :].reshape(n, 12)
    for k, (i, j) in enumerate((i, j) for i in range(3) for j in range(4)):
        images[f"T{i}{j}"] = flat[:, k]
    dots = []
    for i in range(n):
        rc = machine.plates[truth.plate_names[i]].row_col()
        dots.append(pd.DataFrame({"image_id": plan["image_id"].iloc[i], "row": rc[:, 0], "col": rc[:, 1],
                                  "u_px": truth.centres_px[i][:, 0], "v_px": truth.centres_px[i][:, 1]}))
    return images, pd.concat(dots, ignore_index=True)


def campaign_metadata(machine: Machine, campaign_id: str, size: str) -> dict:
    """campaign.json content: geometry and *nominal* camera data only (no true intrinsics)."""
    src = machine.source
    cams = {}
    for name, cam in machine.cameras.items():
        c = cam.scaled(SIZES[size])
        cams[name] = {"width_px": c.width_px, "height_px": c.height_px, "pixel_size_mm": c.pixel_size_mm,
                      "focal_length_mm": src["cameras"][name]["focal_length_mm"],
                      "focus_distance_mm": c.focus_distance_mm}
    machine_geometry = {k: src[k] for k in ("name", "axes", "tool_chain", "workpiece_chain", "attachments",
                                             "tip", "workpiece", "views", "plates", "notes")}
    targets = dict(src.get("calibration_targets", {}))  # optional: a camera without one calibrates on its plate
    return {"format_version": 1, "campaign_id": campaign_id, "simulated": True,
            "fivecal_version": FIVECAL_VERSION, "machine": {**machine_geometry, "calibration_targets": targets},
            "cameras": cams, "plates": src["plates"], "views": src["views"], "calibration_targets": targets}


EFFECT_MODULES_DIR = "effect_modules"


def record_effect_modules(truth_dir: Path, modules) -> list[str]:
    """Copy the source of each user effect module (dotted path or ``.py`` file, as
    :func:`tasks.machine.effects.load_effect_modules` takes them) into ``<truth_dir>/effect_modules/``;
    returns the file names, for truth.json. The truth then holds every family it names, so the
    simulator's side of later runs needs no module of the user's."""
    names = []
    for module in modules:
        source = module_source_file(module)
        target = Path(truth_dir) / EFFECT_MODULES_DIR / source.name
        if source.name in names:
            raise ValueError(f"effect modules {module!r} and another share the file name {source.name}")
        target.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(target, source.read_bytes())
        names.append(source.name)
    return names


def read_truth(campaign_folder: Path) -> tuple[dict, ErrorModel]:
    """truth.json of a simulated campaign and its true error model, the effects of the user modules
    recorded with it (:func:`record_effect_modules`) parsed without adding them to the catalogue
    (:func:`tasks.machine.effects.private_families`): simulator side only."""
    truth_dir = Path(campaign_folder) / TRUTH_DIR
    doc = json.loads((truth_dir / "truth.json").read_text())
    families = private_families([truth_dir / EFFECT_MODULES_DIR / n for n in doc.get("effect_modules", [])])
    return doc, ErrorModel.from_dict(doc["error_model"], families)


def write_campaign_truth(folder: Path, campaign_id: str, seed: int, size: str, effects: list[str],
                         plan: CampaignPlan, effect_modules: list[str] | None = None
                         ) -> tuple[Machine, pd.DataFrame, CampaignTruth]:
    """Plan the campaign, run the true prototype, and write metadata, manifest and truth/.

    effect_modules: the user modules that define families of ``effects`` (already loaded); their
    source is recorded in truth/ (:func:`record_effect_modules`). Returns what :func:`write_images`
    needs. Images are not written here.
    """
    machine = load_machine("prototype")
    errors = load_prototype_errors()
    errors.effects = [parse_effect(s) for s in effects]
    poses, fixture = plan_campaign(machine, plan, seed)
    truth = simulate_truth(machine, errors, poses, fixture, size)
    folder = Path(folder)
    write_metadata(folder, campaign_metadata(machine, campaign_id, size))
    write_manifest(folder, manifest_from_plan(poses))
    images, dots = truth_tables(poses, truth, machine)
    provenance = {"fivecal_version": FIVECAL_VERSION, "seed": seed, "size": size}
    atomic_write_parquet(folder / TRUTH_DIR / "images.parquet", images, provenance)
    atomic_write_parquet(folder / TRUTH_DIR / "dots.parquet", dots, provenance)
    truth_doc = {"seed": seed, "size": size, "plan": asdict(plan), "effects": list(effects),
                 "error_model": errors.to_dict(),
                 "effect_modules": record_effect_modules(folder / TRUTH_DIR, effect_modules or []),
                 "cameras": {n: c.to_dict() for n, c in truth.cameras.items()},
                 "note": "Ground truth of a simulated campaign. No analysis stage reads this folder."}
    atomic_write_text(folder / TRUTH_DIR / "truth.json", json.dumps(truth_doc, indent=1))
    return machine, poses, truth


def write_images(folder: Path, machine: Machine, poses: pd.DataFrame, truth: CampaignTruth, rows, seed: int) -> int:
    """Render and write the images of manifest ``rows``; returns how many were written."""
    for i in rows:
        camera, image_id = poses["camera"].iloc[i], poses["image_id"].iloc[i]
        png = encode_png(render_image(machine, truth, camera, int(i), seed))
        atomic_write_bytes(Path(folder) / "images" / camera / f"{image_id}.png", png)
    return len(rows)


def write_campaign(folder: Path, campaign_id: str, seed: int = 0, size: str = "small",
                   effects: list[str] | None = None, plan: CampaignPlan | None = None,
                   effect_modules: list[str] | None = None) -> Path:
    """A whole simulated campaign written sequentially, without Prefect (tests, notebooks)."""
    machine, poses, truth = write_campaign_truth(folder, campaign_id, seed, size, list(effects or []),
                                                 plan or CampaignPlan(), effect_modules)
    write_images(folder, machine, poses, truth, range(len(poses)), seed)
    return Path(folder)
