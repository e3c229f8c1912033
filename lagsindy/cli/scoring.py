"""The scores ``lagsindy fit`` prints: on the fitted data, and on held-out data.

The held-out score refits the model on the other rows with the fitted model's
choices (formulation, case, fixed term, window), so it is one fit, not a search.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from ._io import _group_rows

WEAK_TARGET = "forces over the test windows (what the weak form fits)"


def held_out_rows(groups, n, share):
    """The held-out rows (a mask) and their description.

    Several trajectories: the last ``share`` of them (at least one, and at least one
    left to fit), in order of first appearance. One trajectory: its final time block
    of ``share`` of the samples.
    """
    rows = _group_rows(groups, n)
    if len(rows) >= 2:
        k = min(max(1, int(round(share * len(rows)))), len(rows) - 1)
        held = np.concatenate(rows[-k:])
        where = f"the last {k} of {len(rows)} trajectories"
    else:
        k = max(1, int(round(share * n)))
        held = np.arange(n - k, n)
        where = f"the final {k} of {n} samples"
    mask = np.zeros(n, dtype=bool)
    mask[held] = True
    return mask, where


def held_out_score(est, X, tau, groups, share):
    """R^2 on held-out rows of a refit of ``est`` on the other rows.

    The refit's warnings are not shown again. Returns the score, what it is of (see
    :func:`score`), a description of the held-out rows and the refit's seconds.
    """
    from ..formulation.probes import without_probes

    mask, where = held_out_rows(groups, len(X), share)
    train, test = np.flatnonzero(~mask), np.flatnonzero(mask)
    sub = refit_like(est)
    start = time.perf_counter()
    with warnings.catch_warnings(), without_probes():
        warnings.simplefilter("ignore")
        sub.fit(
            X.iloc[train],
            None if tau is None else tau[train],
            groups=None if groups is None else np.asarray(groups)[train],
        )
        test_groups = None if groups is None else np.asarray(groups)[test]
        value, target = score(
            sub, X.iloc[test], None if tau is None else tau[test], test_groups
        )
    return value, target, where, time.perf_counter() - start


def score(est, X, tau, groups):
    """R^2 of what the fit minimised, and what it is of.

    With forces and the weak form: of the forces integrated over the test windows
    (pointwise forces would count the noise of estimated accelerations against a
    right model); pointwise when the rows are too short for a window. Else
    ``est.score``.
    """
    if tau is None:
        return est.score(X), "accelerations"
    if est.formulation_ == "weak":
        import torch

        Xt = torch.tensor(np.asarray(X, dtype=float))
        try:
            return est.fitted_.weak_r2(Xt, tau, groups), WEAK_TARGET
        except ValueError:
            pass  # shorter than a window: pointwise
    return est.score(
        X, tau
    ), "forces (pointwise)" if est.formulation_ == "weak" else "forces"


def refit_like(est, **params):
    """An unfitted, quiet copy of ``est`` that repeats its fitted choices
    (formulation, case, fixed term) instead of searching again, with ``params``."""
    from .. import pipeline
    from ..formulation import StrongForm, WeakForm
    from ..joint import refit_config

    form = pipeline.fitted_formulation(est)  # with the window est's fit chose
    if est.formulation_ == "weak":
        form = WeakForm(**form.get_params())  # "auto" chose the weak form
    else:
        form = StrongForm()
    sub = pipeline.copy_with(
        refit_config(est), verbose=0, formulation=form, case=est.case_
    )
    sub.set_params(**params)
    if est.case_ == "fixed":
        sub.set_params(fixed_term=est.fixed_term_ or "mass")
    return sub
