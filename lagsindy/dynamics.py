r"""Mechanical models: a Lagrangian, dissipation and inputs, and their equations of motion.

A :class:`MechanicalModel` is the one object behind both the benchmark systems and the
models that :class:`~lagsindy.LagrangianSINDy` learns. From a Lagrangian
:math:`L(q, \dot q)`, a Rayleigh dissipation function :math:`D(q, \dot q)`, extra
generalized forces :math:`Q(q, \dot q)` and an input matrix :math:`B`, it derives
once, symbolically,

.. math::

    M(q, \dot q)\,\ddot q + h(q, \dot q) = B u + Q - \partial D / \partial \dot q,
    \qquad M = \nabla_{\dot q}^2 L,\;
    h = (\nabla_q \nabla_{\dot q} L)\, \dot q - \nabla_q L,

and evaluates it with lambdified numpy code (vectorised over samples) for inverse
dynamics, forward dynamics and simulation with :func:`scipy.integrate.solve_ivp`.
"""

from __future__ import annotations

import bisect
import math
import warnings
from collections.abc import Callable, Sequence

import numpy as np
import sympy as sp
from scipy.integrate import DOP853, RK23, RK45, solve_ivp

from ._expr import canonical, check_coordinate_names, symbols_for

# A mass matrix whose eigenvalues differ in sign, or whose smallest magnitude
# eigenvalue is below this fraction of the largest, is treated as singular.
MASS_MATRIX_RCOND = 1e-10
# After a failed integration, a mass matrix whose smallest eigenvalue fell below this
# fraction of its initial size is named as the cause.
NEAR_SINGULAR = 1e-3


_EXPLICIT_RK = {"RK23": RK23, "RK45": RK45, "DOP853": DOP853}


def _integrate_between(solver_class, rhs, t, y0, rtol, atol, max_step):
    """Integrate an explicit Runge-Kutta method stopping exactly at every ``t[k]``.

    A sampled input is linearly interpolated, so its slope jumps at every sample: a
    step across such a kink fails the error test again and again (150 right-hand
    side evaluations per sample at 1 kHz). Ending every step at the next sample keeps
    the input smooth within each step, and the step-size control carries over from
    one interval to the next.

    Returns
    -------
    states : ndarray of shape (len(t), len(y0))
    status : int
        0 on success, -1 when the solver failed.
    message : str
    """
    out = np.empty((t.size, y0.size))
    out[0] = y0
    solver = solver_class(
        rhs, t[0], y0, t[1], rtol=rtol, atol=atol, max_step=max_step, vectorized=False
    )
    for k in range(1, t.size):
        solver.t_bound = t[k]
        solver.status = "running"
        while solver.status == "running":
            message = solver.step()
            if solver.status == "failed":
                return out, -1, message
        out[k] = solver.y
    return (
        out,
        0,
        "The solver successfully reached the end of the integration interval.",
    )


def _float_stepper(solver_class, d):
    """One step of ``solver_class``'s Runge-Kutta tableau on ``d`` Python floats.

    The step is generated as straight-line code (every stage unrolled, zero
    coefficients dropped), so a small system pays neither numpy's per-call overhead
    nor scipy's step machinery. It returns ``(y_new, f_new, error_norm)`` with the
    same error norm as :mod:`scipy.integrate` (root-mean-square of the error over
    ``atol + rtol * max(|y|, |y_new|)``; DOP853's combined 5th/3rd order estimate).
    """
    key = (solver_class.__name__, d)
    cached = _STEPPERS.get(key)
    if cached is not None:
        return cached
    A, B, C = solver_class.A, solver_class.B, solver_class.C
    s = solver_class.n_stages
    comps = range(d)

    def combo(coefs, stage_names, i):
        terms = [f"{float(c)!r}*{k}_{i}" for c, k in zip(coefs, stage_names) if c != 0]
        return " + ".join(terms) if terms else "0.0"

    names = [f"k{j}" for j in range(s + 1)]
    ys = ", ".join(f"y_{i}" for i in comps)
    lines = [
        "def step(f, t, h, y, k0, rtol, atol):",
        f"    {ys}, = y",
        f"    {', '.join(f'k0_{i}' for i in comps)}, = k0",
    ]
    for j in range(1, s):
        arg = ", ".join(f"y_{i} + h*({combo(A[j, :j], names[:j], i)})" for i in comps)
        lines.append(
            f"    {', '.join(f'k{j}_{i}' for i in comps)}, = "
            f"f(t + {float(C[j])!r}*h, ({arg},))"
        )
    for i in comps:
        lines.append(f"    n_{i} = y_{i} + h*({combo(B, names[:s], i)})")
    new = ", ".join(f"n_{i}" for i in comps)
    lines.append(f"    fn = f(t + h, ({new},))")
    lines.append(f"    {', '.join(f'k{s}_{i}' for i in comps)}, = fn")
    for i in comps:
        lines.append(f"    c_{i} = atol + rtol*max(abs(y_{i}), abs(n_{i}))")
    if hasattr(solver_class, "E5"):
        e5 = " + ".join(
            f"(({combo(solver_class.E5, names, i)})/c_{i})**2" for i in comps
        )
        e3 = " + ".join(
            f"(({combo(solver_class.E3, names, i)})/c_{i})**2" for i in comps
        )
        lines += [
            f"    e5 = {e5}",
            f"    e3 = {e3}",
            "    if e5 == 0.0 and e3 == 0.0:",
            f"        return ({new},), fn, 0.0",
            f"    return ({new},), fn, abs(h)*e5/math.sqrt((e5 + 0.01*e3)*{d})",
        ]
    else:
        e = " + ".join(f"(({combo(solver_class.E, names, i)})/c_{i})**2" for i in comps)
        lines.append(f"    return ({new},), fn, abs(h)*math.sqrt(({e})/{d})")
    namespace = {"math": math}
    exec("\n".join(lines), namespace)  # noqa: S102 - code generated from the tableau above
    _STEPPERS[key] = namespace["step"]
    return namespace["step"]


_STEPPERS: dict = {}
# scipy's step-size controller constants (scipy.integrate._ivp.rk).
_SAFETY, _MIN_FACTOR, _MAX_FACTOR = 0.9, 0.2, 10.0


def _integrate_floats(solver_class, rhs, segment, t, y0, rtol, atol, max_step):
    """Sample-to-sample integration like :func:`_integrate_between`, on Python floats.

    ``rhs(t, y)`` takes and returns tuples of floats; ``segment(k)`` is called before
    the steps of each interval ``[t[k], t[k+1]]`` (it sets the input's piece there).
    The step-size control is scipy's: a rejected step shrinks by ``0.9 err^(-1/(p+1))``
    (at least 0.2x), an accepted one grows by at most 10x, and ``max_step`` bounds it.

    Returns
    -------
    states : list of tuples, status : int (0 or -1), message : str, last : (t, y)
    """
    exponent = -1.0 / (solver_class.error_estimator_order + 1)
    if rtol < 100 * np.finfo(float).eps:  # as scipy does
        warnings.warn(
            f"rtol={rtol:g} is below 100 machine epsilons; "
            f"using {100 * np.finfo(float).eps:.3g}",
            stacklevel=3,
        )
        rtol = 100 * np.finfo(float).eps
    stepper = _float_stepper(solver_class, len(y0))
    times = t.tolist()
    y = tuple(float(v) for v in y0)
    out = [y]
    segment(0)
    f = tuple(rhs(times[0], y))
    h_abs = min(max_step, times[1] - times[0])
    for k in range(times.__len__() - 1):
        segment(k)
        tt, t_end = times[k], times[k + 1]
        while tt < t_end:
            min_step = 10 * math.ulp(tt)
            h_abs = min(h_abs, max_step)
            rejected = False
            while True:
                if h_abs < min_step:
                    message = "Required step size is less than spacing between numbers."
                    return out, -1, message, (tt, y)
                h = h_abs
                t_new = tt + h
                if t_new > t_end:
                    t_new = t_end
                    h = t_new - tt
                    h_abs = h
                try:
                    y_new, f_new, err = stepper(rhs, tt, h, y, f, rtol, atol)
                except (ZeroDivisionError, OverflowError):
                    err = math.inf
                if err < 1.0:
                    if err == 0.0:
                        factor = _MAX_FACTOR
                    else:
                        factor = min(_MAX_FACTOR, _SAFETY * err**exponent)
                    if rejected:
                        factor = min(1.0, factor)
                    h_abs *= factor
                    break
                if not math.isfinite(err):
                    # A non-finite step: a singular mass matrix or a blow-up; halve.
                    h_abs *= 0.5
                else:
                    h_abs *= max(_MIN_FACTOR, _SAFETY * err**exponent)
                rejected = True
            tt, y, f = t_new, y_new, f_new
        out.append(y)
    message = "The solver successfully reached the end of the integration interval."
    return out, 0, message, (tt, y)


class SingularMassMatrixError(ValueError):
    """The mass matrix of a model is singular or indefinite at some state.

    A Lagrangian is only a valid mechanical model where its mass matrix
    ``d2L/dqdot2`` is definite (positive, or negative for a Lagrangian learned up to
    a negative scale from passive data). Attributes ``t``, ``q``, ``qd`` and
    ``eigenvalues`` locate the failure.
    """

    def __init__(self, message, *, t=None, q=None, qd=None, eigenvalues=None):
        super().__init__(message)
        self.t, self.q, self.qd, self.eigenvalues = t, q, qd, eigenvalues


def _lambdify_entries(args, exprs):
    """One numpy function for a list of expressions, broadcasting constants."""
    f = sp.lambdify(args, list(exprs), modules="numpy", cse=True)

    def evaluate(*values):
        shape = np.broadcast(*values).shape if values else ()
        out = f(*values)
        return [np.broadcast_to(np.asarray(v, dtype=float), shape) for v in out]

    return evaluate


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
                    f"forces must have one entry per coordinate ({n}), got {len(forces)}"
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

    # ------------------------------------------------------------------ symbolic
    @property
    def n_dof(self) -> int:
        return len(self.coordinates)

    @property
    def n_inputs(self) -> int:
        return self.input_matrix.shape[1]

    @property
    def symbols(self):
        """``(q, qd, qdd)`` lists of sympy symbols."""
        return symbols_for(self.coordinates)

    def _derive(self):
        cache = self.__dict__.get("_equations")
        if cache is not None:
            return cache
        q, qd, _ = self.symbols
        L = self.lagrangian
        grad_qd = [sp.diff(L, v) for v in qd]
        mass = sp.Matrix([[sp.diff(g, v) for v in qd] for g in grad_qd])
        bias = [
            sum(sp.diff(grad_qd[i], q[j]) * qd[j] for j in range(self.n_dof))
            - sp.diff(L, q[i])
            for i in range(self.n_dof)
        ]
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
        """Symbolic equations ``M qdd + h - Q = B u`` (left-hand sides), one per coordinate."""
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
        cache = self.__dict__.get("_compiled")
        if cache is not None:
            return cache
        eq = self._derive()
        q, qd, _ = self.symbols
        args = list(q) + list(qd)
        n = self.n_dof
        mass_entries = [eq["mass"][i, j] for i in range(n) for j in range(n)]
        rest = [eq["bias"][i] - eq["forces"][i] for i in range(n)]
        cache = {
            "terms": _lambdify_entries(args, mass_entries + rest),
            "energy": _lambdify_entries(args, [eq["energy"]]),
        }
        self._compiled = cache
        return cache

    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop("_compiled", None)  # lambdified code is rebuilt lazily
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
        values = self._numeric()["terms"](*q.T, *qd.T)
        n = self.n_dof
        mass = np.stack(values[: n * n], axis=-1).reshape(q.shape[0], n, n)
        rest = np.stack(values[n * n :], axis=-1)
        return mass, rest

    def mass_matrix(self, q, qd) -> np.ndarray:
        """Mass matrix at each sample, shape (n_samples, n_dof, n_dof)."""
        q, qd = self._split_state(q, qd)
        return self._mass_and_rest(q, qd)[0]

    def inverse_dynamics(self, q, qd, qdd) -> np.ndarray:
        """Generalized forces ``B u`` needed for the accelerations, shape (n_samples, n_dof)."""
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
        self._check_mass(mass, q, qd, t)
        return np.linalg.solve(mass, rhs[..., None])[..., 0]

    def _check_mass(self, mass, q, qd, t=None, reference=None):
        """Raise where ``mass`` is indefinite or (relative to ``reference``) singular.

        ``reference`` is a typical eigenvalue magnitude per sample (e.g. at the start of
        a simulation); without it only the spread within each matrix is used.
        """
        eig = np.linalg.eigvalsh(mass)
        big = np.abs(eig).max(axis=1)
        if reference is not None:
            big = np.maximum(big, reference)
        bad = ~(
            (
                np.all(eig > MASS_MATRIX_RCOND * big[:, None], axis=1)
                | np.all(eig < -MASS_MATRIX_RCOND * big[:, None], axis=1)
            )
            & (big > 0)
        )
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            when = ""
            if t is not None:
                tt = np.broadcast_to(np.asarray(t, dtype=float), (q.shape[0],))[i]
                when = f" at t={tt:.6g}"
            state = ", ".join(
                f"{n}={a:.6g}, {n}_dot={b:.6g}"
                for n, a, b in zip(self.coordinates, q[i], qd[i])
            )
            raise SingularMassMatrixError(
                f"the mass matrix of {self.name} is singular or indefinite{when} "
                f"(sample {i}: {state}; eigenvalues {np.array2string(eig[i], precision=4)}); "
                "the Lagrangian is not a valid mechanical model at this state. "
                "Check the learned terms (lower lam, more data or a wider library), "
                "or start the simulation elsewhere.",
                t=None if t is None else float(np.broadcast_to(t, (q.shape[0],))[i]),
                q=q[i].copy(),
                qd=qd[i].copy(),
                eigenvalues=eig[i].copy(),
            )

    def energy(self, q, qd) -> np.ndarray:
        """Energy function ``sum qdot dL/dqdot - L`` at each sample, shape (n_samples,)."""
        q, qd = self._split_state(q, qd)
        return self._numeric()["energy"](*q.T, *qd.T)[0].copy()

    # ------------------------------------------------------------------ simulation
    def _input_function(self, tau, t, batch):
        """Turn ``tau`` (None, array sampled at t, or callable) into u(t, states)."""
        m = self.n_inputs
        if tau is None:
            return None
        if callable(tau):
            return tau
        arr = np.asarray(tau, dtype=float)
        t = np.asarray(t, dtype=float)
        if batch is None:
            if arr.ndim == 1 and m == 1:
                arr = arr[:, None]
            if arr.shape != (t.shape[0], m):
                raise ValueError(
                    f"tau sampled at t must have shape ({t.shape[0]}, {m}), got {arr.shape}"
                )
            return lambda tt, _x: np.array(
                [np.interp(tt, t, arr[:, j]) for j in range(m)]
            )
        if arr.shape != (batch, t.shape[0], m):
            raise ValueError(
                f"tau for {batch} trajectories must have shape ({batch}, {t.shape[0]}, {m}), "
                f"got {arr.shape}"
            )
        return lambda tt, _x: np.stack(
            [[np.interp(tt, t, arr[b, :, j]) for j in range(m)] for b in range(batch)]
        )

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

        Notes
        -----
        With a sampled ``tau``, every step ends at a sample (the interpolated input
        has a kink there). For one trajectory of a 1- or 2-dof model with an explicit
        method (RK23, RK45, DOP853), the step is the method's tableau unrolled on
        Python floats, with scipy's error norm and step-size control: the same
        result as scipy's solver to rounding, several times faster.

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
        """
        x0 = np.asarray(x0, dtype=float)
        t = np.asarray(t, dtype=float).ravel()
        n = self.n_dof
        batch = None if x0.ndim == 1 else x0.shape[0]
        if x0.shape[-1] != 2 * n or x0.ndim > 2:
            raise ValueError(
                f"x0 must have shape ({2 * n},) or (n_trajectories, {2 * n}), got {x0.shape}"
            )
        if t.size < 1 or np.any(np.diff(t) <= 0):
            raise ValueError(
                "t must be a non-empty, strictly increasing array of times"
            )
        u_fn = self._input_function(tau, t, batch)
        b_mat = self.input_matrix
        rows = 1 if batch is None else batch
        x_start = x0.reshape(rows, 2 * n)
        start_mass, _ = self._mass_and_rest(x_start[:, :n], x_start[:, n:])
        self._check_mass(start_mass, x_start[:, :n], x_start[:, n:], t[0])
        reference = np.abs(np.linalg.eigvalsh(start_mass)).max(axis=1)
        last = {}
        evaluate = self._numeric()["terms"]
        n_mass = n * n

        def rhs(tt, y):
            # The mass matrix is checked at the start and at every output time
            # (below), not here: an eigen-decomposition per step dominated the cost.
            x = y.reshape(rows, 2 * n)
            q, qd = x[:, :n], x[:, n:]
            last["t"], last["y"] = tt, y
            values = evaluate(*q.T, *qd.T)
            mass = np.stack(values[:n_mass], axis=-1).reshape(rows, n, n)
            force = -np.stack(values[n_mass:], axis=-1)
            if u_fn is not None:
                u = np.asarray(u_fn(tt, x[0] if batch is None else x), dtype=float)
                force = force + np.reshape(u, (rows, -1)) @ b_mat.T
            try:
                qdd = np.linalg.solve(mass, force[..., None])[..., 0]
            except np.linalg.LinAlgError:
                qdd = np.full_like(force, np.nan)
            if not np.all(np.isfinite(qdd)):
                self._check_mass(mass, q, qd, tt, reference)
            return np.concatenate([qd, qdd], axis=1).ravel()

        if t.size == 1:
            return x0.copy()[None] if batch is None else x0.copy()[:, None]
        sampled = tau is not None and not callable(tau)
        if batch is None and n <= 2:
            fast = self._scalar_rhs(tau, t, sampled, u_fn, reference, last)
            rhs = fast or rhs
        floats = (
            self._float_rhs(tau, t)
            if sampled and method in _EXPLICIT_RK and batch is None and n <= 2
            else None
        )
        if floats is not None:
            rows_out, status, message, (t_last, y_last) = _integrate_floats(
                _EXPLICIT_RK[method], *floats, t, x0.ravel(), rtol, atol, max_step
            )
            y = np.array(rows_out, dtype=float)
            if status != 0:
                last["t"], last["y"] = t_last, np.array(y_last, dtype=float)
        elif sampled and method in _EXPLICIT_RK:
            y, status, message = _integrate_between(
                _EXPLICIT_RK[method], rhs, t, x0.ravel(), rtol, atol, max_step
            )
        else:
            sol = solve_ivp(
                rhs,
                (t[0], t[-1]),
                x0.ravel(),
                method=method,
                t_eval=t,
                rtol=rtol,
                atol=atol,
                max_step=max_step,
            )
            y, status, message = sol.y.T, sol.status, sol.message
        if status != 0:
            if "y" in last:
                last["x"] = np.asarray(last["y"]).reshape(rows, 2 * n)
            self._diagnose_failure(last, reference, message)
        states = y.reshape(t.size, rows, 2 * n)
        # One check of the mass matrix at all output times together.
        flat = states.reshape(-1, 2 * n)
        mass, _ = self._mass_and_rest(flat[:, :n], flat[:, n:])
        self._check_mass(
            mass,
            flat[:, :n],
            flat[:, n:],
            np.repeat(t, rows),
            np.tile(reference, t.size),
        )
        return states[:, 0] if batch is None else states.transpose(1, 0, 2)

    def _math_terms(self):
        """``f(q..., qd...)`` -> ``[M row-major..., bias - forces...]`` on floats, or None.

        Lambdified with the ``math`` module; None when an expression needs a function
        the math module lacks (the callers then keep the numpy path).
        """
        n = self.n_dof
        eq = self._derive()
        q_s, qd_s, _ = self.symbols
        exprs = [eq["mass"][i, j] for i in range(n) for j in range(n)]
        exprs += [eq["bias"][i] - eq["forces"][i] for i in range(n)]
        try:
            f = sp.lambdify(list(q_s) + list(qd_s), exprs, modules="math", cse=True)
            values = [float(v) for v in f(*([0.1] * (2 * n)))]
        except Exception:  # a function the math module lacks: use numpy
            return None
        return f if len(values) == n * n + n else None

    def _scalar_rhs(self, tau, t, sampled, u_fn, reference, last):
        """Right-hand side of one trajectory on Python floats (1 or 2 dof), or None.

        Numpy's per-call overhead on arrays of one sample dominates a small model's
        right-hand side; the ``math`` module on floats is several times faster.
        """
        n = self.n_dof
        f = self._math_terms()
        if f is None:
            return None
        b_mat = self.input_matrix
        if sampled:
            arr = np.asarray(tau, dtype=float).reshape(t.size, -1) @ b_mat.T
            times, forces = t.tolist(), arr.tolist()
            slopes = (np.diff(arr, axis=0) / np.diff(t)[:, None]).tolist()
            last_index = t.size - 2

        def rhs(tt, y):
            last["t"], last["y"] = tt, y
            v = f(*y.tolist())
            if sampled:
                k = min(max(bisect.bisect_right(times, tt) - 1, 0), last_index)
                h = tt - times[k]
                extra = [a + h * b for a, b in zip(forces[k], slopes[k])]
            elif u_fn is not None:
                extra = (np.reshape(u_fn(tt, y), (-1,)) @ b_mat.T).tolist()
            else:
                extra = [0.0] * n
            if n == 1:
                m, r = v[0], extra[0] - v[1]
                qdd = [r / m] if m != 0 else [math.nan]
            else:
                a, b, c, d = v[0], v[1], v[2], v[3]
                r0, r1 = extra[0] - v[4], extra[1] - v[5]
                det = a * d - b * c
                qdd = (
                    [(d * r0 - b * r1) / det, (a * r1 - c * r0) / det]
                    if det != 0
                    else [math.nan, math.nan]
                )
            if not all(math.isfinite(x) for x in qdd):
                x = np.asarray(y, dtype=float)[None]
                mass = np.asarray(v[: n * n], dtype=float).reshape(1, n, n)
                self._check_mass(mass, x[:, :n], x[:, n:], tt, reference)
            return np.array(y.tolist()[n:] + qdd)

        return rhs

    def _float_rhs(self, tau, t):
        """``(rhs, segment)`` on tuples of floats for a sampled input (1 or 2 dof), or None.

        ``segment(k)`` selects the input's linear piece on ``[t[k], t[k+1]]`` so the
        right-hand side needs no search; ``rhs(t, y)`` returns ``(qd..., qdd...)``
        with the 1x1 or 2x2 mass matrix solved in closed form (a zero determinant
        raises ZeroDivisionError, which the integrator treats as a failed step).
        """
        n = self.n_dof
        f = self._math_terms()
        if f is None:
            return None
        arr = np.asarray(tau, dtype=float).reshape(t.size, -1) @ self.input_matrix.T
        forces = arr.tolist()
        slopes = (np.diff(arr, axis=0) / np.diff(t)[:, None]).tolist()
        times = t.tolist()
        piece = [0.0] * (1 + 2 * n)

        def segment(k):
            piece[0] = times[k]
            piece[1 : 1 + n] = forces[k]
            piece[1 + n :] = slopes[k]

        if n == 1:

            def rhs(tt, y):
                m, r = f(*y)
                return (y[1], (piece[1] + (tt - piece[0]) * piece[2] - r) / m)

        else:

            def rhs(tt, y):
                a, b, c, d, r0, r1 = f(*y)
                dt = tt - piece[0]
                r0 = piece[1] + dt * piece[3] - r0
                r1 = piece[2] + dt * piece[4] - r1
                det = a * d - b * c
                return (y[2], y[3], (d * r0 - b * r1) / det, (a * r1 - c * r0) / det)

        return rhs, segment

    def _diagnose_failure(self, last, reference, message):
        """After a failed integration: blame a nearly singular mass matrix if there is one."""
        n = self.n_dof
        if "x" in last:
            x = last["x"]
            mass, _ = self._mass_and_rest(x[:, :n], x[:, n:])
            small = np.abs(np.linalg.eigvalsh(mass)).min(axis=1) / np.maximum(
                reference, 1e-300
            )
            i = int(np.argmin(small))
            if small[i] < NEAR_SINGULAR:
                state = ", ".join(
                    f"{nm}={a:.6g}, {nm}_dot={b:.6g}"
                    for nm, a, b in zip(self.coordinates, x[i, :n], x[i, n:])
                )
                raise SingularMassMatrixError(
                    f"the mass matrix of {self.name} became nearly singular at "
                    f"t={last['t']:.6g} (trajectory {i}: {state}; smallest eigenvalue "
                    f"{small[i]:.2g} of its value at the start), so the accelerations blow "
                    f"up and the integrator stopped ({message}). The Lagrangian is not a "
                    "valid mechanical model there.",
                    t=float(last["t"]),
                    q=x[i, :n].copy(),
                    qd=x[i, n:].copy(),
                    eigenvalues=np.linalg.eigvalsh(mass[i]),
                )
        raise RuntimeError(f"integration of {self.name} failed: {message}")

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

        lines = [f"L = {fmt(self.lagrangian)}"]
        if self.dissipation != 0:
            lines.append(f"D = {fmt(self.dissipation)}")
        for name, f in zip(self.coordinates, self.forces):
            if f != 0:
                lines.append(f"Q_{name} = {fmt(f)}")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return f"MechanicalModel({self.name!r}, coordinates={self.coordinates}, L={self.lagrangian})"

    def __str__(self) -> str:
        return self.equation()


def rollout_error(
    model_a: MechanicalModel, model_b: MechanicalModel, x0, t, tau=None
) -> dict:
    """Integrate two models from the same state and compare their trajectories.

    Used as the paper's validation metric: train on 5 s, integrate both the learned
    and the true model for a further horizon and measure how far they drift apart.

    Returns
    -------
    dict with keys ``"max_abs_q"`` (largest absolute position difference),
    ``"rmse_q"``, ``"states_a"``, ``"states_b"``; a model that fails to integrate
    gives ``inf`` errors and the exception text under ``"error"``.
    """
    sa = model_a.simulate(x0, t, tau)
    try:
        sb = model_b.simulate(x0, t, tau)
    except (SingularMassMatrixError, RuntimeError, np.linalg.LinAlgError) as exc:
        return {
            "max_abs_q": np.inf,
            "rmse_q": np.inf,
            "states_a": sa,
            "states_b": None,
            "error": str(exc),
        }
    n = model_a.n_dof
    diff = sa[..., :n] - sb[..., :n]
    return {
        "max_abs_q": float(np.abs(diff).max()),
        "rmse_q": float(np.sqrt(np.mean(diff**2))),
        "states_a": sa,
        "states_b": sb,
    }


InputFunction = Callable[[float, np.ndarray], np.ndarray]
