"""Physically consistent parameters and the URDF write-back round trip."""

import numpy as np
import pytest
from _robot_oracle import ARM7_JOINTS, DATA

from lagsindy import CandidateLibrary
from lagsindy.robots import base_parameters, consistent_parameters, feasibility, to_urdf
from lagsindy.robots.export import pseudo_inertia, reread

ARM7 = str(DATA / "arm7.urdf")
PLANAR = str(DATA / "planar2.urdf")


def test_write_back_round_trip(tmp_path):
    lib = CandidateLibrary.from_urdf(ARM7, ARM7_JOINTS, locked={"finger_joint1": 0.03})
    rng = np.random.default_rng(0)
    pi = lib.nominal_.copy()
    pi[-7:] = rng.uniform(0.05, 0.3, 7)  # rotor inertias
    damping, friction = rng.uniform(0.1, 1, 7), rng.uniform(0.1, 2, 7)
    out = to_urdf(
        lib, pi, tmp_path / "arm7_identified.urdf", damping=damping, friction=friction
    )
    back = reread(lib, out)
    n_link = 70
    # the hand and fingers now live in link7's inertial; measured max difference 2e-16
    np.testing.assert_allclose(
        back.nominal_[:n_link], pi[:n_link], rtol=1e-10, atol=1e-14
    )
    np.testing.assert_allclose(back.tree_.damping, damping, rtol=1e-11)
    np.testing.assert_allclose(back.tree_.friction, friction, rtol=1e-11)
    text = out.read_text()
    assert "lagsindy: armature" in text and "inertia merged into link7" in text
    # the written file reads alike whatever the (now massless) fingers' position
    other = reread(lib.set_params(locked={"finger_joint1": 0.0}), out)
    np.testing.assert_allclose(
        other.nominal_[:n_link], pi[:n_link], rtol=1e-10, atol=1e-14
    )


def test_write_back_rejects_inconsistent_mass(tmp_path):
    lib = CandidateLibrary.from_urdf(PLANAR)
    pi = lib.nominal_.copy()
    pi[0] = 0.0  # upper arm massless but with a first moment
    with pytest.raises(ValueError, match="not physically consistent"):
        to_urdf(lib, pi, tmp_path / "x.urdf")
    with pytest.raises(ValueError, match=r"shape \(22,\)"):
        to_urdf(lib, pi[:5], tmp_path / "x.urdf")


def test_consistent_parameters_reproduce_base_parameters():
    lib = CandidateLibrary.from_urdf(ARM7, ARM7_JOINTS)
    base = base_parameters(lib)
    rng = np.random.default_rng(1)
    truth = lib.nominal_.copy()
    truth[:70] *= np.repeat(rng.uniform(0.8, 1.2, 7), 10)  # heavier or lighter links
    truth[70:] = rng.uniform(0.05, 0.2, 7)
    assert feasibility(truth, 7).min() > 0
    beta = base.values(truth)
    out = consistent_parameters(lib, base, beta)
    assert out.success and out.violation < 1e-8
    assert out.min_eigenvalue.min() > 0 and np.all(out.parameters[70:] >= 0)
    np.testing.assert_allclose(
        base.values(out.parameters), beta, rtol=0, atol=1e-8 * np.abs(beta).max()
    )


def test_inconsistent_base_parameters_warn():
    lib = CandidateLibrary.from_urdf(PLANAR)
    base = base_parameters(lib)
    beta = base.values(lib.nominal_)
    k = base.labels.index("Iyy_upper_arm + 0.2025*m_forearm + Ia_shoulder")
    beta[
        k
    ] = -0.05  # a negative inertia about the shoulder: no mass distribution has it
    with pytest.warns(UserWarning, match="no physically consistent parameters"):
        out = consistent_parameters(lib, base, beta)
    assert not out.success and out.violation > 1e-3
    assert out.min_eigenvalue.min() > 0  # still a consistent representative


def test_pseudo_inertia_of_a_point_mass_is_rank_one():
    m, c = 2.0, np.array([0.1, -0.2, 0.3])
    params = np.r_[m, m * c, 0, 0, 0, 0, 0, 0]
    i = m * (c @ c * np.eye(3) - np.outer(c, c))
    params[4:] = [i[0, 0], i[0, 1], i[1, 1], i[0, 2], i[1, 2], i[2, 2]]
    w = np.linalg.eigvalsh(pseudo_inertia(params))
    assert abs(w[:3]).max() < 1e-12 and w[3] > 0


def test_inconsistent_reference_is_projected_onto_the_consistent_set():
    lib = CandidateLibrary.from_urdf(ARM7, ARM7_JOINTS)
    base = base_parameters(lib)
    beta = base.values(lib.nominal_)
    reference = lib.nominal_.copy()
    reference[14] = -0.5  # link 2: Ixx < 0, no mass distribution has it
    assert feasibility(reference, 7).min() < 0
    out = consistent_parameters(lib, base, beta, reference=reference)
    assert out.success and out.min_eigenvalue.min() > 0
    np.testing.assert_allclose(base.values(out.parameters), beta, rtol=0, atol=1e-9)
