"""Local PoE forward kinematics against an independent construction; IK round trips."""

import numpy as np
from scipy.spatial.transform import Rotation

from tasks.core.units import ARCSEC, UM
from tasks.machine.context import PoseContext, approach_directions
from tasks.machine.description import AXIS_ORDER
from tasks.machine.effects import parse_effect
from tasks.machine.error_model import PIGE_SCREWS
from tasks.machine.inverse_kinematics import inverse
from tasks.machine.kinematics import forward
from tasks.simulation.prototype_errors import load_prototype_errors


def homogeneous(R=None, p=(0.0, 0.0, 0.0)):
    T = np.eye(4)
    T[:3, :3] = np.eye(3) if R is None else R
    T[:3, 3] = p
    return T


def independent_chain(machine, command, errors):
    """Tip-in-workpiece pose built one homogeneous matrix at a time with scipy rotations."""
    q = {a: command[i] for i, a in enumerate(AXIS_ORDER)}

    def joint(axis, prev_home):
        ax = machine.axes[axis]
        home = np.asarray(ax.home_position_mm)
        T = homogeneous(p=home - prev_home)
        pos = np.deg2rad(q[axis]) if ax.is_rotary else q[axis]
        if axis in errors.pdge:
            e = errors.pdge[axis](np.array([pos]))[0]
            R = Rotation.from_euler("XYZ", e[3:]).as_matrix()  # intrinsic x, then y, then z
            T = T @ homogeneous(R, e[:3])
        E = np.eye(4)  # the PIGEs move the axis line (eqs. 9–11 in their order): motion E · J · E⁻¹
        for name, (j, k) in PIGE_SCREWS.items():
            if j != axis or name not in errors.pige:
                continue
            v = errors.pige[name]
            if k < 3:
                E = E @ homogeneous(p=np.eye(3)[k] * v)
            else:
                E = E @ homogeneous(Rotation.from_rotvec(np.eye(3)[k - 3] * v).as_matrix())
        d = np.asarray(ax.direction, float)
        motion = homogeneous(Rotation.from_rotvec(d * pos).as_matrix()) if ax.is_rotary else homogeneous(p=d * pos)
        return T @ E @ motion @ np.linalg.inv(E), home

    def chain_pose(chain, link):
        T, prev = np.eye(4), np.zeros(3)
        for axis in chain:
            J, prev = joint(axis, prev)
            T = T @ J
            if axis == link:
                break
        return T

    def attachment(name):
        att = machine.attachments[name]
        return chain_pose(machine.chain_of(att.link), att.link) @ att.pose_in_link

    return np.linalg.inv(attachment(machine.workpiece)) @ attachment(machine.tip)


def test_poe_chain_equals_independent_product(machine, errors):
    rng = np.random.default_rng(1)
    cmds = np.column_stack([rng.uniform(-250, 250, (20, 2)), rng.uniform(-150, 150, 20),
                            rng.uniform(-90, 90, 20), rng.uniform(-180, 180, 20)])
    poe = forward(machine, cmds, errors).tool_in_workpiece()
    for i, c in enumerate(cmds):
        assert np.allclose(poe[i], independent_chain(machine, c, errors), rtol=0, atol=1e-12)


def test_ideal_machine_tip_is_where_the_drawing_puts_it(machine):
    # A = C = 0, X = 10: tip moves 10 mm along the workpiece x (plate a is aligned with base)
    g0 = forward(machine, [0, 0, 0, 0, 0]).tool_in_workpiece()[0]
    g1 = forward(machine, [10, 0, 0, 0, 0]).tool_in_workpiece()[0]
    assert np.allclose(g1[:3, 3] - g0[:3, 3], [10, 0, 0], atol=1e-12)
    # C = 90° turns the workpiece under the tool: the tip seen from the workpiece turns by -90°
    g2 = forward(machine, [0, 0, 0, 0, 90]).tool_in_workpiece()[0]
    assert np.allclose(g2[:3, 3], [0, 60, 20], atol=1e-12)


def test_ik_of_fk_round_trips_under_a_nonzero_error_model(machine, errors):
    errors = load_prototype_errors()
    errors.effects = [parse_effect("pitch_cyclic:axis=X,period_mm=5,amplitude_um=6")]
    rng = np.random.default_rng(2)
    cmds = np.column_stack([rng.uniform(-30, 30, (40, 3)), rng.uniform(-60, 60, 40), rng.uniform(-170, 170, 40)])
    g = forward(machine, cmds, errors).tool_in_workpiece()
    solved = inverse(machine, g[:, :3, 3], g[:, :3, 2], errors, prefer=cmds)
    assert np.abs(solved - cmds).max() < 1e-7
    g2 = forward(machine, solved, errors).tool_in_workpiece()
    assert np.abs(g2[:, :3, 3] - g[:, :3, 3]).max() < 1e-9


def test_compensation_by_ik_removes_the_true_error(machine, errors):
    # commands that make the real machine put the tip where the ideal machine would
    rng = np.random.default_rng(3)
    nominal = np.column_stack([rng.uniform(-20, 20, (10, 3)), rng.uniform(-30, 30, 10), rng.uniform(-90, 90, 10)])
    target = forward(machine, nominal).tool_in_workpiece()
    before = np.linalg.norm(forward(machine, nominal, errors).tool_in_workpiece()[:, :3, 3] - target[:, :3, 3], axis=1)
    comp = inverse(machine, target[:, :3, 3], target[:, :3, 2], errors, initial=nominal)
    after = np.linalg.norm(forward(machine, comp, errors).tool_in_workpiece()[:, :3, 3] - target[:, :3, 3], axis=1)
    assert before.mean() > 30 * UM
    assert after.max() < 2e-9  # mm: the IK stops when every component is within 1e-9


def test_batched_fk_equals_pose_by_pose(machine, errors):
    rng = np.random.default_rng(4)
    cmds = rng.uniform(-20, 20, (6, 5))
    batch = forward(machine, cmds, errors).tool_in_workpiece()
    for i in range(6):
        assert np.allclose(batch[i], forward(machine, cmds[i], errors).tool_in_workpiece()[0], atol=1e-14)


def test_approach_directions_forward_fill_signs():
    cmds = np.array([[1, 0, 0, 0, 0], [2, 0, 0, 0, 0], [2, 1, 0, 0, 0], [1, 1, 0, 0, 0]], float)
    d = approach_directions(cmds)
    assert d[:, 0].tolist() == [1, 1, 1, -1]
    assert d[:, 1].tolist() == [0, 0, 1, 1]


def test_context_reaches_backlash(machine):
    e = parse_effect("backlash:axis=Y,amount_um=8")
    q = np.zeros((2, 5))
    ctx = PoseContext(np.array([[0, 1, 0, 0, 0], [0, -1, 0, 0, 0]], float), np.zeros(2), np.full(2, 20.0))
    dy = e.joint_errors(machine, q, ctx)["Y"][:, 1] / UM
    assert np.allclose(dy, [4.0, -4.0])
    assert ARCSEC > 0
