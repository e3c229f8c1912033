"""Explicit Runge-Kutta steppers for simulation: scipy's tableaux, stepped to samples.

:func:`integrate_between` drives a :mod:`scipy.integrate` solver so that every step
ends at a sample (a sampled input has a kink there); :func:`integrate_floats` does
the same with the method's tableau unrolled into straight-line Python code on
floats (:func:`float_stepper`, generated once per method and size), with scipy's
error norm and step-size control, for one trajectory of a small model.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
from scipy.integrate import DOP853, RK23, RK45

EXPLICIT_RK = {"RK23": RK23, "RK45": RK45, "DOP853": DOP853}


def integrate_between(solver_class, rhs, t, y0, rtol, atol, max_step):
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


def float_stepper(solver_class, d):
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


def integrate_floats(solver_class, rhs, segment, t, y0, rtol, atol, max_step):
    """Sample-to-sample integration like :func:`integrate_between`, on Python floats.

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
    stepper = float_stepper(solver_class, len(y0))
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
