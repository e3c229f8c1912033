"""The passes over partitioned data: each partition's sums, summed.

Every pass maps a function over the partitions (:meth:`PartitionedData.map_reduce`)
and adds the results with :func:`combine`. The strong form needs one pass (the Gram
statistics); the weak form first scans the trajectories (lengths, the time-order
check, the noise covariance, and, without ``dt``, three rounds of an exact
distributed weighted median for the sampling interval), decides what the in-memory
:func:`~lagsindy.formulation.weak.weak_gram` decides from those sums, then sums
every test window's statistics in one pass. Case III and case II gather the rows
their searches evaluate (the same rows an in-memory fit would use) in one more pass.
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import torch

from ..differentiation import check_weak_form_segments
from ..formulation.forms import GramStatistics, TrajectoryStatistics
from ..formulation.weak import (
    NEGLIGIBLE_NOISE,
    TIME_ORDER_LAGS,
    TIME_ORDER_MIN,
    WHITE_VELOCITY,
    WINDOW_FIRST,
    check_order,
    step_ratios,
    estimate_noise_covariance,
    trajectory_segments,
    weighted_median,
    window_ladder,
    window_stride,
)

__all__ = [
    "GatheredRows",
    "combine",
    "gather_rows",
    "strong_pass",
    "trajectory_pass",
    "weak_decisions",
    "weak_pass",
    "weak_scan",
]

# Rows per partition kept for the fit's checks (mass matrix, warnings), and in all.
SAMPLE_PER_PARTITION = 500
SAMPLE_ROWS = 5000
# Bins of the second round of the distributed weighted median.
MEDIAN_BINS = 4096

# Keys whose values are lists concatenated in partition order (the others add).
_CONCAT = ("labels", "sizes", "sample", "lengths", "rows", "traj", "medians", "values")
_OPERATORS: dict = {}


def combine(a, b):
    """The sum of two partial results of a pass.

    Parameters
    ----------
    a, b : dict or None
        Partial results (of consecutive partitions, ``a`` first); ``None`` is
        nothing.

    Returns
    -------
    dict
        Numbers and arrays added, lists (``labels``, ``sizes``, ...) concatenated
        in order, nested dicts combined alike.

    Raises
    ------
    ValueError
        When a trajectory label is in both (split across partitions).
    """
    if a is None:
        return b
    if b is None:
        return a
    if "labels" in a:
        both = set(a["labels"]).intersection(b["labels"])
        if both:
            some = sorted(both, key=str)[:3]
            raise ValueError(
                f"trajectories {some} are split across partitions: every "
                "trajectory must lie in one partition (repartition by the "
                "trajectory column, e.g. ddf.shuffle('trajectory') or "
                "ddf.set_index('trajectory'), or write the Parquet dataset "
                "partitioned by trajectory)"
            )
    out = {}
    for key in a:
        x, y = a[key], b[key]
        if key in _CONCAT:
            out[key] = x + y
        elif isinstance(x, dict):
            out[key] = combine(x, y)
        elif x is None or y is None:
            out[key] = y if x is None else x
        else:
            out[key] = x + y
    return out


def _operator(setup, dtype):
    """The fit's operator (with its probe forces), built once per setup and
    thread (a threaded scheduler runs partitions side by side; an operator keeps
    buffers between calls)."""
    from ..pipeline import fit_operator

    key = (id(setup), dtype, threading.get_ident())
    if key not in _OPERATORS or _OPERATORS[key][0] is not setup:
        if len(_OPERATORS) > 8:
            _OPERATORS.clear()
        _OPERATORS[key] = (setup, *fit_operator(setup, "cpu", dtype))
    return _OPERATORS[key][1:]


def _tensors(chunk, dtype):
    Xt = torch.as_tensor(chunk.X, dtype=dtype)
    tau = None if chunk.tau is None else torch.as_tensor(chunk.tau, dtype=dtype)
    return Xt, tau


def _base(chunk, index):
    """What every pass reports: the trajectories, the size, a sample of rows."""
    n = chunk.X.shape[0]
    take = np.unique(np.linspace(0, n - 1, min(n, SAMPLE_PER_PARTITION)).round())
    take = take.astype(np.int64) if n else np.zeros(0, np.int64)
    tau = None if chunk.tau is None else chunk.tau[take]
    return {
        "labels": chunk.trajectories,
        "sizes": [(index, n)],
        "sample": [(chunk.X[take], tau)],
    }


# ------------------------------------------------------------------ strong form
@dataclasses.dataclass
class strong_pass:  # noqa: N801 - used like a function
    """Per partition: the strong form's Gram statistics (with probe forces)."""

    setup: object
    dtype: object

    def __call__(self, chunk):
        op, _ = _operator(self.setup, self.dtype)
        out = _base(chunk, chunk.index)
        Xt, tau = _tensors(chunk, self.dtype)
        out["gram"] = op.gram(Xt, tau) if Xt.shape[0] else None
        out["n"] = int(Xt.shape[0])
        return out


# -------------------------------------------------------------------- weak form
def _time_order_sums(X, n_dof, segments):
    """Per lag of :func:`~lagsindy.formulation.weak.check_time_order`: the sums
    ``(a b, a a, b b)`` its correlation is made of (zeros when no pair fits)."""
    out = np.zeros((len(TIME_ORDER_LAGS), 3))
    segments = [s for s in segments if len(s) > 0]
    if not segments:
        return out
    rows = torch.cat(list(segments))
    q, qd = X[rows, :n_dof], X[rows, n_dof : 2 * n_dof]
    lengths = torch.as_tensor([len(s) for s in segments])
    starts = torch.cumsum(lengths, 0) - lengths
    seg_of = torch.repeat_interleave(torch.arange(len(segments)), lengths)
    left = lengths[seg_of] - 1 - (torch.arange(rows.numel()) - starts[seg_of])
    mid = torch.cat([qd.new_zeros((1, n_dof)), (qd[1:] + qd[:-1]) / 2])
    cum = torch.cumsum(mid, dim=0)
    for j, k in enumerate(TIME_ORDER_LAGS):
        if rows.numel() <= k:
            break
        pairs = (left[:-k] >= k).unsqueeze(1)
        a = torch.where(pairs, q[k:] - q[:-k], 0.0)
        b = torch.where(pairs, cum[k:] - cum[:-k], 0.0)
        out[j] = [float((a * b).sum()), float((a * a).sum()), float((b * b).sum())]
    return out


def _moments(x):
    """``(n, mean, M2)`` of the columns of ``x`` (combined exactly by
    :func:`_pooled_std`)."""
    n = x.shape[0]
    if n == 0:
        z = np.zeros(x.shape[1])
        return [(0, z, z)]
    mean = x.mean(0)
    return [(n, mean, ((x - mean) ** 2).sum(0))]


def _pooled_std(moments):
    """Unbiased standard deviation of the columns from per-part moments."""
    n, mean, m2 = 0, 0.0, 0.0
    for nk, mk, m2k in moments:
        if nk == 0:
            continue
        delta = mk - mean
        total = n + nk
        mean = mean + delta * nk / total
        m2 = m2 + m2k + delta**2 * n * nk / total
        n = total
    return np.sqrt(m2 / (n - 1)) if n > 1 else np.full(np.shape(mean), np.nan)


@dataclasses.dataclass
class weak_scan:  # noqa: N801
    """Per partition: what the weak form decides on before any statistics."""

    n_dof: int
    first: int
    dt_round: int = 0  # 0: no dt needed; 1: local medians; 2: histogram; 3: values
    bracket: tuple = ()

    def __call__(self, chunk):
        d = self.n_dof
        out = _base(chunk, chunk.index)
        Xt = torch.as_tensor(chunk.X, dtype=torch.float64)
        segments = trajectory_segments(Xt, d, chunk.labels) if len(Xt) else []
        if self.dt_round > 1:
            out.pop("sample")
            out["dt"] = _median_round(chunk.X, d, segments, self.dt_round, self.bracket)
            return out
        usable = [s for s in segments if s.shape[0] >= self.first]
        out["lengths"] = [int(s.shape[0]) for s in segments]
        out["order"] = _time_order_sums(Xt, d, usable)
        long = [s for s in usable if s.shape[0] > 4]
        n4 = sum(int(s.shape[0]) - 4 for s in long)
        cov = estimate_noise_covariance(Xt, usable, d).numpy()
        out["z"] = cov * (70.0 * n4)
        out["n4"] = n4
        rows = torch.cat(usable) if usable else torch.zeros(0, dtype=torch.long)
        out["moments"] = _moments(chunk.X[rows.numpy(), : 2 * d])
        out["long_moments"] = _moments(
            chunk.X[torch.cat(long).numpy(), : 2 * d] if long else np.zeros((0, 2 * d))
        )
        if self.dt_round == 1:
            r, w = step_ratios(chunk.X, d, segments)
            out["medians"] = [(weighted_median(r, w), float(w.sum()))] if w.size else []
        return out


def _median_round(X, d, segments, round_, bracket):
    r, w = step_ratios(X, d, segments)
    lo, hi = bracket[:2]
    below = float(w[r < lo].sum())
    inside = (r >= lo) & (r <= hi)
    k = _bins(r[inside], lo, hi)
    if round_ == 2:
        return {"below": below, "hist": np.bincount(k, w[inside], MEDIAN_BINS)}
    pick = k == bracket[2]
    return {"below": below, "values": [(r[inside][pick], w[inside][pick])]}


def _bins(r, lo, hi):
    if hi <= lo:
        return np.zeros(r.shape, dtype=np.int64)
    k = np.floor((r - lo) / (hi - lo) * MEDIAN_BINS).astype(np.int64)
    return np.clip(k, 0, MEDIAN_BINS - 1)


def sampling_interval(data, n_dof, medians):
    """The weighted median of every step's ratio (what
    :func:`~lagsindy.formulation.weak.estimate_sampling_interval` returns on all
    rows), from the partitions' own medians and two more passes: a histogram
    between the smallest and largest partition median (which bracket the overall
    one), then the values of the bin that holds it."""
    if not medians:
        raise ValueError("cannot estimate dt: the velocities are all zero; pass dt=")
    values = np.array([m for m, _ in medians])
    half = sum(w for _, w in medians) / 2
    lo, hi = float(values.min()), float(values.max())
    if lo == hi:
        return lo
    scan = weak_scan(n_dof, WINDOW_FIRST, 2, (lo, hi))
    hist = data.map_reduce(scan, combine)["dt"]
    cum = hist["below"] + np.cumsum(hist["hist"])
    k = int(min(np.searchsorted(cum, half), MEDIAN_BINS - 1))
    scan = weak_scan(n_dof, WINDOW_FIRST, 3, (lo, hi, k))
    found = data.map_reduce(scan, combine)["dt"]
    r = np.concatenate([v for v, _ in found["values"]])
    w = np.concatenate([w for _, w in found["values"]])
    order = np.argsort(r, kind="stable")
    below = hist["below"] + float(hist["hist"][:k].sum())  # under bin k
    cum = below + np.cumsum(w[order])
    j = int(np.searchsorted(cum, half))
    return float(r[order][min(j, r.size - 1)])


def weak_decisions(scan, params, n_dof, n_terms, dt):
    """What :func:`~lagsindy.formulation.weak.weak_gram` decides, from the scan's
    sums: ``(windows, cov_applied)``; raises the same errors."""
    window, noise_cov = params["window"], params["noise_cov"]
    auto = isinstance(window, str)
    first = WINDOW_FIRST if auto else int(window)
    lengths = np.asarray(scan["lengths"], dtype=np.int64)
    usable = lengths[lengths >= first]
    if not usable.size:
        longest = int(lengths.max()) if lengths.size else 0
        raise ValueError(
            f"no trajectory is as long as window={first} samples (the longest has "
            f"{longest}); lower window or record longer trajectories"
        )
    order = 0.0
    for ab, aa, bb in scan["order"]:
        den = float(np.sqrt(aa * bb))
        if den > 0:
            order = max(order, ab / den)
            if order >= TIME_ORDER_MIN:
                break
    check_order(order)
    n4 = scan["n4"]
    estimated = scan["z"] / (70.0 * n4) if n4 else np.zeros_like(scan["z"])
    if isinstance(noise_cov, str):
        cov = estimated
    elif noise_cov is None:
        cov = None
    else:
        cov = np.asarray(noise_cov, dtype=np.float64)
        if cov.shape != (2 * n_dof, 2 * n_dof):
            raise ValueError(
                f"noise_cov must have shape ({2 * n_dof}, {2 * n_dof}) for [q, "
                f"q_dot], got {cov.shape}"
            )
    windows = [first]
    white = False
    if n4:
        level = np.sqrt(np.diagonal(estimated)[n_dof:])
        spread = _pooled_std(scan["long_moments"])[n_dof:]
        white = bool((level > WHITE_VELOCITY * spread).all())
    if auto and not white:
        windows = window_ladder(usable, n_dof, n_terms, first)
    counts = {
        w: int(((usable[usable >= w] - w) // window_stride(w) + 1).sum())
        for w in windows
    }
    if counts[first] * n_dof < n_terms:
        raise ValueError(
            f"too few windows: {counts[first]} window(s) x {n_dof} coordinate(s) for "
            f"{n_terms} candidate terms; lower window or record more data"
        )
    windows = [w for w in windows if counts[w] * n_dof >= n_terms]
    applied = cov
    if isinstance(noise_cov, str):
        spread = _pooled_std(scan["moments"])
        if (np.sqrt(np.diagonal(cov)) <= NEGLIGIBLE_NOISE * spread).all():
            applied = None
    return windows, applied


@dataclasses.dataclass
class weak_pass:  # noqa: N801
    """Per partition: every window's weak statistics (noise part over every
    sample), after the in-memory fit's check of the trajectories' clocks."""

    setup: object
    dtype: object
    windows: list
    dt: float
    cov: np.ndarray | None

    def __call__(self, chunk):
        op, _ = _operator(self.setup, self.dtype)
        d = op.n_dof
        out = _base(chunk, chunk.index)
        Xt, tau = _tensors(chunk, self.dtype)
        out["weak"] = {w: None for w in self.windows}
        out["windows"] = {w: 0 for w in self.windows}
        if not Xt.shape[0]:
            return out
        segments = trajectory_segments(Xt, d, chunk.labels)
        check_weak_form_segments(chunk.X, d, [s.numpy() for s in segments], self.dt)
        first = self.windows[0]
        usable = [s for s in segments if s.shape[0] >= first]
        if not usable:
            return out
        cov = None if self.cov is None else torch.as_tensor(self.cov, dtype=self.dtype)
        grams = op.weak_grams(
            Xt,
            tau,
            {w: [s for s in usable if s.shape[0] >= w] for w in self.windows},
            strides={w: window_stride(w) for w in self.windows},
            dt=float(self.dt),
            noise_cov=cov,
            noise_rows=int(Xt.shape[0]),
        )
        for w, (gram, n) in grams.items():
            out["weak"][w], out["windows"][w] = gram, int(n)
        return out


# ------------------------------------------------------------ per trajectory
@dataclasses.dataclass
class trajectory_pass:  # noqa: N801
    """Per partition: the formulation's ``trajectory_statistics`` (one per
    sampling interval of ``dts``), for the bootstrap; ``steps``: also the
    sampling-interval ratios of each trajectory."""

    setup: object
    dtype: object
    formulation: object
    dts: list | None = None
    steps: bool = False

    def __call__(self, chunk):
        setup = self.setup
        op = setup.operator(range(setup.n_features), "cpu", self.dtype)
        Xt, tau = _tensors(chunk, self.dtype)
        out = {"labels": chunk.trajectories, "sizes": [(chunk.index, len(Xt))]}
        if self.dts is None:
            per = [self.formulation.trajectory_statistics(op, Xt, tau, chunk.labels)]
        else:
            per = self.formulation.trajectory_statistics(
                op, Xt, tau, chunk.labels, dts=self.dts
            )
        out["traj"] = [per]
        out["rows"] = []
        if self.steps:
            segments = trajectory_segments(Xt, op.n_dof, chunk.labels)
            out["rows"] = [step_ratios(chunk.X, op.n_dof, [s]) for s in segments]
        return out


def stack_trajectories(parts) -> list:
    """The partitions' per-trajectory statistics stacked along the trajectories.

    Parameters
    ----------
    parts : list of list of TrajectoryStatistics
        Per partition (in order), one per sampling interval.

    Returns
    -------
    list of TrajectoryStatistics
        One per sampling interval, over every trajectory.
    """
    out = []
    for node in range(len(parts[0])):
        items = [p[node] for p in parts]
        noise = None
        if items[0].noise is not None:
            noise = torch.cat([t.noise for t in items])
        out.append(
            dataclasses.replace(
                items[0],
                grams=torch.cat([t.grams for t in items]),
                noise=noise,
                n_rows=np.concatenate([t.n_rows for t in items]),
                rows=[r for t in items for r in t.rows],
            )
        )
    return out


# ---------------------------------------------------------------------- rows
@dataclasses.dataclass
class gather_rows:  # noqa: N801
    """Per partition: the rows at the given indices (``wanted[index]``)."""

    wanted: dict

    def __call__(self, chunk):
        take = self.wanted.get(chunk.index)
        if take is None:
            return {"rows": []}
        tau = None if chunk.tau is None else chunk.tau[take]
        return {"rows": [(chunk.index, chunk.X[take], tau)]}


class GatheredRows:
    """Some rows of the data, indexed like the whole data (a tensor of
    ``n_rows`` rows whose rows at ``rows`` are known): what case III's and case
    II's searches index."""

    def __init__(self, rows, values, n_rows):
        self.rows = np.asarray(rows, dtype=np.int64)
        self.values = values
        self.shape = (int(n_rows), int(values.shape[1]))
        self.device, self.dtype = values.device, values.dtype

    def __len__(self):
        return self.shape[0]

    def __getitem__(self, index):
        idx = np.asarray(index.cpu() if torch.is_tensor(index) else index)
        pos = np.searchsorted(self.rows, idx)
        if np.any(pos >= self.rows.size) or np.any(
            self.rows[np.minimum(pos, self.rows.size - 1)] != idx
        ):
            raise IndexError("a row that was not gathered from the partitions")
        return self.values[torch.as_tensor(pos, device=self.device)]


def gram_statistics(total, formulation_name, **kwargs) -> GramStatistics:
    """A :class:`GramStatistics` of summed parts."""
    return GramStatistics(total["gram"], int(total["n"]), formulation_name, **kwargs)


__all__ += [
    "SAMPLE_ROWS",
    "TrajectoryStatistics",
    "gram_statistics",
    "sampling_interval",
    "stack_trajectories",
]
