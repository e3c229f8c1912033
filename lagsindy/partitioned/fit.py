"""A fit from partitioned data: the passes, then the in-memory fit's solve.

:func:`fit_state` builds the :class:`~lagsindy.pipeline.FitSetup` an in-memory fit
of the same parameters builds, sums the statistics over the partitions
(:mod:`.statistics`), and hands them to the same
:func:`~lagsindy.pipeline.solve_ladder`, :func:`~lagsindy.pipeline.fitted_state`
and :func:`~lagsindy.pipeline.check_fit`. The model equals the in-memory fit of the
concatenated partitions (same rows, same trajectory labels) up to rounding, with
one difference by design: the weak form's noise correction is summed over every
sample, where an in-memory fit of more than ``NOISE_ROWS`` (10,000) rows estimates
it from a subsample.
"""

from __future__ import annotations

import numpy as np
import torch

from .. import pipeline
from .._torch import resolve_device, resolve_dtype
from ..cases.acceleration import CASE_II_ROWS
from ..cases.fixed import SCORING_ROWS, SELECTION_ROWS
from ..formulation.forms import AutoForm, GramStatistics, StrongForm, WeakForm
from ..formulation.probes import split_probes
from ..formulation.weak import WINDOW_FIRST
from .sources import as_partitioned
from .statistics import (
    SAMPLE_ROWS,
    GatheredRows,
    combine,
    gather_rows,
    sampling_interval,
    strong_pass,
    weak_decisions,
    weak_pass,
    weak_scan,
)

__all__ = ["fit_state", "partitioned_setup"]


def partitioned_setup(params: dict, data):
    """The fit setup of an estimator's parameters on partitioned data.

    Parameters
    ----------
    params : dict
        ``LagrangianSINDy.get_params(deep=False)``.
    data : PartitionedData

    Returns
    -------
    setup : FitSetup
        As an in-memory fit of the same parameters builds it.
    formulation : StrongForm or WeakForm
    """
    library = params.get("library")
    coordinates = data.layout["coordinates"]
    if library is not None and library.coordinates is not None:
        wanted = library.coordinates
        wanted = [wanted] if isinstance(wanted, str) else list(wanted)
        if data.layout["positional"]:  # q0, q1, ...: the library names them
            if len(wanted) != len(coordinates):
                raise ValueError(
                    f"the library has {len(wanted)} coordinates {wanted}, the data "
                    f"{len(coordinates)}"
                )
            coordinates = wanted
        elif sorted(wanted) != sorted(coordinates):
            raise ValueError(
                f"the library's coordinates {wanted} differ from the data's "
                f"{coordinates}"
            )
        elif wanted != coordinates:  # read the columns in the library's order
            data.coordinates = wanted
            data.layout = data._layout()
            coordinates = wanted
    # n_samples is checked after the first pass (it is not known before)
    library = pipeline.build_library(library, coordinates, 1 << 62)
    case = pipeline.resolve_case(
        params.get("case", "auto"), True if data.has_forces else None
    )
    dissipation = pipeline.build_dissipation(params.get("dissipation"), library)
    setup = pipeline.make_setup(params, library, dissipation, case)
    formulation = pipeline.formulation_of(params, case)
    if not isinstance(formulation, (StrongForm, WeakForm)):
        raise ValueError(
            "partitioned data are fitted in the strong or the weak form "
            f"(formulation='strong', 'weak' or 'auto'), not {formulation!r}"
        )
    return setup, formulation


def _check_rows(setup, n_rows):
    n_dof, n_terms = len(setup.library.coordinates_), len(setup.library.terms_)
    if n_rows * n_dof < n_terms:
        raise ValueError(
            f"too few samples: {n_rows} sample(s) x {n_dof} coordinate(s) give "
            f"{n_rows * n_dof} equations for {n_terms} candidate terms; record more "
            "data or use a smaller library"
        )


def _sample(total, dtype, device):
    """The rows kept for the fit's checks (at most ``SAMPLE_ROWS``, evenly)."""
    X = np.concatenate([x for x, _ in total["sample"]])
    taus = [t for _, t in total["sample"]]
    tau = None if taus[0] is None else np.concatenate(taus)
    take = np.unique(np.linspace(0, len(X) - 1, min(len(X), SAMPLE_ROWS)).round())
    take = take.astype(np.int64)
    Xt = torch.as_tensor(X[take], dtype=dtype, device=device)
    return Xt, None if tau is None else tau[take]


def _weak_ladder(data, setup, formulation, params, dtype, verbose):
    """The weak form's statistics per window (the in-memory decisions), the
    first pass's totals."""
    op, _ = pipeline.fit_operator(setup, "cpu", dtype)
    d, n_terms = op.n_dof, op.n_terms
    window = formulation.window
    first = WINDOW_FIRST if isinstance(window, str) else int(window)
    dt = formulation.dt
    scan = data.map_reduce(weak_scan(d, first, 1 if dt is None else 0), combine)
    _check_rows(setup, sum(n for _, n in scan["sizes"]))
    if dt is None:
        dt = sampling_interval(data, d, scan["medians"])
        if not dt > 0:
            raise ValueError(
                f"could not estimate a positive sampling interval (got {dt:.3g}); "
                "are the rows time-ordered? Pass dt="
            )
    decide = {"window": window, "noise_cov": formulation.noise_cov}
    windows, cov = weak_decisions(scan, decide, d, n_terms, dt)
    if verbose:
        print(f"[lagsindy] partitioned weak form: dt={dt:.6g}, windows {windows}")
    total = data.map_reduce(weak_pass(setup, dtype, windows, dt, cov), combine)

    def stats(w):
        return lambda: GramStatistics(
            total["weak"][w], total["windows"][w], "weak", float(dt), cov, w
        )

    return [stats(w) for w in windows], total


def _needs_rows(setup) -> bool:
    """Whether the solve evaluates rows of the data (case III's search or mass
    normalization, case II)."""
    if setup.case == "acceleration":
        return True
    fixed = setup.fixed_term
    return setup.case == "fixed" and (
        fixed is None or (isinstance(fixed, str) and fixed == "mass")
    )


def _gathered(data, setup, total, dtype, device):
    """The rows the searches evaluate, gathered from the partitions (the rows an
    in-memory fit of all the rows would use)."""
    sizes = total["sizes"]
    n = sum(s for _, s in sizes)
    solver = setup.solver
    sizes_used = [SELECTION_ROWS, SCORING_ROWS]  # case III's search
    if setup.case == "acceleration":  # case II starts from case III's search
        sizes_used.append(CASE_II_ROWS)
    rows = np.unique(
        np.concatenate([solver.subsample_rows(n, size) for size in sizes_used])
    )
    starts = np.cumsum([0] + [s for _, s in sizes])
    wanted = {}
    for (index, size), start in zip(sizes, starts):
        inside = rows[(rows >= start) & (rows < start + size)]
        if inside.size:
            wanted[index] = inside - start
    got = data.map_reduce(gather_rows(wanted), combine)["rows"]
    order = {index: k for k, (index, _) in enumerate(sizes)}
    got.sort(key=lambda item: order[item[0]])
    values = np.concatenate([x for _, x, _ in got])
    return GatheredRows(rows, torch.as_tensor(values, dtype=dtype, device=device), n)


def fit_state(params: dict, X, y=None, groups=None):
    """Fit an estimator's parameters to partitioned data.

    Parameters
    ----------
    params : dict
        ``LagrangianSINDy.get_params(deep=False)``.
    X : PartitionedData or what :func:`~.sources.as_partitioned` takes
    y, groups : str, list or None
        Force columns and the trajectory column (see :func:`as_partitioned`).

    Returns
    -------
    fitted : FittedLagrangian
    feature_names : list of str or None
        The state columns, for ``feature_names_in_``.
    """
    data = as_partitioned(X, groups=groups, y=y)
    device, dtype = resolve_device(params["device"]), resolve_dtype(params["dtype"])
    setup, formulation = partitioned_setup(params, data)
    verbose = params.get("verbose", 0)
    n_targets = int(data.has_forces)
    _, names = pipeline.fit_operator(setup, "cpu", dtype)
    total, ladder = None, None
    if isinstance(formulation, WeakForm):
        try:
            ladder, total = _weak_ladder(
                data, setup, formulation, params, dtype, verbose
            )
        except ValueError as exc:
            if not isinstance(formulation, AutoForm):
                raise
            formulation.warn_fallback(exc)
    if ladder is None:
        total = data.map_reduce(strong_pass(setup, dtype), combine)
        _check_rows(setup, total["n"])
        summed = GramStatistics(total["gram"], int(total["n"]), "strong")
        ladder = [lambda: summed]
    ladder = [_moved(build, device) for build in ladder]
    ladder = split_probes(ladder, setup.n_features, names, n_targets)
    Xs, tau_s = _sample(total, dtype, device)
    Xsolve = _gathered(data, setup, total, dtype, device) if _needs_rows(setup) else Xs
    stats, solution = pipeline.solve_ladder(
        ladder, setup, Xsolve, tau_s, verbose=verbose
    )
    fitted = pipeline.fitted_state(setup, stats, solution, tau_1d=False)
    # (stacklevel: the caller of LagrangianSINDy.fit, one frame further than
    # in memory)
    pipeline.check_fit(fitted, setup, stats, solution, Xs, tau_s)
    return fitted, data.feature_names


def _moved(build, device):
    def run():
        stats = build()
        if stats.gram.device != device:
            stats.gram = stats.gram.to(device)
        return stats

    return run
