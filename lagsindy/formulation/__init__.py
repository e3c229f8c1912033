"""Formulations of the Euler-Lagrange regression: Gram statistics from the data.

* :mod:`~lagsindy.formulation.operator`: the Euler-Lagrange columns of a library
  (batched kernels and ``torch.func``), their strong-form Gram statistics;
* :mod:`~lagsindy.formulation.weak`: the integral (weak) form over trajectories;
* :mod:`~lagsindy.formulation.scaling`: row and column balancing of the statistics.

:func:`gram_statistics` is the switch between them used by
:class:`~lagsindy.LagrangianSINDy` (``formulation=``).
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from .operator import EulerLagrangeOperator
from .probes import UnmodelledForceWarning
from .scaling import BalancedGram, IdentifiabilityWarning
from .weak import WindowWarning, weak_gram, window_ladder, window_stride

__all__ = [
    "BalancedGram",
    "EulerLagrangeOperator",
    "GramStatistics",
    "IdentifiabilityWarning",
    "UnmodelledForceWarning",
    "WindowWarning",
    "feature_operator",
    "gram_statistics",
    "weak_gram",
    "window_ladder",
    "window_stride",
]


@dataclass
class GramStatistics:
    """Per-coordinate Gram statistics of one fit and how they were made.

    Attributes
    ----------
    gram : Tensor of shape (n_dof, P, P)
        ``A_i^T A_i`` over the candidate columns followed by the target (tau).
    n_rows : int
        Samples (strong form) or windows (weak form) behind ``gram``.
    formulation : {"strong", "weak"}
    dt : float or None
        Sampling interval of the weak form.
    noise_cov : ndarray or None
        Noise covariance subtracted by the weak form (its Gram is then a corrected
        one and is projected onto the positive semi-definite cone when balanced).
    window : int or None
        Samples per test function of the weak form.
    probe_gram : Tensor of shape (n_dof, P + n_probes, P + n_probes) or None
        The Gram statistics with probe forces before the target (see
        :mod:`~lagsindy.formulation.probes`); ``gram`` is this without them.
    probe_names : tuple of str
        The probe forces' names.
    """

    gram: torch.Tensor
    n_rows: int
    formulation: str
    dt: float | None = None
    noise_cov: np.ndarray | None = None
    window: int | None = None
    probe_gram: torch.Tensor | None = None
    probe_names: tuple = ()

    @property
    def corrected(self) -> bool:
        return self.noise_cov is not None


def gram_statistics(
    operator, Xt, tau_t, groups, *, formulation, window, dt=None, noise_cov="auto"
) -> list:
    """Gram statistics in the requested formulation (``"auto"``: weak when it can run).

    ``"auto"`` falls back to the strong form, with a warning that says why, when the
    rows are not time-ordered trajectories at least ``window`` samples long.

    Returns
    -------
    list of callables returning GramStatistics
        One entry, or with the weak form and ``window="auto"`` one per window of
        :func:`~lagsindy.formulation.weak.window_ladder` (smallest first); each sums
        its statistics when called, so windows never tried cost nothing.
    """
    if formulation in ("weak", "auto"):
        try:
            grams, dt_, cov = weak_gram(
                operator, Xt, tau_t, groups, window=window, dt=dt, noise_cov=noise_cov
            )
            return [
                functools.partial(_weak_statistics, build, dt_, cov, w)
                for w, build in grams
            ]
        except ValueError as exc:
            if formulation == "weak":
                raise
            warnings.warn(
                "formulation='auto' fell back to the strong form, which is biased "
                f"when the data are noisy, because the weak form cannot run: {exc}. "
                "Pass time-ordered trajectories (groups=trajectory labels, dt=) to "
                "get the weak form, or formulation='strong' to silence this.",
                UserWarning,
                stacklevel=3,
            )
    stats = GramStatistics(operator.gram(Xt, tau_t), Xt.shape[0], "strong")
    return [lambda: stats]


def _weak_statistics(build, dt, cov, window) -> GramStatistics:
    gram, n_rows = build()
    return GramStatistics(gram, n_rows, "weak", dt, cov, window)


def feature_operator(coordinates, terms, force_terms, indices, device, dtype):
    """Operator of the features at ``indices`` (Lagrangian terms, then force terms)."""
    n_terms = len(terms)
    return EulerLagrangeOperator(
        coordinates,
        [terms[k] for k in indices if k < n_terms],
        forces=[force_terms[k - n_terms].forces for k in indices if k >= n_terms],
        dtype=dtype,
        device=device,
    )
