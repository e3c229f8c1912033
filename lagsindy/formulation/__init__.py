"""Formulations of the Euler-Lagrange regression: Gram statistics from the data.

* :mod:`~lagsindy.formulation.forms`: the formulations as objects
  (:class:`StrongForm`, :class:`WeakForm`, :class:`AutoForm`), each turning data into
  Gram statistics of all rows or per trajectory;
* :mod:`~lagsindy.formulation.operator`: the Euler-Lagrange columns of a library
  (batched kernels and ``torch.func``), their strong-form Gram statistics;
* :mod:`~lagsindy.formulation.weak`: the integral (weak) form over trajectories;
* :mod:`~lagsindy.formulation.scaling`: row and column balancing of the statistics;
* :mod:`~lagsindy.formulation.probes`: probe forces (what the fit may miss);
* :mod:`~lagsindy.formulation.clocked`: rows given time stamps put on an even clock.
"""

from __future__ import annotations

from ..evaluator import is_term_function, subset_terms
from .forms import (
    AutoForm,
    GramStatistics,
    StrongForm,
    TrajectoryStatistics,
    WeakForm,
    make_formulation,
)
from .operator import EulerLagrangeOperator
from .probes import UnmodelledForceWarning
from .scaling import BalancedGram, IdentifiabilityWarning
from .weak import WindowWarning, weak_gram, window_ladder, window_stride

__all__ = [
    "AutoForm",
    "BalancedGram",
    "EulerLagrangeOperator",
    "GramStatistics",
    "IdentifiabilityWarning",
    "StrongForm",
    "TrajectoryStatistics",
    "UnmodelledForceWarning",
    "WeakForm",
    "WindowWarning",
    "feature_operator",
    "gram_statistics",
    "make_formulation",
    "weak_gram",
    "window_ladder",
    "window_stride",
]


def gram_statistics(
    operator, Xt, tau_t, groups, *, formulation, window, dt=None, noise_cov="auto"
) -> list:
    """Gram statistics in the requested formulation (``"auto"``: weak when it can run).

    The 0.2 entry point; it is :func:`~lagsindy.formulation.forms.make_formulation`'s
    object's ``statistics``: a list of functions returning :class:`GramStatistics`
    (one per window the weak form tries with ``window="auto"``).
    """
    form = make_formulation(formulation, window=window, dt=dt, noise_cov=noise_cov)
    return form.statistics(operator, Xt, tau_t, groups)


def feature_operator(coordinates, terms, force_terms, indices, device, dtype):
    """Operator of the features at ``indices`` (Lagrangian terms, then force terms)."""
    n_terms = len(terms.names) if is_term_function(terms) else len(terms)
    return EulerLagrangeOperator(
        coordinates,
        subset_terms(terms, [k for k in indices if k < n_terms]),
        forces=[force_terms[k - n_terms].forces for k in indices if k >= n_terms],
        dtype=dtype,
        device=device,
    )
