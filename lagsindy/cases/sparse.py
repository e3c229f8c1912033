"""The staged sparse solve with an estimator's settings, shared by the cases.

:class:`SparseSolve` carries the solver hyperparameters of
:class:`~lagsindy.LagrangianSINDy` (``lam``, thresholds, stages, ``debias``...) and
what they need to know about the features (which are Lagrangian terms, which are
dissipative). The cases (and the bootstrap, which re-solves from Gram statistics)
call it instead of the estimator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from sklearn.utils import check_random_state

from .._torch import to_numpy
from ..formulation.scaling import dense_residual, dense_residuals
from ..solvers import GramQuadratic, staged_fista
from ..solvers.staged import staged_fista_batch

# Starts of the staged path: lam, lam / lam_decay, ...; and the relative residual
# margin within which the sparsest of their results is preferred.
LAM_STARTS = 2
PATH_TIE = 0.1
# Absolute relative-residual margin below which a path is not restarted (clean data:
# residuals at rounding level differ by large factors that mean nothing).
PATH_FLOOR = 1e-9


@dataclass
class SparseSolve:
    """Settings of the staged sparse solve (see ``LagrangianSINDy``'s parameters).

    ``n_terms`` features are Lagrangian terms (threshold ``threshold``), the rest
    dissipation terms (``dissipation_threshold``); ``dissipative[k]`` says whether
    feature ``k`` must stay non-negative.
    """

    lam: float
    alpha: float | None
    threshold: float
    dissipation_threshold: float
    lam_decay: float
    step_growth: float
    max_stages: int
    max_iter: int
    tol: float
    solver_tol: float
    debias: bool
    n_terms: int
    dissipative: np.ndarray
    random_state: object = None
    verbose: int = 0

    @classmethod
    def from_params(cls, params: dict, n_terms: int, dissipative, **kwargs):
        """From an estimator's ``get_params()`` (extra keys are ignored)."""
        names = (
            "lam alpha threshold dissipation_threshold lam_decay step_growth "
            "max_stages max_iter tol solver_tol debias random_state verbose"
        ).split()
        values = {k: params[k] for k in names}
        values.update(kwargs)
        return cls(n_terms=n_terms, dissipative=np.asarray(dissipative, bool), **values)

    def thresholds(self, features) -> np.ndarray:
        return np.where(
            np.asarray(features) < self.n_terms,
            self.threshold,
            self.dissipation_threshold,
        )

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

    def staged(self, datafit, lam, features, weights, verbose, **kwargs):
        return staged_fista(
            datafit,
            lam=lam,
            penalty_weights=weights,
            threshold=torch.as_tensor(
                self.thresholds(features), dtype=weights.dtype, device=weights.device
            ),
            verbose=verbose,
            **self._schedule(),
            **kwargs,
        )

    def _schedule(self) -> dict:
        """The staged schedule's settings, shared by one solve and the batch."""
        return dict(
            lam_decay=self.lam_decay,
            step_growth=self.step_growth,
            alpha=self.alpha,
            max_stages=self.max_stages,
            max_iter=self.max_iter,
            tol=self.tol,
            solver_tol=self.solver_tol,
            debias=self.debias,
        )

    def stages(
        self,
        datafit,
        features,
        weights,
        verbose,
        starts=None,
        constrain=True,
        first=None,
        **kwargs,
    ):
        """The staged sparse solve of ``datafit`` (features: their library indices).

        ``weights`` are the features' L1 weights; ``kwargs`` go to
        :func:`~lagsindy.solvers.staged_fista` (``reference``, ``w0``). ``first``: the
        result of the first start, already computed (by a call with ``starts=1`` on
        the same problem and settings); only the later starts are then run, when
        needed, so the outcome is the same as without it.
        """
        # ``starts`` (default LAM_STARTS) first-stage weights are tried.
        # The first stage's L1 weight can be too strong for a given problem: on
        # nearly collinear columns (the weak form's window averages, real data) it
        # shrinks the true terms below the threshold and the hard threshold removes
        # them for good (the MultiArm double pendulum, weak form: lam=1e-3 kept 10
        # terms at relative residual 6.1e-4, lam=1e-4 the six physical ones at
        # 2.8e-5). The path is therefore also started from lam / lam_decay, and the
        # sparsest path whose residual is within PATH_TIE of the best is kept (then
        # the larger lam), so a weaker start only wins by fitting clearly better.
        # No path's residual can be below the dense least-squares residual of all
        # the features, so when the first path is within PATH_TIE of that bound no
        # other start can fit clearly better and it is not run (most fits).
        starts = LAM_STARTS if starts is None else starts
        # Dissipation that opposes motion (viscous, relative, drag, Coulomb) cannot
        # have a negative coefficient: projected in FISTA and in the refit. Only where
        # the scale's sign is physical (forces given, or a positive kinetic energy
        # fixes it); case II's sign is chosen after the fit.
        if constrain and isinstance(datafit, GramQuadratic):
            kwargs["nonneg"] = self.nonneg(features, weights.device)
        if not isinstance(datafit, GramQuadratic) or self.lam == 0 or starts <= 1:
            if first is not None:
                return first
            return self.staged(datafit, self.lam, features, weights, verbose, **kwargs)
        results = []
        bound = None
        for k in range(starts):
            lam = self.lam / self.lam_decay**k if self.lam_decay > 1 else self.lam
            if k == 0 and first is not None:
                res = first
            else:
                extra = dict(kwargs)
                if k > 0 and results[-1].first_stage is not None:
                    extra["w0"] = results[-1].first_stage
                res = self.staged(datafit, lam, features, weights, verbose, **extra)
            results.append(res)
            if self.lam_decay <= 1 or res.cost <= PATH_FLOOR:  # bound >= 0: no need
                break
            if bound is None:
                bound = dense_residual(datafit)
            if res.cost <= (1 + PATH_TIE) * bound + PATH_FLOOR:
                break
            if verbose and k + 1 < starts:
                print(
                    f"[lagsindy] relative residual {res.cost:.3g} (after the refit) is "
                    "above the dense "
                    f"least-squares bound {bound:.3g}: restarting the path from "
                    f"lam={lam / self.lam_decay:.3g}"
                )
        return _sparsest_near_best(results)

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
        datafit, to_coef = balanced.problem(free, target, sign)
        weights = torch.as_tensor(
            penalty[free], dtype=datafit.rhs.dtype, device=datafit.rhs.device
        )
        scale = to_coef(torch.ones_like(datafit.rhs))
        kwargs = {}
        if start is not None:
            kwargs["w0"] = (
                torch.as_tensor(start[free], dtype=scale.dtype, device=scale.device)
                / scale
            )
        result = self.stages(
            datafit,
            free,
            weights,
            verbose,
            reference=reference,
            starts=starts,
            constrain=constrain,
            first=first,
            **kwargs,
        )
        coef = np.zeros(balanced.n_features)
        coef[free] = to_numpy(to_coef(result.coef))
        if result is not first:  # ``first``'s records were mapped by its own solve
            remap_stages(result.stages, free, to_numpy(scale), balanced.n_features)
        return coef, result

    def solve_many(self, balanced, jobs, penalty, reference, starts=None, extra=()):
        """:meth:`solve` of several problems, their staged solves batched.

        ``jobs`` holds one ``(free, target, sign, constrain, first)`` tuple per
        problem (the arguments of :meth:`solve` of the same names; ``verbose`` is 0
        and there is no warm start). Problems of the same size on the CPU in double
        precision go through :func:`~lagsindy.solvers.staged.staged_fista_batch`
        together, one batch per start of the path; the outcome is that of
        :meth:`solve` on each, up to rounding.

        ``extra`` holds ``(datafit, features, weights)`` problems that are not cut
        from ``balanced`` (case III's mass normalization); their outcome is that of
        :meth:`stages` (``verbose`` 0, ``constrain`` true), up to rounding. When
        they have as many features as the jobs they join the batch, which then
        iterates on each problem's own matrix instead of one shared matrix (the
        same work, one batch fewer).

        Returns
        -------
        list
            As :meth:`solve` returns, ``(coef, result)``, in the order of ``jobs``;
            then the :meth:`stages` result of each of ``extra``, in its variables.
        """
        starts = LAM_STARTS if starts is None else starts
        gram = balanced.gram

        def alone():  # the extra problems, each solved on its own
            return [
                self.stages(datafit, features, weights, 0, starts, reference=reference)
                for datafit, features, weights in extra
            ]

        n_jobs = len(jobs) + len(extra)
        if n_jobs <= 1 or gram.device.type != "cpu" or gram.dtype != torch.float64:
            return [
                self.solve(
                    balanced,
                    free,
                    target,
                    sign,
                    penalty,
                    reference,
                    0,
                    starts=starts,
                    constrain=constrain,
                    first=first,
                )
                for free, target, sign, constrain, first in jobs
            ] + alone()
        sizes = {len(job[0]) for job in jobs} | {len(e[1]) for e in extra}
        if len(sizes) > 1:  # the extra problems on their own
            batched = self.solve_many(balanced, jobs, penalty, reference, starts)
            return batched + alone()
        prepared = []
        pairs, union, block = balanced.problems([job[:3] for job in jobs])
        for (free, _, _, constrain, first), (datafit, to_coef) in zip(jobs, pairs):
            weights = torch.as_tensor(penalty[free], dtype=gram.dtype)
            nonneg = self.nonneg(free, weights.device) if constrain else None
            prepared.append(
                (np.asarray(free), datafit, to_coef, weights, nonneg, first)
            )
        for datafit, features, weights in extra:  # to_coef None: results as they are
            nonneg = self.nonneg(features, weights.device)
            prepared.append(
                (np.asarray(features), datafit, None, weights, nonneg, None)
            )
        return self._batch(balanced, prepared, reference, starts, union, block)

    def _batch(self, balanced, prepared, reference, starts, union, block):
        """The staged solves (every start) of ``prepared`` problems of ``balanced``.

        ``union`` holds the problems' columns and ``block`` its scaled Gram block
        (:meth:`BalancedGram.problems`). Problems without a ``to_coef`` (the extra
        problems of :meth:`solve_many`) bring their own matrices.
        """
        n_features = balanced.n_features
        n = len(prepared)
        # Every problem's Gram matrix is a block of one scaled Gram matrix: the
        # batched iterations multiply by that matrix once for all of them. With
        # extra problems, each multiplies by its own (one matrix holding them all,
        # block-diagonally, made the dense steps of the batch, e.g. the refit's
        # eigendecompositions, 8 times the work).
        shared = None
        if all(job[2] is not None for job in prepared):
            index = [np.searchsorted(union, job[0]) for job in prepared]
            shared = to_numpy(block), index
        paths = [[] for _ in range(n)]
        open_ = list(range(n))
        bounds = [None] * n
        one_start = self.lam == 0 or starts <= 1
        for k in range(1 if one_start else starts):
            lam = self.lam / self.lam_decay**k if self.lam_decay > 1 else self.lam
            run = [j for j in open_ if not (k == 0 and prepared[j][5] is not None)]
            solved = staged_fista_batch(
                [prepared[j][1] for j in run],
                lam=lam,
                penalty_weights=[prepared[j][3] for j in run],
                threshold=[
                    torch.as_tensor(
                        self.thresholds(prepared[j][0]), dtype=prepared[j][3].dtype
                    )
                    for j in run
                ],
                reference=reference,
                **self._schedule(),
                nonneg=[prepared[j][4] for j in run],
                shared=None if shared is None else (shared[0], [index[j] for j in run]),
                w0=None if k == 0 else [paths[j][-1].first_stage for j in run],
            )
            fresh = dict(zip(run, solved))
            latest = {j: fresh[j] if j in fresh else prepared[j][5] for j in open_}
            for j in open_:
                paths[j].append(latest[j])
            if one_start or self.lam_decay <= 1:
                break
            # A residual at the floor stops whatever the bound (it is >= 0); the
            # bounds of the others, at once.
            above = [j for j in open_ if latest[j].cost > PATH_FLOOR]
            todo = [j for j in above if bounds[j] is None]
            for j, v in zip(todo, dense_residuals([prepared[j][1] for j in todo])):
                bounds[j] = v
            open_ = [
                j
                for j in above
                if latest[j].cost > (1 + PATH_TIE) * bounds[j] + PATH_FLOOR
            ]
            if not open_:
                break
        out = []
        for (free, datafit, to_coef, _, _, first), path in zip(prepared, paths):
            result = _sparsest_near_best(path)
            if to_coef is None:
                out.append(result)
                continue
            coef = np.zeros(n_features)
            coef[free] = to_numpy(to_coef(result.coef))
            if result is not first:  # ``first``'s records were mapped by its own solve
                scale = to_numpy(to_coef(torch.ones_like(datafit.rhs)))
                remap_stages(result.stages, free, scale, n_features)
            out.append((coef, result))
        return out


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
