"""L1 problems for the solver tests: known minimisers, random Gram statistics."""

import numpy as np
import torch

from lagsindy.solvers import GramQuadratic, fista_batch


def known_lasso(p=8, collinear=1e-2, seed=0):
    """An ill-conditioned L1 problem built around a known sparse minimiser."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((200, p))
    A[:, 1] = A[:, 0] + collinear * rng.standard_normal(200)  # nearly collinear
    G = A.T @ A / 200
    lam = 0.05
    x = np.zeros(p)
    x[[0, 1, 4]] = [1.5, -0.7, 0.3]
    grad_off = 0.5 * lam * np.cos(np.arange(p))  # |grad| < lam off the support
    b = G @ x + lam * np.sign(x)
    off = x == 0
    b[off] = (G @ x)[off] - grad_off[off]
    return G, b, lam, x


def wandering_lasso(seed=1, p=30, n_on=15, collinear=1e-2):
    """An L1 problem with a known minimiser on which FISTA wanders among supports.

    Fifteen pairs of nearly collinear columns (condition number ~1e5) and half the
    coordinates in the support: FISTA's iterates change support for hundreds of
    iterations. The minimiser ``x`` is built in: ``b`` puts the gradient at
    ``-lam sign(x)`` on the support and strictly inside ``(-lam, lam)`` off it.
    """
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((300, p))
    for j in range(0, p - 1, 2):
        A[:, j + 1] = A[:, j] + collinear * A[:, j + 1]
    G = A.T @ A / 300
    lam = 1e-3
    x = np.zeros(p)
    on = rng.choice(p, n_on, replace=False)
    x[on] = rng.choice([-1.0, 1.0], n_on) * rng.uniform(0.2, 1.0, n_on)
    b = G @ x + lam * np.sign(x)
    off = x == 0
    b[off] = (G @ x)[off] - lam * rng.uniform(-0.9, 0.9, off.sum())
    return G, b, lam, x


def solve_stacked(problems):
    """:func:`fista_batch` from zero of ``problems`` (``(G, b, lam, x)``, one lam)."""
    G = np.stack([g for g, _, _, _ in problems])
    b = np.stack([b_ for _, b_, _, _ in problems])
    ones = np.ones_like(b)
    lam = problems[0][2]
    return fista_batch(
        G, b, np.zeros(len(problems)), lam, ones, np.zeros_like(b), ones > 0
    )


def gram_problem(A, y):
    """The :class:`GramQuadratic` of least squares ``y ~ A w``."""
    n = A.shape[0]
    A, y = torch.tensor(A), torch.tensor(y)
    return GramQuadratic(A.T @ A / n, A.T @ y / n, float(y @ y / n))


def random_gram(rng, n_rows, p, collinear=1e-3, n_true=3):
    """Gram statistics ``(G, b, c)`` of a noisy sparse regression whose first two
    columns are nearly collinear (slow directions: long FISTA runs)."""
    A = rng.standard_normal((n_rows, p))
    A[:, 1] = A[:, 0] + collinear * A[:, 1]
    truth = rng.choice([-1.0, 1.0], n_true) * rng.uniform(0.3, 1.0, n_true)
    y = A[:, :n_true] @ truth + 0.01 * rng.standard_normal(n_rows)
    return A.T @ A / n_rows, A.T @ y / n_rows, float(y @ y / n_rows)


class TensorGram(GramQuadratic):
    """A Gram quadratic that :func:`fista` iterates through the datafit contract
    (torch tensors, no exact finishes), as it does one on a GPU."""
