r"""The weak (integral) formulation: trajectories, sampling interval, noise.

The weak form integrates the Euler-Lagrange equations against smooth test functions
over windows of each trajectory (the integrals: :mod:`.weak_integrals`, the test
functions: :mod:`.testfunctions`). This module finds the trajectories in the rows,
checks that they are time-ordered, estimates the sampling interval and the noise
covariance, chooses the window and builds the weak Gram statistics.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from .._stacklevel import outside_stacklevel
from .._torch import to_numpy, to_tensor
from ..differentiation import check_weak_form_segments
from .testfunctions import bump_function  # noqa: F401  (its 0.2 home)

# Smallest correlation between position steps and integrated velocities for which
# rows count as time-ordered trajectories (see check_time_order: shuffled rows give
# about 0; white noise of 0.2 on q and qd at dt = 0.01 still gives 0.92).
TIME_ORDER_MIN = 0.2
# Lags (in samples) of the time-order check.
TIME_ORDER_LAGS = (1, 2, 4, 8, 16, 32)


def check_order(order: float) -> None:
    """Refuse rows whose position steps correlate with the velocities at ``order``
    below :data:`TIME_ORDER_MIN` (what shuffled, not time-ordered, rows give)."""
    if order < TIME_ORDER_MIN:
        raise ValueError(
            "the rows do not look like time-ordered trajectories (the position "
            "steps q[s+1] - q[s] correlate with the velocities at only "
            f"{order:.2f}; shuffled rows give about 0): the weak formulation "
            "integrates along time, so keep each trajectory's rows in time order "
            "and pass groups="
        )


# window="auto": the first window tried (samples), at most this many windows (each
# 2 w - 1 after the previous), each applying to at least this fraction of the
# samples the first one uses.
WINDOW_FIRST = 81
WINDOW_RUNGS = 4
WINDOW_COVERAGE = 0.9
# window="auto" keeps a window when the next one changes the coefficients by at most
# this (white noise: below 0.5 % on the paper's systems; the cart-pendulum with noise
# 1e-2 on positions and P-spline derivatives: 8 % from 81 to 161, 0.3 % from 161 to
# 321; benchmarks/results/defaults.md).
WINDOW_CHANGE = 0.03
# Velocities whose white-noise level (relative to their spread) is above this carry
# noise the correction handles, and window="auto" keeps the first window (measured
# on the cart-pendulum: 6e-4 to 2e-3 at noise 1e-3 on q, qd; 2e-6 for P-spline
# derivatives
# and for noise-free data; 6e-3 to 0.16 for Savitzky-Golay derivatives, on which 81
# samples are as good as longer windows).
WHITE_VELOCITY = 1e-4
# noise_cov="auto" skips the correction when every channel's estimated white-noise
# level is at most this fraction of its spread (noise-free and spline-smoothed data:
# 0 to 2e-5, the signal's own fourth differences; the correction would change the
# Gram by about the square, 1e-8, less after the window's averaging).
NEGLIGIBLE_NOISE = 1e-4


class WindowWarning(UserWarning):
    """The weak form's coefficients depend on the test-function window."""


def window_stride(window: int) -> int:
    """Samples between the starts of consecutive test-function windows."""
    return max(1, int(window) // 4)


def window_ladder(lengths, n_dof, n_terms, first=WINDOW_FIRST):
    """Windows ``window="auto"`` tries, smallest first.

    ``first``, then ``2 w - 1`` while the longer window still applies to at least
    ``WINDOW_COVERAGE`` of the samples the first one uses and leaves at least twice
    as many windows times coordinates as candidate terms; at most ``WINDOW_RUNGS``.

    Parameters
    ----------
    lengths : sequence of int
        Samples per trajectory.
    n_dof, n_terms : int
    first : int

    Returns
    -------
    list of int
        Empty when no trajectory is ``first`` samples long.
    """
    lengths = np.asarray(lengths, dtype=np.int64)
    base = lengths[lengths >= first].sum()
    if base == 0:
        return []
    ladder, window = [first], first
    while len(ladder) < WINDOW_RUNGS:
        window = 2 * window - 1
        usable = lengths[lengths >= window]
        stride = window_stride(window)
        n_windows = int(((usable - window) // stride + 1).sum()) if usable.size else 0
        if usable.sum() < WINDOW_COVERAGE * base or n_windows * n_dof < 2 * n_terms:
            break
        ladder.append(window)
    return ladder


def weak_gram(
    operator, Xt, tau_t, groups, *, window, dt=None, noise_cov="auto", extra=None
):
    """Weak-form Gram statistics of ``operator`` on time-ordered trajectories.

    Parameters
    ----------
    operator : EulerLagrangeOperator
    Xt : Tensor of shape (n_samples, 3 * n_dof)
    tau_t : Tensor of shape (n_samples, n_dof) or None
    groups : array-like of shape (n_samples,) or None
        Trajectory labels; ``None``: one record, split where the positions jump.
    window : int or "auto"
        Samples per test function; ``"auto"``: the statistics of every window of
        :func:`window_ladder`, for the caller to choose among.
    dt : float or None
        Sampling interval; ``None`` estimates it.
    noise_cov : "auto", array-like of shape (2 * n_dof, 2 * n_dof) or None
        Noise covariance of ``[q, q_dot]`` to correct for.
    extra : Tensor of shape (n_samples, n_dof, n_extra), optional
        Further per-sample integrands (see ``EulerLagrangeOperator.weak_grams``).

    Returns
    -------
    grams : list of (window, build)
        ``build()`` returns ``(gram, n_windows)``, ``gram`` a Tensor of shape
        (n_dof, P, P) (summed when asked for); one entry unless ``window="auto"``.
    dt : float
        The sampling interval used.
    cov : ndarray or None
        The noise covariance whose effect is subtracted (``None``: no correction,
        also when the estimated noise is negligible).

    Raises
    ------
    ValueError
        When the rows are not time-ordered trajectories at least ``window`` long
        (the message says what to pass instead).
    """
    d = operator.n_dof
    if groups is not None and len(groups) != Xt.shape[0]:
        raise ValueError(
            f"groups must have one label per row of X ({Xt.shape[0]}), got {len(groups)}"
        )
    if dt is None:
        rough = (
            trajectory_segments(Xt, d, groups, dt=0.0)
            if groups is not None
            else [torch.arange(Xt.shape[0], device=Xt.device)]
        )
        dt = estimate_sampling_interval(Xt, d, rough)
        if not dt > 0:
            raise ValueError(
                f"could not estimate a positive sampling interval (got {dt:.3g}); "
                "are the rows time-ordered? Pass dt="
            )
    segments = trajectory_segments(Xt, d, groups, dt=dt)
    if groups is not None:  # never integrate across a gap inside a trajectory
        parts = [to_numpy(s) for s in segments]
        check_weak_form_segments(to_numpy(Xt), d, parts, dt)
    auto = isinstance(window, str)
    first = WINDOW_FIRST if auto else int(window)
    # s.shape[0], not len(s): len() of a tensor costs several microseconds
    usable = [s for s in segments if s.shape[0] >= first]
    if not usable:
        longest = max(s.shape[0] for s in segments)
        raise ValueError(
            f"no trajectory is as long as window={first} samples (the longest has "
            f"{longest}); lower window or record longer trajectories"
        )
    order = check_time_order(Xt, d, usable, enough=TIME_ORDER_MIN)
    check_order(order)
    if isinstance(noise_cov, str):
        cov = estimate_noise_covariance(Xt, usable, d)
    elif noise_cov is None:
        cov = None
    else:
        cov = to_tensor(noise_cov, dtype=Xt.dtype, device=Xt.device)
        if cov.shape != (2 * d, 2 * d):
            raise ValueError(
                f"noise_cov must have shape ({2 * d}, {2 * d}) for [q, q_dot], got "
                f"{tuple(cov.shape)}"
            )
    windows = [first]
    if auto and not white_velocities(Xt, usable, d):
        lengths = [s.shape[0] for s in usable]
        windows = window_ladder(lengths, d, operator.n_terms, first)
    by_window = {w: [s for s in usable if s.shape[0] >= w] for w in windows}
    # Windows per rung, known before any sum: (len - w) // stride + 1 per segment.
    counts = {
        w: sum((s.shape[0] - w) // window_stride(w) + 1 for s in by_window[w])
        for w in windows
    }
    if counts[first] * d < operator.n_terms:
        raise ValueError(
            f"too few windows: {counts[first]} window(s) x {d} coordinate(s) for "
            f"{operator.n_terms} candidate terms; lower window or record "
            "more data"
        )
    windows = [w for w in windows if counts[w] * d >= operator.n_terms]
    # An estimated noise level far below the signal (noise-free or spline-smoothed
    # data) changes the Gram by about its square, 1e-8 relative: not worth its cost.
    applied = cov
    if isinstance(noise_cov, str) and negligible_noise(Xt, usable, cov):
        applied = None
    builders = operator.weak_grams(
        Xt,
        tau_t,
        {w: by_window[w] for w in windows},
        strides={w: window_stride(w) for w in windows},
        dt=float(dt),
        noise_cov=applied,
        extra=extra,
        lazy=True,
    )
    grams = [(w, builders[w]) for w in windows]
    return grams, float(dt), None if applied is None else to_numpy(applied)


def negligible_noise(X: torch.Tensor, segments, cov: torch.Tensor) -> bool:
    """Whether every channel's noise level in ``cov`` is at most ``NEGLIGIBLE_NOISE``
    of the channel's spread over ``segments`` (then the correction is skipped)."""
    if cov is None:
        return True
    rows = torch.cat(list(segments))
    spread = X[rows, : cov.shape[0]].std(dim=0)
    return bool((torch.sqrt(torch.diagonal(cov)) <= NEGLIGIBLE_NOISE * spread).all())


def white_velocities(X: torch.Tensor, segments, n_dof: int) -> bool:
    """Whether every velocity carries white noise the noise correction sees.

    True when the white-noise level of each velocity channel (fourth differences,
    :func:`estimate_noise_covariance`) is above ``WHITE_VELOCITY`` of the channel's
    spread: measured velocities, or a short filter's. Velocities differentiated
    from a smoothing spline (or noise-free ones) have almost none (1e-6 of their
    spread, against 6e-4 or more at noise 1e-3 on measured velocities): their errors, if
    any, are smooth in time, which ``window="auto"`` checks for.
    """
    found = _fourth_differences(X, segments, slice(n_dof, 2 * n_dof))
    if found is None:
        return False
    qd, d4 = found
    level = torch.sqrt(d4.pow(2).mean(0) / 70.0)
    spread = qd.std(dim=0)
    return bool((level > WHITE_VELOCITY * spread).all())


def _fourth_differences(X: torch.Tensor, segments, columns):
    """``(x, d4)``: the ``columns`` of the rows of the segments longer than 4 rows,
    and their fourth differences along each segment (those across two segments left
    out), or None without such a segment.

    All segments at once: the same values, in the same order, as one
    ``torch.diff(x, n=4)`` per segment.
    """
    as_rows = (torch.as_tensor(seg, device=X.device) for seg in segments)
    long = [seg for seg in as_rows if seg.shape[0] > 4]
    if not long:
        return None
    rows = torch.cat(long)
    x = X[rows, columns]
    lengths = torch.as_tensor([seg.shape[0] for seg in long], device=X.device)
    owner = torch.repeat_interleave(torch.arange(len(long), device=X.device), lengths)
    inside = owner[4:] == owner[:-4]  # the five rows of a difference in one segment
    return x, torch.diff(x, n=4, dim=0)[inside]


def estimate_noise_covariance(X: torch.Tensor, segments, n_dof: int) -> torch.Tensor:
    r"""Covariance of white measurement noise on ``[q, qd]`` from the data itself.

    Fourth-order differences along each trajectory remove a smooth signal almost
    entirely (the signal contributes :math:`h^4 x^{(4)}`) and multiply white noise
    variance by 70, so :math:`\hat\Lambda = \sum \Delta^4 x \, \Delta^4 x^\top /
    (70\, N)`. Cross-channel covariances are kept, so noise shared between channels
    (the ``shared`` protocol) is captured too. Noise that is not white (derivatives
    from a smoothing filter) is underestimated.

    Returns
    -------
    Tensor of shape (2 * n_dof, 2 * n_dof)
    """
    found = _fourth_differences(X, segments, slice(0, 2 * n_dof))
    if found is None:
        return X.new_zeros((2 * n_dof, 2 * n_dof))
    z = found[1]
    return z.T @ z / (70.0 * z.shape[0])


def trajectory_segments(X: torch.Tensor, n_dof: int, groups=None, dt=None):
    """Rows of each trajectory, for the weak form.

    With ``groups``, each label's rows (in their order in X) form one trajectory.
    Without, consecutive rows are split where the positions (or, when X holds
    accelerations, the velocities) jump: where ``q[s+1] - q[s]`` differs from
    ``dt * (qd[s] + qd[s+1]) / 2`` by more than 8 times its robust spread and by more
    than half the median step ``|q[s+1] - q[s]|`` (so that noise-free trajectories
    ending close to where the next one starts are still told apart).

    Returns
    -------
    list of LongTensor
    """
    n = X.shape[0]
    if groups is not None:
        groups = np.asarray(groups)
        if groups.shape != (n,):
            raise ValueError(
                f"groups must have one label per row of X ({n}), got shape {groups.shape}"
            )
        # each label's rows in order, labels in order of first appearance: one
        # stable sort by label instead of one comparison of every row per label
        _, first, inverse = np.unique(groups, return_index=True, return_inverse=True)
        rows = np.argsort(inverse.ravel(), kind="stable")
        counts = np.bincount(inverse.ravel(), minlength=first.size)
        parts = np.split(rows, np.cumsum(counts)[:-1])
        return [torch.as_tensor(parts[k], device=X.device) for k in np.argsort(first)]
    jump = position_jumps(X[:, :n_dof], X[:, n_dof : 2 * n_dof], dt)
    if X.shape[1] >= 3 * n_dof:  # velocities jump too where a trajectory ends
        jump |= position_jumps(X[:, n_dof : 2 * n_dof], X[:, 2 * n_dof : 3 * n_dof], dt)
    cuts = [0] + (torch.nonzero(jump).flatten() + 1).tolist() + [n]
    return [
        torch.arange(a, b, device=X.device)
        for a, b in zip(cuts[:-1], cuts[1:])
        if b > a
    ]


def position_jumps(x: torch.Tensor, xd: torch.Tensor, dt: float) -> torch.Tensor:
    """Rows ``s`` after which ``x`` jumps (see :func:`trajectory_segments`)."""
    step = x[1:] - x[:-1]
    mismatch = (step - dt * (xd[1:] + xd[:-1]) / 2).abs()
    spread = (
        1.4826 * (mismatch - mismatch.median(dim=0).values).abs().median(dim=0).values
    )
    floor = 0.5 * step.abs().median(dim=0).values
    return (mismatch > torch.maximum(8 * spread, floor)).any(dim=1)


def check_time_order(X: torch.Tensor, n_dof: int, segments, enough=None) -> float:
    """How well the position steps follow the velocities: about 1 if time-ordered.

    For lags ``k`` in ``TIME_ORDER_LAGS`` (shorter than the segments), the
    correlation of ``q[s+k] - q[s]`` with the trapezoid integral of ``qd`` from ``s``
    to ``s+k`` (up to the factor ``dt``); the largest over the lags is returned. It is
    about 0 for shuffled rows at every lag. Along trajectories, white noise lowers
    the lag-1 correlation (0.61 at noise 0.02 and 0.15 at 0.1 on q and qd sampled
    every 0.01, cart-pendulum), but not the longer lags' (0.997 and 0.93 at lag 16):
    the integrated motion grows with the lag, the noise of a position difference
    does not. (Lag 1 alone rejected time-ordered data at noise 0.08 and above.)

    With ``enough``, the lags stop at the first whose correlation reaches it (that
    value is returned): enough to tell whether the largest reaches ``enough``.
    """
    # All segments at once: positions, and the running trapezoid integral of the
    # velocities over all rows; a lag's pairs are those inside one segment, whose
    # integrals then never include a step across segments.
    segments = [seg for seg in segments if len(seg) > 0]
    if not segments:
        return 0.0
    rows = torch.cat(list(segments))
    q, qd = X[rows, :n_dof], X[rows, n_dof : 2 * n_dof]
    lengths = torch.as_tensor([len(seg) for seg in segments], device=X.device)
    starts = torch.cumsum(lengths, 0) - lengths
    # position of each row inside its segment, and the rows left after it
    seg_of = torch.repeat_interleave(
        torch.arange(len(segments), device=X.device), lengths
    )
    position = torch.arange(rows.numel(), device=X.device) - starts[seg_of]
    left = lengths[seg_of] - 1 - position
    mid = torch.cat([qd.new_zeros((1, n_dof)), (qd[1:] + qd[:-1]) / 2])
    cum = torch.cumsum(mid, dim=0)
    best = 0.0
    for k in TIME_ORDER_LAGS:
        pairs = (left[:-k] >= k).unsqueeze(1) if rows.numel() > k else None
        if pairs is None or not bool(pairs.any()):
            break
        a = torch.where(pairs, q[k:] - q[:-k], 0.0)
        b = torch.where(pairs, cum[k:] - cum[:-k], 0.0)
        den = float(torch.sqrt((a * a).sum() * (b * b).sum()))
        if den > 0:
            best = max(best, float((a * b).sum()) / den)
            if enough is not None and best >= enough:
                break
    return best


def estimate_sampling_interval(X: torch.Tensor, n_dof: int, segments) -> float:
    """Sampling interval from ``q[s+1] - q[s] = dt * (qd[s] + qd[s+1]) / 2``.

    The weighted median of the per-step ratios (weights ``((qd[s] + qd[s+1]) / 2)^2``,
    so fast, well-determined steps count most) is insensitive to the few jumps where
    one trajectory ends and the next begins, and to noise.
    """
    # On NumPy arrays (in X's dtype): boolean masks cost several times less there.
    # Overflows give inf and nan silently, as in torch (the fit then reports
    # non-finite statistics).
    Xn = X.detach().cpu().numpy() if torch.is_tensor(X) else np.asarray(X)
    idx = [
        seg.cpu().numpy() if torch.is_tensor(seg) else np.asarray(seg)
        for seg in segments
    ]
    ratios, weights = step_ratios(Xn, n_dof, idx)
    if weights.size == 0:
        raise ValueError("cannot estimate dt: the velocities are all zero; pass dt=")
    with np.errstate(all="ignore"):
        return weighted_median(ratios, weights)


def step_ratios(X, n_dof, segments):
    """Each step's position change over its mean velocity, per coordinate, and its
    weight (the mean velocity squared), over every segment (index arrays into the
    rows of ``X``) of at least 2 rows; the steps across two segments and those at
    zero velocity are left out. Their weighted median is the sampling interval
    (:func:`estimate_sampling_interval`)."""
    idx = [np.asarray(i).astype(np.intp, copy=False) for i in segments]
    idx = [i for i in idx if i.size >= 2]
    if not idx:
        return np.zeros(0), np.zeros(0)
    with np.errstate(all="ignore"):
        # All segments at once, the steps across two segments left out: the same
        # ratios, in the same order, as one segment after the other.
        rows = np.concatenate(idx)
        inside = np.ones(rows.size - 1, dtype=bool)
        inside[np.cumsum([i.size for i in idx])[:-1] - 1] = False
        q, qd = X[rows, :n_dof], X[rows, n_dof : 2 * n_dof]
        mid = ((qd[1:] + qd[:-1]) / 2)[inside]
        ok = np.abs(mid) > 0
        return (q[1:] - q[:-1])[inside][ok] / mid[ok], mid[ok] ** 2


# Candidates below which weighted_median sorts what is left instead of selecting.
_MEDIAN_SORT = 512


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The smallest value ``v`` whose weight ``sum(weights[values <= v])`` is at least
    half the total weight (non-negative weights).

    The lower weighted median, found by selection (quickselect on
    :func:`numpy.partition`) in linear expected time rather than by a full sort;
    the sums differ from a sorted cumulative sum only by their rounding.
    """
    values = np.asarray(values, dtype=np.float64)
    weights = np.asarray(weights, dtype=np.float64)
    with np.errstate(all="ignore"):  # inf and nan pass silently, as in torch
        return _weighted_median(values, weights)


def _weighted_median(values, weights):
    half = weights.sum() / 2
    below = 0.0  # weight of the values already known to lie below the result
    while values.size > _MEDIAN_SORT:
        pivot = np.partition(values, values.size // 2)[values.size // 2]
        lower = values < pivot
        w_lower = below + weights[lower].sum()
        if w_lower >= half:
            values, weights = values[lower], weights[lower]
            continue
        equal = values == pivot
        w_equal = w_lower + weights[equal].sum()
        if w_equal >= half:
            return float(pivot)
        upper = ~(lower | equal)
        values, weights, below = values[upper], weights[upper], w_equal
    order = np.argsort(values, kind="stable")
    cum = below + np.cumsum(weights[order])
    k = int(np.searchsorted(cum, half))
    return float(values[order][min(k, values.size - 1)])


def window_change(a, b) -> float:
    """Relative change between two coefficient vectors (``inf``: other terms)."""
    if not np.array_equal(a != 0, b != 0):
        return float("inf")
    scale = max(np.linalg.norm(a), np.linalg.norm(b))
    return float(np.linalg.norm(a - b) / scale) if scale > 0 else 0.0


def choose_window(ladder, solve, *, search=False, verbose=0, prefer=None):
    """Solve on each window of ``ladder`` until the next window confirms the result.

    ``ladder`` holds functions returning the Gram statistics of each window;
    ``solve(stats, like=None)`` solves on them (with ``like``, a previous solution,
    in its scale: case III's search is not repeated to check a window, and runs
    again only when the check moves on; ``search`` says so). The first window whose
    solution the next one reproduces (:func:`window_change` at most
    ``WINDOW_CHANGE``) is kept, with the warnings of its own solve. When no pair
    agrees, the first window is kept and a :class:`WindowWarning` says how the
    coefficients moved: a misspecified model (a missing term or effect) depends on
    the weighting of the residual, so a longer window is no better there.
    ``prefer(stats, solution, others)``, when given, may replace the kept solution
    by one on the kept statistics informed by the other windows' solutions
    (case I: :func:`~lagsindy.cases.forces.better_support`).

    Returns
    -------
    stats : GramStatistics
    solution : Solution
    """

    def recorded(stats, like=None):
        if verbose:
            print(f"[lagsindy] weak form, test window {stats.window} samples")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            solution = solve(stats, like)
        return stats, solution, caught

    if len(ladder) == 1:
        stats = ladder[0]()
        return stats, solve(stats)
    current = recorded(ladder[0]())
    results, changes = [current], []
    for k, build in enumerate(ladder[1:], start=2):
        check = recorded(build(), current[1])
        changes.append(window_change(current[1].coef, check[1].coef))
        if changes[-1] <= WINDOW_CHANGE:
            break
        results.append(check)
        if k < len(ladder):  # the next window's own fit, to check against
            current = recorded(check[0]) if search else check
    settled = changes[-1] <= WINDOW_CHANGE
    stats, solution, caught = current if settled else results[0]
    if prefer is not None:
        others = [r[1] for r in (*results, check) if r[1] is not solution]
        with warnings.catch_warnings(record=True) as again:
            warnings.simplefilter("always")
            chosen = prefer(stats, solution, others)
        if chosen is not solution:
            solution, caught = chosen, again
            if verbose:
                print(
                    "[lagsindy] another window's terms, solved on this window, fit "
                    "every equation better: kept"
                )
    if verbose:
        print(f"[lagsindy] kept the test window of {stats.window} samples")
    for w in caught:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    if not settled:
        sizes = ", ".join(str(r[0].window) for r in results)
        moves = ", ".join("other terms" if np.isinf(c) else f"{c:.1%}" for c in changes)
        warnings.warn(
            "the weak form's coefficients depend on the test window: fits with "
            f"windows of {sizes} samples differ step by step ({moves}); the "
            f"{stats.window}-sample fit is kept. Either the model misses an effect "
            "(a term, friction, an input delay: run lagsindy.diagnose), or the "
            "derivatives carry smooth errors (estimated by smoothing) that bias "
            "short windows: then record longer trajectories or pass a longer "
            "window= and check that the coefficients settle.",
            WindowWarning,
            stacklevel=outside_stacklevel(),
        )
    return stats, solution
