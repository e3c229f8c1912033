"""A standalone Python module (numpy only) of a model's equations of motion.

The module written by :func:`python_source` needs numpy and nothing else. Its
functions take states ``x = [q..., q_dot...]`` with any leading (batch) axes.

How it computes (measured in ``benchmarks/results/export.md``):

* the expressions are printed once with :func:`sympy.cse` for numpy arrays and once
  for Python floats with the ``math`` module (a single state, where numpy's per-call
  overhead would dominate);
* batches run in blocks of ``BLOCK`` states, whose temporaries stay in the cache
  (whole-array temporaries of a million states made the evaluation 3x slower);
* the mass matrix is solved by Gaussian elimination written out for the model's
  size, without pivoting; its pivots are the ratios of leading principal minors,
  which all have one sign exactly when the matrix is definite (Sylvester), as a
  valid mass matrix is. Rows whose pivots differ in sign or vanish are solved again
  with :func:`numpy.linalg.solve` (LU with partial pivoting), so an indefinite or
  singular mass matrix gives LAPACK's answer or its ``LinAlgError``, never a result
  of an unstable elimination. ``numpy.linalg.solve`` on every row was 4x slower
  than the elimination for the triple pendulum.
"""

from __future__ import annotations

import sympy as sp

from .equations import ModelEquations
from .printing import (
    MathExactPrinter,
    NumpyExactPrinter,
    check_printable,
    common_subexpressions,
    numbered,
)

# States per block of a batch evaluation.
BLOCK = 2048


def symbolic(eq: ModelEquations):
    """Mass entries (row-major), rest and energy over the symbols q0.., v0.."""
    n = eq.n_dof
    qs, vs = numbered("q", n), numbered("v", n)
    sub = {**dict(zip(eq.q, qs)), **dict(zip(eq.qd, vs))}
    # A factor 1.0 (a unit coefficient) is exact to drop and costs an operation.
    sub.update({sp.Float(1.0): sp.Integer(1), sp.Float(-1.0): sp.Integer(-1)})
    mass = [eq.mass[i, j].xreplace(sub) for i in range(n) for j in range(n)]
    rest = [r.xreplace(sub) for r in eq.rest]
    return qs, vs, mass, rest, eq.energy.xreplace(sub)


def _cse_lines(exprs, printer, indent="    "):
    """``(lines, values)``: cse assignments and the printed reduced expressions."""
    check_printable(exprs, printer)
    replacements, reduced = common_subexpressions(exprs)
    lines = [f"{indent}{sym} = {printer.doprint(value)}" for sym, value in replacements]
    return lines, [printer.doprint(e) for e in reduced]


def elimination_lines(n, mass, rhs, indent="    "):
    """Straight-line Gaussian elimination (no pivoting) of ``mass x = rhs``.

    ``mass`` holds the row-major names or values of the entries, ``rhs`` those of
    the right-hand side. Defines ``x0 .. x{n-1}`` and ``ok`` (the pivots share one
    sign and none is zero); works on floats and on numpy arrays alike.
    """
    a = [[mass[i * n + j] for j in range(n)] for i in range(n)]
    b = list(rhs)
    lines = []
    pivots = []
    for k in range(n):
        pivot = f"p{k}"
        lines.append(f"{indent}{pivot} = {a[k][k]}")
        pivots.append(pivot)
        a[k][k] = pivot
        for i in range(k + 1, n):
            f = f"f{i}_{k}"
            lines.append(f"{indent}{f} = {a[i][k]}/{pivot}")
            for j in range(k + 1, n):
                name = f"a{i}_{j}_{k}"
                lines.append(f"{indent}{name} = {a[i][j]} - {f}*{a[k][j]}")
                a[i][j] = name
            name = f"b{i}_{k}"
            lines.append(f"{indent}{name} = {b[i]} - {f}*{b[k]}")
            b[i] = name
    for i in range(n - 1, -1, -1):
        terms = "".join(f" - {a[i][j]}*x{j}" for j in range(i + 1, n))
        lines.append(f"{indent}x{i} = ({b[i]}{terms})/{a[i][i]}")
    if n == 1:
        lines.append(f"{indent}ok = p0 != 0.0")
    else:
        same = " & ".join(f"(p0*{p} > 0.0)" for p in pivots[1:])
        lines.append(f"{indent}ok = {same}")
    return lines


def _forward_function(name, args, inputs, mass, rest, printer, doc):
    """``def name(q.., v.., g..)`` returning ``(x0, .., ok)``: accelerations."""
    n = len(rest)
    lines = [
        f"def {name}({', '.join(map(str, list(args) + inputs))}):",
        f'    """{doc}"""',
    ]
    body, values = _cse_lines(mass + rest, printer)
    lines += body
    m_names = []
    for k, v in enumerate(values[: n * n]):
        lines.append(f"    m{k} = {v}")
        m_names.append(f"m{k}")
    rhs = []
    for i, v in enumerate(values[n * n :]):
        lines.append(f"    r{i} = {inputs[i]} - ({v})")
        rhs.append(f"r{i}")
    lines += elimination_lines(n, m_names, rhs)
    lines.append(f"    return ({''.join(f'x{i}, ' for i in range(n))}ok)")
    return lines


def _terms_function(name, args, mass, rest, printer, doc):
    n = len(rest)
    lines = [f"def {name}({', '.join(map(str, args))}):", f'    """{doc}"""']
    body, values = _cse_lines(mass + rest, printer)
    lines += body
    m = "".join(f"{v}, " for v in values[: n * n])
    r = "".join(f"{v}, " for v in values[n * n :])
    lines += ["    return (", f"        ({m}),", f"        ({r}),", "    )"]
    return lines


def _generalized_function(eq: ModelEquations):
    """``def _generalized_float(u0, ..)`` -> the generalized forces ``B u`` (floats)."""
    m = eq.n_inputs
    us = [f"u{j}" for j in range(m)]
    lines = [f"def _generalized_float({', '.join(us)}):"]
    out = []
    for row in eq.input_matrix:
        parts = [
            us[j] if float(b) == 1.0 else f"{float(b)!r}*{us[j]}"
            for j, b in enumerate(row)
            if float(b) != 0.0
        ]
        out.append(" + ".join(parts) if parts else "0.0")
    lines.append(f"    return ({''.join(f'{o}, ' for o in out)})")
    return lines


def _docstring(eq: ModelEquations, name: str) -> list:
    n = eq.n_dof
    lines = [
        f'"""{name}: equations of motion exported by lagsindy; needs numpy only.',
        "",
    ]
    lines += eq.provenance_lines()
    lines += [
        "",
        "Equations: M(q, q_dot) q_ddot + r(q, q_dot) = B u, with M = d2L/dq_dot2 and r",
        "the Coriolis, centrifugal, potential and dissipation terms.",
        "",
        "Functions (x = [q..., q_dot...]; leading axes are batches):",
        f"    forward_dynamics(x, u=None) -> q_ddot, shape (..., {n})",
        f"    state_derivative(x, u=None) -> [q_dot, q_ddot], shape (..., {2 * n})",
        f"    inverse_dynamics(q, q_dot, q_ddot) -> generalized forces B u, (..., {n})",
        f"    mass_matrix(q, q_dot) -> shape (..., {n}, {n})",
        "    energy(q, q_dot) -> shape (...)",
        f"u has shape (..., {eq.n_inputs}) (or (...) for a single input); None means",
        "no input.",
        '"""',
    ]
    return lines


_HELPERS = '''

def _state(x):
    x = numpy.asarray(x, dtype=float)
    if x.ndim == 0 or x.shape[-1] != 2 * N_DOF:
        raise ValueError(
            f"x must have shape (..., {2 * N_DOF}) = [q..., q_dot...], got {x.shape}"
        )
    return x


def _coordinates(*arrays):
    out = [numpy.asarray(a, dtype=float) for a in arrays]
    for a in out:
        if a.ndim == 0 or a.shape[-1] != N_DOF:
            raise ValueError(
                f"q, q_dot and q_ddot must have shape (..., {N_DOF}), got {a.shape}"
            )
    return numpy.broadcast_arrays(*out)


def _stack(values, shape):
    out = numpy.empty(shape + (len(values),))
    for k, value in enumerate(values):
        out[..., k] = value
    return out


def _generalized_forces(u, lead):
    """B u for inputs u of shape (..., N_INPUTS); with one input, u may also have
    the states' leading shape (``lead`` axes) or be a number."""
    u = numpy.asarray(u, dtype=float)
    if N_INPUTS == 1 and (u.ndim == 0 or u.ndim == lead):
        u = u[..., None]
    if u.shape[-1] != N_INPUTS:
        raise ValueError(f"u must have shape (..., {N_INPUTS}), got {u.shape}")
    return u @ INPUT_MATRIX.T


def _solve_rows(x, g):
    """Accelerations of rows x (n, 2 * N_DOF) by numpy.linalg.solve (pivoted LU)."""
    m, r = _terms(*x.T)
    shape = x.shape[:-1]
    mass = _stack(m, shape).reshape(shape + (N_DOF, N_DOF))
    rhs = g - _stack(r, shape)
    return numpy.linalg.solve(mass, rhs[..., None])[..., 0]


def _forward_one(x, u):
    """forward_dynamics of one state on Python floats."""
    if u is None:
        g = (0.0,) * N_DOF
    else:
        if isinstance(u, (float, int)):
            u = (float(u),)
        else:
            u = numpy.asarray(u, dtype=float).reshape(-1).tolist()
        if len(u) != N_INPUTS:
            raise ValueError(f"u must have {N_INPUTS} entries, got {len(u)}")
        g = _generalized_float(*u)
    try:
        out = _forward_float(*x.tolist(), *g)
    except (ZeroDivisionError, OverflowError):
        out = (False,)
    if out[-1]:
        return numpy.array(out[:-1])
    return _solve_rows(x[None], numpy.array(g))[0]


def forward_dynamics(x, u=None):
    """Accelerations q_ddot = M^-1 (B u - r) at states x = [q..., q_dot...].

    Parameters
    ----------
    x : array-like of shape (..., 2 * N_DOF)
    u : array-like of shape (..., N_INPUTS), optional
        Inputs (broadcast against x's leading axes); None: no input.

    Returns
    -------
    ndarray of shape (..., N_DOF)

    Raises
    ------
    numpy.linalg.LinAlgError
        Where the mass matrix is singular.
    """
    x = _state(x)
    if x.ndim == 1 and (u is None or numpy.ndim(u) <= 1):
        return _forward_one(x, u)
    if u is None:
        g = numpy.zeros(N_DOF)
    else:
        g = _generalized_forces(u, x.ndim - 1)
    shape = numpy.broadcast_shapes(x.shape[:-1], g.shape[:-1])
    x = numpy.broadcast_to(x, shape + (2 * N_DOF,)).reshape(-1, 2 * N_DOF)
    g = numpy.broadcast_to(g, shape + (N_DOF,)).reshape(-1, N_DOF)
    out = numpy.empty((x.shape[0], N_DOF))
    for start in range(0, x.shape[0], BLOCK):
        xb = numpy.ascontiguousarray(x[start : start + BLOCK].T)
        gb = numpy.ascontiguousarray(g[start : start + BLOCK].T)
        block = out[start : start + BLOCK]
        try:
            with numpy.errstate(divide="ignore", invalid="ignore", over="ignore"):
                *acc, ok = _forward_block(*xb, *gb)
        except (ZeroDivisionError, OverflowError):  # a constant zero pivot
            acc, ok = (), False
        for i, a in enumerate(acc):
            block[:, i] = a
        if not numpy.all(ok):
            bad = numpy.flatnonzero(~numpy.broadcast_to(ok, (xb.shape[1],)))
            block[bad] = _solve_rows(xb.T[bad], gb.T[bad])
    return out.reshape(shape + (N_DOF,))


def state_derivative(x, u=None):
    """[q_dot, q_ddot] at states x (the right-hand side for an ODE solver)."""
    x = _state(x)
    qdd = forward_dynamics(x, u)
    qd = numpy.broadcast_to(x[..., N_DOF:], qdd.shape)
    return numpy.concatenate([qd, qdd], axis=-1)


def inverse_dynamics(q, q_dot, q_ddot):
    """Generalized forces B u = M q_ddot + r, shape (..., N_DOF)."""
    q, qd, qdd = _coordinates(q, q_dot, q_ddot)
    args = [q[..., i] for i in range(N_DOF)] + [qd[..., i] for i in range(N_DOF)]
    m, r = _terms(*args)
    n = N_DOF
    out = _stack(r, q.shape[:-1])
    for i in range(n):
        for j in range(n):
            out[..., i] += m[i * n + j] * qdd[..., j]
    return out


def mass_matrix(q, q_dot):
    """Mass matrix M = d2L/dq_dot2, shape (..., N_DOF, N_DOF)."""
    q, qd = _coordinates(q, q_dot)
    args = [q[..., i] for i in range(N_DOF)] + [qd[..., i] for i in range(N_DOF)]
    m, _ = _terms(*args)
    return _stack(m, q.shape[:-1]).reshape(q.shape[:-1] + (N_DOF, N_DOF))


def energy(q, q_dot):
    """Energy function sum q_dot dL/dq_dot - L, shape (...)."""
    q, qd = _coordinates(q, q_dot)
    args = [q[..., i] for i in range(N_DOF)] + [qd[..., i] for i in range(N_DOF)]
    out = numpy.empty(q.shape[:-1])
    out[...] = _energy(*args)
    return out
'''


def python_source(eq: ModelEquations, name: str = "model") -> str:
    """The text of a standalone numpy module of ``eq`` (see the module docstring)."""
    n = eq.n_dof
    qs, vs, mass, rest, energy = symbolic(eq)
    args = qs + vs
    gs = [f"g{i}" for i in range(n)]
    matrix = [[float(v) for v in row] for row in eq.input_matrix]
    lines = _docstring(eq, name)
    lines += [
        "",
        "import math  # noqa: F401 - used by the single-state expressions",
        "",
        "import numpy",
        "",
        f"N_DOF = {n}",
        f"N_INPUTS = {eq.n_inputs}",
        f"COORDINATES = {tuple(eq.coordinates)!r}",
        f"INPUT_MATRIX = numpy.array({matrix!r})",
        f"BLOCK = {BLOCK}",
        "",
        "",
    ]
    numpy_printer, math_printer = NumpyExactPrinter(), MathExactPrinter()
    lines += _terms_function(
        "_terms",
        args,
        mass,
        rest,
        numpy_printer,
        "Mass matrix entries (row-major) and r, on numpy arrays.",
    )
    lines += ["", ""]
    lines += _forward_function(
        "_forward_block",
        args,
        gs,
        mass,
        rest,
        numpy_printer,
        "Accelerations (no pivoting) and whether the pivots share a sign; arrays.",
    )
    lines += ["", ""]
    lines += _forward_function(
        "_forward_float",
        args,
        gs,
        mass,
        rest,
        math_printer,
        "Accelerations (no pivoting) and whether the pivots share a sign; floats.",
    )
    lines += ["", ""]
    lines += _generalized_function(eq)
    lines += ["", ""]
    body, values = _cse_lines([energy], numpy_printer)
    lines += [f"def _energy({', '.join(map(str, args))}):", '    """The energy."""']
    lines += body + [f"    return {values[0]}"]
    return "\n".join(lines) + "\n" + _HELPERS


def load_python(source: str, name: str = "model"):
    """Execute module text from :func:`python_source` and return it as a module."""
    import types

    module = types.ModuleType(name)
    code = compile(source, f"<lagsindy export {name}>", "exec")
    exec(code, module.__dict__)  # noqa: S102 - text generated by python_source
    return module


__all__ = ["BLOCK", "elimination_lines", "load_python", "python_source", "symbolic"]
