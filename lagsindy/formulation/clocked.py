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

from .._stacklevel import outside_stacklevel
from ..differentiation import CleanedClock, edge_rows, to_even_clock
from .forms import StrongForm, WeakForm
from .weak import WINDOW_FIRST


def rows_on_even_clock(formulation, X, tau, groups, t, *, verbose=0):
    """The rows, forces, groups and formulation a fit with time stamps uses.

    Rows near a segment's end (``clock.edge``: within 3 samples of a gap or a
    trajectory's end, or in a segment too short to differentiate on its own; for
    an array of times, :func:`~lagsindy.differentiation.edge_rows`) are left out
    first: their one-sided derivative estimates are several times less accurate
    than the interior's and dominate strong fits, and in the weak form they
    pushed edge-heavy records to a wrong model (``benchmarks/results/clocks.md``,
    section 5).

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
        (its cleaned times, its rebuilt cycle as the step, its edge rows; its
        segments when ``groups`` is None).
    verbose : int, default=0
        Print the clock line (``clock["report"]``) when positive.

    Returns
    -------
    X, tau, groups, formulation, clock
        For a weak (or automatic) formulation on an uneven clock: the rows every
        ``dt`` within each gap-free segment (:func:`to_even_clock`; ``dt``: the
        formulation's, else the clock's rebuilt cycle, else the median frame step),
        their forces and segment labels, and the formulation with that ``dt``.
        When no segment is as long as the weak form's window, the strong form on
        the rows as given, with a warning saying why. For the strong form, the rows
        as given (they are independent samples; the clock does not matter). Edge
        rows are left out in every case. ``clock``: a dict with ``rows`` (given),
        ``edge_rows`` (left out), ``fit_rows`` (fitted), ``dt`` (the even clock's
        step, or None) and ``report`` (one line saying what was done), which the
        estimator keeps as ``clock_``.
    """
    n = X.shape[0]
    if isinstance(t, CleanedClock):
        if t.keep.shape != (n,):
            raise ValueError(
                f"t is a CleanedClock of {t.keep.shape[0]} rows, but X has "
                f"{n}: pass the clock of the same rows"
            )
        if groups is None:
            groups = t.groups
        period, edge, t = t.period, t.edge, t.t
    else:
        t = np.asarray(t, dtype=np.float64).ravel()
        if t.shape != (n,):
            raise ValueError(f"t must have one time per row of X ({n}), got {t.size}")
        period, edge = None, edge_rows(t, groups)
    X, tau, groups, t = _without_edges(X, tau, groups, t, edge)
    out = _on_even_clock(formulation, X, tau, groups, t, period)
    clock = _clock_record(n, int(edge.sum()), out[0].shape[0], out[4])
    if verbose and clock["report"]:
        print(f"[lagsindy] {clock['report']}")
    return (*out[:4], clock)


def _without_edges(X, tau, groups, t, edge):
    """The rows, forces, groups and times without the ``edge`` rows."""
    if not edge.any():
        return X, tau, groups, t
    if edge.all():
        raise ValueError(
            "every row lies within 3 samples of a segment's end (or in a segment "
            "too short to differentiate): nothing is left to fit. Record longer "
            "stretches without gaps, or raise the gap factor"
        )
    keep = ~edge
    return (
        X[keep],
        None if tau is None else tau[keep],
        None if groups is None else np.asarray(groups)[keep],
        t[keep],
    )


def _clock_record(n_rows, n_edge, n_fit, even):
    parts = []
    if n_edge:
        parts.append(
            f"{n_edge} of {n_rows} rows lie within 3 samples of a segment's end or "
            "in a segment too short to differentiate (one-sided derivative "
            "estimates, several times less accurate): left out of the fit"
        )
    if even is not None and even.changed:
        parts.append(f"the rows put on an even clock of dt = {even.dt:.4g} s")
    report = "clock: " + "; ".join(parts) if parts else ""
    return {
        "rows": n_rows,
        "edge_rows": n_edge,
        "fit_rows": n_fit,
        "dt": None if even is None else even.dt,
        "report": report,
    }


def _on_even_clock(formulation, X, tau, groups, t, period):
    """``(X, tau, groups, formulation, even)`` of the fit; ``even`` (the
    :class:`~lagsindy.differentiation.EvenClock`) None when the rows are fitted as
    given."""
    if not isinstance(formulation, WeakForm):
        return X, tau, groups, formulation, None
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
                stacklevel=outside_stacklevel(),
            )
            return X, tau, groups, StrongForm(), None
    if params.get("dt") is None:
        params["dt"] = even.dt
    return even.X, even.tau, even.groups, type(formulation)(**params), even


def frame_on_clock(formulation, X, tau, groups, t, *, even=False):
    """:func:`rows_on_even_clock` for data as a user gives them: ``X`` an array or
    a DataFrame of columns ``[q..., q_dot..., q_ddot...]`` (in this order; kept),
    ``tau`` an array or a DataFrame (columns kept). ``even``: the rows on an even
    clock also for the strong form (a diagnosis integrates along trajectories; the
    formulation returned is then the one given). Returns ``(X, tau, groups,
    formulation)``."""
    import pandas as pd

    names = list(X.columns) if isinstance(X, pd.DataFrame) else None
    Xa = np.asarray(X, dtype=np.float64)
    if Xa.ndim != 2 or Xa.shape[1] % 3:
        raise ValueError(f"X must be (n_samples, 3 * n_dof), got shape {Xa.shape}")
    d = Xa.shape[1] // 3
    if names is not None and names[d:] != [
        f"{c}_{k}" for k in ("dot", "ddot") for c in names[:d]
    ]:
        raise ValueError(
            f"X's columns {names} are not [q..., q_dot..., q_ddot...] in this "
            "order: reorder them to put the rows on the fit's clock"
        )
    tau_names = list(tau.columns) if isinstance(tau, pd.DataFrame) else None
    tau_a = None if tau is None else np.asarray(tau, dtype=np.float64)
    use = WeakForm() if even and not isinstance(formulation, WeakForm) else formulation
    Xa, tau_a, groups, form, _ = rows_on_even_clock(use, Xa, tau_a, groups, t)
    form = form if use is formulation else formulation
    X = Xa if names is None else pd.DataFrame(Xa, columns=names)
    tau = tau_a if tau_names is None else pd.DataFrame(tau_a, columns=tau_names)
    return X, tau, groups, form
