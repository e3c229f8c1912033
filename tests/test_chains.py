"""Serial planar chains: the chain library, compound-link systems, recovery from noisy data."""

import numpy as np
import pytest
import sympy as sp
from _multiarm_triple_reference import accelerations as reference_accelerations
from sklearn.base import clone

from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy.systems import (
    chain_lagrangian,
    make_dataset,
    multiarm_triple_pendulum,
    n_link_lagrangian,
    planar_chain,
    triple_pendulum,
)

ANGLES3 = ["theta1", "theta2", "theta3"]


# ----------------------------------------------------------------------------- library
def test_chain_library_terms_and_documented_sizes():
    lib = CandidateLibrary.chain(ANGLES3)
    assert [str(t) for t in lib.terms_] == [
        "theta1_dot**2",
        "theta2_dot**2",
        "theta3_dot**2",
        "theta1_dot*theta2_dot*cos(theta1 - theta2)",
        "theta1_dot*theta3_dot*cos(theta1 - theta3)",
        "theta2_dot*theta3_dot*cos(theta2 - theta3)",
        "cos(theta1)",
        "sin(theta1)",
        "cos(theta2)",
        "sin(theta2)",
        "cos(theta3)",
        "sin(theta3)",
    ]
    assert lib.removed_ == []
    assert len(CandidateLibrary.chain(ANGLES3, sin_coupling=True)) == 15
    seven = [f"q{i}" for i in range(1, 8)]
    assert len(CandidateLibrary.chain(seven)) == 42
    assert len(CandidateLibrary.chain(seven, sin_coupling=True)) == 63


def test_chain_library_prismatic_revolute():
    cart = CandidateLibrary.chain(["x", "theta"], angles=["theta"])
    assert [str(t) for t in cart.terms_] == [
        "x_dot**2",
        "theta_dot**2",
        "theta_dot*x_dot*cos(theta)",
        "theta_dot*x_dot*sin(theta)",
        "x",
        "x**2",
        "cos(theta)",
        "sin(theta)",
    ]
    gantry = CandidateLibrary.chain(["x", "y", "theta"], angles=["theta"], degree=1)
    names = [str(t) for t in gantry.terms_]
    assert "x_dot*y_dot" in names and "y" in names and "y**2" not in names
    assert len(gantry) == 3 + 4 + 1 + 2 + 2


def test_chain_library_is_a_parameter_object_with_reductions():
    lib = CandidateLibrary.chain(ANGLES3, terms=["theta1_dot", "cos(theta1)**2"])
    assert clone(lib).get_params() == lib.get_params()
    removed = dict(lib.removed_)
    assert removed["theta1_dot"].startswith("trivial")
    assert "cos(theta1)**2" in [str(t) for t in lib.terms_]
    est = LagrangianSINDy(CandidateLibrary.chain())
    assert "library__sin_coupling" in est.get_params()
    est.set_params(library__coordinates=ANGLES3, library__sin_coupling=True)
    assert len(est.library) == 15
    assert len(clone(est).library) == 15
    with pytest.raises(ValueError, match="angles"):
        CandidateLibrary.chain(["x"], angles=["theta"]).build()


def test_libraries_add_up():
    a = CandidateLibrary.chain(["theta1", "theta2"])
    b = CandidateLibrary.from_terms(
        ["theta1", "theta2"], ["theta1_dot*theta2_dot", "cos(theta1)"]
    )
    both = a + b
    assert len(both) == len(a) + 1  # cos(theta1) appears once
    assert str(both.terms_[-1]) == "theta1_dot*theta2_dot"
    assert len(clone(both)) == len(both)
    with pytest.raises(ValueError, match="different coordinates"):
        a + CandidateLibrary.chain(["x"])


# ----------------------------------------------------------------------------- systems
def _random_parameters(rng):
    m = rng.uniform(0.1, 1.0, 3)
    a = rng.uniform(0.05, 0.3, 3)
    length = rng.uniform(0.1, 0.3, 2)
    inertia = rng.uniform(1e-4, 1e-2, 3)
    k = rng.uniform(1e-4, 1e-2, 3)
    return [*m, *a, *length, *inertia, *k, rng.uniform(9.7, 9.9)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_multiarm_triple_pendulum_equals_the_authors_reference_ode(seed):
    """Accelerations equal TriplePendulumODE_Mounted.m (ported) at random states."""
    rng = np.random.default_rng(seed)
    params = _random_parameters(rng)
    system = multiarm_triple_pendulum(params)
    q = rng.uniform(-np.pi, np.pi, (40, 3))
    qd = rng.uniform(-6.0, 6.0, (40, 3))
    ours = system.forward_dynamics(q, qd)
    ref = np.stack(
        [
            reference_accelerations(np.r_[q[i] + np.pi, qd[i]], *params)
            for i in range(40)
        ]
    )
    # measured max |difference| 2.8e-13 with |accelerations| up to 75 rad/s^2
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-10 * np.abs(ref).max())


def test_multiarm_triple_pendulum_is_the_nine_term_chain_model():
    system = multiarm_triple_pendulum(_random_parameters(np.random.default_rng(3)))
    lib = CandidateLibrary.chain(system.coordinates)
    coef = system.true_coefficients(lib)
    assert np.count_nonzero(coef) == 9
    assert not np.any(coef[[7, 9, 11]])  # no sin(phi_i) potential
    with pytest.raises(ValueError, match="15 values"):
        multiarm_triple_pendulum([1.0] * 14)


def test_compound_chain_reduces_to_point_masses():
    """a = L, I = 0: the compound Lagrangian is the point-mass one, compact or not."""
    masses, lengths = [1.2, 0.8, 0.5], [0.9, 0.7, 0.5]
    compact, _, _ = chain_lagrangian(masses, lengths, com=lengths, inertia=[0] * 3)
    expanded, _ = n_link_lagrangian(masses, lengths)
    diff = sp.expand(sp.expand_trig(compact) - expanded)
    assert diff == 0 or max(abs(float(c)) for c in sp.Poly(diff).coeffs()) < 1e-12
    assert "cos(theta1 - theta2)" in str(compact)


def test_triple_pendulum_default_is_unchanged():
    terms = triple_pendulum().terms()
    assert terms == pytest.approx(
        {
            "theta1_dot**2": 1.5,
            "theta2_dot**2": 1.0,
            "theta3_dot**2": 0.5,
            "theta1_dot*theta2_dot*cos(theta1)*cos(theta2)": 2.0,
            "theta1_dot*theta2_dot*sin(theta1)*sin(theta2)": 2.0,
            "theta1_dot*theta3_dot*cos(theta1)*cos(theta3)": 1.0,
            "theta1_dot*theta3_dot*sin(theta1)*sin(theta3)": 1.0,
            "theta2_dot*theta3_dot*cos(theta2)*cos(theta3)": 1.0,
            "theta2_dot*theta3_dot*sin(theta2)*sin(theta3)": 1.0,
            "cos(theta1)": 3 * 9.81,
            "cos(theta2)": 2 * 9.81,
            "cos(theta3)": 9.81,
        }
    )
    assert triple_pendulum().dissipation == 0


def test_compound_triple_pendulum_damping_acts_on_relative_velocities():
    system = triple_pendulum(
        com=[0.5, 0.5, 0.5], inertia=[0.1, 0.1, 0.1], damping=[0.1, 0.2, 0.3]
    )
    qd = sp.symbols("theta1_dot theta2_dot theta3_dot", real=True)
    force = [-sp.diff(system.dissipation, v) for v in qd]
    # joint 2 pushes link 1 by +k2 (qd2 - qd1) and link 2 by -k2 (qd2 - qd1)
    assert sp.expand(force[0] - (-0.1 * qd[0] + 0.2 * (qd[1] - qd[0]))) == 0
    assert sp.expand(force[2] - (-0.3 * (qd[2] - qd[1]))) == 0


# ----------------------------------------------------------------------------- recovery
CHAINS = {
    2: dict(masses=[1.0, 0.6], lengths=[1.0, 0.7]),
    3: dict(masses=[1.2, 0.8, 0.5], lengths=[0.9, 0.7, 0.5]),
    4: dict(masses=[1.5, 1.0, 0.7, 0.4], lengths=[1.0, 0.8, 0.6, 0.5]),
}


def _recovery_error(n, excitation):
    """Max relative coefficient error (after the passive scale), or inf if wrong support."""
    system = planar_chain(**CHAINS[n])
    data = make_dataset(
        system,
        n_trajectories=4,
        duration=4.0,
        excitation=excitation,
        noise=1e-3,
        protocol="sensor",
        random_state=0,
    )
    est = LagrangianSINDy(system.paper_library(), formulation="weak", random_state=0)
    est.fit(data.X, data.tau, groups=data.groups)
    true = system.true_coefficients(est.library_)
    coef = est.coef_
    if excitation is None:
        pivot = est.library_.index("theta1_dot**2")
        coef, true = coef / coef[pivot], true / true[pivot]
    if not np.array_equal(coef != 0, true != 0):
        return np.inf, est
    nz = true != 0
    return float(np.max(np.abs(coef[nz] - true[nz]) / np.abs(true[nz]))), est


@pytest.mark.parametrize("n", [2, 3])
@pytest.mark.parametrize("excitation", ["paper", None])
def test_chain_recovered_from_noisy_positions(n, excitation):
    err, est = _recovery_error(n, excitation)
    # measured max errors 0.04 % to 0.08 % (acceptance: exact support, 2 %)
    assert err < 0.005, est.equation()


@pytest.mark.slow
@pytest.mark.parametrize("excitation", ["paper", None])
def test_four_link_chain_recovered_from_noisy_positions(excitation):
    err, est = _recovery_error(4, excitation)
    # measured 0.17 % (forced), 0.06 % (passive)
    assert err < 0.01, est.equation()


def test_compact_form_survives_printing_tables_and_files(tmp_path):
    system = planar_chain(**CHAINS[2])
    data = make_dataset(
        system, n_trajectories=2, duration=3.0, excitation="paper", random_state=1
    )
    est = LagrangianSINDy(system.paper_library(), formulation="weak", random_state=0)
    est.fit(data.X, data.tau, groups=data.groups)
    key = "theta1_dot*theta2_dot*cos(theta1 - theta2)"
    assert key in str(est.lagrangian_)
    assert key in est.equation()
    assert key in set(est.coef_table()["term"])
    path = est.save(tmp_path / "chain.json")
    assert key in path.read_text()
    loaded = LagrangianSINDy.load(path)
    assert key in loaded.equation()
    np.testing.assert_array_equal(loaded.coef_, est.coef_)
    np.testing.assert_allclose(
        loaded.predict(data.X[:50]), est.predict(data.X[:50]), rtol=0, atol=1e-12
    )


# ----------------------------------------------------------------------------- relative
def relative_two_link_arm(damping=None):
    """A compound two-link arm recorded with a relative elbow angle (q2 = theta2 - theta1)."""
    from lagsindy._expr import symbols_for
    from lagsindy.systems.base import System

    absolute, _, _ = chain_lagrangian(
        [1.3, 0.7],
        [0.45, 0.35],
        com=[0.22, 0.17],
        inertia=[0.024, 0.0083],
        names=["t1", "t2"],
    )
    (t1, t2), (t1d, t2d), _ = symbols_for(["t1", "t2"])
    (q1, q2), (q1d, q2d), _ = symbols_for(["q1", "q2"])
    lagrangian = absolute.subs(
        {t1: q1, t2: q1 + q2, t1d: q1d, t2d: q1d + q2d}, simultaneous=True
    )
    ranges = {"q1": (-1, 1), "q2": (-1, 1), "q1_dot": (-1, 1), "q2_dot": (-1, 1)}
    return System(
        lagrangian,
        ["q1", "q2"],
        angles=["q1", "q2"],
        initial_ranges=ranges,
        name="relative two-link arm",
    )


def test_relative_chain_library_terms():
    lib = CandidateLibrary.chain(["q1", "q2"], relative=True)
    assert [str(t) for t in lib.terms_] == [
        "q1_dot**2",
        "(q1_dot + q2_dot)**2",
        "q1_dot*(q1_dot + q2_dot)*cos(q2)",
        "cos(q1)",
        "sin(q1)",
        "cos(q1 + q2)",
        "sin(q1 + q2)",
    ]
    three = CandidateLibrary.chain(["q1", "q2", "q3"], relative=True)
    assert "q1_dot*(q1_dot + q2_dot + q3_dot)*cos(q2 + q3)" in [
        str(t) for t in three.terms_
    ]
    assert len(three) == len(CandidateLibrary.chain(["q1", "q2", "q3"])) == 12
    cart = CandidateLibrary.chain(["x", "q1", "q2"], angles=["q1", "q2"], relative=True)
    assert "x_dot*(q1_dot + q2_dot)*cos(q1 + q2)" in [str(t) for t in cart.terms_]
    assert clone(lib).get_params()["relative"] is True


def test_relative_arm_is_five_terms_of_the_relative_library_only():
    system = relative_two_link_arm()
    coef = system.true_coefficients(CandidateLibrary.chain(["q1", "q2"], relative=True))
    assert np.count_nonzero(coef) == 5
    with pytest.raises(ValueError, match="cannot represent"):
        system.true_coefficients(CandidateLibrary.chain(["q1", "q2"]))


def test_relative_arm_fitted_exactly():
    system = relative_two_link_arm()
    data = make_dataset(
        system, n_trajectories=4, duration=3.0, excitation="sincos", random_state=0
    )
    lib = CandidateLibrary.chain(system.coordinates, relative=True)
    est = LagrangianSINDy(lib, random_state=0).fit(data.X, data.tau)
    true = system.true_coefficients(est.library_)
    assert np.array_equal(est.coef_ != 0, true != 0), est.equation()
    nz = true != 0
    # measured max relative error 3.9e-4 (noise-free data); the generic degree-3
    # library (55 terms) also contains it, the absolute chain library does not
    np.testing.assert_allclose(est.coef_[nz], true[nz], rtol=1e-3)
