"""Fits on a CUDA device agree with the same fits on the CPU (``-m gpu``).

Deselected by default (``pytest -m gpu`` runs them); each skips without CUDA. The
CPU fit is the reference: the support must be the same and the coefficients equal
to float64 round-off of the reductions, whose order differs between the devices.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"),
]
DEVICE = "cuda"


def _pair(make, X, tau, t=None):
    cpu = make("cpu").fit(X, tau, t=t)
    gpu = make(DEVICE).fit(X, tau, t=t)
    return cpu, gpu


def test_weak_form_fit_on_cuda_matches_cpu():
    from lagsindy.systems import cart_pendulum, make_dataset

    system = cart_pendulum()
    data = make_dataset(system, n_trajectories=4, excitation="sincos", random_state=0)
    lib = system.paper_library()
    cpu, gpu = _pair(
        lambda device: LagrangianSINDy(lib, formulation="weak", device=device),
        data.X,
        data.tau,
    )
    np.testing.assert_array_equal(gpu.support_, cpu.support_)
    np.testing.assert_allclose(gpu.coef_, cpu.coef_, rtol=1e-8, atol=1e-10)


def _robot_record():
    from lagsindy.robots import example_urdf

    lib = CandidateLibrary.from_urdf(example_urdf("planar2"))
    t = np.arange(0.0, 4.0, 0.002)
    w = np.array([[0.7, 1.9], [1.3, 3.1]])
    q = 0.4 * np.sin(np.outer(t, w[0])) + 0.2 * np.cos(np.outer(t, w[1]))
    qd = 0.4 * w[0] * np.cos(np.outer(t, w[0])) - 0.2 * w[1] * np.sin(
        np.outer(t, w[1])
    )
    qdd = -0.4 * w[0] ** 2 * np.sin(np.outer(t, w[0])) - 0.2 * w[1] ** 2 * np.cos(
        np.outer(t, w[1])
    )
    truth = lib.nominal_.copy()
    truth[-2:] = [0.02, 0.01]
    tau = lib.euler_lagrange_columns(q, qd, qdd) @ truth + [0.6, 0.3] * qd
    return lib, t, np.hstack([q, qd, qdd]), tau


@pytest.mark.parametrize("formulation", ["strong", "weak"])
def test_robot_fit_on_cuda_matches_cpu(formulation):
    lib, t, X, tau = _robot_record()
    cpu, gpu = _pair(
        lambda device: LagrangianSINDy(
            lib,
            dissipation=DissipationLibrary(["viscous"]),
            formulation=formulation,
            device=device,
        ),
        X,
        tau,
        t if formulation == "weak" else None,
    )
    np.testing.assert_array_equal(gpu.support_, cpu.support_)
    np.testing.assert_allclose(gpu.coef_, cpu.coef_, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(
        gpu.dissipation_coef_, cpu.dissipation_coef_, rtol=1e-7, atol=1e-9
    )
    a, b = cpu.predict(X[:50]), gpu.predict(X[:50])
    np.testing.assert_allclose(b, a, rtol=1e-8, atol=1e-10 * np.abs(a).max())
