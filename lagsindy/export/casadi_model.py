"""CasADi functions of a model's equations of motion (for optimal control).

:func:`to_casadi` builds CasADi ``SX`` expressions from the model's sympy
equations (after :func:`sympy.cse`, so shared subexpressions stay shared) and wraps
them in :class:`casadi.Function` objects, which CasADi differentiates exactly and
can generate C code for. CasADi is an optional dependency
(``pip install lagsindy[casadi]``).
"""

from __future__ import annotations

from dataclasses import dataclass

import sympy as sp

from .equations import ModelEquations, model_equations
from .printing import common_subexpressions
from .python_code import symbolic


def _import_casadi():
    try:
        import casadi
    except ImportError:  # pragma: no cover - depends on the environment
        raise ImportError(
            "to_casadi needs CasADi, an optional dependency: pip install casadi "
            "(or pip install 'lagsindy[casadi]')"
        ) from None
    return casadi


def _converter(ca, symbols: dict):
    """A function sympy expression -> CasADi SX over ``symbols`` (memoized)."""
    functions = {
        sp.sin: ca.sin,
        sp.cos: ca.cos,
        sp.tan: ca.tan,
        sp.sinh: ca.sinh,
        sp.cosh: ca.cosh,
        sp.tanh: ca.tanh,
        sp.exp: ca.exp,
        sp.log: ca.log,
        sp.Abs: ca.fabs,
        sp.sign: ca.sign,
        sp.asin: ca.asin,
        sp.acos: ca.acos,
        sp.atan: ca.atan,
    }
    memo = dict(symbols)

    def convert(e):
        if e in memo:
            return memo[e]
        if e.is_Number:
            out = float(e)
        elif e.is_Add:
            args = [convert(a) for a in e.args]
            out = args[0]
            for a in args[1:]:
                out = out + a
        elif e.is_Mul:
            args = [convert(a) for a in e.args]
            out = args[0]
            for a in args[1:]:
                out = out * a
        elif e.is_Pow:
            base, exp = e.args
            b = convert(base)
            if exp.is_Integer:
                k = int(exp)
                out = ca.constpow(b, abs(k)) if abs(k) > 1 else b
                if k < 0:
                    out = 1.0 / out
                if k == 0:
                    out = 1.0
            elif exp == sp.Rational(1, 2):
                out = ca.sqrt(b)
            else:
                out = b ** convert(exp)
        elif e.func in functions:
            out = functions[e.func](convert(e.args[0]))
        else:
            raise ValueError(
                f"the expression {e} uses {e.func}, which to_casadi cannot convert"
            )
        memo[e] = out
        return out

    return convert, memo


@dataclass
class CasadiModel:
    """CasADi functions of a model (all differentiable, all ``casadi.Function``).

    Attributes
    ----------
    forward_dynamics : casadi.Function
        ``(x[2 n_dof], u[n_inputs]) -> q_ddot[n_dof]``.
    state_derivative : casadi.Function
        ``(x, u) -> [q_dot, q_ddot]`` (the ODE right-hand side for integrators and
        optimal control).
    inverse_dynamics : casadi.Function
        ``(q, q_dot, q_ddot) -> tau[n_dof]``, the generalized forces ``B u``.
    mass_matrix : casadi.Function
        ``(q, q_dot) -> M[n_dof x n_dof]``.
    energy : casadi.Function
        ``(q, q_dot) -> E``.
    n_dof, n_inputs : int
    coordinates : list of str
    input_matrix : ndarray of shape (n_dof, n_inputs)

    Notes
    -----
    Each function evaluates one state; ``f.map(n)`` evaluates n columns at once.
    """

    forward_dynamics: object
    state_derivative: object
    inverse_dynamics: object
    mass_matrix: object
    energy: object
    n_dof: int
    n_inputs: int
    coordinates: list
    input_matrix: object


def casadi_functions(eq: ModelEquations, name: str = "model") -> CasadiModel:
    """:class:`CasadiModel` of prepared equations (see :func:`to_casadi`)."""
    ca = _import_casadi()
    n, m = eq.n_dof, eq.n_inputs
    qs, vs, mass, rest, energy = symbolic(eq)
    q, qd = ca.SX.sym("q", n), ca.SX.sym("q_dot", n)
    qdd, u = ca.SX.sym("q_ddot", n), ca.SX.sym("u", m)
    symbols = {s: q[i] for i, s in enumerate(qs)}
    symbols.update({s: qd[i] for i, s in enumerate(vs)})
    replacements, reduced = common_subexpressions(mass + rest + [energy])
    convert, memo = _converter(ca, symbols)
    for sym, value in replacements:
        memo[sym] = convert(value)
    values = [convert(e) for e in reduced]
    M = ca.reshape(ca.vertcat(*[ca.SX(v) for v in values[: n * n]]), n, n).T
    r = ca.vertcat(*[ca.SX(v) for v in values[n * n : n * n + n]])
    E = ca.SX(values[-1])
    B = ca.DM(eq.input_matrix)
    x = ca.vertcat(q, qd)
    acc = ca.solve(M, ca.mtimes(B, u) - r)
    names = {"x": ["x", "u"], "q": ["q", "q_dot"]}
    return CasadiModel(
        forward_dynamics=ca.Function(
            f"{name}_forward_dynamics", [x, u], [acc], names["x"], ["q_ddot"]
        ),
        state_derivative=ca.Function(
            f"{name}_state_derivative",
            [x, u],
            [ca.vertcat(qd, acc)],
            names["x"],
            ["x_dot"],
        ),
        inverse_dynamics=ca.Function(
            f"{name}_inverse_dynamics",
            [q, qd, qdd],
            [ca.mtimes(M, qdd) + r],
            ["q", "q_dot", "q_ddot"],
            ["tau"],
        ),
        mass_matrix=ca.Function(f"{name}_mass_matrix", [q, qd], [M], names["q"], ["M"]),
        energy=ca.Function(f"{name}_energy", [q, qd], [E], names["q"], ["E"]),
        n_dof=n,
        n_inputs=m,
        coordinates=list(eq.coordinates),
        input_matrix=eq.input_matrix.copy(),
    )


def to_casadi(source, input_matrix=None, *, name: str = "model") -> CasadiModel:
    """CasADi functions of a model's forward and inverse dynamics, mass matrix, energy.

    Parameters
    ----------
    source : LagrangianSINDy, FittedLagrangian or MechanicalModel
        A fitted (or loaded) estimator, its ``fitted_`` state, or a model.
    input_matrix : array-like of shape (n_dof, n_inputs), optional
        How the inputs ``u`` enter (generalized force ``B u``); default: the
        model's own (the identity for a learned model).
    name : str, default="model"
        Prefix of the functions' names (CasADi's code generation uses them).

    Returns
    -------
    CasadiModel
        ``forward_dynamics(x, u)``, ``state_derivative(x, u)``,
        ``inverse_dynamics(q, q_dot, q_ddot)``, ``mass_matrix(q, q_dot)`` and
        ``energy(q, q_dot)`` as ``casadi.Function`` (exact derivatives by
        ``casadi.jacobian`` or the functions' ``jacobian()``).

    Raises
    ------
    ImportError
        When CasADi is not installed (``pip install casadi``).

    Examples
    --------
    >>> from lagsindy.systems import cart_pendulum
    >>> from lagsindy.export import to_casadi
    >>> f = to_casadi(cart_pendulum())  # doctest: +SKIP
    >>> f.forward_dynamics([0, 3.14, 0, 0], [0.0])  # doctest: +SKIP
    """
    _import_casadi()
    return casadi_functions(model_equations(source, input_matrix), name=name)


__all__ = ["CasadiModel", "casadi_functions", "to_casadi"]
