"""The PIGEs' signs, pinned through the forward kinematics of the prototype (tasks/machine/error_model.py's
table, docs/virtual-machine.md): each case moves one point by a figure worked out by hand."""

import numpy as np
import pytest

from tasks.core.units import ARCSEC, UM
from tasks.machine.description import load_machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward


@pytest.fixture(scope="module")
def machine():
    return load_machine("prototype")


def moved_um(machine, pige: dict[str, float], commands, frame: str) -> np.ndarray:
    """Displacement (µm, base frame) of the origin of ``frame`` (a link or attachment) that the
    PIGEs (mm, rad) cause at ``commands`` (X Y Z mm, A C deg)."""
    actual = forward(machine, [commands], ErrorModel(pige=pige)).pose(frame)[0, :3, 3]
    ideal = forward(machine, [commands]).pose(frame)[0, :3, 3]
    return (actual - ideal) / UM


@pytest.mark.parametrize("c_deg, expected_um", [(0, (0, 0)), (90, (10, -10)), (180, (20, 0)), (-90, (10, 10))])
def test_delta_cx_moves_the_table_centre_on_a_circle_of_its_size(machine, c_deg, expected_um):
    """+10 µm δCX shifts C's line to x = +10 µm: the table centre (C's link origin, on the nominal
    axis) turns about it on a 10 µm circle, +20 µm in X at C = 180°."""
    d = moved_um(machine, {"delta_CX": 10 * UM}, [0, 0, 0, 0, c_deg], "C")
    np.testing.assert_allclose(d, [*expected_um, 0], atol=1e-9)


@pytest.mark.parametrize("y_mm", [-200.0, 100.0])
def test_gamma_yx_gives_an_x_error_of_minus_gamma_times_y(machine, y_mm):
    """+10″ γYX turns Y's direction of travel about z: its +y end goes toward −x, so the tip's X
    error is −γ·Y (and its Y error second order)."""
    gamma = 10 * ARCSEC
    d = moved_um(machine, {"gamma_YX": gamma}, [0, y_mm, 0, 0, 0], "tip")
    np.testing.assert_allclose(d, [-gamma * y_mm / UM, y_mm * (np.cos(gamma) - 1) / UM, 0], atol=1e-9)


def test_alpha_az_tips_the_a_axis_x_end_toward_minus_z(machine):
    """+10″ αAZ turns A's axis about y: a point on the nominal axis 150 mm out (plate b's centre)
    leaves it and is carried round by A: (0, −150α sin A, −150α(1 − cos A)) = (0, −3.636, −0.974) µm
    at A = 30°."""
    d = moved_um(machine, {"alpha_AZ": 10 * ARCSEC}, [0, 0, 0, 30, 0], "plate_b")
    np.testing.assert_allclose(d, [0, -3.636, -0.974], atol=5e-4)
    assert np.allclose(moved_um(machine, {"alpha_AZ": 10 * ARCSEC}, [0, 0, 0, 0, 0], "plate_b"), 0, atol=1e-9)


R10 = 10 * ARCSEC / UM  # µm per mm of lever arm for 10″


@pytest.mark.parametrize("name, frame, commands, expected_um", [
    # C's +z end toward −y: plate a's centre, 40 mm up C's nominal axis, at C = 180° is 2·40·β off in −y
    ("beta_CY", "plate_a", [0, 0, 0, 0, 180], (0, -80 * R10, 0)),
    ("alpha_CX", "plate_a", [0, 0, 0, 0, 180], (80 * R10, 0, 0)),    # C's +z end toward +x
    ("alpha_YZ", "tip", [0, 0, 50, 0, 0], (0, -50 * R10, 0)),        # Z's +z end toward −y
    ("beta_XZ", "tip", [0, 0, 50, 0, 0], (50 * R10, 0, 0)),          # Z's +z end toward +x
    # A's +x end toward +y: plate b (150 mm along A) at A = 90° goes 150β toward +y and −z
    ("beta_AY", "plate_b", [0, 0, 0, 90, 0], (0, 150 * R10, -150 * R10)),
])
def test_the_tilt_of_each_axis_points_where_the_table_says(machine, name, frame, commands, expected_um):
    d = moved_um(machine, {name: 10 * ARCSEC}, commands, frame)
    np.testing.assert_allclose(d, expected_um, atol=1e-3)
