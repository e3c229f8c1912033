"""URDF reading, the energy terms and base parameters, checked without pinocchio."""

import pickle

import numpy as np
import pytest
import torch
from _robot_oracle import DATA
from sklearn.base import clone
from torch.func import jacfwd, vmap

from lagsindy import CandidateLibrary
from lagsindy.robots import RobotLibrary, base_parameters, build_tree
from lagsindy.robots.urdf import axis_rotation, transform_parameters

PLANAR = str(DATA / "planar2.urdf")
MIXED = str(DATA / "mixed.urdf")


def planar_lagrangian(q, qd, g=9.81):
    """The two-link arm of planar2.urdf by hand (relative elbow angle)."""
    m1, c1, i1, l1 = 1.3, 0.22, 0.024, 0.45
    m2, c2, i2 = 0.7, 0.17, 0.0083
    q1, q2 = q[:, 0], q[:, 1]
    w1, w2 = qd[:, 0], qd[:, 0] + qd[:, 1]
    # rotation about +y: a point (0, 0, -c) goes to (-c sin q, 0, -c cos q)
    x2d = -l1 * np.cos(q1) * w1 - c2 * np.cos(q1 + q2) * w2
    z2d = l1 * np.sin(q1) * w1 + c2 * np.sin(q1 + q2) * w2
    kinetic = (
        0.5 * (i1 + m1 * c1**2) * w1**2
        + 0.5 * i2 * w2**2
        + 0.5 * m2 * (x2d**2 + z2d**2)
    )
    z1, z2 = -c1 * np.cos(q1), -l1 * np.cos(q1) - c2 * np.cos(q1 + q2)
    return kinetic - g * (m1 * z1 + m2 * z2)


def test_terms_reproduce_the_hand_written_lagrangian():
    lib = CandidateLibrary.from_urdf(PLANAR)
    assert lib.coordinates_ == ["shoulder", "elbow"]
    rng = np.random.default_rng(0)
    q, qd = rng.uniform(-3, 3, (50, 2)), rng.uniform(-4, 4, (50, 2))
    phi = lib.torch_terms().fn_batch(torch.tensor(q), torch.tensor(qd)).numpy()
    # measured max |difference| 1.8e-15 (|L| up to 6)
    np.testing.assert_allclose(
        phi @ lib.nominal_, planar_lagrangian(q, qd), rtol=0, atol=1e-12
    )


def test_term_function_contract():
    terms = CandidateLibrary.from_urdf(
        MIXED, ["spin", "rail", "tilt", "side"]
    ).torch_terms()
    assert len(terms.names) == terms.n_terms == 10 * 4 + 4
    rng = np.random.default_rng(1)
    q, qd = torch.tensor(rng.normal(size=(6, 4))), torch.tensor(rng.normal(size=(6, 4)))
    batch = terms.fn_batch(q, qd)
    assert batch.shape == (6, terms.n_terms)
    one = torch.stack([terms.fn(q[i], qd[i]) for i in range(6)])
    torch.testing.assert_close(one, batch, rtol=0, atol=1e-14)
    jac = vmap(jacfwd(terms.fn, argnums=0))(q, qd)  # torch.func-safe
    assert jac.shape == (6, terms.n_terms, 4)
    # float32 follows the input
    assert terms.fn_batch(q.float(), qd.float()).dtype == torch.float32


def test_kinetic_energy_is_quadratic_and_potential_has_gravity():
    lib = RobotLibrary(PLANAR).build()
    terms = lib.torch_terms()
    q = torch.tensor([[0.3, -0.7]], dtype=torch.float64)
    qd = torch.tensor([[1.1, 0.4]], dtype=torch.float64)
    kin, pot = terms.energies(q, qd, lib.nominal_)
    kin2, pot2 = terms.energies(q, 2 * qd, lib.nominal_)
    assert float(kin2) == pytest.approx(4 * float(kin), rel=1e-12)
    assert float(pot2) == pytest.approx(float(pot), rel=1e-12)
    up = RobotLibrary(PLANAR, gravity=(0, 0, 9.81)).build().torch_terms()
    assert float(up.energies(q, qd, lib.nominal_)[1]) == pytest.approx(-float(pot))


def test_fixed_joints_merge_and_locked_defaults():
    tree = build_tree(MIXED, ["rail", "spin", "tilt", "side"])
    names = [b.name for b in tree.bodies]
    assert names == ["slider", "turret", "arm", "side_arm"]  # tree order, file order
    assert tree.bodies[1].links == ["turret", "bracket"]
    assert tree.bodies[2].links == ["arm", "finger_a", "finger_b"]
    assert tree.locked == {"finger_a_joint": 0.0, "finger_b_joint": 0.0}
    # the bracket's mass rides on the turret; the pedestal on the fixed base is ignored
    assert tree.bodies[1].parameters[0] == pytest.approx(1.5 + 0.4)
    assert tree.bodies[2].parameters[0] == pytest.approx(0.9 + 0.1)
    assert tree.coordinates == ["rail", "spin", "tilt", "side"]
    assert [b.coordinate for b in tree.bodies] == [0, 1, 2, 3]


def test_transform_parameters_is_a_rigid_motion():
    rng = np.random.default_rng(2)
    params = np.array([2.0, 0.1, -0.2, 0.3, 0.5, 0.01, 0.4, -0.02, 0.03, 0.6])
    rot, p = axis_rotation(np.array([0.6, 0.0, 0.8]), 0.7), rng.normal(size=3)
    moved = transform_parameters(params, rot, p)
    back = transform_parameters(moved, rot.T, -rot.T @ p)
    np.testing.assert_allclose(back, params, rtol=0, atol=1e-14)
    # the centre of mass moves as a point
    np.testing.assert_allclose(moved[1:4] / 2.0, rot @ (params[1:4] / 2.0) + p)


@pytest.mark.parametrize(
    "joints, locked, match",
    [
        (["nope"], None, "not in mixed.urdf"),
        (["finger_b_joint"], None, "mimic joint cannot be a coordinate"),
        (None, None, "mimics 'finger_a_joint', which is a coordinate"),
        (["spin", "spin"], None, "twice"),
        (["spin"], {"finger_b_joint": 0.01}, "lock 'finger_a_joint' instead"),
        (["spin"], {"spin": 0.1}, "both a coordinate and locked"),
        (["spin"], {"bracket_mount": 0.1}, "not a moving joint"),
    ],
)
def test_clear_errors(joints, locked, match):
    with pytest.raises(ValueError, match=match):
        build_tree(MIXED, joints, locked)


def test_unsupported_joint_and_bad_names(tmp_path):
    text = open(PLANAR).read()
    (tmp_path / "float.urdf").write_text(
        text.replace('type="fixed"', 'type="floating"')
    )
    with pytest.raises(ValueError, match="floating base is not"):
        build_tree(tmp_path / "float.urdf")
    (tmp_path / "dash.urdf").write_text(text.replace('"elbow"', '"elbow-joint"'))
    with pytest.raises(ValueError, match="rename the joint"):
        RobotLibrary(tmp_path / "dash.urdf").build()
    (tmp_path / "bad.xml").write_text("<robot><link")
    with pytest.raises(ValueError, match="not a readable URDF"):
        build_tree(tmp_path / "bad.xml")


def test_library_is_a_parameter_object():
    lib = CandidateLibrary.from_urdf(PLANAR, armature=False)
    assert isinstance(lib, RobotLibrary)
    assert len(lib) == 20 and lib.index("Iyy_forearm") == 16
    assert list(lib.get_feature_names_out()[:2]) == ["m_upper_arm", "mx_upper_arm"]
    with pytest.raises(ValueError, match="Ia_<joint>"):
        lib.index("m_nothing")
    twin = clone(lib)
    assert twin.get_params() == lib.get_params() and len(twin) == 20
    back = pickle.loads(pickle.dumps(lib))
    np.testing.assert_array_equal(back.nominal_, lib.nominal_)
    q = np.array([[0.1, 0.2]])
    np.testing.assert_allclose(
        back.euler_lagrange_columns(q, q, q), lib.euler_lagrange_columns(q, q, q)
    )
    lib.set_params(armature=True)
    assert len(lib) == 22  # rebuilt on a parameter change
    with pytest.raises(ValueError, match=r"shape \(n_samples, 2\)"):
        lib.euler_lagrange_columns(q[:, :1], q, q)


def test_planar_base_parameters_in_link_terms():
    bp = base_parameters(CandidateLibrary.from_urdf(PLANAR))
    assert bp.labels == [
        "mx_upper_arm",
        "mz_upper_arm - 0.45*m_forearm",
        "Iyy_upper_arm + 0.2025*m_forearm + Ia_shoulder",
        "mx_forearm",
        "mz_forearm",
        "Iyy_forearm",
        "Ia_elbow",
    ]
    assert bp.rank_qr == bp.n_base == 7
    # parameters without any effect (planar: out-of-plane inertia, m of link 1, ...)
    names = [bp.names[i] for i in bp.unidentifiable]
    assert "Ixx_upper_arm" in names and "m_upper_arm" in names and "my_forearm" in names
    # values are never thresholded: a tiny link keeps its base parameters
    lib = CandidateLibrary.from_urdf(PLANAR)
    tiny = lib.nominal_ * 1e-9
    # mx of both links and Ia_elbow are 0 in the file; the other four stay
    assert np.count_nonzero(bp.values(tiny)) == 4
    assert "beta1   = mx_upper_arm" in str(bp)


@pytest.mark.parametrize(
    "path, joints", [(MIXED, ["tilt", "spin", "side", "rail"]), (PLANAR, None)]
)
def test_recursive_regressor_equals_autograd_columns(path, joints):
    lib = CandidateLibrary.from_urdf(
        path, joints, locked={"finger_a_joint": 0.02} if joints else None
    )
    rng = np.random.default_rng(4)
    n, d = 25, len(lib.coordinates_)
    q, qd, qdd = (rng.uniform(-3, 3, (n, d)) for _ in range(3))
    fast = lib.euler_lagrange_columns(q, qd, qdd)
    slow = lib.euler_lagrange_columns(q, qd, qdd, method="autograd")
    # measured max |difference| 8.9e-15 (entries up to 10)
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-11)
    with pytest.raises(ValueError, match="'recursive' or 'autograd'"):
        lib.euler_lagrange_columns(q, qd, qdd, method="fast")


def test_base_parameter_library_index():
    base = CandidateLibrary.from_urdf(PLANAR, armature=False).regression_library()
    names = list(base.get_feature_names_out())
    assert len(base) == len(names) and base.index(names[1]) == 1
    # a link parameter standing alone in a base parameter gives that one's position
    alone = [
        name
        for j, name in enumerate(base.robot_.terms_)
        if np.count_nonzero(base.base_.matrix[:, j]) == 1
    ]
    k = base.index(alone[0])
    assert np.count_nonzero(base.base_.matrix[k]) >= 1
    shared = [
        name
        for j, name in enumerate(base.robot_.terms_)
        if np.count_nonzero(base.base_.matrix[:, j]) > 1
    ]
    with pytest.raises(ValueError, match="enters [0-9]+ base parameters"):
        base.index(shared[0])
    with pytest.raises(ValueError, match="moves no torque"):
        base.index("my_upper_arm")  # about the joint axis: it moves nothing
    with pytest.raises(ValueError, match="not a base parameter of this robot"):
        base.index("m_nothing")
