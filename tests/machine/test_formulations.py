"""Table 5's formulations: local PoE (eq. 12), modified DH with Hayati's β, global PoE with fixed screws.

Each test checks a property that can be derived by hand. Without errors all three agree. A PIGE
moves one axis line and nothing at home, so DH (its table derived from the moved lines) and the
global PoE (the moved screw) carry every PIGE exactly, each through a parameter that can be named.
A PDGE is a six-component error motion before its joint's motion: a component that DH's link
cannot carry shows up exactly at its own size, the others to second order. The global PoE is
exact when only the last joint of each chain has PDGEs, and it is off by a closed-form amount when
an earlier joint's error motion should have moved a later screw.
"""

import copy

import numpy as np
import pytest

from tasks.core.units import ARCSEC, UM
from tasks.machine.description import machine_from_dict
from tasks.machine.error_model import PIGE_SCREWS, ErrorModel
from tasks.machine.formulations import (
    DH,
    GLOBAL_POE,
    LOCAL_POE,
    TABLE5_COLUMNS,
    axis_lines,
    compare_formulations,
    dh_lost_error,
    dh_parameter_table,
    dh_pige_parameters,
    dh_tool_in_workpiece,
    global_poe_tool_in_workpiece,
    local_poe_tool_in_workpiece,
)
from tasks.machine.kinematics import forward, position_orientation_error
from tasks.report.tables import format_table5


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


# --- PIGEs: axis-line errors, which both alternatives carry exactly ---------------------------------


def pige_value(name, size=40.0):
    """A PIGE of ``size`` µm or arcsec, in mm / rad."""
    return size * (ARCSEC if name[0] in "abg" else UM)


def test_a_pige_moves_only_its_own_axis_line_by_its_own_size(machine):
    # δ_AY: A's line through (0, δ, 0), still along x; α_AZ: A turned about y, direction (cos α, 0, −sin α)
    ref = axis_lines(machine, machine.workpiece_chain)
    (p, z), c = axis_lines(machine, machine.workpiece_chain, {"delta_AY": 0.03})
    assert np.allclose(p, [0, 0.03, 0], atol=1e-15) and np.allclose(z, [1, 0, 0], atol=1e-15)
    assert all(np.array_equal(u, v) for u, v in zip(c, ref[1], strict=True))
    (_, z), _ = axis_lines(machine, machine.workpiece_chain, {"alpha_AZ": 1e-4})
    assert np.allclose(z, [np.cos(1e-4), 0, -np.sin(1e-4)], atol=1e-15)


@pytest.mark.parametrize("name", list(PIGE_SCREWS))
def test_dh_and_global_poe_carry_every_pige_exactly(machine, name):
    # a PIGE moves one axis line and nothing at home: the DH table of the moved lines and the
    # moved global screw are the true chain, to rounding
    cmds = random_commands(30, 4)
    em = ErrorModel(pige={name: pige_value(name)})
    truth = forward(machine, cmds, em).tool_in_workpiece()
    for fn in (dh_tool_in_workpiece, global_poe_tool_in_workpiece):
        dt, dR = errors_of(fn(machine, cmds, em), truth)
        assert dt.max() < 1e-9 and dR.max() < 1e-12, fn.__name__
    # and the error is really there: the ideal model misses it (40 µm or 40″ on ~100 mm levers)
    assert errors_of(forward(machine, cmds).tool_in_workpiece(), truth)[0].mean() > 2 * UM


def test_all_prototype_piges_together_are_exact_in_dh_and_global_poe(machine, errors):
    cmds = random_commands(40, 11)
    em = ErrorModel(pige=errors.pige)
    truth = forward(machine, cmds, em).tool_in_workpiece()
    assert errors_of(forward(machine, cmds).tool_in_workpiece(), truth)[0].mean() > 5 * UM
    for fn in (dh_tool_in_workpiece, global_poe_tool_in_workpiece):
        dt, dR = errors_of(fn(machine, cmds, em), truth)
        assert dt.max() < 1e-9 and dR.max() < 1e-12, fn.__name__


def test_each_pige_is_one_dh_parameter_or_the_base_and_tool_placement(machine):
    # derived by hand from the prototype's lines (A ∥ x and C ∥ z through the origin; X, Y, Z through
    # (0, 0, 40)): a squareness is the twist α between the two axes of its link, or (α_YZ: Z turned
    # about X's line) X's θ offset; a shift of A or C across the other axis is their distance a; a
    # shift along the other axis, or a tilt about it, only moves frame 0 (Craig: frame 0 = frame 1,
    # on A's line) and the last DH frame's tool transform
    t = dh_pige_parameters(machine)
    links = t[~t.link.isin(["base", "tool"])]
    carried = {r.pige: (r.link, r.parameter, round(r.change, 6)) for r in links.itertuples()}
    assert len(links) == len(carried)  # at most one DH link parameter per PIGE
    assert carried == {
        "delta_AY": ("C", "a", 1.0), "alpha_AZ": ("C", "alpha", 1.0), "delta_CY": ("C", "a", -1.0),
        "alpha_CX": ("C", "alpha", -1.0), "gamma_YX": ("X", "alpha", 1.0), "alpha_YZ": ("X", "theta", 1.0),
        "beta_XZ": ("Z", "alpha", -1.0),
    }
    placement = t[t.link.isin(["base", "tool"])]
    assert set(placement.pige) | set(carried) == set(PIGE_SCREWS)  # every PIGE lands somewhere
    assert np.allclose(placement.change, 1.0, atol=1e-6)  # a unit line error moves a frame by one unit


@pytest.mark.parametrize("name", ["delta_CX", "delta_CY", "beta_CY", "alpha_CX"])
def test_hayati_beta_keeps_a_pige_of_a_parallel_axis_small_and_exact(machine, name):
    # A ∥ C, 50 mm apart: a tilt of C makes the axes skew by 60″; plain DH would put their common
    # normal 50 mm / 60″ ≈ 170 m away. With Hayati's β every parameter moves by the PIGE's order
    par = variant(machine, A={"direction": [0, 0, 1]}, C={"home_position_mm": [50, 0, 0]})
    value = pige_value(name, 60.0)
    cmds = random_commands(20, 5)
    em = ErrorModel(pige={name: value})
    dt, dR = errors_of(dh_tool_in_workpiece(par, cmds, em), forward(par, cmds, em).tool_in_workpiece())
    assert dt.max() < 1e-9 and dR.max() < 1e-12
    ref = dh_parameter_table(par).set_index("joint")
    moved = dh_parameter_table(par, pige=em.pige).set_index("joint")
    # a and d move by at most the 60 µm shift (δ_CX: a = 50.06 mm), not by metres
    assert np.abs(moved[["a_mm", "d_mm"]].to_numpy() - ref[["a_mm", "d_mm"]].to_numpy()).max() <= 60 * UM + 1e-9
    if name == "alpha_CX":  # C tilted about y, towards A: exactly Hayati's β of the C link
        assert abs(moved.loc["C", "beta_deg"]) == pytest.approx(60 / 3600, rel=1e-9)
        assert moved.loc["C", "alpha_deg"] == pytest.approx(ref.loc["C", "alpha_deg"], abs=1e-12)


# --- PDGEs: DH's per-joint projection keeps 4 (5) of 6 components ---------------------------------


@pytest.mark.parametrize(("axis", "k"), [("A", 2), ("C", 0)])
def test_a_dropped_pdge_translation_appears_at_its_full_size(machine, axis, k):
    # a constant error motion of A along z (C along x, i.e. along A's axis) before the joint's motion:
    # the table says its link cannot translate that way, so DH = ideal and the truth is shifted by δ everywhere
    delta = 25 * UM
    offset = np.zeros(6)
    offset[k] = delta
    em = ErrorModel(joint_offsets={axis: offset})
    cmds = random_commands(30, 3)
    dt, dR = errors_of(dh_tool_in_workpiece(machine, cmds, em), forward(machine, cmds, em).tool_in_workpiece())
    assert np.allclose(dt, delta, rtol=0, atol=1e-12)
    assert dR.max() < 1e-12


def test_dh_with_only_representable_pdge_components_is_second_order(machine, errors):
    # remove the PDGE components the table says each link loses (local frame = base orientation at
    # home); keep every PIGE (carried exactly by the moved table)
    lost = {"Y": [0], "X": [1, 4], "Z": [0, 3], "A": [2], "C": [0, 3]}  # indices into (δx δy δz εx εy εz)
    pdge = {}
    for axis, profile in errors.pdge.items():
        p = copy.deepcopy(profile)
        for k in lost[axis]:
            p.offset[k], p.chebyshev[k], p.sine_amplitude[k] = 0.0, 0.0, 0.0
        pdge[axis] = p
    em = ErrorModel(pige=errors.pige, pdge=pdge)
    cmds = random_commands(40, 10) * [0.1, 0.1, 0.1, 0.3, 1.0]
    truth = forward(machine, cmds, em).tool_in_workpiece()
    assert errors_of(forward(machine, cmds).tool_in_workpiece(), truth)[0].mean() > 20 * UM
    dt, dR = errors_of(dh_tool_in_workpiece(machine, cmds, em), truth)
    assert dt.max() < 0.1 * UM and dR.max() < 0.1 * ARCSEC  # ε² × lever arm


def test_hayati_links_lose_no_pdge_rotation(machine, errors):
    # α, θ and β span all three rotations of links Y and A (link 1, Hayati); X, Z and C lose one
    lost = dh_lost_error(machine, errors, random_commands(20, 12)).set_index("joint")
    assert lost.loc[["Y", "A"], "lost_rotation_arcsec"].max() < 1e-6
    assert (lost.loc[["X", "Z", "C"], "lost_rotation_arcsec"] > 0.1).all()
    assert (lost.lost_translation_um <= lost.of_translation_um + 1e-9).all()


# --- global PoE: exact without coupling, off by a closed-form amount with it ---------------------


def test_global_poe_is_exact_when_only_the_last_joints_have_pdges(machine, errors):
    em = ErrorModel(pige=errors.pige, pdge={a: errors.pdge[a] for a in ("C", "Z")})
    cmds = random_commands(40, 6)
    truth = forward(machine, cmds, em).tool_in_workpiece()
    assert errors_of(forward(machine, cmds).tool_in_workpiece(), truth)[0].mean() > 10 * UM
    dt, dR = errors_of(global_poe_tool_in_workpiece(machine, cmds, em), truth)
    assert dt.max() < 1e-9 and dR.max() < 1e-12


def test_global_poe_misses_the_shift_of_c_by_a_constant_a_error_motion(machine):
    # A's error motion δy before its motion shifts the C axis; the fixed C screw does not follow:
    # tip off by |(R_C − I) δ| = 2|sin(C/2)| δ. The same δ as the PIGE δ_AY (A's line moved, nothing at
    # home) is carried exactly (test above): the loss is the PDGE's coupling, not the shift
    delta = 27 * UM
    cmds = random_commands(40, 7)
    em = ErrorModel(joint_offsets={"A": [0, delta, 0, 0, 0, 0]})
    dt, dR = errors_of(global_poe_tool_in_workpiece(machine, cmds, em), forward(machine, cmds, em).tool_in_workpiece())
    expected = 2 * np.abs(np.sin(np.radians(cmds[:, 4]) / 2)) * delta
    assert np.allclose(dt, expected, rtol=0, atol=1e-12)
    assert dR.max() < 1e-12 and dt.mean() > 10 * UM


def test_global_poe_misses_the_tilt_of_c_by_a_constant_a_error_motion(machine):
    # A's error motion εy tilts the C axis about y; the fixed C screw does not: orientation off by
    # 2|sin(C/2)| ε (first order)
    eps = 45 * ARCSEC
    cmds = random_commands(40, 8)
    em = ErrorModel(joint_offsets={"A": [0, 0, 0, 0, eps, 0]})
    _, dR = errors_of(global_poe_tool_in_workpiece(machine, cmds, em), forward(machine, cmds, em).tool_in_workpiece())
    expected = 2 * np.abs(np.sin(np.radians(cmds[:, 4]) / 2)) * eps
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
    # with the PIGEs alone both alternatives are exact: what they lose in Table 5 is PDGE
    pige_only = compare_formulations(machine, ErrorModel(pige=errors.pige), cmds, repeats=1)
    assert (pige_only[["position_error_norm_um", "orientation_error_norm_arcsec"]].to_numpy() < 1e-6).all()
    assert (df[["mean_single_run_ms", "total_300_ms"]].to_numpy() > 0).all()
    md = format_table5(df)
    assert len([line for line in md.splitlines() if line.startswith("|")]) == 5 and "Denavit–Hartenberg" in md
