"""The dispensing test's physics and tip fit at pose level, against the simulator's truth."""

from dataclasses import replace

import numpy as np
import pytest

from tasks.analysis.compensation import compensate, desired_tip_poses
from tasks.dispensing.tip import constant_tool_frame_error, fit_tip_offset, landing_points, tool_offset_of
from tasks.dispensing.workpiece import Workpiece, ring_layout
from tasks.machine.description import load_machine
from tasks.machine.effects import ToolOffset
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward
from tasks.simulation.prototype_errors import load_prototype_errors

TRUE_OFFSET_UM = np.array([1.9, -2.1, 10.8])  # the constant of seed 43 in issue 31


@pytest.fixture(scope="module")
def setup():
    machine = load_machine("prototype")
    identified = load_prototype_errors()  # what the plates gave: all but the tip
    truth = replace(identified, effects=[ToolOffset(dx_um=1.9, dy_um=-2.1, dz_um=10.8)])
    wp = Workpiece()
    layout = ring_layout(machine, wp, np.array([[-20, 20], [-20, 20], [0, 0], [-30, 30], [-180, 180]]), 3)
    return machine, identified, truth, wp, layout


def test_nominal_tip_sits_above_each_ring_and_rings_do_not_touch(setup):
    machine, _, _, wp, layout = setup
    tip = forward(machine, layout.commands).tool_in_workpiece()[:, :3, 3]
    assert np.abs(tip[:, :2] - layout.centres).max() < 1e-9
    np.testing.assert_allclose(tip[:, 2], layout.surface_z_mm + wp.standoff_mm, atol=1e-9)
    gaps = np.linalg.norm(layout.centres[:, None] - layout.centres[None], axis=2) + 1e9 * np.eye(len(tip))
    assert gaps.min() >= wp.min_spacing_mm
    assert np.ptp(layout.commands[:, 3]) > 50 and np.ptp(layout.commands[:, 4]) > 300  # A and C spread


def test_tool_axis_offset_moves_dots_only_when_tilted(setup):
    machine, _, _, _, layout = setup
    nominal = layout.commands
    flat = nominal.copy()
    flat[:, 3] = 0.0
    along_axis = ErrorModel(effects=[ToolOffset(dz_um=10.0)])
    shift_flat = landing_points(machine, along_axis, flat) - landing_points(machine, None, flat)
    shift_tilted = landing_points(machine, along_axis, nominal) - landing_points(machine, None, nominal)
    assert np.abs(shift_flat).max() < 1e-9
    sin_a = np.abs(np.sin(np.deg2rad(nominal[:, 3])))
    np.testing.assert_allclose(np.linalg.norm(shift_tilted, axis=1), 10e-3 * sin_a, atol=1e-9)


def test_tip_fit_recovers_the_offset_and_closes_the_compensation(setup):
    machine, identified, truth, _, layout = setup
    nominal = layout.commands
    compensated = compensate(machine, identified, nominal).commands
    rings = layout.centres
    rng = np.random.default_rng(0)
    noise_um = 1.0
    measured = landing_points(machine, truth, compensated) - rings + rng.normal(0, noise_um * 1e-3, rings.shape)
    fit = fit_tip_offset(machine, identified, compensated, rings, measured)
    assert fit.residual_rms_um == pytest.approx(noise_um, rel=0.2)
    assert np.all(np.abs(fit.offset_um - TRUE_OFFSET_UM) < 3.5 * fit.uncertainty_um)
    assert fit.uncertainty_um[2] > fit.uncertainty_um[0]  # the tool axis shows only through sin A
    np.testing.assert_allclose(tool_offset_of(fit.model), fit.offset_um)
    desired = desired_tip_poses(machine, nominal)
    before = constant_tool_frame_error(machine, truth, desired, compensated)
    np.testing.assert_allclose(before, TRUE_OFFSET_UM, atol=0.05)
    after = constant_tool_frame_error(machine, truth, desired, compensate(machine, fit.model, nominal).commands)
    assert np.linalg.norm(after) < 0.1 * np.linalg.norm(before)


def test_tip_fit_needs_a_tilt(setup):
    machine, identified, _, _, layout = setup
    flat = layout.commands.copy()
    flat[:, 3] = 0.0
    with pytest.raises(ValueError, match="more than one A"):
        fit_tip_offset(machine, identified, flat, layout.centres, np.zeros((len(flat), 2)))


def test_rings_sit_on_pads_that_spread_the_dispensing_z_over_the_poses_z_range(setup):
    machine = setup[0]
    wp = Workpiece(rings=60)
    z_range = (-4.0, 1.0)
    layout = ring_layout(machine, wp, np.array([[-5, 5], [-20, 20], z_range, [-24, 24], [-180, 180]]), 5)
    np.testing.assert_allclose(layout.surface_z_mm, np.round(layout.surface_z_mm / wp.step_mm) * wp.step_mm)
    tip = forward(machine, layout.commands).tool_in_workpiece()[:, :3, 3]
    np.testing.assert_allclose(tip[:, 2], layout.surface_z_mm + wp.standoff_mm, atol=1e-9)
    z = layout.commands[:, 2]  # the pad's rounding moves each Z command by at most half a step
    assert z.min() >= z_range[0] - wp.step_mm / 2 and z.max() <= z_range[1] + wp.step_mm / 2
    assert np.ptp(z) > 0.8 * (z_range[1] - z_range[0]) and len(np.unique(layout.surface_z_mm)) > 5
