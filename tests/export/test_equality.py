"""Exports equal the estimator: Python, C and CasADi against LagrangianSINDy.

Every shipped system (lagsindy.systems.SYSTEMS), without and with dissipation
(viscous and Coulomb friction on every coordinate), is written as a model file and
loaded as a fitted estimator (tests/export/_models.py); on 1,000 random states the
exported forward dynamics equal ``est.predict_acceleration`` and the exported
inverse dynamics ``est.predict`` (torch code), the energy ``est.model_.energy``.
"""

import numpy as np
import pytest

from lagsindy.export import (
    CModel,
    compile_c,
    export_model,
    export_source,
    find_compiler,
    load_python,
)
from lagsindy.systems import SYSTEMS

from ._models import random_states, relative_error, true_estimator

# The acceptance bound is 1e-12 (relative, per state). Measured largest errors over
# the 16 models: forward 3.5e-14 (Python batched, C and CasADi alike, the damped
# single pendulum: the estimator's pseudo-inverse), Python single states 6.2e-15,
# inverse 1.1e-14 (damped elastic pendulum). The tests hold the measured size (~5x).
RTOL = 2e-13
# The energy against the model's (numpy) energy, relative to the batch's largest
# |E| (E crosses zero): measured 4.7e-16.
ENERGY_RTOL = 3e-15

CASES = [(name, damped) for name in SYSTEMS for damped in (False, True)]
IDS = [f"{name}{'-damped' if damped else ''}" for name, damped in CASES]


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """{(name, damped): (estimator, X, tau, predict_acceleration, predict)}."""
    folder = tmp_path_factory.mktemp("models")
    out = {}
    for name, damped in CASES:
        est, _ = true_estimator(name, damped, folder)
        X, tau = random_states(name)
        out[name, damped] = (
            est,
            X,
            tau,
            est.predict_acceleration(X, tau),
            est.predict(X),
        )
    return out


def _energy_error(energy, est, X):
    n = est.n_dof_
    ref = est.model_.energy(X[:, :n], X[:, n : 2 * n])
    return float(np.abs(energy - ref).max() / np.abs(ref).max())


@pytest.mark.parametrize(("name", "damped"), CASES, ids=IDS)
def test_python_export_equals_the_estimator(models, name, damped):
    est, X, tau, acc, forces = models[name, damped]
    n = est.n_dof_
    module = load_python(export_source(est, "python"))
    assert relative_error(module.forward_dynamics(X[:, : 2 * n], tau), acc) < RTOL
    single = np.array(
        [module.forward_dynamics(X[i, : 2 * n], tau[i]) for i in range(100)]
    )
    assert relative_error(single, acc[:100]) < RTOL
    inverse = module.inverse_dynamics(X[:, :n], X[:, n : 2 * n], X[:, 2 * n :])
    assert relative_error(inverse, forces) < RTOL
    assert _energy_error(module.energy(X[:, :n], X[:, n : 2 * n]), est, X) < ENERGY_RTOL


@pytest.mark.skipif(find_compiler() is None, reason="no C compiler")
@pytest.mark.parametrize(("name", "damped"), CASES, ids=IDS)
def test_c_export_equals_the_estimator(models, name, damped, tmp_path):
    est, X, tau, acc, forces = models[name, damped]
    n = est.n_dof_
    c_file, _ = export_model(est, tmp_path / f"{name}.c")
    model = CModel(compile_c(c_file, flags=("-O2", "-Wall", "-Werror")), name)
    assert relative_error(model.forward_dynamics(X[:, : 2 * n], tau), acc) < RTOL
    inverse = model.inverse_dynamics(X[:, :n], X[:, n : 2 * n], X[:, 2 * n :])
    assert relative_error(inverse, forces) < RTOL
    assert _energy_error(model.energy(X[:, :n], X[:, n : 2 * n]), est, X) < ENERGY_RTOL


@pytest.mark.parametrize(("name", "damped"), CASES, ids=IDS)
def test_casadi_export_equals_the_estimator(models, name, damped):
    pytest.importorskip("casadi")
    from lagsindy.export import to_casadi

    est, X, tau, acc, forces = models[name, damped]
    n, k = est.n_dof_, X.shape[0]
    f = to_casadi(est)
    out = np.array(f.forward_dynamics.map(k)(X[:, : 2 * n].T, tau.T)).T
    assert relative_error(out, acc) < RTOL
    inverse = f.inverse_dynamics.map(k)(X[:, :n].T, X[:, n : 2 * n].T, X[:, 2 * n :].T)
    assert relative_error(np.array(inverse).T, forces) < RTOL
    energy = np.array(f.energy.map(k)(X[:, :n].T, X[:, n : 2 * n].T)).ravel()
    assert _energy_error(energy, est, X) < ENERGY_RTOL
