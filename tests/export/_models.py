"""Estimators of the shipped systems' true models, built through a saved model file.

A model document (the format of :func:`lagsindy.io.save_model`) is written with the
system's own Lagrangian terms and coefficients, and viscous plus Coulomb friction on
every coordinate when asked, and read back with :func:`lagsindy.io.load_model`: a
fitted estimator, exactly as a user's saved model would be, whose forward and
inverse dynamics are the estimator's (torch) code.
"""

import json

import numpy as np

from lagsindy import __version__
from lagsindy._expr import state_names
from lagsindy.dissipation import make_term
from lagsindy.io import expression_to_string, load_model
from lagsindy.systems import SYSTEMS

# Damping of the "damped" variants, per coordinate: viscous b, Coulomb mu (eps 0.01).
VISCOUS = 0.15
COULOMB = 0.07

# Uniform ranges of the random states (positions, velocities, accelerations,
# generalized forces): the elastic pendulum's radius stays positive (its mass
# matrix is singular at r = 0), the spherical pendulum's theta away from the pole.
POSITIONS = {
    "elastic_pendulum": {"r": (0.5, 1.5)},
    "spherical_pendulum": {"theta": (0.3, 2.8)},
}


def model_document(name: str, damped: bool) -> dict:
    system = SYSTEMS[name]()
    coords = list(system.coordinates)
    terms, coefficients = [], []
    for text, c in system.terms().items():
        if text != "1":  # a constant shifts the energy only; a model file has none
            terms.append(text)
            coefficients.append(c)
    dissipation = []
    if damped:
        for kind, value in (("viscous", VISCOUS), ("coulomb", COULOMB)):
            for c in coords:
                t = make_term(kind, c, coords)
                dissipation.append(
                    {
                        "name": t.name,
                        "kind": t.kind,
                        "coordinates": list(t.coordinates),
                        "forces": [expression_to_string(f) for f in t.forces],
                        "rayleigh": None
                        if t.rayleigh is None
                        else expression_to_string(t.rayleigh),
                        "coefficient": value,
                    }
                )
    return {
        "format": "lagsindy-model",
        "schema_version": 1,
        "lagsindy_version": __version__,
        "coordinates": coords,
        "terms": terms,
        "coefficients": coefficients,
        "case": "forces",
        "fixed_term": None,
        "unpenalized": [],
        "hyperparameters": {},
        "n_features_in": 3 * len(coords),
        "feature_names_in": None,
        "tau_1d": False,
        "n_iter": 0,
        "residual": None,
        "dissipation": dissipation,
        "normalization": None,
    }


def true_estimator(name: str, damped: bool, folder):
    """A fitted LagrangianSINDy of system ``name``'s true model (from a file)."""
    path = folder / f"{name}{'_damped' if damped else ''}.json"
    path.write_text(json.dumps(model_document(name, damped)))
    return load_model(path), path


def random_states(name: str, n_states: int = 1000, seed: int = 0):
    """``(X, tau)``: X = [q, q_dot, q_ddot] rows and generalized forces."""
    system = SYSTEMS[name]()
    coords = list(system.coordinates)
    n = len(coords)
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, (n_states, n))
    for j, c in enumerate(coords):
        low, high = POSITIONS.get(name, {}).get(c, (-np.pi, np.pi))
        q[:, j] = rng.uniform(low, high, n_states)
    qd = rng.uniform(-3.0, 3.0, (n_states, n))
    qdd = rng.uniform(-3.0, 3.0, (n_states, n))
    tau = rng.uniform(-2.0, 2.0, (n_states, n))
    X = np.concatenate([q, qd, qdd], axis=1)
    assert len(state_names(coords)) == X.shape[1]
    return X, tau


def relative_error(a, b) -> float:
    """Largest ``|a - b|`` per state relative to that state's ``max |b|``."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    a, b = a.reshape(a.shape[0], -1), b.reshape(b.shape[0], -1)
    scale = np.abs(b).max(axis=1)
    return float((np.abs(a - b).max(axis=1) / scale).max())
