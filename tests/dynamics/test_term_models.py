"""Models given by terms and coefficients (MechanicalModel.from_terms), simulated
through the evaluator: a torch term function against the sympy double pendulum."""

import pickle

import numpy as np
import pytest
import sympy as sp
import torch

from lagsindy import MechanicalModel
from lagsindy.evaluator import TorchTerms
from lagsindy.systems import double_pendulum

G = 9.81


def _link_energies(q, qd):
    """Per-mass energies of the double pendulum (two unit rods, angles from the
    downward vertical), from its kinematics: each point mass's kinetic energy and
    minus its potential energy, per unit mass."""
    r1 = torch.stack([torch.cos(q[0]), torch.sin(q[0])])
    r2 = torch.stack([torch.cos(q[1]), torch.sin(q[1])])
    v1 = qd[0] * r1
    v2 = v1 + qd[1] * r2
    return torch.stack(
        [
            (v1 * v1).sum() / 2,
            (v2 * v2).sum() / 2,
            G * torch.cos(q[0]),  # -V1 / m1: height -cos(theta1)
            G * (torch.cos(q[0]) + torch.cos(q[1])),
        ]
    )


LINKS = TorchTerms(["T1", "T2", "U1", "U2"], _link_energies)
MASSES = [1.0, 1.0, 1.0, 1.0]


@pytest.fixture(scope="module")
def models():
    true = double_pendulum()
    torch_model = MechanicalModel.from_terms(
        true.coordinates, LINKS, MASSES, name="links"
    )
    # the true Lagrangian's own terms, unit coefficients: the sympy terms' path
    terms = sp.Add.make_args(true.lagrangian)
    sympy_terms = MechanicalModel.from_terms(true.coordinates, terms, np.ones(6))
    return true, torch_model, sympy_terms


def test_term_models_evaluate_the_sympy_equations(models):
    true, torch_model, sympy_terms = models
    rng = np.random.default_rng(0)
    q, qd = rng.uniform(-2, 2, (2, 30, 2))
    tau = rng.normal(size=(30, 2))
    for model in (torch_model, sympy_terms):
        for got, want in [
            (model.mass_matrix(q, qd), true.mass_matrix(q, qd)),
            (model.forward_dynamics(q, qd, tau), true.forward_dynamics(q, qd, tau)),
            (model.inverse_dynamics(q, qd, tau), true.inverse_dynamics(q, qd, tau)),
            (model.energy(q, qd), true.energy(q, qd)),
        ]:
            # measured: 4.4e-15 at most (entries up to 40)
            np.testing.assert_allclose(got, want, rtol=0, atol=2e-14)


def test_torch_term_model_simulates_as_the_sympy_double_pendulum(models):
    """Same trajectories (passive and driven by a sampled input) to rounding."""
    true, torch_model, sympy_terms = models
    t = np.arange(0.0, 1.0, 0.05)  # few samples: a torch model's steps cost ~1 ms
    u = np.stack([np.cos(3 * t) - np.sin(3 * t), np.sin(3 * t)], axis=1)
    x0 = [0.8, -0.5, 0.3, 1.0]
    # measured: 8.4e-15 passive; 3.7e-12 driven (the sympy model steps on Python
    # floats, the term models through scipy's solver: same tableau and step
    # control, other rounding)
    for tau, bound in ((None, 5e-14), (u, 2e-11)):
        want = true.simulate(x0, t, tau)
        for model in (torch_model, sympy_terms):
            got = model.simulate(x0, t, tau)
            np.testing.assert_allclose(got, want, rtol=0, atol=bound)
    batch = sympy_terms.simulate(np.array([x0, x0]), t)
    np.testing.assert_allclose(batch[1], true.simulate(x0, t), rtol=0, atol=5e-14)


def test_term_models_describe_themselves_and_refuse_symbolic_methods(models):
    _, torch_model, sympy_terms = models
    assert torch_model.lagrangian is None and torch_model.lagrangian_terms is LINKS
    assert torch_model.equation(3) == "L = 1*T1 + 1*T2 + 1*U1 + 1*U2"
    assert "T1" in repr(torch_model)
    with pytest.raises(TypeError, match="torch term function"):
        torch_model.mass_matrix_expr()
    # sympy terms keep their symbolic side: L is the sum of the terms
    assert sympy_terms.mass_matrix_expr()[0, 0] == 2.0
    again = pickle.loads(pickle.dumps(sympy_terms))
    q = np.array([[0.1, 0.2]])
    np.testing.assert_array_equal(
        again.mass_matrix(q, q), sympy_terms.mass_matrix(q, q)
    )


def test_term_models_take_dissipation_and_forces():
    """Dissipation and extra forces enter a term model as they do a sympy one."""
    kw = dict(dissipation="0.3*theta1_dot**2/2", forces=["0", "-0.1*theta2_dot"])
    true = MechanicalModel(double_pendulum().lagrangian, ["theta1", "theta2"], **kw)
    model = MechanicalModel.from_terms(["theta1", "theta2"], LINKS, MASSES, **kw)
    rng = np.random.default_rng(1)
    q, qd = rng.uniform(-2, 2, (2, 10, 2))
    np.testing.assert_allclose(  # measured: 5.3e-15
        model.forward_dynamics(q, qd), true.forward_dynamics(q, qd), rtol=0, atol=3e-14
    )
    with pytest.raises(ValueError, match="one entry per term"):
        MechanicalModel.from_terms(["theta1", "theta2"], LINKS, [1.0, 2.0])
