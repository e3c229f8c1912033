r"""Mechanical models: a Lagrangian, dissipation and inputs, their equations of motion.

A :class:`MechanicalModel` is the one object behind both the benchmark systems and the
models that :class:`~lagsindy.LagrangianSINDy` learns. From a Lagrangian
:math:`L(q, \dot q)`, a Rayleigh dissipation function :math:`D(q, \dot q)`, extra
generalized forces :math:`Q(q, \dot q)` and an input matrix :math:`B`, it derives
once, symbolically,

.. math::

    M(q, \dot q)\,\ddot q + h(q, \dot q) = B u + Q - \partial D / \partial \dot q,
    \qquad M = \nabla_{\dot q}^2 L,\;
    h = (\nabla_q \nabla_{\dot q} L)\, \dot q - \nabla_q L,

and evaluates it with one compiled NumPy function of the state (the evaluator's
NumPy path, :class:`~lagsindy.evaluator.NumpyParts`) for inverse dynamics, forward
dynamics and simulation (:mod:`.simulation`).

A model can also be given by terms and coefficients, :math:`L = \sum_k c_k \phi_k`
(:meth:`MechanicalModel.from_terms`), with the terms sympy expressions or a torch
term function (no sympy Lagrangian: e.g. a robot's link energies); it then evaluates
:math:`M = \sum_k c_k M_k` and :math:`h = \sum_k c_k h_k` from the per-term parts of
a :class:`~lagsindy.evaluator.TermEvaluator`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import sympy as sp
import torch

from .._expr import canonical, check_coordinate_names, symbols_for
from ..evaluator import (
    NumpyParts,
    TermEvaluator,
    euler_lagrange_parts,
    is_term_function,
)
from . import simulation
from .checks import check_mass


def _lambdify_entries(args, exprs):
    """One numpy function for a list of expressions, broadcasting constants."""
    f = sp.lambdify(args, list(exprs), modules="numpy", cse=True)

    def evaluate(*values):
        shape = np.broadcast(*values).shape if values else ()
        out = f(*values)
        return [np.broadcast_to(np.asarray(v, dtype=float), shape) for v in out]

    return evaluate


class _SymbolicNumeric:
    """Numeric evaluation of a sympy Lagrangian's derived equations of motion."""

    def __init__(self, model):
        eq = model._derive()
        q, qd, _ = model.symbols
        n = model.n_dof
        self._args = list(q) + list(qd)
        mass_entries = [eq["mass"][i, j] for i in range(n) for j in range(n)]
        rest = [eq["bias"][i] - eq["forces"][i] for i in range(n)]
        self._exprs = mass_entries + rest
        self._parts = NumpyParts.from_expressions(
            model.coordinates, [mass_entries], [rest]
        )
        self._energy = _lambdify_entries(self._args, [eq["energy"]])
        self._floats = False  # not compiled yet (None: the math module cannot)

    def mass_and_rest(self, q, qd):
        mass, rest = self._parts.parts(q, qd)
        return mass[:, 0], rest[:, 0]

    def energy(self, q, qd):
        return self._energy(*q.T, *qd.T)[0].copy()

    def floats(self):
        """``f(q..., qd...)`` -> ``[M row-major..., bias - forces...]`` on floats, or
        None.

        Lambdified with the ``math`` module; None when an expression needs a function
        the math module lacks (the callers then keep the numpy path).
        """
        if self._floats is False:
            n = len(self._args) // 2
            try:
                f = sp.lambdify(self._args, self._exprs, modules="math", cse=True)
                values = [float(v) for v in f(*([0.1] * (2 * n)))]
            except Exception:  # a function the math module lacks: use numpy
                f, values = None, []
            self._floats = f if len(values) == n * n + n else None
        return self._floats


def _with_forces(dynamics, model, generalized):
    """``(q, qd) -> (M, h - Q)`` from a term function's own ``dynamics(q, qd) -> (M,
    h)`` and the generalized forces ``Q`` (sympy, lambdified with NumPy); None when
    NumPy cannot evaluate the forces (the caller keeps the torch path)."""
    acting = [i for i, g in enumerate(generalized) if g != 0]
    if not acting:
        return dynamics
    q, qd, _ = model.symbols
    one = sp.Dummy("one")  # every entry an array of the states' length, even a constant
    try:
        f = sp.lambdify(
            [*q, *qd, one], [one * generalized[i] for i in acting], "numpy", cse=True
        )
        f(*np.full((2 * model.n_dof + 1, 1), 0.5))
    except Exception:  # a function NumPy lacks
        return None
    every = len(acting) == model.n_dof

    def mass_and_rest(q_, qd_):
        mass, bias = dynamics(q_, qd_)
        values = np.stack(f(*q_.T, *qd_.T, np.ones(q_.shape[0])), axis=-1)
        if every:
            return mass, bias - values
        bias = bias.copy()
        bias[:, acting] -= values
        return mass, bias

    return mass_and_rest


class _TermNumeric:
    """Numeric evaluation of ``L = sum_k c_k phi_k`` through the terms' evaluator."""

    def __init__(self, model):
        n = model.n_dof
        _, qd, _ = model.symbols
        generalized = [
            model.forces[i] - sp.diff(model.dissipation, qd[i]) for i in range(n)
        ]
        forces = [generalized] if any(g != 0 for g in generalized) else []
        self.evaluator = TermEvaluator(
            model.coordinates, model.lagrangian_terms, forces
        )
        self.coef = np.asarray(model.lagrangian_coef, dtype=float)
        weights = np.concatenate([self.coef, np.ones(len(forces))])
        self.mass_and_rest = self.evaluator.numpy_model(weights)
        own = getattr(model.lagrangian_terms, "numpy_dynamics", None)
        if callable(own):  # the terms evaluate their own model: a robot's
            # rigid-body algorithms, far cheaper per call than torch on one state
            fast = _with_forces(own(self.coef), model, generalized)
            self.mass_and_rest = fast or self.mass_and_rest

    def energy(self, q, qd):
        q_t, qd_t = torch.as_tensor(q), torch.as_tensor(qd)
        return self.evaluator.energies(self.coef, q_t, qd_t).numpy()

    def floats(self):
        return None


class MechanicalModel:
    """Equations of motion of a Lagrangian system, and their simulation.

    Parameters
    ----------
    lagrangian : sympy.Expr or str
        :math:`L(q, \\dot q)` over the coordinates and their velocities (named
        ``<coordinate>_dot``). Strings are parsed without ``eval``.
    coordinates : sequence of str
        Generalized coordinate names, e.g. ``["x", "theta"]``.
    dissipation : sympy.Expr or str, optional
        Rayleigh dissipation function :math:`D`; its generalized force is
        :math:`-\\partial D / \\partial \\dot q`.
    forces : sequence of sympy.Expr or str, optional
        Extra generalized forces :math:`Q(q, \\dot q)` (one per coordinate), for
        non-smooth effects such as Coulomb friction.
    input_matrix : array-like of shape (n_dof, n_inputs), optional
        How inputs :math:`u` enter: generalized force :math:`B u`. Default: the
        identity (one input per coordinate).
    name : str, optional
        Display name.

    Attributes
    ----------
    n_dof : int
    n_inputs : int
    lagrangian_terms : sequence of sympy.Expr, torch term function or None
        The terms of a model given by terms (:meth:`from_terms`), else None.
    lagrangian_coef : ndarray of shape (n_terms,) or None
        Their coefficients.

    Examples
    --------
    >>> from lagsindy import MechanicalModel
    >>> pendulum = MechanicalModel("0.5*theta_dot**2 + 9.81*cos(theta)", ["theta"])
    >>> states = pendulum.simulate([0.1, 0.0], [0.0, 0.5, 1.0])
    >>> states.shape
    (3, 2)
    """

    def __init__(
        self,
        lagrangian,
        coordinates: Sequence[str],
        *,
        dissipation=None,
        forces=None,
        input_matrix=None,
        name: str | None = None,
    ):
        self.coordinates = check_coordinate_names(coordinates)
        self.lagrangian = canonical(lagrangian, self.coordinates)
        self._terms, self._coef = None, None
        self._set_forces_and_inputs(dissipation, forces, input_matrix, name)

    def _set_forces_and_inputs(self, dissipation, forces, input_matrix, name):
        self.dissipation = (
            sp.Integer(0)
            if dissipation is None
            else canonical(dissipation, self.coordinates)
        )
        n = len(self.coordinates)
        if forces is None:
            self.forces = [sp.Integer(0)] * n
        else:
            forces = list(forces)
            if len(forces) != n:
                raise ValueError(
                    f"forces must have one entry per coordinate ({n}), "
                    f"got {len(forces)}"
                )
            self.forces = [canonical(f, self.coordinates) for f in forces]
        if input_matrix is None:
            self.input_matrix = np.eye(n)
        else:
            b = np.asarray(input_matrix, dtype=float)
            if b.ndim == 1:
                b = b[:, None]
            if b.ndim != 2 or b.shape[0] != n:
                raise ValueError(
                    f"input_matrix must have shape (n_dof={n}, n_inputs), got {b.shape}"
                )
            self.input_matrix = b
        self.name = name or "model"

    @classmethod
    def from_terms(
        cls,
        coordinates: Sequence[str],
        terms,
        coef,
        *,
        dissipation=None,
        forces=None,
        input_matrix=None,
        name: str | None = None,
    ) -> MechanicalModel:
        """A model with Lagrangian ``sum_k coef[k] * terms[k]``, evaluated per term.

        Its mass matrix and bias come from the per-term parts of a
        :class:`~lagsindy.evaluator.TermEvaluator`, so the terms need not be sympy
        expressions: a torch term function (``names`` and ``fn(q, qd)``, see
        :mod:`lagsindy.evaluator`) simulates as well. Symbolic methods
        (:meth:`equations_of_motion`, :meth:`mass_matrix_expr`) need sympy terms.

        Parameters
        ----------
        coordinates : sequence of str
        terms : sequence of sympy.Expr or str, or a torch term function
        coef : array-like of shape (n_terms,)
        dissipation, forces, input_matrix, name
            As for :class:`MechanicalModel` (sympy expressions).

        Returns
        -------
        MechanicalModel
        """
        self = cls.__new__(cls)
        self.coordinates = check_coordinate_names(coordinates)
        if is_term_function(terms):
            n_terms, self.lagrangian = len(terms.names), None
        else:
            terms = [canonical(t, self.coordinates) for t in terms]
            n_terms = len(terms)
        coef = np.asarray(coef, dtype=float).ravel()
        if coef.shape != (n_terms,):
            raise ValueError(
                f"coef must have one entry per term ({n_terms}), got shape {coef.shape}"
            )
        if not is_term_function(terms):
            self.lagrangian = sp.Add(*[sp.Float(c) * t for c, t in zip(coef, terms)])
        self._terms, self._coef = terms, coef
        self._set_forces_and_inputs(dissipation, forces, input_matrix, name)
        return self

    @property
    def lagrangian_terms(self):
        """The terms of a model given by terms (:meth:`from_terms`), else None."""
        return self.__dict__.get("_terms")

    @property
    def lagrangian_coef(self) -> np.ndarray | None:
        """The coefficients of :attr:`lagrangian_terms`, else None."""
        return self.__dict__.get("_coef")

    # ------------------------------------------------------------------ symbolic
    @property
    def n_dof(self) -> int:
        """Number of generalized coordinates."""
        return len(self.coordinates)

    @property
    def n_inputs(self) -> int:
        """Number of inputs ``u`` (columns of ``input_matrix``; force ``B u``)."""
        return self.input_matrix.shape[1]

    @property
    def symbols(self):
        """``(q, qd, qdd)`` lists of sympy symbols."""
        return symbols_for(self.coordinates)

    def _derive(self):
        cache = self.__dict__.get("_equations")
        if cache is not None:
            return cache
        if self.lagrangian is None:
            raise TypeError(
                f"{self.name} is given by a torch term function, not a sympy "
                "Lagrangian: it has no symbolic equations (its numeric ones come "
                "from lagsindy.evaluator)"
            )
        q, qd, _ = self.symbols
        L = self.lagrangian
        grad_qd, mass, bias = euler_lagrange_parts(L, q, qd)
        mass = sp.Matrix(mass)
        generalized = [
            self.forces[i] - sp.diff(self.dissipation, qd[i]) for i in range(self.n_dof)
        ]
        energy = sum(v * g for v, g in zip(qd, grad_qd)) - L
        cache = {
            "mass": mass,
            "bias": [sp.expand(b) for b in bias],
            "forces": generalized,
            "energy": energy,
        }
        self._equations = cache
        return cache

    def equations_of_motion(self) -> list:
        """Symbolic equations ``M qdd + h - Q = B u`` (left-hand sides), one per
        coordinate."""
        eq = self._derive()
        _, _, qdd = self.symbols
        lhs = eq["mass"] * sp.Matrix(qdd)
        return [
            sp.simplify(lhs[i] + eq["bias"][i] - eq["forces"][i])
            for i in range(self.n_dof)
        ]

    def mass_matrix_expr(self) -> sp.Matrix:
        """Symbolic mass matrix ``d2L/dqdot2``."""
        return self._derive()["mass"]

    def _numeric(self):
        """The numeric evaluation (compiled once; dropped when pickled)."""
        cache = self.__dict__.get("_compiled")
        if cache is None:
            terms = self.__dict__.get("_terms")
            cache = (_SymbolicNumeric if terms is None else _TermNumeric)(self)
            self._compiled = cache
        return cache

    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop("_compiled", None)  # compiled code is rebuilt lazily
        return state

    # ------------------------------------------------------------------ numeric
    def _split_state(self, q, qd):
        q = np.atleast_2d(np.asarray(q, dtype=float))
        qd = np.atleast_2d(np.asarray(qd, dtype=float))
        if q.shape[-1] != self.n_dof or qd.shape != q.shape:
            raise ValueError(
                f"q and qd must have shape (n_samples, {self.n_dof}), got {q.shape} "
                f"and {qd.shape}"
            )
        return q, qd

    def _mass_and_rest(self, q, qd):
        """``M`` (S, d, d) and ``h - Q + dD/dqd`` (S, d) at the states."""
        return self._numeric().mass_and_rest(q, qd)

    def _float_terms(self):
        """``f(q..., qd...)`` -> ``[M row-major..., rest...]`` on Python floats, or None
        (see :mod:`.simulation`)."""
        return self._numeric().floats()

    def mass_matrix(self, q, qd) -> np.ndarray:
        """Mass matrix at each sample, shape (n_samples, n_dof, n_dof)."""
        q, qd = self._split_state(q, qd)
        return self._mass_and_rest(q, qd)[0]

    def inverse_dynamics(self, q, qd, qdd) -> np.ndarray:
        """Generalized forces ``B u`` for the accelerations, (n_samples, n_dof)."""
        q, qd = self._split_state(q, qd)
        qdd = np.atleast_2d(np.asarray(qdd, dtype=float))
        mass, rest = self._mass_and_rest(q, qd)
        return np.einsum("sij,sj->si", mass, qdd) + rest

    def forward_dynamics(self, q, qd, tau=None, *, t=None) -> np.ndarray:
        """Accelerations under generalized forces ``tau``, shape (n_samples, n_dof).

        Parameters
        ----------
        q, qd : array-like of shape (n_samples, n_dof)
        tau : array-like of shape (n_samples, n_dof), optional
            Generalized forces (already multiplied by the input matrix).
        t : array-like, optional
            Times, only used to locate a singular mass matrix in the error.

        Raises
        ------
        SingularMassMatrixError
            Where the mass matrix is singular or indefinite.
        """
        q, qd = self._split_state(q, qd)
        mass, rest = self._mass_and_rest(q, qd)
        rhs = (
            -rest
            if tau is None
            else np.asarray(tau, dtype=float).reshape(rest.shape) - rest
        )
        check_mass(self, mass, q, qd, t)
        return np.linalg.solve(mass, rhs[..., None])[..., 0]

    def energy(self, q, qd) -> np.ndarray:
        """Energy function ``sum qdot dL/dqdot - L`` at each sample, (n_samples,)."""
        q, qd = self._split_state(q, qd)
        return self._numeric().energy(q, qd)

    # ------------------------------------------------------------------ simulation
    def simulate(
        self,
        x0,
        t,
        tau=None,
        *,
        method: str = "DOP853",
        rtol: float = 1e-9,
        atol: float = 1e-9,
        max_step: float = np.inf,
    ) -> np.ndarray:
        """Integrate the equations of motion from ``x0`` over the times ``t``.

        Parameters
        ----------
        x0 : array-like of shape (2 * n_dof,) or (n_trajectories, 2 * n_dof)
            Initial state ``[q..., qdot...]``; a 2-D array integrates a batch of
            trajectories together (vectorised, one shared step size).
        t : array-like of shape (n_times,)
            Increasing output times; integration starts at ``t[0]``.
        tau : None, array-like or callable, optional
            Inputs ``u`` (``n_inputs`` per time; generalized force ``B u``): ``None``
            (unforced), an array sampled at ``t`` (shape (n_times, n_inputs), or
            (n_trajectories, n_times, n_inputs) for a batch; linearly interpolated),
            or a callable ``tau(t, state)`` returning (n_inputs,) or
            (n_trajectories, n_inputs).
        method : str, default="DOP853"
            Any :func:`scipy.integrate.solve_ivp` method.
        rtol, atol : float, default=1e-9
        max_step : float, default=inf

        Returns
        -------
        ndarray of shape (n_times, 2 * n_dof) or (n_trajectories, n_times, 2 * n_dof)

        Raises
        ------
        SingularMassMatrixError
            When the mass matrix becomes singular or indefinite along the way (the
            message names the time and the state).
        RuntimeError
            When the integrator fails for another reason.

        Notes
        -----
        With a sampled ``tau``, every step ends at a sample (the interpolated input
        has a kink there). For one trajectory of a 1- or 2-dof model with an explicit
        method (RK23, RK45, DOP853), the step is the method's tableau unrolled on
        Python floats, with scipy's error norm and step-size control: the same
        result as scipy's solver to rounding, several times faster.
        """
        return simulation.simulate(
            self, x0, t, tau, method=method, rtol=rtol, atol=atol, max_step=max_step
        )

    def trajectory_to_X(self, states, tau=None) -> np.ndarray:
        """``[q, qdot, qddot]`` rows from simulated states, with exact accelerations.

        Parameters
        ----------
        states : array-like of shape (n_samples, 2 * n_dof)
        tau : array-like of shape (n_samples, n_dof), optional
            Generalized forces ``B u`` at the same samples.
        """
        states = np.atleast_2d(np.asarray(states, dtype=float))
        n = self.n_dof
        qdd = self.forward_dynamics(states[:, :n], states[:, n:], tau)
        return np.concatenate([states, qdd], axis=1)

    # ------------------------------------------------------------------ display
    def equation(self, precision: int = 4) -> str:
        """Readable ``L = ...`` (and ``D = ...``, forces) with rounded numbers."""

        def fmt(e):
            return str(
                sp.sympify(e).xreplace(
                    {f: sp.Float(f, precision) for f in sp.sympify(e).atoms(sp.Float)}
                )
            )

        if self.lagrangian is None:  # a torch term function
            lagrangian = " + ".join(
                f"{c:.{precision}g}*{n}" for c, n in zip(self._coef, self._terms.names)
            )
            lines = [f"L = {lagrangian or 0}"]
        else:
            lines = [f"L = {fmt(self.lagrangian)}"]
        if self.dissipation != 0:
            lines.append(f"D = {fmt(self.dissipation)}")
        for name, f in zip(self.coordinates, self.forces):
            if f != 0:
                lines.append(f"Q_{name} = {fmt(f)}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        lagrangian = self.lagrangian if self.lagrangian is not None else self._terms
        return (
            f"MechanicalModel({self.name!r}, coordinates={self.coordinates}, "
            f"L={lagrangian})"
        )

    def __str__(self) -> str:
        return self.equation()
