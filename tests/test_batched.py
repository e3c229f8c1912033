"""The batched Euler-Lagrange kernels against sympy and against the torch.func path."""

import pickle

import numpy as np
import pytest
import sympy as sp
import torch
from _sympy_reference import random_states, sympy_columns

from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy._batched import compile_terms
from lagsindy._expr import compile_torch, symbols_for
from lagsindy.evaluator import (
    lagrangian_columns,
    lagrangian_components,
    lagrangian_gradients,
    lagrangian_hessians,
)
from lagsindy.library import _KINDS

# Every generated kind of library (a kind added to library._KINDS is tested too),
# on a cart-like system (one raw coordinate, one angle) and on two angles.
SETUPS = [
    (["x", "theta"], ["theta"], 3),
    (["theta1", "theta2"], "all", 2),
]
CASES = [(kind, *setup) for kind in _KINDS for setup in SETUPS]


def _assert_close(got, want, what):
    # Relative to each column's size: measured agreement is about 1e-15.
    scale = np.maximum(np.abs(want).max(axis=0, keepdims=True), 1.0)
    np.testing.assert_array_less(np.abs(got - want) / scale, 1e-10, err_msg=what)


@pytest.mark.parametrize("kind,names,angles,degree", CASES)
def test_batched_columns_match_sympy_and_torch_func(kind, names, angles, degree):
    lib = CandidateLibrary(names, kind=kind, angles=angles, degree=degree).build()
    kernels = compile_terms(lib.terms_, names)
    assert kernels.general.size == 0  # every generated term takes the batched path
    q, qd, qdd = random_states(len(names), 40, 0)
    got = lagrangian_columns(kernels, q, qd, qdd).numpy()
    want = sympy_columns(lib.terms_, names, q, qd, qdd)
    _assert_close(got, want, f"{kind} {names}: batched vs sympy")
    q_s, qd_s, _ = symbols_for(names)
    old = lagrangian_columns(compile_torch(lib.terms_, (q_s, qd_s)), q, qd, qdd)
    _assert_close(got, old.numpy(), f"{kind} {names}: batched vs torch.func")


@pytest.mark.parametrize("kind,names,angles,degree", CASES[:2])
def test_batched_components_and_gradients_match_torch_func(kind, names, angles, degree):
    lib = CandidateLibrary(names, kind=kind, angles=angles, degree=degree).build()
    kernels = compile_terms(lib.terms_, names)
    q_s, qd_s, _ = symbols_for(names)
    plain = compile_torch(lib.terms_, (q_s, qd_s))
    q, qd, _ = random_states(len(names), 30, 1)
    for got, want in zip(
        lagrangian_components(kernels, q, qd), lagrangian_components(plain, q, qd)
    ):
        _assert_close(got.numpy(), want.numpy(), "components")
    _assert_close(
        lagrangian_gradients(kernels, q, qd).numpy(),
        lagrangian_gradients(plain, q, qd).numpy(),
        "gradients",
    )
    # the weak form's noise correction: full Hessians over [q, qd]
    _assert_close(
        kernels.hessians(q, qd, lagrangian_hessians).numpy(),
        lagrangian_hessians(plain, q, qd).numpy(),
        "hessians",
    )
    general = _general_components()
    _assert_close(
        kernels.mass_matrices(q, qd, general).numpy(),
        lagrangian_components(plain, q, qd)[0].numpy(),
        "mass matrices",
    )
    # samples last: the same values (bit for bit: one kernel, no arithmetic)
    assert torch.equal(
        kernels.mass_matrices_t(q, qd, general),
        kernels.mass_matrices(q, qd, general).permute(1, 2, 3, 0),
    )
    assert torch.equal(
        kernels.hessians_t(q, qd, lagrangian_hessians),
        kernels.hessians(q, qd, lagrangian_hessians).permute(1, 2, 3, 0),
    )
    assert torch.equal(
        kernels.gradients_t(q, qd, lagrangian_gradients),
        kernels.gradients(q, qd, lagrangian_gradients).permute(1, 2, 0),
    )


def _general_components():
    def general(f, q, qd):
        return lagrangian_components(f, q, qd)

    return general


def test_mixed_terms_split_between_batched_and_general_paths():
    names = ["theta1", "theta2"]
    t1, t2 = sp.symbols(names, real=True)
    w1, w2 = sp.symbols(["theta1_dot", "theta2_dot"], real=True)
    terms = [
        w1 * w2 * sp.cos(t1 - t2),  # batched: chain difference
        sp.exp(t1) * w1**2,  # general
        w2**2 * sp.sin(2 * t2),  # batched: multiple angle
        (w1 + t2) ** 2,  # general: a power of a sum
        sp.sqrt(1 + w1**2),  # general
        3 * w1**2 * t2**3 + w2**2 / 2,  # batched: a sum of monomials
        sp.cos(t1 + 1) * w2**2,  # general: constant offset
    ]
    kernels = compile_terms(terms, names)
    assert kernels.supported.tolist() == [0, 2, 5]
    assert kernels.general.tolist() == [1, 3, 4, 6]
    q, qd, qdd = random_states(2, 25, 2)
    got = lagrangian_columns(kernels, q, qd, qdd).numpy()
    _assert_close(got, sympy_columns(terms, names, q, qd, qdd), "mixed vs sympy")
    hess = kernels.hessians(q, qd, lagrangian_hessians).numpy()
    q_s, qd_s, _ = symbols_for(names)
    x_s = q_s + qd_s
    for k in (0, 1, 5):  # batched, general, batched sum
        h = sp.lambdify(x_s, sp.hessian(terms[k], x_s), modules="numpy")
        want = np.stack([np.asarray(h(*row), float) for row in np.c_[q, qd]])
        _assert_close(hess[:, k], want, f"hessian of term {k} vs sympy")
    # the samples-last layouts, general terms included
    general = _general_components()
    assert torch.equal(
        kernels.mass_matrices_t(q, qd, general),
        kernels.mass_matrices(q, qd, general).permute(1, 2, 3, 0),
    )
    assert torch.equal(
        kernels.hessians_t(q, qd, lagrangian_hessians),
        kernels.hessians(q, qd, lagrangian_hessians).permute(1, 2, 3, 0),
    )
    assert torch.equal(
        kernels.gradients_t(q, qd, lagrangian_gradients),
        kernels.gradients(q, qd, lagrangian_gradients).permute(1, 2, 0),
    )


def test_kernels_are_callable_per_sample_and_pickle():
    lib = CandidateLibrary.polynomial(["x", "theta"], angles=["theta"], degree=2)
    kernels = lib.to_torch()
    q, qd, qdd = random_states(2, 10, 4)
    per_sample = torch.func.vmap(kernels)(q, qd)
    q_s, qd_s, _ = symbols_for(lib.coordinates_)
    f = sp.lambdify(q_s + qd_s, lib.terms_, modules="numpy")
    want = np.stack(
        [np.broadcast_to(v, (10,)) for v in f(*q.numpy().T, *qd.numpy().T)], 1
    )
    np.testing.assert_allclose(per_sample.numpy(), want, rtol=1e-13)
    again = pickle.loads(pickle.dumps(kernels))
    np.testing.assert_array_equal(
        lagrangian_columns(again, q, qd, qdd).numpy(),
        lagrangian_columns(kernels, q, qd, qdd).numpy(),
    )


def test_batched_rows_in_several_batches(monkeypatch):
    """Row batching of the kernels (small BATCH_ELEMENTS) changes nothing."""
    import lagsindy._batched as batched

    lib = CandidateLibrary.polynomial(["x", "theta"], angles=["theta"], degree=3)
    kernels = compile_terms(lib.terms_, lib.coordinates_)
    q, qd, qdd = random_states(2, 1000, 5)
    whole = lagrangian_columns(kernels, q, qd, qdd)
    monkeypatch.setattr(batched, "BATCH_ELEMENTS", 1)  # 256 rows per batch
    got = lagrangian_columns(kernels, q, qd, qdd)
    # measured: equal bit for bit; the margin leaves room for SIMD kernels that
    # round a vector's tail differently on other CPUs (a batching bug shows at O(1))
    scale = float(whole.abs().max())
    np.testing.assert_allclose(got, whole, rtol=1e-14, atol=1e-14 * scale)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_fit_on_cuda_matches_cpu():
    from lagsindy.systems import cart_pendulum, make_dataset

    system = cart_pendulum()
    data = make_dataset(system, n_trajectories=4, excitation="sincos", random_state=0)
    lib = system.paper_library()
    cpu = LagrangianSINDy(lib, formulation="strong").fit(data.X, data.tau)
    gpu = LagrangianSINDy(lib, formulation="strong", device="cuda").fit(
        data.X, data.tau
    )
    np.testing.assert_array_equal(gpu.support_, cpu.support_)
    np.testing.assert_allclose(gpu.coef_, cpu.coef_, rtol=1e-8, atol=1e-10)


def test_a_kernel_without_entries_writes_zeros():
    """torch's sparse addmm leaves ``out`` untouched for a matrix without entries:
    the single pendulum's mixed derivatives (all zero) came out of uninitialized
    memory, now and then NaN (a case II fit failed in some processes only)."""
    from lagsindy.systems import single_pendulum

    lib = single_pendulum().paper_library().build()
    fn = compile_terms(lib.terms_, lib.coordinates_)
    kernel = fn.plan["cross"]
    assert kernel.tensors(torch.zeros(1, dtype=torch.float64))[3]._nnz() == 0
    q, qd, _ = random_states(1, 50, seed=3)
    base = fn._base(q.T, qd.T, None)
    out = torch.full((kernel.n_out, 50), float("nan"), dtype=torch.float64)
    kernel.evaluate(base, out=out)
    assert torch.equal(out, torch.zeros_like(out))
    blocks = [torch.full((kernel.n_out, 50), float("nan"), dtype=torch.float64)]
    kernel.evaluate_blocks(base, blocks)
    assert torch.equal(blocks[0], torch.zeros_like(blocks[0]))


def test_building_kernels_warns_nothing_and_leaves_torch_settings():
    """torch 2.11 warned "Sparse invariant checks are implicitly disabled" at each
    sparse matrix built without the global check set (a ``--quiet`` command printed
    it); the check is now set around the construction and restored after."""
    import warnings

    from lagsindy.systems import cart_pendulum

    lib = cart_pendulum().paper_library().build()
    fn = compile_terms(lib.terms_, lib.coordinates_)
    q = torch.rand(7, 2, dtype=torch.float64)
    before = torch.sparse.check_sparse_tensor_invariants.is_enabled()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lagrangian_columns(fn, q, torch.rand_like(q), torch.rand_like(q))
    assert torch.sparse.check_sparse_tensor_invariants.is_enabled() == before
