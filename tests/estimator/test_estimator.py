"""The LagrangianSINDy estimator's API: data frames and coordinate names,
predictions against the model's equations, unpenalized terms, the staged path and
its verbose output, custom libraries, and reused dissipation terms."""

import numpy as np
import pandas as pd
import pytest
import sympy as sp

from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy.solvers import StagedFISTA
from lagsindy.systems import cart_pendulum, make_dataset, single_pendulum


def _learned(est):
    names = est.term_names_
    return {names[k]: est.coef_[k] for k in np.flatnonzero(est.coef_)}


def test_dataframe_input_uses_column_names(cart_active):
    df = pd.DataFrame(cart_active.X, columns=cart_active.feature_names)
    shuffled = df[df.columns[::-1]].assign(extra=1.0)
    est = LagrangianSINDy(cart_pendulum().paper_library()).fit(
        shuffled, cart_active.tau
    )
    assert list(est.feature_names_in_) == cart_active.feature_names
    ref = LagrangianSINDy(cart_pendulum().paper_library()).fit(
        cart_active.X, cart_active.tau
    )
    np.testing.assert_allclose(est.coef_, ref.coef_, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(
        est.predict(shuffled), ref.predict(cart_active.X), atol=1e-10
    )


def test_default_library_takes_coordinates_from_dataframe(single_active):
    df = pd.DataFrame(single_active.X, columns=["phi", "phi_dot", "phi_ddot"])
    est = LagrangianSINDy().fit(df, single_active.tau[:, 0])
    assert est.coordinates_ == ["phi"]
    learned = _learned(est)
    assert set(learned) == {"phi_dot**2", "cos(phi)"}
    assert est.predict(df).shape == (len(df),)  # 1-D tau in, 1-D predictions out


def test_numpy_input_without_library_names_coordinates_q():
    data = make_dataset(
        single_pendulum(), n_trajectories=10, excitation="paper", random_state=6
    )
    est = LagrangianSINDy().fit(data.X, data.tau)
    assert est.coordinates_ == ["q0"]
    assert "cos(q0)" in _learned(est)


def test_predictions_agree_with_model_equations(cart_active):
    est = LagrangianSINDy(cart_pendulum().paper_library(), formulation="strong").fit(
        cart_active.X, cart_active.tau
    )
    X = cart_active.X[:500]
    n = 2
    forces = est.model_.inverse_dynamics(X[:, :n], X[:, n : 2 * n], X[:, 2 * n :])
    np.testing.assert_allclose(est.predict(X), forces, rtol=1e-9, atol=1e-9)
    acc = est.predict_acceleration(X, cart_active.tau[:500])
    # measured: 3.1e-10 relative, 2.7e-12 absolute
    np.testing.assert_allclose(acc, X[:, 2 * n :], rtol=2e-9, atol=1.5e-11)
    assert isinstance(est.lagrangian_, sp.Expr)
    assert est.equation(3).startswith("L = ")


def test_unpenalized_terms_are_kept(single_active):
    lib = single_pendulum().paper_library()
    est = LagrangianSINDy(lib, unpenalized=["theta**2"]).fit(
        single_active.X, single_active.tau
    )
    # an unpenalised term is never thresholded: it stays in the support, with the
    # value the data give it (near zero here, as theta**2 is not in the truth)
    k = lib.index("theta**2")
    assert est.support_[k] and abs(est.coef_[k]) < 1e-6


def test_verbose_prints_stages(single_active, capsys):
    LagrangianSINDy(single_pendulum().paper_library(), verbose=1).fit(
        single_active.X, single_active.tau
    )
    out = capsys.readouterr().out
    assert "stage 1" in out and "lam=" in out


def test_stages_record_the_path(cart_active):
    est = LagrangianSINDy(
        cart_pendulum().paper_library(), solver=StagedFISTA(tol=0.0, max_stages=3)
    ).fit(cart_active.X, cart_active.tau)
    assert len(est.stages_) == 3
    lams = [st.lam for st in est.stages_]
    assert lams[1] == pytest.approx(lams[0] / 10) and lams[2] == pytest.approx(
        lams[1] / 10
    )
    assert est.stages_[0].coef.shape == est.coef_.shape
    assert est.n_iter_ == sum(st.n_iter for st in est.stages_)


def test_custom_library_and_user_alpha(single_active):
    lib = CandidateLibrary.from_terms(
        ["theta"], ["theta_dot**2", "cos(theta)", "theta**2", "theta_dot**2*cos(theta)"]
    )
    est = LagrangianSINDy(lib, alpha=0.01).fit(single_active.X, single_active.tau)
    assert set(_learned(est)) == {"theta_dot**2", "cos(theta)"}


def test_dissipation_terms_are_built_once_per_parameters(monkeypatch):
    """A refit with an equal dissipation library reuses its built terms (diagnose
    refits several times); other parameters build again, and the fits agree."""
    import lagsindy.dissipation as dissipation_module
    import lagsindy.pipeline as estimator_module
    from lagsindy import DissipationLibrary
    from lagsindy.systems import cart_pendulum, make_dataset

    monkeypatch.setattr(estimator_module, "_BUILT_DISSIPATION", {})
    calls = []
    original = dissipation_module.make_term

    def counted(*args, **kwargs):
        calls.append(args[0])
        return original(*args, **kwargs)

    monkeypatch.setattr(dissipation_module, "make_term", counted)
    system = cart_pendulum()
    data = make_dataset(system, n_trajectories=3, excitation="sincos", random_state=0)
    fits = []
    for kinds in (["viscous"], ["viscous"], ["viscous", "coulomb"]):
        est = LagrangianSINDy(
            system.paper_library(), dissipation=DissipationLibrary(kinds=kinds)
        )
        fits.append(est.fit(data.X, data.tau, groups=data.groups))
    assert calls == ["viscous", "viscous"] + ["viscous"] * 2 + ["coulomb"] * 2
    np.testing.assert_array_equal(fits[0].coef_, fits[1].coef_)
    names = [t.name for t in fits[1].dissipation_library_.terms_]
    assert names == ["viscous(x)", "viscous(theta)"]


def test_verbose_announces_a_restart_only_when_one_follows(capsys):
    """The last start of the path was announced as restarting, with nothing after."""
    data = make_dataset(
        cart_pendulum(), n_trajectories=20, duration=5.0, excitation="sincos",
        noise=0.01, protocol="paper", random_state=0,
    )  # fmt: skip
    LagrangianSINDy(cart_pendulum().paper_library(), verbose=1).fit(
        data.X, data.tau, groups=data.groups
    )
    lines = capsys.readouterr().out.splitlines()
    restarts = [i for i, line in enumerate(lines) if "restarting the path" in line]
    assert restarts  # measured: 1
    for i in restarts:
        assert "stage 1: lam=" in lines[i + 1]
