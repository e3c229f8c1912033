"""The staged sparse solve with an estimator's settings, shared by the cases.

:class:`SparseSolve` holds what the cases need to run the staged schedule: the
estimator's ``lam`` and ``alpha``, the schedule's settings
(:class:`~lagsindy.solvers.StagedFISTA`) and what they need to know about the
features (which are Lagrangian terms, which are dissipative). The cases (and the
bootstrap, which re-solves from Gram statistics) call it instead of the estimator.

Every solve runs the multi-start path of :meth:`SparseSolve._paths`, written once:
one problem (:meth:`~SparseSolve.solve`, :meth:`~SparseSolve.stages`), several cut
from one scaled Gram matrix (:meth:`~SparseSolve.solve_many`), or the same job on
several Gram matrices (:meth:`~SparseSolve.solve_across`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from sklearn.utils import check_random_state

from .._torch import to_numpy
from ..formulation.scaling import dense_residuals
from ..solvers import GramQuadratic, StagedFISTA, staged_fista_batch

# Starts of the staged path: lam, lam / lam_decay, ...; and the relative residual
# margin within which the sparsest of their results is preferred.
LAM_STARTS = 2
PATH_TIE = 0.1
# Absolute relative-residual margin below which a path is not restarted (clean data:
# residuals at rounding level differ by large factors that mean nothing).
PATH_FLOOR = 1e-9

_SETTINGS = tuple(StagedFISTA().get_params())


@dataclass
class _Problem:
    """One problem of the path: its datafit, the library indices of its variables,
    their L1 weights and non-negative ones, a warm start of the first stage, the
    first start's result when already computed, and ``to_coef`` (its variables in
    coefficient units; ``None`` for a problem not cut from a :class:`BalancedGram`)."""

    datafit: object
    features: np.ndarray
    weights: torch.Tensor
    nonneg: torch.Tensor | None = None
    w0: torch.Tensor | None = None
    first: object = None
    to_coef: object = None


@dataclass
class SparseSolve:
    """The staged sparse solve with an estimator's settings.

    ``n_terms`` features are Lagrangian terms (threshold ``settings.threshold``), the
    rest dissipation terms (``settings.dissipation_threshold``); ``dissipative[k]``
    says whether feature ``k`` must stay non-negative. The settings' parameters
    read through: ``solver.max_iter`` is ``solver.settings.max_iter``.

    Attributes
    ----------
    lam : float
        The L1 weight of the first stage (the estimator's ``lam``).
    alpha : float or None
        The first stage's step (``None``: ``1/L``).
    settings : StagedFISTA
    n_terms : int
    dissipative : ndarray of bool
    random_state : int, RandomState instance or None
        Seeds the row subsamples (:meth:`subsample_rows`).
    verbose : int
    """

    lam: float
    alpha: float | None
    settings: StagedFISTA
    n_terms: int
    dissipative: np.ndarray
    random_state: object = None
    verbose: int = 0

    def __getattr__(self, name):
        # Only called when the attribute is not found: the settings' parameters.
        settings = self.__dict__.get("settings")
        if name in _SETTINGS and settings is not None:
            return getattr(settings, name)
        raise AttributeError(f"{type(self).__name__!r} has no attribute {name!r}")

    @classmethod
    def from_settings(
        cls,
        settings: StagedFISTA,
        *,
        lam: float,
        alpha: float | None,
        n_terms: int,
        dissipative,
        random_state=None,
        verbose: int = 0,
    ) -> SparseSolve:
        """The solve of ``settings`` with ``lam`` and ``alpha`` (checked first).

        Parameters
        ----------
        settings : StagedFISTA
        lam : float
        alpha : float or None
        n_terms : int
            The number of Lagrangian terms (the first features).
        dissipative : array-like of bool
            Per feature: whether its coefficient must stay non-negative.
        random_state : int, RandomState instance or None, default=None
        verbose : int, default=0

        Returns
        -------
        SparseSolve
        """
        return cls(
            lam,
            alpha,
            settings.validate(),
            n_terms,
            np.asarray(dissipative, dtype=bool),
            random_state,
            verbose,
        )

    def thresholds(self, features) -> np.ndarray:
        """The hard thresholds of ``features`` (library indices)."""
        return self.settings.thresholds(np.asarray(features) >= self.n_terms)

    def nonneg(self, features, device):
        """Mask of the dissipative features (coefficients kept non-negative)."""
        mask = self.dissipative[np.asarray(features, dtype=np.int64)]
        if not mask.any():
            return None
        return torch.as_tensor(mask, dtype=torch.bool, device=device)

    def subsample_rows(self, n, size):
        """Sorted row indices of a subsample of at most ``size`` of ``n`` rows.

        All rows when they fit; otherwise a random choice seeded by ``random_state``,
        or evenly spaced rows when it is ``None``, so a fit never draws from (or
        changes) numpy's or torch's global random state.
        """
        if n <= size:
            return np.arange(n)
        if self.random_state is None:
            # Points more than 1 apart (n > size) round to distinct integers, in
            # order: no np.unique needed (it took 0.8 ms).
            return np.linspace(0, n - 1, size).round().astype(np.int64)
        rng = check_random_state(self.random_state)
        return np.sort(rng.choice(n, size=size, replace=False))

    # ------------------------------------------------------------------- solves
    def stages(
        self,
        datafit,
        features,
        weights,
        verbose,
        starts=None,
        constrain=True,
        first=None,
        reference=0.0,
        w0=None,
    ):
        """The staged sparse solve of ``datafit`` (features: their library indices).

        ``weights`` are the features' L1 weights, ``reference`` the magnitude of a
        fixed term in the variables' units (1 for case III) and ``w0`` a warm start
        of the first stage. ``first``: the result of the first start, already
        computed (by a call with ``starts=1`` on the same problem and settings);
        only the later starts are then run, when needed, so the outcome is the same
        as without it. Dissipative features stay non-negative where ``constrain``
        (and the datafit is a Gram quadratic: case II's sign is chosen after the
        fit). See :meth:`_paths` for the starts.
        """
        problem = self._problem(datafit, features, weights, constrain, w0=w0)
        problem.first = first
        return self._paths([problem], starts, reference, verbose)[0]

    def solve(
        self,
        balanced,
        free,
        target,
        sign,
        penalty,
        reference,
        verbose,
        starts=None,
        constrain=True,
        start=None,
        first=None,
    ):
        """Sparse fit of ``sign * column[target]`` by the columns ``free``.

        Returns the coefficients over all features (zero outside ``free``) and the
        staged result, whose stage records are mapped to coefficient units over all
        features. ``start``: a warm start in coefficient units over all features.
        ``first``: the result of an earlier ``solve`` of the same problem with
        ``starts=1`` (and the same other arguments); it stands for the first start
        (see :meth:`stages`), so only the later starts are run, when needed.
        """
        ((datafit, to_coef),), _, _ = balanced.problems([(free, target, sign)])
        problem = self._problem(datafit, free, penalty, constrain, to_coef, start)
        problem.first = first
        result = self._paths([problem], starts, reference, verbose)[0]
        return _in_coefficients(problem, result, balanced.n_features)

    def solve_many(self, balanced, jobs, penalty, reference, starts=None, extra=()):
        """:meth:`solve` of several problems, their staged solves batched.

        ``jobs`` holds one ``(free, target, sign, constrain, first)`` tuple per
        problem (the arguments of :meth:`solve` of the same names; ``verbose`` is 0
        and there is no warm start). Their Gram matrices are blocks of one scaled
        matrix, so the batched iterations multiply by that matrix once for all of
        them (CPU double precision; see
        :func:`~lagsindy.solvers.staged_fista_batch`); the outcome is that of
        :meth:`solve` on each, up to rounding.

        ``extra`` holds ``(datafit, features, weights)`` problems that are not cut
        from ``balanced`` (case III's mass normalization); their outcome is that of
        :meth:`stages` (``verbose`` 0, ``constrain`` true), up to rounding. When
        they have as many features as the jobs they join the batch, which then
        iterates on each problem's own matrix instead of one shared matrix (the
        same work, one batch fewer); otherwise they are solved alone.

        Returns
        -------
        list
            As :meth:`solve` returns, ``(coef, result)``, in the order of ``jobs``;
            then the :meth:`stages` result of each of ``extra``, in its variables.
        """
        problems, shared = [], None
        if jobs:
            pairs, union, block = balanced.problems([job[:3] for job in jobs])
            for (free, _, _, constrain, first), (datafit, to_coef) in zip(jobs, pairs):
                problem = self._problem(datafit, free, penalty, constrain, to_coef)
                problem.first = first
                problems.append(problem)
            if not extra and block.device.type == "cpu":
                index = [np.searchsorted(union, job[0]) for job in jobs]
                shared = to_numpy(block), index
        for datafit, features, weights in extra:
            problems.append(self._problem(datafit, features, weights, True))
        results = self._paths(problems, starts, reference, 0, shared)
        n_features = balanced.n_features
        out = [
            _in_coefficients(p, r, n_features)
            for p, r in zip(problems[: len(jobs)], results)
        ]
        return out + results[len(jobs) :]

    def solve_across(
        self, balanced, free, target, sign, penalty, reference, start=None, starts=None
    ):
        """:meth:`solve` of one job on each of several scaled Gram matrices, batched.

        The job ``(free, target, sign, penalty, reference, start)`` is that of
        :meth:`solve` (``start`` in coefficient units, as there); ``balanced`` is a
        list of :class:`~lagsindy.formulation.scaling.BalancedGram` (e.g. the
        resamples of a bootstrap). The problems have one size, each its own matrix:
        their stages advance in lockstep, every start of the path as :meth:`solve`
        runs it, so each gets the outcome of its own :meth:`solve`, up to rounding.

        Returns
        -------
        list
            One entry per matrix: ``(coef, result)`` as :meth:`solve` returns them,
            or ``None`` where that problem must be solved alone: its statistics are
            not finite, its target column or a column of ``free`` is zero on it, the
            batch's divergence guard gave up, or its coefficients are not finite.
            (Columns outside ``free`` are the caller's: a column identifiable on one
            matrix only changes what its own solve would take.)
        """
        out = [None] * len(balanced)
        members, problems = [], []
        for i, bal in enumerate(balanced):
            if not _fits_job(bal, free, target):
                continue
            ((datafit, to_coef),), _, _ = bal.problems([(free, target, sign)])
            problems.append(self._problem(datafit, free, penalty, True, to_coef, start))
            members.append(i)
        try:
            results = self._paths(problems, starts, reference, 0)
        except FloatingPointError:
            return out
        for i, problem, result in zip(members, problems, results):
            coef, result = _in_coefficients(problem, result, balanced[i].n_features)
            if np.all(np.isfinite(coef)):
                out[i] = (coef, result)
        return out

    # ------------------------------------------------------------------ the path
    def _problem(
        self, datafit, features, weights, constrain, to_coef=None, start=None, w0=None
    ):
        """A :class:`_Problem`: ``weights`` over the features, or ``penalty`` over
        all (an array indexed by ``features``); ``start`` a warm start in coefficient
        units over all features (with ``to_coef``), ``w0`` one in its variables."""
        features = np.asarray(features)
        like = datafit.zeros()
        if not isinstance(weights, torch.Tensor):
            weights = torch.as_tensor(
                weights[features], dtype=like.dtype, device=like.device
            )
        nonneg = None
        if constrain and isinstance(datafit, GramQuadratic):
            nonneg = self.nonneg(features, like.device)
        if start is not None:
            scale = to_coef(torch.ones_like(like))
            w0 = torch.as_tensor(start[features], dtype=like.dtype, device=like.device)
            w0 = w0 / scale
        return _Problem(datafit, features, weights, nonneg, w0, None, to_coef)

    def _paths(self, problems, starts, reference, verbose, shared=None):
        """The staged solve of every problem, from ``starts`` first-stage weights.

        The first stage's L1 weight can be too strong for a given problem: on
        nearly collinear columns (the weak form's window averages, real data) it
        shrinks the true terms below the threshold and the hard threshold removes
        them for good (the MultiArm double pendulum, weak form: lam=1e-3 kept 10
        terms at relative residual 6.1e-4, lam=1e-4 the six physical ones at
        2.8e-5). The path is therefore also started from ``lam / lam_decay``, ...
        (``starts``, default :data:`LAM_STARTS`, each warm-started at the previous
        start's first stage), and the sparsest path whose residual is within
        :data:`PATH_TIE` of the best is kept (then the larger lam), so a weaker
        start only wins by fitting clearly better. No path's residual can be below
        the dense least-squares residual of all the features, so when a path is
        within :data:`PATH_TIE` of that bound (or at :data:`PATH_FLOOR`) no other
        start can fit clearly better and it is not run (most fits). Case II's
        datafit, ``lam = 0`` and ``starts=1`` take one start.

        The problems advance together: each start is one
        :func:`~lagsindy.solvers.staged_fista_batch` call over the problems still
        open (``shared``: its shared matrix, see there).
        """
        starts = LAM_STARTS if starts is None else starts
        decay = self.settings.lam_decay
        one_start = self.lam == 0 or starts <= 1 or decay <= 1
        paths = [[] for _ in problems]
        bounds = {}
        open_ = list(range(len(problems)))
        for k in range(starts):
            lam = self.lam / decay**k if decay > 1 else self.lam
            run = [j for j in open_ if k > 0 or problems[j].first is None]
            # a later start is warm-started at the previous start's first stage
            w0 = [
                problems[j].w0 if k == 0 else _first_stage(paths[j][-1], problems[j])
                for j in run
            ]
            solved = self._staged(problems, run, lam, reference, verbose, shared, w0)
            for j in open_:
                paths[j].append(solved.get(j, problems[j].first))
            if one_start:
                break
            # Case II's datafit takes one start; a residual at the floor needs no
            # bound (it is >= 0); the bounds of the others, at once.
            above = [
                j
                for j in open_
                if isinstance(problems[j].datafit, GramQuadratic)
                and paths[j][-1].cost > PATH_FLOOR
            ]
            todo = [j for j in above if j not in bounds]
            if todo:
                found = dense_residuals([problems[j].datafit for j in todo])
                bounds.update(zip(todo, found))
            open_ = [
                j
                for j in above
                if paths[j][-1].cost > (1 + PATH_TIE) * bounds[j] + PATH_FLOOR
            ]
            if verbose and k + 1 < starts:
                for j in open_:
                    print(
                        f"[lagsindy] relative residual {paths[j][-1].cost:.3g} (after "
                        f"the refit) is above the dense least-squares bound "
                        f"{bounds[j]:.3g}: restarting the path from "
                        f"lam={lam / decay:.3g}"
                    )
            if not open_:
                break
        return [_sparsest_near_best(path) for path in paths]

    def _staged(self, problems, run, lam, reference, verbose, shared, w0):
        """One start of the path of the problems ``run`` (from ``w0``, one each):
        their staged results by index."""
        if not run:
            return {}
        chosen = [problems[j] for j in run]
        solved = staged_fista_batch(
            [p.datafit for p in chosen],
            lam=lam,
            alpha=self.alpha,
            penalty_weights=[p.weights for p in chosen],
            threshold=[self.thresholds(p.features) for p in chosen],
            reference=reference,
            nonneg=[p.nonneg for p in chosen],
            w0=w0,
            shared=None if shared is None else (shared[0], [shared[1][j] for j in run]),
            verbose=verbose,
            **self.settings.schedule(),
        )
        return dict(zip(run, solved))


def _first_stage(result, problem):
    """Where the next start of the path begins: ``result``'s first stage (the
    problem's own start if it ran none)."""
    return problem.w0 if result.first_stage is None else result.first_stage


def _fits_job(balanced, free, target) -> bool:
    """Whether the job can be cut from ``balanced``: finite statistics, a non-zero
    target column and every column of ``free`` non-zero."""
    if not bool(torch.isfinite(balanced.gram).all()):
        return False
    if balanced.target_scale(target) <= 0:
        return False
    return bool(to_numpy(balanced.identifiable())[np.asarray(free)].all())


def _in_coefficients(problem, result, n_features):
    """``(coef, result)`` of a problem cut from a :class:`BalancedGram`: its
    coefficients over all features, and its stage records mapped to them (unless
    the result is ``problem.first``, whose records its own solve mapped)."""
    coef = np.zeros(n_features)
    coef[problem.features] = to_numpy(problem.to_coef(result.coef))
    if result is not problem.first:
        scale = to_numpy(problem.to_coef(torch.ones_like(result.coef)))
        remap_stages(result.stages, problem.features, scale, n_features)
    return coef, result


def _sparsest_near_best(paths):
    """The sparsest of the paths whose residual is within PATH_TIE of the best (the
    earlier start among equally sparse ones)."""
    if len(paths) == 1:  # most solves: no support to count
        return paths[0]
    best = min(r.cost for r in paths)
    near = [r for r in paths if r.cost <= (1 + PATH_TIE) * best + 1e-12]
    return min(near, key=lambda r: int((r.coef != 0).sum()))


def remap_stages(stages, free, scale, n_features):
    """Stage records in coefficient units over all ``n_features`` features.

    ``free`` are the features of the solved problem and ``scale`` converts its
    variables to coefficients (``coef = w * scale``).
    """
    if not stages:
        return
    full = np.zeros((len(stages), n_features))
    full[:, free] = np.stack([st.coef for st in stages]) * scale
    for st, row in zip(stages, full):
        st.coef = row
        st.support = free[st.support]
