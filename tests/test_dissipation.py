import numpy as np
import pytest
import sympy as sp

from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy
from lagsindy.dissipation import make_term, reduce_forces
from lagsindy.formulation import WeakForm
from lagsindy.systems import (
    cart_pendulum,
    double_pendulum,
    make_dataset,
    single_pendulum,
)


def test_terms_have_the_documented_forces():
    coords = ["x", "y"]
    xd, yd = sp.symbols("x_dot y_dot", real=True)
    viscous = make_term("viscous", "x", coords)
    assert viscous.forces == (-xd, 0) and viscous.rayleigh == xd**2 / 2
    rel = make_term("relative", ("x", "y"), coords)
    assert sp.simplify(rel.forces[0] - (yd - xd)) == 0
    assert sp.simplify(rel.forces[1] - (xd - yd)) == 0
    drag = make_term("drag", "y", coords)
    f = sp.lambdify(yd, drag.forces[1])
    assert f(2.0) == -4.0 and f(-2.0) == 4.0
    # forces are -dD/dqdot for every Rayleigh term (numerically, away from 0)
    for term in (viscous, rel, drag):
        for v in (0.7, -1.3):
            for i, s in enumerate((xd, yd)):
                want = -sp.diff(term.rayleigh, s).subs({xd: v, yd: -0.4})
                assert float(term.forces[i].subs({xd: v, yd: -0.4})) == pytest.approx(
                    float(want)
                )
    coulomb = make_term("coulomb", "x", coords, eps=0.05)
    assert sp.simplify(coulomb.forces[0] + sp.tanh(xd / 0.05)) == 0
    assert make_term("bias", "y", coords).forces == (0, 1)


def test_library_builds_names_and_rejects_bad_specs():
    lib = DissipationLibrary(
        ["viscous", "relative"], coordinates=["a", "b", "c"]
    ).build()
    assert list(lib.get_feature_names_out()) == [
        "viscous(a)",
        "viscous(b)",
        "viscous(c)",
        "relative(a,b)",
        "relative(a,c)",
        "relative(b,c)",
    ]
    extra = DissipationLibrary((), coordinates=["a"], terms=[("drag", "a")]).build()
    assert [t.name for t in extra.terms_] == ["drag(a)"]
    with pytest.raises(ValueError, match="unknown dissipation kinds"):
        DissipationLibrary(["sticky"], coordinates=["a"]).build()
    with pytest.raises(ValueError, match="not one of the coordinates"):
        DissipationLibrary((), coordinates=["a"], terms=[("viscous", "z")]).build()
    with pytest.raises(ValueError, match="two different coordinates"):
        DissipationLibrary(
            (), coordinates=["a"], terms=[("relative", ("a", "a"))]
        ).build()


def test_constant_force_duplicating_a_linear_potential_is_removed():
    lagrangian = CandidateLibrary.polynomial(["x"], degree=2).terms_  # contains x
    forces = DissipationLibrary(["viscous", "bias"], coordinates=["x"]).build().terms_
    kept, removed = reduce_forces(lagrangian, forces, ["x"])
    assert [t.name for t in kept] == ["viscous(x)"]
    assert removed[0][0] == "bias(x)" and "linear potential" in removed[0][1]


def test_reduction_is_reused_for_the_same_candidates(monkeypatch):
    from lagsindy import dissipation, euler_lagrange

    lagrangian = CandidateLibrary.polynomial(["x"], degree=2).terms_  # contains x
    forces = DissipationLibrary(["viscous", "bias"], coordinates=["x"]).build().terms_
    first = reduce_forces(lagrangian, forces, ["x"])

    def no_operator(*args, **kwargs):
        raise AssertionError("the reduction ran again")

    monkeypatch.setattr(euler_lagrange, "EulerLagrangeOperator", no_operator)
    assert reduce_forces(lagrangian, forces, ["x"]) == first
    # Other Lagrangian terms (no linear potential) are another reduction: the bias
    # force then stays.
    monkeypatch.undo()
    without_x = [t for t in lagrangian if str(t) != "x"]
    kept, removed = reduce_forces(without_x, forces, ["x"])
    assert [t.name for t in kept] == ["viscous(x)", "bias(x)"] and removed == []
    assert len(dissipation._REDUCED) <= dissipation._REDUCED_SIZE


@pytest.mark.parametrize(
    "system, effect, value",
    [
        (
            double_pendulum().with_damping(viscous={"theta1": 0.3}),
            "viscous(theta1)",
            0.3,
        ),
        (cart_pendulum().with_damping(coulomb={"x": 0.2}), "coulomb(x)", 0.2),
    ],
)
def test_joint_fit_recovers_dissipation(system, effect, value):
    data = make_dataset(system, n_trajectories=20, excitation="sincos", random_state=0)
    # Exact derivatives: the strong form is exact to rounding (the weak form's
    # quadrature gives about 5e-6 here), which the tolerances below test.
    est = LagrangianSINDy(
        system.paper_library(),
        dissipation=DissipationLibrary(["viscous", "coulomb", "drag"]),
        formulation="strong",
    ).fit(data.X, data.tau)
    table = est.coef_table()
    found = table[(table.kind == "dissipation") & table.kept]
    assert list(found.term) == [effect]
    assert float(found.coefficient.iloc[0]) == pytest.approx(value, rel=1e-6)
    truth = system.true_coefficients(est.library_)
    np.testing.assert_allclose(est.coef_, truth, atol=1e-8)
    # the learned model simulates with its dissipation and tracks the truth
    x0 = data.initial_states[0]
    t = np.linspace(0, 3, 301)
    np.testing.assert_allclose(est.simulate(x0, t), system.simulate(x0, t), atol=1e-5)


def test_no_dissipation_found_in_undamped_data():
    system = single_pendulum()
    data = make_dataset(
        system,
        n_trajectories=20,
        excitation="sincos",
        noise=0.01,
        protocol="paper",
        random_state=1,
    )
    est = LagrangianSINDy(
        system.paper_library(),
        formulation=WeakForm(dt=0.01),
        dissipation=DissipationLibrary(["viscous", "coulomb", "drag"]),
    )
    est.fit(data.X, data.tau, groups=data.groups)
    assert not np.any(est.dissipation_coef_)
    assert est.dissipation_["D"] == 0 and all(
        f == 0 for f in est.dissipation_["forces"]
    )


def test_passive_case_III_with_damping():
    system = single_pendulum().with_damping(viscous={"theta": 0.2})
    data = make_dataset(system, n_trajectories=20, excitation=None, random_state=2)
    est = LagrangianSINDy(
        system.paper_library(),
        fixed_term="theta_dot**2",
        dissipation=DissipationLibrary(["viscous"]),
        formulation="strong",  # exact derivatives: exact to rounding (weak: 7e-5)
    ).fit(data.X)
    # L / 0.5 = theta_dot**2 + 19.62 cos(theta), D / 0.5 = 0.4 * theta_dot**2 / 2
    assert est.dissipation_coef_[0] == pytest.approx(0.4, rel=1e-6)
    assert est.score(data.X) > 0.999999


def test_unpenalized_dissipation_names_and_errors(single_active):
    lib = single_pendulum().paper_library()
    est = LagrangianSINDy(
        lib, dissipation=DissipationLibrary(["viscous"]), unpenalized=["viscous(theta)"]
    ).fit(single_active.X, single_active.tau)
    # undamped data: kept at rounding level (measured 4.1e-9), never exactly 0
    assert 0 < abs(est.dissipation_coef_[0]) < 4e-8
    # weak damping (0.002) that the threshold drops when penalised is kept exactly
    damped = make_dataset(
        single_pendulum().with_damping(viscous={"theta": 0.002}),
        n_trajectories=10,
        excitation="paper",
        random_state=1,
    )
    kept = LagrangianSINDy(
        lib, dissipation=DissipationLibrary(["viscous"]), unpenalized=["viscous(theta)"]
    ).fit(damped.X, damped.tau)
    dropped = LagrangianSINDy(lib, dissipation=DissipationLibrary(["viscous"]))
    dropped.fit(damped.X, damped.tau)
    assert dropped.dissipation_coef_[0] == 0.0
    # measured relative error 2.2e-6
    assert kept.dissipation_coef_[0] == pytest.approx(0.002, rel=2e-5)
    with pytest.raises(ValueError, match="unpenalized"):
        LagrangianSINDy(
            lib,
            dissipation=DissipationLibrary(["viscous"]),
            unpenalized=["drag(theta)"],
        ).fit(single_active.X, single_active.tau)
    with pytest.raises(ValueError, match="coordinates"):
        LagrangianSINDy(
            lib, dissipation=DissipationLibrary(["viscous"], coordinates=["x"])
        ).fit(single_active.X, single_active.tau)
