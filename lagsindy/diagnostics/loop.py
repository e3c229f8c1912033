"""The steps of :func:`~lagsindy.diagnose`: delay, joint revision, swaps, additions.

:class:`Search` holds one diagnosis (the data's columns, folds and scorers, and the
current model); each step is a method that replaces the current model only by one
that predicts held-out data better. See :mod:`lagsindy.diagnostics` for the loop
and the criterion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from .._torch import to_tensor
from ..cases.forces import known_columns
from ..delay import diagnose_delay
from .catalogue import _DISSIPATIVE, _NONNEGATIVE, _catalogue, _effect_coefficient
from .joint_delay import diagnose_joint_delays
from .report import Candidate
from .scoring import (
    _adjusted_tau,
    _columns,
    _fit_model,
    _mass_definite,
    _mass_samples,
    _NoWindows,
    _start_coefficients,
    _Statistics,
    _support_in,
    _time_folds,
    _weighted_scorer,
)

__all__ = ["DiagnosisSettings", "Search"]

# Held-out residual below this fraction of the scale is rounding.
PRECISION = 1e-10


@dataclass(frozen=True)
class DiagnosisSettings:
    """The settings of one diagnosis (see :func:`~lagsindy.diagnose`'s parameters).

    ``eps`` is resolved (one Coulomb smoothing velocity per coordinate) and
    ``angles`` is the list of angular coordinates.
    """

    catalogue: tuple
    extra_terms: tuple
    angles: tuple
    eps: dict
    n_splits: int = 3
    window: int | None = None
    min_explained: float = 0.05
    min_improvement: float = 0.01
    verbose: int = 0
    units: tuple = ()


class Search:
    """One diagnosis: the data's columns, folds and scorers, and the current model.

    Each step of :func:`~lagsindy.diagnose` is a method that replaces the current
    model (``current``, its column ``support``, held-out ``value``, ``effects`` and
    ``gains``) only by one that predicts held-out data better.
    """

    def __init__(self, est, Xa, tau_a, groups, settings: DiagnosisSettings):
        st = settings
        catalogue, extra_terms, angles = st.catalogue, st.extra_terms, st.angles
        n_splits, window, verbose = st.n_splits, st.window, st.verbose
        min_explained, min_improvement = st.min_explained, st.min_improvement
        self.settings = settings
        self.est, self.Xa, self.groups, self.eps = est, Xa, groups, dict(st.eps)
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
        candidates = _catalogue(
            est,
            catalogue,
            list(extra_terms),
            list(angles),
            tau_a,
            self.eps,
            dict(st.units),
        )
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
        self.known = known_columns(est.library_)  # held at their value (robots)
        for name in getattr(est.library_, "nonnegative_", ()):  # rotor inertias
            self.nonneg[index[name]] = True

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
        self.tau_scored = None  # the input scored on, when not tau_a
        self.scorer_rec, self.scorer_s_rec = self.scorer, self.scorer_s
        # once accepted: [(Candidate, delay in s, its std)], one per joint delay
        self.delay = None
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
            self.known,
        )

    def support_of(self, model):
        return _support_in(self.index, model)

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
        return size**2 > PRECISION * self.total_ref

    def improves(self, jt, st, model, effs):
        """``model`` (support ``st``, held-out ``jt``) beats the current one."""
        return (
            jt < (1 - self.min_improvement) * self.value
            and self.valid(st)
            and self.nonneg_ok(model, effs)
        )

    # ------------------------------------------------------ step 0: input delay
    def _use_input(self, tau, scoring=None):
        """Refit on the input ``tau`` (the recorded one shifted) and score on
        ``scoring`` (default ``tau``; per-joint delays: each fold's rows shifted by
        the delays estimated without it)."""
        Xt = self.Xt
        self.tau_scored = scoring
        scoring = tau if scoring is None else scoring
        tau_sh = to_tensor(scoring, dtype=torch.float64, device="cpu")
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
        self.tau_a = tau

    def _use_recorded(self):
        self.scorer, self.scorer_s = self.scorer_rec, self.scorer_s_rec
        self.tau_a, self.tau_scored = self.tau_recorded, None

    def input_delay(self, per_joint=False):
        """Accept an input delay when the model refitted on the shifted input wins.

        ``per_joint``: one delay per driven input column (``"joint_delay"``,
        :mod:`.joint_delay`), each kept only when significant against its spread,
        and then only while setting it back to 0 worsens both held-out criteria
        (trajectory and pointwise) by ``min_improvement``; the delays together
        must improve both too."""
        est, verbose = self.est, self.verbose
        # The delay is estimated with the dissipative catalogue as candidates:
        # an input delay and missing damping both shift the phase of the force.
        joint_config = _fit_model(
            est, None, None, None, penalized=self.diss, eps=self.eps, fit=False
        )
        try:  # the joint revision's fit: the delay search's first fit too
            joint = self.fit_with([], {}, penalized=self.diss)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            joint = None  # the delay search fits (and fails) on its own
        args = (joint_config, self.Xf, self.tau_a, self.segments, float(self.dt))
        if per_joint:
            found = diagnose_joint_delays(
                *args,
                verbose,
                fitted_at_zero=joint,
                coordinates=self.coords,
                folds=self.folds,
            )
        else:
            found = diagnose_delay(*args, verbose, fitted_at_zero=joint)
        if found is None:
            return
        estimate, shifted, cross = found if per_joint else (*found, None)
        # What the dissipative candidates explain at delay 0: a delay must explain
        # more than they can (missing damping also shifts the force's phase, and a
        # delay then stands in for it).
        joint_value = self._joint_value(joint)
        kept = estimate.kept() if per_joint else None
        self._use_input(shifted, cross)
        trial, st, jt = self._delay_trial()
        if per_joint and trial is not None:
            kept, trial, st, jt = self._prune_joint_delays(kept, st, jt)
        wins = (
            trial is not None
            and jt < (1 - self.min_improvement) * self.value
            and self.valid(st)
            and (not per_joint or self._pointwise_better(st))
        )
        # (the joint fit on the shifted input only when the delay wins alone)
        damping_alone = (
            wins
            and joint_value is not None
            and not self._joint_value(None) < (1 - self.min_improvement) * joint_value
        )
        text = (
            ", ".join(
                f"{c} {1e3 * v:.1f} ms" for c, v in zip(self.coords, estimate.delays)
            )
            if per_joint
            else f"{1e3 * estimate.delay:.1f} ms"
        )
        if wins and not damping_alone:
            if per_joint:
                self.delay = [
                    (
                        Candidate("joint_delay", f"delay({c})", (c,), estimate),
                        float(kept[i]),
                        float(estimate.std[i]),
                    )
                    for i, c in enumerate(self.coords)
                    if kept[i] != 0
                ]
            else:
                driven = tuple(
                    c
                    for i, c in enumerate(self.coords)
                    if np.any(self.tau_recorded[:, i] != 0)
                )
                cand = Candidate("delay", "delay", driven, estimate)
                self.delay = [(cand, float(estimate.delay), float(estimate.std))]
            self.current, self.support, self.value = trial, st, jt
            for cand, _, _ in self.delay:
                self.history[cand.name] = ("added", jt)
            if verbose:
                print(f"[lagsindy] input delay {text}: held-out {jt:.4g}")
        else:
            if verbose:
                why = (
                    "the dissipative candidates explain as much without it"
                    if damping_alone
                    else f"held-out criterion {self.value:.4g} -> {jt:.4g}"
                )
                print(
                    f"[lagsindy] an input delay of {text} does not improve the "
                    f"prediction ({why})"
                )
            self._use_recorded()

    def _pointwise_better(self, st):
        """Whether the pointwise held-out criterion on the current input beats the
        recorded input's by ``min_improvement`` (per-joint delays must improve
        both criteria: a delay moves the force at every sample, while a fraction
        of a sample's shift of a noisy record improved the trajectory criterion
        alone, by 9 % on a delay-free arm, the pointwise one by 0.3 %)."""
        before = self.scorer_s_rec.score(self.support)[0]
        return self.scorer_s.score(st)[0] < (1 - self.min_improvement) * before

    def _delay_trial(self):
        """The model refitted on the current input: (model, support, held-out)."""
        try:
            trial = self.fit_with([], {})
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            return None, self.s0, np.inf
        st = self.support_of(trial)
        return trial, st, self.J(st)[0]

    def _prune_joint_delays(self, kept, st, jt):
        """Drop the joint delays whose removal does not worsen the held-out
        criterion by ``min_improvement`` (on the trial's support); refit when one
        was dropped. Returns the kept delays, the trial, its support and value."""
        shifted, cross = self.tau_a, self.tau_scored

        def without(columns):
            a, b = shifted.copy(), cross.copy()
            for i in columns:
                a[:, i] = b[:, i] = self.tau_recorded[:, i]
            return a, b

        drop = []
        p_with = self.scorer_s.score(st)[0]
        if np.count_nonzero(kept) > 1:
            for i in np.flatnonzero(kept):
                self._use_input(*without([i]))
                v, p = self.J(st)[0], self.scorer_s.score(st)[0]
                if not (
                    jt < (1 - self.min_improvement) * v
                    and p_with < (1 - self.min_improvement) * p
                ):
                    drop.append(i)
        kept = kept.copy()
        kept[drop] = 0.0
        if drop and self.verbose:
            print(
                "[lagsindy] per-joint delays that do not improve the held-out "
                f"criterion: {[self.coords[i] for i in drop]}"
            )
        if not drop:
            self._use_input(shifted, cross)
            return kept, self.fit_with([], {}), st, jt
        if not np.any(kept):
            self._use_input(shifted, cross)
            return kept, None, st, np.inf
        self._use_input(*without(drop))
        trial, st, jt = self._delay_trial()
        return kept, trial, st, jt

    def _joint_value(self, joint):
        """Held-out criterion, on the current input, of the joint fit with the
        dissipative candidates (``joint``: that fit already made; ``None``: fit it);
        ``None`` without dissipative candidates or when the fit fails."""
        if not self.diss:
            return None
        if joint is None:
            try:
                joint = self.fit_with([], {}, penalized=self.diss)
            except (ValueError, FloatingPointError, np.linalg.LinAlgError):
                return None
        return self.J(self.support_of(joint))[0]

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
            if min(self.value, self.scorer_s.score(self.support)[0]) ** 2 <= PRECISION:
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
