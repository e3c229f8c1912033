"""LagrangianSINDy on URDF libraries: base parameters, friction kinds, consistency,
the spring kind, est.to_urdf and the parameter table (no pinocchio needed)."""

import warnings

import numpy as np
import pytest
import torch
from _robot_fit_data import planar_data, two_sines

from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy
from lagsindy.evaluator import TermEvaluator, TorchTerms, subset_terms
from lagsindy.robots import (
    FRICTION_KINDS,
    ROBOT_CATALOGUE,
    example_urdf,
    feasibility,
    parameter_table,
)
from lagsindy.robots import consistency as cons

ARM7_JOINTS = [f"joint{i}" for i in range(1, 8)]


def _fit(data, *, kinds=FRICTION_KINDS, form="strong", strict=True, **lib_kw):
    lib = CandidateLibrary.from_urdf(example_urdf("planar2"), **lib_kw)
    est = LagrangianSINDy(
        lib, dissipation=DissipationLibrary(list(kinds)), formulation=form
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error" if strict else "ignore", UserWarning)
        return est.fit(data.X, data.tau)


@pytest.fixture(scope="module")
def planar():
    return planar_data()


@pytest.fixture(scope="module")
def strong_fit(planar):
    return _fit(planar)


def test_fit_regresses_on_base_parameters(strong_fit, planar):
    lib = strong_fit.library_
    assert lib.terms_ == [
        "mx_upper_arm",
        "mz_upper_arm",
        "Iyy_upper_arm",
        "mx_forearm",
        "mz_forearm",
        "Iyy_forearm",
        "Ia_elbow",
    ]
    assert lib.base_.labels[2] == "Iyy_upper_arm + 0.2025*m_forearm + Ia_shoulder"
    beta = lib.base_.values(planar.truth)
    # noise-free data, a model the library contains: measured 2.5e-12
    np.testing.assert_allclose(strong_fit.coef_, beta, rtol=0, atol=1e-10)


def test_friction_kinds_per_joint(strong_fit, planar):
    names = [t.name for t in strong_fit.dissipation_terms_]
    coef = dict(zip(names, strong_fit.dissipation_coef_))
    for j, joint in enumerate(["shoulder", "elbow"]):
        assert coef[f"viscous({joint})"] == pytest.approx(planar.viscous[j], rel=1e-8)
        assert coef[f"coulomb({joint})"] == pytest.approx(planar.coulomb[j], rel=1e-8)
        # the bias force is +1 per unit coefficient on the force side: -offset
        # (measured 1.1e-7 relative after the consistent refit)
        assert coef[f"bias({joint})"] == pytest.approx(-planar.offset[j], rel=1e-5)


def test_weak_form_fit(planar):
    est = _fit(planar, form="weak")
    assert est.formulation_ == "weak"
    beta = est.library_.base_.values(planar.truth)
    # measured 8.7e-7 of the largest base parameter
    assert np.abs(est.coef_ - beta).max() <= 5e-6 * np.abs(beta).max()
    assert est.score(planar.X, planar.tau) > 1 - 1e-9


def test_base_parameters_unpenalized_by_default():
    lib = CandidateLibrary.from_urdf(example_urdf("planar2")).regression_library()
    assert lib.unpenalized_ == lib.terms_
    penalized = CandidateLibrary.from_urdf(example_urdf("planar2"), penalize=True)
    assert penalized.regression_library().unpenalized_ == []


def test_penalty_acts_on_friction_only(planar):
    """The L1 weights: 0 on the base parameters, 1 on the dissipation candidates."""
    lib = CandidateLibrary.from_urdf(example_urdf("planar2"))
    est = LagrangianSINDy(lib, dissipation=DissipationLibrary(["viscous", "bias"]))
    _, _, setup = est._setup(planar.X, planar.tau, est.get_params(deep=False))
    np.testing.assert_array_equal(setup.penalty(), [0.0] * 7 + [1.0] * 4)


def test_penalize_true_thresholds_base_parameters(planar):
    lib = CandidateLibrary.from_urdf(example_urdf("planar2"), penalize=True)
    est = LagrangianSINDy(lib, dissipation=DissipationLibrary(["viscous"]), lam=0.9)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(planar.X, planar.tau)
    assert np.sum(est.coef_ != 0) < len(est.coef_)


# ------------------------------------------------------------------ consistency
@pytest.fixture(scope="module")
def inconsistent():
    """Torques of a negative rotor inertia on the elbow: base parameters outside the
    consistent set."""
    return planar_data(armature=(0.02, -0.02))


def test_consistent_by_default(inconsistent):
    est = _fit(inconsistent)
    lib = est.library_
    pi = lib.link_parameters(est.coef_)
    assert feasibility(pi, 2).min() >= -1e-12
    assert pi[-2:].min() >= 0.0
    # the constrained base parameters are those of the link parameters
    np.testing.assert_allclose(lib.base_.values(pi), est.coef_, atol=1e-9)
    ia = est.coef_[lib.terms_.index("Ia_elbow")]
    assert ia >= 0.0 and ia < 1e-3  # the bound holds: measured 0 (true -0.02)


def test_unconstrained_fit_reports_violation(inconsistent):
    with pytest.warns(UserWarning, match="not physically consistent"):
        est = _fit_quiet_except_violation(inconsistent)
    ia = est.coef_[est.library_.terms_.index("Ia_elbow")]
    assert ia == pytest.approx(-0.02, rel=1e-6)
    assert est.library_.violation_ > cons.VIOLATION_TOL


def _fit_quiet_except_violation(data):
    lib = CandidateLibrary.from_urdf(example_urdf("planar2"), consistent=False)
    est = LagrangianSINDy(
        lib, dissipation=DissipationLibrary(list(FRICTION_KINDS)), formulation="strong"
    )
    return est.fit(data.X, data.tau)


@pytest.mark.parametrize("factor, warns", [(0.999, False), (1.001, True)])
def test_violation_threshold_boundary(planar, monkeypatch, factor, warns):
    monkeypatch.setattr(cons, "violation", lambda *a, **k: factor * cons.VIOLATION_TOL)
    lib = CandidateLibrary.from_urdf(example_urdf("planar2"), consistent=False)
    est = LagrangianSINDy(lib, dissipation=DissipationLibrary(["viscous"]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est.fit(planar.X, planar.tau)
    hit = any("not physically consistent" in str(w.message) for w in caught)
    assert hit is warns


def test_constrained_refit_keeps_a_consistent_fit(strong_fit, planar):
    """A consistent truth: the constraint costs nothing (objective measured 0)."""
    lib = strong_fit.library_
    pi = lib.link_parameters(strong_fit.coef_)
    assert feasibility(pi, 2).min() > 0
    np.testing.assert_allclose(
        strong_fit.coef_, lib.base_.values(planar.truth), atol=1e-9
    )


# ------------------------------------------------------------------ spring, diagnose
def test_spring_kind_registered():
    from lagsindy.force_kinds import get

    kind = get("spring")
    assert not kind.dissipative
    term = DissipationLibrary(["spring"], coordinates=["x"]).build().terms_[0]
    assert str(term.forces[0]) == "-x"


def test_spring_fitted(planar):
    data = planar_data(spring=(1, 3.0, 0.2))
    est = _fit(data, kinds=list(FRICTION_KINDS) + ["spring"])
    coef = dict(zip([t.name for t in est.dissipation_terms_], est.dissipation_coef_))
    assert coef["spring(elbow)"] == pytest.approx(3.0, rel=1e-7)
    # tau = offset + k (q - rest): the bias coefficient is -(offset - k rest) = 0.65
    assert coef["bias(elbow)"] == pytest.approx(0.05 + 0.6, rel=1e-6)
    assert coef["spring(shoulder)"] == pytest.approx(0.0, abs=1e-8)


def test_diagnose_finds_the_spring():
    from lagsindy import diagnose

    data = planar_data(spring=(1, 3.0, 0.0), duration=6.0)
    est = _fit(data, strict=False)  # (warns: the spring is missing)
    report = diagnose(est, data.X, data.tau, catalogue=["viscous", "spring"])
    # the spring first; the refit with it turns on the elbow's own friction terms
    assert report.effects[0] == "spring(elbow)"
    assert report.steps[0].how in ("added", "joint")
    assert report.steps[0].coefficient == pytest.approx(3.0, rel=1e-3)


def test_diagnose_finds_coupled_joints_and_no_delay():
    """A damper between the joints on delay-free data: its force lags like a
    delayed input's, and diagnose took it for a -8.9 ms delay (and viscous friction
    12 % off) until a delay had to explain more than the dissipative candidates."""
    from lagsindy import diagnose

    lib = CandidateLibrary.from_urdf(example_urdf("planar2"))
    t, q, qd, qdd = two_sines(6.0)
    tau = lib.euler_lagrange_columns(q, qd, qdd) @ lib.nominal_ + [0.6, 0.3] * qd
    tau += 0.8 * (qd[:, :1] - qd[:, 1:]) * [1.0, -1.0]
    tau += 0.01 * tau.std(0) * np.random.default_rng(0).standard_normal(tau.shape)
    X = np.hstack([q, qd, qdd])
    est = LagrangianSINDy(
        lib, dissipation=DissipationLibrary(["viscous"]), formulation="strong"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the fit warns: something is missing
        est.fit(X, tau)
        report = diagnose(est, X, tau, catalogue=[*ROBOT_CATALOGUE, "relative"])
    assert "delay" not in report.effects
    assert report.input_delays == {}  # nor a delay per joint ("joint_delay")
    final = dict(
        zip(
            [f.name for f in report.final.dissipation_terms_],
            report.final.dissipation_coef_,
        )
    )
    # measured: 0.8000, 0.595, 0.301
    assert final["relative(shoulder,elbow)"] == pytest.approx(0.8, rel=5e-3)
    assert final["viscous(shoulder)"] == pytest.approx(0.6, rel=0.02)
    assert final["viscous(elbow)"] == pytest.approx(0.3, rel=0.02)


def test_conservative_candidates_refused_for_robots(strong_fit, planar):
    from lagsindy import diagnose

    with pytest.raises(ValueError, match="ROBOT_CATALOGUE"):
        diagnose(strong_fit, planar.X, planar.tau, catalogue=["conservative"])


# ------------------------------------------------------------------ out
def test_to_urdf_round_trip(strong_fit, tmp_path):
    path = strong_fit.to_urdf(tmp_path / "identified.urdf")
    back = CandidateLibrary.from_urdf(path)
    lib = strong_fit.library_
    # the written link parameters reproduce the fitted base parameters (rotor
    # inertias are a comment: add the fitted ones back)
    pi = back.nominal_.copy()
    pi[-2:] = lib.link_parameters(strong_fit.coef_)[-2:]
    np.testing.assert_allclose(lib.base_.values(pi), strong_fit.coef_, atol=1e-9)
    np.testing.assert_allclose(back.tree_.damping, [0.6, 0.3], rtol=1e-8)
    np.testing.assert_allclose(back.tree_.friction, [0.4, 0.2], rtol=1e-8)


def test_to_urdf_needs_a_urdf_library(tmp_path):
    from lagsindy.systems import make_dataset, single_pendulum

    data = make_dataset(single_pendulum(), n_trajectories=2, duration=1.0)
    est = LagrangianSINDy(single_pendulum().paper_library()).fit(data.X, data.tau)
    with pytest.raises(ValueError, match="from_urdf"):
        est.to_urdf(tmp_path / "x.urdf")


def test_model_file_and_pickle(strong_fit, tmp_path, monkeypatch):
    """(Model files of robot fits: tests/robots/test_robot_files.py.)"""
    import pickle

    monkeypatch.setenv("LAGSINDY_CACHE_DIR", str(tmp_path / "cache"))
    loaded = LagrangianSINDy.load(strong_fit.save(tmp_path / "m.json"))
    np.testing.assert_array_equal(loaded.coef_, strong_fit.coef_)
    back = pickle.loads(pickle.dumps(strong_fit))
    np.testing.assert_array_equal(back.coef_, strong_fit.coef_)


def test_parameter_table(strong_fit):
    table = parameter_table(strong_fit)
    assert list(table.columns) == ["parameter", "combination", "value", "urdf"]
    assert table.parameter.tolist() == strong_fit.library_.terms_
    np.testing.assert_array_equal(table.value, strong_fit.coef_)


def test_parameter_table_with_bootstrap(planar):
    from lagsindy import bootstrap

    est = _fit(planar)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = bootstrap(est, planar.X, planar.tau, n_resamples=8, random_state=0)
    table = parameter_table(est, report)
    assert np.all(table.low <= table.value + 1e-9)
    assert np.all(table.high >= table.value - 1e-9)


# ------------------------------------------------------------------ evaluator seams
def test_base_terms_fast_paths_equal_autograd():
    lib = CandidateLibrary.from_urdf(example_urdf("arm7"), ARM7_JOINTS)
    terms = lib.regression_library().torch_terms()
    rng = np.random.default_rng(1)
    q, qd, qdd = (torch.as_tensor(rng.uniform(-1, 1, (4, 7))) for _ in range(3))
    fast = TermEvaluator(lib.coordinates_, terms)
    slow = TermEvaluator(lib.coordinates_, TorchTerms(terms.names, terms.fn))
    # measured 4e-15
    for a, b in zip(fast.parts(q, qd), slow.parts(q, qd)):
        np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-12)
    np.testing.assert_allclose(
        fast.columns(q, qd, qdd).numpy(), slow.columns(q, qd, qdd).numpy(), atol=1e-12
    )


def test_subset_terms_of_a_plain_term_function():
    terms = TorchTerms(
        ["a", "b", "c"], lambda q, qd: torch.stack([q[0], qd[0], q[0] ** 2])
    )
    sub = subset_terms(terms, [2, 0])
    assert sub.names == ["c", "a"]
    x = torch.tensor([3.0], dtype=torch.float64)
    assert sub.fn(x, x).tolist() == [9.0, 3.0]
    assert subset_terms(["x", "y"], [1]) == ["y"]
