"""The datafits (lagsindy.solvers.datafits): the Gram quadratics cut from
:class:`~lagsindy.formulation.scaling.BalancedGram` and case II's acceleration datafit."""

import numpy as np
import pytest
import torch

from lagsindy.formulation.scaling import BalancedGram
from lagsindy.solvers import AccelerationDatafit


def test_balanced_gram_is_invariant_to_row_and_column_units():
    rng = np.random.default_rng(9)
    a = rng.normal(size=(200, 2, 4))
    y = a @ np.array([1.0, -1.0, 0.5, 0.0])
    full = np.concatenate([a, y[:, :, None]], axis=2)
    g1 = torch.tensor(np.einsum("sip,siq->ipq", full, full))
    scaled = (
        full * np.array([1.0, 1000.0])[None, :, None] * np.array([1, 7.0, 1, 0.01, 1])
    )
    g2 = torch.tensor(np.einsum("sip,siq->ipq", scaled, scaled))
    d1, _ = BalancedGram(g1, 200, 4).problem(np.arange(4), 4)
    d2, _ = BalancedGram(g2, 200, 4).problem(np.arange(4), 4)
    np.testing.assert_allclose(d1.gram.numpy(), d2.gram.numpy(), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(d1.rhs.numpy(), d2.rhs.numpy(), rtol=1e-9, atol=1e-12)


def test_balanced_gram_projects_an_indefinite_corrected_gram_to_the_nearest_psd():
    """Eigenvalues clamped at 0: the nearest PSD matrix in the Frobenius norm."""
    rng = np.random.default_rng(10)
    Q, _ = np.linalg.qr(rng.normal(size=(4, 4)))
    # a noise correction subtracted too much: one eigenvalue is negative
    corrected = Q @ np.diag([2.0, 1.0, -0.5, 0.3]) @ Q.T
    nearest = Q @ np.diag([2.0, 1.0, 0.0, 0.3]) @ Q.T
    gram = torch.tensor(corrected)[None]  # one coordinate, one sample: no averaging
    raw = BalancedGram(gram, 1, 3, normalize=False)
    np.testing.assert_allclose(raw.gram.numpy(), corrected, atol=1e-15)
    projected = BalancedGram(gram, 1, 3, normalize=False, project_psd=True)
    # measured max deviation 3e-16 (rounding of eigh)
    np.testing.assert_allclose(projected.gram.numpy(), nearest, atol=3e-15)
    # no PSD matrix is closer: random PSD matrices around the result are all farther
    dist = np.linalg.norm(projected.gram.numpy() - corrected)
    assert dist == pytest.approx(0.5, rel=1e-12)
    root = Q @ np.diag(np.sqrt([2.0, 1.0, 0.0, 0.3]))
    for _ in range(200):
        F = root + 0.1 * rng.normal(size=(4, 4))
        assert np.linalg.norm(F @ F.T - corrected) >= dist
    # balanced, over two coordinates: still positive semi-definite after the scaling
    two = torch.tensor(np.stack([corrected, 4.0 * corrected]))
    assert float(torch.linalg.eigvalsh(BalancedGram(two, 10, 3).gram)[0]) < -0.09
    balanced = BalancedGram(two, 10, 3, project_psd=True)
    # zero in exact arithmetic: eigvalsh's rounding is a small multiple of
    # eps * |G| (measured -3e-18, -1.7e-17 and 3e-17 with different BLAS kernels)
    evals = torch.linalg.eigvalsh(balanced.gram)
    assert float(evals[0]) >= -4 * np.finfo(float).eps * float(evals[-1])


@pytest.mark.parametrize("d", [1, 2])
def test_acceleration_datafit_analytic_gradient_equals_autograd(d):
    """Case II's gradient (the adjoint of the per-sample solve) against autograd of
    the loss, for one and two coordinates with symmetric positive term matrices."""
    g = torch.Generator().manual_seed(d)
    s, p = 50, 6
    half = torch.randn(s, p, d, d, dtype=torch.float64, generator=g)
    mass = half @ half.transpose(2, 3) + 0.5 * torch.eye(d, dtype=torch.float64)
    bias = torch.randn(s, p, d, dtype=torch.float64, generator=g)
    qdd = torch.randn(s, d, dtype=torch.float64, generator=g)
    scale = torch.rand(p, dtype=torch.float64, generator=g) + 0.5
    fit = AccelerationDatafit(mass, bias, qdd, scale)
    w = torch.rand(p, dtype=torch.float64, generator=g)
    wr = w.clone().requires_grad_(True)
    (want,) = torch.autograd.grad(fit._loss(wr), wr)
    # the solve is cached per point: another point's loss first, then w (twice)
    fit.value(w + 0.1)
    # measured: equal to 1e-16 relative
    torch.testing.assert_close(fit.gradient(w), want, rtol=1e-12, atol=0.0)
    torch.testing.assert_close(fit.gradient(w), want, rtol=1e-12, atol=0.0)
    # the prediction: minus M(c)^-1 b(c), per sample
    c = w / scale
    mc = torch.einsum("skij,k->sij", mass, c)
    bc = torch.einsum("ski,k->si", bias, c)
    torch.testing.assert_close(fit.predict(w), -torch.linalg.solve(mc, bc))
