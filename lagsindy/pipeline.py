"""The one fit pipeline: Gram statistics in, a fitted Lagrangian out.

Every consumer (the estimator's ``fit``, the bootstrap, the diagnosis, the delay
search) runs the same two steps:

1. a formulation (:mod:`lagsindy.formulation.forms`) turns the data into Gram
   statistics, of all rows or per trajectory (folds and resamples are sums);
2. :func:`solve` turns statistics into a :class:`~lagsindy.cases.Solution` (scaled by
   :class:`~lagsindy.formulation.scaling.BalancedGram`, solved by the case of
   :mod:`lagsindy.cases` with the staged sparse solve), and :func:`fitted_state` into a
   :class:`~lagsindy.model.FittedLagrangian`.

What a solve needs besides the statistics is one :class:`FitSetup` (the built
library and dissipation candidates, the case, the solver settings, which terms are
unpenalized, how passive data fix the scale). The functions here are pure: they read
their arguments and return results; :func:`check_fit` is the one that warns.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
from sklearn.base import clone

from . import _validation as val
from ._stacklevel import outside_stacklevel
from ._torch import to_numpy, to_tensor
from .cases import Problem, SparseSolve, solve_case
from .cases.forces import (
    better_support,
    fits_better,
    hold_known,
    known_columns,
    misses_an_equation,
)
from .dissipation import DissipationLibrary, reduce_forces
from .evaluator import library_terms
from .formulation import feature_operator
from .formulation.clocked import frame_on_clock
from .formulation.forms import StrongForm, WeakForm, with_window
from .formulation.probes import (
    PROBE_KINDS,
    PROBED_CASES,
    probe_forces,
    probe_term,
    probing,
    split_probes,
    warn_unmodelled,
)
from .formulation.scaling import BalancedGram, warn_if_not_identifiable
from .formulation.weak import choose_window
from .model import POOR_ACCELERATIONS, FittedLagrangian, feature_index
from .settings import (
    as_objects,
    build_library,
    formulation_settings,
    resolve_case,
    solver_settings,
)
from .solvers import warn_not_converged

__all__ = [
    "Dissipation",
    "FitSetup",
    "build_dissipation",
    "build_library",
    "check_fit",
    "constrained",
    "copy_with",
    "fit_data",
    "fit_operator",
    "fit_statistics",
    "fitted_formulation",
    "fitted_state",
    "formulation_of",
    "on_fit_clock",
    "probes_of",
    "problem",
    "resolve_case",
    "solve",
    "solve_ladder",
]


@dataclass
class Dissipation:
    """The dissipation candidates of a fit.

    ``terms``: the :class:`~lagsindy.dissipation.ForceTerm` candidates a Lagrangian
    column does not cover; ``removed``: ``(name, reason)`` of those it does;
    ``library``: the built :class:`~lagsindy.dissipation.DissipationLibrary` (or
    ``None`` without one).
    """

    terms: list = field(default_factory=list)
    removed: list = field(default_factory=list)
    library: object = None


@dataclass
class FitSetup:
    """What a solve needs besides the statistics.

    Attributes
    ----------
    library : CandidateLibrary
        The built library; its terms are the first features.
    dissipation : Dissipation
    case : {"forces", "fixed", "acceleration"}
    solver : SparseSolve
        The staged sparse solve with its settings.
    unpenalized : list
        Names of the features that are neither shrunk nor thresholded.
    fixed_term : str, sympy.Expr, "mass" or None
        How passive data fix the scale (case III).
    normalize : bool
        Balance the rows and columns of the statistics.
    """

    library: object
    dissipation: Dissipation
    case: str
    solver: SparseSolve
    unpenalized: list = field(default_factory=list)
    fixed_term: object = None
    normalize: bool = True

    @property
    def n_terms(self) -> int:
        return len(self.library.terms_)

    @property
    def n_features(self) -> int:
        return self.n_terms + len(self.dissipation.terms)

    @property
    def names(self) -> np.ndarray:
        names = list(self.library.get_feature_names_out())
        return np.asarray(names + [t.name for t in self.dissipation.terms], object)

    def penalty(self) -> np.ndarray:
        """L1 weight per feature: 0 for the unpenalized ones."""
        weights = np.ones(self.n_features)
        d = self.dissipation
        for term in self.unpenalized:
            weights[feature_index(self.library, d.terms, d.removed, term)] = 0.0
        return weights

    def operator(self, indices, device, dtype, extra_forces=()):
        """Euler-Lagrange operator of the features at ``indices`` (then
        ``extra_forces``, force terms that are not features)."""
        forces = list(self.dissipation.terms) + list(extra_forces)
        return feature_operator(
            self.library.coordinates_,
            library_terms(self.library),
            forces,
            indices,
            device,
            dtype,
        )


# ----------------------------------------------------------------------- building
# Built dissipation candidates by library parameters (``diagnose`` refits the same
# dissipation library several times; building simplifies every term with sympy).
_BUILT_DISSIPATION: dict = {}
_BUILT_DISSIPATION_SIZE = 16


def _build_cached(dlib):
    """``dlib.build()``, reusing the terms built earlier from equal parameters.

    The terms (frozen :class:`~lagsindy.dissipation.ForceTerm`) are shared, the
    lists are not; only the library class itself is cached (a subclass may build
    differently).
    """
    if type(dlib) is not DissipationLibrary:
        return dlib.build()
    key = repr(sorted(dlib.get_params(deep=False).items()))
    if key not in _BUILT_DISSIPATION:
        dlib.build()
        if len(_BUILT_DISSIPATION) >= _BUILT_DISSIPATION_SIZE:
            _BUILT_DISSIPATION.pop(next(iter(_BUILT_DISSIPATION)))
        _BUILT_DISSIPATION[key] = (list(dlib.coordinates_), list(dlib.terms_))
        return dlib
    names, terms = _BUILT_DISSIPATION[key]
    dlib.coordinates_, dlib.terms_ = list(names), list(terms)
    return dlib


def build_dissipation(dissipation, library) -> Dissipation:
    """The candidates of ``dissipation`` (a DissipationLibrary, unbuilt) that a
    column of the built ``library`` does not cover."""
    if dissipation is None:
        return Dissipation()
    coordinates = list(library.coordinates_)
    dlib = clone(dissipation)
    if dlib.coordinates is None:
        dlib.set_params(coordinates=coordinates)
    _build_cached(dlib)
    if list(dlib.coordinates_) != coordinates:
        raise ValueError(
            f"the dissipation library's coordinates {list(dlib.coordinates_)} differ "
            f"from the Lagrangian library's {coordinates}"
        )
    terms, removed = reduce_forces(library_terms(library), dlib.terms_, coordinates)
    return Dissipation(terms, removed, dlib)


# --------------------------------------------------------------------- statistics
def fit_statistics(formulation, setup: FitSetup, Xt, tau_t, groups) -> list:
    """The statistics a fit solves on (a list of functions, see
    :mod:`lagsindy.formulation.forms`): every feature's columns and the target; in
    the probed cases without a dissipation library, with probe forces set aside (see
    :mod:`lagsindy.formulation.probes`)."""
    operator, names = fit_operator(setup, Xt.device, Xt.dtype)
    ladder = formulation.statistics(operator, Xt, tau_t, groups)
    return split_probes(ladder, setup.n_features, names, int(tau_t is not None))


def fit_operator(setup: FitSetup, device, dtype):
    """The Euler-Lagrange operator a fit's statistics use, and the names of the
    probe forces it adds after the features (in the probed cases without a
    dissipation library): ``(operator, names)``. The statistics of its columns go
    through :func:`~lagsindy.formulation.probes.split_probes` (``n_features`` and
    ``names``) before a solve, as :func:`fit_statistics` does."""
    probes = []
    if setup.case in PROBED_CASES and setup.dissipation.library is None and probing():
        probes = build_dissipation(DissipationLibrary(PROBE_KINDS), setup.library).terms
    operator = setup.operator(
        range(setup.n_features + len(probes)), device, dtype, extra_forces=probes
    )
    return operator, [t.name for t in probes]


# -------------------------------------------------------------------------- solve
def problem(
    stats, setup: FitSetup, Xt=None, tau=None, *, memo=None, start=None
) -> Problem:
    """Balance the statistics and collect what the case needs.

    ``Xt`` (the data) is needed by case III's search and case II; ``tau`` only to
    say what is wrong when the target is zero.
    """
    n_features = setup.n_features
    if not bool(torch.isfinite(stats.gram).all()):
        val.raise_not_finite(stats.gram, setup.library.terms_, Xt, tau)
    known = known_columns(setup.library)  # held terms: moved to the target
    if known:
        held = hold_known(stats.gram, known, setup.case)
        stats = dataclasses.replace(stats, gram=held)
    balanced = BalancedGram(
        stats.gram,
        stats.n_rows,
        n_features,
        normalize=setup.normalize,
        project_psd=stats.corrected,
    )
    identifiable = balanced.identifiable().cpu().numpy()
    identifiable[list(known)] = False
    if not identifiable.any():
        raise ValueError(
            "no candidate term varies on the data (every Euler-Lagrange column is "
            "zero): the velocities and accelerations may all be zero; record motion"
        )
    if setup.case == "forces" and balanced.target_scale(n_features) <= 0:
        raise ValueError(
            "tau is identically zero: for passive data call fit(X) without tau "
            "(case III or case='acceleration')"
            if tau is None or not np.any(tau)
            else "tau is too small to use (largest |tau| = "
            f"{np.abs(tau).max():.3g}, its squares underflow): change its units"
        )
    out = Problem(
        balanced=balanced,
        identifiable=identifiable,
        penalty=setup.penalty(),
        Xt=Xt,
        library=setup.library,
        dissipation_terms=setup.dissipation.terms,
        names=setup.names,
        solver=setup.solver,
        fixed_term=setup.fixed_term,
        start=start,
    )
    if memo is not None:
        out.memo = memo
    return out


def solve(
    stats,
    setup: FitSetup,
    Xt=None,
    tau=None,
    *,
    memo=None,
    start=None,
    warn=True,
    support=None,
):
    """Solve the case on ``stats``: the :class:`~lagsindy.cases.Solution`.

    ``memo``: what problems on the same data share (see
    :class:`~lagsindy.cases.Problem`); ``start``: a warm start in coefficient units;
    ``warn``: warn when the data leave combinations of terms undetermined;
    ``support``: a mask of the features the solve may use (the others left out).
    """
    p = problem(stats, setup, Xt, tau, memo=memo, start=start)
    if support is not None:
        p.identifiable = p.identifiable & np.asarray(support, dtype=bool)
    solution = constrained(setup, p, solve_case(setup.case, p))
    for k, v in known_columns(setup.library).items():
        solution.coef[k] = v
    solution.row_scale = p.balanced.row_scale
    if warn and setup.case != "acceleration":
        free = np.flatnonzero(p.identifiable)
        allowed = 1 if setup.case == "fixed" else 0
        warn_if_not_identifiable(p.balanced, free, p.names, allowed=allowed)
    return solution


def constrained(setup: FitSetup, p: Problem, solution):
    """A case I ``solution`` under the library's ``constrain`` hook (robots)."""
    hook = getattr(setup.library, "constrain", None)
    return hook(p, solution) if callable(hook) and setup.case == "forces" else solution


def solve_ladder(ladder, setup: FitSetup, Xt, tau=None, *, verbose=0):
    """Statistics and solution, the weak form's window chosen by
    :func:`~lagsindy.formulation.weak.choose_window` among the ``ladder``'s."""
    search = setup.case == "fixed" and setup.fixed_term is None
    memo = {}  # what the windows' problems share (data and library only)

    def run(stats, like=None):
        use = setup
        if like is not None and search:  # confirm with the scale already chosen
            scale = (
                "mass"
                if like.normalization == "mass"
                else setup.library.terms_[like.fixed]
            )
            use = dataclasses.replace(setup, fixed_term=scale)
        return solve(stats, use, Xt, tau, memo=memo)

    def prefer(stats, solution, others):  # case I: a light link's equation
        return better_support(
            stats.gram,
            solution,
            others,
            lambda mask: solve(stats, setup, Xt, tau, memo=memo, support=mask),
        )

    forces = setup.case == "forces"
    return choose_window(
        ladder, run, search=search, verbose=verbose, prefer=prefer if forces else None
    )


def fitted_state(setup: FitSetup, stats, solution, *, tau_1d=False):
    """The :class:`~lagsindy.model.FittedLagrangian` of a solution (no checks)."""
    n_terms, coef, result = setup.n_terms, solution.coef, solution.result
    if not np.all(np.isfinite(coef)):
        raise FloatingPointError(
            "the fit produced non-finite coefficients; check the data scale"
        )
    fixed = solution.fixed
    d = setup.dissipation
    return FittedLagrangian(
        library=setup.library,
        coef=coef[:n_terms],
        case=setup.case,
        dissipation_terms=d.terms,
        dissipation_coef=coef[n_terms:],
        dissipation_removed=d.removed,
        dissipation_library=d.library,
        fixed_term=None if fixed is None else str(setup.library.terms_[fixed]),
        normalization=solution.normalization if setup.case == "fixed" else None,
        formulation=stats.formulation,
        dt=stats.dt,
        noise_cov=stats.noise_cov,
        window=stats.window,
        stages=result.stages,
        n_iter=result.n_iter,
        residual=result.cost,
        tau_1d=tau_1d,
    )


def fit_data(setup: FitSetup, formulation, Xt, tau, groups, *, tau_1d=False, verbose=0):
    """An in-memory fit, from the data to a checked fitted state.

    The statistics of ``formulation`` (the weak form's window chosen on its
    ladder), the solve, the fitted state, a solve again with each equation judged
    on its own when a coordinate is predicted poorly
    (:func:`judge_each_equation`), and the fit's checks (:func:`check_fit`).

    Parameters
    ----------
    setup : FitSetup
    formulation : StrongForm, WeakForm or AutoForm
    Xt : Tensor of shape (n_samples, 3 * n_dof)
    tau : ndarray of shape (n_samples, n_dof) or None
    groups : array-like or None
    tau_1d : bool, default=False
        Whether the user gave tau as a 1-D array (predictions are then 1-D).
    verbose : int, default=0

    Returns
    -------
    fitted : FittedLagrangian
    stats : GramStatistics
        The statistics solved (of the chosen window).
    solution : Solution
    """
    tau_t = None if tau is None else to_tensor(tau, dtype=Xt.dtype, device=Xt.device)
    ladder = fit_statistics(formulation, setup, Xt, tau_t, groups)
    stats, solution = solve_ladder(ladder, setup, Xt, tau, verbose=verbose)
    fitted = fitted_state(setup, stats, solution, tau_1d=tau_1d)
    solution, fitted = judge_each_equation(
        setup, stats, solution, fitted, Xt, tau, tau_1d=tau_1d
    )
    check_fit(fitted, setup, stats, solution, Xt, tau)
    return fitted, stats, solution


def judge_each_equation(
    setup: FitSetup, stats, solution, fitted, Xt, tau, *, tau_1d=False
):
    """Case I with several coordinates: the solution again with every term judged
    within each coordinate's equation, when a coordinate's accelerations are
    predicted poorly.

    The default threshold keeps a term that is small next to the largest only when
    it carries a large share (``equation_threshold``) of some coordinate's
    equation. A strongly driven light link's gravity and coupling can be a few
    percent of its own equation and far less of the heavy one's: they are dropped,
    and the model predicts that link's accelerations poorly (R^2 below
    ``POOR_ACCELERATIONS`` from the measured forces). Then the solve is repeated
    with ``equation_threshold = threshold`` (each term judged in its own equation
    with the threshold itself) and kept, with a warning that says so, when every
    coordinate then scores at least ``POOR_ACCELERATIONS``. Returns ``(solution,
    fitted)``: the ones given, or those of the repeated solve (its rule recorded).
    """
    settings = setup.solver.settings
    per_equation = settings.threshold
    if (
        setup.case != "forces"
        or tau is None
        or len(setup.library.coordinates) < 2
        or settings.equation_threshold is None
        or settings.equation_threshold <= per_equation
        or not np.any(solution.coef[: setup.n_terms])
    ):
        return solution, fitted
    scores = fitted.coordinate_acceleration_r2(Xt, tau)
    poor = {k: r2 for k, r2 in scores.items() if r2 < POOR_ACCELERATIONS}
    if not poor and not misses_an_equation(stats.gram, solution.coef):
        return solution, fitted
    solver = dataclasses.replace(
        setup.solver,
        settings=clone(settings).set_params(equation_threshold=per_equation),
    )
    use = dataclasses.replace(setup, solver=solver)
    with warnings.catch_warnings(record=True) as held:  # said only if kept
        warnings.simplefilter("always")
        again = solve(stats, use, Xt, tau)
    if not np.all(np.isfinite(again.coef)):
        return solution, fitted
    more = np.count_nonzero(again.coef) > np.count_nonzero(solution.coef)
    gains = [] if poor else fits_better(stats.gram, solution, again, more_terms=more)
    if not (poor or gains):
        return solution, fitted
    refitted = fitted_state(use, stats, again, tau_1d=tau_1d)
    refitted.equation_threshold = per_equation  # refits use the same rule
    new_scores = refitted.coordinate_acceleration_r2(Xt, tau)
    if not new_scores or min(new_scores.values()) < POOR_ACCELERATIONS:
        return solution, fitted
    for w in held:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    names = fitted.coordinates
    which = ", ".join(f"{k} (R^2 {r2:.2f})" for k, r2 in poor.items())
    now = ", ".join(f"{k} {new_scores[k]:.2f}" for k in poor)
    said = f"predicted the accelerations of {which} poorly"
    if gains:
        said = "missed " + ", ".join(
            f"{names[i]}'s equation by {a:.1e} of its energy" for i, a, _ in gains
        )
        now = ", ".join(f"{names[i]} {b:.1e}" for i, _, b in gains)
    warnings.warn(
        f"the model at the default threshold {said}: terms that the equation of a "
        f"light or strongly driven coordinate needs were small next to the other "
        f"coordinates' terms. Refitted with every term judged within each "
        f"coordinate's equation (equation_threshold={per_equation:g}); now {now}.",
        UserWarning,
        stacklevel=outside_stacklevel(),
    )
    return again, refitted


def check_fit(fitted, setup: FitSetup, stats, solution, Xt, tau):
    """The fit's checks, each a warning that says what is likely wrong (pointing at
    the user's line): FISTA not converged, an empty model, the learned mass matrix
    (stored as ``fitted.mass_check``), angles in polynomials beyond two turns,
    missing friction or damping (probe forces), residual and acceleration checks."""
    stacklevel = outside_stacklevel()
    n_terms, coef = setup.n_terms, solution.coef
    warn_not_converged(solution.result.stages, setup.solver.max_iter)
    if not np.any(coef[:n_terms]):
        warnings.warn(
            "every Lagrangian term was thresholded away: the learned Lagrangian is "
            "zero. Lower lam or threshold.",
            UserWarning,
            stacklevel=stacklevel,
        )
    fitted.mass_check = fitted.checked_mass(Xt, stacklevel=stacklevel)
    norms = stats.gram.diagonal(dim1=1, dim2=2).sum(0).clamp(min=0).sqrt()
    fitted.warn_angle_polynomials(Xt, to_numpy(norms)[:n_terms], stacklevel=stacklevel)
    probed, sign = probes_of(fitted, setup, stats, solution)
    if warn_unmodelled(probed, sign, stacklevel=stacklevel):
        fitted.unmodelled = {"share": float(probed.share), "named": dict(probed.named)}
    else:
        fitted.warn_unexplained(stacklevel=stacklevel, Xt=Xt)
        fitted.warn_poor_accelerations(
            Xt, solution.score, stacklevel=stacklevel, tau=tau
        )
    return fitted


def probes_of(fitted, setup: FitSetup, stats, solution):
    """``(ProbeResult or None, kinetic_sign)``: what the probe forces explain of the
    fit's residual (see :func:`~lagsindy.formulation.probes.probe_forces`), and the
    sign of the learned kinetic energy (-1 when ``fitted.mass_check`` finds the mass
    matrix mostly negative)."""
    coef = solution.coef
    probed = probe_forces(
        stats,
        coef,
        setup.normalize,
        probe_term(setup.case, coef[: setup.n_terms], solution.fixed),
        solution.row_scale,
    )
    check = fitted.mass_check
    sign = -1.0 if check is not None and check.negative > 0.5 else 1.0
    return probed, sign


# ------------------------------------------------------------------------- setups
def _term_index(library, param, term) -> int:
    """Index of a term named by a parameter, with the parameter in the message."""
    try:
        return library.index(term)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{param}={term!r}: {exc}") from None


def check_known_terms(setup: FitSetup):
    """Resolve ``fixed_term`` and ``unpenalized`` before any heavy computation."""
    case, fixed = setup.case, setup.fixed_term
    if fixed is not None:
        if case != "fixed":
            why = (
                "with tau the forces set the scale"
                if case == "forces"
                else "case II fixes the scale by a unit norm instead"
            )
            raise ValueError(
                f"fixed_term={fixed!r} is only used in case III (passive "
                f"data, fit(X) without tau), but this fit is case={case!r} and "
                f"{why}: drop fixed_term (unpenalized=[...] keeps a known term "
                "without fixing its value)."
            )
        if not (isinstance(fixed, str) and fixed == "mass"):
            _term_index(setup.library, "fixed_term", fixed)
    d = setup.dissipation
    for term in setup.unpenalized:
        try:
            feature_index(setup.library, d.terms, d.removed, term)
        except (ValueError, TypeError) as exc:
            raise ValueError(f"unpenalized={term!r}: {exc}") from None


def make_setup(params: dict, library, dissipation: Dissipation, case: str) -> FitSetup:
    """The :class:`FitSetup` of an estimator's parameters (``get_params()``; the
    solver settings: :func:`~lagsindy.settings.solver_settings`), its built library
    and dissipation, and the case."""
    n_terms = len(library.terms_)
    dissipative = [False] * n_terms + [t.dissipative for t in dissipation.terms]
    solver = SparseSolve.from_settings(
        solver_settings(params),
        lam=params.get("lam", 1e-3),
        alpha=params.get("alpha"),
        n_terms=n_terms,
        dissipative=dissipative,
        random_state=params.get("random_state"),
        verbose=params.get("verbose", 0),
    )
    setup = FitSetup(
        library=library,
        dissipation=dissipation,
        case=case,
        solver=solver,
        unpenalized=_as_list(params.get("unpenalized"))
        + list(getattr(library, "unpenalized_", ())),
        fixed_term=params.get("fixed_term"),
        normalize=params.get("normalize", True),
    )
    check_known_terms(setup)
    return setup


def formulation_of(params: dict, case: str = "forces"):
    """The formulation object of an estimator's parameters (``get_params()``; see
    :func:`~lagsindy.settings.formulation_settings`); case II always the strong
    form."""
    formulation = formulation_settings(params)
    if case == "acceleration":
        if type(formulation) is WeakForm:
            raise ValueError(
                "formulation='weak' is for cases I and III; case='acceleration' "
                "needs the strong form"
            )
        return StrongForm()
    return formulation


def copy_with(est, **params):
    """An unfitted copy of ``est`` with its settings as objects (its deprecated flat
    parameters folded into ``solver`` and ``formulation``, so refits do not warn
    again and accept a formulation object), then ``params`` set."""
    copy = clone(est).set_params(**as_objects(est.get_params(deep=False)))
    return copy.set_params(**params) if params else copy


def fitted_formulation(est):
    """The formulation a fitted estimator's fit used, with the test-function window
    its fit chose (``window="auto"`` chose ``est.window_``): what refits of the same
    configuration on other rows (folds, shifted inputs, resamples) should use. An
    unfitted ``est``: the formulation of its parameters."""
    form = formulation_of(est.get_params(deep=False), getattr(est, "case_", "forces"))
    window = getattr(est, "window_", None)
    return form if window is None else with_window(form, window)


def _as_list(terms) -> list:
    """``unpenalized`` as a list (it may be an array of terms, or None)."""
    return [] if terms is None else list(terms)


def setup_of(est, **changes) -> FitSetup:
    """The :class:`FitSetup` of a fitted estimator (its built library, dissipation
    terms, case and settings; in case III the scale its fit chose), as its fit
    used it; ``changes`` replace fields (e.g. ``fixed_term=None``)."""
    fitted = est.fitted_
    dissipation = Dissipation(
        list(fitted.dissipation_terms),
        list(fitted.dissipation_removed),
        fitted.dissipation_library,
    )
    params = est.get_params(deep=False)
    setup = make_setup(params, fitted.library, dissipation, fitted.case)
    if fitted.case == "fixed":
        scale = "mass" if fitted.normalization == "mass" else fitted.fixed_term
        setup = dataclasses.replace(setup, fixed_term=scale)
    setup.solver = dataclasses.replace(setup.solver, verbose=0)
    return dataclasses.replace(setup, **changes) if changes else setup


def on_fit_clock(est, X, tau=None, groups=None, t=None, *, what="", even=False):
    """``(est, X, tau, groups)`` as a fit given the time stamps ``t`` used them
    (:func:`~lagsindy.formulation.clocked.frame_on_clock`; ``est`` copied with the
    clock's ``dt``), for refits of the rows (``what``: who refits; ``even``: rows on
    an even clock whatever the formulation, for a trajectory criterion).
    ``t=None``: as given; a fitted ``est`` whose fit had time stamps is refused."""
    if t is None:
        if getattr(est, "clock_", None) is not None:
            raise ValueError(
                f"est was fitted with time stamps, fit(X, tau, t=...) ("
                f"{est.clock_['report'] or 'an even clock'}), and {what} would take "
                "the rows as evenly spaced, edge rows included: pass the same t= to "
                f"{what}(est, X, tau, ..., t=...)"
            )
        return est, X, tau, groups
    fitted = getattr(est, "fitted_", None)
    case = resolve_case(est.case, tau) if fitted is None else fitted.case
    form = formulation_of(est.get_params(deep=False), case)
    X, tau, groups, form = frame_on_clock(form, X, tau, groups, t, even=even)
    if fitted is None:
        return copy_with(est, formulation=form), X, tau, groups
    params = {**copy_with(est).get_params(deep=False), "formulation": form}
    params["feature_names_in"] = getattr(est, "feature_names_in_", None)
    est = type(est).from_fitted(dataclasses.replace(fitted, clock=None), **params)
    return est, X, tau, groups
