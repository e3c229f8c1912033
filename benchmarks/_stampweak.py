"""A prototype weak form on the actual time stamps, for ``benchmarks.clocks``.

Not part of the package: it measures whether integrating on the real sample times
(test functions in seconds, quadrature weights of
:func:`lagsindy.differentiation.time_test_functions`) beats putting the rows on an
even clock. Windows of 0.8 s (81 samples at 100 Hz) every 0.2 s, inside each
gap-free segment; no noise correction (the rows are P-spline estimates, whose white
noise is negligible) and no window search.
"""

from __future__ import annotations

import numpy as np
import torch
from sklearn.base import BaseEstimator

from lagsindy.differentiation import time_test_functions
from lagsindy.formulation.forms import GramStatistics, group_rows
from lagsindy.formulation.weak_integrals import _weak_integrands


class StampWeakForm(BaseEstimator):
    """The weak form with test functions defined in time over the rows' stamps."""

    name = "weak"

    def __init__(self, t=None, window=0.8, stride=0.2):
        self.t = t
        self.window = window
        self.stride = stride

    def statistics(self, operator, X, tau=None, groups=None, *, extra=None) -> list:
        t = np.asarray(self.t, dtype=float)
        ev = operator.evaluator
        d = ev.n_dof
        labels = np.zeros(X.shape[0]) if groups is None else np.asarray(groups)
        order = torch.arange(X.shape[0], device=X.device)
        a_int, b_int = _weak_integrands(
            ev, X[:, :d], X[:, d : 2 * d], order, tau, extra
        )
        a_np, b_np = a_int.cpu().numpy(), b_int.cpu().numpy()
        width = a_np.shape[2]
        gram = np.zeros((d, width, width))
        n_windows = 0
        for rows in group_rows(labels):
            if t[rows[-1]] - t[rows[0]] < self.window:
                continue  # shorter than a window: left out, as the weak form does
            w = time_test_functions(t[rows], window=self.window, stride=self.stride)
            cols = w.columns(a_np[rows], b_np[rows])  # (windows, d, width)
            gram += np.einsum("wdp,wdq->dpq", cols, cols)
            n_windows += w.n_windows
        if n_windows == 0:
            raise ValueError("no segment is as long as a window")
        steps = np.diff(t)
        dt = float(np.median(steps[steps > 0]))
        stats = GramStatistics(
            torch.as_tensor(gram, dtype=X.dtype, device=X.device),
            n_windows,
            "weak",
            dt,
            None,
            int(round(self.window / dt)) + 1,
        )
        return [lambda: stats]


def fit_uneven(X, tau, t, groups, library=None):
    """The benchmark hook: a fit on the cleaned rows with the stamp weak form."""
    from lagsindy import LagrangianSINDy

    form = StampWeakForm(t=t)
    return LagrangianSINDy(library, formulation=form).fit(X, tau, groups=groups)


def stamp_report(cmd) -> int:
    """``python -m benchmarks.clocks --stamp``: the acceptance case (20 % jitter,
    5 % dropped frames, two gaps) with this prototype beside the default route."""
    import time

    from ._common import header, write
    from .clocks import _camera_table, camera_study

    t0 = time.perf_counter()
    sizes = (10, 8.0)
    rows = camera_study(sizes, fit_uneven, (0.2,), (0.05,))
    body = _camera_table(rows, sizes)
    body += f"\nTotal time: {time.perf_counter() - t0:.0f} s.\n"
    write("clocks_stamp.md", header("Real clocks: time-stamp weak form", cmd) + body)
    return 0
