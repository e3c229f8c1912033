r"""Close the loop: find what a fitted Lagrangian leaves unexplained, and add it.

:func:`diagnose` takes a fitted :class:`~lagsindy.LagrangianSINDy` and data, computes
the residual of the Euler-Lagrange equations, and tests a catalogue of candidate
missing effects for how much of that residual each explains **on held-out
trajectories**: viscous damping, relative (joint) damping, quadratic drag and Coulomb
friction on every coordinate, a constant offset force, an input gain error (when
several coordinates are driven) and missing conservative terms (a spring ``q**2`` on
every coordinate, ``cos``/``sin`` of angles, or terms you pass). The best effect that
explains a significant share of the held-out residual is added, the model is refitted
(the Lagrangian's sparse search runs again, with the found effects kept as known,
unpenalised terms), and the search repeats until nothing significant is left.

How a candidate is scored. The data are split by trajectory into ``n_splits`` folds.
For every fold the Gram statistics of the current model's terms, all candidates and
the target are accumulated once (strong or weak form, as the estimator was fitted).
For a candidate ``j`` and fold ``f``, the current terms are refitted by least squares
with and without ``j`` on the other folds, and the residual sum of squares is
evaluated on fold ``f``; the *explained share* is ``1 - SSE(with j) / SSE(without)``.
A candidate is accepted when its mean share reaches ``min_explained``, it improves
every fold (so it does not just fit noise), and the refitted model predicts the
accelerations of held-out trajectories better than before; the best-scoring first.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import sympy as sp
import torch
from sklearn.base import clone
from sklearn.model_selection import GroupKFold
from sklearn.utils.validation import check_is_fitted

from ._expr import symbols_for
from ._torch import to_numpy, to_tensor
from .dissipation import DEFAULT_EPS, DissipationLibrary, ForceTerm, make_term
from .euler_lagrange import EulerLagrangeOperator, trajectory_segments
from .solvers import BalancedGram

DEFAULT_CATALOGUE = (
    "viscous",
    "relative",
    "drag",
    "coulomb",
    "bias",
    "gain",
    "conservative",
)
_DISSIPATIVE = ("viscous", "relative", "drag", "coulomb", "bias")
# Held-out residual below this fraction of the target's sum of squares is rounding
# (the Gram-matrix arithmetic of the scores cannot resolve less).
_PRECISION = 1e-10
_KIND_TEXT = {
    "viscous": "viscous damping",
    "relative": "relative (joint) damping",
    "drag": "quadratic drag",
    "coulomb": "Coulomb friction",
    "bias": "constant offset force",
    "gain": "input gain error",
    "conservative": "missing conservative term",
}


@dataclass
class Candidate:
    """A candidate missing effect (see :func:`diagnose`)."""

    kind: str
    name: str
    coordinates: tuple
    term: object  # ForceTerm, sympy.Expr (conservative) or int (gain: coordinate index)

    @property
    def description(self) -> str:
        return _KIND_TEXT.get(self.kind, self.kind)


@dataclass
class Step:
    """One accepted effect and the model after adding it."""

    candidate: Candidate
    coefficient: float
    units: str
    explained: float
    fold_explained: list
    residual_rms: np.ndarray
    heldout_error: float
    equation: str
    ranking: pd.DataFrame


@dataclass
class DiagnosisReport:
    """What :func:`diagnose` found.

    Attributes
    ----------
    initial : LagrangianSINDy
        The model that was diagnosed (unchanged).
    final : LagrangianSINDy
        The model refitted with every effect found.
    residual_rms_before : ndarray of shape (n_dof,)
        RMS of the Euler-Lagrange (force) residual per coordinate, before.
    force_rms : ndarray of shape (n_dof,)
        RMS of the generalized forces the model explains (the scale of the residual).
    heldout_error_before : float
        Held-out relative RMS error of predicted accelerations, before.
    steps : list of Step
        Effects in the order they were added, each with its coefficient and units,
        held-out explained share, the residual and the held-out error after it.
    rankings : list of DataFrame
        The candidates' scores in every round (the last round found nothing
        significant, unless ``max_effects`` was reached).
    coordinates : list of str
    passive : bool
        Passive data fix the model only up to scale: coefficients are relative to the
        fixed term (whose coefficient is 1).
    """

    initial: object
    final: object
    residual_rms_before: np.ndarray
    force_rms: np.ndarray
    heldout_error_before: float
    steps: list
    rankings: list
    coordinates: list
    passive: bool
    settings: dict = field(default_factory=dict)
    _data: dict = field(default_factory=dict, repr=False)

    @property
    def effects(self) -> list:
        """Names of the effects found, in order."""
        return [s.candidate.name for s in self.steps]

    def to_frame(self) -> pd.DataFrame:
        """One row per step: effect, coefficient, units, shares, residual, error."""
        rows = []
        for k, s in enumerate(self.steps, 1):
            rows.append(
                {
                    "step": k,
                    "effect": s.candidate.description,
                    "term": s.candidate.name,
                    "coordinates": ",".join(s.candidate.coordinates),
                    "coefficient": s.coefficient,
                    "units": s.units,
                    "explained": s.explained,
                    "residual_rms": float(np.sqrt(np.mean(s.residual_rms**2))),
                    "heldout_error": s.heldout_error,
                }
            )
        return pd.DataFrame(rows)

    def __str__(self) -> str:
        lines = []
        scale = (
            "  (passive data: coefficients relative to the fixed term)"
            if self.passive
            else ""
        )
        lines.append(
            f"Residual diagnosis over {self.settings.get('n_splits')} held-out folds of "
            f"trajectories{scale}"
        )
        rel = self.residual_rms_before / np.maximum(self.force_rms, 1e-300)
        per = ", ".join(
            f"{c}: {r:.3g} ({p:.2%} of the model's forces)"
            for c, r, p in zip(self.coordinates, self.residual_rms_before, rel)
        )
        lines.append(f"before: residual RMS {per}")
        lines.append(
            f"        held-out acceleration error {self.heldout_error_before:.3g} (relative RMS)"
        )
        if not self.steps:
            lines.append(
                "no candidate explains a significant share of the held-out residual"
            )
        else:
            head = (
                f"{'step':>4}  {'effect':<26} {'term':<24} {'coefficient':>13} "
                f"{'units':<14} {'explained':>9}  {'residual RMS':>12}  {'held-out error':>14}"
            )
            lines.append(head)
            lines.append("-" * len(head))
            previous = self.heldout_error_before
            for k, s in enumerate(self.steps, 1):
                gain = previous / s.heldout_error if s.heldout_error > 0 else np.inf
                lines.append(
                    f"{k:>4}  {s.candidate.description:<26} {s.candidate.name:<24} "
                    f"{s.coefficient:>13.5g} {s.units:<14} {s.explained:>9.1%}  "
                    f"{float(np.sqrt(np.mean(s.residual_rms**2))):>12.3g}  "
                    f"{s.heldout_error:>8.3g} (x{gain:.3g})"
                )
                previous = s.heldout_error
        last = self.rankings[-1] if self.rankings else None
        if last is not None and "rejected" in last.attrs:
            name, before, after = last.attrs["rejected"]
            lines.append(
                f"stopped: {name} explains part of the residual but does not improve "
                f"held-out predictions ({before:.3g} -> {after:.3g})"
            )
        elif last is not None and not len(last):
            lines.append("stopped: the remaining residual is at rounding level")
        elif last is not None and (
            not self.steps or len(self.rankings) > len(self.steps)
        ):
            top = last.iloc[0]
            lines.append(
                f"stopped: the best remaining candidate, {top['term']}, explains "
                f"{top['explained']:.2%} of the held-out residual "
                f"(needs {self.settings.get('min_explained'):.0%} and every fold better)"
            )
        lines.append("final model:")
        lines.extend("  " + line for line in self.final.equation(4).splitlines())
        return "\n".join(lines)

    def plot(self, path=None):
        """Residual against the identified variable of each effect, before and after.

        Parameters
        ----------
        path : str or path-like, optional
            Save the figure as PNG there.

        Returns
        -------
        matplotlib.figure.Figure
        """
        try:
            import matplotlib

            if path is not None:
                matplotlib.use("Agg", force=False)
            import matplotlib.pyplot as plt
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError(
                "plotting needs matplotlib: pip install 'lagsindy[plot]'"
            ) from exc
        X = self._data["X"]
        n = len(self.coordinates)
        before = self._data["residual_before"]
        # Nothing found: one panel per coordinate, its residual against its velocity.
        panels = self.steps or [(None, i) for i in range(n)]
        fig, axes = plt.subplots(
            1, len(panels), figsize=(4.5 * len(panels), 3.6), squeeze=False
        )
        rng = np.random.default_rng(0)
        idx = rng.choice(X.shape[0], size=min(X.shape[0], 4000), replace=False)
        for ax, step in zip(axes[0], panels):
            if isinstance(step, tuple):
                step, i = step
                var, label = X[:, n + i], f"{self.coordinates[i]}_dot"
                after = None
            else:
                cand = step.candidate
                i = self.coordinates.index(cand.coordinates[0])
                after = self._data["residuals"][self.steps.index(step)]
                if cand.kind == "relative":
                    j = self.coordinates.index(cand.coordinates[1])
                    var = X[:, n + i] - X[:, n + j]
                    label = f"{cand.coordinates[0]}_dot - {cand.coordinates[1]}_dot"
                elif cand.kind == "conservative":
                    var, label = X[:, i], cand.coordinates[0]
                elif cand.kind == "gain":
                    var, label = self._data["tau"][:, i], f"tau_{cand.coordinates[0]}"
                else:
                    var, label = X[:, n + i], f"{cand.coordinates[0]}_dot"
            ax.scatter(var[idx], before[idx, i], s=2, alpha=0.4, label="before")
            if after is not None:
                ax.scatter(var[idx], after[idx, i], s=2, alpha=0.4, label="after")
            ax.set_xlabel(label)
            ax.set_ylabel(f"residual on {self.coordinates[i]}")
            ax.set_title(step.candidate.name if step is not None else "residual")
            ax.legend(markerscale=4)
        fig.tight_layout()
        if path is not None:
            fig.savefig(path, dpi=120)
        return fig


# ----------------------------------------------------------------------------- helpers
def _units(est, cand, angles, passive):
    if passive:
        return "rel. to fixed"
    unit = {
        c: (("rad", "N*m") if c in angles else ("m", "N")) for c in est.coordinates_
    }
    if cand.kind == "gain":
        return "(factor - 1)"
    if cand.kind == "conservative":
        return (
            "J"
            if not any(str(s).endswith("_dot") for s in cand.term.free_symbols)
            else "J*..."
        )
    return cand.term.units(unit)


def _catalogue(est, kinds, extra_terms, angles, tau, eps):
    """Candidate effects not already in the model."""
    coords = est.coordinates_
    present_forces = {
        t.name for t, d in zip(est.dissipation_terms_, est.dissipation_coef_) if d != 0
    }
    present_terms = {str(t) for t, c in zip(est.library_.terms_, est.coef_) if c != 0}
    out = []
    for kind in kinds:
        if kind in _DISSIPATIVE:
            targets = (
                [tuple(p) for p in _pairs(coords)]
                if kind == "relative"
                else [(c,) for c in coords]
            )
            for tgt in targets:
                term = make_term(
                    kind, tgt if kind == "relative" else tgt[0], coords, eps=eps
                )
                if term.name not in present_forces:
                    out.append(Candidate(kind, term.name, tgt, term))
        elif kind == "gain":
            if tau is None:
                continue
            driven = [i for i in range(len(coords)) if np.any(tau[:, i] != 0)]
            if len(driven) < 2:
                continue  # one input: a gain error is the Lagrangian's own scale
            for i in driven:
                out.append(Candidate("gain", f"gain({coords[i]})", (coords[i],), i))
        elif kind == "conservative":
            q, _, _ = symbols_for(coords)
            terms = []
            for c, s in zip(coords, q):
                terms.append(s**2)
                if c in angles:
                    terms += [sp.cos(s), sp.sin(s)]
            from ._expr import canonical

            terms += [canonical(t, coords) for t in (extra_terms or [])]
            for t in terms:
                if str(t) not in present_terms:
                    names = tuple(sorted({str(s) for s in t.free_symbols}))
                    own = tuple(c for c in coords if c in names or f"{c}_dot" in names)
                    out.append(
                        Candidate("conservative", str(t), own or (coords[0],), t)
                    )
        else:
            raise ValueError(
                f"unknown candidate kind {kind!r}; use some of {DEFAULT_CATALOGUE}"
            )
    return out


def _pairs(coords):
    return [(a, b) for k, a in enumerate(coords) for b in coords[k + 1 :]]


def _folds(n, groups, n_splits):
    if groups is None:
        # No trajectory labels: contiguous blocks keep neighbouring samples together.
        groups = np.repeat(np.arange(4 * n_splits), int(np.ceil(n / (4 * n_splits))))[
            :n
        ]
    groups = np.asarray(groups)
    if len(np.unique(groups)) < n_splits:
        raise ValueError(
            f"need at least n_splits={n_splits} trajectories (groups) to hold some out, "
            f"got {len(np.unique(groups))}"
        )
    return [test for _, test in GroupKFold(n_splits).split(np.zeros(n), groups=groups)]


class _Problem:
    """Per-fold Gram statistics of the current terms, the candidates and the target."""

    def __init__(self, est, Xt, tau_t, groups, folds, candidates):
        self.est = est
        lib_terms = [t for t, c in zip(est.library_.terms_, est.coef_) if c != 0]
        base_forces = [
            t for t, d in zip(est.dissipation_terms_, est.dissipation_coef_) if d != 0
        ]
        cons = [c for c in candidates if c.kind == "conservative"]
        diss = [c for c in candidates if c.kind in _DISSIPATIVE]
        gain = [c for c in candidates if c.kind == "gain"]
        terms = lib_terms + [c.term for c in cons]
        forces = [t.forces for t in base_forces] + [c.term.forces for c in diss]
        op = EulerLagrangeOperator(
            est.coordinates_, terms, forces=forces, dtype=Xt.dtype, device=Xt.device
        )
        # Column layout of A: [lib terms | conservative cands | base forces | diss cands
        #                      | gain cands | target]
        n_l, n_c, n_b, n_d = len(lib_terms), len(cons), len(base_forces), len(diss)
        self.base = list(range(n_l)) + list(range(n_l + n_c, n_l + n_c + n_b))
        self.cand_index = {}
        for k, c in enumerate(cons):
            self.cand_index[c.name] = n_l + k
        for k, c in enumerate(diss):
            self.cand_index[c.name] = n_l + n_c + n_b + k
        for k, c in enumerate(gain):
            self.cand_index[c.name] = n_l + n_c + n_b + n_d + k
        d = est.n_dof_
        extra = None
        if gain:
            extra = Xt.new_zeros((Xt.shape[0], d, len(gain)))
            for k, c in enumerate(gain):
                extra[:, c.term, k] = -tau_t[:, c.term]
        self.width = op.n_columns + len(gain)
        self.passive = tau_t is None
        fixed = est.fixed_term_
        if self.passive:
            if fixed is None:  # case II: the largest scaled term sets the scale
                big = int(np.argmax(np.abs(np.asarray(est.coef_)[est.coef_ != 0])))
                self.fixed_col = big
            else:
                self.fixed_col = [str(t) for t in lib_terms].index(fixed)
            self.base.remove(self.fixed_col)
        grams, noises = [], []
        for rows in folds:
            rows_t = torch.as_tensor(rows, device=Xt.device)
            sub_x = Xt[rows_t]
            sub_tau = None if tau_t is None else tau_t[rows_t]
            sub_extra = None if extra is None else extra[rows_t]
            if est.formulation == "weak":
                segs = trajectory_segments(
                    sub_x, d, None if groups is None else groups[rows], dt=est.dt_
                )
                segs = [s for s in segs if len(s) >= est.window]
                cov = (
                    None
                    if est.noise_cov_ is None
                    else to_tensor(est.noise_cov_, dtype=Xt.dtype, device=Xt.device)
                )
                g, noise, _ = op.weak_gram(
                    sub_x,
                    sub_tau,
                    segs,
                    window=int(est.window),
                    stride=max(1, int(est.window) // 4),
                    dt=est.dt_,
                    noise_cov=cov,
                    extra=sub_extra,
                    return_noise=True,
                )
            else:
                g = op.gram(sub_x, sub_tau, extra=sub_extra)
                noise = torch.zeros_like(g)
            grams.append(g)
            noises.append(noise)
        total = sum(grams)
        self.target = None if self.passive else self.width
        n_feat = self.width
        scaler = BalancedGram(total, 1, n_feat, normalize=True)
        w = 1.0 / scaler.row_scale**2
        scale = torch.ones(total.shape[1], dtype=total.dtype, device=total.device)
        scale[:n_feat] = torch.where(
            scaler.col_scale > 0, scaler.col_scale, torch.ones_like(scaler.col_scale)
        )

        def combine(g):
            return to_numpy(
                (g * w[:, None, None]).sum(0) / (scale[:, None] * scale[None, :])
            )

        # Coefficients are fitted on noise-corrected statistics (unbiased), held-out
        # errors measured on the raw ones (the error the data really show).
        self.grams = [combine(g) for g in grams]
        self.fit_grams = [combine(g - nz) for g, nz in zip(grams, noises)]
        self.scale = to_numpy(scale)

    def heldout(self, features):
        """Per-fold held-out SSE and the all-data LS coefficients (scaled) of ``features``."""
        # Case I: tau ~ A c. Passive: -A[:, fixed] ~ A c (the fixed term's coefficient is 1).
        t = self.fixed_col if self.passive else self.target
        sign = -1.0 if self.passive else 1.0
        f = list(features)
        sse = []
        for k, test in enumerate(self.grams):
            train = sum(g for j, g in enumerate(self.fit_grams) if j != k)
            coef = _lstsq(train[np.ix_(f, f)], sign * train[f, t])
            yy = test[t, t]
            b = sign * test[f, t]
            sse.append(max(yy - 2 * coef @ b + coef @ test[np.ix_(f, f)] @ coef, 0.0))
        full = sum(self.fit_grams)
        coef = _lstsq(full[np.ix_(f, f)], sign * full[f, t])
        return np.array(sse), coef


def _lstsq(g, b):
    evals, evecs = np.linalg.eigh((g + g.T) / 2)
    keep = evals > 1e-12 * max(evals[-1], 1e-300)
    inv = np.where(keep, 1.0 / np.where(keep, evals, 1.0), 0.0)
    return evecs @ (inv * (evecs.T @ b))


def _score(problem, candidates):
    base_sse, _ = problem.heldout(problem.base)
    t = problem.fixed_col if problem.passive else problem.target
    total = sum(g[t, t] for g in problem.grams)
    if base_sse.sum() <= _PRECISION * total:
        # The model already explains the data to rounding: nothing left to attribute.
        return pd.DataFrame(
            columns=["kind", "term", "explained", "worst_fold", "coefficient"]
        ), base_sse
    rows = []
    for cand in candidates:
        j = problem.cand_index[cand.name]
        sse, coef = problem.heldout(problem.base + [j])
        share = 1.0 - sse / np.maximum(base_sse, 1e-300)
        raw = coef[-1] / problem.scale[j]
        if problem.passive:
            raw = raw * problem.scale[problem.fixed_col]
        rows.append(
            {
                "kind": cand.kind,
                "term": cand.name,
                "explained": float(np.mean(share)),
                "worst_fold": float(np.min(share)),
                "coefficient": float(raw),
            }
        )
    table = pd.DataFrame(rows)
    if len(table):
        table = table.sort_values(
            "explained", ascending=False, kind="stable"
        ).reset_index(drop=True)
    return table, base_sse


def _refit(est, effects, X, tau, groups):
    """Refit ``est``'s configuration with the effects added as known terms."""
    new = clone(est)
    unpenalized = list(est.unpenalized or [])
    library = clone(est.library_)
    cons = [c for c in effects if c.kind == "conservative"]
    if cons:
        library.set_params(terms=list(library.terms or []) + [c.term for c in cons])
        unpenalized += [str(c.term) for c in cons]
    diss = [c for c in effects if c.kind in _DISSIPATIVE]
    if diss:
        base = est.dissipation
        if base is None:
            dlib = DissipationLibrary(
                kinds=(), coordinates=est.coordinates_, eps=_eps(diss)
            )
        else:
            dlib = clone(base)
        specs = list(dlib.terms or [])
        for c in diss:
            spec = (c.kind, c.coordinates if c.kind == "relative" else c.coordinates[0])
            specs.append(spec)
        dlib.set_params(terms=specs)
        new.set_params(dissipation=dlib)
        unpenalized += [c.name for c in diss]
    new.set_params(library=library, unpenalized=unpenalized or None)
    if est.case_ == "fixed":
        new.set_params(fixed_term=_normalization(est))
    new.set_params(verbose=0)  # refits are quiet; the result keeps est's verbose
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        new.fit(X, tau, groups=groups)
    return new.set_params(verbose=est.verbose)


def _normalization(est):
    """The case III scale the fitted estimator chose, to keep it in refits."""
    return "mass" if getattr(est, "normalization_", None) == "mass" else est.fixed_term_


def _eps(cands):
    for c in cands:
        if c.kind == "coulomb":
            return _coulomb_eps(c.term)
    return DEFAULT_EPS


def _coulomb_eps(term: ForceTerm) -> float:
    """The smoothing velocity of a Coulomb term, read off its tanh(qdot / eps)."""
    expr = [f for f in term.forces if f != 0][0]
    tanh = next(iter(expr.atoms(sp.tanh)))
    coeff = tanh.args[0].as_coeff_Mul()[0]
    return float(1.0 / coeff)


def _adjusted_tau(tau, gains):
    if tau is None or not gains:
        return tau
    out = tau.copy()
    for i, gamma in gains.items():
        out[:, i] = out[:, i] * (1.0 + gamma)
    return out


def _heldout_error(est, X, tau, groups, folds):
    """Held-out relative RMS error of predicted accelerations (refit per fold)."""
    n = est.n_dof_
    num = den = 0.0
    for test in folds:
        train = np.setdiff1d(np.arange(len(X)), test)
        model = clone(est).set_params(verbose=0)  # no stage lines per fold
        if est.case_ == "fixed":
            model.set_params(fixed_term=_normalization(est))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model.fit(
                _take(X, train),
                None if tau is None else tau[train],
                groups=None if groups is None else groups[train],
            )
            pred = model.predict_acceleration(
                _take(X, test), None if tau is None else tau[test]
            )
        true = np.asarray(X)[test, 2 * n : 3 * n]
        num += float(np.sum((np.asarray(pred) - true) ** 2))
        den += float(np.sum((true - true.mean(axis=0)) ** 2))
    return float(np.sqrt(num / max(den, 1e-300)))


def _force_scale(est, Xt):
    """Per-coordinate RMS of the summed magnitudes of the model's force contributions."""
    coef = est._all_coef()
    support = np.flatnonzero(coef)
    if support.size == 0:
        return np.ones(est.n_dof_)
    cols = est._feature_operator(support, Xt.device, Xt.dtype).columns(Xt)
    size = (cols.abs() * torch.as_tensor(np.abs(coef[support]), dtype=Xt.dtype)).sum(2)
    return np.sqrt(np.mean(to_numpy(size) ** 2, axis=0))


def _take(X, rows):
    return X.iloc[rows] if isinstance(X, pd.DataFrame) else X[rows]


def _residual(est, X, tau):
    """Euler-Lagrange (force) residual per sample: tau - Theta c (or -Theta c)."""
    pred = np.asarray(est.predict(X), dtype=float).reshape(len(X), -1)
    return (np.zeros_like(pred) if tau is None else tau) - pred


# ----------------------------------------------------------------------------- API
def diagnose(
    est,
    X,
    tau=None,
    groups=None,
    *,
    catalogue=DEFAULT_CATALOGUE,
    extra_terms=None,
    angles=None,
    n_splits: int = 3,
    min_explained: float = 0.02,
    max_effects: int = 3,
    min_improvement: float = 1e-3,
    eps: float = DEFAULT_EPS,
    verbose: int = 0,
) -> DiagnosisReport:
    """Find the missing effects a fitted model leaves in its residual, add and refit.

    Parameters
    ----------
    est : LagrangianSINDy
        A fitted estimator (not modified).
    X : array-like or DataFrame of shape (n_samples, 3 * n_dof)
        Data in the estimator's layout (the data it was fitted on, or new data).
    tau : array-like of shape (n_samples, n_dof), default=None
        Generalized forces; ``None`` for passive data (the model's scale is then set by
        its fixed term).
    groups : array-like of shape (n_samples,), default=None
        Trajectory labels; folds hold out whole trajectories. Without them, the rows
        are cut into contiguous blocks.
    catalogue : sequence of str, default=all kinds
        Candidate kinds: ``"viscous"``, ``"relative"``, ``"drag"``, ``"coulomb"``,
        ``"bias"``, ``"gain"``, ``"conservative"``.
    extra_terms : list of str or sympy.Expr, default=None
        More conservative candidates (Lagrangian terms), beside ``q**2`` for every
        coordinate and ``cos``/``sin`` of angles.
    angles : list of str, default=None
        Angular coordinates (for candidates and units); default: the library's
        ``angles``.
    n_splits : int, default=3
        Folds of trajectories for the held-out scores.
    min_explained : float, default=0.02
        Smallest mean held-out share of the residual an effect must explain (and it
        must improve every fold).
    max_effects : int, default=3
    min_improvement : float, default=1e-3
        An effect is kept only if the refitted model also predicts the accelerations
        of held-out trajectories better, by at least this fraction.
    eps : float, default=0.01
        Smoothing velocity of Coulomb candidates.
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
    >>> est = LagrangianSINDy(system.paper_library()).fit(data.X, data.tau)
    >>> report = diagnose(est, data.X, data.tau, groups=data.groups)
    >>> report.effects
    ['viscous(theta)']
    >>> round(report.steps[0].coefficient, 3)
    0.2
    """
    check_is_fitted(est)
    Xa, _, _ = est._check_X(X, reset=False, coordinates=est.coordinates_)
    tau_a = None if tau is None else est._check_tau(tau, Xa.shape[0], est.n_dof_)
    if (tau_a is None) != (est.case_ != "forces"):
        raise ValueError(
            "diagnose the model with the kind of data it was fitted on: tau for a model "
            "fitted with tau (case I), no tau for a passive model"
        )
    if not 0 < min_explained < 1:
        raise ValueError(f"min_explained must be in (0, 1), got {min_explained}")
    if groups is not None:
        groups = np.asarray(groups)
        if groups.shape != (Xa.shape[0],):
            raise ValueError(
                f"groups must have one label per row of X ({Xa.shape[0]}), got {groups.shape}"
            )
    lib_angles = getattr(est.library_, "angles", None)
    if angles is None:
        angles = est.coordinates_ if lib_angles == "all" else list(lib_angles or [])
    folds = _folds(Xa.shape[0], groups, n_splits)
    Xt = to_tensor(Xa, dtype=torch.float64, device="cpu")
    # Refits and predictions see X as the estimator was fitted on it (named columns
    # for a DataFrame-fitted model), so scikit-learn's feature-name checks hold.
    names = getattr(est, "feature_names_in_", None)
    Xf = Xa if names is None else pd.DataFrame(Xa, columns=list(names))
    passive = tau_a is None

    before_residual = _residual(est, Xf, tau_a)
    force_scale = _force_scale(est, Xt)
    before_err = _heldout_error(est, Xf, tau_a, groups, folds)
    if verbose:
        print(f"[lagsindy] before: held-out acceleration error {before_err:.3g}")

    current, effects, steps, rankings, residuals = est, [], [], [], []
    gains = {}
    for _ in range(max_effects):
        candidates = _catalogue(current, catalogue, extra_terms, angles, tau_a, eps)
        candidates = [c for c in candidates if c.name not in {e.name for e in effects}]
        if not candidates:
            break
        tau_now = _adjusted_tau(tau_a, gains)
        tau_t = (
            None
            if tau_now is None
            else to_tensor(tau_now, dtype=Xt.dtype, device=Xt.device)
        )
        problem = _Problem(current, Xt, tau_t, groups, folds, candidates)
        table, _ = _score(problem, candidates)
        rankings.append(table)
        if verbose:
            print(table.head(5).to_string())
        if not len(table):
            if verbose:
                print(
                    "[lagsindy] the residual is at rounding level: nothing left to explain"
                )
            break
        top = table.iloc[0]
        if top["explained"] < min_explained or top["worst_fold"] <= 0:
            break
        best = next(c for c in candidates if c.name == top["term"])
        trial_gains, trial_effects = dict(gains), list(effects)
        if best.kind == "gain":
            trial_gains[best.term] = trial_gains.get(best.term, 0.0) + float(
                top["coefficient"]
            )
        else:
            trial_effects.append(best)
        tau_now = _adjusted_tau(tau_a, trial_gains)
        trial = _refit(est, trial_effects, Xf, tau_now, groups)
        err = _heldout_error(trial, Xf, tau_now, groups, folds)
        previous = steps[-1].heldout_error if steps else before_err
        if not err < (1 - min_improvement) * previous:
            # It explains residual but does not predict held-out motion better: noise.
            rejected = top["term"]
            if verbose:
                print(
                    f"[lagsindy] {rejected} does not improve held-out predictions "
                    f"({previous:.3g} -> {err:.3g}): stop"
                )
            table.attrs["rejected"] = (rejected, previous, err)
            break
        current, gains, effects = trial, trial_gains, trial_effects
        coefficient = _effect_coefficient(current, best, gains)
        residual = _residual(current, Xf, tau_now)
        residuals.append(residual)
        steps.append(
            Step(
                candidate=best,
                coefficient=coefficient,
                units=_units(current, best, angles, passive),
                explained=float(top["explained"]),
                fold_explained=[],
                residual_rms=np.sqrt(np.mean(residual**2, axis=0)),
                heldout_error=err,
                equation=current.equation(4),
                ranking=table,
            )
        )
        if verbose:
            print(
                f"[lagsindy] added {best.name}: coefficient {coefficient:.5g}, "
                f"held-out error {err:.3g}"
            )
    return DiagnosisReport(
        initial=est,
        final=current,
        residual_rms_before=np.sqrt(np.mean(before_residual**2, axis=0)),
        force_rms=force_scale,
        heldout_error_before=before_err,
        steps=steps,
        rankings=rankings,
        coordinates=list(est.coordinates_),
        passive=passive,
        settings={
            "n_splits": n_splits,
            "min_explained": min_explained,
            "catalogue": tuple(catalogue),
        },
        _data={
            "X": Xa,
            "tau": tau_a,
            "residual_before": before_residual,
            "residuals": residuals,
        },
    )


def _effect_coefficient(est, cand, gains):
    if cand.kind == "gain":
        return float(gains[cand.term])
    if cand.kind == "conservative":
        names = [str(t) for t in est.library_.terms_]
        return (
            float(est.coef_[names.index(str(cand.term))])
            if str(cand.term) in names
            else 0.0
        )
    for t, d in zip(est.dissipation_terms_, est.dissipation_coef_):
        if t.name == cand.name:
            return float(d)
    return 0.0
