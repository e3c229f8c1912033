import numpy as np
import pytest
import sympy as sp
from sklearn.base import clone

from lagsindy import CandidateLibrary
from lagsindy.library import euler_lagrange_expressions
from lagsindy.systems import (
    cart_pendulum,
    double_pendulum,
    single_pendulum,
    spherical_pendulum,
)


@pytest.mark.parametrize(
    "system, n_candidates, n_kept",
    [
        # Paper counts of generated candidates: 14 (the paper keeps 12 after removing
        # two trivial terms), 55, 89, 59. More trivial and dependent terms go here.
        (single_pendulum, 14, 9),
        (cart_pendulum, 55, 39),
        (double_pendulum, 89, 63),
        (spherical_pendulum, 59, 38),
    ],
)
def test_paper_library_counts(system, n_candidates, n_kept):
    lib = system().paper_library()
    assert len(lib.candidates_) == n_candidates
    assert len(lib) == n_kept
    assert len(lib.removed_) == n_candidates - n_kept


def test_trivial_terms_removed():
    lib = CandidateLibrary.from_terms(
        ["theta"],
        ["theta_dot", "theta*theta_dot", "theta_dot*sin(theta)", "theta_dot**2"],
    )
    assert list(lib.get_feature_names_out()) == ["theta_dot**2"]
    reasons = dict(lib.removed_)
    assert set(reasons) == {"theta_dot", "theta*theta_dot", "theta_dot*sin(theta)"}
    assert all(r.startswith("trivial") for r in reasons.values())


def test_dependent_terms_reported_with_combination():
    lib = CandidateLibrary.from_terms(
        ["theta"], ["sin(theta)**2", "cos(theta)**2", "cos(theta)"]
    )
    assert list(lib.get_feature_names_out()) == ["sin(theta)**2", "cos(theta)"]
    ((name, reason),) = lib.removed_
    assert name == "cos(theta)**2"
    assert "dependent" in reason and "-1*[sin(theta)**2]" in reason


def test_no_reduction_when_disabled():
    lib = CandidateLibrary.from_terms(
        ["theta"],
        ["theta_dot", "sin(theta)**2", "cos(theta)**2"],
        remove_trivial=False,
        remove_dependent=False,
    )
    assert len(lib) == 3


def test_true_terms_survive_reduction():
    for system in (single_pendulum, cart_pendulum, double_pendulum, spherical_pendulum):
        s = system()
        lib = s.paper_library()
        names = set(lib.get_feature_names_out())
        assert set(s.terms()) <= names, s.name


def test_decompose_maps_equivalent_lagrangians():
    lib = spherical_pendulum().paper_library()
    # 1 - cos^2 instead of sin^2, plus a constant and a total derivative
    expr = "0.5*phi_dot**2*(1 - cos(theta)**2) + 0.5*theta_dot**2 + 9.81*cos(theta) + 3 + theta_dot*sin(theta)"
    coef, resid = lib.decompose(expr)
    assert resid < 1e-10
    names = list(lib.get_feature_names_out())
    got = {names[k]: round(c, 10) for k, c in enumerate(coef) if c != 0}
    # 0.5*phi_dot**2*(1 - cos^2) = 0.5*phi_dot**2*sin^2 exactly; the rest is trivial
    assert got == {
        "phi_dot**2*sin(theta)**2": 0.5,
        "theta_dot**2": 0.5,
        "cos(theta)": 9.81,
    }


def test_decompose_is_exact_in_a_wide_ill_conditioned_library():
    """theta**k * sin/cos(theta) on [-pi, pi]: least squares would leave round-off."""
    lib = CandidateLibrary.polynomial(
        ["theta"], angles=["theta"], degree=5, raw_angles=True
    )
    coef, resid = lib.decompose("0.5*theta_dot**2 + 9.81*cos(theta) - 9.81")
    names = list(lib.get_feature_names_out())
    assert {names[k]: c for k, c in enumerate(coef) if c != 0} == {
        "theta_dot**2": 0.5,
        "cos(theta)": 9.81,
    }
    assert resid < 1e-12


def test_index_and_errors():
    lib = cart_pendulum().paper_library()
    assert lib.get_feature_names_out()[lib.index("theta_dot**2")] == "theta_dot**2"
    assert lib.index(sp.Symbol("theta_dot") ** 2) == lib.index("theta_dot**2")
    with pytest.raises(ValueError, match="trivial"):
        lib.index("x_dot")
    with pytest.raises(ValueError, match="not in the library"):
        lib.index("x**4")
    with pytest.raises(ValueError):
        lib.index("y**2")


def test_parameters_are_clonable_and_rebuild():
    lib = CandidateLibrary.polynomial(["x"], degree=2)
    n2 = len(lib)
    lib2 = clone(lib).set_params(degree=3)
    assert len(lib2) > n2
    assert len(lib) == n2
    assert lib.get_params()["degree"] == 2


def test_builder_errors():
    with pytest.raises(ValueError, match="angles"):
        CandidateLibrary.polynomial(["x"], angles=["theta"]).build()
    with pytest.raises(ValueError, match="coordinates"):
        CandidateLibrary.polynomial(degree=2).build()
    with pytest.raises(ValueError, match="degree"):
        CandidateLibrary.polynomial(["x"], degree=0).build()
    with pytest.raises(ValueError, match="empty"):
        CandidateLibrary(["x"]).build()
    with pytest.raises(ValueError, match="unknown name"):
        CandidateLibrary.from_terms(["x"], ["y**2"]).build()


def test_euler_lagrange_expressions_of_pendulum():
    th, thd, thdd = sp.symbols("theta theta_dot theta_ddot", real=True)
    (el,) = euler_lagrange_expressions(thd**2 / 2 + 9.81 * sp.cos(th), ["theta"])
    assert sp.simplify(el - (thdd + 9.81 * sp.sin(th))) == 0


def test_separated_construction_counts():
    lib = CandidateLibrary.separated(
        ["a", "b"], angles="all", degree=2, remove_trivial=False, remove_dependent=False
    )
    # trig: 4 + 10, velocities: 2 + 3, cross 14 * 5
    assert len(lib) == 14 + 5 + 70
    assert np.all([isinstance(t, sp.Expr) for t in lib.terms_])


def test_feature_names_cache_follows_set_params_and_clone():
    lib = CandidateLibrary.polynomial(["x", "theta"], angles=["theta"], degree=2)
    names = lib.get_feature_names_out()
    assert names.tolist() == [str(t) for t in lib.terms_]
    names[0] = "changed"  # each call returns a new array
    assert lib.get_feature_names_out()[0] == str(lib.terms_[0])
    lib.set_params(degree=3)  # rebuilt: the names of the new terms
    assert lib.get_feature_names_out().tolist() == [str(t) for t in lib.terms_]
    assert len(lib.get_feature_names_out()) == len(lib) > len(names)
    copy = clone(lib).set_params(angles=None, raw_angles=True)
    assert copy.get_feature_names_out().tolist() == [str(t) for t in copy.terms_]
    assert "cos(theta)" in lib.get_feature_names_out().tolist()
    assert "cos(theta)" not in copy.get_feature_names_out().tolist()


def test_dependent_terms_name_their_combination():
    """The removal message gives the combination of earlier kept columns (one
    triangular solve of the Gram-Schmidt basis, the same text as a least-squares fit
    of the kept columns gave)."""
    lib = CandidateLibrary.from_terms(
        ["x", "theta"],
        ["x_dot**2", "cos(theta)", "theta_dot**2", "0.5*x_dot**2 - 3*cos(theta)"],
    )
    assert lib.removed_ == [
        (
            "0.5*x_dot**2 - 3*cos(theta)",
            "dependent: its Euler-Lagrange column equals +0.5*[x_dot**2] "
            "-3*[cos(theta)]",
        )
    ]
    angles = ["theta1", "theta2"]
    lib = CandidateLibrary.polynomial(angles, angles=angles, degree=4)
    assert len(lib) == 128 and len(lib.candidates_) == 209
    assert lib.removed_[-1] == (
        "cos(theta2)**4",
        "dependent: its Euler-Lagrange column equals -2*[sin(theta2)**2] "
        "+1*[sin(theta2)**4]",
    )
