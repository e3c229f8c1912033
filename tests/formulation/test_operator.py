"""The Euler-Lagrange operator's fast paths against plain reference computations.

Each fast path replaced a simpler computation (the strong-form Gram accumulated in
reused chunk buffers, kernels writing into given buffers, the weak form's integrands
and banded window sums); the simpler one is written out here as the reference (the
code before the change, or the definition), so that the two must keep agreeing: to
rounding where the order of the sums changed, exactly where the fast path only
copies.
"""

import numpy as np
import pytest
import sympy as sp
import torch
from _sympy_reference import random_states, sympy_columns

import lagsindy.formulation.operator as operator_module
import lagsindy.formulation.weak as weak_module
from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy._batched import compile_terms
from lagsindy.euler_lagrange import EulerLagrangeOperator
from lagsindy.formulation.weak import _band, _correlate
from lagsindy.systems import cart_pendulum, make_dataset


@pytest.mark.parametrize("cache", [1, 3000, 1 << 20])
def test_gram_in_reused_chunk_buffers_matches_sympy_columns(monkeypatch, cache):
    """The Gram accumulated chunk by chunk in one reused buffer (columns written in
    place, forces, extra columns and the target beside them) equals A^T A of the
    sympy columns, whatever the chunk size (1: the 256-row minimum; 3000 elements:
    chunks of 13 rows and a partial last chunk; the default: one chunk)."""
    monkeypatch.setattr(operator_module, "GRAM_CACHE", cache)
    monkeypatch.setattr(operator_module, "GRAM_MIN_CHUNK", 1 if cache > 1 else 256)
    names = ["x", "theta"]
    lib = CandidateLibrary.polynomial(names, angles=["theta"], degree=3).build()
    w1, w2 = sp.symbols("x_dot theta_dot", real=True)
    op = EulerLagrangeOperator(names, lib.terms_, forces=[[-w1, 0], [0, -(w2**3)]])
    q, qd, qdd = random_states(2, 300, 0)
    X = torch.cat([q, qd, qdd], dim=1)
    rng = np.random.default_rng(1)
    y = torch.tensor(rng.normal(size=(300, 2)))
    extra = torch.tensor(rng.normal(size=(300, 2, 1)))
    forces = -np.stack([-qd[:, 0].numpy(), -(qd[:, 1].numpy() ** 3)], 1)  # columns -Q
    force_cols = np.zeros((300, 2, 2))
    force_cols[:, 0, 0], force_cols[:, 1, 1] = forces[:, 0], forces[:, 1]
    a = np.concatenate(
        [
            sympy_columns(lib.terms_, names, q, qd, qdd),
            force_cols,
            extra.numpy(),
            y.numpy()[:, :, None],
        ],
        axis=2,
    )
    want = np.einsum("sip,siq->ipq", a, a)
    got = op.gram(X, y, extra=extra).numpy()
    # measured: 1.4e-16 of the largest entry, at every chunk size
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-13 * np.abs(want).max())


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


def test_weak_integrands_written_from_the_kernel_equal_the_concatenated_ones():
    """The weak form's per-sample integrands, copied straight from the gradient
    kernel into their buffers, equal those concatenated from the gradients (the
    previous construction): dphi/dqd beside zeros, and dphi/dq, forces, -extra,
    -y."""
    from lagsindy.formulation.operator import lagrangian_gradients

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
    g = lagrangian_gradients(op._fn, qo, qdo)
    forces = op.force_values(qo, qdo)
    e, tau = extra[order], y[order].unsqueeze(2)
    zeros = [torch.zeros_like(x) for x in (forces, e, tau)]
    want_a = torch.cat([g[:, :, 2:].transpose(1, 2), *zeros], dim=2)
    want_b = torch.cat([g[:, :, :2].transpose(1, 2), forces, -e, -tau], dim=2)
    a_int, b_int = op._weak_integrands(qo, qdo, order, y, extra)
    # measured: equal (both are copies of the same kernel values)
    np.testing.assert_array_equal(a_int.numpy(), want_a.numpy())
    np.testing.assert_array_equal(b_int.numpy(), want_b.numpy())


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
    monkeypatch.setattr(weak_module, "BAND_ENTRIES", 100)
    monkeypatch.setattr(weak_module, "BAND_BLOCK", 4)
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
    assert isinstance(band, weak_module._BlockBand)
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
    whole = LagrangianSINDy(library, window=81).fit(data.X, data.tau)
    monkeypatch.setattr(weak_module, "BAND_ENTRIES", 1000)
    monkeypatch.setattr(weak_module, "BAND_BLOCK", 8)
    blocks = LagrangianSINDy(library, window=81).fit(data.X, data.tau)
    # measured: 3.1e-13 relative at most
    np.testing.assert_allclose(blocks.coef_, whole.coef_, rtol=1e-12, atol=0)
    assert np.array_equal(blocks.coef_ != 0, whole.coef_ != 0)
