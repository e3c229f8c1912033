"""Record handling: trajectory labels, time stamps, gaps and glitches.

Contiguous trajectories (:func:`_segments`), time checks (:func:`_check_times`,
:func:`_is_uniform`), angle masks, gaps and timing glitches (:func:`split_gaps`),
and the weak form's check for trajectories that jump
(:func:`check_weak_form_segments`).
"""

from __future__ import annotations

import math
import warnings
from numbers import Real

import numpy as np

# Relative tolerance on the spacing of time stamps under which a trajectory counts as
# uniformly sampled (np.arange(n) / rate varies by about 1e-13 relative).
_UNIFORM_RTOL = 1e-6


def _segments(groups, n: int) -> list[tuple[object, slice]]:
    """Contiguous blocks of equal labels, checking that no label appears twice."""
    if groups is None:
        return [(None, slice(0, n))]
    labels = np.asarray(groups)
    if labels.ndim != 1 or labels.shape[0] != n:
        raise ValueError(
            f"groups must be 1-D with one trajectory label per row ({n} rows), got "
            f"shape {labels.shape}"
        )
    if n == 0:
        return []
    change = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    starts = np.r_[0, change]
    stops = np.r_[change, n]
    seen = {}
    out = []
    for a, b in zip(starts, stops):
        key = labels[a].item() if hasattr(labels[a], "item") else labels[a]
        if key in seen:
            raise ValueError(
                f"the rows of trajectory {key!r} are not contiguous: it occupies "
                f"rows {seen[key][0]}-{seen[key][1] - 1} and again from row {a}. Rows "
                "of one trajectory must be contiguous and in time order; sort them, "
                "e.g. df.sort_values(['trajectory', 't'])."
            )
        seen[key] = (int(a), int(b))
        out.append((key, slice(int(a), int(b))))
    return out


def _angle_mask(angles, n_dof: int, names=None) -> np.ndarray:
    """Boolean mask over the coordinates from indices, names, a mask, or ``"all"``."""
    mask = np.zeros(n_dof, dtype=bool)
    if angles is None:
        return mask
    if isinstance(angles, str):
        if angles == "all":
            return ~mask
        angles = [angles]
    arr = np.asarray(angles)
    if arr.dtype == bool:
        if arr.shape != (n_dof,):
            raise ValueError(
                f"angles as a boolean mask needs one entry per coordinate ({n_dof}), "
                f"got shape {arr.shape}"
            )
        return arr.copy()
    for a in arr.ravel().tolist():
        if isinstance(a, str):
            if names is None or a not in names:
                raise ValueError(
                    f"angles names {a!r}, which is not a coordinate; the coordinates "
                    f"are {list(names) if names is not None else list(range(n_dof))}. "
                    "Pass "
                    "names of position columns, their indices, or a boolean mask."
                )
            mask[list(names).index(a)] = True
        elif isinstance(a, (int, np.integer)) and -n_dof <= a < n_dof:
            mask[a] = True
        else:
            raise ValueError(
                f"angles must hold coordinate indices in [0, {n_dof}) (or names, or "
                f"be a boolean mask), got {a!r}"
            )
    return mask


def _check_times(t, n: int, segments, ordered: bool = True) -> np.ndarray:
    """Time stamps as floats, one per row (a float: a uniform step per trajectory).

    ``ordered=False`` leaves the order unchecked (the clock cleaning of
    :func:`~lagsindy.differentiation.clean_clock` sorts out equal and slightly
    backward stamps, and raises on the rest).
    """
    if np.ndim(t) == 0:
        dt = float(t)
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(
                f"t as a sampling interval must be finite and > 0, got {t!r}"
            )
        times = np.empty(n)
        for _, sl in segments:
            times[sl] = dt * np.arange(sl.stop - sl.start)
        return times
    try:
        times = np.asarray(t, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError("t must hold numeric time stamps, one per row") from None
    if times.ndim != 1 or times.shape[0] != n:
        raise ValueError(
            f"t must be 1-D with one time stamp per row ({n} rows), got shape "
            f"{times.shape}"
        )
    bad = np.flatnonzero(~np.isfinite(times))
    if bad.size:
        raise ValueError(
            f"t contains {bad.size} NaN or infinite time stamp(s), the first at row "
            f"{bad[0]}; drop or repair those rows"
        )
    if ordered:
        _check_order(times, segments)
    return times


def _check_order(times, segments, allowed=None) -> None:
    """Raise unless ``times`` increase within each trajectory.

    ``allowed``: boolean mask over the rows whose step from the previous row may be
    <= 0 (rows the clock cleaning merges away).
    """
    for key, sl in segments:
        steps = np.diff(times[sl])
        bad = steps <= 0
        if allowed is not None:
            bad &= ~allowed[sl.start + 1 : sl.stop]
        wrong = np.flatnonzero(bad)
        if wrong.size:
            r = sl.start + wrong[0]
            raise_backwards(key, r + 1, r, times)


def raise_backwards(key, row, previous, stamps, advice=""):
    """Raise the error of a time stamp (``stamps[row]``) not after the one at
    ``previous`` in trajectory ``key`` (``None``: no groups given), with
    ``advice`` appended."""
    where = "" if key is None else f" (trajectory {key!r})"
    hint = (
        " If several trajectories are stacked, pass groups= (their labels)."
        if key is None
        else ""
    )
    raise ValueError(
        "t must be strictly increasing within each trajectory, but row "
        f"{row}{where} has t = {float(stamps[row])!r} after "
        f"t = {float(stamps[previous])!r} at row {previous}. Rows of one trajectory "
        f"must be contiguous and in time order.{hint}{advice}"
    )


def _is_uniform(t: np.ndarray) -> bool:
    steps = np.diff(t)
    mean = (t[-1] - t[0]) / (len(t) - 1)
    return bool(np.max(np.abs(steps - mean)) <= _UNIFORM_RTOL * mean)


# ----------------------------------------------------------------- gaps and glitches
# A step longer than this many times the median step of its trajectory is a gap.
_GAP_FACTOR = 5.0
# A step shorter than this fraction of the median step is a timing glitch.
_GLITCH_FRACTION = 0.25
# On a regular clock, a step longer than this many median steps (and no gap) means
# dropped samples.
_SKIP_FACTOR = 1.5


def _split_at_gaps(times, segments, factor):
    """Cut segments at gaps; returns (new segments, gaps, glitches, skips).

    ``gaps`` lists ``(key, row, step, median)`` for each step longer than ``factor``
    median steps (the row is the first after the gap). In trajectories on a regular
    clock (90 % of the steps within 10 % of the median), ``glitches`` are the rows
    that come less than ``_GLITCH_FRACTION`` median steps after the previous row,
    and ``skips`` those after a step of more than ``_SKIP_FACTOR`` median steps that
    is no gap (dropped samples).
    """
    out, gaps, glitches, skips = [], [], [], []
    for key, sl in segments:
        steps = np.diff(times[sl])
        if steps.size == 0:
            out.append((key, sl))
            continue
        median = float(np.median(steps))
        # glitches and skips only mean something on a regular clock (most steps
        # near the median)
        if np.mean(np.abs(steps - median) <= 0.1 * median) >= 0.9:
            short = np.flatnonzero(steps < _GLITCH_FRACTION * median)
            glitches.extend((sl.start + 1 + short).tolist())
            long = steps > _SKIP_FACTOR * median
            if factor is not None:
                long &= steps <= factor * median
            skips.extend((sl.start + 1 + np.flatnonzero(long)).tolist())
        if factor is None:
            out.append((key, sl))
            continue
        cut = np.flatnonzero(steps > factor * median)
        if cut.size == 0:
            out.append((key, sl))
            continue
        bounds = [sl.start, *(sl.start + cut + 1).tolist(), sl.stop]
        for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
            out.append(((key, k), slice(a, b)))
        for c in cut:
            gaps.append((key, sl.start + int(c) + 1, float(steps[c]), median))
    return out, gaps, glitches, skips


def _describe_rows(rows, times, limit=5):
    shown = ", ".join(f"{r} (t = {times[r]:.6g})" for r in rows[:limit])
    return shown + (f" and {len(rows) - limit} more" if len(rows) > limit else "")


def _warn_gaps(gaps, times, factor, stacklevel=3):
    warnings.warn(_gap_text(gaps, times, factor), UserWarning, stacklevel=stacklevel)


def _gap_text(gaps, times, factor) -> str:
    rows = [g[1] for g in gaps]
    worst = max(gaps, key=lambda g: g[2] / g[3])
    return (
        f"{len(gaps)} gap(s) in the time stamps (a step longer than {factor:g} times "
        f"the trajectory's median step) before row(s) {_describe_rows(rows, times)}; "
        f"the longest is {worst[2]:.4g} s against a median step of {worst[3]:.4g} s. "
        f"Derivatives were estimated on the {len(gaps)} extra segment(s) separately. "
        "Fit with the segments as trajectories, so that the weak form and "
        "cross-validation never span a gap: groups = split_gaps(t, groups) "
        "(lagsindy.differentiation), or derivatives(..., return_groups=True)"
    )


def _warn_skips(rows, times, stacklevel=3):
    warnings.warn(
        f"{len(rows)} step(s) of the time stamps are more than {_SKIP_FACTOR:g} times "
        f"their trajectory's median step (dropped samples?), before row(s) "
        f"{_describe_rows(rows, times)}. The derivatives use the time stamps as "
        "given, but the weak form (the fit's default) assumes evenly spaced samples "
        "within a trajectory, and such steps bias it (0.5 % of the samples dropped "
        "moved a cart-pendulum's coefficients by 2 %). Keep these derivatives and "
        "fit with the trajectories cut there, groups=split_gaps(t, groups, "
        "gap_factor=1.5) (lagsindy.differentiation; the same fit was then exact), "
        "or interpolate the record onto a regular clock",
        UserWarning,
        stacklevel=stacklevel,
    )


# A step between consecutive samples larger than this, in a coordinate whose values
# stay within one turn, is read as an angle wrapped to (-pi, pi] or [0, 2 pi): a
# wrap jumps by 2 pi minus the true step.
_WRAP_STEP = 1.5 * math.pi
_TURN = 2 * math.pi * (1 + 1e-9)


def _wrapped_columns(q, segments, mask) -> list:
    """Coordinates (not in ``mask``) that look like wrapped angles.

    Returns ``(column, rows)`` for each coordinate whose values span at most one
    turn and that jumps by more than ``_WRAP_STEP`` between consecutive samples of
    a segment, where the jump less a turn is a step like the segment's others (at
    most twice the largest of them); ``rows`` are the rows after each jump.
    """
    out = []
    inside = np.zeros(max(q.shape[0] - 1, 0), dtype=bool)  # steps within a segment
    for _, sl in segments:
        inside[sl.start : sl.stop - 1] = True
    for j in np.flatnonzero(~mask):
        col = q[:, j]
        if col.size < 2 or np.ptp(col) > _TURN:
            continue
        if not np.any(inside & (np.abs(np.diff(col)) > _WRAP_STEP)):
            continue  # most data: no jump at all, no loop over the segments
        rows = []
        for _, sl in segments:
            step = np.abs(np.diff(col[sl]))
            jump = step > _WRAP_STEP
            if jump.any():
                usual = 2 * step[~jump].max() if (~jump).any() else np.inf
                wrap = jump & (np.abs(step - 2 * np.pi) <= usual)
                rows.append(sl.start + 1 + np.flatnonzero(wrap))
        rows = np.concatenate(rows) if rows else np.zeros(0, dtype=int)
        if rows.size:
            out.append((int(j), rows))
    return out


def _warn_wrapped(wrapped, times, stacklevel=3):
    columns = [j for j, _ in wrapped]
    j, rows = wrapped[0]
    warnings.warn(
        f"coordinate(s) {columns} look like wrapped angles: their values stay within "
        "one turn and jump by more than 1.5 pi between consecutive samples (column "
        f"{j}: {len(rows)} time(s), before row(s) {_describe_rows(list(rows), times)})."
        " Differentiated as they are, each jump becomes a spike in the velocity and "
        "acceleration. If they are angles, unwrap them per trajectory first "
        f"(angles={columns})",
        UserWarning,
        stacklevel=stacklevel,
    )


def _warn_glitches(glitches, times, stacklevel=3):
    warnings.warn(
        f"{len(glitches)} row(s) come less than {_GLITCH_FRACTION:g} median steps "
        f"after the previous row: {_describe_rows(glitches, times)}. Duplicated or "
        "mistimed frames? Their derivatives are kept (the time stamps are used as "
        "given), but check those rows and drop them or repair their time stamps",
        UserWarning,
        stacklevel=stacklevel,
    )


def split_gaps(t, groups=None, *, gap_factor: float = _GAP_FACTOR) -> np.ndarray:
    """Trajectory labels with every trajectory cut at its gaps in time.

    A gap is a time step longer than ``gap_factor`` times the median step of its
    trajectory. Pass the result as ``groups`` to :func:`derivatives`,
    :meth:`LagrangianSINDy.fit <lagsindy.LagrangianSINDy.fit>` and cross-validation,
    so that no estimate (splines, the weak form's integrals) spans a gap.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Time stamps, strictly increasing within each trajectory.
    groups : array-like of shape (n_samples,), default=None
        Trajectory labels (rows of a trajectory contiguous); ``None``: one trajectory.
    gap_factor : float, default=5.0
        Steps longer than this many median steps are gaps.

    Returns
    -------
    ndarray of int of shape (n_samples,)
        Segment number of each row, 0, 1, ... in row order (a trajectory without
        gaps keeps one number).

    Examples
    --------
    >>> import numpy as np
    >>> from lagsindy.differentiation import split_gaps
    >>> t = np.r_[np.arange(5), np.arange(10, 14)] * 0.01
    >>> split_gaps(t).tolist()
    [0, 0, 0, 0, 0, 1, 1, 1, 1]
    """
    if not (isinstance(gap_factor, Real) and gap_factor > 1):
        raise ValueError(f"gap_factor must be a number > 1, got {gap_factor!r}")
    n = np.shape(t)[0] if np.ndim(t) else 0
    segments = _segments(groups, n)
    times = _check_times(t, n, segments)
    cut, *_ = _split_at_gaps(times, segments, gap_factor)
    labels = np.empty(n, dtype=int)
    for k, (_, sl) in enumerate(cut):
        labels[sl] = k
    return labels


def check_weak_form_segments(X, n_dof: int, segments, dt: float) -> None:
    """Refuse trajectories that jump in time, for the weak form (uniform ``dt``).

    The weak form integrates over windows of consecutive rows as if they were
    ``dt`` apart. Where a trajectory has a gap, the positions jump between two rows:
    ``|q[s+1] - q[s]|`` exceeds 4 times ``|dt (qd[s] + qd[s+1]) / 2|`` plus 10 times
    the robust spread of that mismatch (the noise).

    Parameters
    ----------
    X : ndarray of shape (n_samples, >= 2 * n_dof)
        ``[q, q_dot, ...]``.
    n_dof : int
        Number of coordinates.
    segments : list of integer arrays
        Rows of each trajectory, in time order.
    dt : float
        The sampling interval the weak form assumes.

    Raises
    ------
    ValueError
        Naming the trajectory and row of the first jump, and what to do.
    """
    X = np.asarray(X, dtype=float)
    q, qd = X[:, :n_dof], X[:, n_dof : 2 * n_dof]
    # Segments of one length at once (each its own medians): the same values as
    # one segment after the other, the first jumping segment reported.
    by_length = {}
    for k, rows in enumerate(segments):
        rows = np.asarray(rows).astype(np.intp)
        if rows.size >= 3:
            by_length.setdefault(rows.size, []).append((k, rows))
    first = None  # (segment, step) of the first jump
    for group in by_length.values():
        idx = np.stack([rows for _, rows in group])  # (segments, length)
        step = np.diff(q[idx], axis=1)
        expected = dt * (qd[idx][:, 1:] + qd[idx][:, :-1]) / 2
        mismatch = np.abs(step - expected)
        centre = np.median(mismatch, axis=1, keepdims=True)
        spread = 1.4826 * np.median(np.abs(mismatch - centre), axis=1, keepdims=True)
        jump = (np.abs(step) > 4 * np.abs(expected) + 10 * spread + 1e-12).any(axis=2)
        for j in np.flatnonzero(jump.any(axis=1)):
            if first is None or group[j][0] < first[0]:
                first = (group[j][0], int(np.flatnonzero(jump[j])[0]))
    if first is not None:
        k, s = first
        rows = np.asarray(segments[k]).astype(np.intp)
        step = np.abs(q[rows[s + 1]] - q[rows[s]])
        wrapped = [
            j for j in np.flatnonzero(step > _WRAP_STEP) if np.ptp(q[:, j]) <= _TURN
        ]
        hint = (
            f". If coordinate(s) {[int(j) for j in wrapped]} are angles, they jump there "
            "by nearly 2 pi within one turn: wrapped to (-pi, pi]? Unwrap them per "
            "trajectory (numpy.unwrap, or derivatives(..., angles=[...])) and "
            "recompute the derivatives"
            if wrapped
            else ""
        )
        raise ValueError(
            "formulation='weak' integrates over consecutive rows as if they were "
            f"dt = {dt:.4g} s apart, but trajectory {k} (rows {rows[0]}-"
            f"{rows[-1]}) jumps between rows {rows[s]} and {rows[s + 1]}: the "
            "positions change far more than the velocities allow, as across a gap "
            "in the time stamps. Cut the trajectories at their gaps and pass the "
            "segments as groups (groups = lagsindy.differentiation.split_gaps(t, "
            "groups), or derivatives(..., return_groups=True)), or fit with "
            "formulation='strong'" + hint
        )
