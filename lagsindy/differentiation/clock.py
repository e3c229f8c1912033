"""Clock cleaning: real time stamps made fit for differentiation and integration.

Camera, motion-capture and logger records never tick evenly. :func:`clean_clock`
looks at every trajectory's stamps and positions and returns a
:class:`CleanedClock`: which rows are distinct samples, the time of each, the
segments between gaps and the rows near a segment's end, with one line per defect
found. :func:`~lagsindy.differentiation.derivatives` runs it by default.

What it does, per trajectory:

1. **Stale rows**: a row whose positions repeat the previous row's exactly, in every
   coordinate, while the system moves (the neighbouring steps are large and carry on
   in the same direction, and the step after the repeat covers the missed motion) is a
   logger re-reading a stale sample: dropped.
2. **A regular cycle under jittery stamps** (a 1 kHz robot cycle stamped by a
   logging computer; evenly exposed frames stamped on arrival): found from the stamps
   when they cluster on multiples of a base period, or from recorded velocities
   (``velocities=``; position increments / (velocity x period) sit on integers).
   When the positions are clearly smoother on the cycle than on the stamps (the
   P-spline's GCV score, an estimate of the unexplained variance, at most half), the
   stamps disagree with the motion and the time base is rebuilt on the cycle. When
   the stamps are the better clock (irregular sampling, truthfully stamped), they are
   kept and nothing is said.
3. **Near-duplicate stamps**: a row less than a quarter of the base period after the
   previous one (equal stamps included) is merged into it (dropped; it gets the
   estimate of the row it merges into).
4. **Gaps**: a step longer than ``gap_factor`` base periods splits the trajectory
   into segments. Single dropped frames (steps of 1.5 to ``gap_factor`` periods) are
   kept: derivatives and integrals use the actual times.
5. **Short segments** (fewer samples than the differentiation method needs, between
   two gaps): kept as their own segments, but :func:`derivatives` estimates them
   with the neighbouring segments across the gaps; their rows are flagged ``edge``.
6. **Edges**: the first and last ``edge_samples`` rows of every segment, where every
   derivative estimate is one-sided and its error several times the interior's,
   are flagged (``edge``), for fits and scores to leave out.

Dropped rows stay in the output of :func:`derivatives` (one row per input row, so
the rows still line up with the user's other columns, e.g. forces): each gets the
estimate of the row it repeats (``source``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from numbers import Real

import numpy as np

from .cycle import (
    MOTION_ROWS,
    cycle_from_motion,
    cycle_from_stamps,
    cycle_from_velocities,
    motion_scores,
)
from .records import (
    _GAP_FACTOR,
    _GLITCH_FRACTION,
    _SKIP_FACTOR,
    _angle_mask,
    _check_times,
    _describe_rows,
    _gap_text,
    _is_uniform,
    _segments,
    raise_backwards,
)

# Rows flagged at each end of a segment. Measured (benchmarks/results/clocks.md):
# on a double pendulum at 100 Hz with noise 1e-3 rad, the P-spline's q_ddot error at
# the 1st, 2nd and 3rd sample from a segment end is 8-10x, 5-7x and 2-3x the
# interior's, from the 4th on below 2x.
EDGE_SAMPLES = 3
# A stale row needs the steps around it larger than this fraction of the
# coordinate's median step: an encoder near a turning point of the shipped
# MultiArm single pendulum (steps of 3e-5 to 6e-5 rad against a median of 4e-3,
# 0.007 to 0.015 medians, and a resolution of 1.6e-4) repeats a reading with the
# motion carrying on; a logger's stale rows on a simulated double pendulum (noise
# 1e-5 rad) sat down to 0.1 medians as it started from rest.
STALE_MIN_STEP = 0.03
# The positions must be at least this much smoother (GCV score ratio) on a cycle
# than on the stamps for the time base to be rebuilt.
REBUILD_RATIO = 0.9


class ClockWarning(UserWarning):
    """A defect of the time stamps, found and handled by the clock cleaning."""


@dataclass(frozen=True)
class CleanedClock:
    """What :func:`clean_clock` found and decided, row by row.

    Attributes
    ----------
    keep : ndarray of bool of shape (n_samples,)
        Rows that are distinct samples (not stale repeats, not merged
        near-duplicates).
    source : ndarray of int of shape (n_samples,)
        For each row, the row whose sample it carries: itself when kept, the row it
        repeats or merges into otherwise.
    t : ndarray of shape (n_samples,)
        The time of each row on the cleaned clock (rebuilt on a regular cycle when
        the stamps disagreed with the motion); dropped rows carry their source's.
    groups : ndarray of int of shape (n_samples,)
        Segment number of each row, 0, 1, ... in row order (trajectories cut at
        their gaps); dropped rows carry their source's.
    valid : ndarray of bool of shape (n_samples,)
        Rows that get an estimate (False only where :func:`derivatives` found a
        segment too short to differentiate with no neighbour to lean on).
    edge : ndarray of bool of shape (n_samples,)
        Rows within ``edge_samples`` kept rows of a segment's end, and every row of
        a segment shorter than ``min_samples``: their estimates are less accurate
        (fits and scores should leave them out).
    report : tuple of str
        One line per defect found (and one counting the edge rows).
    defects : dict of str to ndarray
        Rows concerned, per defect: ``"stale"``, ``"duplicate"`` (rows dropped),
        ``"gap"`` (first row after each gap), ``"dropped"`` (first row after each
        dropped frame), ``"short"`` (kept rows of segments shorter than
        ``min_samples``), ``"retimed"``
        (rows of trajectories whose time base was rebuilt).
    period : float or None
        The cycle the time base was rebuilt on (None: the stamps were kept).
    """

    keep: np.ndarray
    source: np.ndarray
    t: np.ndarray
    groups: np.ndarray
    valid: np.ndarray
    edge: np.ndarray
    report: tuple = ()
    defects: dict = field(default_factory=dict)
    period: float | None = None
    _warnings: tuple = ()

    @property
    def rows(self) -> np.ndarray:
        """Indices of the kept rows."""
        return np.flatnonzero(self.keep)

    @property
    def changed(self) -> bool:
        """Whether any row is dropped or any time differs from the stamps."""
        return bool(self.defects.get("_changed", False))

    def warn(self, stacklevel: int = 2) -> None:
        """Issue one :class:`ClockWarning` per defect (each one line)."""
        for text in self._warnings:
            warnings.warn(text, ClockWarning, stacklevel=stacklevel + 1)

    def __repr__(self) -> str:
        lines = "\n".join(f"  {r}" for r in self.report) or "  (no defect)"
        return (
            f"CleanedClock({int(self.keep.sum())} of {len(self.keep)} rows kept, "
            f"{len(np.unique(self.groups))} segment(s)):\n{lines}"
        )


# ----------------------------------------------------------------- stale rows
def _stale_rows(q: np.ndarray) -> np.ndarray:
    """Rows (of one trajectory) that repeat the previous row's state while it moves.

    A run of rows equal to row ``k0`` is stale when, in some coordinate, the step
    into ``k0`` (``b``), the jump out of the run (``a``) and the step after it
    (``c``, the next step that is no repeat; ``b`` and ``c`` per cycle when they
    come out of other runs of repeats) have the same sign, ``b`` and ``c``
    exceed 3 of the coordinate's smallest steps (the encoder's resolution) and
    ``STALE_MIN_STEP`` (0.03) of its median step, and the jump catches up the
    missed motion, ``|a| >= 0.75 (r + 1) m`` for ``r`` repeats, ``m`` the smaller
    of ``|b|``, ``|c|`` and the median of the nonzero steps around (``b`` or ``c``
    may span skipped cycles). An encoder sitting still at a turning point (a change of
    direction, or a jump no larger than the steps around it: quantization) is no
    stale row.
    """
    n = q.shape[0]
    stale = np.zeros(n, dtype=bool)
    if n < 3:
        return stale
    same = np.all(q[1:] == q[:-1], axis=1)  # row k + 1 equals row k
    if not same.any():
        return stale
    step = np.abs(np.diff(q, axis=0))
    moving = step > 0
    least = np.array(
        [step[moving[:, j], j].min() if moving[:, j].any() else 0.0
         for j in range(q.shape[1])]
    )  # fmt: skip
    typical = np.array(
        [np.median(step[moving[:, j], j]) if moving[:, j].any() else 0.0
         for j in range(q.shape[1])]
    )  # fmt: skip
    threshold = np.maximum(3 * least, STALE_MIN_STEP * typical)
    d = np.diff(q, axis=0)  # d[k] = q[k + 1] - q[k]
    starts = np.flatnonzero(same)
    runs = []  # (k0, r): rows k0 + 1 .. k0 + r repeat row k0
    i = 0
    while i < starts.size:
        r = 1
        while i + r < starts.size and starts[i + r] == starts[i] + r:
            r += 1
        runs.append((int(starts[i]), r))
        i += r
    ending = {k0 + r: r for k0, r in runs}  # last row of a run -> its length
    for k0, r in runs:
        if k0 < 1:
            continue  # needs a step before
        if k0 + r + 1 >= n:  # the trajectory ends on the repeats: the step before
            b = d[k0 - 1] / (ending.get(k0 - 1, 0) + 1)  # alone tells it moves
            if np.any(np.abs(b) > np.maximum(threshold, 0.5 * typical)):
                stale[k0 + 1 : k0 + r + 1] = True
            continue
        # the step into k0 and the one after the jump, per cycle: a step out of
        # an earlier run of repeats covers that run's cycles too
        b = d[k0 - 1] / (ending.get(k0 - 1, 0) + 1)
        a = q[k0 + r + 1] - q[k0]
        j = k0 + r + 1  # the step after the jump, skipping further repeats
        while j + 1 < n and same[j]:
            j += 1
        c = d[j] / (j - k0 - r) if j + 1 < n else b
        # the motion per cycle: the smaller of b, c and the median step around
        # (b or c may span skipped cycles)
        near = np.abs(d[max(k0 - 5, 0) : min(k0 + r + 6, n - 1)])
        near = np.where(near > 0, near, np.nan)
        local = np.nanmedian(near, axis=0) if np.isfinite(near).any() else np.inf
        per_cycle = np.fmin(np.minimum(np.abs(b), np.abs(c)), local)
        ok = (
            (np.sign(a) == np.sign(b))
            & (np.sign(c) == np.sign(b))
            & (np.abs(b) > threshold)
            & (np.abs(c) > threshold)
            & (np.abs(a) >= 0.75 * (r + 1) * per_cycle)
        )
        if ok.any():
            stale[k0 + 1 : k0 + r + 1] = True
    return stale


# ----------------------------------------------------------------- main entry
def clean_clock(
    t,
    q,
    groups=None,
    *,
    velocities=None,
    period: float | None = None,
    rebuild="auto",
    gap_factor: float | None = _GAP_FACTOR,
    angles=None,
    min_samples: int = 7,
    edge_samples: int = EDGE_SAMPLES,
    warn: bool = False,
) -> CleanedClock:
    """Find and handle the defects of a record's clock, trajectory by trajectory.

    Stale repeated rows are dropped, a jittery clock over a regular cycle is rebuilt
    on the cycle when the motion says the stamps are wrong, near-duplicate stamps are
    merged, trajectories are cut at long gaps (single dropped frames are kept), and
    the rows near each segment's end are flagged. See the module docstring for the
    exact rules.

    Parameters
    ----------
    t : array-like of shape (n_samples,) or float
        Time stamps (a float: a uniform step from 0 in each trajectory).
    q : array-like of shape (n_samples, n_dof) or (n_samples,)
        Positions.
    groups : array-like of shape (n_samples,), default=None
        Trajectory labels (rows of a trajectory contiguous); ``None``: one.
    velocities : array-like of shape (n_samples, n_dof), default=None
        Velocities recorded with the positions (a robot's joint velocities), in
        units of q per second. They tell the cycle count of every step where the
        stamps jitter too much to (position increment / (velocity x period) is an
        integer).
    period : float, default=None
        The recorder's cycle, when known (e.g. 0.001 for 1 kHz); ``None``: found
        from the stamps or the velocities.
    rebuild : {"auto", True, False}, default="auto"
        ``"auto"``: rebuild the time base on a regular cycle when the positions are
        at least twice smoother on it (GCV score) than on the stamps; ``True``:
        whenever a cycle is found; ``False``: keep the stamps.
    gap_factor : float or None, default=5.0
        Steps longer than this many base periods (the cycle, or the median step)
        cut the trajectory; ``None``: no cut.
    angles : list of int, boolean mask or "all", default=None
        Angular coordinates, unwrapped for the motion check.
    min_samples : int, default=7
        Segments with fewer samples are reported (``defects["short"]``) and flagged
        ``edge``.
    edge_samples : int, default=3
        Rows flagged at each end of every segment.
    warn : bool, default=False
        Issue one :class:`ClockWarning` per defect found.

    Returns
    -------
    CleanedClock

    Raises
    ------
    ValueError
        When a time stamp goes back by more than a quarter of the base period and no
        cycle explains it, or an argument is invalid.

    Examples
    --------
    >>> import numpy as np
    >>> from lagsindy.differentiation import clean_clock
    >>> t = np.arange(100) * 0.01
    >>> q = np.sin(3 * t)
    >>> q[40] = q[39]  # a logger re-read a stale sample
    >>> clock = clean_clock(t, q)
    >>> int(clock.source[40]), bool(clock.keep[40])
    (39, False)
    >>> print(clock.report[0][:44])
    1 row(s) repeat the previous row's positions
    """
    q = np.asarray(q, dtype=np.float64)
    if q.ndim == 1:
        q = q[:, None]
    n, n_dof = q.shape
    if gap_factor is not None and not (isinstance(gap_factor, Real) and gap_factor > 1):
        raise ValueError(f"gap_factor must be a number > 1 or None, got {gap_factor!r}")
    if rebuild not in ("auto", True, False):
        raise ValueError(f"rebuild must be 'auto', True or False, got {rebuild!r}")
    if period is not None and not (isinstance(period, Real) and period > 0):
        raise ValueError(f"period must be a number > 0 or None, got {period!r}")
    if not (isinstance(edge_samples, (int, np.integer)) and edge_samples >= 0):
        raise ValueError(f"edge_samples must be an integer >= 0, got {edge_samples!r}")
    if velocities is not None:
        velocities = np.asarray(velocities, dtype=np.float64)
        if velocities.ndim == 1:
            velocities = velocities[:, None]
        if velocities.shape != (n, n_dof) or not np.all(np.isfinite(velocities)):
            raise ValueError(
                f"velocities must be finite, of shape ({n}, {n_dof}) like q, got "
                f"shape {velocities.shape}"
            )
    mask = _angle_mask(angles, n_dof)
    user = _segments(groups, n)
    stamps = _check_times(t, n, user, ordered=False)
    state = _State(n)
    state.velocities = velocities is not None
    for key, sl in user:
        _clean_trajectory(
            state, key, sl, stamps, q, velocities, mask, period, rebuild, gap_factor
        )
    return state.finish(stamps, min_samples, edge_samples, gap_factor, warn)


class _State:
    """Row arrays being filled trajectory by trajectory, and the defects found."""

    def __init__(self, n):
        self.source = np.arange(n)
        self.t = np.empty(n)
        self.cut = np.zeros(n, dtype=bool)  # row starts a new segment
        self.rows = {k: [] for k in ("stale", "duplicate", "gap", "dropped")}
        self.gaps = []  # (key, row, step, base) as _warn_gaps reads them
        self.retimed = []  # (rows, period, jitter rms, ratio)
        self.stamped = []  # stamps kept although a cycle was found: (rows, ratio)

    def finish(self, stamps, min_samples, edge_samples, factor, warn):
        n = self.source.size
        source = self.source
        keep = source == np.arange(n)
        kept = np.flatnonzero(keep)
        groups = np.empty(n, dtype=int)
        groups[kept] = np.cumsum(self.cut[kept]) - 1
        groups[~keep] = groups[source[~keep]]
        valid = np.ones(n, dtype=bool)
        edge = np.zeros(n, dtype=bool)
        short = []
        if kept.size:
            starts = np.flatnonzero(np.r_[True, np.diff(groups[kept]) != 0])
            stops = np.r_[starts[1:], kept.size]
            for a, b in zip(starts, stops):
                if b - a < min_samples:
                    short.append(kept[a:b])
                    continue
                edge[kept[a : a + edge_samples]] = True
                edge[kept[max(b - edge_samples, a) : b]] = True
        short = np.concatenate(short) if short else np.zeros(0, dtype=int)
        edge[short] = True
        edge[~keep] = edge[source[~keep]]
        lines, texts = self._lines(stamps, factor, min_samples, short, groups)
        count = int(edge.sum())
        lines.append(
            f"{count} row(s) lie within {edge_samples} sample(s) of a segment's end "
            "(one-sided derivative estimates, several times less accurate): flagged "
            "in edge"
        )
        defects = {k: np.asarray(sorted(v), dtype=int) for k, v in self.rows.items()}
        defects["short"] = np.sort(short)
        defects["retimed"] = (
            np.concatenate([r for r, *_ in self.retimed])
            if self.retimed
            else np.zeros(0, dtype=int)
        )
        defects["_changed"] = bool((~keep).any() or defects["retimed"].size)
        clock = CleanedClock(
            keep=keep,
            source=source.copy(),
            t=self.t.copy(),
            groups=groups,
            valid=valid,
            edge=edge,
            report=tuple(lines),
            defects=defects,
            period=self.retimed[0][1] if self.retimed else None,
            _warnings=tuple(texts),
        )
        if warn:
            clock.warn(stacklevel=3)
        return clock

    def _lines(self, stamps, factor, min_samples, short, groups):
        """Report lines (every defect) and warning texts (the same, one each)."""
        texts = []
        stale = sorted(self.rows["stale"])
        if stale:
            texts.append(
                f"{len(stale)} row(s) repeat the previous row's positions exactly "
                "while the system moves (a logger re-reading a stale sample?): "
                f"{_describe_rows(stale, stamps)}. Dropped: each carries the "
                "estimate of the row it repeats (clock.keep marks the distinct rows)"
            )
        if self.retimed:
            rows = np.concatenate([r for r, *_ in self.retimed])
            periods = [e[1] for e in self.retimed]
            jitter = np.sqrt(np.mean([e[2] ** 2 for e in self.retimed]))
            ratios = np.array([e[3] for e in self.retimed])
            trusted = min(e[4] for e in self.retimed)
            if np.all(np.isfinite(ratios) & (ratios > 0)):
                why = (
                    f"the positions are {1 / ratios.max():.3g}x to "
                    f"{1 / ratios.min():.3g}x smoother on it (GCV)"
                )
            elif np.any(ratios == 0):
                why = "some stamps go back in time"
            else:
                why = "rebuild=True"
            texts.append(
                f"the time stamps of {len(self.retimed)} trajectory(ies) ({rows.size} "
                f"rows, from row {rows.min()}) disagree with the motion: they scatter "
                f"by {jitter:.3g} s rms around a regular cycle of "
                f"{np.median(periods):.6g} s and {why}; the time base was rebuilt on "
                "the cycle (clock.t; rebuild=False keeps the stamps)"
                + (
                    f". Only {trusted:.0%} of the steps could be counted with "
                    "confidence (the rest from jittery stamps)"
                    + (
                        ""
                        if self.velocities
                        else ": pass the recorded velocities (clean_clock(..., "
                        "velocities=)) if there are any"
                    )
                    if trusted < 0.9
                    else ""
                )
            )
        dup = sorted(self.rows["duplicate"])
        if dup:
            texts.append(
                f"{len(dup)} row(s) come less than {_GLITCH_FRACTION:g} median steps "
                f"after the previous row: {_describe_rows(dup, stamps)}. "
                "Near-duplicate or mistimed frames: merged into the previous row "
                "(each carries its estimate)"
            )
        if self.gaps:
            texts.append(_gap_text(self.gaps, stamps, factor))
        dropped = sorted(self.rows["dropped"])
        if dropped:
            texts.append(
                f"{len(dropped)} step(s) of the time stamps are more than "
                f"{_SKIP_FACTOR:g} times their trajectory's median step (dropped "
                f"frames), before row(s) {_describe_rows(dropped, stamps)}: kept, "
                "the derivatives use the actual times. LagrangianSINDy's weak form "
                "takes rows as evenly spaced unless it is given the times, and such "
                "steps bias it (0.5 % of the samples dropped moved a cart-pendulum's "
                "coefficients by 2 %): fit with the times, fit(X, tau, t=clock) "
                "(derivatives(..., return_clock=True)), which puts the rows on an "
                "even clock"
            )
        if short.size:
            n_seg = len(np.unique(groups[short]))
            where = _describe_rows(short.tolist(), stamps, limit=3)
            texts.append(
                f"{n_seg} segment(s) between gaps have fewer than {min_samples} "
                f"samples ({short.size} row(s): {where}): too few to differentiate on "
                "their own; derivatives estimates them across the neighbouring "
                "gap(s) (less accurate: flagged in clock.edge)"
            )
        return list(texts), texts


def _clean_trajectory(state, key, sl, stamps, q, v, mask, period, rebuild, factor):
    rows = np.arange(sl.start, sl.stop)
    state.t[sl] = stamps[sl]
    state.cut[sl.start] = True
    if rows.size < 2:
        return
    stale = _stale_rows(q[sl])
    fresh = rows[~stale]
    state.rows["stale"].extend(rows[stale].tolist())
    tf = stamps[fresh]
    counts = None
    if rebuild is not False and fresh.size >= 16 and not _is_uniform(tf):
        counts, base = _try_cycle(state, fresh, tf, q, v, mask, period, rebuild, factor)
    times = state.t[fresh]  # on the cycle when rebuilt, else the stamps
    if counts is not None:
        position, unit, close = counts.astype(np.float64), 1.0, _GLITCH_FRACTION
    else:
        steps = np.diff(tf)
        moves = np.abs(steps[steps != 0])
        position, unit = tf, float(np.median(moves)) if moves.size else 1.0
        # on an irregular clock close stamps are legitimate samples: only equal or
        # backward stamps are defects there
        regular = _regular(steps, unit)
        close = _GLITCH_FRACTION if regular else 0.0
    # near-duplicates (equal or slightly backward stamps included): merged into the
    # previous kept row
    keep = np.ones(fresh.size, dtype=bool)
    if np.any(np.diff(position) <= close * unit):
        last = 0
        for i in range(1, fresh.size):
            step = position[i] - position[last]
            if step <= close * unit:
                if step < -_GLITCH_FRACTION * unit:
                    _raise_backwards(key, fresh[i], fresh[last], stamps)
                keep[i] = False
                state.source[fresh[i]] = fresh[last]
            else:
                last = i
        state.rows["duplicate"].extend(fresh[~keep].tolist())
    for r in rows[stale]:  # a stale row carries what the row before it carries
        state.source[r] = state.source[r - 1]
    kept = fresh[keep]
    # gaps and dropped frames, in the units of ``position`` (as _split_at_gaps
    # does on the stamps, so that an even clock is cut at the same rows)
    steps = np.diff(position[keep])
    if counts is None:
        unit = float(np.median(steps)) if steps.size else 1.0
        base = unit
        regular = _regular(steps, unit)
    else:
        unit = 1.0
        regular = True
    if factor is not None:
        cut = np.flatnonzero(steps > factor * unit)
        for c in cut:
            row = int(kept[c + 1])
            state.cut[row] = True
            state.gaps.append(
                (key, row, float(times[keep][c + 1] - times[keep][c]), float(base))
            )
        state.rows["gap"].extend(kept[cut + 1].tolist())
    if regular:
        skipped = steps > _SKIP_FACTOR * unit
        if factor is not None:
            skipped &= steps <= factor * unit
        state.rows["dropped"].extend(kept[np.flatnonzero(skipped) + 1].tolist())
    moved = rows[state.source[rows] != rows]
    state.t[moved] = state.t[state.source[moved]]


def _regular(steps, unit) -> bool:
    """A regular clock: 90 % of the steps within 10 % of a whole number (>= 1) of
    ``unit`` (dropped frames are steps of 2, 3, ... units)."""
    if steps.size == 0 or not unit > 0:
        return False
    whole = np.maximum(np.round(steps / unit), 1.0)
    return bool(np.mean(np.abs(steps - whole * unit) <= 0.1 * unit) >= 0.9)


def _raise_backwards(key, row, previous, stamps):
    raise_backwards(
        key,
        row,
        previous,
        stamps,
        " (Equal or nearly equal stamps are merged; a stamp that goes back further "
        "is refused unless a regular cycle under the stamps explains it, and none "
        "could be counted from the stamps and the positions: if the recorder logged "
        "velocities, pass them, clock = clean_clock(t, q, groups, velocities=v), "
        "then derivatives(q, t, groups=groups, clean=clock).)",
    )


def _try_cycle(state, fresh, tf, q, v, mask, period, rebuild, factor):
    """Rebuild the time of the rows ``fresh`` on a regular cycle when the motion
    agrees better with it; returns (counts, period) or (None, None)."""
    found = cycle_from_stamps(tf, period)
    if found is None and v is not None:
        found = cycle_from_velocities(tf, q[fresh], v[fresh], period)
    if found is None and (rebuild is True or np.any(np.diff(tf) <= 0)):
        qf = q[fresh].copy()
        if mask.any():
            qf[:, mask] = np.unwrap(qf[:, mask], axis=0)
        found = cycle_from_motion(tf, qf, period)
    if found is None:
        return None, None
    counts, phase, p, trusted = found
    cycle = phase + counts * p
    jitter = float(np.sqrt(np.mean((tf - cycle) ** 2)))
    if jitter <= 1e-6 * p:  # the stamps are on the cycle already
        return None, None
    distinct = np.r_[True, np.diff(counts) > 0]
    ratio = np.nan
    if rebuild == "auto":
        ratio = _motion_ratio(q[fresh], tf, cycle, counts, distinct, mask, factor)
        if not ratio <= REBUILD_RATIO:
            state.stamped.append((fresh, ratio))
            return None, None
    state.t[fresh] = cycle
    state.retimed.append((fresh, p, jitter, ratio, trusted))
    return counts, p


def _motion_ratio(qf, tf, cycle, counts, distinct, mask, factor):
    """Geometric mean over coordinates of GCV(cycle) / GCV(stamps), on the rows
    with distinct counts (stamps out of order: 0, the stamps cannot be right)."""
    rows = np.flatnonzero(distinct)[:MOTION_ROWS]
    qs = qf[rows].copy()
    if mask.any():
        qs[:, mask] = np.unwrap(qs[:, mask], axis=0)
    ts, tc = tf[rows], cycle[rows]
    if np.any(np.diff(ts) <= 0):
        return 0.0
    steps = np.diff(counts[rows])
    bounds = [0]
    if factor is not None:
        bounds += (np.flatnonzero(steps > factor) + 1).tolist()
    bounds.append(rows.size)
    pieces = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
    on_stamps = motion_scores(qs, ts, pieces)
    on_cycle = motion_scores(qs, tc, pieces)
    good = (on_stamps > 0) & np.isfinite(on_stamps) & np.isfinite(on_cycle)
    if not good.any():
        return np.nan
    return float(np.exp(np.mean(np.log(np.maximum(on_cycle[good], 1e-300)
                                       / on_stamps[good]))))  # fmt: skip
