"""The energy regressor's Euler-Lagrange columns equal pinocchio's joint torque regressor."""

import numpy as np
import pytest
from _robot_oracle import (
    ARM7_JOINTS,
    DATA,
    PANDA_JOINTS,
    example_robot,
    pinocchio_model,
    pinocchio_regressor,
)

from lagsindy import CandidateLibrary
from lagsindy.robots import base_parameters
from lagsindy.robots.base_parameters import exciting_states

pin = pytest.importorskip("pinocchio")

CASES = {
    "planar2": lambda: (str(DATA / "planar2.urdf"), None, None),
    "mixed": lambda: (
        str(DATA / "mixed.urdf"),
        ["spin", "rail", "tilt", "side"],  # not the file's order
        {"finger_a_joint": 0.03},  # finger_b mimics it
    ),
    "arm6": lambda: (str(DATA / "arm6.urdf"), None, None),
    "arm7": lambda: (str(DATA / "arm7.urdf"), ARM7_JOINTS, {"finger_joint1": 0.03}),
    "ur5": lambda: (example_robot("ur_description/urdf/ur5_robot.urdf"), None, None),
    "panda": lambda: (
        example_robot("panda_description/urdf/panda.urdf"),
        PANDA_JOINTS,
        {"panda_finger_joint1": 0.02},
    ),
}


@pytest.mark.parametrize("method", ["recursive", "autograd"])
@pytest.mark.parametrize("name", list(CASES))
def test_regressor_equals_pinocchio(name, method):
    path, joints, locked = CASES[name]()
    lib = CandidateLibrary.from_urdf(path, joints, locked=locked)
    tree = lib.tree_
    rng = np.random.default_rng(7)
    n = 40
    q = rng.uniform(-np.pi, np.pi, (n, tree.n_dof))
    qd = rng.uniform(-3.0, 3.0, (n, tree.n_dof))
    qdd = rng.uniform(-8.0, 8.0, (n, tree.n_dof))
    ours = lib.euler_lagrange_columns(q, qd, qdd, method=method)
    model = pinocchio_model(pin, tree)
    theirs, params = pinocchio_regressor(pin, model, tree, q, qd, qdd)
    n_link = 10 * len(tree.bodies)
    # measured max |difference| 2.2e-14 (Panda, entries up to 19)
    np.testing.assert_allclose(ours[:, :, :n_link], theirs, rtol=0, atol=1e-10)
    # the armature columns are qdd
    np.testing.assert_allclose(
        ours[:, :, n_link:], qdd[:, :, None] * np.eye(tree.n_dof)
    )
    # the merged and locked links' inertias are pinocchio's
    np.testing.assert_allclose(lib.nominal_[:n_link], params, rtol=0, atol=1e-12)
    # and the nominal model's torques are pinocchio's inverse dynamics
    data = model.createData()
    if name in ("planar2", "arm7", "panda"):
        for s in range(3):
            tau = pin.rnea(model, data, q[s], qd[s], qdd[s])
            np.testing.assert_allclose(ours[s] @ lib.nominal_, tau, rtol=0, atol=1e-10)


def test_locked_position_moves_the_merged_inertia():
    path, joints, _ = CASES["mixed"]()
    a = CandidateLibrary.from_urdf(path, joints, locked={"finger_a_joint": 0.0})
    b = CandidateLibrary.from_urdf(path, joints, locked={"finger_a_joint": 0.04})
    assert b.locked_["finger_b_joint"] == pytest.approx(0.04)  # mimic followed
    k = a.index("Ixx_arm")  # the fingers move along +-y: their first moments cancel
    assert a.nominal_[k] != pytest.approx(b.nominal_[k])
    # pinocchio agrees at the other position too
    rng = np.random.default_rng(1)
    q, qd, qdd = (rng.uniform(-1, 1, (5, 4)) for _ in range(3))
    theirs, params = pinocchio_regressor(
        pin, pinocchio_model(pin, b.tree_), b.tree_, q, qd, qdd
    )
    np.testing.assert_allclose(b.nominal_[: params.size], params, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["arm7", "panda"])
def test_seven_joint_base_parameters(name):
    path, joints, locked = CASES[name]()
    link = "panda_link" if name == "panda" else "link"
    lib = CandidateLibrary.from_urdf(path, joints, armature=False, locked=locked)
    bp = base_parameters(lib)
    assert (len(lib), bp.n_base) == (70, 43)  # the classical count for this arm
    assert bp.labels[0] == f"Izz_{link}1 + Iyy_{link}2"
    lib_a = CandidateLibrary.from_urdf(path, joints, locked=locked)
    bp_a = base_parameters(lib_a)
    # joint 1's and joint 2's rotor inertias join link inertias; 5 more base parameters
    assert bp_a.n_base == 48
    assert bp_a.labels[0].endswith("_joint1")  # ... + Ia_<joint1>
    # the base regressor reproduces the full one at new states
    rng = np.random.default_rng(3)
    q, qd, qdd = exciting_states(lib_a.tree_.lower, lib_a.tree_.upper, 30, rng)
    full = lib_a.euler_lagrange_columns(q, qd, qdd)
    pi = rng.normal(size=len(lib_a))
    np.testing.assert_allclose(
        bp_a.columns(full) @ bp_a.values(pi), full @ pi, rtol=0, atol=1e-9
    )
