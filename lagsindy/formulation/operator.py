r"""Euler-Lagrange regression tensors by torch automatic differentiation.

For a library of candidate functions :math:`\phi_k(q, \dot q)` the Euler-Lagrange
operator applied to each candidate is, per sample (paper eqs. 5-8),

.. math::

    \Theta_{:, k} = M_k \ddot q + N_k \dot q - O_k, \quad
    M_k = \nabla_{\dot q}^\top \nabla_{\dot q} \phi_k, \;
    N_k = \nabla_q^\top \nabla_{\dot q} \phi_k, \;
    O_k = \nabla_q \phi_k,

so that a Lagrangian :math:`L = \sum_k c_k \phi_k` has generalized forces
:math:`\tau = \Theta c`. Derivatives come from ``torch.func`` (forward mode, vmapped
over samples); :math:`M_k \ddot q + N_k \dot q` is computed as one Jacobian-vector
product of :math:`\nabla_{\dot q}\phi_k` along :math:`(\dot q, \ddot q)`, which avoids
forming the Hessians when only :math:`\Theta` is needed.

Non-conservative force columns (Rayleigh dissipation, Coulomb friction, ...) enter
the same tensor as ``-Q_j(q, qdot)`` so that ``Theta @ c = tau`` still holds.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import hashlib
import warnings
from collections.abc import Callable, Sequence

import numpy as np
import sympy as sp
import torch
from torch.func import jacfwd, jvp, vmap

from .._batched import TermKernels, compile_terms
from .._expr import compile_torch, symbols_for
from .weak import _band, _correlate, _noise_block, _window_weights, bump_function

DEFAULT_CHUNK_SIZE = 32_768
# Elements (float64: 8 bytes each) of the buffers of one chunk of the strong-form Gram
# (``EulerLagrangeOperator.gram``): the columns are written and multiplied while
# they are still in the processor's cache, rather than streamed through memory.
GRAM_CACHE = 1 << 20
GRAM_MIN_CHUNK = 256
# Samples used to evaluate the weak form's noise correction (a sum over samples).
NOISE_ROWS = 10_000
# Elements (float64) of the weak form's integrands and gradient kernel output per
# chunk of trajectories (EulerLagrangeOperator._integrand_chunks).
WEAK_CHUNK = 1 << 19

# Per-window weak-form columns of the features kept for reuse (see reuse_weak_columns);
# None outside a reuse block.
_WEAK_REUSE = contextvars.ContextVar("lagsindy_weak_reuse", default=None)


@contextlib.contextmanager
def reuse_weak_columns():
    """Within the block, weak-form statistics of the same samples reuse the features.

    Refits of the same samples differ in their input (an input delay search) or in
    some features (diagnose adds effects), while each feature's window sums stay the
    same. Inside this block :meth:`EulerLagrangeOperator.weak_grams` keeps the
    features' Gram block, noise part and window columns (keyed by the samples,
    windows, sampling interval and noise covariance); a later call whose features
    are all among a kept call's gathers their block and only integrates its input,
    equal to a fresh call up to rounding. The kept columns go when the block ends.
    """
    token = _WEAK_REUSE.set({})
    try:
        yield
    finally:
        _WEAK_REUSE.reset(token)


TermFunction = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


@contextlib.contextmanager
def _quiet_forward_ad():
    """Silence torch's own deprecation notice raised when forward AD first loads."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*torch.jit.script.*is deprecated")
        yield


def _chunks(n: int, size: int):
    size = max(1, int(size))
    return (slice(start, min(n, start + size)) for start in range(0, n, size))


def _columns_one(fn: TermFunction):
    grad_qd = jacfwd(fn, argnums=1)  # (p, dof)

    def one(q, qd, qdd):
        _, total = jvp(grad_qd, (q, qd), (qd, qdd))  # M qdd + N qd, (p, dof)
        o = jacfwd(fn, argnums=0)(q, qd)  # (p, dof)
        return (total - o).transpose(0, 1)  # (dof, p)

    return one


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
        return fn.columns_t(q, qd, qdd, _general_columns(chunk_size)).permute(2, 0, 1)
    batched = vmap(_columns_one(fn))
    with _quiet_forward_ad():
        parts = [
            batched(q[sl], qd[sl], qdd[sl]) for sl in _chunks(q.shape[0], chunk_size)
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
        return fn.components(q, qd, _general_components(chunk_size))
    grad_qd = jacfwd(fn, argnums=1)

    def one(q1, qd1):
        n_mat, m_mat = jacfwd(grad_qd, argnums=(0, 1))(q1, qd1)
        o = jacfwd(fn, argnums=0)(q1, qd1)
        return m_mat, n_mat, o

    batched = vmap(one)
    ms, ns, os_ = [], [], []
    for sl in _chunks(q.shape[0], chunk_size):
        with _quiet_forward_ad():
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

    def grads(q1, qd1):
        return torch.cat(
            [jacfwd(fn, argnums=0)(q1, qd1), jacfwd(fn, argnums=1)(q1, qd1)], 1
        )

    with _quiet_forward_ad():
        jq, jqd = vmap(jacfwd(grads, argnums=(0, 1)))(q, qd)
    return torch.cat([jq, jqd], dim=3)


def _general_columns(chunk_size):
    def general(f, q, qd, qdd):
        return lagrangian_columns(f, q, qd, qdd, chunk_size=chunk_size)

    return general


def _general_components(chunk_size):
    def general(f, q, qd):
        return lagrangian_components(f, q, qd, chunk_size=chunk_size)

    return general


class EulerLagrangeOperator:
    """Regression tensor of a Lagrangian library and optional force terms.

    Parameters
    ----------
    coordinates : sequence of str
        Coordinate names (their order is the dof order).
    terms : sequence of sympy.Expr
        Lagrangian candidate functions of the coordinates and velocities.
    forces : sequence of sequence of sympy.Expr, optional
        Generalized force vectors ``Q_j(q, qd)`` (one entry per coordinate) of
        non-conservative candidates; their columns are ``-Q_j``.
    dtype : torch.dtype, default=torch.float64
    device : str or torch.device, default="cpu"
    chunk_size : int, default=32768

    Notes
    -----
    Columns are ordered: Lagrangian terms first, then force terms.
    """

    def __init__(
        self,
        coordinates: Sequence[str],
        terms: Sequence[sp.Expr],
        forces: Sequence[Sequence[sp.Expr]] | None = None,
        *,
        dtype: torch.dtype = torch.float64,
        device="cpu",
        chunk_size: int = DEFAULT_CHUNK_SIZE,
    ):
        self.coordinates = list(coordinates)
        self.terms = list(terms)
        self.forces = [list(f) for f in (forces or [])]
        self.dtype = dtype
        self.device = torch.device(device)
        self.chunk_size = chunk_size
        q, qd, _ = symbols_for(self.coordinates)
        self._symbols = (q, qd)
        # Terms that are monomials in q, qd, sin and cos of linear forms of q go
        # through batched kernels; the others through torch.func (lagsindy._batched).
        self._fn = compile_terms(self.terms, self.coordinates) if self.terms else None
        flat = [e for f in self.forces for e in f]
        self._force_fn = compile_torch(flat, (q, qd)) if flat else None

    @property
    def n_dof(self) -> int:
        return len(self.coordinates)

    @property
    def n_terms(self) -> int:
        return len(self.terms)

    @property
    def n_columns(self) -> int:
        return len(self.terms) + len(self.forces)

    def _split(self, X: torch.Tensor):
        n = self.n_dof
        return X[:, :n], X[:, n : 2 * n], X[:, 2 * n : 3 * n]

    def columns(self, X: torch.Tensor) -> torch.Tensor:
        """Regression tensor of shape (n_samples, n_dof, n_columns) at ``X``.

        ``X`` has columns ``[q..., qd..., qdd...]``.
        """
        q, qd, qdd = self._split(X)
        parts = []
        if self._fn is not None:
            parts.append(
                lagrangian_columns(self._fn, q, qd, qdd, chunk_size=self.chunk_size)
            )
        if self._force_fn is not None:
            parts.append(-self.force_values(q, qd))
        if not parts:
            return X.new_zeros((X.shape[0], self.n_dof, 0))
        return torch.cat(parts, dim=2)

    def force_values(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """Generalized forces ``Q_j`` of the force terms, shape (n_samples, n_dof, n_forces)."""
        if self._force_fn is None:
            return q.new_zeros((q.shape[0], self.n_dof, 0))
        # The compiled function is elementwise: given (n_dof, n) rows it evaluates
        # every sample at once, (n_forces * n_dof, n), without vmap.
        values = self._force_fn(q.T, qd.T).T
        return values.reshape(q.shape[0], len(self.forces), self.n_dof).transpose(1, 2)

    def force_jacobians(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """``d Q_ji / d x_b`` over ``x = [q, qd]``, shape (n, n_forces, n_dof, 2 n_dof).

        Each sample's forces depend on that sample only, so one reverse pass per
        force component over the sum of all samples gives every sample's gradient.
        (Reverse mode: forward-mode dual numbers would import ``torch._dynamo`` on
        their first product with a constant, seconds per process.)
        """
        return self._force_jacobians_t(q, qd).permute(3, 0, 1, 2)

    def _force_jacobians_t(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """:meth:`force_jacobians` in the layout (n_forces, n_dof, 2 n_dof, n)."""
        d, n = self.n_dof, q.shape[0]
        if self._force_fn is None:
            return q.new_zeros((0, d, 2 * d, n))
        x = torch.cat([q.T, qd.T]).detach().requires_grad_(True)  # (2d, n)
        rows = []
        with torch.enable_grad():
            out = self._force_fn(x[:d], x[d:])  # (n_forces * d, n)
            for r in range(out.shape[0] if out.requires_grad else 0):
                (grad,) = torch.autograd.grad(
                    out[r].sum(), x, retain_graph=True, allow_unused=True
                )
                rows.append(torch.zeros_like(x) if grad is None else grad)
        if not rows:  # constant forces
            rows = [torch.zeros_like(x)] * out.shape[0]
        jac = torch.stack(rows).detach()  # (n_forces * d, 2d, n)
        return jac.reshape(len(self.forces), d, 2 * d, n)

    def mass_matrices(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """``M_k`` of every Lagrangian term, shape (n_samples, n_terms, n_dof, n_dof)."""
        if self._fn is None:
            return q.new_zeros((q.shape[0], 0, self.n_dof, self.n_dof))
        return self._fn.mass_matrices(q, qd, _general_components(self.chunk_size))

    def mass_matrices_t(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """:meth:`mass_matrices` in the layout (n_terms, n_dof, n_dof, n_samples)."""
        if isinstance(self._fn, TermKernels):
            return self._fn.mass_matrices_t(q, qd, _general_components(self.chunk_size))
        return self.mass_matrices(q, qd).permute(1, 2, 3, 0)

    def gram(self, X: torch.Tensor, y: torch.Tensor | None = None, extra=None):
        """Per-dof Gram statistics of ``A = [Theta | extra | y]``, accumulated in chunks.

        Parameters
        ----------
        X : Tensor of shape (n_samples, 3 * n_dof)
        y : Tensor of shape (n_samples, n_dof), optional
            Target generalized forces, appended as the last column of ``A``.
        extra : Tensor of shape (n_samples, n_dof, n_extra), optional
            Further left-hand-side columns given per sample (e.g. a measured input,
            to test an input gain error).

        Returns
        -------
        Tensor of shape (n_dof, n_columns (+1), n_columns (+1))
            ``G[i] = A[:, i, :].T @ A[:, i, :]``, so Theta is never held in memory
            whole.
        """
        n_extra = 0 if extra is None else extra.shape[2]
        width = self._width(y, extra)
        out = X.new_zeros((self.n_dof, width, width))
        p, buf, work = self.n_columns, None, {}
        for sl in _chunks(X.shape[0], self._gram_chunk(width)):
            # layout (n_dof, columns, samples): one matrix product per dof, on a
            # buffer reused from chunk to chunk (cache-sized: its columns are
            # written, then read by the product while they are still in cache)
            m = sl.stop - sl.start
            if buf is None or buf.shape[2] != m:
                buf = X.new_empty((self.n_dof, width, m))
            self._columns_into(X[sl], buf[:, :p], work)
            if extra is not None:
                buf[:, p : p + n_extra] = extra[sl].permute(1, 2, 0)
            if y is not None:
                buf[:, -1] = y[sl].T
            out.baddbmm_(buf, buf.transpose(1, 2))
        return out

    def _gram_chunk(self, width: int) -> int:
        """Samples per chunk of :meth:`gram`: its buffers fit about ``GRAM_CACHE``."""
        per_sample = self.n_dof * width
        if isinstance(self._fn, TermKernels) and self._fn.plan is not None:
            kernel = self._fn.plan["columns"]
            per_sample += kernel.n_rows + 2 * kernel.level_width
        step = GRAM_CACHE // max(per_sample, 1)
        return max(GRAM_MIN_CHUNK, min(int(self.chunk_size), step))

    def _columns_into(self, X: torch.Tensor, out: torch.Tensor, work: dict):
        """:meth:`columns_t` written into ``out`` (n_dof, n_columns, n_samples)."""
        if not isinstance(self._fn, TermKernels) or self._fn.plan is None:
            out.copy_(self.columns_t(X))
            return out
        q, qd, qdd = self._split(X)
        p = self.n_terms
        self._fn.columns_into(
            q, qd, qdd, out[:, :p], _general_columns(self.chunk_size), work
        )
        if self._force_fn is not None:
            out[:, p:] = -self.force_values(q, qd).permute(1, 2, 0)
        return out

    def columns_t(self, X: torch.Tensor) -> torch.Tensor:
        """:meth:`columns` in the layout (n_dof, n_columns, n_samples)."""
        q, qd, qdd = self._split(X)
        if not isinstance(self._fn, TermKernels) and self._fn is not None:
            return self.columns(X).permute(1, 2, 0)  # a plain per-sample function
        parts = []
        if self._fn is not None:
            parts.append(
                self._fn.columns_t(q, qd, qdd, _general_columns(self.chunk_size))
            )
        if self._force_fn is not None:
            parts.append(-self.force_values(q, qd).permute(1, 2, 0))
        if not parts:
            return X.new_zeros((self.n_dof, 0, X.shape[0]))
        return torch.cat(parts, dim=1)

    def weak_gram(
        self,
        X: torch.Tensor,
        y: torch.Tensor | None,
        segments,
        *,
        window: int,
        stride: int,
        dt: float,
        noise_cov: torch.Tensor | None = None,
        noise_rows: int = NOISE_ROWS,
        extra: torch.Tensor | None = None,
        return_noise: bool = False,
    ):
        r"""Per-dof Gram statistics of the weak (integral) Euler-Lagrange equations.

        Multiplying the Euler-Lagrange equations by a test function :math:`\psi_w`
        supported on a window of ``window`` samples and integrating by parts gives,
        for each window and coordinate,

        .. math::

            \sum_k c_k \int \big(-\dot\psi_w \partial_{\dot q}\phi_k
            - \psi_w \partial_q \phi_k\big) dt - \sum_j d_j \int \psi_w Q_j dt
            = \int \psi_w \tau\, dt,

        which needs no accelerations and averages measurement noise over the window.
        With ``noise_cov`` (the covariance :math:`\Lambda` of white noise on
        :math:`[q, \dot q]`), the noise-induced part of the Gram matrix,
        :math:`\sum_w \sum_s J_{ws}^\top \Lambda J_{ws}` to first order in the noise
        (:math:`J_{ws}` the sensitivity of window :math:`w`'s columns to sample
        :math:`s`), is subtracted: an errors-in-variables correction of the
        attenuation that noisy regressors cause. The correction is a sum over samples;
        it is evaluated on at most ``noise_rows`` samples drawn with a fixed seed and
        scaled up (an unbiased estimate).

        Parameters
        ----------
        X : Tensor of shape (n_samples, >= 2 * n_dof)
            Rows ``[q, qd, ...]``; accelerations are not used.
        y : Tensor of shape (n_samples, n_dof) or None
            Generalized forces (assumed noise-free or independent of the noise on X).
        segments : list of LongTensor
            Rows of each trajectory, in time order, uniformly sampled; each at least
            ``window`` long.
        window, stride : int
            Samples per test function, and between window starts.
        dt : float
            Sampling interval.
        noise_cov : Tensor of shape (2 * n_dof, 2 * n_dof), optional
        noise_rows : int, default=10000
        extra : Tensor of shape (n_samples, n_dof, n_extra), optional
            Further left-hand-side integrands given per sample, integrated against
            the test functions like forces (no noise correction for them).
        return_noise : bool, default=False
            Return the uncorrected Gram and the noise part separately (their
            difference is the corrected Gram).

        Returns
        -------
        gram : Tensor of shape (n_dof, P, P)
            With ``P = n_columns (+ n_extra) (+ 1 for y)``; corrected for noise when
            ``noise_cov`` is given.
        noise : Tensor of shape (n_dof, P, P)
            Only with ``return_noise=True`` (then ``gram`` is uncorrected).
        n_windows : int
        """
        out = self.weak_grams(
            X,
            y,
            {int(window): segments},
            strides={int(window): stride},
            dt=dt,
            noise_cov=noise_cov,
            noise_rows=noise_rows,
            extra=extra,
            return_noise=return_noise,
        )
        return out[int(window)]

    def weak_grams(
        self,
        X: torch.Tensor,
        y: torch.Tensor | None,
        segments_by_window: dict,
        *,
        strides: dict,
        dt: float,
        noise_cov: torch.Tensor | None = None,
        noise_rows: int = NOISE_ROWS,
        extra: torch.Tensor | None = None,
        return_noise: bool = False,
        lazy: bool = False,
        per_segment: bool = False,
    ) -> dict:
        """:meth:`weak_gram` for several windows from one evaluation of the integrands.

        The per-sample integrands and (with ``noise_cov``) their sensitivities to the
        noise do not depend on the window, only their sums over windows do; so trying
        several windows costs little more than one.

        Parameters
        ----------
        segments_by_window : dict of int to list of LongTensor
            For each window (samples), the trajectories it is applied to (each at
            least that long); every window's segments must be among the first
            window's (the integrands are evaluated on those).
        strides : dict of int to int
            Samples between window starts, per window.
        lazy : bool, default=False
            Return, per window, a function of no arguments that sums the statistics
            when called (the shared integrands are evaluated now), so that windows
            never asked for cost nothing more. It also takes ``dt=`` (another
            sampling interval: the integrands do not depend on it, only the test
            functions do).
        per_segment : bool, default=False
            Keep each segment's statistics apart: ``gram`` (and ``noise``) get a
            leading axis over the window's segments and ``n_windows`` is an array
            (what a bootstrap over trajectories resamples). The noise part is then
            summed over every sample (``noise_rows`` is not used).

        Returns
        -------
        dict of int to tuple (or to a function returning it, with ``lazy=True``)
            Per window, ``(gram, n_windows)``, or ``(gram, noise, n_windows)`` with
            ``return_noise=True`` (see :meth:`weak_gram`).
        """
        d = self.n_dof
        windows = list(segments_by_window)
        base = list(segments_by_window[windows[0]])
        order = torch.cat(base)
        q, qd = X[order, :d], X[order, d : 2 * d]
        store = _WEAK_REUSE.get()
        key = None
        if store is not None and extra is None and not per_segment:
            key = self._reuse_key(
                X, order, segments_by_window, strides, dt, noise_cov, noise_rows
            )
            found = self._kept_block(store.get(key, ()), windows)
            if found is not None:
                return self._reused_grams(
                    *found, X, y, order, windows, dt, return_noise, lazy
                )
        lengths = [int(s.shape[0]) for s in base]
        chunks, owner = self._integrand_chunks(q, qd, order, y, extra, lengths)
        width = chunks[0][1].shape[2]
        # Where each base segment's rows sit (by its first row): its position among
        # all the rows, its length and the chunk of integrands that holds it.
        starts = np.cumsum([0] + lengths[:-1])
        offsets = {
            int(seg[0]): (int(start), length, c)
            for seg, start, length, c in zip(base, starts, lengths, owner)
        }
        sens = None
        if noise_cov is not None:
            rows = order.shape[0] if per_segment else noise_rows
            sens = self._noise_sensitivities(q, qd, rows)

        def build(window, dt=dt):
            stride = int(strides[window])
            psi, dpsi = (k.to(X) for k in bump_function(window, dt))
            grams, counts, slices, feats = [], [], [], []
            weights = [X.new_zeros(order.shape[0]) for _ in range(3)]
            bands = {}  # per segment length: the windows' banded matrices
            for seg in segments_by_window[window]:
                first, n, c = offsets[int(seg[0])]
                sl = slice(first, first + n)
                slices.append(sl)
                if n not in bands:
                    bands[n] = (_band(dpsi, n, stride), _band(psi, n, stride))
                band_a, band_b = bands[n]
                begin, a_int, b_int = chunks[c]
                here = slice(first - begin, first - begin + n)
                cols = -dt * (
                    _correlate(a_int[here], dpsi, stride, band_a)
                    + _correlate(b_int[here], psi, stride, band_b)
                )
                counts.append(cols.shape[0])
                by_dof = cols.transpose(0, 1)  # (dof, windows, columns)
                grams.append(torch.bmm(by_dof.transpose(1, 2), by_dof))
                if key is not None:
                    feats.append((sl, cols[:, :, : self.n_columns]))
                if sens is not None:
                    for acc, w in zip(
                        weights, _window_weights(n, -dt * dpsi, -dt * psi, stride)
                    ):
                        acc[sl] = w
            if per_segment:
                gram = (
                    torch.stack(grams) if grams else X.new_zeros((0, d, width, width))
                )
                n_windows = np.asarray(counts, dtype=np.int64)
            else:
                gram = X.new_zeros((d, width, width))
                for g in grams:
                    gram += g
                n_windows = sum(counts)
            noise = torch.zeros_like(gram)
            if sens is not None:
                noise = _noise_block(
                    d, sens, weights, noise_cov, width, slices if per_segment else None
                )
            if key is not None:  # the features' part, for fits with other forces
                ids = self._feature_ids()
                entries = store.setdefault(key, [])
                kept = next((e[1] for e in entries if e[0] == ids), None)
                if kept is None:
                    kept = {}
                    entries.append((ids, kept))
                pf = self.n_columns
                # copies: the caller owns the returned matrices (and may change them)
                kept[window] = (
                    gram[:, :pf, :pf].clone(),
                    noise[:, :pf, :pf].clone(),
                    n_windows,
                    stride,
                    feats,
                )
            return (
                (gram, noise, n_windows) if return_noise else (gram - noise, n_windows)
            )

        if lazy:
            return {w: functools.partial(build, w) for w in windows}
        return {w: build(w) for w in windows}

    def _integrand_chunks(self, q, qd, order, y, extra, lengths):
        """:meth:`_weak_integrands` by consecutive groups of whole segments.

        On the CPU a group holds about :data:`WEAK_CHUNK` elements of integrands and
        kernel output (at least one segment): the buffers stay in cache and are
        reused by the allocator, not mapped afresh (on 50,000 rows x 39 terms one
        block took 2x longer). On a GPU all rows form one group. The integrands
        are those of one call on all rows.

        Returns
        -------
        chunks : list of (start, a, b)
            The integrands (see :meth:`_weak_integrands`) of the rows
            ``order[start:start + len(a)]``.
        owner : list of int
            The chunk of each segment.
        """
        per_row = self.n_dof * 2 * (self._width(y, extra) + self.n_terms)
        # On a GPU one launch of each kernel over all rows costs less than many.
        on_cpu = q.device.type == "cpu"
        target = max(1, WEAK_CHUNK // per_row) if on_cpu else max(1, q.shape[0])
        bounds, owner, start, size = [], [], 0, 0
        for length in lengths:
            owner.append(len(bounds))
            size += length
            if size >= target:
                bounds.append((start, start + size))
                start, size = start + size, 0
        if size or not bounds:
            bounds.append((start, start + size))
        chunks = [
            (a, *self._weak_integrands(q[a:b], qd[a:b], order[a:b], y, extra))
            for a, b in bounds
        ]
        return chunks, owner

    def _width(self, y, extra) -> int:
        """Columns of the statistics and integrands: features, ``extra``, ``y``."""
        n_extra = 0 if extra is None else extra.shape[2]
        return self.n_columns + n_extra + (0 if y is None else 1)

    def _weak_integrands(self, q, qd, order, y, extra):
        """Integrands per sample, each of shape (n, n_dof, width): the a-weighted part
        (with dpsi: dphi/dqd, zeros beside it) and the b-weighted part (with psi:
        dphi/dq, the forces, ``-extra``, ``-y``).

        Written into two buffers: when every term is batched, straight from the
        gradient kernel's (term, [q, qd], sample) output, one transposing copy per
        coordinate and buffer.
        """
        d, n = self.n_dof, q.shape[0]
        p = self.n_terms
        f = len(self.forces)
        n_extra = 0 if extra is None else extra.shape[2]
        width = self._width(y, extra)
        a_int = q.new_zeros((n, d, width))
        b_int = q.new_empty((n, d, width))
        if self._fn is not None:
            kernels = self._fn
            batched = isinstance(kernels, TermKernels) and kernels.plan is not None
            if batched and not kernels.general.size:
                g = kernels._batched("grad", q, qd).view(p, 2 * d, n)
                # one 2-d transpose per coordinate: a third faster than one
                # 3-d permuted copy of each half
                for i in range(d):
                    a_int[:, i, :p] = g[:, d + i].T  # dphi/dqd_i: (n, p)
                    b_int[:, i, :p] = g[:, i].T  # dphi/dq_i
            else:
                g = lagrangian_gradients(kernels, q, qd, chunk_size=self.chunk_size)
                a_int[:, :, :p] = g[:, :, d:].transpose(1, 2)
                b_int[:, :, :p] = g[:, :, :d].transpose(1, 2)
        if self._force_fn is not None:
            b_int[:, :, p : p + f] = self.force_values(q, qd)  # (n, d, f)
        if extra is not None:
            # the column below is then +int psi e
            b_int[:, :, p + f : p + f + n_extra] = -extra[order]
        if y is not None:
            b_int[:, :, -1] = -y[order]  # so that the column below is +int psi tau
        return a_int, b_int

    def _reuse_key(self, X, order, segments_by_window, strides, dt, noise_cov, rows):
        """What the feature part of :meth:`weak_grams` depends on besides the
        features themselves (labelled by :meth:`_feature_ids`) and ``y``: the
        samples, the windows, the sampling interval and the noise correction."""
        d = self.n_dof
        digest = hashlib.blake2b(
            X[order, : 2 * d].detach().cpu().contiguous().numpy().tobytes(),
            digest_size=16,
        ).hexdigest()
        layout = tuple(
            (int(w), int(strides[w]), tuple((int(s[0]), len(s)) for s in segs))
            for w, segs in segments_by_window.items()
        )
        cov = None if noise_cov is None else noise_cov.detach().cpu().numpy().tobytes()
        return (
            tuple(self.coordinates),
            str(X.dtype),
            str(X.device),
            digest,
            layout,
            float(dt),
            cov,
            int(rows),
        )

    def _feature_ids(self) -> tuple:
        """What identifies each feature (column) across operators: its term or force."""
        return tuple(("term", t) for t in self.terms) + tuple(
            ("force", tuple(f)) for f in self.forces
        )

    def _kept_block(self, entries, windows):
        """``(kept, index)``: a reuse entry holding every feature of this operator
        (at ``index`` in its columns) for every window asked for, or None."""
        ids = self._feature_ids()
        for have, kept in entries:
            if all(w in kept for w in windows):
                position = {f: k for k, f in enumerate(have)}
                if all(f in position for f in ids):
                    return kept, [position[f] for f in ids]
        return None

    def _reused_grams(self, kept, index, X, y, order, windows, dt, return_noise, lazy):
        """:meth:`weak_grams` from a reuse block's kept feature columns and new ``y``.

        The feature block of each Gram matrix (and of its noise part) is gathered
        from the kept one at ``index``; the force row and column are sums of the kept
        feature columns times the new force's window integrals.
        """
        tau = None if y is None else y[order]
        index = torch.as_tensor(index, dtype=torch.long, device=X.device)
        pf = len(index)
        width = pf + (0 if y is None else 1)

        def build(window):
            kept_gram, kept_noise, n_windows, stride, feats = kept[window]
            gram = kept_gram.new_zeros((self.n_dof, width, width))
            noise = torch.zeros_like(gram)
            gram[:, :pf, :pf] = kept_gram[:, index][:, :, index]
            noise[:, :pf, :pf] = kept_noise[:, index][:, :, index]
            if tau is not None:
                psi, _ = (k.to(X) for k in bump_function(window, dt))
                cross = gram.new_zeros((self.n_dof, pf))
                square = gram.new_zeros(self.n_dof)
                for sl, cols in feats:
                    ycols = -dt * _correlate(-tau[sl], psi, stride)
                    cross += torch.einsum("wip,wi->ip", cols[:, :, index], ycols)
                    square += (ycols * ycols).sum(0)
                gram[:, :pf, pf] = cross
                gram[:, pf, :pf] = cross
                gram[:, pf, pf] = square
            return (
                (gram, noise, n_windows) if return_noise else (gram - noise, n_windows)
            )

        if lazy:
            return {w: functools.partial(build, w) for w in windows}
        return {w: build(w) for w in windows}

    def _noise_sensitivities(self, q, qd, noise_rows):
        """Rows used by the noise correction and the integrands' sensitivities there.

        Returns ``(rows, factor, h1, h2)``: ``rows`` the sample indices (``None``: all),
        ``factor`` the scale-up of the subsample, and ``h1[k, i, x, s]``,
        ``h2[k, i, x, s]`` the derivatives of the a- and b-integrands of feature ``k``
        and coordinate ``i`` with respect to ``x = [q, qd]`` at sample ``s`` (samples
        last: the kernels' own layout, in which :func:`~.weak._noise_block` needs no
        transposing copies).
        """
        d = self.n_dof
        n = q.shape[0]
        rows, factor = None, 1.0
        if n > noise_rows:
            pick = np.sort(
                np.random.default_rng(0).choice(n, noise_rows, replace=False)
            )
            rows = torch.as_tensor(pick, device=q.device)
            q, qd = q[rows], qd[rows]
            factor = n / noise_rows
        h1_parts, h2_parts = [], []
        if self._fn is not None:
            if isinstance(self._fn, TermKernels):
                hess = self._fn.hessians_t(q, qd, lagrangian_hessians)
            else:  # (p, 2d, 2d, n)
                hess = lagrangian_hessians(self._fn, q, qd).permute(1, 2, 3, 0)
            h1_parts.append(hess[:, d:])
            h2_parts.append(hess[:, :d])
        if self._force_fn is not None:
            jac = self._force_jacobians_t(q, qd)  # (f, d, 2d, n)
            h1_parts.append(torch.zeros_like(jac))
            h2_parts.append(jac)
        if len(h1_parts) == 1:  # views of the hessians: no copy needed
            return rows, factor, h1_parts[0], h2_parts[0]
        return rows, factor, torch.cat(h1_parts), torch.cat(h2_parts)


def forward_accelerations(
    operator: EulerLagrangeOperator,
    coef: torch.Tensor,
    X: torch.Tensor,
    tau: torch.Tensor | None = None,
) -> torch.Tensor:
    r"""Accelerations of the model ``sum_k c_k phi_k`` (paper eq. 10).

    :math:`\ddot q = M(c)^{+} (\tau - h(c))` with :math:`M(c) = \sum_k c_k M_k`
    (Moore-Penrose pseudo-inverse, as in the paper) and the velocity/position part
    :math:`h(c) = \Theta c - M(c) \ddot q` read off the regression tensor, so that
    force columns (dissipation) enter too. The ``qdd`` columns of ``X`` only serve to
    form :math:`h`; they cancel out.

    Returns
    -------
    Tensor of shape (n_samples, n_dof)
    """
    n = operator.n_dof
    q, qd, qdd = X[:, :n], X[:, n : 2 * n], X[:, 2 * n : 3 * n]
    theta = operator.columns(X)
    mass = operator.mass_matrices(q, qd)
    return accelerations_from(theta, mass, coef, qdd, tau)


def accelerations_from(theta, mass, coef, qdd, tau=None) -> torch.Tensor:
    """:func:`forward_accelerations` from precomputed columns and mass matrices.

    ``theta`` (n_samples, n_dof, n_features) holds the model's columns (Lagrangian
    terms, then force terms), ``mass`` (n_samples, n_terms, n_dof, n_dof) the
    per-term mass matrices of its Lagrangian terms.
    """
    mc = torch.einsum("skij,k->sij", mass, coef[: mass.shape[1]])
    bias = theta @ coef - torch.einsum("sij,sj->si", mc, qdd)
    rhs = -bias if tau is None else tau - bias
    return (torch.linalg.pinv(mc, hermitian=True) @ rhs.unsqueeze(-1)).squeeze(-1)


# ----------------------------------------------------------------------------- weak form
def lagrangian_gradients(
    fn: TermFunction,
    q: torch.Tensor,
    qd: torch.Tensor,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> torch.Tensor:
    """``[d phi_k / dq, d phi_k / dqd]`` per sample, shape (n_samples, n_terms, 2 * n_dof)."""
    if isinstance(fn, TermKernels):

        def general(f, q1, qd1):
            return lagrangian_gradients(f, q1, qd1, chunk_size=chunk_size)

        return fn.gradients(q, qd, general)

    def one(q1, qd1):
        return torch.cat(
            [jacfwd(fn, argnums=0)(q1, qd1), jacfwd(fn, argnums=1)(q1, qd1)], 1
        )

    batched = vmap(one)
    with _quiet_forward_ad():
        parts = [batched(q[sl], qd[sl]) for sl in _chunks(q.shape[0], chunk_size)]
    return torch.cat(parts, dim=0)
