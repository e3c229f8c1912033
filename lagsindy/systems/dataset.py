"""Reproducible training data from a system, with the three named noise protocols."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from sklearn.utils import check_random_state

from .._expr import state_names
from .base import System

PROTOCOLS = ("shared", "paper", "sensor")
EXCITATIONS = ("paper", "sincos", None)


@dataclass
class Dataset:
    """Trajectories ready for :meth:`LagrangianSINDy.fit`.

    Attributes
    ----------
    X : ndarray of shape (n_samples, 3 * n_dof)
        ``[q..., q_dot..., q_ddot...]`` as measured under the noise protocol.
    tau : ndarray of shape (n_samples, n_dof) or None
        Generalized forces ``B u`` (noise-free); ``None`` for passive data.
    groups : ndarray of shape (n_samples,)
        Trajectory index of each row (for ``GroupKFold`` and differentiation).
    t : ndarray of shape (n_samples,)
        Time of each row within its trajectory.
    X_clean : ndarray of shape (n_samples, 3 * n_dof)
        Exact states and accelerations (accelerations from the equations of motion).
    u : ndarray of shape (n_samples, n_inputs) or None
        Inputs before the input matrix.
    coordinates : list of str
    protocol : str
    noise : float
    omega : ndarray of shape (n_trajectories,)
        Input frequencies.
    initial_states : ndarray of shape (n_trajectories, 2 * n_dof)
    """

    X: np.ndarray
    tau: np.ndarray | None
    groups: np.ndarray
    t: np.ndarray
    X_clean: np.ndarray
    u: np.ndarray | None
    coordinates: list
    protocol: str
    noise: float
    omega: np.ndarray
    initial_states: np.ndarray
    system_name: str = ""
    meta: dict = field(default_factory=dict)

    @property
    def feature_names(self) -> list:
        return state_names(self.coordinates)

    def to_frame(self) -> pd.DataFrame:
        """One DataFrame: ``trajectory``, ``t``, the X columns by name, then ``tau_<q>``."""
        df = pd.DataFrame(self.X, columns=self.feature_names)
        df.insert(0, "t", self.t)
        df.insert(0, "trajectory", self.groups)
        if self.tau is not None:
            for i, name in enumerate(self.coordinates):
                df[f"tau_{name}"] = self.tau[:, i]
        return df


def make_dataset(
    system: System,
    n_trajectories: int = 100,
    duration: float = 5.0,
    rate: float = 100.0,
    *,
    excitation: str | None = "paper",
    amplitude: float = 1.0,
    noise: float = 0.0,
    protocol: str = "shared",
    derivative_method: str = "pspline",
    random_state=None,
) -> Dataset:
    """Simulate a system from random initial states and add noise by a named protocol.

    Parameters
    ----------
    system : System
    n_trajectories : int, default=100
    duration : float, default=5.0
        Seconds per trajectory.
    rate : float, default=100.0
        Samples per second (the paper: 100 trajectories x 5 s x 100 Hz).
    excitation : {"paper", "sincos", None}, default="paper"
        ``"paper"``: the input form the paper's authors used for this system;
        ``"sincos"``: ``a sin(w t) + b cos(w t)`` on every input with
        ``a, b ~ U(-amplitude, amplitude)``; ``None``: passive (no input).
        Frequencies are ``w ~ U(pi/2, pi)``, one per trajectory.
    amplitude : float, default=1.0
    noise : float, default=0.0
        Standard deviation sigma of the zero-mean Gaussian noise.
    protocol : {"shared", "paper", "sensor"}, default="shared"
        ``"shared"``: one scalar sample per time step added to every channel (q,
        q_dot, q_ddot of every coordinate alike), as in the authors' code;
        ``"paper"``: independent noise on each entry of q, q_dot, q_ddot (as the
        paper's text describes); ``"sensor"``: noise on q alone, with q_dot and
        q_ddot estimated by :func:`lagsindy.differentiation.derivatives`.
    derivative_method : str, default="pspline"
        Differentiation method for the ``"sensor"`` protocol (see
        :func:`lagsindy.differentiation.derivatives`; ``"pspline"`` chooses its
        smoothing by generalized cross-validation, so it suits every noise level).
    random_state : int, RandomState instance or None, default=None
        Makes the data bit-for-bit reproducible.

    Returns
    -------
    Dataset
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"protocol must be one of {PROTOCOLS}, got {protocol!r}")
    if excitation not in EXCITATIONS:
        raise ValueError(f"excitation must be one of {EXCITATIONS}, got {excitation!r}")
    if noise < 0 or not math.isfinite(noise):
        raise ValueError(f"noise must be a finite standard deviation >= 0, got {noise}")
    n_steps = int(round(duration * rate))
    if n_trajectories < 1 or n_steps < 2:
        raise ValueError("need at least one trajectory of at least two samples")
    rng = check_random_state(random_state)
    n = system.n_dof
    m = system.n_inputs
    t = np.arange(n_steps) / rate
    x0 = system.sample_initial_states(n_trajectories, rng)
    omega = rng.uniform(math.pi / 2, math.pi, n_trajectories)
    if excitation == "paper":

        def u_fn(tt, _x):
            return system.paper_input(tt, omega)
    elif excitation == "sincos":
        a = rng.uniform(-amplitude, amplitude, (n_trajectories, m))
        b = rng.uniform(-amplitude, amplitude, (n_trajectories, m))

        def u_fn(tt, _x):
            return a * np.sin(omega[:, None] * tt) + b * np.cos(omega[:, None] * tt)
    else:
        u_fn = None
    states = system.simulate(x0, t, u_fn)  # (n_traj, n_steps, 2n)
    if u_fn is None:
        u = None
        tau = None
    else:
        u = np.stack([u_fn(tt, None) for tt in t], axis=1).reshape(-1, m)
        tau = u @ system.input_matrix.T
    flat = states.reshape(-1, 2 * n)
    X_clean = system.trajectory_to_X(flat, tau)
    groups = np.repeat(np.arange(n_trajectories), n_steps)
    t_rows = np.tile(t, n_trajectories)
    if protocol == "shared":
        X = X_clean + noise * rng.standard_normal((X_clean.shape[0], 1))
    elif protocol == "paper":
        X = X_clean + noise * rng.standard_normal(X_clean.shape)
    else:
        from ..differentiation import derivatives

        q = X_clean[:, :n] + noise * rng.standard_normal((X_clean.shape[0], n))
        X = derivatives(q, t_rows, groups=groups, method=derivative_method)
    return Dataset(
        X=X,
        tau=tau,
        groups=groups,
        t=t_rows,
        X_clean=X_clean,
        u=u,
        coordinates=list(system.coordinates),
        protocol=protocol,
        noise=float(noise),
        omega=omega,
        initial_states=x0,
        system_name=system.name,
    )
