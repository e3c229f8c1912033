"""The diagnosis of light and undriven links (issue #41 items 2 and 4): a degenerate
starting model is revised jointly, the report says how it relates to the fit's
warning, relative damping only between coordinates of one kind, a bootstrap that
cannot solve a resample is reported, not fatal.

The starting models are conservative fits (tests/diagnostics/conftest.py)."""

import re
import warnings

import numpy as np
import pytest

from lagsindy import LagrangianSINDy, bootstrap, diagnose
from lagsindy.diagnostics.catalogue import _catalogue, same_kind
from lagsindy.systems import cart_pendulum, double_pendulum, make_dataset
from tests._undriven import (
    CART_POLE_TERMS,
    TRUE_POLE_RATIO,
    chain_library,
    found_damping,
    light_pendulum_data,
    pole_ratio,
)


@pytest.fixture(scope="module")
def collapsed():
    """The conservative fit of a 0.02 kg pole under a damped cart: x_dot**2 alone
    (singular mass matrix along theta), with the fit's warning of missing damping."""
    from lagsindy.joint import conservative_fits

    _, data, _ = light_pendulum_data(0.01, 3.0)
    with warnings.catch_warnings(), conservative_fits():
        warnings.simplefilter("ignore")
        est = LagrangianSINDy(chain_library()).fit(data.X, data.tau, groups=data.groups)
    assert not est.mass_check_.ok and est.fitted_.unmodelled
    return est, data


def _quiet(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*args, **kwargs)


def test_a_degenerate_starting_model_is_revised_jointly(collapsed):
    """revise=False, yet the starting model cannot predict the pole's accelerations:
    the joint revision runs and finds the pole and the damping."""
    est, data = collapsed
    report = _quiet(diagnose, est, data.X, data.tau, groups=data.groups, revise=False)
    kept = {str(n) for n, c in zip(report.final.term_names_, report.final.coef_) if c}
    assert kept == set(CART_POLE_TERMS)
    # measured: ratio 0.99996 of l / 2g, viscous(x) 2.9995
    assert pole_ratio(report.final) == pytest.approx(TRUE_POLE_RATIO, rel=2e-4)
    assert found_damping(report.final) == pytest.approx(3.0, rel=1e-3)
    assert [s.how for s in report.steps] == ["joint"]  # step 1, not an addition
    text = str(report)
    assert "note: the starting model cannot predict accelerations" in text
    assert "revised jointly" in text


def test_the_undriven_coordinates_force_scale_is_the_final_models(collapsed):
    """The pole has no measured force and no term in the starting model: its
    residual was reported as 5e+300 % of a zero scale."""
    est, data = collapsed
    report = _quiet(diagnose, est, data.X, data.tau, groups=data.groups)
    assert np.all(report.force_rms > 0)
    after = report.residual_rms_after / report.force_rms
    assert after[1] < 0.05  # measured 0.007 (0.7 %)


def test_the_report_says_why_it_does_not_follow_the_fits_warning(collapsed):
    """The fit warned of viscous(x); a catalogue without damping cannot add it: the
    report says so instead of contradicting the warning silently."""
    est, data = collapsed
    report = _quiet(
        diagnose, est, data.X, data.tau, groups=data.groups, catalogue=["conservative"]
    )
    (note,) = [n for n in report.settings["notes"] if n.startswith("the fit warned")]
    # measured 2.99 (the paper's threshold rule) and 3 (the default)
    assert re.search(r"viscous\(x\) = (2\.99|3\b)", note), note
    assert "the diagnosis adds none" in note
    assert "the catalogue holds no friction or damping kind" in note
    assert "note: the fit warned" in str(report)


def test_relative_damping_only_between_coordinates_of_one_kind():
    assert not same_kind(("x", "theta"), ["theta"])  # a length and an angle
    assert same_kind(("theta1", "theta2"), ["theta1", "theta2"])
    assert same_kind(("x", "y"), [])
    assert not same_kind(("x", "y"), [], {"x": ("px", "V"), "y": ("m", "N")})
    assert same_kind(("x", "y"), [], {"x": ("m", "N"), "y": ("m", "N")})
    assert same_kind(("x",), ["theta"])


def _fitted(system):
    data = make_dataset(system, n_trajectories=3, duration=2.0, random_state=0)
    est = _quiet(
        LagrangianSINDy(system.paper_library(), formulation="strong").fit,
        data.X,
        data.tau,
    )
    return est, data


def test_the_catalogue_pairs_only_coordinates_of_one_kind():
    est, data = _fitted(cart_pendulum())
    eps = {"x": 0.01, "theta": 0.01}
    names = {c.name for c in _catalogue(est, ["relative"], [], ["theta"], None, eps)}
    assert names == set()  # relative(x,theta) mixed m/s and rad/s
    est, data = _fitted(double_pendulum())
    eps = {"theta1": 0.01, "theta2": 0.01}
    angles = ["theta1", "theta2"]
    names = {c.name for c in _catalogue(est, ["relative"], [], angles, None, eps)}
    assert names == {"relative(theta1,theta2)"}


def test_a_bootstrap_batch_that_cannot_be_solved_is_not_fatal(monkeypatch):
    """A resample of motionless stretches can make the batched solve fail
    ("Eigenvalues did not converge"): the resamples are solved one at a time."""
    import importlib

    module = importlib.import_module("lagsindy.uncertainty.bootstrap")

    calls = []

    def fails(*args, **kwargs):
        calls.append(1)
        raise np.linalg.LinAlgError("Eigenvalues did not converge")

    system = cart_pendulum()
    data = make_dataset(system, n_trajectories=10, duration=2.0, random_state=0)
    est = LagrangianSINDy(system.paper_library(), formulation="strong")
    monkeypatch.setattr(module, "batched_resamples", fails)
    report = _quiet(
        bootstrap, est, data.X, data.tau, groups=data.groups, n_resamples=5,
        random_state=0,
    )  # fmt: skip
    assert calls and report.n_failed == 0 and report.fast_path
    assert np.all(np.isfinite(report.low[report.coefficient != 0]))


def test_diagnose_keeps_its_report_when_the_bootstrap_fails(collapsed, monkeypatch):
    import lagsindy.diagnostics.summary as summary

    def fails(*args, **kwargs):
        raise np.linalg.LinAlgError("Eigenvalues did not converge")

    est, data = collapsed
    monkeypatch.setattr(summary, "_bootstrap_final", fails)
    report = _quiet(diagnose, est, data.X, data.tau, groups=data.groups, bootstrap=5)
    assert report.bootstrap is None and report.effects == ["viscous(x)"]
    assert "the bootstrap failed (LinAlgError: Eigenvalues did not converge)" in str(
        report
    )


def test_a_cyclic_undriven_coordinate_does_not_collapse_the_scorer():
    """Spherical pendulum, damped and driven on theta, phi free (cyclic): phi's
    equation is the rate of a conserved momentum, at noise level. Weighted by that
    scale alone it collapsed every refit of diagnose's scorer, which then traded
    cos(theta) for sin(theta)*cos(theta) plus bias(theta) = -6.87 (equivalent within
    1-2 % over theta in 0.77-1.33 rad). With the floor on the scales: no effect."""
    from lagsindy import diagnose
    from lagsindy.systems import make_dataset, spherical_pendulum

    system = spherical_pendulum().with_damping(viscous={"theta": 0.4})
    system.input_matrix = np.array([[1.0], [0.0]])
    system.__dict__.pop("_equations", None)
    system.__dict__.pop("_compiled", None)
    data = make_dataset(
        system,
        20,
        8.0,
        random_state=3,
        excitation="sincos",
        amplitude=1.0,
        noise=1e-3,
        protocol="sensor",
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # joint fit, identifiability
        est = LagrangianSINDy(system.paper_library()).fit(
            data.X, data.tau, groups=data.groups
        )
        report = diagnose(est, data.X, data.tau, groups=data.groups)
    assert report.effects == ["viscous(theta)"]  # the starting model's, nothing added
    assert set(report.final.term_names_[report.final.coef_ != 0]) == {
        "theta_dot**2",
        "cos(theta)",
        "phi_dot**2*sin(theta)**2",
    }
