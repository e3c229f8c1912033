"""lagsindy.diagnose: the residual diagnosis finds undeclared effects, adds nothing
where there is none, reports, plots and bootstraps (issue 5 acceptance)."""

import numpy as np
import pytest
import sympy as sp

from lagsindy import CandidateLibrary, LagrangianSINDy, diagnose
from lagsindy.systems import (
    cart_pendulum,
    double_pendulum,
    make_dataset,
    single_pendulum,
)


def _drag_pendulum(c):
    system = single_pendulum()
    v = sp.Symbol("theta_dot", real=True)
    system.dissipation = sp.Float(c) * sp.Abs(v) ** 3 / 3
    system.name = f"single pendulum (quadratic drag {c})"
    return system


def _fit_and_diagnose(system, *, n=20, duration=4.0, noise=0.0, library=None, **fit_kw):
    data = make_dataset(
        system,
        n_trajectories=n,
        duration=duration,
        excitation="sincos",
        noise=noise,
        protocol="paper",
        random_state=0,
    )
    est = LagrangianSINDy(library or system.paper_library(), **fit_kw)
    est.fit(data.X, data.tau, groups=data.groups)
    return diagnose(est, data.X, data.tau, groups=data.groups), data


@pytest.mark.parametrize(
    "system, effect, value, rel",
    [
        # rel: about 5x the measured relative error of the coefficient
        (
            double_pendulum().with_damping(viscous={"theta1": 0.3}),
            "viscous(theta1)",
            0.3,
            1.1e-5,  # measured 2.2e-6
        ),
        # measured 2.7e-3
        (cart_pendulum().with_damping(coulomb={"x": 0.2}), "coulomb(x)", 0.2, 0.014),
        (_drag_pendulum(0.1), "drag(theta)", 0.1, 3e-7),  # measured 5.6e-8
    ],
    ids=["double-viscous", "cart-coulomb", "single-drag"],
)
def test_diagnosis_names_the_effect_and_fixes_the_model(system, effect, value, rel):
    report, _ = _fit_and_diagnose(system)
    first = report.steps[0]
    assert first.candidate.name == effect  # right kind, right coordinate, first
    assert first.coefficient == pytest.approx(value, rel=rel)
    assert first.explained > 0.999  # measured 0.99979 (cart-coulomb), 1 - 1e-7 others
    # measured 69 (cart-coulomb), 2.8e3 (double-viscous), 2.1e6 (single-drag)
    assert report.heldout_error_before / first.heldout_error >= 30
    assert report.effects == [effect]  # nothing spurious after it


@pytest.mark.parametrize("noise", [0.0, 0.01])
@pytest.mark.parametrize(
    "factory", [single_pendulum, cart_pendulum], ids=["single", "cart"]
)
def test_no_false_positive_without_an_undeclared_effect(factory, noise):
    report, _ = _fit_and_diagnose(factory(), noise=noise)
    assert report.steps == []
    assert report.final is report.initial


@pytest.mark.slow  # ~20 s of the default suite's 5-minute budget
def test_no_false_positive_weak_form_double_pendulum():
    report, _ = _fit_and_diagnose(
        double_pendulum(), noise=0.01, formulation="weak", dt=0.01
    )
    assert report.steps == []


@pytest.mark.slow  # ~20 s of the default suite's 5-minute budget
def test_noisy_damping_found_with_weak_form():
    system = double_pendulum().with_damping(viscous={"theta1": 0.3})
    report, _ = _fit_and_diagnose(system, noise=0.01, formulation="weak", dt=0.01)
    assert report.effects == ["viscous(theta1)"]
    assert report.steps[0].coefficient == pytest.approx(0.3, rel=0.05)


def test_effect_that_worsens_a_held_out_trajectory_is_not_added():
    """Damping in two of three trajectories (one fold each) explains most of the
    pooled held-out residual (measured 78 %) but predicts the undamped trajectory
    worse: neither the joint revision nor the forward search may keep it (both
    require every fold to improve)."""
    parts = [
        make_dataset(
            single_pendulum().with_damping(viscous={"theta": c})
            if c
            else single_pendulum(),
            n_trajectories=1,
            duration=5.0,
            excitation="sincos",
            random_state=k,
        )
        for k, c in enumerate([0.0, 0.2, 0.2])
    ]
    X = np.vstack([p.X for p in parts])
    tau = np.vstack([p.tau for p in parts])
    groups = np.repeat([0, 1, 2], [len(p.X) for p in parts])
    lib = CandidateLibrary.from_terms(["theta"], ["theta_dot**2", "cos(theta)"])
    est = LagrangianSINDy(lib).fit(X, tau, groups=groups)
    report = diagnose(est, X, tau, groups=groups, catalogue=("viscous",))
    assert report.effects == []
    assert report.final is report.initial
    top = report.rankings[0].iloc[0]
    assert top["term"] == "viscous(theta)" and not top["every_fold"]
    assert top["explained"] > 0.5  # measured 0.78: not rejected for its share
    assert "every fold better" in report.stop_reason


def test_missing_conservative_term():
    """A spring on the cart, with a library that has no x**2: found as a term."""
    q = sp.symbols("x theta x_dot theta_dot", real=True)
    system = cart_pendulum()
    system.lagrangian = system.lagrangian - 0.5 * q[0] ** 2
    system.__dict__.pop("_equations", None)
    system.__dict__.pop("_compiled", None)
    lib = CandidateLibrary.from_terms(
        ["x", "theta"],
        [
            "x_dot**2",
            "theta_dot**2",
            "x_dot*theta_dot*cos(theta)",
            "cos(theta)",
            "theta_dot**2*cos(theta)",
            "x_dot**2*cos(theta)",
        ],
    )
    report, _ = _fit_and_diagnose(system, library=lib)
    assert report.effects[0] == "x**2"
    assert report.steps[0].coefficient == pytest.approx(-0.5, rel=3e-7)  # 5.7e-8
    assert report.heldout_error_before / report.steps[0].heldout_error >= 10


def test_input_gain_error_on_one_of_two_inputs():
    system = double_pendulum()
    data = make_dataset(
        system, n_trajectories=20, duration=4.0, excitation="sincos", random_state=3
    )
    measured = data.tau.copy()
    measured[:, 1] /= 0.8  # the second actuator delivers 80 % of the recorded torque
    est = LagrangianSINDy(system.paper_library()).fit(data.X, measured)
    report = diagnose(est, data.X, measured, groups=data.groups)
    assert report.effects[0] == "gain(theta2)"
    # measured 3.9e-6 relative
    assert 1 + report.steps[0].coefficient == pytest.approx(0.8, rel=2e-5)


def test_passive_diagnosis_in_case_III():
    system = single_pendulum().with_damping(viscous={"theta": 0.2})
    data = make_dataset(
        system, n_trajectories=20, duration=4.0, excitation=None, random_state=4
    )
    est = LagrangianSINDy(system.paper_library(), fixed_term="theta_dot**2").fit(data.X)
    report = diagnose(est, data.X, groups=data.groups)
    assert report.passive and report.effects == ["viscous(theta)"]
    # scale fixed by theta_dot**2 = 1 (true 0.5): damping 0.2 becomes 0.4
    assert report.steps[0].coefficient == pytest.approx(0.4, rel=3.2e-4)  # 6.3e-5
    assert report.final.score(data.X) > 0.99999


def test_report_text_table_and_plot(tmp_path):
    system = double_pendulum().with_damping(viscous={"theta1": 0.3})
    report, data = _fit_and_diagnose(system, n=12, duration=3.0)
    text = str(report)
    # no units given: none invented (issue 14 item 5)
    assert "viscous damping" in text and "per unit of theta1_dot" in text
    assert "N*m*s/rad" not in text
    units = {"theta1": ("rad", "N*m"), "theta2": ("rad", "N*m")}
    with_units = diagnose(
        report.initial, data.X, data.tau, groups=data.groups, units=units
    )
    assert "N*m*s/rad" in str(with_units)
    assert "held-out" in text and "final model" in text and "D = " in text
    frame = report.to_frame()
    assert list(frame.term) == ["viscous(theta1)"]
    path = tmp_path / "diagnosis.png"
    fig = report.plot(path)
    assert path.stat().st_size > 1000 and len(fig.axes) == 1


def test_diagnose_errors(single_active):
    est = LagrangianSINDy(single_pendulum().paper_library()).fit(
        single_active.X, single_active.tau
    )
    with pytest.raises(ValueError, match="kind of data"):
        diagnose(est, single_active.X)
    with pytest.raises(ValueError, match="min_explained"):
        diagnose(est, single_active.X, single_active.tau, min_explained=2)
    with pytest.raises(ValueError, match="groups"):
        diagnose(est, single_active.X, single_active.tau, groups=[0, 1])
    with pytest.raises(ValueError, match="unknown candidate kind"):
        diagnose(
            est,
            single_active.X,
            single_active.tau,
            groups=single_active.groups,
            catalogue=("magic",),
        )


# ------------------------------------------------------------- bootstrap intervals
def _noisy_force_pendulum():
    system = single_pendulum().with_damping(viscous={"theta": 0.2})
    data = make_dataset(
        system, n_trajectories=10, duration=2.0, excitation="sincos", random_state=0
    )
    rng = np.random.default_rng(1)
    tau = data.tau + 0.05 * rng.standard_normal(data.tau.shape)
    return system, data, tau


def test_diagnose_with_bootstrap_intervals(tmp_path, capsys):
    """Noise on the forces: the effect and the Lagrangian terms get intervals that
    hold the truth, are narrow, and appear in the table, the frame and the CLI."""
    system, data, tau = _noisy_force_pendulum()
    est = LagrangianSINDy(system.paper_library(), formulation="strong")
    est.fit(data.X, tau, groups=data.groups)
    report = diagnose(
        est, data.X, tau, groups=data.groups, bootstrap=20, random_state=0
    )
    assert report.effects == ["viscous(theta)"]
    step = report.steps[0]
    assert step.low < step.coefficient < step.high
    assert step.low < 0.2 < step.high
    # measured half-width 0.9 % of 0.2 (12 trajectories: 0.6 %)
    assert 0.001 * 0.2 < (step.high - step.low) / 2 < 0.03 * 0.2
    frame = report.to_frame()
    assert {"low", "high"} <= set(frame.columns)
    assert frame.loc[0, "low"] == step.low and frame.loc[0, "high"] == step.high
    boot = report.bootstrap.to_frame().set_index("term")
    assert boot.loc["viscous(theta)", "low"] == step.low  # joined on the term name
    cos = boot.loc["cos(theta)"]
    assert cos.low < cos.coefficient < cos.high
    assert cos.high - cos.low < 0.02 * 9.81  # measured 1.1 %
    text = str(report)
    assert "95% interval" in text and "bootstrap of the final model" in text
    with pytest.raises(ValueError, match="bootstrap"):
        diagnose(est, data.X, tau, groups=data.groups, bootstrap=1)

    from lagsindy.cli import main

    frame_csv = data.to_frame()
    frame_csv[[c for c in frame_csv.columns if c.startswith("tau")]] = tau
    csv = tmp_path / "data.csv"
    frame_csv.to_csv(csv, index=False)
    path = tmp_path / "model.json"
    est.save(path)
    code = main(
        ["diagnose", str(csv), "--model", str(path), "--bootstrap", "10", "--quiet"]
    )
    assert code == 0
    out = capsys.readouterr().out
    assert "95% interval" in out and "bootstrap of the final model" in out
