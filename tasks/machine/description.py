"""A five-axis machine described as data: axes, chains, attachments, cameras and plates.

The description is a JSON file (see ``tasks/machine/machines/prototype.json`` and
``docs/machine-description.md``). Another five-axis layout is a new file, not new code.

Frames: the base frame B has its origin at the intersection of the rotary axes with every
axis at its zero command. Every axis owns a link frame whose home pose (all axes at zero) is
``home_position_mm`` with the base orientation; the joint moves that frame by
``exp(xi * theta)`` with the unit twist ``xi`` expressed in the frame itself (local PoE,
eqs. 4–7). Attachments (cameras, plates, the dispensing tip) ride on one link with a fixed pose
in that link's frame. Units: mm, radians inside; degrees only in files and commands of A/C.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from tasks.core import se3
from tasks.machine.camera_model import CameraModel
from tasks.machine.plate import DotPlate

MACHINES_DIR = Path(__file__).parent / "machines"
AXIS_ORDER = ("X", "Y", "Z", "A", "C")  # column order of command arrays everywhere
COMMAND_COLUMNS = ("X_mm", "Y_mm", "Z_mm", "A_deg", "C_deg")  # table columns of the commands, in AXIS_ORDER
CALIBRATION_STAGE = "camera_calibration"  # the campaign stage of the self-calibration views


@dataclass(frozen=True)
class Axis:
    """One joint. direction: unit vector in the base frame; home_position_mm: link frame origin
    at home (for a rotary axis a point on its axis); stroke in mm (linear) or degrees (rotary)."""

    name: str
    kind: str  # "linear" | "rotary"
    direction: tuple[float, float, float]
    home_position_mm: tuple[float, float, float]
    stroke: tuple[float, float]

    @property
    def is_rotary(self) -> bool:
        return self.kind == "rotary"

    @property
    def unit_twist(self) -> np.ndarray:
        """(6,) unit screw (v, w) in the axis' own link frame (origin on the axis: v = 0 for rotary)."""
        d = np.asarray(self.direction, dtype=float)
        return np.concatenate([np.zeros(3), d]) if self.is_rotary else np.concatenate([d, np.zeros(3)])

    def to_internal(self, command: np.ndarray) -> np.ndarray:
        """Command (mm or deg) -> joint displacement (mm or rad)."""
        return np.deg2rad(command) if self.is_rotary else np.asarray(command, dtype=float)


@dataclass(frozen=True)
class Attachment:
    """A rigid body riding on ``link`` ("base" or an axis name) at ``pose_in_link`` (4×4, mm)."""

    name: str
    link: str
    pose_in_link: np.ndarray = field(compare=False)


def plate_seen(views: Mapping[str, str], calibration_targets: Mapping[str, str], camera: str, stage: str) -> str:
    """Name of the plate ``camera`` sees in an image of campaign ``stage``: its self-calibration
    target (``calibration_targets``) in the ``camera_calibration`` stage, the plate it measures
    (``views``) in every other stage and when it has no target of its own."""
    if stage == CALIBRATION_STAGE:
        return calibration_targets.get(camera, views[camera])
    return views[camera]


@dataclass(frozen=True)
class Machine:
    """The whole machine description. See the module docstring for frames and units."""

    name: str
    axes: dict[str, Axis]
    tool_chain: tuple[str, ...]
    workpiece_chain: tuple[str, ...]
    attachments: dict[str, Attachment]
    cameras: dict[str, CameraModel]
    plates: dict[str, DotPlate]
    views: dict[str, str]  # camera name -> plate name it measures
    tip: str = "tip"
    workpiece: str = "plate_a"
    notes: tuple[str, ...] = ()
    source: dict = field(default_factory=dict, compare=False, repr=False)
    calibration_targets: dict[str, str] = field(default_factory=dict)  # camera -> plate it self-calibrates on

    @property
    def linear_axes(self) -> tuple[str, ...]:
        """Names of the linear axes, in the description's order."""
        return tuple(name for name, axis in self.axes.items() if not axis.is_rotary)

    def plate_seen(self, camera: str, stage: str) -> str:
        """Name of the plate ``camera`` sees in an image of campaign ``stage`` (:func:`plate_seen`)."""
        return plate_seen(self.views, self.calibration_targets, camera, stage)

    def chain_of(self, axis: str) -> tuple[str, ...]:
        for chain in (self.tool_chain, self.workpiece_chain):
            if axis in chain:
                return chain
        raise KeyError(axis)

    def parents(self, link: str) -> tuple[str, ...]:
        """Axes from the base up to and including ``link`` (empty for "base")."""
        if link == "base":
            return ()
        chain = self.chain_of(link)
        return chain[: chain.index(link) + 1]

    @cached_property
    def link_offsets(self) -> dict[str, np.ndarray]:
        """Fixed transform from the previous link frame to each axis frame at home (4×4):
        the ``e^{t̂_{i-1,i}}`` factors of eq. 12."""
        out = {}
        for chain in (self.tool_chain, self.workpiece_chain):
            prev = np.zeros(3)
            for name in chain:
                here = np.asarray(self.axes[name].home_position_mm, dtype=float)
                out[name] = se3.translation(here - prev)
                prev = here
        return out

    def strokes_command(self) -> np.ndarray:
        """(5, 2) stroke limits in command units (mm, deg), in AXIS_ORDER."""
        return np.array([self.axes[a].stroke for a in AXIS_ORDER], dtype=float)

    def commands_to_internal(self, commands: np.ndarray) -> np.ndarray:
        """(N, 5) commands X/Y/Z mm, A/C deg -> (N, 5) mm, rad."""
        q = np.array(commands, dtype=float, copy=True)
        for i, a in enumerate(AXIS_ORDER):
            q[..., i] = self.axes[a].to_internal(q[..., i])
        return q


def _pose_from_spec(spec: dict) -> np.ndarray:
    """4×4 from {"position_mm": [x,y,z], "x_axis": [...], "z_axis": [...]} in the link frame."""
    p = np.asarray(spec["position_mm"], dtype=float)
    z = np.asarray(spec.get("z_axis", (0, 0, 1)), dtype=float)
    x = np.asarray(spec.get("x_axis", (1, 0, 0)), dtype=float)
    z = z / np.linalg.norm(z)
    x = x - z * (x @ z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return se3.from_rotation_translation(np.stack([x, y, z], axis=1), p)


def machine_from_dict(d: dict) -> Machine:
    """Build a :class:`Machine` from its JSON description (see docs/machine-description.md)."""
    axes = {
        name: Axis(
            name=name,
            kind=a["kind"],
            direction=tuple(float(v) for v in a["direction"]),
            home_position_mm=tuple(float(v) for v in a["home_position_mm"]),
            stroke=(float(a["stroke"][0]), float(a["stroke"][1])),
        )
        for name, a in d["axes"].items()
    }
    missing = set(AXIS_ORDER) - set(axes)
    if missing:
        raise ValueError(f"machine description lacks axes {sorted(missing)}")
    attachments = {
        name: Attachment(name=name, link=a["link"], pose_in_link=_pose_from_spec(a))
        for name, a in d["attachments"].items()
    }
    for att in attachments.values():
        if att.link != "base" and att.link not in axes:
            raise ValueError(f"attachment {att.name!r} rides on unknown link {att.link!r}")
    cameras = {n: CameraModel.from_dict({**c, "name": n}) for n, c in d["cameras"].items()}
    plates = {n: DotPlate.from_dict({**p, "name": n}) for n, p in d["plates"].items()}
    return Machine(
        name=d["name"],
        axes=axes,
        tool_chain=tuple(d["tool_chain"]),
        workpiece_chain=tuple(d["workpiece_chain"]),
        attachments=attachments,
        cameras=cameras,
        plates=plates,
        views=dict(d["views"]),
        tip=d.get("tip", "tip"),
        workpiece=d.get("workpiece", "plate_a"),
        notes=tuple(d.get("notes", ())),
        source=d,
        calibration_targets=dict(d.get("calibration_targets", {})),
    )


def load_machine(name_or_path: str | Path = "prototype") -> Machine:
    """Load a machine description by name (from tasks/machine/machines/) or from a JSON file path."""
    path = Path(name_or_path)
    if not path.suffix:
        path = MACHINES_DIR / f"{name_or_path}.json"
    with open(path) as f:
        return machine_from_dict(json.load(f))
