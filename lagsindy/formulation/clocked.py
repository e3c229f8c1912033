"""Fits given time stamps: the weak form's rows put on an even clock first.

The weak form integrates over consecutive rows as if they were ``dt`` apart. A real
clock (jittered stamps, dropped frames, gaps) breaks that silently: windows of
uneven rows give coefficients several percent off, and trajectories whose positions
jump across dropped frames push ``formulation="auto"`` to the strong form
(``benchmarks/results/clocks.md``). :func:`rows_on_even_clock` is what
``LagrangianSINDy.fit(X, tau, groups=..., t=...)`` does with the time stamps.
"""

from __future__ import annotations

import warnings
from numbers import Integral

import numpy as np

from ..differentiation import CleanedClock, to_even_clock
from .forms import StrongForm, WeakForm
from .weak import WINDOW_FIRST


def rows_on_even_clock(formulation, X, tau, groups, t, *, stacklevel=3):
    """The rows, forces, groups and formulation a fit with time stamps uses.

    Parameters
    ----------
    formulation : formulation object
        What the estimator's parameters give (:func:`make_formulation`).
    X : ndarray of shape (n_samples, 3 * n_dof)
        Validated rows ``[q, q_dot, q_ddot]``.
    tau : ndarray or None
        Forces of the rows.
    groups : array-like or None
        Trajectory labels.
    t : array-like of shape (n_samples,) or CleanedClock
        Time of each row, or the clock of ``derivatives(..., return_clock=True)``
        (its cleaned times, its rebuilt cycle as the step; its segments when
        ``groups`` is None).

    Returns
    -------
    X, tau, groups, formulation
        For a weak (or automatic) formulation on an uneven clock: the rows every
        ``dt`` within each gap-free segment (:func:`to_even_clock`; ``dt``: the
        formulation's, else the clock's rebuilt cycle, else the median frame step),
        their forces and segment labels, and the formulation with that ``dt``.
        When no segment is as long as the weak form's window, the strong form on
        the rows as given, with a warning saying why. For the strong form, the rows
        as given (they are independent samples; the clock does not matter).
    """
    if isinstance(t, CleanedClock):
        if t.keep.shape != (X.shape[0],):
            raise ValueError(
                f"t is a CleanedClock of {t.keep.shape[0]} rows, but X has "
                f"{X.shape[0]}: pass the clock of the same rows"
            )
        if groups is None:
            groups = t.groups
        period, t = t.period, t.t
    else:
        period = None
    if not isinstance(formulation, WeakForm):
        return X, tau, groups, formulation
    params = formulation.get_params()
    step = params.get("dt") or period  # a given dt is the even clock's step
    even = to_even_clock(X, t, groups, tau, dt=step)
    lengths = np.bincount(even.groups)
    window = formulation.window
    need = int(window) if isinstance(window, Integral) else WINDOW_FIRST
    if lengths.max() < need:
        if type(formulation) is not WeakForm:  # "auto": the strong form is left
            warnings.warn(
                "the fit uses the strong form (biased when the data are noisy), the "
                "only option left: on the even clock of dt = "
                f"{even.dt:.4g} s, the longest gap-free segment of the time stamps "
                f"has {int(lengths.max())} samples, fewer than the weak form's "
                f"window of {need}. Record longer stretches without gaps, or pass a "
                "smaller window= (at least 5 samples).",
                UserWarning,
                stacklevel=stacklevel + 1,
            )
            return X, tau, groups, StrongForm()
    if params.get("dt") is None:
        params["dt"] = even.dt
    return even.X, even.tau, even.groups, type(formulation)(**params)
