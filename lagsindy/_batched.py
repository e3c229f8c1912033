r"""Batched Euler-Lagrange kernels for libraries of monomials in base features.

Most candidate terms are products of integer powers of *base features*: the
coordinates :math:`q_i`, the velocities :math:`\dot q_i`, and :math:`\sin(a \cdot q)`,
:math:`\cos(a \cdot q)` for linear forms :math:`a \cdot q` of the coordinates
(``sin(theta)``, ``cos(theta1 - theta2)``, ``sin(2*theta)``). The derivative of such a
monomial is again a sum of monomials (:math:`d \sin(a \cdot q)/dq_i = a_i \cos(a
\cdot q)`), so every entry of :math:`M_k`, :math:`N_k \dot q` and :math:`O_k` is known
at compile time as a short list of (coefficient, monomial) pairs. Evaluation is then a
handful of batched tensor operations for the whole library, whatever its size:

1. the base features of all samples (one ``sin``/``cos`` per distinct argument);
2. their powers (a table of successive products, no general ``pow``);
3. every distinct monomial as a product of a few gathered powers;
4. the columns as one sparse matrix product of coefficient-weighted monomials,
   written in place (``addmm``) into the caller's buffer.

Terms outside this form (``exp``, ``sqrt``, powers of sums, negative powers) keep the
general path: the sympy tree compiled by :func:`lagsindy._expr.compile_torch` and
differentiated by ``torch.func``. All tensors follow the device and dtype of the
input, so the same kernels run on CPU and CUDA.
"""

from __future__ import annotations

import functools
from collections import defaultdict
from collections.abc import Sequence

import numpy as np
import sympy as sp
import torch

from ._expr import compile_torch, symbols_for

# Elements (rows x entries) evaluated at once by the batched kernels: bounds the
# temporary memory to about 8 bytes times this per float64 tensor.
BATCH_ELEMENTS = 1 << 22


# ----------------------------------------------------------------- symbolic form
class _Unsupported(Exception):
    """A term that is not a polynomial in the base features."""


class _Features:
    """Registry of base features: ("q", i), ("qd", i), ("qdd", i), ("sin", a), ("cos", a).

    The accelerations only enter the Euler-Lagrange columns, never a term.
    """

    def __init__(self, n_dof):
        self.n_dof = n_dof
        self.keys = [(kind, i) for kind in ("q", "qd", "qdd") for i in range(n_dof)]
        self.index = {k: j for j, k in enumerate(self.keys)}

    def trig(self, kind, a):
        for k in ("sin", "cos"):  # both, so that derivatives stay in the registry
            if (k, a) not in self.index:
                self.index[(k, a)] = len(self.keys)
                self.keys.append((k, a))
        return self.index[(kind, a)]

    def derivative(self, f, var):
        """``d feature_f / d var`` as ``(coefficient, feature or None)``, or None if 0.

        ``var`` is ``("q", i)`` or ``("qd", i)``.
        """
        kind, arg = self.keys[f]
        if kind in ("q", "qd", "qdd"):
            return (1.0, None) if (kind, arg) == var else None
        if var[0] != "q" or arg[var[1]] == 0:
            return None
        a_i = arg[var[1]]
        if kind == "sin":
            return (a_i, self.index[("cos", arg)])
        return (-a_i, self.index[("sin", arg)])


def _mono(exps: dict) -> tuple:
    return tuple(sorted((f, e) for f, e in exps.items() if e))


def _poly_mul(a: dict, b: dict) -> dict:
    out = defaultdict(float)
    for ma, ca in a.items():
        for mb, cb in b.items():
            exps = dict(ma)
            for f, e in mb:
                exps[f] = exps.get(f, 0) + e
            out[_mono(exps)] += ca * cb
    return {m: c for m, c in out.items() if c != 0.0}


def _poly_add(a: dict, b: dict, scale: float = 1.0) -> dict:
    out = defaultdict(float, a)
    for m, c in b.items():
        out[m] += scale * c
    return {m: c for m, c in out.items() if c != 0.0}


def _poly_diff(p: dict, var, feats: _Features) -> dict:
    out = defaultdict(float)
    for mono, c in p.items():
        for f, e in mono:
            d = feats.derivative(f, var)
            if d is None:
                continue
            coef, g = d
            exps = dict(mono)
            exps[f] -= 1
            if g is not None:
                exps[g] = exps.get(g, 0) + 1
            out[_mono(exps)] += c * e * coef
    return {m: c for m, c in out.items() if c != 0.0}


def _to_poly(expr, symbols: dict, q, feats: _Features) -> dict:
    """A sympy expression as ``{monomial: coefficient}``; raises :class:`_Unsupported`."""
    if expr.is_Number:
        v = float(expr)
        return {(): v} if v != 0.0 else {}
    if expr.is_Symbol:
        if expr not in symbols:
            raise _Unsupported(expr)
        return {((symbols[expr], 1),): 1.0}
    if expr.is_Add:
        out = {}
        for a in expr.args:
            out = _poly_add(out, _to_poly(a, symbols, q, feats))
        return out
    if expr.is_Mul:
        out = {(): 1.0}
        for a in expr.args:
            out = _poly_mul(out, _to_poly(a, symbols, q, feats))
        return out
    if expr.is_Pow:
        e = expr.exp
        if not (e.is_Integer and int(e) >= 0):
            raise _Unsupported(expr)
        base = _to_poly(expr.base, symbols, q, feats)
        if len(base) != 1 or len(next(iter(base))) != 1:
            raise _Unsupported(expr)  # powers of sums: keep the general path
        ((mono, c),) = base.items()
        ((f, e0),) = mono
        return {((f, e0 * int(e)),): c ** int(e)}
    if expr.func in (sp.sin, sp.cos) and len(expr.args) == 1:
        arg = expr.args[0]
        if not arg.free_symbols or not arg.free_symbols <= set(q):
            raise _Unsupported(expr)
        coeffs = [arg.diff(s) for s in q]
        if not all(c.is_Number for c in coeffs):
            raise _Unsupported(expr)
        if sp.expand(arg - sum(c * s for c, s in zip(coeffs, q))) != 0:
            raise _Unsupported(expr)  # a constant offset
        a = tuple(float(c) for c in coeffs)
        f = feats.trig("sin" if expr.func is sp.sin else "cos", a)
        return {((f, 1),): 1.0}
    raise _Unsupported(expr)


def _sparse_matrix(indices, values, size):
    """A coalesced sparse COO matrix, its invariants checked.

    The global check is set explicitly around the construction: torch 2.11 warned
    "Sparse invariant checks are implicitly disabled" at every construction when
    only ``check_invariants=`` was passed (seen in a ``--quiet`` command's stderr).
    """
    with torch.sparse.check_sparse_tensor_invariants(enable=True):
        matrix = torch.sparse_coo_tensor(indices, values, size, check_invariants=True)
        return matrix.coalesce()


class _Kernel:
    """One batched output: ``out[r] = sum_u S[r, u] * monomial_u`` at every sample.

    The monomials are built level by level, each as a stored monomial with one
    factor fewer times one power of a base feature, so a monomial of ``m`` factors
    costs one multiplication. Everything here is numpy; :meth:`tensors` moves it to
    a device.
    """

    def __init__(self, n_out: int):
        self.n_out = n_out
        self.merged: dict[tuple, float] = defaultdict(float)

    def add(self, out: int, poly: dict):
        for mono, c in poly.items():
            self.merged[(out, mono)] += c

    def finish(self):
        entries = {k: c for k, c in self.merged.items() if c != 0.0}
        del self.merged
        closure = set()
        for _, mono in entries:
            while len(mono) > 1 and mono not in closure:
                closure.add(mono)
                mono = mono[:-1]
        factors = sorted(
            {fe for _, mono in entries for fe in mono}
            | {fe for mono in closure for fe in mono}
        )
        row = {(): 0}
        for fe in factors:
            row[(fe,)] = len(row)
        self.pow_feature = np.asarray([f for f, _ in factors], dtype=np.int64)
        self.pow_exponent = np.asarray([e for _, e in factors], dtype=np.int64)
        self.levels = []
        for length in range(2, 1 + max((len(m) for m in closure), default=1)):
            level = sorted(m for m in closure if len(m) == length)
            first = len(row)
            for m in level:
                row[m] = len(row)
            self.levels.append(
                (
                    first,
                    len(row),
                    np.asarray([row[m[:-1]] for m in level], dtype=np.int64),
                    np.asarray([row[(m[-1],)] for m in level], dtype=np.int64),
                )
            )
        self.n_rows = len(row)
        keys = sorted(entries, key=lambda k: (k[0], row[k[1]]))
        self.indices = np.asarray(
            [[k[0] for k in keys], [row[k[1]] for k in keys]], dtype=np.int64
        ).reshape(2, -1)
        self.values = np.asarray([entries[k] for k in keys], dtype=np.float64)
        # Powers by repeated multiplication (a table of x, x^2, ... of the features
        # that appear), not by a general pow: pow with a tensor of exponents costs
        # tens of nanoseconds per element.
        used = sorted({int(f) for f in self.pow_feature})
        position = {f: j for j, f in enumerate(used)}
        self.table_feature = np.asarray(used, dtype=np.int64)
        self.table_depth = int(self.pow_exponent.max(initial=1))
        self.table_index = np.asarray(
            [
                (int(e) - 1) * len(used) + position[int(f)]
                for f, e in zip(self.pow_feature, self.pow_exponent)
            ],
            dtype=np.int64,
        )
        self.level_width = max((b - a for a, b, _, _ in self.levels), default=0)
        self._cache = {}
        return self

    @property
    def width(self) -> int:
        return max(self.n_rows, self.n_out)

    def tensors(self, like: torch.Tensor):
        """Index tensors and sparse matrix of the kernel, on ``like``'s device/dtype."""
        key = (like.device, like.dtype)
        hit = self._cache.get(key)
        if hit is None:

            def long(a):
                return torch.as_tensor(a, dtype=torch.long, device=like.device)

            matrix = _sparse_matrix(
                long(self.indices),
                torch.as_tensor(self.values, dtype=like.dtype, device=like.device),
                (self.n_out, self.n_rows),
            )
            hit = (
                long(self.table_feature),
                long(self.table_index),
                [(a, b, long(p), long(f)) for a, b, p, f in self.levels],
                matrix,
            )
            self._cache[key] = hit
        return hit

    def blocks(self, like: torch.Tensor, n_blocks: int) -> list:
        """The sparse matrix split into ``n_blocks`` equal blocks of output rows."""
        key = (like.device, like.dtype, int(n_blocks))
        hit = self._cache.get(key)
        if hit is None:
            size = self.n_out // n_blocks
            hit = []
            for b in range(n_blocks):
                keep = (self.indices[0] >= b * size) & (
                    self.indices[0] < (b + 1) * size
                )
                idx = self.indices[:, keep].copy()
                idx[0] -= b * size
                hit.append(
                    _sparse_matrix(
                        torch.as_tensor(idx, dtype=torch.long, device=like.device),
                        torch.as_tensor(
                            self.values[keep], dtype=like.dtype, device=like.device
                        ),
                        (size, self.n_rows),
                    )
                )
            self._cache[key] = hit
        return hit

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_cache"] = {}
        return state

    def monomials(self, base: torch.Tensor, work: dict | None = None) -> torch.Tensor:
        """Every stored monomial ``(n_rows, n)`` from base features ``(n_features, n)``.

        ``work``: a dict kept between calls on as many samples, whose buffers are
        reused (no new memory per call).
        """
        table_feature, table_index, levels, _ = self.tensors(base)
        n = base.shape[1]
        work = {} if work is None else work

        def buffer(name, rows):
            buf = work.get(name)
            if (
                buf is None
                or buf.shape != (rows, n)
                or buf.dtype != base.dtype
                or buf.device != base.device
            ):
                buf = work[name] = base.new_empty((rows, n))
            return buf

        rows = buffer("rows", self.n_rows)
        rows[0] = 1.0
        n_pow = table_index.numel()
        if n_pow:
            if self.table_depth == 1:
                torch.index_select(base, 0, table_feature, out=rows[1 : 1 + n_pow])
            else:
                width = table_feature.numel()
                table = buffer("table", self.table_depth * width)
                torch.index_select(base, 0, table_feature, out=table[:width])
                for e in range(1, self.table_depth):
                    torch.mul(
                        table[(e - 1) * width : e * width],
                        table[:width],
                        out=table[e * width : (e + 1) * width],
                    )
                torch.index_select(table, 0, table_index, out=rows[1 : 1 + n_pow])
        if levels:
            left = buffer("left", self.level_width)
            right = buffer("right", self.level_width)
        for first, stop, parent, factor in levels:
            m = stop - first
            torch.index_select(rows, 0, parent, out=left[:m])
            torch.index_select(rows, 0, factor, out=right[:m])
            torch.mul(left[:m], right[:m], out=rows[first:stop])
        return rows

    def evaluate(
        self, base: torch.Tensor, out: torch.Tensor | None = None, work=None
    ) -> torch.Tensor:
        """Outputs ``(n_out, n)`` from the base features ``(n_features, n)``.

        ``out``: where to write them (else a new tensor); ``work``: see
        :meth:`monomials`.
        """
        matrix = self.tensors(base)[3]
        rows = self.monomials(base, work)
        if out is None:
            out = base.new_empty((self.n_out, base.shape[1]))
        return _sparse_mm_into(out, matrix, rows)

    def evaluate_blocks(self, base: torch.Tensor, outs: Sequence, work=None):
        """:meth:`evaluate` into ``outs``: one tensor per equal block of outputs.

        Each of ``outs`` has shape ``(n_out // len(outs), n)`` (e.g. one coordinate's
        columns inside a larger buffer).
        """
        rows = self.monomials(base, work)
        for matrix, out in zip(self.blocks(base, len(outs)), outs):
            _sparse_mm_into(out, matrix, rows)


def _sparse_mm_into(out, matrix, rows):
    """``out = matrix @ rows`` for a sparse ``matrix``, whatever ``out`` held.

    ``torch.addmm`` with ``beta=0`` ignores ``out``'s content (not even its NaNs
    propagate), except when the sparse matrix has no stored entry: then it leaves
    ``out`` untouched (torch 2.13), and a buffer from ``new_empty`` kept whatever
    memory held. A kernel without entries (every term's derivative is zero, as the
    mixed derivatives of a single pendulum's terms) must give zeros.
    """
    if matrix._nnz() == 0:
        return out.zero_()
    return torch.addmm(out, matrix, rows, beta=0, out=out)


@functools.lru_cache(maxsize=128)
def _compile_plan(terms: tuple, coordinates: tuple):
    """Symbolic derivatives of the supported terms as batched index tensors.

    Returns ``(plan, supported)``: ``supported`` are the indices of the terms in the
    batched form (``plan`` is None when there are none).
    """
    n = len(coordinates)
    q, qd, _ = symbols_for(coordinates)
    feats = _Features(n)
    symbols = {s: j for j, s in enumerate(list(q) + list(qd))}
    polys, supported = [], []
    for k, term in enumerate(terms):
        try:
            polys.append(_to_poly(sp.sympify(term), symbols, q, feats))
        except _Unsupported:
            continue
        supported.append(k)
    if not supported:
        return None, ()
    p = len(supported)
    kernels = {
        "columns": _Kernel(n * p),  # (dof, term)
        "mass": _Kernel(p * n * n),  # (term, dof, dof)
        "cross": _Kernel(p * n * n),
        "force": _Kernel(p * n),  # (term, dof)
        "grad": _Kernel(p * 2 * n),  # (term, [q dofs, qd dofs])
        "hess": _Kernel(p * 4 * n * n),  # (term, [q, qd], [q, qd])
    }
    for col, phi in enumerate(polys):
        grad_qd = [_poly_diff(phi, ("qd", i), feats) for i in range(n)]
        grad_q = [_poly_diff(phi, ("q", i), feats) for i in range(n)]
        for i in range(n):
            # Theta_i = sum_j M_ij qdd_j + sum_j N_ij qd_j - O_i: products with the
            # base features qdd_j and qd_j, so one polynomial per column.
            column = {k: -c for k, c in grad_q[i].items()}
            for j in range(n):
                m_ij = _poly_diff(grad_qd[i], ("qd", j), feats)
                n_ij = _poly_diff(grad_qd[i], ("q", j), feats)
                kernels["mass"].add((col * n + i) * n + j, m_ij)
                kernels["cross"].add((col * n + i) * n + j, n_ij)
                column = _poly_add(column, _poly_mul(m_ij, {((2 * n + j, 1),): 1.0}))
                column = _poly_add(column, _poly_mul(n_ij, {((n + j, 1),): 1.0}))
            kernels["columns"].add(i * p + col, column)
            kernels["force"].add(col * n + i, grad_q[i])
            kernels["grad"].add(col * 2 * n + i, grad_q[i])
            kernels["grad"].add(col * 2 * n + n + i, grad_qd[i])
        # Full Hessian over x = [q, qd] (the weak form's noise correction): row a
        # is d(d phi / d x_a) / d x_b.
        grads = grad_q + grad_qd
        for a, g_a in enumerate(grads):
            for b in range(2 * n):
                var = ("q", b) if b < n else ("qd", b - n)
                kernels["hess"].add(
                    (col * 2 * n + a) * 2 * n + b, _poly_diff(g_a, var, feats)
                )
    plan = {k: v.finish() for k, v in kernels.items()}
    plan["trig"] = [
        (kind, [(i, a) for i, a in enumerate(arg) if a != 0])
        for kind, arg in feats.keys[3 * n :]
    ]
    return plan, tuple(supported)


# ----------------------------------------------------------------- evaluation
class TermKernels:
    """Euler-Lagrange kernels of a list of candidate terms.

    Calling the object evaluates the terms at one sample, ``f(q, qd) -> (n_terms,)``
    (the general path, composable with ``torch.func``), exactly like the function of
    :func:`lagsindy._expr.compile_torch`. The methods evaluate derivatives for many
    samples at once: terms that are polynomials in the base features (see the module
    docstring) through the batched kernels, the others through ``torch.func``.

    Parameters
    ----------
    terms : sequence of sympy.Expr
    coordinates : sequence of str
    """

    def __init__(self, terms: Sequence[sp.Expr], coordinates: Sequence[str]):
        self.terms = [sp.sympify(t) for t in terms]
        self.coordinates = list(coordinates)
        self.n_dof = len(self.coordinates)
        self.plan, supported = _compile_plan(tuple(self.terms), tuple(self.coordinates))
        self.supported = np.asarray(supported, dtype=np.int64)
        self.general = np.setdiff1d(np.arange(len(self.terms)), self.supported)
        self._fn = None
        self._general_fn = None

    @property
    def n_terms(self) -> int:
        return len(self.terms)

    # ------------------------------------------------------------- general path
    def __call__(self, q, qd):
        if self._fn is None:
            q_s, qd_s, _ = symbols_for(self.coordinates)
            self._fn = compile_torch(self.terms, (q_s, qd_s))
        return self._fn(q, qd)

    def _general(self):
        if self._general_fn is None:
            q_s, qd_s, _ = symbols_for(self.coordinates)
            self._general_fn = compile_torch(
                [self.terms[k] for k in self.general], (q_s, qd_s)
            )
        return self._general_fn

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_fn"] = state["_general_fn"] = None
        return state

    # ------------------------------------------------------------- batched path
    def _base(self, q_t, qd_t, qdd_t, work=None):
        """Base features ``(n_features, n)``: q, qd, qdd, then sin/cos rows.

        ``work``: a dict kept between calls on as many samples; the features are
        written into its buffer.
        """
        d, n = self.n_dof, q_t.shape[1]
        n_features = 3 * d + len(self.plan["trig"])
        base = None if work is None else work.get("base")
        if (
            base is None
            or base.shape != (n_features, n)
            or base.dtype != q_t.dtype
            or base.device != q_t.device
        ):
            base = q_t.new_empty((n_features, n))
            if work is not None:
                work["base"] = base
        base[:d] = q_t
        base[d : 2 * d] = qd_t
        base[2 * d : 3 * d] = q_t if qdd_t is None else qdd_t  # qdd unused without it
        for k, (kind, arg) in enumerate(self.plan["trig"], start=3 * d):
            x = None
            for i, a in arg:
                term = q_t[i] if a == 1.0 else a * q_t[i]
                x = term if x is None else x + term
            (torch.sin if kind == "sin" else torch.cos)(x, out=base[k])
        return base

    def _batched(self, kind, q, qd, qdd=None):
        """``(n_out, n_samples)`` outputs of one kernel, in row batches."""
        kernel = self.plan[kind]
        step = max(256, BATCH_ELEMENTS // max(kernel.width, 1))
        n = q.shape[0]
        if n <= step:
            return kernel.evaluate(
                self._base(q.T, qd.T, None if qdd is None else qdd.T)
            )
        out = q.new_empty((kernel.n_out, n))
        work = {}
        for start in range(0, n, step):
            sl = slice(start, start + step)
            base = self._base(
                q[sl].T, qd[sl].T, None if qdd is None else qdd[sl].T, work
            )
            kernel.evaluate(base, out=out[:, sl], work=work)
        return out

    def columns_t(self, q, qd, qdd, general_columns):
        """Columns in the layout (n_dof, n_terms, n_samples)."""
        n, p = self.n_dof, self.n_terms
        out = q.new_empty((n, p, q.shape[0]))
        if self.plan is not None:
            ps = len(self.supported)
            vals = self._batched("columns", q, qd, qdd).reshape(n, ps, -1)
            if not self.general.size:
                return vals
            out[:, torch.as_tensor(self.supported, device=q.device)] = vals
        if self.general.size:
            g = general_columns(self._general(), q, qd, qdd)  # (n_samples, n, p_g)
            out[:, torch.as_tensor(self.general, device=q.device)] = g.permute(1, 2, 0)
        return out

    def columns_into(self, q, qd, qdd, out, general_columns, work=None):
        """:meth:`columns_t` written into ``out`` of shape (n_dof, n_terms, n_samples).

        When every term is batched, each coordinate's columns are written straight
        into ``out[i]`` (no intermediate tensor); ``work`` (a dict kept between
        calls on as many samples) holds the reused buffers.
        """
        if self.plan is None or self.general.size:
            out.copy_(self.columns_t(q, qd, qdd, general_columns))
            return out
        base = self._base(q.T, qd.T, qdd.T, work)
        self.plan["columns"].evaluate_blocks(
            base, [out[i] for i in range(self.n_dof)], work
        )
        return out

    def components(self, q, qd, general_components):
        """``M``, ``N`` (n, p, d, d) and ``O`` (n, p, d) of every term."""
        n, p, s = self.n_dof, self.n_terms, q.shape[0]
        m_out = q.new_empty((s, p, n, n))
        n_out = q.new_empty((s, p, n, n))
        o_out = q.new_empty((s, p, n))
        if self.plan is not None:
            ps = len(self.supported)
            idx = torch.as_tensor(self.supported, device=q.device)
            m_out[:, idx] = self._batched("mass", q, qd).T.reshape(s, ps, n, n)
            n_out[:, idx] = self._batched("cross", q, qd).T.reshape(s, ps, n, n)
            o_out[:, idx] = self._batched("force", q, qd).T.reshape(s, ps, n)
        if self.general.size:
            idx = torch.as_tensor(self.general, device=q.device)
            m_g, n_g, o_g = general_components(self._general(), q, qd)
            m_out[:, idx], n_out[:, idx], o_out[:, idx] = m_g, n_g, o_g
        return m_out, n_out, o_out

    def _per_term(self, kind, tail, q, qd, general):
        """Output ``kind`` of every term, shape (n, p, *tail): batched terms through
        their kernel, the others through ``general(function, q, qd)``."""
        s = q.shape[0]
        out = q.new_empty((s, self.n_terms, *tail))
        if self.plan is not None:
            vals = self._batched(kind, q, qd).T.reshape(s, len(self.supported), *tail)
            if not self.general.size:
                return out.copy_(vals)  # a plain copy: much cheaper than indexing
            out[:, torch.as_tensor(self.supported, device=q.device)] = vals
        if self.general.size:
            idx = torch.as_tensor(self.general, device=q.device)
            out[:, idx] = general(self._general(), q, qd)
        return out

    def mass_matrices(self, q, qd, general_components):
        """``M`` of every term, shape (n, p, d, d)."""
        n = self.n_dof

        def general(f, q_, qd_):
            return general_components(f, q_, qd_)[0]

        return self._per_term("mass", (n, n), q, qd, general)

    def mass_matrices_t(self, q, qd, general_components):
        """:meth:`mass_matrices` in the layout (p, d, d, n) (samples last).

        The kernel's own layout: without general terms no copy is made, and a
        combination of the terms' mass matrices is one matrix product.
        """
        n, s = self.n_dof, q.shape[0]
        if self.plan is not None and not self.general.size:
            return self._batched("mass", q, qd).reshape(self.n_terms, n, n, s)
        return self.mass_matrices(q, qd, general_components).permute(1, 2, 3, 0)

    def gradients(self, q, qd, general_gradients):
        """``[d phi / dq, d phi / dqd]`` per sample, shape (n, p, 2 d)."""
        return self._per_term("grad", (2 * self.n_dof,), q, qd, general_gradients)

    def gradients_t(self, q, qd, general_gradients):
        """:meth:`gradients` in the layout (p, 2 d, n) (samples last).

        The kernel's own layout: without general terms no copy is made.
        """
        if self.plan is not None and not self.general.size:
            return self._batched("grad", q, qd).view(self.n_terms, 2 * self.n_dof, -1)
        return self.gradients(q, qd, general_gradients).permute(1, 2, 0)

    def hessians(self, q, qd, general_hessians):
        r"""Hessians of every term over ``x = [q, qd]``, shape (n, p, 2 d, 2 d).

        ``out[s, k, a, b]`` is :math:`\partial^2 \phi_k / \partial x_a \partial x_b`
        at sample ``s``.
        """
        n2 = 2 * self.n_dof
        return self._per_term("hess", (n2, n2), q, qd, general_hessians)

    def hessians_t(self, q, qd, general_hessians):
        """:meth:`hessians` in the layout (p, 2 d, 2 d, n) (samples last).

        The kernel's own layout: without general terms no copy is made.
        """
        n2, s = 2 * self.n_dof, q.shape[0]
        if self.plan is not None and not self.general.size:
            return self._batched("hess", q, qd).reshape(self.n_terms, n2, n2, s)
        return self.hessians(q, qd, general_hessians).permute(1, 2, 3, 0)


def compile_terms(terms: Sequence[sp.Expr], coordinates: Sequence[str]) -> TermKernels:
    """Compile candidate terms into :class:`TermKernels` (batched where possible)."""
    return TermKernels(terms, coordinates)
