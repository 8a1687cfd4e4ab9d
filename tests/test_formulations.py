"""Table 5's formulations: local PoE (eq. 12), modified DH with Hayati's β, global PoE with fixed screws.

Each test checks a property that can be derived by hand: without errors all three agree. A PIGE
that the DH projection drops shows up exactly at its own size. A PIGE that the projection keeps
shows up not at all. The global PoE is exact when only the last joint of each chain has errors,
and it is off by a closed-form amount when the error of an earlier joint should have moved a
later screw.
"""

import copy

import numpy as np
import pytest

from tasks.error_model import ARCSEC, UM, ErrorModel
from tasks.formulations import (
    DH,
    GLOBAL_POE,
    LOCAL_POE,
    TABLE5_COLUMNS,
    compare_formulations,
    dh_parameter_table,
    dh_pige_loss,
    dh_tool_in_workpiece,
    format_table5,
    global_poe_tool_in_workpiece,
    local_poe_tool_in_workpiece,
)
from tasks.kinematics import forward, position_orientation_error
from tasks.machine import machine_from_dict


def random_commands(n, seed, machine=None):
    """(n, 5) commands over the prototype's strokes (X, Y ±250 mm, Z ±150 mm, A ±90°, C ±180°)."""
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(-250, 250, (n, 2)), rng.uniform(-150, 150, n),
                            rng.uniform(-90, 90, n), rng.uniform(-180, 180, n)])


def variant(machine, **axes):
    """The prototype with some axes replaced: variant(m, C={"direction": [...], ...})."""
    d = copy.deepcopy(machine.source)
    for name, fields in axes.items():
        d["axes"][name].update(fields)
    return machine_from_dict(d)


def errors_of(g, truth):
    dt, dR = position_orientation_error(g, truth)
    return dt, dR


# --- no errors: the three formulations are the same kinematics ------------------------------------


@pytest.mark.parametrize("layout", ["prototype", "offset_axes", "parallel_rotaries"])
def test_without_errors_all_three_agree_with_forward(machine, layout):
    if layout == "offset_axes":  # non-intersecting axis lines: non-zero a and d in the DH table
        machine = variant(machine, X={"home_position_mm": [10, 20, 60]}, Z={"home_position_mm": [-5, 0, 80]},
                          C={"home_position_mm": [0, 30, 0]})
    elif layout == "parallel_rotaries":  # A ∥ C: Hayati's β on the C link
        machine = variant(machine, A={"direction": [0, 0, 1]}, C={"home_position_mm": [50, 0, 0]})
    cmds = random_commands(40, 1)
    truth = forward(machine, cmds).tool_in_workpiece()
    for fn in (local_poe_tool_in_workpiece, dh_tool_in_workpiece, global_poe_tool_in_workpiece):
        for errs in (None, ErrorModel.none()):
            g = fn(machine, cmds, errs)
            assert g.shape == (40, 4, 4)
            assert np.abs(g[:, :3, 3] - truth[:, :3, 3]).max() < 1e-9  # mm
            assert np.abs(g[:, :3, :3] - truth[:, :3, :3]).max() < 1e-12


def test_dh_parameters_of_the_prototype(machine):
    t = dh_parameter_table(machine).set_index("joint")
    # tool chain Y -> X -> Z and workpiece chain A -> C: all axes intersect, so every a and d is 0
    assert (t[["a_mm", "d_mm"]].to_numpy() == 0).all()
    assert t.loc["X", "alpha_deg"] == pytest.approx(90) and t.loc["X", "theta_deg"] == pytest.approx(-90)
    assert t.loc["Z", "alpha_deg"] == pytest.approx(90) and t.loc["C", "alpha_deg"] == pytest.approx(90)
    # Craig's frame 0 = frame 1 at home makes link 1 of each chain a parallel pair: Hayati's β there only
    assert t["hayati_beta"].to_dict() == {"Y": True, "X": False, "Z": False, "A": True, "C": False}
    assert t.loc["C", "lost_translation_along"] == "x" and t.loc["C", "lost_rotation_about"] == "x"


def test_dh_tables_of_other_layouts(machine):
    offset = variant(machine, C={"home_position_mm": [0, 30, 0]})
    assert dh_parameter_table(offset).set_index("joint").loc["C", "a_mm"] == pytest.approx(30)
    par = dh_parameter_table(variant(machine, A={"direction": [0, 0, 1]}, C={"home_position_mm": [50, 0, 0]}))
    row = par.set_index("joint").loc["C"]
    assert bool(row["hayati_beta"]) and row["a_mm"] == pytest.approx(50)


# --- local PoE is the reference -----------------------------------------------------------------


def test_local_poe_is_forward_and_has_zero_error(machine, errors):
    cmds = random_commands(12, 2)
    truth = forward(machine, cmds, errors).tool_in_workpiece()
    assert np.array_equal(local_poe_tool_in_workpiece(machine, cmds, errors), truth)


# --- DH: what the per-joint projection keeps and what it loses ----------------------------------


def test_dh_loses_exactly_the_piges_it_cannot_represent(machine):
    loss = dh_pige_loss(machine).set_index("pige")["lost_fraction"]
    assert set(loss[loss > 0.5].index) == {"delta_AZ", "delta_CX", "beta_CY", "alpha_YZ"}
    assert np.allclose(loss[loss < 0.5], 0.0, atol=1e-12)


@pytest.mark.parametrize("name", ["delta_AZ", "delta_CX"])
def test_a_dropped_translation_pige_appears_at_its_full_size(machine, name):
    # the DH link cannot move along this direction: DH = ideal, the truth is shifted by δ everywhere
    delta = 25 * UM
    cmds = random_commands(30, 3)
    em = ErrorModel(pige={name: delta})
    dt, dR = errors_of(dh_tool_in_workpiece(machine, cmds, em), forward(machine, cmds, em).tool_in_workpiece())
    assert np.allclose(dt, delta, rtol=0, atol=1e-12)
    assert dR.max() < 1e-12


@pytest.mark.parametrize("name", ["delta_AY", "alpha_AZ", "beta_AY", "delta_CY", "alpha_CX", "gamma_YX", "beta_XZ"])
def test_a_representable_pige_is_carried_exactly(machine, name):
    value = 40 * (ARCSEC if name[0] in "abg" else UM)
    cmds = random_commands(30, 4)
    em = ErrorModel(pige={name: value})
    truth = forward(machine, cmds, em).tool_in_workpiece()
    dt, dR = errors_of(dh_tool_in_workpiece(machine, cmds, em), truth)
    assert dt.max() < 1e-9 and dR.max() < 1e-6 * ARCSEC
    # and the error is really there: the ideal model misses it
    assert errors_of(forward(machine, cmds).tool_in_workpiece(), truth)[0].mean() > 1 * UM


def test_dh_with_only_representable_components_is_second_order(machine, errors):
    # remove the components the table says each link loses (local frame = base orientation at home)
    lost = {"Y": [0], "X": [1, 4], "Z": [0, 3], "A": [2], "C": [0, 3]}  # indices into (δx δy δz εx εy εz)
    pdge = {}
    for axis, profile in errors.pdge.items():
        p = copy.deepcopy(profile)
        for k in lost[axis]:
            p.offset[k], p.chebyshev[k], p.sine_amplitude[k] = 0.0, 0.0, 0.0
        pdge[axis] = p
    kept = {n: v for n, v in errors.pige.items() if n not in ("delta_AZ", "delta_CX", "beta_CY", "alpha_YZ")}
    em = ErrorModel(pige=kept, pdge=pdge)
    cmds = random_commands(40, 10) * [0.1, 0.1, 0.1, 0.3, 1.0]
    truth = forward(machine, cmds, em).tool_in_workpiece()
    assert errors_of(forward(machine, cmds).tool_in_workpiece(), truth)[0].mean() > 20 * UM
    dt, dR = errors_of(dh_tool_in_workpiece(machine, cmds, em), truth)
    assert dt.max() < 0.1 * UM and dR.max() < 0.1 * ARCSEC  # ε² × lever arm


def test_hayati_beta_carries_a_tilt_between_parallel_axes(machine):
    par = variant(machine, A={"direction": [0, 0, 1]}, C={"home_position_mm": [50, 0, 0]})
    cmds = random_commands(20, 5)
    em = ErrorModel(pige={"alpha_CX": 60 * ARCSEC})  # C tilted about y: a rotation about y_{i-1}
    dt, dR = errors_of(dh_tool_in_workpiece(par, cmds, em), forward(par, cmds, em).tool_in_workpiece())
    assert dt.max() < 1e-9 and dR.max() < 1e-6 * ARCSEC


# --- global PoE: exact without coupling, off by a closed-form amount with it ---------------------


def test_global_poe_is_exact_when_only_the_last_joints_have_errors(machine, errors):
    last = ("delta_CX", "delta_CY", "beta_CY", "alpha_CX", "alpha_YZ", "beta_XZ")  # C and Z
    em = ErrorModel(pige={n: errors.pige[n] for n in last}, pdge={a: errors.pdge[a] for a in ("C", "Z")})
    cmds = random_commands(40, 6)
    truth = forward(machine, cmds, em).tool_in_workpiece()
    assert errors_of(forward(machine, cmds).tool_in_workpiece(), truth)[0].mean() > 10 * UM
    dt, dR = errors_of(global_poe_tool_in_workpiece(machine, cmds, em), truth)
    assert dt.max() < 1e-9 and dR.max() < 1e-9


def test_global_poe_misses_the_shift_of_c_by_an_a_axis_offset(machine):
    # δ_AY shifts the C axis; the fixed C screw does not follow: tip off by |(R_C − I) δ| = 2|sin(C/2)| δ
    delta = 27 * UM
    cmds = random_commands(40, 7)
    em = ErrorModel(pige={"delta_AY": delta})
    dt, dR = errors_of(global_poe_tool_in_workpiece(machine, cmds, em), forward(machine, cmds, em).tool_in_workpiece())
    expected = 2 * np.abs(np.sin(np.radians(cmds[:, 4]) / 2)) * delta
    assert np.allclose(dt, expected, rtol=0, atol=1e-12)
    assert dR.max() < 1e-12 and dt.mean() > 10 * UM


def test_global_poe_misses_the_tilt_of_c_by_an_a_axis_tilt(machine):
    # α_AZ tilts the C axis about y; the fixed C screw does not: orientation off by 2|sin(C/2)| α (first order)
    alpha = 45 * ARCSEC
    cmds = random_commands(40, 8)
    em = ErrorModel(pige={"alpha_AZ": alpha})
    _, dR = errors_of(global_poe_tool_in_workpiece(machine, cmds, em), forward(machine, cmds, em).tool_in_workpiece())
    expected = 2 * np.abs(np.sin(np.radians(cmds[:, 4]) / 2)) * alpha
    assert np.allclose(dR, expected, rtol=1e-3, atol=1e-3 * ARCSEC)
    assert dR.mean() > 20 * ARCSEC


# --- Table 5 -------------------------------------------------------------------------------------


def test_table5_columns_and_honest_numbers(machine, errors):
    cmds = random_commands(8, 9) * [0.1, 0.1, 0.1, 0.3, 1.0]
    df = compare_formulations(machine, errors, cmds, repeats=1)
    assert list(df.columns) == list(TABLE5_COLUMNS)
    assert list(df.formulation) == [LOCAL_POE, DH, GLOBAL_POE]
    t = df.set_index("formulation")
    assert t.loc[LOCAL_POE, "position_error_norm_um"] == 0 and t.loc[LOCAL_POE, "orientation_error_norm_arcsec"] == 0
    assert t.loc[DH, "position_error_norm_um"] > 1 and t.loc[GLOBAL_POE, "position_error_norm_um"] > 1
    assert (df[["mean_single_run_ms", "total_300_ms"]].to_numpy() > 0).all()
    md = format_table5(df)
    assert md.count("\n") == 4 and "Denavit–Hartenberg" in md
