"""Case I's check of the kept support against the other test windows' supports
(lagsindy.cases.forces.better_support): a support with no more terms that meets
every coordinate's equation at least as well and one clearly better replaces the
fit's, and nothing else does."""

import warnings

import numpy as np
import pytest
import torch

import lagsindy.pipeline as pipeline
from lagsindy import DissipationLibrary, LagrangianSINDy
from lagsindy.cases import Solution
from lagsindy.cases.forces import (
    SUPPORT_GAIN,
    SUPPORT_TIE,
    better_support,
    equation_residuals,
)

RNG = np.random.default_rng(0)
A = RNG.normal(size=(2, 300, 4))  # two equations, four candidate columns
GOOD = np.array([2.0, 0.0, 1.0, 0.0])  # the support both equations agree on
NOISE = 1e-3 * RNG.normal(size=(2, 300))


def _gram(tau):
    M = np.concatenate([A, tau[:, :, None]], axis=2)
    return torch.as_tensor(np.einsum("dnp,dnq->dpq", M, M))


GRAM = _gram(np.einsum("dnp,p->dn", A, GOOD) + NOISE)


def _solution(coef):
    return Solution(np.asarray(coef, dtype=float), None)


def _audit(current, alternative):
    calls = []

    def resolve(mask):
        calls.append(mask)
        return _solution(alternative)

    out = better_support(GRAM, _solution(current), [_solution(alternative)], resolve)
    return out, calls


def test_equation_residuals_are_the_squared_residuals_per_equation():
    coef = np.array([1.0, 0.5, -0.2, 0.0])
    tau = np.einsum("dnp,p->dn", A, GOOD) + NOISE
    direct = ((tau - np.einsum("dnp,p->dn", A, coef)) ** 2).sum(axis=1)
    residual, energy = equation_residuals(GRAM, coef)
    np.testing.assert_allclose(residual, direct, rtol=1e-10)
    assert np.all(energy > residual)


def test_a_support_that_fits_every_equation_better_replaces_the_fit():
    # the current support swaps column 2 for column 1 and 3: worse in both
    current = np.array([2.0, 0.3, 0.0, 0.4])
    out, calls = _audit(current, GOOD)
    assert np.array_equal(out.coef, GOOD)
    assert len(calls) == 1 and calls[0].tolist() == [True, False, True, False]


def test_a_support_with_more_terms_is_not_tried():
    current = np.array([2.0, 0.0, 0.0, 0.0])
    out, calls = _audit(current, np.array([2.0, 0.1, 1.0, 0.0]))
    assert calls == [] and np.array_equal(out.coef, current)


def _equation_scaled(factor_per_equation):
    """A current solution whose residual is the good one's times the given factor
    per equation (the good one's residual is the noise's)."""
    base, _ = equation_residuals(GRAM, GOOD)
    return base * np.asarray(factor_per_equation)


@pytest.mark.parametrize(
    "factors, replaced",
    [
        # the alternative (GOOD) leaves equation 2 at 1/2.2 of the current's and
        # equation 1 the same: replaced
        ((1.0, 2.2), True),
        # only 1/1.8 better: not a clear gain (SUPPORT_GAIN = 0.5)
        ((1.0, 1.8), False),
        # much better on equation 2 but 2 % worse on equation 1: not replaced
        ((0.98, 100.0), False),
        # 0.5 % worse on equation 1 (within SUPPORT_TIE): replaced
        ((0.995, 100.0), True),
    ],
)
def test_the_gain_and_the_tie_at_their_boundaries(monkeypatch, factors, replaced):
    assert SUPPORT_GAIN == 0.5 and SUPPORT_TIE == 0.01
    current = np.array([2.0, 0.0, 0.0, 0.7])  # another support of the same size
    target = _equation_scaled(factors)
    good, energy = equation_residuals(GRAM, GOOD)
    import lagsindy.cases.forces as forces

    def fake(gram, coef):
        if np.array_equal(coef, current):
            return target, energy
        return good, energy

    monkeypatch.setattr(forces, "equation_residuals", fake)
    out, _ = _audit(current, GOOD)
    assert (out.coef is not current) == replaced


def _light_pole(seed):
    from lagsindy import CandidateLibrary
    from lagsindy.systems import cart_pendulum, make_dataset

    # a 20 g pole (0.3 m) on a 2 kg cart with viscous damping 1.0, force on the
    # cart only: the pole's equation is homogeneous and tiny next to the cart's
    system = cart_pendulum(2.0, 0.02, 0.3, 9.81).with_damping(viscous={"x": 1.0})
    data = make_dataset(
        system, 8, 8.0, excitation="sincos", amplitude=1.0, noise=1e-3,
        protocol="sensor", random_state=100 * seed + 1,
    )  # fmt: skip
    library = CandidateLibrary.polynomial(["x", "theta"], angles=["theta"], degree=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = LagrangianSINDy(library, dissipation=DissipationLibrary(["viscous"]))
        return est.fit(data.X, data.tau, groups=data.groups)


@pytest.mark.parametrize("seed", [2, 3])
def test_a_light_pole_keeps_its_terms_in_the_degree_3_library(monkeypatch, seed):
    est = _light_pole(seed)
    coef = dict(zip(est.term_names_, est.coef_))
    kept = {k for k, v in coef.items() if v != 0}
    assert kept == {
        "x_dot**2", "theta_dot**2", "theta_dot*x_dot*cos(theta)", "cos(theta)"
    }  # fmt: skip
    # theta_dot**2 / cos(theta) = l / 2g = 0.01529; measured -0.021 % (seed 2) and
    # -0.006 % (seed 3) on 8 trajectories
    ratio = coef["theta_dot**2"] / coef["cos(theta)"]
    assert ratio == pytest.approx(0.3 / (2 * 9.81), rel=1e-3)
    # without the check the 161-sample window's fit swapped theta_dot**2 for
    # theta_dot**2*cos(theta) + sin(theta)**2
    monkeypatch.setattr(pipeline, "better_support", lambda g, cur, o, r: cur)
    swapped = dict(zip(*(lambda e: (e.term_names_, e.coef_))(_light_pole(seed))))
    assert swapped["theta_dot**2"] == 0 and swapped["sin(theta)**2"] != 0


def _light_second_link():
    """A double pendulum driven at the first joint only (second link 2 % of the
    first, 0.5 m), viscous damping at the first joint, positions with noise 1e-3."""
    from lagsindy import CandidateLibrary
    from lagsindy.systems import double_pendulum, make_dataset
    from lagsindy.systems.base import System

    base = double_pendulum(1.0, 0.02, 1.0, 0.5)
    system = System(
        base.lagrangian, base.coordinates, angles=base.angles,
        initial_ranges=base.initial_ranges, input_matrix=[[1.0], [0.0]],
        paper_input=lambda t, w: np.cos(w * t)[:, None], name="light second link",
    ).with_damping(viscous={"theta1": 0.5})  # fmt: skip
    data = make_dataset(
        system, 10, 8.0, excitation="sincos", amplitude=2.0, noise=1e-3,
        protocol="sensor", random_state=0,
    )  # fmt: skip
    library = CandidateLibrary.separated(["theta1", "theta2"], angles="all", degree=2)
    return system, data, library


def test_a_light_second_link_keeps_both_halves_of_its_coupling():
    """The union threshold dropped theta1_dot*theta2_dot*sin(theta1)*sin(theta2)
    (the second link's parameters came out 40 % off, without a word); the solve
    with every term judged in its own equation meets that link's equation 10^4
    times better with one more term, so it is kept, with a warning that says so."""
    system, data, library = _light_second_link()
    est = LagrangianSINDy(library, dissipation=DissipationLibrary(["viscous"]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est.fit(data.X, data.tau, groups=data.groups)
    said = [str(w.message) for w in caught if "equation_threshold=" in str(w.message)]
    assert len(said) == 1, said
    assert "theta2's equation by 3.2e-02 of its energy" in said[0]  # now 9.0e-06
    assert est.equation_threshold_ == pytest.approx(0.05)
    true = np.asarray(system.true_coefficients(est.library_), dtype=float)
    assert np.array_equal(est.coef_ != 0, true != 0)
    # largest coefficient error 1.26 % (theta2's terms), measured
    np.testing.assert_allclose(est.coef_[true != 0], true[true != 0], rtol=0.03)


def test_more_terms_need_a_material_tenfold_gain(monkeypatch):
    """A solution with more terms replaces the fit's only for a residual at most a
    tenth of one that is at least 1e-4 of the equation's energy."""
    from lagsindy.cases import forces

    energy = np.array([1.0, 1.0])

    def case(before, after):
        def fake(gram, coef):
            return (
                np.asarray(before) if coef is cur.coef else np.asarray(after)
            ), energy

        monkeypatch.setattr(forces, "equation_residuals", fake)
        return forces.fits_better(None, cur, alt, more_terms=True)

    cur, alt = _solution([1.0, 0.0]), _solution([1.0, 1.0])
    assert case([1e-3, 2e-3], [1e-3, 1.9e-4])  # 0.095 x of a material residual
    assert not case([1e-3, 2e-3], [1e-3, 2.1e-4])  # 0.105 x: not tenfold
    assert not case([1e-3, 0.9e-4], [1e-3, 1e-6])  # below 1e-4 of the energy
    assert not case([1e-3, 2e-3], [1.02e-3, 1e-6])  # another equation 2 % worse
    assert case([1e-3, 2e-3], [1.005e-3, 1e-6])  # 0.5 % worse: within the tie
