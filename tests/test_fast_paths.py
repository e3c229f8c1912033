"""The fit's fast paths (issue 16) against plain reference computations.

Each fast path replaced a simpler computation; the simpler one is written out here
as the reference (the code before the change, or the definition), so that the two
must keep agreeing: to rounding where the order of the sums changed, exactly where
the fast path only selects (medians) or copies.
"""

import numpy as np
import pytest
import torch
from _sympy_reference import random_states, sympy_columns
from sklearn.base import clone

from lagsindy import CandidateLibrary
from lagsindy._batched import compile_terms
from lagsindy.euler_lagrange import EulerLagrangeOperator
from lagsindy.formulation.scaling import BalancedGram, balance_rows
from lagsindy.formulation.weak import (
    check_time_order,
    trajectory_segments,
    weighted_median,
)
from lagsindy.systems import cart_pendulum, make_dataset


# ----------------------------------------------------------------- strong-form Gram
def test_kernel_output_buffers_ignore_their_old_content():
    """Kernels write into given buffers (addmm with beta=0): stale values, NaN
    included, never leak into the result, and reused work buffers of another
    sample count are replaced."""
    lib = CandidateLibrary.polynomial(["x", "theta"], angles=["theta"], degree=4)
    kernels = compile_terms(lib.build().terms_, ["x", "theta"])
    kernel = kernels.plan["columns"]
    work = {}
    for n, seed in ((50, 0), (17, 1), (50, 2)):
        q, qd, qdd = random_states(2, n, seed)
        base = kernels._base(q.T, qd.T, qdd.T, work)
        fresh = kernel.evaluate(base.clone())
        stale = torch.full((kernel.n_out, n), float("nan"), dtype=torch.float64)
        kernel.evaluate(base, out=stale, work=work)
        np.testing.assert_array_equal(stale.numpy(), fresh.numpy())
        blocks = torch.full((2, kernel.n_out // 2, n), float("nan"), dtype=q.dtype)
        kernel.evaluate_blocks(base, [blocks[0], blocks[1]], work)
        np.testing.assert_array_equal(
            blocks.reshape(kernel.n_out, n).numpy(), fresh.numpy()
        )
        want = sympy_columns(lib.terms_, ["x", "theta"], q, qd, qdd)
        # columns (dof, term) against sympy; measured: 3e-14 on entries up to 240
        got = fresh.reshape(2, -1, n).permute(2, 0, 1).numpy()
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def _sorted_weighted_median(r, w):
    """The previous implementation: full sort, cumulative weights."""
    r, w = torch.as_tensor(r), torch.as_tensor(w)
    order = torch.argsort(r)
    cum = torch.cumsum(w[order], 0)
    k = int(torch.searchsorted(cum, cum[-1] / 2))
    return float(r[order][min(k, r.numel() - 1)])


@pytest.mark.parametrize("n", [1, 2, 7, 600, 5001])
def test_weighted_median_by_selection_equals_the_sorted_one(n):
    rng = np.random.default_rng(n)
    cases = [
        (rng.normal(size=n), rng.random(n)),
        (rng.integers(-4, 4, n).astype(float), rng.random(n)),  # ties
        (rng.integers(-2, 2, n).astype(float), np.ones(n)),  # ties, equal weights
        (rng.normal(size=n), rng.integers(0, 3, n).astype(float)),  # zero weights
    ]
    # exactly half the weight below the middle value: the lower one is the median
    cases.append((np.repeat([0.0, 1.0], [n // 2 + n % 2, n // 2]), np.ones(n)))
    for values, weights in cases:
        if weights.sum() == 0:
            continue
        assert weighted_median(values, weights) == _sorted_weighted_median(
            values, weights
        )


def _per_segment_time_order(X, n_dof, segments, lags=(1, 2, 4, 8, 16, 32)):
    """The previous implementation: one segment at a time."""
    tracks = []
    for seg in segments:
        q, qd = X[seg, :n_dof], X[seg, n_dof : 2 * n_dof]
        trap = torch.cumsum((qd[1:] + qd[:-1]) / 2, dim=0)
        tracks.append((q, torch.cat([trap.new_zeros((1, n_dof)), trap])))
    best = 0.0
    for k in lags:
        long_enough = [(q, cum) for q, cum in tracks if q.shape[0] > k]
        if not long_enough:
            break
        a = torch.cat([(q[k:] - q[:-k]).flatten() for q, _ in long_enough])
        b = torch.cat([(cum[k:] - cum[:-k]).flatten() for _, cum in long_enough])
        den = float(torch.sqrt((a * a).sum() * (b * b).sum()))
        if den > 0:
            best = max(best, float((a * b).sum()) / den)
    return best


def test_time_order_on_all_segments_at_once_equals_per_segment():
    data = make_dataset(
        cart_pendulum(), n_trajectories=6, excitation="sincos", random_state=0
    )
    X = torch.tensor(data.X)
    segments = trajectory_segments(X, 2, data.groups)
    rng = np.random.default_rng(0)
    short = [s[: int(rng.integers(1, 40))] for s in segments]  # some shorter than lags
    noisy = X + 0.05 * torch.tensor(rng.normal(size=X.shape))
    shuffled = X[torch.as_tensor(rng.permutation(X.shape[0]))]
    for x, segs in [
        (X, segments),
        (X, short),
        (noisy, segments),
        (shuffled, segments),
        (X, [s[:1] for s in segments]),  # no pair at any lag
    ]:
        want = _per_segment_time_order(x, 2, segs)
        # measured: 1.1e-16 at most (the integrals run over all segments at once)
        assert check_time_order(x, 2, segs) == pytest.approx(want, abs=1e-12)
    assert check_time_order(X, 2, segments) > 0.99
    assert check_time_order(X, 2, []) == 0.0
    # enough=: the lags stop once one reaches it; the verdict is the same
    for x in (X, noisy, shuffled):
        full = check_time_order(x, 2, segments)
        quick = check_time_order(x, 2, segments, enough=0.2)
        assert (quick >= 0.2) == (full >= 0.2)
        assert quick == full or full >= quick >= 0.2
    # measured on the noisy rows: lag 1 0.213 (returned with enough=0.2), all lags
    # 0.989, the first lag reaching 0.9 0.960
    lag_one = _per_segment_time_order(noisy, 2, segments, lags=(1,))
    assert check_time_order(noisy, 2, segments, enough=0.2) == pytest.approx(lag_one)
    assert 0.2 <= lag_one < 0.3
    assert 0.9 <= check_time_order(noisy, 2, segments, enough=0.9) < 0.98


def _per_segment_jump(X, n_dof, segments, dt):
    """The previous gap check, one segment at a time: (segment, step) or None."""
    q, qd = X[:, :n_dof], X[:, n_dof : 2 * n_dof]
    for k, rows in enumerate(segments):
        rows = np.asarray(rows)
        if rows.size < 3:
            continue
        step = np.diff(q[rows], axis=0)
        expected = dt * (qd[rows][1:] + qd[rows][:-1]) / 2
        mismatch = np.abs(step - expected)
        centre = np.median(mismatch, axis=0)
        spread = 1.4826 * np.median(np.abs(mismatch - centre), axis=0)
        jump = np.abs(step) > 4 * np.abs(expected) + 10 * spread + 1e-12
        if jump.any():
            return k, int(np.flatnonzero(jump.any(axis=1))[0])
    return None


def test_segment_helpers_at_once_equal_one_segment_at_a_time():
    """trajectory_segments (labels by a sort), estimate_sampling_interval and
    check_weak_form_segments (segments of one length stacked) against loops over
    the labels and segments: the same rows, dt and first jump, bit for bit."""
    from lagsindy.differentiation import check_weak_form_segments
    from lagsindy.formulation.weak import estimate_sampling_interval, weighted_median

    data = make_dataset(
        cart_pendulum(), n_trajectories=6, excitation="sincos", random_state=1
    )
    rng = np.random.default_rng(2)
    X = data.X.copy()
    mixed = np.array(["b", "a", "c", "a", "b", "c"])[data.groups]  # not sorted
    got = trajectory_segments(torch.tensor(X), 2, mixed)
    want = [np.flatnonzero(mixed == v) for v in ("b", "a", "c")]  # first seen
    assert [s.tolist() for s in got] == [w.tolist() for w in want]
    labels = np.array(["d", "b", "f", "a", "e", "c"])[data.groups]
    X[1230:, :2] += 0.3  # a jump inside the third trajectory (rows 1000-1499)
    X[2300:, :2] -= 0.3  # and one inside the fifth: the first is reported
    Xt = torch.tensor(X)
    segments = trajectory_segments(Xt, 2, labels)
    assert [int(s[0]) for s in segments] == [0, 500, 1000, 1500, 2000, 2500]
    cut = [s[: int(rng.integers(2, 500))] for s in segments] + [segments[0][:1]]
    for segs in (segments, cut):
        parts = [s.numpy() for s in segs]
        ratios, weights = [], []
        for rows in parts:
            if rows.size < 2:
                continue
            q, qd = X[rows, :2], X[rows, 2:4]
            mid = (qd[1:] + qd[:-1]) / 2
            ok = np.abs(mid) > 0
            ratios.append((q[1:] - q[:-1])[ok] / mid[ok])
            weights.append(mid[ok] ** 2)
        dt = estimate_sampling_interval(Xt, 2, segs)
        assert dt == weighted_median(np.concatenate(ratios), np.concatenate(weights))
        found = _per_segment_jump(X, 2, parts, 0.01)
        if found is None:
            check_weak_form_segments(X, 2, parts, 0.01)
            continue
        k, s = found
        rows = parts[k]
        with pytest.raises(ValueError, match=f"trajectory {k} .*rows {rows[s]} and"):
            check_weak_form_segments(X, 2, parts, 0.01)
    assert _per_segment_jump(X, 2, [s.numpy() for s in segments], 0.01)[0] == 2


# ----------------------------------------------------------------- scaling
def _torch_balance(mean_sq, max_iter=2000):
    """The previous implementation: the balancing iterations on tensors."""
    rows = torch.ones(mean_sq.shape[0], dtype=mean_sq.dtype)
    for _ in range(max_iter):
        cols = torch.sqrt((mean_sq / rows[:, None] ** 2).mean(dim=0))
        active = cols > 0
        if not bool(active.any()):
            break
        ratio = mean_sq[:, active] / cols[active] ** 2
        new_rows = torch.sqrt(ratio.mean(dim=1))
        new_rows = torch.where(new_rows > 0, new_rows, torch.ones_like(new_rows))
        new_rows = new_rows / torch.exp(torch.log(new_rows).mean())
        if torch.allclose(new_rows, rows, rtol=1e-10, atol=0):
            return new_rows
        rows = new_rows
    return rows


def test_row_balance_on_numpy_equals_the_torch_iterations():
    rng = np.random.default_rng(0)
    for n_dof, p in ((2, 39), (3, 10), (1, 5)):
        mean_sq = rng.lognormal(sigma=3.0, size=(n_dof, p))
        mean_sq[0, 0] = 0.0  # a column zero in one coordinate
        if n_dof > 1:
            mean_sq[:, 1] = 0.0  # a column zero everywhere
        want = _torch_balance(torch.tensor(mean_sq)).numpy()
        # measured: 2.2e-16 relative at most
        np.testing.assert_allclose(balance_rows(mean_sq), want, rtol=1e-13)
    gram = torch.tensor(rng.normal(size=(2, 6, 6)))
    gram = gram @ gram.transpose(1, 2)
    for dtype in (torch.float64, torch.float32):
        balanced = BalancedGram(gram.to(dtype), 10, 5)
        assert balanced.row_scale.dtype == dtype


# ----------------------------------------------------------------- names
def test_feature_names_cache_follows_set_params_and_clone():
    lib = CandidateLibrary.polynomial(["x", "theta"], angles=["theta"], degree=2)
    names = lib.get_feature_names_out()
    assert names.tolist() == [str(t) for t in lib.terms_]
    names[0] = "changed"  # each call returns a new array
    assert lib.get_feature_names_out()[0] == str(lib.terms_[0])
    lib.set_params(degree=3)  # rebuilt: the names of the new terms
    assert lib.get_feature_names_out().tolist() == [str(t) for t in lib.terms_]
    assert len(lib.get_feature_names_out()) == len(lib) > len(names)
    copy = clone(lib).set_params(angles=None, raw_angles=True)
    assert copy.get_feature_names_out().tolist() == [str(t) for t in copy.terms_]
    assert "cos(theta)" in lib.get_feature_names_out().tolist()
    assert "cos(theta)" not in copy.get_feature_names_out().tolist()


def test_fourth_differences_at_once_equal_one_segment_at_a_time():
    """The noise covariance and the white-velocity check take the fourth differences
    of all segments at once: the same as one ``torch.diff`` per segment (segments
    shorter than 5 rows, and in any order, included), bit for bit."""
    from lagsindy.formulation.weak import (
        WHITE_VELOCITY,
        estimate_noise_covariance,
        white_velocities,
    )

    rng = np.random.default_rng(3)
    X = torch.tensor(rng.normal(size=(60, 6)))
    for segs in (
        [torch.arange(0, 25), torch.arange(25, 28), torch.arange(28, 60)],
        [torch.arange(40, 60), torch.arange(0, 40)],
        [torch.arange(0, 4)],
    ):
        parts = [torch.diff(X[s, :4], n=4, dim=0) for s in segs if len(s) > 4]
        want = (
            torch.zeros(4, 4, dtype=X.dtype)
            if not parts
            else (lambda z: z.T @ z / (70.0 * z.shape[0]))(torch.cat(parts))
        )
        assert torch.equal(estimate_noise_covariance(X, segs, 2), want)
        qd = [X[s, 2:4] for s in segs if len(s) > 4]
        if qd:
            level = torch.sqrt(
                torch.cat([torch.diff(v, n=4, dim=0) for v in qd]).pow(2).mean(0) / 70
            )
            white = bool((level > WHITE_VELOCITY * torch.cat(qd).std(dim=0)).all())
        else:
            white = False
        assert white_velocities(X, segs, 2) == white
    # rows given as arrays or lists, as the 0.1 module path's users may pass them
    as_arrays = [np.arange(0, 25), list(range(25, 60))]
    as_tensors = [torch.arange(0, 25), torch.arange(25, 60)]
    assert torch.equal(
        estimate_noise_covariance(X, as_arrays, 2),
        estimate_noise_covariance(X, as_tensors, 2),
    )
