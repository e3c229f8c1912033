"""The batched term kernels' output buffers against sympy columns.

(The strong Gram in reused chunk buffers is tested in ``test_strong.py``; the weak
form's integrands and banded window sums in ``test_weak.py``.)
"""

import numpy as np
import torch
from _sympy_reference import random_states, sympy_columns

from lagsindy import CandidateLibrary
from lagsindy._batched import compile_terms


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
