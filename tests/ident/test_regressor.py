"""The batched regressor against Pinocchio's, and the structural base set."""

from __future__ import annotations

import numpy as np
import pytest

from robid_link.ident.fit.design import base_set_for
from robid_link.ident.model.effects import DEFAULT_MODEL, Block, Effect, Model
from robid_link.ident.model.regressor import reference_regressor, rigid_regressor
from robid_link.ident.model.robot import load_robot

from ..conftest import ROBOTS


def _random_states(robot, n, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.uniform(-2, 2, (n, robot.n)) for _ in range(3))


@pytest.mark.parametrize("name", ["arm3", "industrial6"])
def test_batched_regressor_matches_pinocchio_mdh(name):
    robot = load_robot(ROBOTS / f"{name}.yaml")
    q, qd, qdd = _random_states(robot, 300)
    ours, ref = rigid_regressor(robot, q, qd, qdd), reference_regressor(robot, q, qd, qdd)
    assert np.abs(ours - ref).max() <= 1e-9 * np.abs(ref).max()


def test_batched_regressor_matches_pinocchio_urdf(kuka_dir):
    robot = load_robot(kuka_dir / "kuka_lwr4.urdf")  # unaligned axes, fixed links merged
    q, qd, qdd = _random_states(robot, 300, seed=1)
    ours, ref = rigid_regressor(robot, q, qd, qdd), reference_regressor(robot, q, qd, qdd)
    assert np.abs(ours - ref).max() <= 1e-9 * np.abs(ref).max()


def test_batched_regressor_prismatic_and_offsets(tmp_path):
    desc = tmp_path / "cart.yaml"
    desc.write_text(
        "name: cart\nallow_unlimited: true\njoints:\n"
        "  - {name: rail, type: prismatic, alpha: 0, a: 0, theta: 30, d: 0.2}\n"
        "  - {name: shoulder, alpha: -90, a: 0.1, theta: -90, d: 0.05}\n"
        "  - {name: slide, type: prismatic, alpha: 90, a: 0.3, theta: 10, d: -0.1}\n"
        "  - {name: wrist, alpha: 45, a: 0.05, theta: 20, d: 0.1}\n")
    robot = load_robot(desc)
    q, qd, qdd = _random_states(robot, 200, seed=2)
    ours, ref = rigid_regressor(robot, q, qd, qdd), reference_regressor(robot, q, qd, qdd)
    assert np.abs(ours - ref).max() <= 1e-9 * np.abs(ref).max()


def test_regressor_times_parameters_is_rnea(industrial6):
    q, qd, qdd = _random_states(industrial6, 20, seed=3)
    y = rigid_regressor(industrial6, q, qd, qdd)
    for k in range(20):
        tau = industrial6.rnea(q[k], qd[k], qdd[k])
        np.testing.assert_allclose(y[k] @ industrial6.nominal, tau, rtol=1e-10, atol=1e-9)


def test_base_set_is_structural_and_named(arm3):
    blocks = DEFAULT_MODEL.blocks(arm3)
    b1, names = base_set_for(arm3, blocks)
    assert base_set_for(arm3, blocks)[0] is b1  # memoized per robot object
    # structural, not an accident of the memo: another robot object of the same description
    # gets the same base set, computed afresh from its own random states
    other = load_robot(ROBOTS / "arm3.yaml")
    b2, names2 = base_set_for(other, DEFAULT_MODEL.blocks(other))
    assert b2 is not b1 and names2 == names
    assert b1.independent == b2.independent
    np.testing.assert_allclose(b1.combination, b2.combination, rtol=1e-9, atol=1e-12)
    # 3-axis arm3 (vertical axis, two parallel pitch axes): 15 rigid base parameters
    assert b1.rank == 15 + 6
    exprs = {b1.names[i]: b1.expression(k) for k, i in enumerate(b1.independent)}
    # link 3 hangs a = 0.40 m from joint 3: zz_2 groups 0.16·m_3 (a²·m)
    assert exprs["zz_2"] == "zz_2 + 0.16·m_3"
    assert exprs["mx_2"] == "mx_2 + 0.4·m_3"
    assert "m_1" not in b1.base_names and "m_3" not in b1.base_names


def test_base_regressor_reproduces_full_model(industrial6):
    """W_full·θ = W_base·(K·θ) for any θ: the base set loses nothing."""
    blocks = Model.parse(["rigid_body", "viscous", "coulomb", "offset"]).blocks(industrial6)
    base, names = base_set_for(industrial6, blocks)
    from robid_link.ident.fit.design import block_columns
    from robid_link.ident.model.effects import States

    q, qd, qdd = _random_states(industrial6, 100, seed=4)
    w = block_columns(industrial6, blocks, States(q, qd, qdd))
    theta = np.random.default_rng(5).normal(size=len(names))
    full = w @ theta
    reduced = w[:, :, list(base.independent)] @ (base.combination @ theta)
    np.testing.assert_allclose(reduced, full, rtol=1e-8, atol=1e-8 * np.abs(full).max())


class _Armature(Effect):
    """A rotor-inertia block, local to this test (not registered)."""

    name = "armature_probe"

    def param_names(self, robot, joint, opts):
        return [f"ia_{joint + 1}"]

    def columns(self, robot, st, joint, opts):
        out = np.zeros((len(st), robot.n, 1))
        out[:, joint, 0] = st.qdd[:, joint]
        return out


def test_armature_on_first_joint_is_absorbed(arm3):
    """Declared overlap: rotor inertia of joint 1 is indistinguishable from zz_1."""
    blocks = [*DEFAULT_MODEL.blocks(arm3), *(Block(_Armature(), j) for j in range(3))]
    base, names = base_set_for(arm3, blocks)

    def absorbed_by(name):
        return [base.names[base.independent[k]] for k in base.absorbed[names.index(name)]]

    assert absorbed_by("ia_1") == ["zz_1"]
    # joint 2 is perpendicular to the vertical joint 1: zz_2 only acts through q̈2
    assert absorbed_by("ia_2") == ["zz_2"]
    assert names.index("ia_3") in base.independent


@pytest.mark.parametrize("side", [None, "joint", "motor"])
def test_row_columns_are_the_rows_a_block_loads(industrial6, side):
    """A per-joint effect's columns built on its rows only (``row_columns``) are the rows of
    its full block that are not zero, to the bit — on a coupled wrist (motor 6 loads joints 5
    and 6), either side; and the full block is zero everywhere else."""
    from robid_link.ident.fit.design import random_states
    from robid_link.ident.model.effects import REGISTRY

    rng = np.random.default_rng(3)
    st = random_states(industrial6, rng, 50, industrial6.transmission)
    checked = 0
    for eff in REGISTRY.values():
        if not eff.per_joint or (side is not None and not eff.sided):
            continue
        for j in (0, 4, 5):
            blk = Block(eff, j, {}, side)
            rows, own = blk.row_columns(industrial6, st)
            full = blk.columns(industrial6, st)
            assert np.array_equal(own, full[:, rows, :]), blk.key
            assert rows == blk.rows(industrial6, st.transmission) or not eff.loads, blk.key
            assert not np.any(np.delete(full, rows, axis=1)), blk.key
            checked += 1
    assert checked >= 3 * 10
