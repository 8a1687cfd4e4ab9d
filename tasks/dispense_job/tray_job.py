"""One tray through the job: located areas → mapped (per phase) → bead paths → tour → program →
(simulated trays) executed by the true machine, imaged, beads inspected.

Phases: ``compensated`` (camera 1's calibrated model, the identified machine model, compensated
commands), ``nominal`` (the same pixels through the nominal machine, uncompensated commands: the
machine without its calibration) and ``planar`` (the paper's affine pixel → X/Y map from the tray's
hand–eye pairs, Z from the nominal machine, A = C = 0).

The tour, travel time and bead path come from the planners passed in (tasks.dispense_job.tour_exact,
travel_time, bead_path), so that this module does the wiring only.

Frames: image pixels; workpiece frame (mm) for the calibrated phases, machine X/Y commands (mm) for the
planar phase (what the paper's map gives); commands X, Y, Z (mm), A, C (deg).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from tasks.dispense_job.bead_inspection import axis_offsets, find_beads, measure_beads, pair_beads
from tasks.dispense_job.boards import apply_light, paint_tray, place_boards
from tasks.dispense_job.camera_view import camera_image
from tasks.dispense_job.execute import Glue, bead_truth, draw_widths, landed_beads, paint_beads
from tasks.dispense_job.pixel_map import (
    PlanarMap,
    check_travel,
    commands_at,
    directions_to_workpiece,
    fit_planar_map,
    pixels_to_workpiece,
)
from tasks.dispense_job.program import Motion, program_rows, program_time_s
from tasks.dispense_job.recognition import match_found_boards
from tasks.dispense_job.tray_io import STANDOFF_MM, Tray, camera_spec, tray_spec
from tasks.dispensing.tip import landing_points
from tasks.machine.camera_model import CameraModel
from tasks.machine.description import Machine, load_machine
from tasks.machine.error_model import ErrorModel

PHASES = ("compensated", "nominal", "planar")
TOUR_METHODS = ("optimal", "annealing", "nearest", "return_to_origin")


@dataclass(frozen=True)
class Calibration:
    """What the job needs of the calibrated machine: the description, the identified model (with the
    dispensing test's tip offset when it was run), camera 1's calibrated intrinsics at full
    resolution, and for a simulated campaign its true model."""

    campaign_id: str
    machine: Machine
    model: ErrorModel
    camera: CameraModel
    truth: ErrorModel | None = None
    notes: tuple[str, ...] = field(default=())


@dataclass(frozen=True)
class Planners:
    """The path planners (the other half of the job): ``plan_tour(points (n, 2), home_mm, method, seed)``
    → Tour, ``travel_time_s(path (k, 3), speed (3,), accel (3,))`` → s, ``bead_path(centre (2,),
    angle_deg, size (2,), needle_mm=bead width)`` → (k, 2) waypoints."""

    plan_tour: Callable
    travel_time_s: Callable
    bead_path: Callable


@dataclass
class TrayResult:
    """The rows of the three lake tables for one tray, its programs {phase: DataFrame} and the images of
    the dispensed tray {phase: RGB} (simulated trays)."""

    areas: pd.DataFrame
    paths: pd.DataFrame
    beads: pd.DataFrame
    programs: dict[str, pd.DataFrame]
    dispensed: dict[str, np.ndarray]


def area_rows(tray: Tray, located) -> pd.DataFrame:
    """One row per board found (board_id b00…, in the location's order): ok, reason and the accepted
    area's rectangle in pixels (NaN when rejected)."""
    rows = []
    for i, b in enumerate(located.boards):
        r = b.area.rect if b.area is not None else None
        rows.append({"tray_id": tray.tray_id, "board_id": f"b{i:02d}", "ok": b.ok, "reason": b.reason,
                     "u_px": r.u if r else np.nan, "v_px": r.v if r else np.nan,
                     "angle_px_deg": r.angle_deg if r else np.nan, "length_px": r.length_px if r else np.nan,
                     "width_px": r.width_px if r else np.nan, "area_px": b.area.area_px if r else 0})
    return pd.DataFrame(rows, columns=["tray_id", "board_id", "ok", "reason", "u_px", "v_px", "angle_px_deg",
                                       "length_px", "width_px", "area_px"])


def with_truth(base: pd.DataFrame, tray: Tray, located, cal: Calibration) -> pd.DataFrame:
    """``base`` (area_rows) with ``true_defect`` and ``recognised``: for a simulated tray, each found
    board's centre is mapped onto the tray through the calibrated camera and model and matched to the
    true boards (tasks.dispense_job.recognition); every true board that no found board matched is one
    more row (board_id ``missed-`` + its true id, reason ``not found``). Null for a real tray."""
    if tray.truth is None:
        return base.assign(true_defect=None, recognised=pd.array([pd.NA] * len(base), dtype="boolean"))
    uv = np.array([[b.board.rect.u, b.board.rect.v] for b in located.boards]).reshape(-1, 2)
    xy = pixels_to_workpiece(cal.machine, cal.model, cal.camera, tray.imaging_command, uv, tray.surface_z_mm)
    defects, correct, missed = match_found_boards(xy, base["ok"].to_numpy(bool), base["reason"].tolist(), tray.truth)
    extra = pd.DataFrame({"tray_id": tray.tray_id, "board_id": [f"missed-{b}" for b in missed["board_id"]],
                          "ok": False, "reason": "not found", "area_px": 0,
                          "true_defect": [d or "none" for d in missed["defect"]], "recognised": False})
    out = pd.concat([base.assign(true_defect=defects, recognised=correct), extra], ignore_index=True)
    return out.astype({"ok": bool, "area_px": "int64", "recognised": "boolean"})


class PhaseMap:
    """Pixels → the phase's plane (workpiece mm, or machine X/Y mm for ``planar``) and plane points →
    commands."""

    def __init__(self, phase: str, tray: Tray, cal: Calibration):
        self.phase, self.tray, self.cal = phase, tray, cal
        self.model = cal.model if phase == "compensated" else None
        self.planar: PlanarMap | None = None
        if phase == "planar":
            if tray.hand_eye is None:
                raise ValueError(f"{tray.image_path}: the planar map needs hand_eye pairs in the sidecar")
            self.planar = fit_planar_map(tray.hand_eye[:, :2], tray.hand_eye[:, 2:])
            z = commands_at(cal.machine, None, np.zeros((1, 2)), tray.surface_z_mm, STANDOFF_MM)[0, 2]
            self.planar_z = float(z)

    def points(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) plane points of pixels (N, 2)."""
        if self.planar is not None:
            return self.planar.apply(uv)
        return pixels_to_workpiece(self.cal.machine, self.model, self.cal.camera, self.tray.imaging_command, uv,
                                   self.tray.surface_z_mm)

    def angles(self, uv: np.ndarray, angle_deg: np.ndarray) -> np.ndarray:
        """(N,) plane directions (deg, [0, 180)) of image directions at pixels."""
        if self.planar is not None:
            return self.planar.angle_deg(uv, angle_deg)
        return directions_to_workpiece(self.cal.machine, self.model, self.cal.camera, self.tray.imaging_command,
                                       uv, angle_deg, self.tray.surface_z_mm)

    def commands(self, points: np.ndarray) -> np.ndarray:
        """(N, 5) commands putting the needle over plane points (N, 2)."""
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        if self.planar is not None:
            return np.column_stack([pts, np.full(len(pts), self.planar_z), np.zeros((len(pts), 2))])
        return commands_at(self.cal.machine, self.model, pts, self.tray.surface_z_mm, STANDOFF_MM)


def _sides_mm(pmap: PhaseMap, areas: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """(length, width) (mm) of the areas' rectangles, their ends mapped onto the plane."""
    uv = areas[["u_px", "v_px"]].to_numpy(float)
    t = np.deg2rad(areas["angle_px_deg"].to_numpy(float))
    along = np.column_stack([np.cos(t), -np.sin(t)])
    across = np.column_stack([np.sin(t), np.cos(t)])
    hl = (areas["length_px"].to_numpy(float) / 2)[:, None]
    hw = (areas["width_px"].to_numpy(float) / 2)[:, None]
    length = np.linalg.norm(pmap.points(uv + hl * along) - pmap.points(uv - hl * along), axis=1)
    width = np.linalg.norm(pmap.points(uv + hw * across) - pmap.points(uv - hw * across), axis=1)
    return length, width


def _true_area(tray: Tray, xy_mm: np.ndarray) -> pd.DataFrame | None:
    """The truth row of the board nearest each measured workpiece point (within 3 mm), else NaN rows."""
    if tray.truth is None:
        return None
    t = tray.truth[tray.truth["defect"] != "missing_component"]
    txy = t[["area_x_mm", "area_y_mm"]].to_numpy(float)
    rows = []
    for p in xy_mm:
        d = np.linalg.norm(txy - p, axis=1) if len(txy) else np.array([np.inf])
        k = int(np.argmin(d))
        rows.append(t.iloc[k] if d[k] <= 3.0 else pd.Series(dtype=float))
    return pd.DataFrame(rows).reindex(columns=t.columns).reset_index(drop=True)


def run_tray(tray: Tray, located, cal: Calibration, planners: Planners, phases=PHASES, motion: Motion = Motion(),  # noqa: B008
             glue: Glue = Glue(), seed: int = 0) -> TrayResult:  # noqa: B008
    """The job on one located tray (see the module docstring). Boards whose commands leave the travel
    are rejected with the reason; ValueError naming the image when no board is found or none is left."""
    base = area_rows(tray, located)
    if base.empty:
        raise ValueError(f"{tray.image_path}: no board found in the image")
    base = with_truth(base, tray, located, cal)
    areas_out, paths_out, beads_out, programs, dispensed = [], [], [], {}, {}
    for phase in phases:
        pmap = PhaseMap(phase, tray, cal)
        df = base.assign(phase=phase, x_mm=np.nan, y_mm=np.nan, angle_deg=np.nan, true_x_mm=np.nan,
                         true_y_mm=np.nan, true_angle_deg=np.nan, map_error_um=np.nan)
        ok = df["ok"].to_numpy(bool)
        good = df[ok]
        beads_cmd: list[np.ndarray] = []
        centres_cmd = np.zeros((0, 5))
        if ok.any():
            uv = good[["u_px", "v_px"]].to_numpy(float)
            xy = pmap.points(uv)
            ang = pmap.angles(uv, good["angle_px_deg"].to_numpy(float))
            length, width = _sides_mm(pmap, good)
            df.loc[ok, "x_mm"], df.loc[ok, "y_mm"], df.loc[ok, "angle_deg"] = xy[:, 0], xy[:, 1], ang
            centres_cmd = pmap.commands(xy)
            outside = {}
            for k, board in enumerate(good.board_id):
                label = f"{tray.image_path.name} board {board}"
                try:
                    # the stroke covers the area with the bead the glue lays (narrower than the needle's bore)
                    path = np.asarray(planners.bead_path(xy[k], float(ang[k]), np.array([length[k], width[k]]),
                                                         needle_mm=glue.width_mm), float)
                except ValueError as e:  # this board's bead cannot be planned: the others go on
                    beads_cmd.append(centres_cmd[k:k + 1])
                    outside[board] = f"no bead path ({e})"
                    continue
                beads_cmd.append(pmap.commands(path))
                msgs = check_travel(cal.machine, beads_cmd[k], [label] * len(beads_cmd[k]))
                if msgs:
                    outside[board] = "outside the travel: " + msgs[0].split(": ", 1)[1]
            if outside and len(outside) == len(good) and all("outside the travel" in m for m in outside.values()):
                first, why = next(iter(outside.items()))
                raise ValueError(f"{tray.image_path}: the tray is larger than the machine's travel: every board's "
                                 f"bead leaves it (board {first}: {why})")
            for board, why in outside.items():
                df.loc[df.board_id == board, ["ok", "reason"]] = [False, why]
            keep = [k for k, board in enumerate(good.board_id) if board not in outside]
            beads_cmd = [beads_cmd[k] for k in keep]
            centres_cmd = centres_cmd[keep]
            good = good.iloc[keep]
        ids = good["board_id"].tolist()
        if cal.truth is not None and tray.truth is not None and ids:
            wp = pixels_to_workpiece(cal.machine, cal.model, cal.camera, tray.imaging_command,
                                     good[["u_px", "v_px"]].to_numpy(float), tray.surface_z_mm)
            true = _true_area(tray, wp)
            sent = landing_points(cal.machine, cal.truth, centres_cmd)
            sel = df.board_id.isin(ids)
            df.loc[sel, "true_x_mm"] = true["area_x_mm"].to_numpy(float)
            df.loc[sel, "true_y_mm"] = true["area_y_mm"].to_numpy(float)
            df.loc[sel, "true_angle_deg"] = true["area_angle_deg"].to_numpy(float)
            df.loc[sel, "map_error_um"] = 1e3 * np.linalg.norm(
                sent - true[["area_x_mm", "area_y_mm"]].to_numpy(float), axis=1)
        areas_out.append(df)
        if not ids:
            continue
        home_xy = tuple(float(v) for v in tray.home_xy_mm)
        home = np.array([home_xy[0], home_xy[1], centres_cmd[0, 2] + motion.lift_mm, 0.0, 0.0])
        points = centres_cmd[:, :2]
        for method in TOUR_METHODS:
            tour = planners.plan_tour(points, home_mm=home_xy, method=method, seed=seed)
            program = program_rows(np.asarray(tour.order), ids, beads_cmd, home, motion,
                                   home_between=method == "return_to_origin")
            travel, disp = program_time_s(program, motion, planners.travel_time_s)
            paths_out.append({"tray_id": tray.tray_id, "phase": phase, "method": method, "points": len(ids),
                              "length_mm": float(tour.length_mm), "lower_bound_mm": float(tour.lower_bound_mm),
                              "proven_optimal": bool(tour.proven_optimal), "plan_s": float(tour.seconds),
                              "travel_s": travel, "dispense_s": disp, "chosen": method == "optimal"})
            if method == "optimal":
                programs[phase] = program.assign(tray_id=tray.tray_id, phase=phase)
        if cal.truth is not None and tray.simulated:
            rgb, beads = _execute(tray, cal, pmap, programs[phase], df[df.board_id.isin(ids)], glue,
                                  np.random.default_rng([seed, 3434, PHASES.index(phase)]))
            dispensed[phase] = rgb
            beads_out.append(beads.assign(tray_id=tray.tray_id, phase=phase))
    return TrayResult(pd.concat(areas_out, ignore_index=True), pd.DataFrame(paths_out),
                      pd.concat(beads_out, ignore_index=True) if beads_out else pd.DataFrame(), programs, dispensed)


def _execute(tray: Tray, cal: Calibration, pmap: PhaseMap, program: pd.DataFrame, areas: pd.DataFrame, glue: Glue,
             rng: np.random.Generator) -> tuple[np.ndarray, pd.DataFrame]:
    """The true machine runs the program on the simulated tray; camera 1 images it; the beads are
    inspected through the phase's map. Returns (the image, one row per area)."""
    spec = tray_spec(tray)
    sim = tray.simulated
    placed = place_boards(spec, np.random.default_rng([int(sim["seed"]), 34]), int(sim["boards"]))
    lines = landed_beads(cal.machine, cal.truth, program)
    widths = draw_widths(list(lines), glue, rng)
    texture = paint_beads(spec, paint_tray(spec, placed), lines, widths, glue)
    sensor = load_machine("prototype").cameras["camera1"]  # the true camera at full resolution
    view = camera_image(texture.astype(np.float32), spec, cal.machine, cal.truth, sensor, tray.imaging_command,
                        tray.surface_z_mm)
    rgb = apply_light(camera_spec(spec, sensor), [], view.astype(np.float64), rng)
    found = measure_beads(find_beads(rgb, int(0.5 / tray.mm_per_px ** 2)), pmap.points, tray.mm_per_px)
    paired = pair_beads(areas.rename(columns={"x_mm": "area_x_mm", "y_mm": "area_y_mm", "angle_deg": "area_angle_deg"}),
                        found)
    truth = bead_truth(lines, widths).set_index("board_id")
    cols = {"true_offset_along_mm": [], "true_offset_across_mm": [], "true_bead_length_mm": [],
            "true_bead_width_mm": [], "true_within_tolerance": []}
    for a in areas.itertuples(index=False):
        t = truth.loc[a.board_id]
        along, across = axis_offsets(t.true_bead_x_mm - a.true_x_mm, t.true_bead_y_mm - a.true_y_mm, a.true_angle_deg)
        cols["true_offset_along_mm"].append(along)
        cols["true_offset_across_mm"].append(across)
        cols["true_bead_length_mm"].append(t.true_bead_length_mm)
        cols["true_bead_width_mm"].append(t.true_bead_width_mm)
        cols["true_within_tolerance"].append(bool(np.isfinite(along) and max(abs(along), abs(across)) <= 0.5))
    return rgb, paired.assign(**cols)

