"""lagsindy.diagnostics: the diagnosis loop (revise the Lagrangian, the trajectory
criterion, fair equations, input delays, shared statistics of the refits)."""

import numpy as np
import pytest
import sympy as sp

from lagsindy import CandidateLibrary, LagrangianSINDy, diagnose
from lagsindy.cli import main
from lagsindy.diagnostics import velocity_eps
from lagsindy.dissipation import DissipationLibrary
from lagsindy.formulation import make_formulation
from lagsindy.io import load_model
from lagsindy.systems import (
    cart_pendulum,
    double_pendulum,
    make_dataset,
    single_pendulum,
)
from lagsindy.systems.base import System


def _coefficients(report):
    return {s.candidate.name: s.coefficient for s in report.steps}


def _lagrangian_error(est, truth: dict) -> float:
    """Largest relative error of the true terms; other terms must be absent."""
    got = {str(t): c for t, c in zip(est.library_.terms_, est.coef_) if c != 0}
    assert set(got) == set(truth), f"support {sorted(got)} != {sorted(truth)}"
    return max(abs(got[k] - v) / abs(v) for k, v in truth.items())


# ----------------------------------------------------------------------- item 1
def test_revises_a_lagrangian_that_absorbed_the_damping():
    """Cart-pendulum, viscous on theta and Coulomb on x: the conservative fit is a
    wrong 7-term Lagrangian; the loop ends with the right one and both effects."""
    system = cart_pendulum().with_damping(viscous={"theta": 0.1}, coulomb={"x": 0.2})
    data = make_dataset(
        system,
        n_trajectories=12,
        duration=4.0,
        excitation="sincos",
        protocol="paper",
        random_state=0,
    )
    est = LagrangianSINDy(system.paper_library(), formulation="strong")
    est.fit(data.X, data.tau, groups=data.groups)
    assert est.support_.sum() > 4  # the damping was absorbed into spurious terms
    report = diagnose(est, data.X, data.tau, groups=data.groups)
    assert sorted(report.effects) == ["coulomb(x)", "viscous(theta)"]
    coef = _coefficients(report)
    assert coef["viscous(theta)"] == pytest.approx(0.1, rel=3.5e-3)  # measured 0.07 %
    assert coef["coulomb(x)"] == pytest.approx(0.2, rel=0.07)  # measured 1.4 %
    truth = {
        "x_dot**2": 0.75,
        "theta_dot*x_dot*cos(theta)": 0.5,
        "theta_dot**2": 0.25,
        "cos(theta)": 4.905,
    }
    assert _lagrangian_error(report.final, truth) < 3.5e-3  # measured 0.068 %
    assert report.lagrangian_changes["removed"]
    # never worse (item 7), and the report says what changed
    assert report.heldout_error_after < 0.1 * report.heldout_error_before
    assert "revised" in str(report)


# ----------------------------------------------------------------------- item 2
def _joint_damped_double(b1, b2):
    system = double_pendulum()
    v1, v2 = sp.symbols("theta1_dot theta2_dot", real=True)
    system.dissipation = sp.Float(b1) * v1**2 / 2 + sp.Float(b2) * (v2 - v1) ** 2 / 2
    system.__dict__.pop("_equations", None)
    system.__dict__.pop("_compiled", None)
    return system


@pytest.mark.parametrize(
    "b1, b2, noise, seed",
    [
        # two variants in the default run (about 5 s each), the others with -m slow
        (0.05, 0.03, 1e-3, 1),
        # the joint revision keeps drag(theta1) for the small viscous(theta1) in the
        # next three; the swap move replaces it (measured viscous +7.5 %, +6.5 %,
        # +5.0 %; relative within 0.5 %)
        (0.02, 0.06, 3e-3, 1),
        pytest.param(0.03, 0.05, 3e-3, 2, marks=pytest.mark.slow),
        pytest.param(0.02, 0.06, 2e-3, 1, marks=pytest.mark.slow),
        pytest.param(
            0.015,
            0.04,
            3e-3,
            3,
            marks=[
                pytest.mark.slow,
                pytest.mark.xfail(
                    strict=False,
                    reason="known limitation: drag(theta1) (0.00345) is kept for "
                    "viscous(theta1)=0.015; the swap improves the held-out criterion "
                    "by less than min_improvement=1 %",
                ),
            ],
        ),
    ],
)
def test_small_joint_damping_found_by_the_trajectory_criterion(b1, b2, noise, seed):
    """Passive double pendulum, small joint damping, noise on positions only."""
    system = _joint_damped_double(b1, b2)
    data = make_dataset(
        system,
        n_trajectories=8,
        duration=6.0,
        excitation=None,
        noise=noise,
        protocol="sensor",
        random_state=seed,
    )
    # the default formulation (issue 14's acceptance): "auto", the weak form here
    est = LagrangianSINDy(system.paper_library(), fixed_term="theta1_dot**2").fit(
        data.X, groups=data.groups
    )
    assert est.formulation_ == "weak"
    report = diagnose(est, data.X, groups=data.groups)
    coef = _coefficients(report)
    # theta1_dot**2 has coefficient 1 in the true Lagrangian: same scale
    assert coef["viscous(theta1)"] == pytest.approx(b1, rel=0.20)  # measured 1-7.5 %
    assert coef["relative(theta1,theta2)"] == pytest.approx(b2, rel=0.20)  # <= 0.8 %
    assert set(coef) == {"viscous(theta1)", "relative(theta1,theta2)"}
    # the pointwise criterion barely sees them; the trajectory criterion does
    assert report.heldout_error_after < 0.3 * report.heldout_error_before
    assert report.pointwise_after > 0.8 * report.pointwise_before


# ----------------------------------------------------------------------- item 3
def _cyclic_cart(cart, bob, b):
    """Pendulum driven by a torque on theta over a free cart: x is cyclic, undriven."""
    x, th, xd, thd = sp.symbols("x theta x_dot theta_dot", real=True)
    length, g = 0.8, 9.81
    lag = (
        (cart + bob) / 2 * xd**2
        + bob * length * xd * thd * sp.cos(th)
        + bob * length**2 / 2 * thd**2
        + bob * g * length * sp.cos(th)
    )
    ranges = {"x": (0, 0), "theta": (-2, 2), "x_dot": (-0.5, 0.5), "theta_dot": (-1, 1)}
    system = System(
        lag,
        ["x", "theta"],
        angles=["theta"],
        initial_ranges=ranges,
        input_matrix=[[0.0], [1.0]],
        name="cyclic cart",
    )
    return system.with_damping(viscous={"theta": b})


def test_every_equation_counts_cyclic_undriven_coordinate():
    """The undriven x-equation (forces ~0) must not drown the driven one: the
    candidate that explains the residual ranks first with the right coefficient."""
    system = _cyclic_cart(2.0, 0.3, 0.15)
    data = make_dataset(
        system, n_trajectories=9, duration=4.0, excitation="sincos", random_state=2
    )
    terms = ["x_dot**2", "theta_dot**2", "x_dot*theta_dot*cos(theta)", "cos(theta)"]
    lib = CandidateLibrary.from_terms(["x", "theta"], terms)
    est = LagrangianSINDy(lib, formulation="strong", unpenalized=terms)
    est.fit(data.X, data.tau, groups=data.groups)
    report = diagnose(est, data.X, data.tau, groups=data.groups)
    top = report.rankings[0].iloc[0]
    assert top["term"] == "viscous(theta)"
    assert top["explained"] > 0.99  # measured 100.0 %
    assert top["coefficient"] == pytest.approx(0.15, rel=3.5e-6)  # measured 6.4e-7
    # never worse, whatever the refit does
    assert report.heldout_error_after <= report.heldout_error_before


# ----------------------------------------------------------------------- item 4
@pytest.mark.parametrize("formulation", ["weak", "strong"])
def test_one_long_recording_uses_time_blocks(formulation):
    system = single_pendulum(mass=0.7, length=0.6).with_damping(viscous={"theta": 0.04})
    data = make_dataset(
        system,
        n_trajectories=1,
        duration=20.0,
        excitation="sincos",
        amplitude=2.0,
        noise=1e-3 if formulation == "weak" else 0.0,
        protocol="sensor" if formulation == "weak" else "paper",
        random_state=5,
    )
    est = LagrangianSINDy(
        system.paper_library(), formulation=make_formulation(formulation, dt=0.01)
    )
    est.fit(data.X, data.tau)
    report = diagnose(est, data.X, data.tau)  # no groups, one trajectory
    assert report.settings["fold_kind"] == "time blocks"
    assert report.effects == ["viscous(theta)"]
    assert report.steps[0].coefficient == pytest.approx(0.04, rel=4e-3)  # 0.08 %
    assert "time blocks" in str(report)


# ----------------------------------------------------------------------- item 5
def test_report_final_coefficients_honest_shares_and_invalid_start(monkeypatch):
    system = _cyclic_cart(0.4, 1.0, 0.15)
    data = make_dataset(
        system, n_trajectories=6, duration=3.0, excitation="sincos", random_state=2
    )
    lib = CandidateLibrary.from_terms(
        ["x", "theta"],
        ["x_dot**2", "theta_dot**2", "x_dot*theta_dot*cos(theta)", "cos(theta)"],
    )
    # the undriven cart's inertia is the largest term of its own equation: the
    # default threshold keeps it
    est = LagrangianSINDy(lib, formulation="strong").fit(data.X, data.tau)
    assert "x_dot**2" in est.equation()
    # the paper's global rule alone drops it: the fit cannot predict the cart's
    # accelerations, and the diagnosis says so
    from lagsindy.solvers import StagedFISTA

    defaults = list(StagedFISTA.__init__.__defaults__)
    defaults[-1] = None  # equation_threshold=None
    monkeypatch.setattr(StagedFISTA.__init__, "__defaults__", tuple(defaults))
    est = LagrangianSINDy(lib, formulation="strong").fit(data.X, data.tau)
    assert "x_dot**2" not in est.equation()
    report = diagnose(est, data.X, data.tau, groups=data.groups)
    text = str(report)
    assert "cannot predict some accelerations" in text
    if report.final is not report.initial:  # accepted only if it can predict
        assert report.settings["start_valid"] is False
    # no absurd shares (tau = 0 on the undriven cart is not the scale)
    assert np.all(np.isfinite(report.force_rms))
    assert "%" in text and "e+" not in text.split("final model")[0]


def test_report_shows_final_coefficients_and_units_only_when_given():
    system = single_pendulum().with_damping(
        viscous={"theta": 0.2}, coulomb={"theta": 0.1}
    )
    data = make_dataset(
        system, n_trajectories=9, duration=3.0, excitation="sincos", random_state=0
    )
    est = LagrangianSINDy(system.paper_library(), formulation="strong")
    est.fit(data.X, data.tau, groups=data.groups)
    report = diagnose(est, data.X, data.tau, groups=data.groups)
    final = dict(
        zip(
            [t.name for t in report.final.dissipation_terms_],
            report.final.dissipation_coef_,
        )
    )
    for step in report.steps:  # the table shows the final model's values
        assert step.coefficient == final[step.candidate.name]
    assert _coefficients(report)["viscous(theta)"] == pytest.approx(0.2, rel=0.10)
    assert _coefficients(report)["coulomb(theta)"] == pytest.approx(0.1, rel=0.10)
    assert "per unit of theta_dot" in str(report) and "N*m" not in str(report)
    frame = report.to_frame()
    assert set(frame.term) == {"viscous(theta)", "coulomb(theta)"}


# ----------------------------------------------------------------------- item 6
def test_weak_model_loaded_from_json_can_be_diagnosed(tmp_path, capsys):
    system = single_pendulum().with_damping(viscous={"theta": 0.1})
    data = make_dataset(
        system, n_trajectories=4, duration=4.0, excitation="sincos", random_state=1
    )
    est = LagrangianSINDy(system.paper_library(), formulation="weak")
    est.fit(data.X, data.tau, groups=data.groups)
    path = tmp_path / "weak.json"
    est.save(path)
    loaded = load_model(path)
    report = diagnose(loaded, data.X, data.tau, groups=data.groups)
    assert report.effects == ["viscous(theta)"]
    # measured 1.3e-7 relative (noise-free data)
    assert report.steps[0].coefficient == pytest.approx(0.1, rel=1e-6)
    csv = tmp_path / "data.csv"
    data.to_frame().to_csv(csv, index=False)
    assert main(["diagnose", str(csv), "--model", str(path), "--quiet"]) == 0
    assert "viscous(theta)" in capsys.readouterr().out


# ----------------------------------------------------------------------- item (f)
def test_coulomb_smoothing_from_the_velocity_scale(tmp_path):
    """A slow axis (top speed ~0.19 m/s): eps=0.01 biases viscous friction."""
    x, xd = sp.symbols("x x_dot", real=True)
    system = System(
        xd**2 + 0 * x,
        ["x"],
        initial_ranges={"x": (0, 0), "x_dot": (-0.1, 0.1)},
        input_matrix=[[1.0]],
        name="slow axis",
    ).with_damping(viscous={"x": 3.0}, coulomb={"x": 0.15}, eps=1e-4)
    data = make_dataset(
        system, n_trajectories=8, duration=4.0, excitation="sincos", random_state=3
    )
    eps = velocity_eps(data.X, 1, ["x"])
    top = np.quantile(np.abs(data.X[:, 1]), 0.99)
    assert eps["x"] == pytest.approx(0.01 * top, rel=5e-3)  # 3 significant digits
    lib = CandidateLibrary.from_terms(["x"], ["x_dot**2"])
    fits = {}
    for name, e in [("auto", eps), ("fixed", 0.01)]:
        dis = DissipationLibrary(["viscous", "coulomb"], eps=e)
        fits[name] = LagrangianSINDy(lib, dissipation=dis, formulation="strong").fit(
            data.X, data.tau
        )
    assert fits["auto"].dissipation_coef_[0] == pytest.approx(3.0, rel=0.02)  # 0.8 %
    assert fits["fixed"].dissipation_coef_[0] < 0.97 * 3.0  # measured -4.2 %
    # the per-coordinate eps survives save/load
    path = tmp_path / "axis.json"
    fits["auto"].save(path)
    again = load_model(path)
    assert again.predict(data.X) == pytest.approx(fits["auto"].predict(data.X))
    assert again.dissipation.eps["x"] == pytest.approx(eps["x"], rel=1e-6)


# ----------------------------------------------------------------------- item 7
@pytest.mark.parametrize("noise", [0.0, 0.02])
def test_never_worse_and_no_effect_on_undamped_data(noise):
    system = double_pendulum()
    data = make_dataset(
        system,
        n_trajectories=6,
        duration=4.0,
        excitation="sincos",
        noise=noise,
        protocol="sensor" if noise else "paper",
        random_state=7,
    )
    formulation = "weak" if noise else "strong"
    est = LagrangianSINDy(
        system.paper_library(), formulation=make_formulation(formulation, dt=0.01)
    )
    est.fit(data.X, data.tau, groups=data.groups)
    report = diagnose(est, data.X, data.tau, groups=data.groups)
    assert report.heldout_error_after <= report.heldout_error_before
    assert [e for e in report.effects if e.startswith(("viscous", "relative"))] == []


# ----------------------------------------------------------------------- input delay
@pytest.mark.parametrize(
    "delay, noise",
    [(0.03, 0.0), (0.03, 2e-3), (0.0, 0.0)],
    ids=["30ms", "30ms-noisy", "none"],
)
def test_input_delay_is_an_effect(delay, noise):
    """Forced damped pendulum whose recorded input leads the acting force by 30 ms:
    the delay is found first (with the dissipative catalogue as candidates, else
    the missing damping biases it), then the damping, and the fit is right after."""
    from lagsindy.delay import shift_input

    system = single_pendulum(mass=0.8, length=0.5).with_damping(viscous={"theta": 0.05})
    kw = {"noise": noise, "protocol": "sensor"} if noise else {}
    data = make_dataset(
        system,
        n_trajectories=10,
        duration=3.0,
        excitation="sincos",
        random_state=0,
        **kw,
    )
    # recorded(t) = acting(t + delay): the input acts `delay` after it is recorded
    recorded = shift_input(data.tau, data.t, -delay, data.groups)
    formulation = "weak" if noise else "strong"
    est = LagrangianSINDy(
        system.paper_library(), formulation=make_formulation(formulation, dt=0.01)
    )
    est.fit(data.X, recorded, groups=data.groups)
    report = diagnose(est, data.X, recorded, groups=data.groups)
    coef = _coefficients(report)
    if delay:
        assert report.effects[0] == "delay"
        assert report.steps[0].candidate.description == "input delay"
        assert report.steps[0].units.startswith("ms")
        # measured 29.998 ms (no noise), 29.57 ms (noise 2e-3)
        assert coef["delay"] == pytest.approx(1e3 * delay, abs=2.0 if noise else 0.01)
        assert "input delay" in str(report)
    else:
        assert "delay" not in report.effects
    # measured 0.025 % at most
    assert coef["viscous(theta)"] == pytest.approx(0.05, rel=1.3e-3)
    truth = {"theta_dot**2": 0.1, "cos(theta)": 0.8 * 9.81 * 0.5}
    # measured 9.7e-5 (30 ms), 2.2e-4 (30 ms, noisy), 2e-15 (no delay)
    assert _lagrangian_error(report.final, truth) < 1.1e-3


@pytest.mark.parametrize("delay", [0.03, 0.0], ids=["30ms", "none"])
def test_diagnose_never_fits_the_same_model_twice(delay, monkeypatch):
    """The input delay search's first fit (every row, the recorded input, the
    dissipative catalogue as candidates) is the joint revision's fit: diagnose
    makes it once. No refit repeats another one's configuration and data."""
    import hashlib

    from lagsindy.delay import shift_input

    system = single_pendulum(mass=0.8, length=0.5).with_damping(viscous={"theta": 0.05})
    data = make_dataset(
        system, n_trajectories=10, duration=3.0, excitation="sincos", random_state=0
    )
    recorded = shift_input(data.tau, data.t, -delay, data.groups)
    est = LagrangianSINDy(system.paper_library(), formulation="strong")
    est.fit(data.X, recorded, groups=data.groups)
    seen = []
    original = LagrangianSINDy.fit

    def fingerprinted(self, X, tau=None, **kwargs):
        params = sorted((k, repr(v)) for k, v in self.get_params(deep=True).items())
        arrays = [np.ascontiguousarray(X)] + ([] if tau is None else [np.asarray(tau)])
        digest = hashlib.sha1(b"".join(a.tobytes() for a in arrays)).hexdigest()
        seen.append((repr(params), digest))
        return original(self, X, tau, **kwargs)

    monkeypatch.setattr(LagrangianSINDy, "fit", fingerprinted)
    report = diagnose(est, data.X, recorded, groups=data.groups)
    assert ("delay" in report.effects) == bool(delay)
    assert len(seen) == len(set(seen))
    # measured: 2 fits without a delay (3 before the joint fit was shared: the
    # delay search fitted the same configuration on its own), 5 with one (the
    # delay search's refit at the estimate, the trial and the joint revision on the
    # shifted input, ...)
    assert len(seen) == (5 if delay else 2)


def test_diagnose_refits_share_the_joint_fits_weak_statistics(
    monkeypatch, reused_grams
):
    """Inside diagnose every refit's features are among the joint revision's fit, so
    their weak-form statistics (noise part included) are gathered, not computed
    again: the diagnosis equals the one with every refit's statistics afresh."""
    import contextlib

    import lagsindy.diagnostics.search as search_module

    system = cart_pendulum().with_damping(viscous={"theta": 0.1}, coulomb={"x": 0.2})
    data = make_dataset(
        system,
        n_trajectories=8,
        duration=4.0,
        excitation="sincos",
        noise=1e-3,
        protocol="sensor",
        random_state=0,
    )
    est = LagrangianSINDy(system.paper_library()).fit(
        data.X, data.tau, groups=data.groups
    )
    reused = reused_grams
    shared = diagnose(est, data.X, data.tau, groups=data.groups)
    n_shared = len(reused)
    monkeypatch.setattr(search_module, "reuse_weak_columns", contextlib.nullcontext)
    reused.clear()
    fresh = diagnose(est, data.X, data.tau, groups=data.groups)
    # measured: 3 gathered (the folds' per-trajectory statistics on the input shifted
    # by the delay estimate, one call for every fold since they are kept per
    # trajectory; the trial refit on it; the revised model's refit). The delay does
    # not win here, so the joint fit on the shifted input it would have to beat is
    # not made.
    assert n_shared == 3 and not reused
    assert shared.effects == fresh.effects == ["viscous(theta)", "coulomb(x)"]
    # measured: the same coefficients and held-out error, bit for bit (a gathered
    # block; another BLAS may round the fresh sums differently)
    np.testing.assert_allclose(shared.final.coef_, fresh.final.coef_, rtol=1e-12)
    np.testing.assert_allclose(
        shared.final.dissipation_coef_, fresh.final.dissipation_coef_, rtol=1e-12
    )
    assert shared.heldout_error_after == pytest.approx(
        fresh.heldout_error_after, rel=1e-10
    )
