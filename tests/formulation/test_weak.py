"""The weak form's integrals (lagsindy.formulation.weak_integrals) and its test
functions' window sums (lagsindy.formulation.testfunctions), against direct sums,
brute-force derivatives and fresh calls."""

import numpy as np
import pytest
import sympy as sp
import torch
from _sympy_reference import random_states

from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy._expr import compile_torch, symbols_for
from lagsindy.evaluator import TorchTerms
from lagsindy.formulation import AutoForm, testfunctions, weak_integrals
from lagsindy.formulation.operator import EulerLagrangeOperator
from lagsindy.formulation.testfunctions import _band, _correlate, bump_function
from lagsindy.systems import cart_pendulum, make_dataset, single_pendulum


def test_weak_columns_equal_integrated_strong_columns():
    """int psi * EL(phi) dt: by parts (weak) equals the direct integral of Theta."""
    data = make_dataset(
        cart_pendulum(), n_trajectories=2, excitation="sincos", random_state=0
    )
    lib = cart_pendulum().paper_library()
    op = EulerLagrangeOperator(lib.coordinates_, lib.terms_)
    X = torch.tensor(data.X_clean)
    seg = [torch.arange(0, 500)]
    window, stride, dt = 61, 15, 0.01
    weak, n_w = op.weak_gram(X, None, seg, window=window, stride=stride, dt=dt)
    theta = op.columns(X[:500])  # strong columns (exact accelerations)
    psi, _ = bump_function(window, dt)
    direct = torch.stack(
        [
            (psi[:, None, None] * theta[s : s + window]).sum(0) * dt
            for s in range(0, 500 - window + 1, stride)
        ]
    )
    assert direct.shape[0] == n_w
    ref = torch.einsum("wip,wiq->ipq", direct, direct)
    np.testing.assert_allclose(
        weak.numpy(), ref.numpy(), rtol=2e-4, atol=1e-6 * float(ref.abs().max())
    )


def test_noise_correction_removes_expected_bias():
    """Averaged over noise draws, the corrected Gram matches the clean one.

    The kinetic entry's bias is first order in the noise variance and must vanish;
    entries with sines and cosines keep a small second-order shrinkage
    (E cos(q + e) = exp(-sigma^2 / 2) cos q, 2 % at sigma = 0.2), which the first-order
    correction does not model.
    """
    data = make_dataset(
        single_pendulum(), n_trajectories=4, excitation="paper", random_state=1
    )
    lib = CandidateLibrary.from_terms(["theta"], ["theta_dot**2", "cos(theta)"])
    op = EulerLagrangeOperator(lib.coordinates_, lib.terms_)
    segs = [torch.arange(i * 500, (i + 1) * 500) for i in range(4)]
    kw = dict(window=41, stride=10, dt=0.01)
    clean = op.weak_gram(torch.tensor(data.X_clean), None, segs, **kw)[0][0].numpy()
    sigma, draws = 0.2, 40
    cov = torch.eye(2, dtype=torch.float64) * sigma**2
    rng = np.random.default_rng(2)
    raw, corrected = [], []
    for _ in range(draws):
        noisy = torch.tensor(data.X_clean + sigma * rng.normal(size=data.X_clean.shape))
        raw.append(op.weak_gram(noisy, None, segs, **kw)[0][0].numpy())
        corrected.append(
            op.weak_gram(noisy, None, segs, noise_cov=cov, **kw)[0][0].numpy()
        )
    raw, corrected = np.array(raw), np.array(corrected)
    se = raw.std(axis=0) / np.sqrt(draws)
    assert raw.mean(0)[0, 0] - clean[0, 0] > 5 * se[0, 0]  # attenuation bias
    assert abs(corrected.mean(0)[0, 0] - clean[0, 0]) < 3 * se[0, 0]  # removed
    np.testing.assert_allclose(corrected.mean(0), clean, rtol=0.05, atol=3 * se.max())


def test_noise_part_equals_its_definition_by_brute_force():
    """The noise Gram is sum_w sum_s J_ws^T Lambda J_ws, J_ws = d cols_w / d x_s.

    The reference differentiates each window's columns with respect to each sample
    by reverse-mode autograd of a direct sum over the window (no per-sample weights,
    no factorization), for two coordinates, a non-diagonal Lambda, batched and
    general Lagrangian terms, and force terms.
    """
    import sympy as sp

    names = ["x", "theta"]
    x, t = sp.symbols(names, real=True)
    xd, td = sp.symbols(["x_dot", "theta_dot"], real=True)
    terms = [xd**2, xd * td * sp.cos(t), sp.exp(-(x**2)) * td**2, sp.cos(t)]
    forces = [[-sp.tanh(5 * xd), 0], [td - xd, xd - td]]
    op = EulerLagrangeOperator(names, terms, forces=forces)
    rng = np.random.default_rng(4)
    X = torch.tensor(rng.normal(size=(47, 6)))
    segs = [torch.arange(0, 30), torch.arange(30, 47)]
    window, stride, dt = 9, 4, 0.05
    cov = torch.tensor(
        [
            [0.3, 0.1, 0.0, 0.05],
            [0.1, 0.2, 0.0, 0.0],
            [0.0, 0.0, 0.4, 0.1],
            [0.05, 0.0, 0.1, 0.5],
        ]
    )
    _, noise, _ = op.weak_gram(
        X,
        None,
        segs,
        window=window,
        stride=stride,
        dt=dt,
        noise_cov=cov.double(),
        return_noise=True,
    )
    psi, dpsi = bump_function(window, dt)
    d, p = 2, len(terms) + len(forces)
    q_s, qd_s = [x, t], [xd, td]
    # integrands per coordinate i and column k: a = dphi/dqd_i (zero for forces),
    # b = dphi/dq_i (Q_k,i for forces); each window's column is -dt sum(dpsi a + psi b)
    a_exprs = [
        [sp.diff(f, qd_s[i]) for f in terms] + [0] * len(forces) for i in range(d)
    ]
    b_exprs = [
        [sp.diff(f, q_s[i]) for f in terms] + [fo[i] for fo in forces] for i in range(d)
    ]
    fa = sp.lambdify(q_s + qd_s, a_exprs, modules="numpy")
    fb = sp.lambdify(q_s + qd_s, b_exprs, modules="numpy")
    eps = 1e-6  # central differences of the integrands, per sample
    want = np.zeros((d, p, p))
    covn = cov.numpy()
    for seg in segs:
        rows = X[seg, :4].numpy()
        n = len(rows)
        da = np.zeros((n, d, p, 4))
        db = np.zeros((n, d, p, 4))
        for b in range(4):
            up, down = rows.copy(), rows.copy()
            up[:, b] += eps
            down[:, b] -= eps
            for out, f in ((da, fa), (db, fb)):
                hi = np.array(
                    [np.broadcast_to(np.asarray(f(*r), float), (d, p)) for r in up]
                )
                lo = np.array(
                    [np.broadcast_to(np.asarray(f(*r), float), (d, p)) for r in down]
                )
                out[..., b] = (hi - lo) / (2 * eps)
        for start in range(0, n - window + 1, stride):
            for j in range(window):
                s = start + j
                jac = -dt * (
                    dpsi[j].item() * da[s] + psi[j].item() * db[s]
                )  # (d, p, 4)
                want += np.einsum("ikx,xy,ily->ikl", jac, covn, jac)
    # measured: 2.6e-11 of the largest entry (the central differences' error)
    np.testing.assert_allclose(
        noise[:, :p, :p].numpy(), want, rtol=1e-9, atol=1e-9 * np.abs(want).max()
    )


def _assert_same_to_rounding(a, b):
    """Equal to 1e-12 of the matrix's largest entry: entries that are zero but for
    rounding (1e-21 against 0.14 in the noise part) differ between CPUs and orders of
    summation, so an entrywise relative tolerance alone would fail on some
    machines."""
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())


def test_weak_grams_of_several_windows_equal_one_window_each():
    """One evaluation of the integrands serves every window: the statistics of each
    equal a separate weak_gram call, including the noise part and a trajectory too
    short for the longer window (its rows then carry no weight)."""
    data = make_dataset(
        cart_pendulum(),
        n_trajectories=3,
        excitation="sincos",
        noise=0.01,
        random_state=3,
    )
    lib = cart_pendulum().paper_library()
    op = EulerLagrangeOperator(lib.coordinates_, lib.terms_)
    X = torch.tensor(data.X)
    tau = torch.tensor(data.tau)
    segs = [torch.arange(0, 500), torch.arange(500, 620), torch.arange(1000, 1500)]
    cov = torch.diag(torch.tensor([1e-4, 2e-4, 3e-4, 1e-3], dtype=torch.float64))
    kw = dict(dt=0.01, noise_cov=cov, noise_rows=700, return_noise=True)
    by_window = {61: segs, 161: [segs[0], segs[2]]}
    both = op.weak_grams(X, tau, by_window, strides={61: 15, 161: 40}, **kw)
    for window, stride in ((61, 15), (161, 40)):
        alone = op.weak_gram(
            X, tau, by_window[window], window=window, stride=stride, **kw
        )
        if window == 161:  # the noise subsample differs (fewer rows): compare raw
            alone = (alone[0], None, alone[2])
        for a, b in zip(both[window], alone):
            if b is not None:
                _assert_same_to_rounding(np.asarray(a), np.asarray(b))
    # the noise part of the longer window, with every row sampled, against alone
    kw["noise_rows"] = 10**6
    both = op.weak_grams(X, tau, by_window, strides={61: 15, 161: 40}, **kw)
    alone = op.weak_gram(X, tau, by_window[161], window=161, stride=40, **kw)
    _assert_same_to_rounding(both[161][1].numpy(), alone[1].numpy())
    assert float(alone[1].abs().max()) > 0


def _cart_weak_case(n_trajectories, random_state, noise=0.01):
    """The cart-pendulum's paper-library operator, its rows and inputs as tensors,
    and a noise covariance for [q, qd]."""
    data = make_dataset(
        cart_pendulum(), n_trajectories=n_trajectories, excitation="sincos",
        noise=noise, random_state=random_state,
    )  # fmt: skip
    lib = cart_pendulum().paper_library()
    op = EulerLagrangeOperator(lib.coordinates_, lib.terms_)
    cov = torch.diag(torch.tensor([1e-4, 2e-4, 3e-4, 1e-3], dtype=torch.float64))
    return op, torch.tensor(data.X), torch.tensor(data.tau), cov


def test_reuse_weak_columns_gives_the_statistics_of_a_fresh_call(reused_grams):
    """Inside reuse_weak_columns a second call on the same samples with other forces
    takes the features' part from the first and equals a fresh call (noise part
    included); other samples, or leaving the block, compute afresh."""
    op, X, tau, cov = _cart_weak_case(3, 4)
    shifted = torch.roll(tau, 3, dims=0) * 1.5
    segs = [torch.arange(0, 500), torch.arange(500, 1000), torch.arange(1000, 1500)]
    kw = dict(
        strides={61: 15, 121: 30}, dt=0.01, noise_cov=cov, noise_rows=700,
        return_noise=True,
    )  # fmt: skip
    by_window = {61: segs, 121: segs[:2]}
    reused = reused_grams
    fresh = op.weak_grams(X, shifted, by_window, **kw)
    with weak_integrals.reuse_weak_columns():
        first = op.weak_grams(X, tau, by_window, **kw)
        assert not reused
        again = op.weak_grams(X, shifted, by_window, **kw)
        assert len(reused) == 1
        op.weak_grams(X * 1.01, shifted, by_window, **kw)  # other samples: afresh
        assert len(reused) == 1
    op.weak_grams(X, shifted, by_window, **kw)  # outside the block: afresh
    assert len(reused) == 1
    for window in by_window:
        for a, b in zip(again[window], fresh[window]):
            a, b = np.asarray(a), np.asarray(b)
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
        # the forces' row did change: the comparison can fail
        assert not torch.allclose(first[window][0][:, -1], fresh[window][0][:, -1])


def test_reuse_weak_columns_serves_a_subset_of_the_kept_features(reused_grams):
    """A call whose features are among a kept call's (in another order, forces
    included, with or without a generalized force) takes their block: it equals a
    fresh call to rounding; a feature the kept call lacks means a fresh call."""
    import sympy as sp

    from lagsindy._expr import symbols_for
    from lagsindy.dissipation import make_term

    _, X, tau, cov = _cart_weak_case(3, 5)
    terms = list(cart_pendulum().paper_library().terms_)
    coords = ["x", "theta"]
    forces = [
        make_term(kind, c, coords).forces
        for kind, c in (("viscous", "x"), ("coulomb", "theta"), ("drag", "x"))
    ]
    union = EulerLagrangeOperator(coords, terms, forces=forces)
    pick = [7, 0, 3, 12]  # a few terms, not in the library's order
    sub = EulerLagrangeOperator(coords, [terms[k] for k in pick], forces=forces[1:2])
    q_s, qd_s, _ = symbols_for(coords)
    wider = EulerLagrangeOperator(coords, terms[:3] + [sp.exp(q_s[0]) * qd_s[1] ** 2])
    segs = [torch.arange(0, 500), torch.arange(500, 1000), torch.arange(1000, 1500)]
    kw = dict(strides={61: 15}, dt=0.01, noise_cov=cov, noise_rows=700)
    kw["return_noise"] = True
    reused = reused_grams
    fresh = {y: sub.weak_grams(X, y, {61: segs}, **kw)[61] for y in (None, tau)}
    with weak_integrals.reuse_weak_columns():
        union.weak_grams(X, None, {61: segs}, **kw)  # kept, without a force
        got = {y: sub.weak_grams(X, y, {61: segs}, **kw)[61] for y in (None, tau)}
        assert len(reused) == 2
        wider.weak_grams(X, tau, {61: segs}, **kw)  # a term not kept: afresh
        assert len(reused) == 2
    for y in (None, tau):
        for a, b in zip(got[y][:2], fresh[y][:2]):  # Gram, noise part
            a, b = a.numpy(), b.numpy()
            assert a.shape == b.shape == (2, 5 + (y is not None), 5 + (y is not None))
            # measured: the Gram equal, the noise part to 1.5e-18 of its largest
            # entry (a gather of the kept block; rounding may differ on other BLAS)
            np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-14 * np.abs(b).max())
        assert got[y][2] == fresh[y][2]  # windows
    assert float(fresh[tau][1].abs().max()) > 0  # the noise part is there to compare


def test_reuse_weak_columns_per_segment_with_extra_columns(reused_grams):
    """Statistics kept per segment (what diagnose's folds and the bootstrap sum) are
    reused too, with other forces and other extra columns: equal to a fresh call to
    rounding; a build at another sampling interval is computed afresh."""
    op, X, tau, cov = _cart_weak_case(3, 7)
    segs = [torch.arange(0, 500), torch.arange(500, 1000), torch.arange(1000, 1500)]
    kw = dict(
        strides={61: 15}, dt=0.01, noise_cov=cov, return_noise=True, per_segment=True
    )
    shifted = torch.roll(tau, 5, dims=0) * 1.3
    extra = -tau[:, :, None].repeat(1, 1, 2) * torch.tensor([1.0, 0.5])
    extra_sh = -shifted[:, :, None].repeat(1, 1, 2) * torch.tensor([1.0, 0.5])
    fresh = op.weak_grams(X, shifted, {61: segs}, extra=extra_sh, **kw)[61]
    later = op.weak_grams(X, shifted, {61: segs}, extra=extra_sh, lazy=True, **kw)
    reused = reused_grams
    with weak_integrals.reuse_weak_columns():
        op.weak_grams(X, tau, {61: segs}, extra=extra, **kw)
        assert not reused
        again = op.weak_grams(X, shifted, {61: segs}, extra=extra_sh, **kw)[61]
        assert len(reused) == 1
        lazy = op.weak_grams(X, shifted, {61: segs}, extra=extra_sh, lazy=True, **kw)
        other_dt = lazy[61](dt=0.0101)  # not the kept interval: afresh
        kw_whole = {k: v for k, v in kw.items() if k != "per_segment"}
        op.weak_grams(X, shifted, {61: segs}, **kw_whole)  # summed: another key
        assert len(reused) == 2
    for a, b in zip(again[:2], fresh[:2]):  # Gram and noise part, per segment
        a, b = a.numpy(), b.numpy()
        assert a.shape == b.shape == (3, 2, op.n_columns + 3, op.n_columns + 3)
        # measured: equal bit for bit (a gathered block; the inputs' rows from the
        # kept columns); another BLAS may round the sums differently
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-13 * np.abs(b).max())
    np.testing.assert_array_equal(again[2], fresh[2])  # windows per segment
    assert float(fresh[1].abs().max()) > 0  # the noise part is there to compare
    for a, b in zip(other_dt, later[61](dt=0.0101)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # the comparison can fail: the inputs' rows differ from the first call's
    first = op.weak_grams(X, tau, {61: segs}, extra=extra, **kw)[61]
    assert not torch.allclose(first[0][..., -1], fresh[0][..., -1])


def test_a_build_at_another_sampling_interval_is_not_kept(reused_grams):
    """Inside a reuse block a lazy build asked for at another sampling interval than
    its call's keeps nothing: a later call at the call's interval computes afresh."""
    op, X, tau, cov = _cart_weak_case(3, 8)
    segs = [torch.arange(0, 500), torch.arange(500, 1000), torch.arange(1000, 1500)]
    kw = dict(
        strides={61: 15}, dt=0.01, noise_cov=cov, return_noise=True, per_segment=True
    )
    shifted = torch.roll(tau, 4, dims=0)
    fresh = op.weak_grams(X, shifted, {61: segs}, **kw)[61]
    reused = reused_grams
    with weak_integrals.reuse_weak_columns():
        lazy = op.weak_grams(X, tau, {61: segs}, lazy=True, **kw)
        lazy[61](dt=0.0102)
        again = op.weak_grams(X, shifted, {61: segs}, **kw)[61]
        assert not reused
    for a, b in zip(again, fresh):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_reuse_weak_columns_keeps_its_own_copy():
    """A caller changing the matrices a kept call returned does not change what a
    later call gathers."""
    op, X, tau, _ = _cart_weak_case(2, 6, noise=0.0)
    segs = [torch.arange(0, 500), torch.arange(500, 1000)]
    kw = dict(strides={61: 15}, dt=0.01, return_noise=True)
    with weak_integrals.reuse_weak_columns():
        first = op.weak_grams(X, tau, {61: segs}, **kw)[61]
        want = first[0].clone()
        first[0].mul_(2.0)  # the caller's own business
        again = op.weak_grams(X, tau, {61: segs}, **kw)[61]
    # the force row is summed again (rounding); the doubled matrix would be 2x off
    np.testing.assert_allclose(again[0].numpy(), want.numpy(), rtol=1e-12)


@pytest.mark.parametrize("chunk", [1, 600])
def test_weak_integrands_by_chunks_equal_one_block(monkeypatch, chunk):
    """The integrands evaluated by groups of whole trajectories (one each, or a few)
    give the Gram statistics of one evaluation on all rows, noise part included,
    with trajectories of several lengths."""
    op, X, tau, cov = _cart_weak_case(4, 7)
    segs = [torch.arange(0, 500), torch.arange(500, 800), torch.arange(1000, 1500)]
    segs.append(torch.arange(1500, 1700))
    kw = dict(
        strides={61: 15, 161: 40}, dt=0.01, noise_cov=cov, return_noise=True
    )  # fmt: skip
    by_window = {61: segs, 161: segs[:3]}
    monkeypatch.setattr(weak_integrals, "WEAK_CHUNK", 1 << 40)  # one block
    whole = op.weak_grams(X, tau, by_window, **kw)
    monkeypatch.setattr(weak_integrals, "WEAK_CHUNK", chunk * 316)  # ~chunk rows
    parts = op.weak_grams(X, tau, by_window, **kw)
    order = torch.cat(segs)
    groups, owner = weak_integrals._integrand_chunks(
        op.evaluator,
        X[order, :2],
        X[order, 2:4],
        order,
        tau,
        None,
        [len(s) for s in segs],
    )
    # one trajectory per group, or 500 + 300 and 500 + 200 rows
    assert [g[0] for g in groups] == ([0, 500, 800, 1300] if chunk == 1 else [0, 800])
    assert owner == ([0, 1, 2, 3] if chunk == 1 else [0, 0, 1, 1])
    for window in by_window:
        for a, b in zip(parts[window][:2], whole[window][:2]):
            a, b = a.numpy(), b.numpy()
            # measured: equal (the same kernels row by row, summed in the same order)
            np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13 * np.abs(b).max())
        assert parts[window][2] == whole[window][2]


# ------------------------------------------------ test functions and window sums
def test_band_correlation_equals_the_sliding_sums():
    """Window sums as one banded matrix product: sum_j k[j] x[w * stride + j]."""
    rng = np.random.default_rng(0)
    signal = torch.tensor(rng.normal(size=(203, 2, 3)))
    kernel = torch.tensor(rng.normal(size=41))
    stride = 10
    n_win = (203 - 41) // stride + 1
    want = np.stack(
        [
            np.einsum("j,jab->ab", kernel.numpy(), signal.numpy()[s : s + 41])
            for s in range(0, n_win * stride, stride)
        ]
    )
    got = _correlate(signal, kernel, stride)
    assert got.shape == (n_win, 2, 3)
    # measured: equal (the product may sum in another order elsewhere)
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-13)
    again = _correlate(signal, kernel, stride, _band(kernel, 203, stride))
    np.testing.assert_array_equal(again.numpy(), got.numpy())
    assert _band(kernel, 30, stride).shape == (0, 30)  # shorter than the window


@pytest.mark.parametrize("n", [41 + 10 * (4 * 3 - 1), 41 + 10 * (4 * 3 + 1), 803])
def test_block_band_of_a_long_segment_equals_the_sliding_sums(monkeypatch, n):
    """A long segment's windows go through one block band slid along the rows (the
    whole band grows with the square of the length: 100,000 samples at window 81
    took 8 GB). With blocks of 4 windows: whole blocks only (12 windows), a partial
    last block (14), and many blocks (77)."""
    monkeypatch.setattr(testfunctions, "BAND_ENTRIES", 100)
    monkeypatch.setattr(testfunctions, "BAND_BLOCK", 4)
    rng = np.random.default_rng(1)
    signal = torch.tensor(rng.normal(size=(n, 2, 3)))
    kernel = torch.tensor(rng.normal(size=41))
    stride = 10
    n_win = (n - 41) // stride + 1
    want = np.stack(
        [
            np.einsum("j,jab->ab", kernel.numpy(), signal.numpy()[s : s + 41])
            for s in range(0, n_win * stride, stride)
        ]
    )
    band = _band(kernel, n, stride)
    assert isinstance(band, testfunctions._BlockBand)
    assert band.block.shape == (4, 3 * stride + 41)
    got = _correlate(signal, kernel, stride, band)
    assert got.shape == (n_win, 2, 3)
    # measured: 3.6e-15 at most, against entries of 15 to 30
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=3e-14)


def test_long_record_fits_as_with_the_whole_band(monkeypatch):
    """The weak-form fit of one record through block bands equals the one through
    whole band matrices (blocks of 8 windows on a 3,000-sample record)."""
    data = make_dataset(
        cart_pendulum(), n_trajectories=1, duration=30.0, excitation="sincos",
        random_state=0,
    )  # fmt: skip
    library = cart_pendulum().paper_library()
    whole = LagrangianSINDy(library, formulation=AutoForm(window=81)).fit(
        data.X, data.tau
    )
    monkeypatch.setattr(testfunctions, "BAND_ENTRIES", 1000)
    monkeypatch.setattr(testfunctions, "BAND_BLOCK", 8)
    blocks = LagrangianSINDy(library, formulation=AutoForm(window=81)).fit(
        data.X, data.tau
    )
    # measured: 3.1e-13 relative at most
    np.testing.assert_allclose(blocks.coef_, whole.coef_, rtol=1e-12, atol=0)
    assert np.array_equal(blocks.coef_ != 0, whole.coef_ != 0)


def test_weak_integrands_written_from_the_kernel_equal_the_concatenated_ones():
    """The weak form's per-sample integrands, copied straight from the gradient
    kernel into their buffers, equal those concatenated from the gradients (the
    previous construction): dphi/dqd beside zeros, and dphi/dq, forces, -extra,
    -y."""
    names = ["x", "theta"]
    lib = CandidateLibrary.polynomial(names, angles=["theta"], degree=3).build()
    w1, w2 = sp.symbols("x_dot theta_dot", real=True)
    op = EulerLagrangeOperator(names, lib.terms_, forces=[[-w1, 0], [0, -w2]])
    q, qd, _ = random_states(2, 120, 3)
    rng = np.random.default_rng(4)
    order = torch.as_tensor(rng.permutation(120))
    y = torch.tensor(rng.normal(size=(120, 2)))
    extra = torch.tensor(rng.normal(size=(120, 2, 3)))
    qo, qdo = q[order], qd[order]
    g = op.evaluator.gradients(qo, qdo)
    forces = op.force_values(qo, qdo)
    e, tau = extra[order], y[order].unsqueeze(2)
    zeros = [torch.zeros_like(x) for x in (forces, e, tau)]
    want_a = torch.cat([g[:, :, 2:].transpose(1, 2), *zeros], dim=2)
    want_b = torch.cat([g[:, :, :2].transpose(1, 2), forces, -e, -tau], dim=2)
    a_int, b_int = weak_integrals._weak_integrands(
        op.evaluator, qo, qdo, order, y, extra
    )
    # measured: equal (both are copies of the same kernel values)
    np.testing.assert_array_equal(a_int.numpy(), want_a.numpy())
    np.testing.assert_array_equal(b_int.numpy(), want_b.numpy())


def test_weak_statistics_of_a_torch_term_function_equal_the_sympy_ones():
    """The weak form of terms given as a torch term function (gradients and the
    noise part's Hessians by torch.func) equals that of the same sympy terms
    (batched kernels), noise part and forces included."""
    op, X, tau, cov = _cart_weak_case(2, 9)
    names = op.coordinates
    terms = op.terms[::3]
    q_s, qd_s, _ = symbols_for(names)
    provider = TorchTerms([str(t) for t in terms], compile_torch(terms, (q_s, qd_s)))
    forces = [[-qd_s[0], 0 * qd_s[0]]]
    sym = EulerLagrangeOperator(names, terms, forces=forces)
    tor = EulerLagrangeOperator(names, provider, forces=forces)
    segs = [torch.arange(0, 500), torch.arange(500, 1000)]
    kw = dict(window=61, stride=15, dt=0.01, noise_cov=cov, return_noise=True)
    got = tor.weak_gram(X, tau, segs, **kw)
    want = sym.weak_gram(X, tau, segs, **kw)
    for a, b in zip(got[:2], want[:2]):
        a, b = a.numpy(), b.numpy()
        # measured: 1e-17 of the largest entry at most (rounding)
        np.testing.assert_allclose(a, b, rtol=0, atol=5e-17 * np.abs(b).max())
    assert got[2] == want[2] and float(want[1].abs().max()) > 0
