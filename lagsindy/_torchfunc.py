r"""Euler-Lagrange parts of per-sample term functions by ``torch.func``.

The general path of :class:`lagsindy.evaluator.TermEvaluator`: a function
``fn(q, qd) -> Tensor (n_terms,)`` of one sample is differentiated by forward-mode
automatic differentiation and vmapped over chunks of samples. :math:`M_k \ddot q +
N_k \dot q` is one Jacobian-vector product of :math:`\nabla_{\dot q}\phi_k` along
:math:`(\dot q, \ddot q)`, which avoids forming the Hessians when only the columns
are needed. Each function also takes :class:`lagsindy._batched.TermKernels`, whose
terms in the batched monomial form go through its kernels instead.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable

import torch
from torch.func import jacfwd, jvp, vmap

from ._batched import TermKernels

DEFAULT_CHUNK_SIZE = 32_768

TermFunction = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@contextlib.contextmanager
def quiet_forward_ad():
    """Silence torch's own deprecation notice raised when forward AD first loads."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*torch.jit.script.*is deprecated")
        yield


def chunks(n: int, size: int):
    size = max(1, int(size))
    return (slice(start, min(n, start + size)) for start in range(0, n, size))


def _columns_one(fn: TermFunction):
    grad_qd = jacfwd(fn, argnums=1)  # (p, dof)

    def one(q, qd, qdd):
        _, total = jvp(grad_qd, (q, qd), (qd, qdd))  # M qdd + N qd, (p, dof)
        o = jacfwd(fn, argnums=0)(q, qd)  # (p, dof)
        return (total - o).transpose(0, 1)  # (dof, p)

    return one


def _gradients_one(fn: TermFunction):
    """``[d phi / dq, d phi / dqd]`` of one sample, (p, 2 dof)."""

    def grads(q1, qd1):
        return torch.cat(
            [jacfwd(fn, argnums=0)(q1, qd1), jacfwd(fn, argnums=1)(q1, qd1)], 1
        )

    return grads


def lagrangian_columns(
    fn: TermFunction,
    q: torch.Tensor,
    qd: torch.Tensor,
    qdd: torch.Tensor,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> torch.Tensor:
    """Euler-Lagrange columns of candidate functions at each sample.

    Parameters
    ----------
    fn : callable
        ``fn(q, qd) -> Tensor (n_terms,)`` for one sample (see
        :func:`lagsindy._expr.compile_torch`), differentiated by ``torch.func``; or
        :class:`lagsindy._batched.TermKernels` (from
        :func:`lagsindy._batched.compile_terms`), whose terms in the batched
        monomial form are evaluated as a few batched kernels instead.
    q, qd, qdd : Tensor of shape (n_samples, n_dof)
        Positions, velocities and accelerations.
    chunk_size : int, default=32768
        Samples processed at once (bounds memory).

    Returns
    -------
    Tensor of shape (n_samples, n_dof, n_terms)
        ``Theta[s, i, k] = (M_k qdd + N_k qd - O_k)_i`` at sample ``s``.
    """
    if isinstance(fn, TermKernels):
        return fn.columns_t(q, qd, qdd, general_columns(chunk_size)).permute(2, 0, 1)
    batched = vmap(_columns_one(fn))
    with quiet_forward_ad():
        parts = [
            batched(q[sl], qd[sl], qdd[sl]) for sl in chunks(q.shape[0], chunk_size)
        ]
    return torch.cat(parts, dim=0)


def lagrangian_components(
    fn: TermFunction,
    q: torch.Tensor,
    qd: torch.Tensor,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The paper's ``M_k``, ``N_k`` and ``O_k`` for every candidate at each sample.

    Parameters
    ----------
    fn : callable or TermKernels
        As for :func:`lagrangian_columns`.
    q, qd : Tensor of shape (n_samples, n_dof)
    chunk_size : int, default=32768

    Returns
    -------
    M : Tensor of shape (n_samples, n_terms, n_dof, n_dof)
        ``d2 phi_k / dqd_i dqd_j``.
    N : Tensor of shape (n_samples, n_terms, n_dof, n_dof)
        ``d2 phi_k / dqd_i dq_j``.
    O : Tensor of shape (n_samples, n_terms, n_dof)
        ``d phi_k / dq_i``.
    """
    if isinstance(fn, TermKernels):
        return fn.components(q, qd, general_components(chunk_size))
    grad_qd = jacfwd(fn, argnums=1)

    def one(q1, qd1):
        n_mat, m_mat = jacfwd(grad_qd, argnums=(0, 1))(q1, qd1)
        o = jacfwd(fn, argnums=0)(q1, qd1)
        return m_mat, n_mat, o

    batched = vmap(one)
    ms, ns, os_ = [], [], []
    for sl in chunks(q.shape[0], chunk_size):
        with quiet_forward_ad():
            m_mat, n_mat, o = batched(q[sl], qd[sl])
        ms.append(m_mat)
        ns.append(n_mat)
        os_.append(o)
    return torch.cat(ms), torch.cat(ns), torch.cat(os_)


def lagrangian_hessians(fn: TermFunction, q: torch.Tensor, qd: torch.Tensor):
    """Hessians of the terms over ``x = [q, qd]`` by ``torch.func``, (n, p, 2d, 2d).

    ``out[s, k, a, b] = d^2 phi_k / dx_a dx_b``: the general path of
    :meth:`lagsindy._batched.TermKernels.hessians`.
    """
    with quiet_forward_ad():
        jq, jqd = vmap(jacfwd(_gradients_one(fn), argnums=(0, 1)))(q, qd)
    return torch.cat([jq, jqd], dim=3)


def lagrangian_gradients(
    fn: TermFunction,
    q: torch.Tensor,
    qd: torch.Tensor,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> torch.Tensor:
    """``[d phi_k / dq, d phi_k / dqd]`` per sample, (n_samples, n_terms, 2 n_dof)."""
    if isinstance(fn, TermKernels):

        def general(f, q1, qd1):
            return lagrangian_gradients(f, q1, qd1, chunk_size=chunk_size)

        return fn.gradients(q, qd, general)
    batched = vmap(_gradients_one(fn))
    with quiet_forward_ad():
        parts = [batched(q[sl], qd[sl]) for sl in chunks(q.shape[0], chunk_size)]
    return torch.cat(parts, dim=0)


def general_columns(chunk_size):
    def general(f, q, qd, qdd):
        return lagrangian_columns(f, q, qd, qdd, chunk_size=chunk_size)

    return general


def general_components(chunk_size):
    def general(f, q, qd):
        return lagrangian_components(f, q, qd, chunk_size=chunk_size)

    return general
