"""Every effect family changes the truth as its documentation says."""

import numpy as np
import pytest

from tasks.core.units import ARCSEC, UM
from tasks.machine.context import PoseContext
from tasks.machine.effects import EFFECTS, catalogue_text, parse_effect
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward
from tasks.simulation.render import true_dot_centres
from tasks.simulation.simulate import camera_for_image


def tip_shift_um(machine, spec, cmds, context=None):
    """Tip position change (µm, workpiece frame) that the effect alone causes."""
    base = forward(machine, cmds, ErrorModel(), context).tool_in_workpiece()
    moved = forward(machine, cmds, ErrorModel(effects=[parse_effect(spec)]), context).tool_in_workpiece()
    return (moved[:, :3, 3] - base[:, :3, 3]) / UM, moved, base


def line(axis_index, values):
    cmds = np.zeros((len(values), 5))
    cmds[:, axis_index] = values
    return cmds


def test_scale_grows_linearly_with_position(machine):
    d, _, _ = tip_shift_um(machine, "scale:axis=X,ppm=20", line(0, [-100.0, 0.0, 50.0, 200.0]))
    assert np.allclose(d[:, 0], [-2.0, 0.0, 1.0, 4.0], atol=1e-9)
    assert np.allclose(d[:, 1:], 0, atol=1e-9)


def test_pitch_cyclic_is_a_sine_of_the_documented_period(machine):
    x = np.linspace(0, 10, 21)
    d, _, _ = tip_shift_um(machine, "pitch_cyclic:axis=X,period_mm=5,amplitude_um=6", line(0, x))
    assert np.allclose(d[:, 0], 6 * np.sin(2 * np.pi * x / 5), atol=1e-9)


def test_backlash_depends_on_approach_direction(machine):
    cmds = line(1, [10.0, 10.0])
    ctx = PoseContext(np.array([[0, 1, 0, 0, 0], [0, -1, 0, 0, 0]], float), np.zeros(2), np.full(2, 20.0))
    d, _, _ = tip_shift_um(machine, "backlash:axis=Y,amount_um=8", cmds, ctx)
    assert np.allclose(d[:, 1], [4.0, -4.0], atol=1e-9)


def test_thermal_drift_follows_temperature_or_time(machine):
    cmds = np.zeros((3, 5))
    ctx = PoseContext(np.zeros((3, 5)), np.array([0.0, 3600.0, 7200.0]), np.array([20.0, 21.0, 22.5]))
    d, _, _ = tip_shift_um(machine, "thermal_drift:axis=Z,driver=temperature,um_per_k=3", cmds, ctx)
    assert np.allclose(d[:, 2], [0.0, 3.0, 7.5], atol=1e-9)
    d, _, _ = tip_shift_um(machine, "thermal_drift:axis=Z,driver=time,um_per_hour=2", cmds, ctx)
    assert np.allclose(d[:, 2], [0.0, 2.0, 4.0], atol=1e-9)


def test_gravity_sag_grows_with_a(machine):
    a = np.array([0.0, 30.0, 60.0, 90.0])
    e = parse_effect("gravity_sag:amplitude_um=10").joint_errors(machine, machine.commands_to_internal(line(3, a)),
                                                               PoseContext.neutral(4))
    assert np.allclose(e["A"][:, 2] / UM, -10 * (1 - np.cos(np.deg2rad(a))), atol=1e-12)
    d, _, _ = tip_shift_um(machine, "gravity_sag:amplitude_um=10", line(3, a))
    assert abs(d[0]).max() < 1e-9 and np.linalg.norm(d[3]) == pytest.approx(10.0, rel=1e-6)


@pytest.mark.parametrize("family,harmonic", [("encoder_eccentricity", 1), ("encoder_wobble", 2)])
def test_encoder_harmonics_turn_the_axis_by_the_documented_angle(machine, family, harmonic):
    c = np.array([0.0, 15.0, 45.0, 100.0])
    _, moved, base = tip_shift_um(machine, f"{family}:axis=C,amplitude_arcsec=20,phase_deg=10", line(4, c))
    # The workpiece turns by an extra ε about z, so the tip, seen from it, turns by -ε about the workpiece z,
    # which is +ε about the tip's own z (it points down). R is the extra rotation in the tip frame.
    R = np.swapaxes(base[:, :3, :3], 1, 2) @ moved[:, :3, :3]
    angle = np.arctan2(R[:, 1, 0], R[:, 0, 0]) / ARCSEC
    assert np.allclose(angle, 20 * np.sin(harmonic * np.deg2rad(c) + np.deg2rad(10)), atol=1e-6)


def test_focal_drift_scales_the_focal_length_with_z(machine):
    q = machine.commands_to_internal(line(2, [-10.0, 0.0, 20.0]))
    ch = parse_effect("focal_drift:camera=camera1,ppm_per_mm=50").camera_changes("camera1", machine, q, None)
    assert np.allclose(ch["focal_scale"], [1 - 5e-4, 1.0, 1 + 1e-3])
    assert parse_effect("focal_drift:camera=camera1,ppm_per_mm=50").camera_changes("camera2", machine, q, None) == {}
    cam = camera_for_image(machine.cameras["camera1"], 1 + 1e-3)
    assert cam.focal_length_mm == pytest.approx(16.016)


def test_lens_distortion_moves_projected_centres_by_its_formula(machine):
    cam = machine.cameras["camera1"]
    plate = machine.plates["plate_a"]
    T = forward(machine, [0, 0, 0, 0, 0]).camera_view("camera1")[0]
    base = true_dot_centres(cam, plate, T)
    moved = true_dot_centres(cam, plate, T, extra_distortion=(0.0, 1e-3, 0.0, 0.0, 0.0))
    # s1 adds s1 * r^2 to distorted x (normalised), i.e. fx * s1 * r^2 pixels in u
    p = plate.dot_centres_mm() @ T[:3, :3].T + T[:3, 3]
    r2 = (p[:, 0] / p[:, 2]) ** 2 + (p[:, 1] / p[:, 2]) ** 2
    assert np.allclose(moved[:, 0] - base[:, 0], cam.fx_px * 1e-3 * r2, atol=1e-9)
    assert np.allclose(moved[:, 1], base[:, 1], atol=1e-9)


def test_tool_offset_moves_only_the_tip(machine):
    cmds = line(4, [0.0, 90.0])
    d, _, _ = tip_shift_um(machine, "tool_offset:dx_um=5,dz_um=-3", cmds)
    # tip frame x is workpiece x at C=0; z points down (-z): dz=-3 raises the tip by 3 µm
    assert np.allclose(d[0], [5.0, 0.0, 3.0], atol=1e-9)
    assert np.linalg.norm(d[1]) == pytest.approx(np.hypot(5, 3), rel=1e-9)
    views = forward(machine, cmds, ErrorModel(effects=[parse_effect("tool_offset:dx_um=5")])).camera_view("camera1")
    assert np.allclose(views, forward(machine, cmds).camera_view("camera1"), atol=1e-15)


def test_specs_round_trip_and_bad_specs_are_named():
    for spec in ("pitch_cyclic:axis=X,period_mm=5,amplitude_um=6,phase_deg=0",
                 "encoder_wobble:axis=C,amplitude_arcsec=12,phase_deg=30"):
        assert parse_effect(spec).spec() == spec
    with pytest.raises(ValueError, match="unknown effect family 'pitch'"):
        parse_effect("pitch:axis=X")
    with pytest.raises(ValueError, match="period_mm"):
        parse_effect("pitch_cyclic:axis=X,amplitude_um=6")
    with pytest.raises(ValueError, match="not a number"):
        parse_effect("pitch_cyclic:axis=X,period_mm=five,amplitude_um=6")
    with pytest.raises(ValueError, match="must be one of"):
        parse_effect("pitch_cyclic:axis=A,period_mm=5,amplitude_um=6")
    with pytest.raises(ValueError, match="unknown parameter"):
        parse_effect("scale:axis=X,ppm=3,wobble=2")


def test_catalogue_lists_every_required_family():
    required = {"scale", "pitch_cyclic", "backlash", "thermal_drift", "gravity_sag", "encoder_eccentricity",
                "encoder_wobble", "focal_drift", "lens_distortion", "tool_offset"}
    assert required <= set(EFFECTS)
    text = catalogue_text()
    for name in required:
        assert f"{name}:" in text
