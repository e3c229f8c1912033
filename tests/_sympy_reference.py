"""Reference values for the kernel tests: random states and sympy's columns."""

import numpy as np
import sympy as sp
import torch

from lagsindy._expr import symbols_for
from lagsindy.library import euler_lagrange_expressions


def random_states(n_dof, n, seed):
    """``q, qd, qdd`` tensors of ``n`` random states."""
    rng = np.random.default_rng(seed)
    return [
        torch.tensor(rng.uniform(lo, hi, (n, n_dof)))
        for lo, hi in ((-np.pi, np.pi), (-3, 3), (-3, 3))
    ]


def sympy_columns(terms, names, q, qd, qdd):
    """Theta[s, i, k] from sympy's Euler-Lagrange expressions."""
    q_s, qd_s, qdd_s = symbols_for(names)
    flat = [e for t in terms for e in euler_lagrange_expressions(t, names)]
    f = sp.lambdify(q_s + qd_s + qdd_s, flat, modules="numpy")
    n = q.shape[0]
    values = f(*q.numpy().T, *qd.numpy().T, *qdd.numpy().T)
    out = np.stack([np.broadcast_to(np.asarray(v, float), (n,)) for v in values], 1)
    return out.reshape(n, len(terms), len(names)).transpose(0, 2, 1)
