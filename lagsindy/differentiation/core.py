"""The entry point :func:`derivatives` and the list of its methods."""

from __future__ import annotations

import dataclasses
import math
import warnings
from numbers import Real

import numpy as np
from threadpoolctl import ThreadpoolController

from ._units import unwrap_unit_check
from .clock import CleanedClock, clean_clock
from .methods import _check_savgol_params, _cubic_spline, _finite_difference, _savgol
from .pspline import _pspline
from .records import (
    _GAP_FACTOR,
    _angle_mask,
    _check_times,
    _is_uniform,
    _segments,
    _split_at_gaps,
    _warn_gaps,
    _warn_glitches,
    _warn_skips,
    _warn_wrapped,
    _wrapped_columns,
)

METHODS = ("pspline", "spline", "savgol", "finite_difference")
# Fewest samples per trajectory each method accepts.
_MIN_SAMPLES = {"pspline": 7, "spline": 5, "savgol": 3, "finite_difference": 3}


# ----------------------------------------------------------------- public function
def derivatives(
    q,
    t,
    *,
    groups=None,
    method: str = "pspline",
    window: int = 11,
    polyorder: int = 4,
    smoothing: float | None = None,
    angles=None,
    gap_factor: float | None = _GAP_FACTOR,
    return_groups: bool = False,
    clean=True,
    return_clock: bool = False,
):
    """Estimate ``[q, q_dot, q_ddot]`` from sampled positions, trajectory by trajectory.

    Parameters
    ----------
    q : array-like of shape (n_samples, n_dof) or (n_samples,)
        Measured positions; several trajectories may be stacked (see ``groups``).
    t : array-like of shape (n_samples,) or float
        Time of each row, strictly increasing within a trajectory (it may restart at
        each trajectory); spacing may be non-uniform. A float is a uniform sampling
        interval: each trajectory then starts at 0 with that step.
    groups : array-like of shape (n_samples,), default=None
        Trajectory label of each row (any hashable labels, as for scikit-learn's
        ``GroupKFold``). Rows of one trajectory must be contiguous and in time order.
        Derivatives never use samples of another trajectory. ``None``: one trajectory.
    method : {"pspline", "spline", "savgol", "finite_difference"}, default="pspline"
        ``"pspline"``: quintic penalized spline, smoothing chosen by generalized
        cross-validation (GCV) per trajectory and coordinate; needs no tuning and was
        the most accurate method on the paper's systems at every noise level
        measured (see the module docstring).
        ``"spline"``: scipy's cubic smoothing spline
        (:func:`scipy.interpolate.make_smoothing_spline`, GCV); its second derivative
        is piecewise linear and zero at both ends of each trajectory (natural
        spline), and it is slow (a Python loop inside scipy).
        ``"savgol"``: Savitzky-Golay local polynomials (``window``, ``polyorder``).
        ``"finite_difference"``: second-order central differences, one-sided at the
        ends; no smoothing (noise in q is amplified by about ``1/dt**2`` in q_ddot).
    window : int, default=11
        Savitzky-Golay window length in samples (odd, >= 3). A trajectory shorter
        than the window uses the longest odd window it holds, with ``polyorder``
        lowered below it if needed (a ``UserWarning`` says so).
    polyorder : int, default=4
        Savitzky-Golay polynomial degree (>= 2, so that q_ddot is estimated).
    smoothing : float, default=None
        Fixed smoothing parameter lambda instead of GCV (``None``, recommended). For
        ``"pspline"`` it weighs the sum of squared 4th differences of the B-spline
        coefficients against the sum of squared residuals; for ``"spline"`` it is
        scipy's ``lam``. Ignored by the other methods.
    angles : list of int, boolean mask of shape (n_dof,), or "all", default=None
        Angular coordinates (radians). They are unwrapped with :func:`numpy.unwrap`
        per trajectory before differentiating, so a jump from pi to -pi is read as
        continued rotation; the returned positions of these coordinates are the
        unwrapped (continuous) angles, not reduced to (-pi, pi].
    gap_factor : float or None, default=5.0
        A time step longer than ``gap_factor`` times the median step of its
        trajectory (or the rebuilt cycle) is a gap: the trajectory is cut there and
        each segment is differentiated on its own (nothing is interpolated across a
        gap), with one ``UserWarning`` saying where. Fit with the segments as
        trajectories (``return_groups=True`` or :func:`split_gaps`). ``None``: no
        gap detection.
    return_groups : bool, default=False
        Also return the segment labels (see :func:`split_gaps`).
    clean : bool or CleanedClock, default=True
        Clean the clock first (:func:`clean_clock`, one :class:`ClockWarning` per
        defect found): rows repeating the previous row's positions while the system
        moves (a logger re-reading a stale sample) and near-duplicate stamps are
        dropped from the fits (each such row gets the estimate of the row it
        repeats), stamps that jitter around a regular cycle which the positions
        follow better are rebuilt on it, trajectories are cut at gaps, single
        dropped frames are kept, segments too short to differentiate are estimated
        across their gaps, and the rows near every segment's end are flagged
        (``edge``). An even clock is left exactly as it is. A
        :class:`CleanedClock`: use it (e.g. ``clean_clock(t, q,
        velocities=recorded)``). ``False``: the stamps as given (rows closer than a
        quarter step and dropped samples are only reported).
    return_clock : bool, default=False
        Also return the :class:`CleanedClock` (rows kept, their times, segments,
        ``edge`` rows, the report); needs ``clean``.

    Returns
    -------
    X : ndarray of shape (n_samples, 3 * n_dof)
        Columns ``[q..., q_dot..., q_ddot...]``, rows in the input order. The first
        block is the smoothed fit of q for the smoothing methods and q itself
        (unwrapped) for ``"finite_difference"``.
    groups : ndarray of int of shape (n_samples,)
        Only with ``return_groups=True``: the segment number of each row (the
        trajectories cut at their gaps), to pass as ``groups`` to ``fit``.
    clock : CleanedClock
        Only with ``return_clock=True``. ``clock.rows``, ``clock.t[clock.rows]`` and
        ``clock.groups[clock.rows]`` are the distinct samples on the cleaned clock
        (apply ``clock.rows`` to the other columns, e.g. forces, too);
        ``clock.edge`` marks the rows within 3 samples of a segment's end, whose
        estimates are several times less accurate.

    Raises
    ------
    ValueError
        If q or t contain NaN or infinite values, t goes back within a trajectory
        (by more than a quarter step, with no regular cycle to explain it; with
        ``clean=False``: t is not strictly increasing), a trajectory's rows are not
        contiguous, a trajectory is shorter than the method needs (7 samples for
        ``"pspline"``, 5 for ``"spline"``, 3 otherwise), or a parameter is invalid.

    See Also
    --------
    Derivatives : the same as a scikit-learn transformer.

    Notes
    -----
    One row comes out per row in: rows the clock cleaning drops repeat the estimate
    of their source row, so the output still lines up with the caller's forces.
    Non-uniform time stamps are used directly by every method, with no resampling:
    finite differences use the exact non-uniform stencil weights (the interior
    second derivative is then first order where consecutive steps differ); the
    splines are fitted at the given times; Savitzky-Golay fits its local polynomial
    by least squares at the given times (on a uniform grid this is exactly
    :func:`scipy.signal.savgol_filter`, which is then used).

    Examples
    --------
    >>> import numpy as np
    >>> from lagsindy.differentiation import derivatives
    >>> t = np.linspace(0, 2, 201)
    >>> X = derivatives(np.sin(3 * t), t, method="pspline")
    >>> X.shape
    (201, 3)
    >>> bool(np.max(np.abs(X[:, 2] + 9 * np.sin(3 * t))) < 1e-2)
    True
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    try:
        q = np.asarray(q, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError("q must hold numeric positions (n_samples, n_dof)") from None
    if q.ndim == 1:
        q = q[:, None]
    if q.ndim != 2:
        raise ValueError(f"q must be 2-D (n_samples, n_dof), got shape {q.shape}")
    n, n_dof = q.shape
    bad = np.argwhere(~np.isfinite(q))
    if bad.size:
        raise ValueError(
            f"q contains {len(bad)} NaN or infinite value(s), the first at row "
            f"{bad[0][0]}, column {bad[0][1]}; drop or interpolate those rows first"
        )
    if method == "savgol":
        _check_savgol_params(window, polyorder)
    if smoothing is not None and not (
        isinstance(smoothing, (int, float, np.floating, np.integer))
        and math.isfinite(smoothing)
        and smoothing >= 0
    ):
        raise ValueError(
            f"smoothing must be None (GCV) or a float >= 0, got {smoothing!r}"
        )
    mask = _angle_mask(angles, n_dof)
    if gap_factor is not None and not (isinstance(gap_factor, Real) and gap_factor > 1):
        raise ValueError(f"gap_factor must be a number > 1 or None, got {gap_factor!r}")
    segments = _segments(groups, n)
    need = _MIN_SAMPLES[method]
    clock = None
    if clean is False:
        times = _check_times(t, n, segments)
        segments, gaps, glitches, skips = _split_at_gaps(times, segments, gap_factor)
        if gaps:
            _warn_gaps(gaps, times, gap_factor)
        if glitches:
            _warn_glitches(glitches, times)
        if skips:
            _warn_skips(skips, times)
        rows = None
    else:
        if isinstance(clean, CleanedClock):
            clock = clean
            if clock.keep.shape != (n,):
                raise ValueError(
                    f"clean is a CleanedClock of {clock.keep.shape[0]} rows, but q "
                    f"has {n}; clean the same rows: clean_clock(t, q, groups, ...)"
                )
        elif clean is True:
            _check_lengths(segments, need, method)
            clock = clean_clock(
                t, q, groups, gap_factor=gap_factor, angles=mask, min_samples=need
            )
            clock.warn(stacklevel=2)
        else:
            raise ValueError(
                f"clean must be True, False or a CleanedClock, got {clean!r}"
            )
        short = np.zeros(n, dtype=bool)
        short[clock.defects.get("short", [])] = True
        rows = np.flatnonzero(clock.keep & ~short)
        q_all, q = q, q[rows]
        times = clock.t[rows]
        labels = clock.groups[rows]
        bounds = np.r_[0, np.flatnonzero(np.diff(labels)) + 1, rows.size]
        segments = [
            (int(labels[a]), slice(int(a), int(b)))
            for a, b in zip(bounds[:-1], bounds[1:])
        ]
    unwrap_unit_check(q, segments, mask)
    wrapped = _wrapped_columns(q, segments, mask)
    if wrapped:
        _warn_wrapped(wrapped, times)
    _check_lengths(segments, need, method)
    out = _estimate(
        q, times, segments, mask, method, window, polyorder, smoothing, need
    )
    if clock is not None:
        full = np.full((n, 3 * n_dof), np.nan)
        full[rows] = out
        if short.any():
            args = (method, window, polyorder, smoothing, need)
            clock = _bridge(full, q_all, clock, short, groups, mask, args)
        carried = clock.valid & ~clock.keep
        full[carried] = full[clock.source[carried]]
        out = full
    result = (out,)
    if return_groups:
        if clock is not None:
            result += (clock.groups.copy(),)
        else:
            labels = np.empty(n, dtype=int)
            for k, (_, sl) in enumerate(segments):
                labels[sl] = k
            result += (labels,)
    if return_clock:
        if clock is None:
            raise ValueError(
                "return_clock=True needs the clock cleaning (clean=True or a "
                "CleanedClock)"
            )
        result += (clock,)
    return result[0] if len(result) == 1 else result


def _bridge(full, q, clock, short, groups, mask, args):
    """Estimates of segments too short to differentiate, across their gaps.

    Each run of short segments is fitted together with the nearest full segment on
    each side (same trajectory), and only its own rows are kept from that fit. A run
    with no full neighbour keeps NaN and ``valid`` False (returned clock).
    """
    method, window, polyorder, smoothing, need = args
    n = full.shape[0]
    trajectory = np.empty(n, dtype=int)
    for k, (_, sl) in enumerate(_segments(groups, n)):
        trajectory[sl] = k
    kept = np.flatnonzero(clock.keep)
    label = clock.groups[kept]
    starts = np.r_[0, np.flatnonzero(np.diff(label)) + 1]
    stops = np.r_[starts[1:], kept.size]
    pieces = [kept[a:b] for a, b in zip(starts, stops)]
    is_short = [bool(short[p[0]]) for p in pieces]
    valid = clock.valid.copy()
    i = 0
    while i < len(pieces):
        if not is_short[i]:
            i += 1
            continue
        j = i
        while j + 1 < len(pieces) and is_short[j + 1]:
            j += 1
        run = np.concatenate(pieces[i : j + 1])
        union = [run]
        own = trajectory[run[0]]
        if i > 0 and trajectory[pieces[i - 1][0]] == own:
            union.insert(0, pieces[i - 1])
        if j + 1 < len(pieces) and trajectory[pieces[j + 1][0]] == own:
            union.append(pieces[j + 1])
        union = np.concatenate(union)
        if union.size >= need and len(union) > len(run):
            est = _estimate(
                q[union], clock.t[union], [(None, slice(0, union.size))], mask,
                method, window, polyorder, smoothing, need,
            )  # fmt: skip
            full[run] = est[np.searchsorted(union, run)]
        else:
            valid[run] = False
        i = j + 1
    if not valid.all():
        valid[~clock.keep] = valid[clock.source[~clock.keep]]
        clock = dataclasses.replace(clock, valid=valid)
    return clock


def _check_lengths(segments, need, method):
    """Refuse trajectories (or segments) shorter than the method needs."""
    for key, sl in segments:
        if sl.stop - sl.start < need:
            if isinstance(key, tuple):
                where = (
                    f"segment {key[1]} of "
                    + ("the data" if key[0] is None else f"trajectory {key[0]!r}")
                    + " (between gaps in t) has"
                )
            else:
                where = "the data have" if key is None else f"trajectory {key!r} has"
            raise ValueError(
                f"method={method!r} needs at least {need} samples per trajectory, but "
                f"{where} {sl.stop - sl.start}; use a method that needs fewer "
                "(finite_difference needs 3) or drop the short trajectory"
            )


def _estimate(q, times, segments, mask, method, window, polyorder, smoothing, need):
    """The method's ``[q, q_dot, q_ddot]`` on every segment (rows of ``q``)."""
    n, n_dof = q.shape
    out = np.empty((n, 3 * n_dof))
    shortened = []
    cache = {}
    # The per-trajectory problems are small: BLAS threads only add overhead (and
    # stall badly when cores are shared), so run them single-threaded.
    with _blas_controller().limit(limits=1, user_api="blas"):
        for key, sl in segments:
            qs = q[sl].copy()
            if mask.any():
                qs[:, mask] = np.unwrap(qs[:, mask], axis=0)
            ts = times[sl]
            if method == "finite_difference":
                parts = _finite_difference(qs, ts)
            elif method == "savgol":
                m = sl.stop - sl.start
                w = window if window <= m else m - (1 - m % 2)
                p = min(polyorder, w - 1)
                if w != window:
                    shortened.append((key, m))
                parts = _savgol(qs, ts, w, p, _is_uniform(ts))
            elif method == "spline":
                parts = _cubic_spline(qs, ts, smoothing)
            else:
                parts = _pspline(qs, ts, smoothing, cache)
            out[sl] = np.concatenate(parts, axis=1)
    if shortened:
        warnings.warn(
            f"{len(shortened)} trajectory(ies) are shorter than window={window} (the "
            f"shortest has {min(m for _, m in shortened)} samples); they used the "
            "longest odd window they hold, so their derivatives are less smoothed",
            UserWarning,
            stacklevel=3,
        )
    return out


def _blas_controller() -> ThreadpoolController:
    """One threadpoolctl controller per process (finding the libraries takes ms)."""
    global _CONTROLLER
    if _CONTROLLER is None:
        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER


_CONTROLLER = None
