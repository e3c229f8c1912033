"""The search of :func:`~lagsindy.diagnose`: delay, joint revision, additions, swaps.

See :mod:`lagsindy.diagnostics` for the loop and the criterion.
"""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import torch
from sklearn.utils.validation import check_is_fitted

from .._torch import to_tensor
from .._validation import validate_state, validate_tau
from ..delay import _diagnose_delay
from ..formulation.operator import reuse_weak_columns
from .catalogue import (
    _DISSIPATIVE,
    _NONNEGATIVE,
    DEFAULT_CATALOGUE,
    _catalogue,
    _effect_coefficient,
    velocity_eps,
)
from .report import Candidate, DiagnosisReport, Step, _units
from .scoring import (
    _adjusted_tau,
    _columns,
    _fit_model,
    _force_scale,
    _kept_terms,
    _mass_definite,
    _mass_samples,
    _NoWindows,
    _residual,
    _start_coefficients,
    _Statistics,
    _time_folds,
    _weighted_scorer,
)

# Held-out residual below this fraction of the scale is rounding.
_PRECISION = 1e-10


def diagnose(
    est,
    X,
    tau=None,
    groups=None,
    *,
    catalogue=DEFAULT_CATALOGUE,
    extra_terms=None,
    angles=None,
    units=None,
    n_splits: int = 3,
    min_explained: float = 0.05,
    max_effects: int = 4,
    min_improvement: float = 0.01,
    eps="auto",
    revise: bool = True,
    window=None,
    bootstrap=None,
    random_state=None,
    verbose: int = 0,
) -> DiagnosisReport:
    """Find the missing effects a fitted model leaves in its residual, add and refit.

    See the module documentation for the loop and the criterion.

    Parameters
    ----------
    est : LagrangianSINDy
        A fitted estimator (not modified).
    X : array-like or DataFrame of shape (n_samples, 3 * n_dof)
        Data in the estimator's layout: time-ordered trajectories (the held-out
        trajectory criterion integrates along them).
    tau : array-like of shape (n_samples, n_dof), default=None
        Generalized forces; ``None`` for passive data (the model's scale is then set by
        its fixed term).
    groups : array-like of shape (n_samples,), default=None
        Trajectory labels; folds hold out whole trajectories. Without them,
        trajectories are split where the positions jump. With fewer trajectories
        than ``n_splits``, each is cut into ``n_splits`` time blocks.
    catalogue : sequence of str, default=all kinds
        Candidate kinds: ``"viscous"``, ``"relative"``, ``"drag"``, ``"coulomb"``,
        ``"bias"``, ``"gain"``, ``"conservative"``, ``"delay"``. ``"delay"`` (forced
        data only) estimates a delay between the recorded input and the positions
        first (:func:`lagsindy.delay.estimate_delay`, up to 10 sampling intervals);
        it is kept, as the step ``"delay"`` with its estimate in ms, when the model
        refitted on the shifted input (:func:`lagsindy.delay.shift_input`) predicts
        held-out trajectories better; the other effects are then searched with the
        shifted input, and ``report.final`` is fitted on it (predict with
        ``shift_input(tau, t, report.steps[0].coefficient / 1000)``).
    extra_terms : list of str or sympy.Expr, default=None
        More conservative candidates (Lagrangian terms), beside ``q**2`` for every
        coordinate and ``cos``/``sin`` of angles.
    angles : list of str, default=None
        Angular coordinates (for candidates); default: the library's ``angles``.
    units : dict, default=None
        ``{coordinate: (position unit, force unit)}``, e.g. ``{"x": ("m", "N")}``,
        to print coefficient units; without it units are given in words ("per unit
        of x_dot").
    n_splits : int, default=3
        Held-out folds.
    min_explained : float, default=0.05
        Smallest share of the held-out criterion (squared) a candidate must explain
        to be tried (it must also improve every fold).
    max_effects : int, default=4
    min_improvement : float, default=0.01
        A revision or an effect is kept only if the refitted model's held-out
        criterion falls by at least this fraction.
    eps : "auto", float or dict, default="auto"
        Coulomb smoothing velocity of the candidates: ``"auto"`` takes 1 % of each
        coordinate's top speed (99th percentile of ``|q_dot|``).
    revise : bool, default=True
        First run the Lagrangian's sparse search jointly with the dissipative
        catalogue (step 1), so damping absorbed into wrong Lagrangian terms can be
        undone.
    window : int, default=None
        Samples per test function of the trajectory criterion; ``None``: the
        estimator's ``window`` (at most half the shortest time block).
    bootstrap : int, default=None
        When an integer, the final model's configuration is bootstrapped with that
        many resamples (:func:`lagsindy.bootstrap`, whole trajectories as groups, or
        time blocks with fewer than 10): ``report.bootstrap`` holds the intervals and
        inclusion of every term, and each step's ``low`` and ``high`` the interval of
        its effect (shown in the report's table). Costs about one fit per 10
        resamples on the fast path, one fit per resample otherwise.
    random_state : int, RandomState instance or None, default=None
        Seeds the bootstrap's resamples (the diagnosis itself is deterministic).
    verbose : int, default=0

    Returns
    -------
    DiagnosisReport
        Printable (``print(report)``), with ``report.final`` the refitted model,
        ``report.steps`` the effects found and ``report.plot()`` a figure.

    Examples
    --------
    >>> from lagsindy import LagrangianSINDy, diagnose
    >>> from lagsindy.systems import single_pendulum, make_dataset
    >>> system = single_pendulum().with_damping(viscous={"theta": 0.2})
    >>> data = make_dataset(system, n_trajectories=12, duration=3.0,
    ...                     excitation="sincos", random_state=0)
    >>> est = LagrangianSINDy(system.paper_library(), formulation="strong")
    >>> est = est.fit(data.X, data.tau)
    >>> report = diagnose(est, data.X, data.tau, groups=data.groups)
    >>> report.effects
    ['viscous(theta)']
    >>> round(report.steps[0].coefficient, 3)
    0.2
    """
    check_is_fitted(est)
    Xa, _, _ = validate_state(est, X, reset=False, coordinates=est.coordinates_)
    tau_a = (
        None
        if tau is None
        else validate_tau(tau, Xa.shape[0], est.n_dof_, est.coordinates_)
    )
    if (tau_a is None) != (est.case_ != "forces"):
        raise ValueError(
            "diagnose the model with the kind of data it was fitted on: tau for a "
            "model fitted with tau (case I), no tau for a passive model"
        )
    if not 0 < min_explained < 1:
        raise ValueError(f"min_explained must be in (0, 1), got {min_explained}")
    if bootstrap is not None and not (
        isinstance(bootstrap, (int, np.integer))
        and not isinstance(bootstrap, bool)
        and bootstrap >= 2
    ):
        raise ValueError(
            f"bootstrap must be None or a number of resamples >= 2, got {bootstrap!r}"
        )
    if groups is not None:
        groups = np.asarray(groups)
        if groups.shape != (Xa.shape[0],):
            raise ValueError(
                f"groups must have one label per row of X ({Xa.shape[0]}), got "
                f"{groups.shape}"
            )
    coords = list(est.coordinates_)
    d = est.n_dof_
    lib_angles = getattr(est.library_, "angles", None)
    if angles is None:
        angles = coords if lib_angles == "all" else list(lib_angles or [])
    if isinstance(eps, str):
        if eps != "auto":
            raise ValueError(f"eps must be 'auto', a number or a dict, got {eps!r}")
        eps = velocity_eps(Xa, d, coords)
    elif not isinstance(eps, dict):
        eps = {c: float(eps) for c in coords}

    # The refits share their features' weak-form statistics: each later refit's
    # features are among the joint revision's (the library and the dissipative
    # candidates), so only its input is integrated again.
    with reuse_weak_columns():
        search = _Search(
            est,
            Xa,
            tau_a,
            groups,
            catalogue=catalogue,
            extra_terms=extra_terms,
            angles=angles,
            eps=eps,
            n_splits=n_splits,
            window=window,
            min_explained=min_explained,
            min_improvement=min_improvement,
            verbose=verbose,
        )
        if "delay" in catalogue and tau_a is not None and search.dt and search.dt > 0:
            search.input_delay()  # step 0
        search.total_ref = float(
            sum(search.scorer.w @ r for r in search.scorer.reference)
        )
        if revise and search.diss:
            search.revise()  # step 1
        search.swap_pass()  # step 2b
        search.add_effects(max_effects)  # step 2
        search.swap_pass()
    # outside the block: a bootstrap's refits of resampled rows would only add
    # statistics that nothing reuses
    report = search.report(units, bootstrap, random_state)  # step 3
    if report.degenerate_folds:
        warnings.warn(
            "diagnose excluded degenerate folds from some models' held-out scores "
            "(their refits have a singular or indefinite mass matrix): "
            + ", ".join(report.degenerate_folds),
            UserWarning,
            stacklevel=2,
        )
    return report


class _Search:
    """One diagnosis: the data's columns, folds and scorers, and the current model.

    Each step of :func:`diagnose` is a method that replaces the current model
    (``current``, its column ``support``, held-out ``value``, ``effects`` and
    ``gains``) only by one that predicts held-out data better.
    """

    def __init__(
        self,
        est,
        Xa,
        tau_a,
        groups,
        *,
        catalogue,
        extra_terms,
        angles,
        eps,
        n_splits,
        window,
        min_explained,
        min_improvement,
        verbose,
    ):
        self.est, self.Xa, self.groups, self.eps = est, Xa, groups, eps
        # Refits and predictions see X as the estimator was fitted on it (named columns
        # for a DataFrame-fitted model), so scikit-learn's feature-name checks hold.
        names = getattr(est, "feature_names_in_", None)
        self.Xf = Xa if names is None else pd.DataFrame(Xa, columns=list(names))
        self.catalogue, self.n_splits = catalogue, n_splits
        self.min_explained, self.min_improvement = min_explained, min_improvement
        self.verbose = verbose
        self.coords = list(est.coordinates_)
        self.d = est.n_dof_
        self.passive = passive = tau_a is None
        self.Xt = Xt = to_tensor(Xa, dtype=torch.float64, device="cpu")
        tau_t = None if passive else to_tensor(tau_a, dtype=torch.float64, device="cpu")

        # -------------------------------------------------------- columns and folds
        candidates = _catalogue(est, catalogue, extra_terms, angles, tau_a, eps)
        self.diss = [c for c in candidates if c.kind in _DISSIPATIVE]
        self.gain = [c for c in candidates if c.kind == "gain"]
        self.op, self.index, self.nonneg, self.n_lib = _columns(est, candidates)
        op, index, n_lib = self.op, self.index, self.n_lib
        self.n_features = n_features = len(self.nonneg)
        extra = self._gain_columns(tau_t)

        dt, self.segments, folds, self.fold_kind, win = _time_folds(
            est, Xt, groups, n_splits, window
        )
        self.dt, self.folds, self.win = dt, folds, win
        self.stats_w = None
        if dt and dt > 0 and win >= 9:
            try:
                self.stats_w = _Statistics(
                    op, Xt, tau_t, extra, folds, "weak", window=win, dt=float(dt)
                )
            except _NoWindows:
                self.stats_w = None
        stats_s = _Statistics(op, Xt, tau_t, extra, folds, "strong")

        # The starting model's support and reference scales (fixed for the whole run).
        self.start_coef, self.fixed_col = _start_coefficients(
            est, index, n_features, n_lib, passive
        )
        self.target = None if passive else n_features

        self.mass, self.mass_all = _mass_samples(op, Xt, folds)

        self.scorer_s = self._make_scorer(stats_s)
        self.scorer = (
            self._make_scorer(self.stats_w)
            if self.stats_w is not None
            else self.scorer_s
        )
        self.criterion = (
            "trajectory (weak form)" if self.stats_w is not None else "pointwise"
        )
        self.degenerate = set()

        self.s0 = self.support_of(est)
        self.j0, _ = self.J(self.s0)
        self.start_valid = self.valid(self.s0)
        # A model that cannot predict some accelerations is beaten by any valid one.
        self.value0 = self.j0 if self.start_valid else np.inf
        self.p0 = self.scorer_s.score(self.s0)[0]
        if verbose:
            print(f"[lagsindy] before: held-out {self.criterion} error {self.j0:.4g}")

        self.candidates = candidates
        self.by_name = {c.name: c for c in candidates}
        self.current, self.support, self.value = est, self.s0, self.value0
        self.effects, self.gains, self.rankings, self.history = [], {}, [], {}
        self.stop_reason = ""
        self.swaps = []
        self.tau_a = tau_a
        self.tau_recorded = tau_a
        self.scorer_rec, self.scorer_s_rec = self.scorer, self.scorer_s
        self.delay = None  # (Candidate, DelayEstimate) once accepted
        self._fits = {}  # refits by their effects, gains and candidates (fit_with)

    # ------------------------------------------------------------------ helpers
    def _gain_columns(self, tau_t):
        """Columns of the gain candidates: ``-tau`` on their coordinate."""
        if not self.gain:
            return None
        Xt = self.Xt
        extra = Xt.new_zeros((Xt.shape[0], self.d, len(self.gain)))
        for k, c in enumerate(self.gain):
            extra[:, c.term, k] = -tau_t[:, c.term]
        return extra

    def _make_scorer(self, stats):
        return _weighted_scorer(
            stats,
            self.start_coef,
            self.n_features,
            self.target,
            self.fixed_col,
            self.nonneg,
            self.mass,
        )

    def support_of(self, model):
        index = self.index
        s = {index[name] for name in _kept_terms(model)}
        s |= {
            index[f.name]
            for f, c in zip(model.dissipation_terms_, model.dissipation_coef_)
            if c
        }
        return s

    def valid(self, support):
        coef = self.scorer.coefficients(support)
        c = np.zeros(self.n_lib)
        for j, v in coef.items():
            if j < self.n_lib:
                c[j] = v
        return _mass_definite(self.mass_all, c)

    def J(self, support):
        value, per_fold, bad = self.scorer.score(support)
        for k in bad:
            self.degenerate.add(k)
        return value, per_fold

    def fit_with(self, effs, gns, penalized=()):
        """The estimator refitted with known ``effs``, input gains ``gns`` and the
        ``penalized`` candidates, on the current input.

        Refits are deterministic, so one asked for again (the input delay search's
        fit at delay 0 is the joint revision's fit) is the model already fitted.
        """
        key = (
            tuple(e.name for e in effs),
            tuple(sorted(gns.items())),
            tuple(c.name for c in penalized),
        )
        tau, model = self._fits.get(key, (None, None))
        if model is None or tau is not self.tau_a:
            model = _fit_model(
                self.est,
                self.Xf,
                _adjusted_tau(self.tau_a, gns),
                self.groups,
                effects=effs,
                penalized=penalized,
                eps=self.eps,
            )
            self._fits[key] = (self.tau_a, model)
        return model

    def nonneg_ok(self, model, effs):
        names_ = {e.name for e in effs if e.kind in _NONNEGATIVE}
        return all(
            c >= 0
            for f, c in zip(model.dissipation_terms_, model.dissipation_coef_)
            if f.name in names_
        )

    def contributes(self, model, cand, gns):
        """The effect's share of the force scale is above rounding in ``model``."""
        c = _effect_coefficient(model, cand, gns)
        size = abs(c) * self.scorer.col[self.index[cand.name]]
        return size**2 > _PRECISION * self.total_ref

    def improves(self, jt, st, model, effs):
        """``model`` (support ``st``, held-out ``jt``) beats the current one."""
        return (
            jt < (1 - self.min_improvement) * self.value
            and self.valid(st)
            and self.nonneg_ok(model, effs)
        )

    # ------------------------------------------------------ step 0: input delay
    def input_delay(self):
        """Accept an input delay when the model refitted on the shifted input wins."""
        est, Xt, verbose = self.est, self.Xt, self.verbose
        # The delay is estimated with the dissipative catalogue as candidates:
        # an input delay and missing damping both shift the phase of the force.
        joint_config = _fit_model(
            est, None, None, None, penalized=self.diss, eps=self.eps, fit=False
        )
        try:  # the joint revision's fit: the delay search's first fit too
            joint = self.fit_with([], {}, penalized=self.diss)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            joint = None  # the delay search fits (and fails) on its own
        found = _diagnose_delay(
            joint_config,
            self.Xf,
            self.tau_a,
            self.segments,
            float(self.dt),
            verbose,
            fitted_at_zero=joint,
        )
        if found is None:
            return
        estimate, shifted = found
        tau_sh = to_tensor(shifted, dtype=torch.float64, device="cpu")
        extra_sh = self._gain_columns(tau_sh)
        ss = _Statistics(self.op, Xt, tau_sh, extra_sh, self.folds, "strong")
        sw = None
        if self.stats_w is not None:
            sw = _Statistics(
                self.op,
                Xt,
                tau_sh,
                extra_sh,
                self.folds,
                "weak",
                window=self.win,
                dt=float(self.dt),
            )
        self.scorer_s = self._make_scorer(ss)
        self.scorer = self._make_scorer(sw) if sw is not None else self.scorer_s
        self.tau_a = shifted
        try:
            trial = self.fit_with([], {})
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            trial = None
        st = self.support_of(trial) if trial is not None else self.s0
        jt = self.J(st)[0] if trial is not None else np.inf
        if jt < (1 - self.min_improvement) * self.value and self.valid(st):
            driven = tuple(
                c
                for i, c in enumerate(self.coords)
                if np.any(self.tau_recorded[:, i] != 0)
            )
            cand = Candidate("delay", "delay", driven, estimate)
            self.delay = (cand, estimate)
            self.current, self.support, self.value = trial, st, jt
            self.history[cand.name] = ("added", jt)
            if verbose:
                print(
                    f"[lagsindy] input delay {1e3 * estimate.delay:.1f} ms: "
                    f"held-out {jt:.4g}"
                )
        else:
            if verbose:
                print(
                    f"[lagsindy] an input delay of {1e3 * estimate.delay:.1f} ms "
                    f"does not improve the held-out criterion ({self.value:.4g} -> "
                    f"{jt:.4g})"
                )
            self.scorer, self.scorer_s = self.scorer_rec, self.scorer_s_rec
            self.tau_a = self.tau_recorded

    # -------------------------------------------------- step 1: joint revision of L
    def revise(self):
        """Sparse search over the Lagrangian and the dissipative catalogue together."""
        J, index, verbose = self.J, self.index, self.verbose
        min_explained, min_improvement = self.min_explained, self.min_improvement
        try:
            joint = self.fit_with([], {}, penalized=self.diss)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
            joint = None
            if verbose:
                print(f"[lagsindy] joint fit failed: {exc}")
        if joint is None:
            return
        sj = self.support_of(joint)
        kept = [
            self.by_name[f.name]
            for f, c in zip(joint.dissipation_terms_, joint.dissipation_coef_)
            if c and f.name in self.by_name
        ]
        # Backward pruning: each kept effect must pass the test of an added one
        # (explain min_explained of the held-out criterion, improve every fold,
        # improve the criterion by min_improvement); drop the weakest until so.
        while kept:
            jj, folds_j = J(sj)
            trials = []
            for e in kept:
                v, folds_v = J(sj - {index[e.name]})
                ok = np.isfinite(folds_v) & np.isfinite(folds_j)
                share = 1 - jj**2 / v**2 if np.isfinite(v) and v > 0 else 1.0
                passes = (
                    share >= min_explained
                    and jj < (1 - min_improvement) * v
                    and bool(ok.any() and np.all(folds_j[ok] < folds_v[ok]))
                )
                trials.append((passes, share, e))
            failing = [t for t in trials if not t[0]]
            if not failing:
                break
            weakest = min(failing, key=lambda t: t[1])[2]
            kept.remove(weakest)
            sj = sj - {index[weakest.name]}
        if verbose:
            print(f"[lagsindy] joint revision keeps {[e.name for e in kept]}")
        if not kept:
            return
        revised = self.fit_with(kept, {})
        sr = self.support_of(revised)
        jr, _ = J(sr)
        if self.improves(jr, sr, revised, kept):
            self.current, self.support, self.value = revised, sr, jr
            self.effects = list(kept)
            for e in kept:
                self.history[e.name] = ("joint", jr)
        elif verbose:
            print(
                f"[lagsindy] the revision does not improve the held-out "
                f"criterion ({self.value:.4g} -> {jr:.4g}); kept the model"
            )

    # ----------------------------------------------------------- step 2b: swaps
    def swap_pass(self):
        """Replace accepted dissipative effects by others of the same coordinates.

        The joint search or a greedy addition can keep the wrong effect of a
        coordinate (quadratic drag for small viscous damping): try replacing each
        accepted dissipative effect by another candidate acting on the same
        coordinates, and keep the swap that most improves the held-out criterion.
        """
        J, index = self.J, self.index
        for _ in range(len(self.effects)):
            trials = []
            names = {e.name for e in self.effects}
            for e in self.effects:
                if e.kind not in _DISSIPATIVE:
                    continue
                for c in self.diss:
                    if c.name in names or c.coordinates != e.coordinates:
                        continue
                    v = J((self.support - {index[e.name]}) | {index[c.name]})[0]
                    if v < (1 - self.min_improvement) * self.value:
                        trials.append((v, e, c))
            accepted = False
            for _, e, c in sorted(trials, key=lambda t: t[0])[:3]:
                trial_effects = [c if x is e else x for x in self.effects]
                try:
                    trial = self.fit_with(trial_effects, self.gains)
                except (ValueError, FloatingPointError, np.linalg.LinAlgError):
                    continue
                st = self.support_of(trial)
                st |= {index[f"gain({self.coords[i]})"] for i in self.gains}
                jt, _ = J(st)
                if self.improves(jt, st, trial, trial_effects) and self.contributes(
                    trial, c, self.gains
                ):
                    if self.verbose:
                        print(
                            f"[lagsindy] swapped {e.name} for {c.name}: held-out "
                            f"{self.value:.4g} -> {jt:.4g}"
                        )
                    self.current, self.support, self.value = trial, st, jt
                    self.effects = trial_effects
                    self.history[c.name] = ("swapped", jt)
                    self.swaps.append((e.name, c.name))
                    accepted = True
                    break
            if not accepted:
                break

    # ------------------------------------------------ step 2: forward additions
    def add_effects(self, max_effects):
        """Add the best-ranked candidate while the refitted model predicts better."""
        J, index, verbose = self.J, self.index, self.verbose
        min_explained = self.min_explained
        gain = self.gain
        for _ in range(max(0, max_effects - len(self.effects))):
            if min(self.value, self.scorer_s.score(self.support)[0]) ** 2 <= _PRECISION:
                self.stop_reason = "the remaining residual is at rounding level"
                break
            taken = {e.name for e in self.effects}
            taken |= {f"gain({self.coords[i]})" for i in self.gains}
            pool = [c for c in self.candidates if c.name not in taken]
            if self.gains and len(self.gains) >= len(gain) - 1:
                # Gains on every input would leave the model's scale free (all zero).
                pool = [c for c in pool if c.kind != "gain"]
            if not pool:
                self.stop_reason = "every candidate is in the model"
                break
            base_value, base_folds = J(self.support)
            rows = []
            for c in pool:
                j = index[c.name]
                if j in self.support:
                    continue
                v, folds_v = J(self.support | {j})
                coef = self.scorer.coefficients(self.support | {j}).get(j, 0.0)
                ok = np.isfinite(folds_v) & np.isfinite(base_folds)
                rows.append(
                    {
                        "kind": c.kind,
                        "term": c.name,
                        "explained": float(1 - v**2 / base_value**2)
                        if np.isfinite(base_value) and base_value > 0
                        else (1.0 if np.isfinite(v) else 0.0),
                        "every_fold": bool(
                            ok.any() and np.all(folds_v[ok] < base_folds[ok])
                        ),
                        "criterion": v,
                        "coefficient": float(coef),
                    }
                )
            table = pd.DataFrame(rows)
            if not len(table):
                self.stop_reason = "every candidate is in the model"
                break
            table = table.sort_values("explained", ascending=False, kind="stable")
            table = table.reset_index(drop=True)
            self.rankings.append(table)
            if verbose:
                print(table.head(5).to_string())
            eligible = table[(table.explained >= min_explained) & table.every_fold]
            if not len(eligible):
                top = table.iloc[0]
                self.stop_reason = (
                    f"the best remaining candidate, {top['term']}, explains "
                    f"{top['explained']:.2%} of the held-out residual (needs "
                    f"{min_explained:.0%} and every fold better)"
                )
                break
            if not self._add_one(eligible):
                self.stop_reason = (
                    f"{eligible.iloc[0]['term']} explains part of the residual but "
                    "the refitted model does not predict held-out trajectories better"
                )
                table.attrs["rejected"] = eligible.iloc[0]["term"]
                break
        else:
            self.stop_reason = f"max_effects={max_effects} reached"

    def _add_one(self, eligible):
        """Refit with the first of the top three that improves; whether one did."""
        for _, top in eligible.head(3).iterrows():
            best = self.by_name[top["term"]]
            trial_effects, trial_gains = list(self.effects), dict(self.gains)
            if best.kind == "gain":
                trial_gains[best.term] = trial_gains.get(best.term, 0.0) + float(
                    top["coefficient"]
                )
            else:
                trial_effects.append(best)
            try:
                trial = self.fit_with(trial_effects, trial_gains)
            except (ValueError, FloatingPointError, np.linalg.LinAlgError):
                continue
            st = self.support_of(trial)
            if best.kind == "gain":
                # The adjusted input carries the gain; score with its column too.
                st = st | {self.index[best.name]}
            jt, _ = self.J(st)
            if self.improves(jt, st, trial, trial_effects) and self.contributes(
                trial, best, trial_gains
            ):
                self.current, self.support, self.value = trial, st, jt
                self.effects, self.gains = trial_effects, trial_gains
                self.history[best.name] = ("added", jt)
                if self.verbose:
                    print(f"[lagsindy] added {best.name}: held-out {jt:.4g}")
                return True
            if self.verbose:
                print(
                    f"[lagsindy] {best.name} does not improve held-out predictions "
                    f"after the refit ({self.value:.4g} -> {jt:.4g})"
                )
        return False

    # ------------------------------------------------------ step 3: never worse
    def report(self, units, bootstrap, random_state):
        """Keep the starting model unless the final one is better; the report."""
        est, J, index, coords = self.est, self.J, self.index, self.coords
        final = self.current
        if self.current is not est and not self.value < self.value0:
            final, self.support, self.effects, self.gains = est, self.s0, [], {}
            self.stop_reason = (
                "the diagnosed model does not beat the starting one held out"
            )
            if self.delay is not None:
                self.delay = None
                self.scorer, self.scorer_s = self.scorer_rec, self.scorer_s_rec
                self.tau_a = self.tau_recorded
        if final is est:
            self.value = self.j0
        support, effects, gains = self.support, self.effects, self.gains
        value = self.value
        p1 = self.scorer_s.score(support)[0]
        lib_before, lib_after = _kept_terms(est), _kept_terms(final)
        effect_terms = {e.name for e in effects if e.kind == "conservative"}
        changes = {
            "removed": sorted(lib_before - lib_after),
            "added": sorted(lib_after - lib_before - effect_terms),
        }

        tau_recorded, Xf = self.tau_recorded, self.Xf
        tau_final = _adjusted_tau(self.tau_a, gains)
        residual_before = _residual(est, Xf, tau_recorded)
        residual_after = _residual(final, Xf, tau_final)
        # The scale a residual is compared with: the measured force, or the model's
        # force contributions where they are larger (an undriven coordinate).
        force_rms = _force_scale(est, self.Xt)
        if not self.passive:
            force_rms = np.maximum(force_rms, np.sqrt(np.mean(tau_recorded**2, axis=0)))
        steps = []
        if self.delay is not None:
            cand, estimate = self.delay
            v_without = self.scorer_rec.score(support)[0]
            steps.append(
                Step(
                    candidate=cand,
                    coefficient=1e3 * estimate.delay,
                    units=f"ms (+- {1e3 * estimate.std:.2g} ms)",
                    explained=float(1 - value**2 / v_without**2)
                    if np.isfinite(v_without) and v_without > 0
                    else 1.0,
                    fold_explained=[],
                    residual_rms=np.sqrt(np.mean(residual_after**2, axis=0)),
                    heldout_error=self.history[cand.name][1],
                    equation=final.equation(4),
                    ranking=pd.DataFrame(),
                    how="added",
                )
            )
        all_effects = list(effects) + [
            self.by_name[f"gain({coords[i]})"] for i in gains
        ]
        for e in all_effects:
            how, after = self.history.get(e.name, ("added", value))
            without = support - {index[e.name]}
            v_without = J(without)[0]
            explained = (
                float(1 - value**2 / v_without**2) if np.isfinite(v_without) else 1.0
            )
            steps.append(
                Step(
                    candidate=e,
                    coefficient=_effect_coefficient(final, e, gains),
                    units=_units(e, units, self.passive),
                    explained=explained,
                    fold_explained=[],
                    residual_rms=np.sqrt(np.mean(residual_after**2, axis=0)),
                    heldout_error=after,
                    equation=final.equation(4),
                    ranking=self.rankings[-1] if self.rankings else pd.DataFrame(),
                    how=how,
                )
            )
        boot = None
        if bootstrap is not None:
            boot = _bootstrap_final(
                final,
                Xf,
                tau_final,
                self.groups,
                self.segments,
                self.Xa.shape[0],
                int(bootstrap),
                random_state,
                self.verbose,
            )
            by_term = {t: k for k, t in enumerate(boot.terms)}
            for s in steps:
                k = by_term.get(
                    str(s.candidate.term)
                    if s.candidate.kind == "conservative"
                    else s.candidate.name
                )
                if k is not None and s.candidate.kind != "gain":
                    s.low, s.high = float(boot.low[k]), float(boot.high[k])
        fold_names = [
            f"fold {k + 1} ({sum(len(b) for b in self.folds[k])} samples)"
            for k in sorted(self.degenerate)
        ]
        return DiagnosisReport(
            initial=est,
            final=final,
            residual_rms_before=np.sqrt(np.mean(residual_before**2, axis=0)),
            residual_rms_after=np.sqrt(np.mean(residual_after**2, axis=0)),
            force_rms=force_rms,
            heldout_error_before=float(self.j0),
            heldout_error_after=float(value),
            pointwise_before=float(self.p0),
            pointwise_after=float(p1),
            criterion=self.criterion,
            steps=steps,
            rankings=self.rankings,
            coordinates=coords,
            passive=self.passive,
            lagrangian_changes=changes,
            degenerate_folds=fold_names,
            stop_reason=self.stop_reason,
            bootstrap=boot,
            settings={
                "n_splits": self.n_splits,
                "fold_kind": self.fold_kind,
                "min_explained": self.min_explained,
                "catalogue": tuple(self.catalogue),
                "eps": dict(self.eps),
                "window": self.win if self.stats_w is not None else None,
                "start_valid": self.start_valid,
                "swaps": self.swaps,
            },
            _data={
                "X": self.Xa,
                "tau": tau_recorded,
                "residual_before": residual_before,
                "residual_after": residual_after,
            },
        )


def _bootstrap_final(
    final, X, tau, groups, segments, n, n_resamples, random_state, verbose
):
    """:func:`lagsindy.bootstrap` of the final model's configuration.

    The groups are the trajectories (``groups``, else the segments diagnose found),
    so resamples never join pieces of different trajectories.
    """
    from ..uncertainty import bootstrap as _bootstrap

    if groups is None:
        groups = np.zeros(n, dtype=np.int64)
        for k, seg in enumerate(segments):
            groups[seg] = k
    if verbose:
        print(f"[lagsindy] bootstrap of the final model: {n_resamples} resamples")
    return _bootstrap(
        final,
        X,
        tau,
        groups=groups,
        n_resamples=n_resamples,
        random_state=random_state,
        verbose=max(0, verbose - 1),
    )
