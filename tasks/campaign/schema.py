"""The schema of ``campaign.json``: every key the analysis reads, with its type and range.

SYNOPSIS::

    from tasks.campaign.schema import SchemaFault, check_metadata
    try:
        check_metadata(json.loads(text))
    except SchemaFault as e:
        print(e)  # "plates.plate_a.pitch_mm must be a number > 0 (got -11.0)"

:func:`check_metadata` raises :class:`SchemaFault` naming the first key that breaks the schema,
as a dotted path from the top of the file. It is a plain-Python validator (no dependency): each
check below is one rule of docs/campaign-format.md. Lengths in mm, angles in degrees, image
sizes in px.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

SUPPORTED_FORMAT_VERSIONS = (1,)
AXES = {"X": "linear", "Y": "linear", "Z": "linear", "A": "rotary", "C": "rotary"}
AXIS_UNITS = {"linear": "mm", "rotary": "deg"}
PLATE_KEYS = {"rows", "cols", "pitch_mm", "row_pitch_mm", "dot_diameter_mm", "dark_dots", "margin_mm"}
MIN_DOTS_PER_LINE = 2  # a grid of one row or column has no lattice to order
MAX_DOTS_PER_LINE = 1000


class SchemaFault(ValueError):
    """campaign.json breaks its schema; the message starts with the dotted key at fault."""


def _fault(key: str, what: str, value: Any) -> SchemaFault:
    shown = repr(value)
    return SchemaFault(f"{key} {what} (got {shown[:80] + '…' if len(shown) > 80 else shown})")


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _integer(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _object(meta: Mapping, key: str, path: str, required: bool = True) -> dict | None:
    v = meta.get(key)
    if v is None and not required:
        return None
    if not isinstance(v, dict) or (required and not v):
        raise _fault(f"{path}{key}", "must be a non-empty object", v)
    return v


def _positive(d: Mapping, key: str, path: str, required: bool = True, allow_zero: bool = False) -> None:
    if key not in d and not required:
        return
    v = d.get(key)
    ok = _number(v) and (v >= 0 if allow_zero else v > 0)
    if not ok:
        raise _fault(f"{path}.{key}", f"must be a number {'≥' if allow_zero else '>'} 0", v)


def _vector(d: Mapping, key: str, path: str, required: bool = True, nonzero: bool = False) -> None:
    if key not in d and not required:
        return
    v = d.get(key)
    if not (isinstance(v, list) and len(v) == 3 and all(_number(x) for x in v)):
        raise _fault(f"{path}.{key}", "must be a list of 3 finite numbers", v)
    if nonzero and math.hypot(*v) == 0:
        raise _fault(f"{path}.{key}", "must not be the zero vector", v)


def check_cameras(meta: Mapping) -> None:
    """``cameras``: {camera: {width_px, height_px (positive integers, px), pixel_size_mm,
    focal_length_mm (> 0, mm), optional focus_distance_mm, f_number (> 0)}}."""
    for name, cam in _object(meta, "cameras", "").items():
        path = f"cameras.{name}"
        if not isinstance(cam, dict):
            raise _fault(path, "must be an object", cam)
        for key in ("width_px", "height_px"):
            v = cam.get(key)
            if not _integer(v) or v <= 0:
                raise _fault(f"{path}.{key}", "must be a positive integer", v)
        for key in ("pixel_size_mm", "focal_length_mm"):
            _positive(cam, key, path)
        for key in ("focus_distance_mm", "f_number"):
            _positive(cam, key, path, required=False)


def check_plates(meta: Mapping) -> None:
    """``plates``: {plate: {rows, cols (integers ≥ 2), pitch_mm, dot_diameter_mm (> 0, mm; the
    diameter smaller than the pitches), optional row_pitch_mm (> 0 or null), dark_dots (bool),
    margin_mm (≥ 0)}}; no other key."""
    for name, plate in _object(meta, "plates", "").items():
        path = f"plates.{name}"
        if not isinstance(plate, dict):
            raise _fault(path, "must be an object", plate)
        unknown = sorted(set(plate) - PLATE_KEYS)
        if unknown:
            raise _fault(f"{path}.{unknown[0]}", f"is not a plate key ({', '.join(sorted(PLATE_KEYS))})",
                         plate[unknown[0]])
        for key in ("rows", "cols"):
            v = plate.get(key)
            if not _integer(v) or not MIN_DOTS_PER_LINE <= v <= MAX_DOTS_PER_LINE:
                raise _fault(f"{path}.{key}", f"must be an integer from {MIN_DOTS_PER_LINE} to {MAX_DOTS_PER_LINE}",
                             v)
        _positive(plate, "pitch_mm", path)
        if plate.get("row_pitch_mm") is not None:
            _positive(plate, "row_pitch_mm", path)
        _positive(plate, "dot_diameter_mm", path)
        _positive(plate, "margin_mm", path, required=False, allow_zero=True)
        if "dark_dots" in plate and not isinstance(plate["dark_dots"], bool):
            raise _fault(f"{path}.dark_dots", "must be true or false", plate["dark_dots"])
        pitch = min(plate["pitch_mm"], plate.get("row_pitch_mm") or plate["pitch_mm"])
        if plate["dot_diameter_mm"] >= pitch:
            raise _fault(f"{path}.dot_diameter_mm", f"must be smaller than the pitch ({pitch:g} mm): dots would touch",
                         plate["dot_diameter_mm"])


def check_views(meta: Mapping) -> None:
    """``views`` (required): {camera: plate it measures}; optional ``calibration_targets``:
    {camera: plate of its camera_calibration views}. Cameras and plates must be declared."""
    for key, required in (("views", True), ("calibration_targets", False)):
        mapping = _object(meta, key, "", required=required)
        for camera, plate in (mapping or {}).items():
            if camera not in meta["cameras"]:
                raise _fault(f"{key}.{camera}", f"is not a camera of 'cameras' ({', '.join(meta['cameras'])})", camera)
            if not isinstance(plate, str) or plate not in meta["plates"]:
                raise _fault(f"{key}.{camera}", f"must name a plate of 'plates' ({', '.join(meta['plates'])})", plate)


def check_machine(meta: Mapping) -> None:
    """``machine``: a name; axes X, Y, Z (linear, mm) and A, C (rotary, deg) with kind, direction (non-zero),
    home_position_mm and stroke [low, high] (low < high); tool_chain and workpiece_chain listing
    each axis once; attachments {name: {link (an axis or "base"), position_mm, optional z_axis,
    x_axis (non-zero, not parallel)}} including the tip and every viewing camera and its plates."""
    machine = _object(meta, "machine", "")
    if not isinstance(machine.get("name"), str):
        raise _fault("machine.name", "must be a string", machine.get("name"))
    for key in ("tip", "workpiece"):
        if key in machine and not isinstance(machine[key], str):
            raise _fault(f"machine.{key}", "must be the name of an attachment", machine[key])
    notes = machine.get("notes", [])
    if not isinstance(notes, list) or not all(isinstance(n, str) for n in notes):
        raise _fault("machine.notes", "must be a list of strings", notes)
    axes = _object(machine, "axes", "machine.")
    for axis, kind in AXES.items():
        path = f"machine.axes.{axis}"
        a = axes.get(axis)
        if not isinstance(a, dict):
            raise _fault(path, "must be an object (every axis X, Y, Z, A, C is needed)", a)
        stroke = a.get("stroke")
        if not (isinstance(stroke, list | tuple) and len(stroke) == 2 and all(_number(s) for s in stroke)
                and stroke[0] < stroke[1]):
            raise _fault(f"{path}.stroke", f"must be [low, high] in {AXIS_UNITS[kind]} with low < high", stroke)
        if a.get("kind") != kind:
            raise _fault(f"{path}.kind", f"must be {kind!r}", a.get("kind"))
        _vector(a, "direction", path, nonzero=True)
        _vector(a, "home_position_mm", path)
    chains = []
    for key in ("tool_chain", "workpiece_chain"):
        chain = machine.get(key)
        if not isinstance(chain, list) or not all(isinstance(x, str) and x in AXES for x in chain):
            raise _fault(f"machine.{key}", "must be a list of axis names (X, Y, Z, A, C)", chain)
        chains += chain
    if sorted(chains) != sorted(AXES):
        raise _fault("machine.tool_chain", "and machine.workpiece_chain must list each axis exactly once", chains)
    attachments = _object(machine, "attachments", "machine.")
    for name, att in attachments.items():
        path = f"machine.attachments.{name}"
        if not isinstance(att, dict):
            raise _fault(path, "must be an object", att)
        link = att.get("link")
        if not isinstance(link, str) or (link != "base" and link not in AXES):
            raise _fault(f"{path}.link", "must be an axis name or 'base'", att.get("link"))
        _vector(att, "position_mm", path)
        _vector(att, "z_axis", path, required=False, nonzero=True)
        _vector(att, "x_axis", path, required=False, nonzero=True)
        z, x = att.get("z_axis", [0, 0, 1]), att.get("x_axis", [1, 0, 0])
        cross = (z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0])
        if math.hypot(*cross) <= 1e-9 * math.hypot(*z) * math.hypot(*x):
            raise _fault(f"{path}.x_axis", "must not be parallel to z_axis", x)
    needed = {machine.get("tip", "tip"), *meta["views"], *meta["views"].values()}
    missing = sorted(n for n in needed if n not in attachments)
    if missing:
        raise _fault("machine.attachments", f"lacks {', '.join(missing)} (the tip and every viewing camera "
                     "and its plate are attached to the machine)", sorted(attachments))


def check_metadata(meta: Any) -> None:
    """Check parsed campaign.json ``meta`` against the schema; raises :class:`SchemaFault` naming
    the first key at fault. ``format_version`` and ``campaign_id`` are checked by the caller."""
    if not isinstance(meta, dict):
        raise SchemaFault(f"must hold a JSON object, not {type(meta).__name__}")
    check_cameras(meta)
    check_plates(meta)
    check_views(meta)
    check_machine(meta)
