"""Simulating robot models by the rigid-body algorithms (lagsindy.robots.dynamics).

The fast path (``RobotTerms.numpy_dynamics``: composite rigid body algorithm and
Newton-Euler bias in NumPy, plus rotor inertias and the dissipation forces) must give
the accelerations and the trajectories of the generic path (reverse-mode autograd of
the torch terms) and of the Newton-Euler regressor, and be the path used.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from _robot_fit_data import planar_data

from lagsindy import (
    CandidateLibrary,
    DissipationLibrary,
    LagrangianSINDy,
    MechanicalModel,
    SingularMassMatrixError,
)
from lagsindy.evaluator import TermEvaluator
from lagsindy.robots import BaseTerms, RobotTerms
from lagsindy.robots.dynamics import RigidBodyDynamics

DATA = Path(__file__).resolve().parent / "data"
ROBOTS = {
    "planar2": (None, None),
    "arm6": (None, None),
    "arm7": ([f"joint{i}" for i in range(1, 8)], {"finger_joint1": 0.03}),
    # branching, a prismatic joint, q not in the file's order, a mimic locked
    "mixed": (["spin", "rail", "tilt", "side"], {"finger_a_joint": 0.03}),
}


def _library(name):
    joints, locked = ROBOTS[name]
    return CandidateLibrary.from_urdf(str(DATA / f"{name}.urdf"), joints, locked=locked)


def _friction(coordinates, rng):
    """Viscous, Coulomb (tanh) and offset forces per joint, as sympy text."""
    return [
        f"-{rng.uniform(0.1, 0.5):.3f}*{c}_dot - {rng.uniform(0.05, 0.2):.3f}"
        f"*tanh({c}_dot/0.01) + {rng.uniform(-0.1, 0.1):.3f}"
        for c in coordinates
    ]


def _generic(model):
    """The model's ``(M, h - Q)`` by the generic path (reverse-mode autograd)."""
    numeric = model._numeric()
    weights = np.concatenate([numeric.coef, np.ones(numeric.evaluator.n_forces)])
    return numeric.evaluator.numpy_model(weights)


def _rel(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


@pytest.mark.parametrize("name", list(ROBOTS))
def test_mass_and_bias_equal_the_newton_euler_recursion(name):
    # any parameters, consistent or not: the model is linear in them
    lib = _library(name)
    terms = lib.torch_terms()
    rng = np.random.default_rng(3)
    pi = rng.normal(size=terms.n_terms)
    d = len(lib.coordinates_)
    q, qd = rng.uniform(-2, 2, (2, 20, d))
    mass, bias = terms.numpy_dynamics(pi)(q, qd)
    every = BaseTerms(terms, range(terms.n_terms))
    q_t, qd_t = torch.as_tensor(q), torch.as_tensor(qd)
    want_mass = np.einsum("skij,k->sij", every.mass_matrices(q_t, qd_t).numpy(), pi)
    want_bias = np.einsum("ski,k->si", every.bias(q_t, qd_t).numpy(), pi)
    assert _rel(mass, want_mass) < 1e-10  # measured 2e-15
    assert _rel(bias, want_bias) < 1e-10  # measured 6e-16


@pytest.mark.parametrize("name", list(ROBOTS))
def test_accelerations_equal_the_generic_path(name):
    # the URDF's links with rotor inertias and friction, on random states
    lib = _library(name)
    terms = lib.torch_terms()
    rng = np.random.default_rng(5)
    d = len(lib.coordinates_)
    coef = lib.nominal_.copy()
    coef[-d:] = rng.uniform(0.005, 0.05, d)
    model = MechanicalModel.from_terms(
        lib.coordinates_, terms, coef, forces=_friction(lib.coordinates_, rng)
    )
    q, qd = rng.uniform(-1.5, 1.5, (2, 30, d))
    tau = rng.normal(size=(30, d))
    fast = model.forward_dynamics(q, qd, tau)
    mass, rest = _generic(model)(q, qd)
    slow = np.linalg.solve(mass, (tau - rest)[..., None])[..., 0]
    assert _rel(fast, slow) < 1e-10  # measured 1e-14 or below


def test_many_states_are_evaluated_in_chunks(monkeypatch):
    from lagsindy.robots import dynamics

    terms = _library("arm6").torch_terms()
    dyn = terms.numpy_dynamics(np.random.default_rng(0).normal(size=terms.n_terms))
    q, qd = np.random.default_rng(1).uniform(-1, 1, (2, 25, 6))
    whole = dyn(q, qd)
    monkeypatch.setattr(dynamics, "CHUNK", 7)
    for a, b in zip(dyn(q, qd), whole):
        np.testing.assert_array_equal(a, b)


def test_forces_on_some_joints_only():
    lib = _library("mixed")
    rng = np.random.default_rng(8)
    coef = lib.nominal_.copy()
    coef[-4:] = 0.01
    forces = ["0", "-0.4*rail_dot - 0.1*tanh(rail_dot/0.01)", "0", "0.2"]
    model = MechanicalModel.from_terms(lib.coordinates_, lib.torch_terms(), coef,
                                       forces=forces)  # fmt: skip
    q, qd = rng.uniform(-1, 1, (2, 10, 4))
    fast_mass, fast_rest = model._mass_and_rest(q, qd)
    mass, rest = _generic(model)(q, qd)
    assert _rel(fast_mass, mass) < 1e-10 and _rel(fast_rest, rest) < 1e-10


def test_base_terms_subset_equals_the_generic_path():
    # what a fit simulates: a subset of the terms (base parameters), zeros elsewhere
    lib = _library("arm7")
    terms = lib.torch_terms()
    rng = np.random.default_rng(2)
    keep = np.sort(rng.choice(terms.n_terms, 40, replace=False))
    base = BaseTerms(terms, keep)
    coef = lib.nominal_[keep] + 0.01  # rotor inertias among them positive
    model = MechanicalModel.from_terms(lib.coordinates_, base, coef)
    q, qd = rng.uniform(-1, 1, (2, 10, 7))
    fast_mass, fast_rest = model._mass_and_rest(q, qd)
    mass, rest = _generic(model)(q, qd)
    assert _rel(fast_mass, mass) < 1e-10
    assert _rel(fast_rest, rest) < 1e-10


@pytest.fixture(scope="module")
def planar_fit():
    data = planar_data(duration=6.0)
    lib = CandidateLibrary.from_urdf(str(DATA / "planar2.urdf"))
    est = LagrangianSINDy(
        lib,
        dissipation=DissipationLibrary(["viscous", "coulomb", "bias"]),
        formulation="strong",
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(data.X, data.tau)
    return est


def _without_fast_path(monkeypatch, est):
    """``est``'s model on the generic path (as before the fast path existed)."""
    monkeypatch.setattr(BaseTerms, "numpy_dynamics", None)
    est.model_.__dict__.pop("_compiled", None)


def _both_paths(est, monkeypatch, runs):
    est.model_.__dict__.pop("_compiled", None)
    fast = runs()
    _without_fast_path(monkeypatch, est)
    slow = runs()
    est.model_.__dict__.pop("_compiled", None)
    return [_rel(a, b) for a, b in zip(fast, slow)]


def test_simulated_trajectory_equals_the_generic_paths(planar_fit, monkeypatch):
    # a batch of two trajectories and a forced one, at the default tolerances, over
    # a stretch without velocity reversals (fewer than 60 steps: the generic path
    # costs ~10 ms per call)
    est = planar_fit
    t = np.arange(0.0, 0.05, 0.005)
    batch = np.array([[0.3, -0.4, 0.5, 0.2], [0.1, -0.2, 0.6, 0.4]])
    tau = 0.5 * np.sin(np.outer(t, [1.3, 2.1]))
    rel = _both_paths(
        est,
        monkeypatch,
        lambda: (est.simulate(batch, t), est.simulate(batch[0], t, tau)),
    )
    assert max(rel) < 1e-14  # measured 2.2e-15 and 7e-16


@pytest.mark.slow
def test_simulated_trajectory_equals_the_generic_paths_over_a_second(
    planar_fit, monkeypatch
):
    # The fitted model has Coulomb friction, tanh(qd / 0.01): stiff where a velocity
    # reverses, so at the default rtol=1e-9 the step-size controller's decisions flip
    # on round-off and the two paths differ by the integrator's own error (measured
    # 1.3e-7 relative over 1 s unforced; each is 1.2e-7 to 1.7e-7 from an rtol=1e-13
    # reference). At rtol=1e-11 they agree to round-off.
    est = planar_fit
    t = np.arange(0.0, 1.0, 0.01)
    batch = np.array([[0.3, -0.4, 0.5, 0.2], [-0.2, 0.6, -0.3, 0.1]])
    tau = 0.5 * np.sin(np.outer(t, [1.3, 2.1]))
    rel = _both_paths(
        est,
        monkeypatch,
        lambda: (
            est.simulate(batch, t, rtol=1e-11, atol=1e-11),
            est.simulate(batch[0], t, tau),
        ),
    )
    assert max(rel) < 5e-13  # measured 1.4e-13 and 5e-15


def test_the_fast_path_is_the_one_used(planar_fit, monkeypatch):
    est = planar_fit
    est.model_.__dict__.pop("_compiled", None)
    calls = []
    real = RigidBodyDynamics.__call__

    def counted(self, q, qd):
        calls.append(q.shape)
        return real(self, q, qd)

    def refuse(*args, **kwargs):
        raise AssertionError("the generic (autograd) path was used")

    monkeypatch.setattr(RigidBodyDynamics, "__call__", counted)
    monkeypatch.setattr(TermEvaluator, "_model_parts", refuse)
    est.simulate(np.array([0.3, -0.4, 0.5, 0.2]), np.linspace(0.0, 0.2, 5))
    assert len(calls) > 10  # every right-hand side, one state each
    assert all(shape == (1, 2) for shape in calls[1:-1])
    est.model_.__dict__.pop("_compiled", None)


def test_a_singular_mass_matrix_still_raises(monkeypatch):
    # only the forearm's mass: the shoulder's inertia vanishes with the arm stretched
    lib = _library("planar2")
    terms = lib.torch_terms()
    coef = np.zeros(terms.n_terms)
    coef[terms.names.index("m_forearm")] = 1.0
    x0 = np.array([0.2, 0.0, 0.0, 0.0])

    def message():
        model = MechanicalModel.from_terms(lib.coordinates_, terms, coef)
        with pytest.raises(SingularMassMatrixError) as err:
            model.simulate(x0, np.linspace(0.0, 1.0, 11))
        return str(err.value)

    def without_eigenvalues(text):  # they differ by round-off (-6e-18 vs 0)
        return re.sub(r"eigenvalues \[[^\]]*\]", "eigenvalues [...]", text)

    fast = message()
    assert "mass matrix" in fast and "singular" in fast
    monkeypatch.setattr(RobotTerms, "numpy_dynamics", None)
    assert without_eigenvalues(message()) == without_eigenvalues(fast)


def test_numpy_dynamics_checks_its_coefficients():
    terms = _library("planar2").torch_terms()
    with pytest.raises(ValueError, match="one entry per term"):
        terms.numpy_dynamics(np.ones(3))


def test_the_docstring_example_runs():
    import doctest

    from lagsindy.robots import dynamics

    result = doctest.testmod(dynamics)
    assert result.failed == 0 and result.attempted > 0


@pytest.mark.slow  # the benchmark script end to end at a tiny size (~30 s)
def test_robot_simulation_benchmark_tiny(tmp_path, monkeypatch):
    import benchmarks._common as common
    from benchmarks import robot_simulation

    monkeypatch.setenv("LAGSINDY_BENCH_TINY", "1")
    monkeypatch.setattr(common, "RESULTS", tmp_path)
    assert robot_simulation.main(["--quick"]) == 0
    text = (tmp_path / "robot_simulation_quick.md").read_text()
    assert "python -m benchmarks.robot_simulation --quick" in text
    rows = [line for line in text.splitlines() if line.startswith("| planar2")]
    rows += [line for line in text.splitlines() if line.startswith("| arm7")]
    assert len(rows) == 2
    assert BaseTerms.numpy_dynamics is not None  # the switch was undone
