r"""Per-term Euler-Lagrange parts of candidate terms: the one evaluator.

For candidate terms :math:`\phi_k(q, \dot q)` and generalized force vectors
:math:`Q_j(q, \dot q)`, a :class:`TermEvaluator` gives, for batches of samples,

* the gradients :math:`\partial\phi_k/\partial q`, :math:`\partial\phi_k/\partial\dot q`
  and the Hessians over :math:`x = [q, \dot q]` (the weak form's noise correction);
* :math:`M_k = \nabla_{\dot q}^2 \phi_k`, :math:`N_k = \nabla_q \nabla_{\dot q}\phi_k`,
  :math:`O_k = \nabla_q \phi_k` and the bias :math:`h_k = N_k \dot q - O_k`;
* the columns :math:`\Theta_k = M_k \ddot q + N_k \dot q - O_k` (paper eqs. 5-8),
  followed by the force columns :math:`-Q_j`, so that ``Theta @ c = tau``;
* the force values :math:`Q_j` and their Jacobians over :math:`x`;
* the same ``(M_k, h_k)`` as one compiled NumPy function of the state
  (:meth:`TermEvaluator.numpy_parts`), for the many small calls of rollouts.

Everything that needs these parts (the Euler-Lagrange operator, the weak form,
refine's rollouts, case II, the simulation of models given by terms) asks this
evaluator, so a new kind of term only has to be a new *term provider*.

Term providers
--------------
``terms`` is one of

* a sequence of sympy expressions in the coordinates and their velocities
  (``<name>_dot``), as :class:`~lagsindy.CandidateLibrary` builds them. Terms that
  are monomials in :math:`q`, :math:`\dot q`, :math:`\sin(a\cdot q)`,
  :math:`\cos(a\cdot q)` are differentiated symbolically once and evaluated as
  batched kernels (:mod:`lagsindy._batched`); the others through ``torch.func``;
* a **torch term function**: any object with

  - ``names``: a sequence of ``n_terms`` strings (how the terms print), and
  - ``fn(q, qd) -> Tensor of shape (n_terms,)``: the terms at ONE sample, ``q`` and
    ``qd`` tensors of shape ``(n_dof,)`` (dtype and device of the data).

  ``fn`` must be built from torch operations that ``torch.func`` can transform
  (``jacfwd``, ``jvp``, ``vmap``): no in-place writes into its inputs, no ``.item()``
  or other conversion to Python numbers, no branching on values. It is
  differentiated by forward-mode automatic differentiation, vmapped over samples.
  This is how terms that are not sympy expressions come in (e.g. the energies of a
  robot's links, linear in their inertial parameters). :class:`TorchTerms` wraps a
  plain function. Optionally, batched methods that replace differentiation
  (:class:`lagsindy.robots.fitting.BaseTerms` has them, by the Newton-Euler
  recursion): ``columns(q, qd, qdd)`` (n, n_dof, n_terms), ``mass_matrices(q, qd)``
  (n, n_terms, n_dof, n_dof) and ``bias(q, qd)`` (n, n_terms, n_dof).

Force vectors are always sympy expressions (one per coordinate).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import numpy as np
import sympy as sp
import torch
from torch.func import vmap

from ._batched import TermKernels, compile_terms
from ._expr import compile_torch, symbols_for
from ._torchfunc import (  # noqa: F401  (DEFAULT_CHUNK_SIZE, TermFunction: re-exported)
    DEFAULT_CHUNK_SIZE,
    TermFunction,
    general_columns,
    general_components,
    lagrangian_columns,
    lagrangian_components,
    lagrangian_gradients,
    lagrangian_hessians,
)


class TorchTerms:
    """A torch term function: named terms computed by torch code.

    Parameters
    ----------
    names : sequence of str
        One name per term.
    fn : callable
        ``fn(q, qd) -> Tensor of shape (len(names),)`` at one sample, ``q`` and ``qd``
        of shape ``(n_dof,)``, differentiable by ``torch.func`` (see the module
        docstring).

    Examples
    --------
    >>> import torch
    >>> from lagsindy.evaluator import TermEvaluator, TorchTerms
    >>> def energies(q, qd):
    ...     return torch.stack([qd[0] ** 2, q[0] ** 2])
    >>> ev = TermEvaluator(["x"], TorchTerms(["x_dot**2", "x**2"], energies))
    >>> state = torch.ones(1, 1, dtype=torch.float64)
    >>> ev.mass_matrices(state, state)[0, :, 0, 0]
    tensor([2., 0.], dtype=torch.float64)
    """

    def __init__(self, names: Sequence[str], fn: TermFunction):
        self.names = [str(n) for n in names]
        self.fn = fn

    def __call__(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        return self.fn(q, qd)

    def __repr__(self) -> str:
        return f"TorchTerms({self.names})"


def _checked_provider(provider, n_dof: int):
    """The provider's ``fn``, after one call at a zero state shows its output."""
    zero = torch.zeros(n_dof, dtype=torch.float64)
    try:
        out = provider.fn(zero, zero)
    except Exception as exc:
        raise ValueError(
            f"the torch term function {provider!r} failed on one sample (q and qd "
            f"of shape ({n_dof},), float64): {exc}"
        ) from exc
    n = len(provider.names)
    if not torch.is_tensor(out) or tuple(out.shape) != (n,):
        shape = tuple(out.shape) if torch.is_tensor(out) else type(out).__name__
        raise ValueError(
            f"the torch term function {provider!r} must return a tensor of shape "
            f"({n},) (one value per name) for one sample, got {shape}"
        )
    return provider.fn


def is_term_function(terms) -> bool:
    """Whether ``terms`` is a torch term function (``names`` and ``fn``), not a list."""
    return hasattr(terms, "names") and callable(getattr(terms, "fn", None))


def library_terms(library):
    """The terms of a built library as the evaluator takes them: its torch term
    function when it has one (``library.torch_terms()``, e.g. a robot's), else its
    ``terms_``."""
    provider = getattr(library, "torch_terms", None)
    return provider() if callable(provider) else library.terms_


def subset_terms(terms, indices):
    """Terms at ``indices``: a list of sympy terms, or a torch term function (its
    ``subset(indices)`` when it has one, else a :class:`TorchTerms` picking them)."""
    indices = [int(k) for k in indices]
    if not is_term_function(terms):
        return [terms[k] for k in indices]
    if callable(getattr(terms, "subset", None)):
        return terms.subset(indices)
    fn = terms.fn
    index = torch.as_tensor(indices, dtype=torch.long)
    return TorchTerms(
        [terms.names[k] for k in indices],
        lambda q, qd: fn(q, qd).index_select(-1, index.to(q.device)),
    )


# ------------------------------------------------------------------- evaluator
class TermEvaluator:
    """Per-term Euler-Lagrange parts of candidate terms and force vectors.

    Parameters
    ----------
    coordinates : sequence of str
        Coordinate names (their order is the dof order).
    terms : sequence of sympy.Expr, or a torch term function
        The candidate functions :math:`\\phi_k(q, \\dot q)` (see the module
        docstring for the torch term function's contract).
    forces : sequence of sequence of sympy.Expr, optional
        Generalized force vectors ``Q_j(q, qd)``, one entry per coordinate.
    chunk_size : int, default=32768
        Samples differentiated at once by ``torch.func`` (bounds memory).

    Notes
    -----
    Every method takes tensors of shape (n_samples, n_dof) and follows their dtype
    and device. Methods ending in ``_t`` return the samples-last layout of the
    batched kernels (no transposing copy); the others put samples first.
    """

    def __init__(
        self,
        coordinates: Sequence[str],
        terms,
        forces: Sequence[Sequence[sp.Expr]] | None = None,
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
    ):
        self.coordinates = list(coordinates)
        self.forces = [list(f) for f in (forces or [])]
        self.chunk_size = chunk_size
        if is_term_function(terms):
            self.provider, self.terms = terms, None
            self._names = [str(n) for n in terms.names]
        else:
            # names of sympy terms are printed when asked for: printing costs
            # milliseconds per library, and operators are built by the dozen
            self.provider, self.terms, self._names = None, list(terms), None
        q, qd, _ = symbols_for(self.coordinates)
        self._symbols = (q, qd)
        self._compiled_fn = None
        self._forces_compiled = None
        self._numpy = None

    @property
    def n_dof(self) -> int:
        return len(self.coordinates)

    @property
    def names(self) -> list:
        """One name per term: the provider's, or the sympy terms printed."""
        if self._names is None:
            self._names = [str(t) for t in self.terms]
        return self._names

    @property
    def n_terms(self) -> int:
        return len(self.terms) if self.provider is None else len(self._names)

    @property
    def n_forces(self) -> int:
        return len(self.forces)

    @property
    def n_columns(self) -> int:
        return self.n_terms + self.n_forces

    @property
    def term_ids(self) -> tuple:
        """What identifies each term across evaluators: the sympy expression, or the
        torch term function with the term's name."""
        if self.provider is not None:
            return tuple((self.provider, n) for n in self.names)
        return tuple(self.terms)

    @property
    def fn(self):
        """Per-sample function of the terms, ``fn(q, qd) -> (n_terms,)`` (None without
        terms): the batched kernels (:class:`lagsindy._batched.TermKernels`, also
        callable per sample) for sympy terms, the provider's ``fn`` otherwise."""
        if self.provider is not None:
            if not self.n_terms:
                return None
            if self._compiled_fn is None:  # checked once: the provider's fn itself
                self._compiled_fn = _checked_provider(self.provider, self.n_dof)
            return self._compiled_fn
        if not self.terms:
            return None
        if self._compiled_fn is None:
            # monomials in q, qd, sin and cos of linear forms of q go through
            # batched kernels, the others through torch.func (lagsindy._batched)
            self._compiled_fn = compile_terms(self.terms, self.coordinates)
        return self._compiled_fn

    @property
    def kernels(self) -> TermKernels | None:
        """The batched kernels of sympy terms (None for a torch term function)."""
        fn = self.fn
        return fn if isinstance(fn, TermKernels) else None

    @property
    def fully_batched(self) -> bool:
        """Whether every term goes through the batched kernels."""
        k = self.kernels
        return k is not None and k.plan is not None and not k.general.size

    def column_work(self) -> int:
        """Elements per sample the column kernel works on besides its output (for
        sizing chunks that stay in cache); 0 without batched terms."""
        k = self.kernels
        if k is None or k.plan is None:
            return 0
        kernel = k.plan["columns"]
        return kernel.n_rows + 2 * kernel.level_width

    @property
    def _force_fn(self):
        """The force vectors compiled into one elementwise torch function (None
        without forces)."""
        if self._forces_compiled is None and self.forces:
            flat = [e for f in self.forces for e in f]
            self._forces_compiled = compile_torch(flat, self._symbols)
        return self._forces_compiled

    def __getstate__(self):
        state = self.__dict__.copy()  # compiled code is rebuilt lazily
        state["_numpy"] = state["_forces_compiled"] = None
        return state

    # ------------------------------------------------------------- values
    def values(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """The terms ``phi_k`` at each sample, shape (n_samples, n_terms)."""
        fn = self.fn
        if fn is None:
            return q.new_zeros((q.shape[0], 0))
        return vmap(fn)(q, qd)

    def force_values(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """Generalized forces ``Q_j``, shape (n_samples, n_dof, n_forces)."""
        if self._force_fn is None:
            return q.new_zeros((q.shape[0], self.n_dof, 0))
        # The compiled function is elementwise: given (n_dof, n) rows it evaluates
        # every sample at once, (n_forces * n_dof, n), without vmap.
        values = self._force_fn(q.T, qd.T).T
        return values.reshape(q.shape[0], self.n_forces, self.n_dof).transpose(1, 2)

    def force_jacobians(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """``d Q_ji / d x_b`` over ``x = [q, qd]``, shape (n, n_forces, n_dof, 2 n_dof).

        Each sample's forces depend on that sample only, so one reverse pass per
        force component over the sum of all samples gives every sample's gradient.
        (Reverse mode: forward-mode dual numbers would import ``torch._dynamo`` on
        their first product with a constant, seconds per process.)
        """
        return self.force_jacobians_t(q, qd).permute(3, 0, 1, 2)

    def force_jacobians_t(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
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
        return jac.reshape(self.n_forces, d, 2 * d, n)

    # ------------------------------------------------------------- columns
    def columns(
        self, q: torch.Tensor, qd: torch.Tensor, qdd: torch.Tensor
    ) -> torch.Tensor:
        """Columns ``Theta`` (terms, then ``-Q_j``), (n_samples, n_dof, n_columns)."""
        parts = []
        fast = getattr(self.provider, "columns", None)  # a provider's own recursion
        if callable(fast) and self.n_terms:
            parts.append(fast(q, qd, qdd))
        elif self.fn is not None:
            parts.append(
                lagrangian_columns(self.fn, q, qd, qdd, chunk_size=self.chunk_size)
            )
        if self._force_fn is not None:
            parts.append(-self.force_values(q, qd))
        if not parts:
            return q.new_zeros((q.shape[0], self.n_dof, 0))
        return torch.cat(parts, dim=2)

    def columns_t(
        self, q: torch.Tensor, qd: torch.Tensor, qdd: torch.Tensor
    ) -> torch.Tensor:
        """:meth:`columns` in the layout (n_dof, n_columns, n_samples)."""
        kernels = self.kernels
        if kernels is None and self.fn is not None:  # a plain per-sample function
            return self.columns(q, qd, qdd).permute(1, 2, 0)
        parts = []
        if kernels is not None:
            parts.append(
                kernels.columns_t(q, qd, qdd, general_columns(self.chunk_size))
            )
        if self._force_fn is not None:
            parts.append(-self.force_values(q, qd).permute(1, 2, 0))
        if not parts:
            return q.new_zeros((self.n_dof, 0, q.shape[0]))
        return torch.cat(parts, dim=1)

    def columns_into(self, q, qd, qdd, out: torch.Tensor, work: dict):
        """:meth:`columns_t` written into ``out`` (n_dof, n_columns, n_samples).

        ``work``: a dict kept between calls on as many samples, whose buffers the
        batched kernels reuse.
        """
        kernels = self.kernels
        if kernels is None or kernels.plan is None:
            out.copy_(self.columns_t(q, qd, qdd))
            return out
        p = self.n_terms
        kernels.columns_into(
            q, qd, qdd, out[:, :p], general_columns(self.chunk_size), work
        )
        if self._force_fn is not None:
            out[:, p:] = -self.force_values(q, qd).permute(1, 2, 0)
        return out

    # ------------------------------------------------------------- derivatives
    def components(self, q: torch.Tensor, qd: torch.Tensor):
        """``M_k``, ``N_k`` (n, n_terms, d, d) and ``O_k`` (n, n_terms, d) (see
        :func:`lagrangian_components`)."""
        fn = self.fn
        if fn is None:
            d, n = self.n_dof, q.shape[0]
            return (
                q.new_zeros((n, 0, d, d)),
                q.new_zeros((n, 0, d, d)),
                q.new_zeros((n, 0, d)),
            )
        return lagrangian_components(fn, q, qd, chunk_size=self.chunk_size)

    def parts(self, q: torch.Tensor, qd: torch.Tensor):
        """``M_k`` of the terms and the bias ``h`` of every column.

        Returns
        -------
        M : Tensor of shape (n_samples, n_terms, n_dof, n_dof)
        h : Tensor of shape (n_samples, n_columns, n_dof)
            ``N_k qd - O_k`` for the terms, then ``-Q_j`` for the forces, so that
            the model ``sum_k c_k phi_k`` with forces ``d_j Q_j`` has
            ``M(c) qdd + h(c) = tau``.
        """
        fast = getattr(self.provider, "bias", None)  # a provider's own recursion
        if callable(fast) and self.n_terms:
            mass, bias = self.provider.mass_matrices(q, qd), fast(q, qd)
        else:
            mass, n_mat, o = self.components(q, qd)
            bias = torch.einsum("skij,sj->ski", n_mat, qd) - o
        if self._force_fn is not None:
            bias = torch.cat([bias, -self.force_values(q, qd).transpose(1, 2)], dim=1)
        return mass, bias

    def mass_matrices(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """``M_k`` of every term, shape (n_samples, n_terms, n_dof, n_dof)."""
        kernels = self.kernels
        if kernels is not None:
            return kernels.mass_matrices(q, qd, general_components(self.chunk_size))
        fast = getattr(self.provider, "mass_matrices", None)
        if callable(fast) and self.n_terms:
            return fast(q, qd)
        return self.components(q, qd)[0]

    def mass_matrices_t(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """:meth:`mass_matrices` in the layout (n_terms, n_dof, n_dof, n_samples)."""
        kernels = self.kernels
        if kernels is not None:
            return kernels.mass_matrices_t(q, qd, general_components(self.chunk_size))
        return self.mass_matrices(q, qd).permute(1, 2, 3, 0)

    def gradients(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """``[d phi_k / dq, d phi_k / dqd]``, shape (n_samples, n_terms, 2 n_dof)."""
        if self.fn is None:
            return q.new_zeros((q.shape[0], 0, 2 * self.n_dof))
        return lagrangian_gradients(self.fn, q, qd, chunk_size=self.chunk_size)

    def gradients_t(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """:meth:`gradients` in the layout (n_terms, 2 n_dof, n_samples)."""
        kernels = self.kernels
        if kernels is not None:

            def general(f, q1, qd1):
                return lagrangian_gradients(f, q1, qd1, chunk_size=self.chunk_size)

            return kernels.gradients_t(q, qd, general)
        return self.gradients(q, qd).permute(1, 2, 0)

    def hessians(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """Hessians of every term over ``x = [q, qd]``, shape (n, n_terms, 2d, 2d)."""
        kernels = self.kernels
        if kernels is not None:
            return kernels.hessians(q, qd, lagrangian_hessians)
        if self.fn is None:
            n2 = 2 * self.n_dof
            return q.new_zeros((q.shape[0], 0, n2, n2))
        return lagrangian_hessians(self.fn, q, qd)

    def hessians_t(self, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """:meth:`hessians` in the layout (n_terms, 2d, 2d, n_samples)."""
        kernels = self.kernels
        if kernels is not None:
            return kernels.hessians_t(q, qd, lagrangian_hessians)
        return self.hessians(q, qd).permute(1, 2, 3, 0)

    # ------------------------------------------------------------- numpy path
    def numpy_parts(self) -> NumpyParts:
        """:meth:`parts` as one NumPy function of the state (compiled once, cached).

        For sympy terms, the parts are derived symbolically and lambdified into one
        vectorised function (common subexpressions shared), much faster than torch
        on the small batches of a rollout; a torch term function is evaluated
        through :meth:`parts`.
        """
        if self._numpy is None:
            if self.provider is None:
                self._numpy = _symbolic_parts(
                    tuple(self.coordinates),
                    tuple(self.terms),
                    tuple(tuple(f) for f in self.forces),
                )
            else:
                self._numpy = NumpyParts.from_torch(self)
        return self._numpy

    # ------------------------------------------------------------- one model
    def numpy_model(self, coef) -> Callable:
        """Mass matrix and bias of one model as a NumPy function of the state.

        The model is ``L = sum_k coef[k] phi_k`` with forces ``sum_j coef[n_terms
        + j] Q_j``: ``f(q, qd) -> (M, h)``, ``M`` of shape (S, n_dof, n_dof) and
        ``h`` of shape (S, n_dof), so that ``M qdd + h = tau``.

        Parameters
        ----------
        coef : array-like of shape (n_columns,)

        Returns
        -------
        callable
            Sympy terms: :meth:`numpy_parts` combined with ``coef``. A torch term
            function: reverse-mode derivatives of the scalar ``L`` (two passes and
            one per coordinate, whatever the number of terms: per call much cheaper
            than the per-term forward-mode parts).
        """
        coef = np.asarray(coef, dtype=float)
        if coef.shape != (self.n_columns,):
            raise ValueError(
                f"coef must have one entry per column ({self.n_columns}), got shape "
                f"{coef.shape}"
            )
        p = self.n_terms
        if self.provider is None:
            parts = self.numpy_parts()

            def combined(q, qd):
                mass, rest = parts.parts(q, qd)
                return (
                    np.einsum("skij,k->sij", mass, coef[:p]),
                    np.einsum("ski,k->si", rest, coef),
                )

            return combined

        def reverse(q, qd):
            q_t = torch.as_tensor(np.asarray(q, dtype=float))
            qd_t = torch.as_tensor(np.asarray(qd, dtype=float))
            mass, bias = self._model_parts(coef, q_t, qd_t)
            return mass.numpy(), bias.numpy()

        return reverse

    def _model_parts(self, coef, q: torch.Tensor, qd: torch.Tensor):
        """``(M, h)`` of one model by reverse-mode derivatives of its scalar ``L``."""
        d, n, p = self.n_dof, q.shape[0], self.n_terms
        x = torch.cat([q, qd], 1).detach().requires_grad_(True)
        c = torch.as_tensor(coef[:p], dtype=q.dtype, device=q.device)
        zeros = torch.zeros_like(x)
        with torch.enable_grad():
            lagrangian = self.values(x[:, :d], x[:, d:]) @ c
            grad = _grad_or_zero(lagrangian.sum(), x, zeros, create_graph=True)
            rows = [_grad_or_zero(grad[:, d + i].sum(), x, zeros) for i in range(d)]
        second = torch.stack(rows, 1) if rows else x.new_zeros((n, 0, 2 * d))
        mass, cross = second[:, :, d:], second[:, :, :d]
        bias = torch.einsum("sij,sj->si", cross, qd) - grad[:, :d].detach()
        if self.n_forces:
            w = torch.as_tensor(coef[p:], dtype=q.dtype, device=q.device)
            bias = bias - self.force_values(q, qd) @ w
        return mass.detach(), bias

    def energies(self, coef, q: torch.Tensor, qd: torch.Tensor) -> torch.Tensor:
        """Energy ``dL/dqd @ qd - L`` of ``L = sum_k coef[k] phi_k`` at each sample.

        Parameters
        ----------
        coef : array-like of shape (n_terms,)
        q, qd : Tensor of shape (n_samples, n_dof)

        Returns
        -------
        Tensor of shape (n_samples,)
        """
        d = self.n_dof
        x = torch.cat([q, qd], 1).detach().requires_grad_(True)
        c = torch.as_tensor(np.asarray(coef, dtype=float)[: self.n_terms]).to(q)
        with torch.enable_grad():
            lagrangian = self.values(x[:, :d], x[:, d:]) @ c
            grad = _grad_or_zero(lagrangian.sum(), x, torch.zeros_like(x))
        return ((qd * grad[:, d:]).sum(1) - lagrangian).detach()


def _grad_or_zero(output, x, zeros, create_graph=False):
    """``d output / d x`` (zeros where ``output`` does not depend on ``x``)."""
    if not output.requires_grad:
        return zeros
    (grad,) = torch.autograd.grad(
        output, x, create_graph=create_graph, retain_graph=True, allow_unused=True
    )
    return zeros if grad is None else grad


# ------------------------------------------------------------------- numpy path
def euler_lagrange_parts(phi: sp.Expr, q: Sequence, qd: Sequence):
    """Symbolic ``(dphi/dqd, M, h)`` of one expression.

    ``M[i][j] = d2 phi / dqd_i dqd_j`` and ``h[i] = sum_j (d2 phi / dqd_i dq_j) qd_j
    - d phi / dq_i``, so that the Euler-Lagrange expression of ``phi`` is
    ``M qdd + h``.
    """
    d = len(q)
    grad_v = [sp.diff(phi, v) for v in qd]
    mass = [[sp.diff(g, v) for v in qd] for g in grad_v]
    bias = [
        sum(sp.diff(grad_v[i], q[j]) * qd[j] for j in range(d)) - sp.diff(phi, q[i])
        for i in range(d)
    ]
    return grad_v, mass, bias


class NumpyParts:
    """Per-term parts ``M_k`` and ``h_k`` as one NumPy function of the state.

    Built by :meth:`TermEvaluator.numpy_parts` (or from expressions given directly,
    :meth:`from_expressions`). With ``M(c) = sum_k c_k M_k`` over the first
    ``n_lagrangian`` coefficients and ``h(c) = sum_k c_k h_k`` over all
    ``n_features``, the model has ``M(c) qdd + h(c) = tau``.

    Attributes
    ----------
    n_dof, n_lagrangian, n_features : int
    """

    def __init__(self, n_dof, n_lagrangian, n_features, evaluate):
        self.n_dof, self.n_lagrangian, self.n_features = n_dof, n_lagrangian, n_features
        self._evaluate = evaluate

    @classmethod
    def from_expressions(cls, coordinates, mass, rest):
        """Parts from sympy expressions.

        Parameters
        ----------
        coordinates : sequence of str
        mass : sequence of sequence of sympy.Expr
            Per term, its ``n_dof * n_dof`` mass-matrix entries (row-major).
        rest : sequence of sequence of sympy.Expr
            Per feature, its ``n_dof`` bias entries.

        Constant entries (most of them zero) are set once; only the others are
        evaluated, by one lambdified function that shares their common
        subexpressions.
        """
        q, qd, _ = symbols_for(coordinates)
        d = len(q)
        flat = [e for row in mass for e in row] + [e for row in rest for e in row]
        varying = [i for i, e in enumerate(flat) if e.free_symbols]
        constants = np.array(
            [0.0 if e.free_symbols else float(e) for e in flat], dtype=float
        )
        fn = sp.lambdify(
            [*q, *qd], [flat[i] for i in varying], modules="numpy", cse=True
        )
        k = len(mass) * d * d
        n_lag, n_feat = len(mass), len(rest)

        def evaluate(q_, qd_):
            s = q_.shape[0]
            values = np.tile(constants, (s, 1))
            if varying:
                values[:, varying] = np.column_stack(fn(*q_.T, *qd_.T))
            return (
                values[:, :k].reshape(s, n_lag, d, d),
                values[:, k:].reshape(s, n_feat, d),
            )

        return cls(d, n_lag, n_feat, evaluate)

    @classmethod
    def from_torch(cls, evaluator: TermEvaluator):
        """Parts of a torch term function, through :meth:`TermEvaluator.parts` (in
        float64 on the CPU)."""

        def evaluate(q_, qd_):
            q_t = torch.as_tensor(np.asarray(q_, dtype=float))
            qd_t = torch.as_tensor(np.asarray(qd_, dtype=float))
            mass, rest = evaluator.parts(q_t, qd_t)
            return mass.numpy(), rest.numpy()

        return cls(evaluator.n_dof, evaluator.n_terms, evaluator.n_columns, evaluate)

    def parts(self, q: np.ndarray, qd: np.ndarray):
        """``M`` (S, n_lagrangian, d, d) and ``h`` (S, n_features, d) at the states."""
        return self._evaluate(q, qd)


@functools.lru_cache(maxsize=64)
def _symbolic_parts(coordinates: tuple, terms: tuple, forces: tuple) -> NumpyParts:
    """:meth:`TermEvaluator.numpy_parts` of sympy terms, compiled once per term set."""
    q, qd, _ = symbols_for(coordinates)
    mass, rest = [], []
    for phi in terms:
        _, m, h = euler_lagrange_parts(phi, q, qd)
        mass.append([e for row in m for e in row])
        rest.append(h)
    for force in forces:
        rest.append([-f for f in force])
    return NumpyParts.from_expressions(coordinates, mass, rest)
