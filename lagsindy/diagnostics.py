r"""Close the loop: find what a fitted Lagrangian leaves unexplained, and add it.

:func:`diagnose` takes a fitted :class:`~lagsindy.LagrangianSINDy` and data and looks
for missing effects in a catalogue: viscous damping, relative (joint) damping,
quadratic drag and Coulomb friction on every coordinate, a constant offset force, an
input gain error (when several coordinates are driven) and missing conservative terms
(a spring ``q**2`` on every coordinate, ``cos``/``sin`` of angles, or terms you pass)
and, for forced data, a delay between the recorded input and the positions.

The loop
--------
1. **Revise the Lagrangian jointly with the effects.** A conservative fit of damped
   data absorbs the damping into wrong Lagrangian terms; adding effects on top of it
   cannot undo that. So the sparse search is first run again over the Lagrangian
   library *and* the dissipative catalogue together; the dissipative terms it keeps
   are pruned one by one while removing them does not worsen the held-out criterion,
   and the Lagrangian's sparse search is run once more with the survivors as known
   (unpenalized) terms.
2. **Add effects one at a time.** The remaining candidates are ranked by how much of
   the held-out criterion they explain when added to the current support (least
   squares refit on the other folds); the best is kept only if it improves every
   fold and, after the Lagrangian's sparse search is rerun with it, the new model
   improves the held-out criterion by at least ``min_improvement``.
   Then each accepted dissipative effect is tried against the other candidates of
   the same coordinates (a swap, e.g. quadratic drag for viscous damping), and a
   swap is kept when the refitted model improves the held-out criterion by
   ``min_improvement``.
3. **Never make things worse.** The final model is compared with the starting one on
   the same held-out criterion; if it is not better, the starting model is kept.

The criterion: held-out trajectory prediction
---------------------------------------------
Small damping changes trajectories over seconds but is a tiny share of the
pointwise acceleration residual, where differentiation noise dominates. The
criterion is therefore the **integrated (weak-form) residual**: the Euler-Lagrange
equations integrated against smooth bump functions over windows of the held-out
trajectories (integration by parts removes the accelerations; see
:meth:`lagsindy.euler_lagrange.EulerLagrangeOperator.weak_gram`). Each model's
coefficients are refitted by least squares on the other folds (with the weak form's
noise correction), and the residual of the held-out fold is measured. Damping and
Coulomb coefficients are kept non-negative in these refits (active-set least
squares). The pointwise (strong-form) criterion is computed the same way and
reported beside it. When the rows are not time-ordered trajectories long enough for
the windows, the pointwise criterion is used (the report says so).

Every coordinate counts: each equation is weighted by the inverse energy of the
starting model's force contributions on that coordinate (the sum of the magnitudes
of its terms, or the measured force when larger), not by its residual or its
measured force alone, so an undriven coordinate whose forces nearly cancel does
not drown the others, nor is it drowned.

Folds are whole trajectories (``groups``); with fewer trajectories than
``n_splits`` each trajectory is cut into ``n_splits`` contiguous time blocks. A fold
whose refit has a singular or indefinite mass matrix on its held-out samples cannot
predict accelerations there; it is excluded from that model's score and listed in
the report. A model whose full-data mass matrix is singular or indefinite is never
accepted.
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

from ._expr import canonical, symbols_for
from ._torch import to_numpy, to_tensor
from ._validation import validate_state, validate_tau
from .dissipation import DEFAULT_EPS, DissipationLibrary, make_term
from .euler_lagrange import (
    EulerLagrangeOperator,
    estimate_noise_covariance,
    estimate_sampling_interval,
    trajectory_segments,
)

DEFAULT_CATALOGUE = (
    "delay",
    "viscous",
    "relative",
    "drag",
    "coulomb",
    "bias",
    "gain",
    "conservative",
)
_DISSIPATIVE = ("viscous", "relative", "drag", "coulomb", "bias")
# Kinds whose coefficient must be non-negative (they only remove energy).
_NONNEGATIVE = ("viscous", "relative", "drag", "coulomb")
# Held-out residual below this fraction of the scale is rounding.
_PRECISION = 1e-10
# A refit whose mass matrix is singular or indefinite at more than this fraction of
# the checked samples cannot predict accelerations: the fold (or model) is degenerate.
_MASS_BAD_FRACTION = 0.01
# Samples per fold at which mass matrices are checked.
_MASS_ROWS = 150
# Samples for the noise correction of each fold's weak statistics.
_NOISE_ROWS = 4000
# Coulomb smoothing velocity, relative to the 99th percentile of |q_dot|.
_EPS_FRACTION = 0.01
_KIND_TEXT = {
    "viscous": "viscous damping",
    "relative": "relative (joint) damping",
    "drag": "quadratic drag",
    "coulomb": "Coulomb friction",
    "bias": "constant offset force",
    "gain": "input gain error",
    "conservative": "missing conservative term",
    "delay": "input delay",
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
    """One effect of the final model.

    Attributes
    ----------
    candidate : Candidate
    coefficient : float
        Its coefficient in the **final** model.
    units : str
    explained : float
        Share of the final model's held-out criterion (squared) that removing this
        effect would add back: ``1 - J(final)**2 / J(final without it)**2``.
    heldout_error : float
        Held-out criterion of the model right after this effect was accepted.
    how : str
        ``"joint"`` (kept by the joint sparse search of step 1), ``"added"``, or
        ``"swapped"`` (replaced another effect of the same coordinates, step 2b).
    """

    candidate: Candidate
    coefficient: float
    units: str
    explained: float
    fold_explained: list
    residual_rms: np.ndarray
    heldout_error: float
    equation: str
    ranking: pd.DataFrame
    how: str = "added"
    coefficient_when_added: float = float("nan")
    low: float = float("nan")
    high: float = float("nan")


@dataclass
class DiagnosisReport:
    """What :func:`diagnose` found.

    Attributes
    ----------
    initial : LagrangianSINDy
        The model that was diagnosed (unchanged).
    final : LagrangianSINDy
        The model refitted with every effect found (``initial`` itself when nothing
        improved the held-out criterion).
    residual_rms_before, residual_rms_after : ndarray of shape (n_dof,)
        RMS of the Euler-Lagrange (force) residual per coordinate, on all the data.
    force_rms : ndarray of shape (n_dof,)
        The scale the residual is compared with: the RMS of the measured force on each
        coordinate (forced data), else of the model's force contributions.
    heldout_error_before, heldout_error_after : float
        The held-out criterion (relative RMS residual, every coordinate weighted
        equally) of the starting and the final model.
    pointwise_before, pointwise_after : float
        The held-out pointwise (acceleration-level) criterion, for comparison.
    criterion : str
        ``"trajectory (weak form)"`` or ``"pointwise"``: what effects were accepted on.
    steps : list of Step
        The effects of the final model, in the order they were found.
    rankings : list of DataFrame
        The candidates' scores in every round of the forward search.
    lagrangian_changes : dict
        ``{"removed": [...], "added": [...]}``: Lagrangian terms the revision
        removed from or added to the starting model's support.
    degenerate_folds : list of str
        Folds excluded from some model's score (singular or indefinite mass matrix).
    coordinates : list of str
    passive : bool
        Passive data fix the model only up to scale: coefficients are relative to the
        fixed term (whose coefficient is 1).
    bootstrap : BootstrapReport or None
        With ``diagnose(..., bootstrap=n)``: intervals and inclusion of every term of
        the final model (:func:`lagsindy.bootstrap` of the final configuration); the
        steps' ``low`` and ``high`` are its intervals of the effects.
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
    residual_rms_after: np.ndarray = None
    heldout_error_after: float = float("nan")
    pointwise_before: float = float("nan")
    pointwise_after: float = float("nan")
    criterion: str = "trajectory (weak form)"
    lagrangian_changes: dict = field(default_factory=dict)
    degenerate_folds: list = field(default_factory=list)
    stop_reason: str = ""
    settings: dict = field(default_factory=dict)
    bootstrap: object = None
    _data: dict = field(default_factory=dict, repr=False)

    @property
    def effects(self) -> list:
        """Names of the effects found, in order."""
        return [s.candidate.name for s in self.steps]

    def to_frame(self) -> pd.DataFrame:
        """One row per effect: kind, final coefficient, units, share, criterion.

        ``low`` and ``high`` are the effect's bootstrap interval
        (``diagnose(..., bootstrap=n)``; NaN without it, and for input gain and delay
        effects, which are not coefficients of the refitted model).
        """
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
                    "how": s.how,
                    "heldout_error": s.heldout_error,
                    "low": s.low,
                    "high": s.high,
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
            f"{self.settings.get('fold_kind', 'trajectories')}; criterion: held-out "
            f"{self.criterion} residual{scale}"
        )
        of = (
            "the model's forces"
            if self.passive
            else "the force scale (measured force, or the model's forces if larger)"
        )
        lines.append(
            "before: residual RMS "
            + ", ".join(
                f"{c}: {r:.3g} ({r / max(f, 1e-300):.1%} of {of})"
                for c, r, f in zip(
                    self.coordinates, self.residual_rms_before, self.force_rms
                )
            )
        )
        if self.residual_rms_after is not None:
            lines.append(
                "after:  residual RMS "
                + ", ".join(
                    f"{c}: {r:.3g} ({r / max(f, 1e-300):.1%} of {of})"
                    for c, r, f in zip(
                        self.coordinates, self.residual_rms_after, self.force_rms
                    )
                )
            )
        if not self.settings.get("start_valid", True):
            lines.append(
                "the starting model's mass matrix is singular or indefinite on the "
                "data: it cannot predict some accelerations"
            )
        lines.append(
            f"held-out trajectory (weak-form) error: {self.heldout_error_before:.4g} -> "
            f"{self.heldout_error_after:.4g}"
            if self.criterion.startswith("trajectory")
            else "held-out trajectory (weak-form) error: not available (rows are not "
            "time-ordered trajectories long enough for the windows)"
        )
        lines.append(
            f"held-out pointwise error:              {self.pointwise_before:.4g} -> "
            f"{self.pointwise_after:.4g}   (relative RMS, every coordinate weighted equally)"
        )
        changes = self.lagrangian_changes or {}
        if changes.get("removed") or changes.get("added"):
            lines.append(
                "the Lagrangian was revised jointly with the effects: "
                f"removed {changes.get('removed') or 'nothing'}, "
                f"added {changes.get('added') or 'nothing'}"
            )
        if not self.steps:
            lines.append("no effect improves the held-out criterion")
        else:
            boot = self.bootstrap
            level = f"{boot.level:.0%} interval" if boot is not None else ""
            head = (
                f"{'step':>4}  {'effect':<26} {'term':<24} {'final coef.':>12} "
                + (f"{level:>27} " if boot is not None else "")
                + f"{'units':<24} {'explained':>9}  {'held-out error':>14}"
            )
            lines.append(head)
            lines.append("-" * len(head))
            for k, s in enumerate(self.steps, 1):
                interval = ""
                if boot is not None:
                    interval = (
                        f"[{s.low:>12.5g}, {s.high:>12.5g}] "
                        if np.isfinite(s.low) and np.isfinite(s.high)
                        else f"{'-':>27} "
                    )
                lines.append(
                    f"{k:>4}  {s.candidate.description:<26} {s.candidate.name:<24} "
                    f"{s.coefficient:>12.5g} {interval}{s.units:<24} "
                    f"{s.explained:>9.1%}  {s.heldout_error:>14.4g}"
                )
            lines.append(
                "  explained: share of the final model's held-out residual (squared) "
                "that removing the effect would add back"
            )
        if self.degenerate_folds:
            lines.append(
                "excluded degenerate folds (refit mass matrix singular or indefinite, "
                "cannot predict accelerations): " + "; ".join(self.degenerate_folds)
            )
        for old, new in self.settings.get("swaps", []):
            lines.append(f"swapped {old} for {new} (better held-out criterion)")
        if self.stop_reason:
            lines.append(f"stopped: {self.stop_reason}")
        if self.bootstrap is not None:
            boot = self.bootstrap
            lines.append(
                f"bootstrap of the final model: {boot.n_resamples} resamples of "
                f"{boot.n_groups} {boot.resampling}, {boot.level:.0%} {boot.method} "
                "intervals (terms of the final model)"
                + (f"; {boot.n_failed} resample(s) failed" if boot.n_failed else "")
            )
            width = max([12] + [len(t) for t in boot.terms])
            lines.append(
                f"  {'term':<{width}}  {'coefficient':>12}  {'inclusion':>9}  "
                f"{'low':>12}  {'high':>12}"
            )
            for k, t in enumerate(boot.terms):
                if boot.coefficient[k] == 0:
                    continue
                lines.append(
                    f"  {t:<{width}}  {boot.coefficient[k]:>12.5g}  "
                    f"{boot.inclusion[k]:>9.2f}  {boot.low[k]:>12.5g}  "
                    f"{boot.high[k]:>12.5g}"
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
        after = self._data["residual_after"]
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
            else:
                cand = step.candidate
                i = self.coordinates.index(cand.coordinates[0])
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
            if step is not None:
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
def _units(cand, units, passive):
    """Units of a coefficient: from the user's ``units`` only, else in words."""
    if cand.kind == "gain":
        return "(factor - 1)"
    if passive:
        return "rel. to fixed term"
    c = cand.coordinates[0]
    if units is not None and c in units:
        q_unit, f_unit = units[c]
        if cand.kind == "conservative":
            return f"energy ({f_unit}*{q_unit})"
        return cand.term.units(units)
    if cand.kind == "viscous":
        return f"per unit of {c}_dot"
    if cand.kind == "relative":
        return f"per unit of {c}_dot-{cand.coordinates[1]}_dot"
    if cand.kind == "drag":
        return f"per unit of {c}_dot^2"
    if cand.kind in ("coulomb", "bias"):
        return f"force units of {c}"
    return "energy units"


def velocity_eps(X, n_dof, coordinates) -> dict:
    """Coulomb smoothing velocity per coordinate from the data's velocity scale.

    ``eps = 0.01 * (99th percentile of |q_dot|)``: the smoothed sign reaches 76 % of
    its full value at 1 % of the top speed, so a viscous coefficient fitted beside it
    is not biased (a fixed ``eps=0.01`` biased it by -6 % on an axis whose top speed
    was 0.1 m/s).
    """
    qd = np.abs(np.asarray(X, dtype=float)[:, n_dof : 2 * n_dof])
    top = np.quantile(qd, 0.99, axis=0)
    return {
        c: float(f"{_EPS_FRACTION * t:.3g}") if t > 0 else DEFAULT_EPS
        for c, t in zip(coordinates, top)
    }


def _pairs(coords):
    return [(a, b) for k, a in enumerate(coords) for b in coords[k + 1 :]]


def _catalogue(est, kinds, extra_terms, angles, tau, eps):
    """Candidate effects not already in the model's candidate set."""
    coords = est.coordinates_
    present_forces = {t.name for t in est.dissipation_terms_}
    present_terms = {str(t) for t in est.library_.terms_}
    out = []
    for kind in kinds:
        if kind in _DISSIPATIVE:
            targets = _pairs(coords) if kind == "relative" else [(c,) for c in coords]
            for tgt in targets:
                term = make_term(
                    kind,
                    tgt if kind == "relative" else tgt[0],
                    coords,
                    eps=eps.get(tgt[0], DEFAULT_EPS),
                )
                if term.name not in present_forces:
                    out.append(Candidate(kind, term.name, tuple(tgt), term))
        elif kind == "delay":
            continue  # estimated before the other effects (see diagnose)
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
            terms += [canonical(t, coords) for t in (extra_terms or [])]
            seen = set()
            for t in terms:
                if str(t) in present_terms or str(t) in seen:
                    continue
                seen.add(str(t))
                names = {str(s) for s in t.free_symbols}
                own = tuple(c for c in coords if c in names or f"{c}_dot" in names)
                out.append(Candidate("conservative", str(t), own or (coords[0],), t))
        else:
            raise ValueError(
                f"unknown candidate kind {kind!r}; use some of {DEFAULT_CATALOGUE}"
            )
    return out


def _segments(Xt, d, groups, dt):
    """Time-ordered row blocks of every trajectory."""
    if groups is not None:
        return [s.cpu().numpy() for s in trajectory_segments(Xt, d, groups)]
    return [s.cpu().numpy() for s in trajectory_segments(Xt, d, None, dt=dt)]


def _make_folds(segments, n_splits):
    """Folds as lists of row blocks: whole trajectories, else time blocks."""
    if len(segments) >= n_splits:
        labels = np.concatenate([np.full(len(s), k) for k, s in enumerate(segments)])
        rows = np.concatenate(segments)
        folds = []
        for _, test in GroupKFold(n_splits).split(rows, groups=labels):
            ids = np.unique(labels[test])
            folds.append([segments[k] for k in ids])
        return folds, "trajectories"
    longest = max(len(s) for s in segments)
    if longest < 2 * n_splits:
        raise ValueError(
            f"need at least n_splits={n_splits} trajectories, or trajectories of at "
            f"least {2 * n_splits} samples to cut into time blocks; got "
            f"{len(segments)} trajector(ies) of at most {longest} samples"
        )
    folds = [[] for _ in range(n_splits)]
    for seg in segments:
        for k, block in enumerate(np.array_split(seg, n_splits)):
            if len(block):
                folds[k].append(block)
    return folds, "time blocks"


class _Statistics:
    """Per-fold Gram statistics of every library term, candidate and the target.

    Column layout: ``[library terms + conservative candidates | model forces +
    dissipative candidates | gain candidates | target]``. ``kind`` is ``"weak"``
    (integrated residual over windows) or ``"strong"`` (pointwise).
    """

    def __init__(self, op, Xt, tau_t, extra, folds, kind, *, window=None, dt=None):
        d = op.n_dof
        self.kind = kind
        raw, fit = [], []
        for blocks in folds:
            if kind == "weak":
                segs = [torch.as_tensor(b) for b in blocks if len(b) >= window]
                if not segs:
                    raise _NoWindows()
                cov = estimate_noise_covariance(Xt, segs, d)
                g, noise, n_w = op.weak_gram(
                    Xt,
                    tau_t,
                    segs,
                    window=window,
                    stride=max(1, window // 4),
                    dt=dt,
                    noise_cov=cov,
                    noise_rows=_NOISE_ROWS,
                    extra=extra,
                    return_noise=True,
                )
                if n_w == 0:
                    raise _NoWindows()
                raw.append(to_numpy(g))
                fit.append(to_numpy(g - noise))
            else:
                rows = torch.as_tensor(np.concatenate(blocks))
                g = op.gram(
                    Xt[rows],
                    None if tau_t is None else tau_t[rows],
                    extra=None if extra is None else extra[rows],
                )
                raw.append(to_numpy(g))
                fit.append(raw[-1])
        self.raw = np.stack(raw)  # (K, d, P, P)
        self.fit = np.stack(fit)


class _NoWindows(Exception):
    pass


class _Scorer:
    """Held-out score of any support over the columns of :class:`_Statistics`."""

    def __init__(self, stats, n_features, target, fixed_col, nonneg, weights, mass):
        self.stats = stats
        self.n_features = n_features
        self.target = target  # column index (case I) or None
        self.fixed_col = fixed_col  # passive: column with coefficient 1
        self.nonneg = nonneg  # bool per feature
        self.w = weights  # (d,)
        self.mass = mass  # per fold (rows, n_lib, d, d) mass matrices, or None
        full = np.einsum("i,kipq->pq", weights, stats.fit)
        diag = np.sqrt(np.clip(np.diag(full), 0, None))
        self.col = np.where(diag > 0, diag, 1.0)
        # The target (or the fixed term) keeps its units, so the SSE is in force
        # units squared, comparable with the reference scales, and coefficients
        # unscale by their own column alone.
        self.col[fixed_col if target is None else target] = 1.0
        self._cache = {}

    def _combine(self, g):
        return np.einsum("i,ipq->pq", self.w, g) / np.outer(self.col, self.col)

    def _solve(self, g, free):
        """LS coefficients (scaled) over ``free``; non-negative where required."""
        t = self.fixed_col if self.target is None else self.target
        sign = -1.0 if self.target is None else 1.0
        active = list(free)
        for _ in range(len(free) + 1):
            coef = _lstsq(g[np.ix_(active, active)], sign * g[active, t])
            neg = [(c, j) for c, j in zip(coef, active) if self.nonneg[j] and c < 0]
            if not neg:
                return active, coef
            active.remove(min(neg)[1])
        return active, coef

    def _sse(self, g_test, active, coef):
        """Weighted SSE per coordinate of the held-out residual."""
        t = self.fixed_col if self.target is None else self.target
        sign = -1.0 if self.target is None else 1.0
        out = []
        for gi in g_test:
            gs = gi / np.outer(self.col, self.col)
            yy = gs[t, t]
            b = sign * gs[active, t]
            out.append(
                max(yy - 2 * coef @ b + coef @ gs[np.ix_(active, active)] @ coef, 0)
            )
        return np.asarray(out)

    def coefficients(self, support):
        """Full-data LS coefficients (unscaled) of ``support``, as {column: value}."""
        free = [j for j in support if j != self.fixed_col]
        g = self._combine(self.stats.fit.sum(0))
        active, coef = self._solve(g, free)
        out = {j: c / self.col[j] for j, c in zip(active, coef)}
        if self.fixed_col is not None:
            out[self.fixed_col] = 1.0
        return out

    def score(self, support):
        """Held-out relative RMS residual, per-fold values and degenerate folds."""
        key = tuple(sorted(support))
        if key in self._cache:
            return self._cache[key]
        free = [j for j in key if j != self.fixed_col]
        K = self.stats.raw.shape[0]
        total = self._combine(self.stats.fit.sum(0))
        sse, ref, bad = np.zeros(K), np.zeros(K), []
        for k in range(K):
            train = total - self._combine(self.stats.fit[k])
            active, coef = self._solve(train, free)
            if self.mass is not None and not self._mass_ok(k, active, coef):
                bad.append(k)
            sse[k] = float(self.w @ self._sse(self.stats.raw[k], active, coef))
            ref[k] = float(self.w @ self.reference[k])
        # Degenerate folds are left out, unless every fold is degenerate (the
        # support itself cannot predict accelerations; valid() then rejects it).
        keep = np.ones(K, dtype=bool)
        if len(bad) < K:
            keep[bad] = False
        folds = np.where(keep, sse / np.maximum(ref, 1e-300), np.nan)
        den = ref[keep].sum()
        value = np.sqrt(sse[keep].sum() / den) if den > 0 else np.inf
        out = (float(value), folds, bad if len(bad) < K else [])
        self._cache[key] = out
        return out

    def _mass_ok(self, k, active, coef):
        n_lib = self.mass[k].shape[1]
        c = np.zeros(n_lib)
        for j, v in zip(active, coef):
            if j < n_lib:
                c[j] = v / self.col[j]
        if self.fixed_col is not None and self.fixed_col < n_lib:
            c[self.fixed_col] = 1.0
        return _mass_definite(self.mass[k], c)


def _mass_definite(mass, c):
    m = np.einsum("skij,k->sij", mass, c)
    eig = np.linalg.eigvalsh((m + np.swapaxes(m, 1, 2)) / 2)
    big = np.maximum(np.abs(eig).max(axis=1), 1e-300)
    definite = (eig > 1e-8 * big[:, None]).all(axis=1) | (
        eig < -1e-8 * big[:, None]
    ).all(axis=1)
    return (1.0 - definite.mean()) <= _MASS_BAD_FRACTION


def _lstsq(g, b):
    if len(b) == 0:
        return np.zeros(0)
    evals, evecs = np.linalg.eigh((g + g.T) / 2)
    keep = evals > 1e-12 * max(evals[-1], 1e-300)
    inv = np.where(keep, 1.0 / np.where(keep, evals, 1.0), 0.0)
    return evecs @ (inv * (evecs.T @ b))


def _normalization(est):
    """The case III scale the fitted estimator chose, to keep it in refits."""
    return "mass" if getattr(est, "normalization_", None) == "mass" else est.fixed_term_


def _fit_model(est, X, tau, groups, *, effects=(), penalized=(), eps=None, fit=True):
    """Refit ``est``'s configuration: the Lagrangian's sparse search runs again.

    ``effects`` enter as known (unpenalized) terms, ``penalized`` as candidates.
    ``fit=False`` returns the configured (unfitted, quiet) estimator.
    """
    new = clone(est)
    unpenalized = list(est.unpenalized or [])
    library = clone(est.library_)
    cons = [c for c in list(effects) + list(penalized) if c.kind == "conservative"]
    if cons:
        library.set_params(terms=list(library.terms or []) + [c.term for c in cons])
        unpenalized += [str(c.term) for c in effects if c.kind == "conservative"]
    diss = [c for c in list(effects) + list(penalized) if c.kind in _DISSIPATIVE]
    if diss:
        base = est.dissipation
        dlib = (
            DissipationLibrary(kinds=(), coordinates=est.coordinates_)
            if base is None
            else clone(base)
        )
        old = dlib.eps
        merged = {
            c: (old.get(c, DEFAULT_EPS) if isinstance(old, dict) else float(old))
            for c in est.coordinates_
        }
        for c in diss:
            if c.kind == "coulomb":
                merged[c.coordinates[0]] = (eps or {}).get(
                    c.coordinates[0], DEFAULT_EPS
                )
        specs = list(dlib.terms or [])
        specs += [
            (c.kind, c.coordinates if c.kind == "relative" else c.coordinates[0])
            for c in diss
        ]
        dlib.set_params(terms=specs, eps=merged)
        new.set_params(dissipation=dlib)
        unpenalized += [c.name for c in effects if c.kind in _DISSIPATIVE]
    new.set_params(library=library, unpenalized=unpenalized or None)
    if est.case_ == "fixed":
        new.set_params(fixed_term=_normalization(est))
    new.set_params(verbose=0)  # refits are quiet; the result keeps est's verbose
    if not fit:
        return new
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        new.fit(X, tau, groups=groups)
    return new.set_params(verbose=est.verbose)


def _adjusted_tau(tau, gains):
    if tau is None or not gains:
        return tau
    out = tau.copy()
    for i, gamma in gains.items():
        out[:, i] = out[:, i] * (1.0 + gamma)
    return out


def _residual(est, X, tau):
    """Euler-Lagrange (force) residual per sample: tau - Theta c (or -Theta c)."""
    pred = np.asarray(est.predict(X), dtype=float).reshape(len(X), -1)
    return (np.zeros_like(pred) if tau is None else tau) - pred


def _force_scale(est, Xt):
    """Per-coordinate RMS of the summed magnitudes of the model's force contributions."""
    coef = est.fitted_.all_coef()
    support = np.flatnonzero(coef)
    if support.size == 0:
        return np.ones(est.n_dof_)
    cols = est.fitted_.feature_operator(support, Xt.device, Xt.dtype).columns(Xt)
    size = (cols.abs() * torch.as_tensor(np.abs(coef[support]), dtype=Xt.dtype)).sum(2)
    return np.sqrt(np.mean(to_numpy(size) ** 2, axis=0))


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
    tau_a = None if tau is None else validate_tau(tau, Xa.shape[0], est.n_dof_, est.coordinates_)
    if (tau_a is None) != (est.case_ != "forces"):
        raise ValueError(
            "diagnose the model with the kind of data it was fitted on: tau for a model "
            "fitted with tau (case I), no tau for a passive model"
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
                f"groups must have one label per row of X ({Xa.shape[0]}), got {groups.shape}"
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
    passive = tau_a is None
    Xt = to_tensor(Xa, dtype=torch.float64, device="cpu")
    tau_t = None if passive else to_tensor(tau_a, dtype=torch.float64, device="cpu")
    # Refits and predictions see X as the estimator was fitted on it (named columns
    # for a DataFrame-fitted model), so scikit-learn's feature-name checks hold.
    names = getattr(est, "feature_names_in_", None)
    Xf = Xa if names is None else pd.DataFrame(Xa, columns=list(names))

    # ------------------------------------------------------------ columns and folds
    candidates = _catalogue(est, catalogue, extra_terms, angles, tau_a, eps)
    cons = [c for c in candidates if c.kind == "conservative"]
    diss = [c for c in candidates if c.kind in _DISSIPATIVE]
    gain = [c for c in candidates if c.kind == "gain"]
    lib_terms = list(est.library_.terms_) + [c.term for c in cons]
    forces = list(est.dissipation_terms_) + [c.term for c in diss]
    op = EulerLagrangeOperator(coords, lib_terms, forces=[f.forces for f in forces])
    n_lib, n_force = len(lib_terms), len(forces)
    n_features = n_lib + n_force + len(gain)
    index = {str(t): k for k, t in enumerate(lib_terms)}
    index.update({f.name: n_lib + k for k, f in enumerate(forces)})
    index.update({c.name: n_lib + n_force + k for k, c in enumerate(gain)})
    extra = None
    if gain:
        extra = Xt.new_zeros((Xt.shape[0], d, len(gain)))
        for k, c in enumerate(gain):
            extra[:, c.term, k] = -tau_t[:, c.term]
    nonneg = np.zeros(n_features, dtype=bool)
    for k, f in enumerate(forces):
        nonneg[n_lib + k] = f.kind in _NONNEGATIVE

    dt = getattr(est, "dt_", None) or est.dt
    if dt is None:
        rough = _segments(Xt, d, groups, 0.0) if groups is not None else None
        rough = (
            [torch.as_tensor(s) for s in rough]
            if rough is not None
            else [torch.arange(Xt.shape[0])]
        )
        try:
            dt = estimate_sampling_interval(Xt, d, rough)
        except ValueError:
            dt = None
    segments = _segments(Xt, d, groups, dt if dt and dt > 0 else 0.0)
    folds, fold_kind = _make_folds(segments, n_splits)
    shortest_block = min(max(len(b) for b in blocks) for blocks in folds)
    win = int(window or getattr(est, "window", 81) or 81)
    win = min(win, shortest_block // 2)
    if win % 2 == 0:
        win -= 1
    stats_w = None
    if dt and dt > 0 and win >= 9:
        try:
            stats_w = _Statistics(
                op, Xt, tau_t, extra, folds, "weak", window=win, dt=float(dt)
            )
        except _NoWindows:
            stats_w = None
    stats_s = _Statistics(op, Xt, tau_t, extra, folds, "strong")

    # The starting model's support and reference scales (fixed for the whole run).
    start_coef = np.zeros(n_features)
    for t, c in zip(est.library_.terms_, est.coef_):
        start_coef[index[str(t)]] = c
    for f, c in zip(est.dissipation_terms_, est.dissipation_coef_):
        start_coef[index[f.name]] = c
    fixed_col = None
    if passive:
        if est.fixed_term_ is not None:
            fixed_col = index[str(est.fixed_term_)]
        else:  # mass normalization or case II: the largest term sets the scale
            fixed_col = int(np.argmax(np.abs(start_coef[:n_lib])))
        start_coef = start_coef / start_coef[fixed_col]
    target = None if passive else n_features

    rng = np.random.default_rng(0)
    mass = []
    for blocks in folds:
        rows = np.concatenate(blocks)
        pick = np.sort(rng.choice(rows, size=min(len(rows), _MASS_ROWS), replace=False))
        with torch.no_grad():
            mass.append(to_numpy(op.mass_matrices(Xt[pick, :d], Xt[pick, d : 2 * d])))
    all_rows = np.sort(
        rng.choice(Xa.shape[0], size=min(Xa.shape[0], 400), replace=False)
    )
    mass_all = to_numpy(op.mass_matrices(Xt[all_rows, :d], Xt[all_rows, d : 2 * d]))

    def make_scorer(stats):
        full = stats.fit.sum(0)  # (d, P, P)
        mag = np.sqrt(np.clip(np.einsum("ipp->ip", full)[:, :n_features], 0, None))
        model = mag @ np.abs(start_coef)  # (d,)
        meas = (
            np.zeros(d)
            if passive
            else np.sqrt(np.clip(full[:, target, target], 0, None))
        )
        scale = np.maximum(model, meas) ** 2
        w = 1.0 / np.where(scale > 0, scale, 1.0)
        sc = _Scorer(stats, n_features, target, fixed_col, nonneg, w, mass)
        ref = []
        for g in stats.raw:
            magk = np.sqrt(np.clip(np.einsum("ipp->ip", g)[:, :n_features], 0, None))
            mk = magk @ np.abs(start_coef)
            tk = (
                np.zeros(d)
                if passive
                else np.sqrt(np.clip(g[:, target, target], 0, None))
            )
            ref.append(np.maximum(mk, tk) ** 2)
        sc.reference = ref
        return sc

    scorer_s = make_scorer(stats_s)
    scorer = make_scorer(stats_w) if stats_w is not None else scorer_s
    criterion = "trajectory (weak form)" if stats_w is not None else "pointwise"
    degenerate = set()

    def support_of(model):
        s = {index[str(t)] for t, c in zip(model.library_.terms_, model.coef_) if c}
        s |= {
            index[f.name]
            for f, c in zip(model.dissipation_terms_, model.dissipation_coef_)
            if c
        }
        return s

    def valid(support):
        coef = scorer.coefficients(support)
        c = np.zeros(n_lib)
        for j, v in coef.items():
            if j < n_lib:
                c[j] = v
        return _mass_definite(mass_all, c)

    def J(support):
        value, per_fold, bad = scorer.score(support)
        for k in bad:
            degenerate.add(k)
        return value, per_fold

    s0 = support_of(est)
    j0, _ = J(s0)
    start_valid = valid(s0)
    # A model that cannot predict some accelerations is beaten by any valid one.
    value0 = j0 if start_valid else np.inf
    p0 = scorer_s.score(s0)[0]
    if verbose:
        print(f"[lagsindy] before: held-out {criterion} error {j0:.4g}")

    by_name = {c.name: c for c in candidates}
    current, support, value = est, s0, value0
    effects, gains, rankings, history = [], {}, [], {}
    changes = {"removed": [], "added": []}
    stop_reason = ""

    def fit_with(effs, gns, penalized=()):
        return _fit_model(
            est,
            Xf,
            _adjusted_tau(tau_a, gns),
            groups,
            effects=effs,
            penalized=penalized,
            eps=eps,
        )

    def nonneg_ok(model, effs):
        names_ = {e.name for e in effs if e.kind in _NONNEGATIVE}
        return all(
            c >= 0
            for f, c in zip(model.dissipation_terms_, model.dissipation_coef_)
            if f.name in names_
        )

    # ------------------------------------------------ step 0: input delay
    tau_recorded = tau_a
    scorer_rec, scorer_s_rec = scorer, scorer_s
    delay = None  # (Candidate, DelayEstimate) once accepted
    if "delay" in catalogue and tau_a is not None and dt and dt > 0:
        # The delay is estimated with the dissipative catalogue as candidates:
        # an input delay and missing damping both shift the phase of the force.
        joint_config = _fit_model(
            est, None, None, None, penalized=diss, eps=eps, fit=False
        )
        found = _input_delay(joint_config, Xf, tau_a, segments, float(dt), verbose)
        if found is not None:
            estimate, shifted = found
            tau_sh = to_tensor(shifted, dtype=torch.float64, device="cpu")
            extra_sh = None
            if gain:
                extra_sh = Xt.new_zeros((Xt.shape[0], d, len(gain)))
                for k, c in enumerate(gain):
                    extra_sh[:, c.term, k] = -tau_sh[:, c.term]
            ss = _Statistics(op, Xt, tau_sh, extra_sh, folds, "strong")
            sw = None
            if stats_w is not None:
                sw = _Statistics(
                    op, Xt, tau_sh, extra_sh, folds, "weak", window=win, dt=float(dt)
                )
            scorer_s = make_scorer(ss)
            scorer = make_scorer(sw) if sw is not None else scorer_s
            tau_a = shifted
            try:
                trial = fit_with([], {})
            except (ValueError, FloatingPointError, np.linalg.LinAlgError):
                trial = None
            st = support_of(trial) if trial is not None else s0
            jt = J(st)[0] if trial is not None else np.inf
            if jt < (1 - min_improvement) * value and valid(st):
                driven = tuple(
                    c for i, c in enumerate(coords) if np.any(tau_recorded[:, i] != 0)
                )
                cand = Candidate("delay", "delay", driven, estimate)
                delay = (cand, estimate)
                current, support, value = trial, st, jt
                history[cand.name] = ("added", jt)
                if verbose:
                    print(
                        f"[lagsindy] input delay {1e3 * estimate.delay:.1f} ms: "
                        f"held-out {jt:.4g}"
                    )
            else:
                if verbose:
                    print(
                        f"[lagsindy] an input delay of {1e3 * estimate.delay:.1f} ms "
                        f"does not improve the held-out criterion ({value:.4g} -> "
                        f"{jt:.4g})"
                    )
                scorer, scorer_s, tau_a = scorer_rec, scorer_s_rec, tau_recorded

    total_ref = float(sum(scorer.w @ r for r in scorer.reference))

    def contributes(model, cand, gns):
        """The effect's share of the force scale is above rounding in ``model``."""
        c = _effect_coefficient(model, cand, gns)
        size = abs(c) * scorer.col[index[cand.name]]
        return size**2 > _PRECISION * total_ref

    # ------------------------------------------------ step 1: joint revision of L
    if revise and diss:
        try:
            joint = fit_with([], {}, penalized=diss)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
            joint = None
            if verbose:
                print(f"[lagsindy] joint fit failed: {exc}")
        if joint is not None:
            sj = support_of(joint)
            kept = [
                by_name[f.name]
                for f, c in zip(joint.dissipation_terms_, joint.dissipation_coef_)
                if c and f.name in by_name
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
            if kept:
                revised = fit_with(kept, {})
                sr = support_of(revised)
                jr, _ = J(sr)
                if (
                    jr < (1 - min_improvement) * value
                    and valid(sr)
                    and nonneg_ok(revised, kept)
                ):
                    current, support, value, effects = revised, sr, jr, list(kept)
                    for e in kept:
                        history[e.name] = ("joint", jr)
                elif verbose:
                    print(
                        f"[lagsindy] the revision does not improve the held-out "
                        f"criterion ({value:.4g} -> {jr:.4g}); kept the model"
                    )

    # ------------------------------------------------ step 2b: swaps
    # The joint search or a greedy addition can keep the wrong effect of a
    # coordinate (quadratic drag for small viscous damping): try replacing each
    # accepted dissipative effect by another candidate acting on the same
    # coordinates, and keep the swap that most improves the held-out criterion.
    swaps = []

    def swap_pass():
        nonlocal current, support, value, effects
        for _ in range(len(effects)):
            trials = []
            names = {e.name for e in effects}
            for e in effects:
                if e.kind not in _DISSIPATIVE:
                    continue
                for c in diss:
                    if c.name in names or c.coordinates != e.coordinates:
                        continue
                    v = J((support - {index[e.name]}) | {index[c.name]})[0]
                    if v < (1 - min_improvement) * value:
                        trials.append((v, e, c))
            accepted = False
            for _, e, c in sorted(trials, key=lambda t: t[0])[:3]:
                trial_effects = [c if x is e else x for x in effects]
                try:
                    trial = fit_with(trial_effects, gains)
                except (ValueError, FloatingPointError, np.linalg.LinAlgError):
                    continue
                st = support_of(trial)
                st |= {index[f"gain({coords[i]})"] for i in gains}
                jt, _ = J(st)
                if (
                    jt < (1 - min_improvement) * value
                    and valid(st)
                    and nonneg_ok(trial, trial_effects)
                    and contributes(trial, c, gains)
                ):
                    if verbose:
                        print(
                            f"[lagsindy] swapped {e.name} for {c.name}: held-out "
                            f"{value:.4g} -> {jt:.4g}"
                        )
                    current, support, value, effects = trial, st, jt, trial_effects
                    history[c.name] = ("swapped", jt)
                    swaps.append((e.name, c.name))
                    accepted = True
                    break
            if not accepted:
                break

    swap_pass()

    # ------------------------------------------------ step 2: forward additions
    for _ in range(max(0, max_effects - len(effects))):
        if min(value, scorer_s.score(support)[0]) ** 2 <= _PRECISION:
            stop_reason = "the remaining residual is at rounding level"
            break
        taken = {e.name for e in effects} | {f"gain({coords[i]})" for i in gains}
        pool = [c for c in candidates if c.name not in taken]
        if gains and len(gains) >= len(gain) - 1:
            # Gains on every input would leave the model's scale free (all zero).
            pool = [c for c in pool if c.kind != "gain"]
        if not pool:
            stop_reason = "every candidate is in the model"
            break
        base_value, base_folds = J(support)
        rows = []
        for c in pool:
            j = index[c.name]
            if j in support:
                continue
            v, folds_v = J(support | {j})
            coef = scorer.coefficients(support | {j}).get(j, 0.0)
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
            stop_reason = "every candidate is in the model"
            break
        table = table.sort_values("explained", ascending=False, kind="stable")
        table = table.reset_index(drop=True)
        rankings.append(table)
        if verbose:
            print(table.head(5).to_string())
        eligible = table[(table.explained >= min_explained) & table.every_fold]
        if not len(eligible):
            top = table.iloc[0]
            stop_reason = (
                f"the best remaining candidate, {top['term']}, explains "
                f"{top['explained']:.2%} of the held-out residual (needs "
                f"{min_explained:.0%} and every fold better)"
            )
            break
        accepted = False
        for _, top in eligible.head(3).iterrows():
            best = by_name[top["term"]]
            trial_effects, trial_gains = list(effects), dict(gains)
            if best.kind == "gain":
                trial_gains[best.term] = trial_gains.get(best.term, 0.0) + float(
                    top["coefficient"]
                )
            else:
                trial_effects.append(best)
            try:
                trial = fit_with(trial_effects, trial_gains)
            except (ValueError, FloatingPointError, np.linalg.LinAlgError):
                continue
            st = support_of(trial)
            if best.kind == "gain":
                # The adjusted input carries the gain; score with its column too.
                st = st | {index[best.name]}
            jt, _ = J(st)
            if (
                jt < (1 - min_improvement) * value
                and valid(st)
                and nonneg_ok(trial, trial_effects)
                and contributes(trial, best, trial_gains)
            ):
                current, support, value = trial, st, jt
                effects, gains = trial_effects, trial_gains
                if best.kind == "gain":
                    effects_gain = best
                    history[effects_gain.name] = ("added", jt)
                else:
                    history[best.name] = ("added", jt)
                accepted = True
                if verbose:
                    print(f"[lagsindy] added {best.name}: held-out {jt:.4g}")
                break
            if verbose:
                print(
                    f"[lagsindy] {best.name} does not improve held-out predictions "
                    f"after the refit ({value:.4g} -> {jt:.4g})"
                )
        if not accepted:
            stop_reason = (
                f"{eligible.iloc[0]['term']} explains part of the residual but the "
                "refitted model does not predict held-out trajectories better"
            )
            table.attrs["rejected"] = eligible.iloc[0]["term"]
            break
    else:
        stop_reason = f"max_effects={max_effects} reached"

    swap_pass()

    # ------------------------------------------------ step 3: never worse
    final = current
    if current is not est and not value < value0:
        final, support, effects, gains = est, s0, [], {}
        stop_reason = "the diagnosed model does not beat the starting one held out"
        if delay is not None:
            delay = None
            scorer, scorer_s, tau_a = scorer_rec, scorer_s_rec, tau_recorded
    if final is est:
        value = j0
    p1 = scorer_s.score(support)[0]
    lib_before = {str(t) for t, c in zip(est.library_.terms_, est.coef_) if c}
    lib_after = {str(t) for t, c in zip(final.library_.terms_, final.coef_) if c}
    effect_terms = {e.name for e in effects if e.kind == "conservative"}
    changes = {
        "removed": sorted(lib_before - lib_after),
        "added": sorted(lib_after - lib_before - effect_terms),
    }

    tau_final = _adjusted_tau(tau_a, gains)
    residual_before = _residual(est, Xf, tau_recorded)
    residual_after = _residual(final, Xf, tau_final)
    # The scale a residual is compared with: the measured force, or the model's
    # force contributions where they are larger (an undriven coordinate).
    force_rms = _force_scale(est, Xt)
    if not passive:
        force_rms = np.maximum(force_rms, np.sqrt(np.mean(tau_recorded**2, axis=0)))
    steps = []
    if delay is not None:
        cand, estimate = delay
        v_without = scorer_rec.score(support)[0]
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
                heldout_error=history[cand.name][1],
                equation=final.equation(4),
                ranking=pd.DataFrame(),
                how="added",
            )
        )
    all_effects = list(effects) + [by_name[f"gain({coords[i]})"] for i in gains]
    for e in all_effects:
        how, after = history.get(e.name, ("added", value))
        without = support - {index[e.name]}
        v_without = J(without)[0]
        explained = (
            float(1 - value**2 / v_without**2) if np.isfinite(v_without) else 1.0
        )
        steps.append(
            Step(
                candidate=e,
                coefficient=_effect_coefficient(final, e, gains),
                units=_units(e, units, passive),
                explained=explained,
                fold_explained=[],
                residual_rms=np.sqrt(np.mean(residual_after**2, axis=0)),
                heldout_error=after,
                equation=final.equation(4),
                ranking=rankings[-1] if rankings else pd.DataFrame(),
                how=how,
            )
        )
    boot = None
    if bootstrap is not None:
        boot = _bootstrap_final(
            final,
            Xf,
            tau_final,
            groups,
            segments,
            Xa.shape[0],
            int(bootstrap),
            random_state,
            verbose,
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
        f"fold {k + 1} ({sum(len(b) for b in folds[k])} samples)"
        for k in sorted(degenerate)
    ]
    if fold_names:
        warnings.warn(
            "diagnose excluded degenerate folds from some models' held-out scores "
            "(their refits have a singular or indefinite mass matrix): "
            + ", ".join(fold_names),
            UserWarning,
            stacklevel=2,
        )
    return DiagnosisReport(
        initial=est,
        final=final,
        residual_rms_before=np.sqrt(np.mean(residual_before**2, axis=0)),
        residual_rms_after=np.sqrt(np.mean(residual_after**2, axis=0)),
        force_rms=force_rms,
        heldout_error_before=float(j0),
        heldout_error_after=float(value),
        pointwise_before=float(p0),
        pointwise_after=float(p1),
        criterion=criterion,
        steps=steps,
        rankings=rankings,
        coordinates=coords,
        passive=passive,
        lagrangian_changes=changes,
        degenerate_folds=fold_names,
        stop_reason=stop_reason,
        bootstrap=boot,
        settings={
            "n_splits": n_splits,
            "fold_kind": fold_kind,
            "min_explained": min_explained,
            "catalogue": tuple(catalogue),
            "eps": dict(eps),
            "window": win if stats_w is not None else None,
            "start_valid": start_valid,
            "swaps": swaps,
        },
        _data={
            "X": Xa,
            "tau": tau_recorded,
            "residual_before": residual_before,
            "residual_after": residual_after,
        },
    )


def _input_delay(est, X, tau, segments, dt, verbose):
    """Estimate an input delay; ``(DelayEstimate, shifted tau)`` or None.

    :func:`lagsindy.delay.estimate_delay` (held-out force prediction over folds of
    trajectories, up to 10 sampling intervals either way) with the (unfitted)
    configuration ``est``. Kept only when the estimate is at least a tenth of a sampling
    interval and twice its standard error; :func:`diagnose` then accepts it only if
    the model refitted on the shifted input improves its held-out criterion.
    """
    from .delay import estimate_delay, shift_input

    n = len(tau)
    t = np.zeros(n)
    labels = np.zeros(n, dtype=np.int64)
    for k, seg in enumerate(segments):
        t[seg] = np.arange(len(seg)) * dt
        labels[seg] = k
    groups = labels if len(segments) >= 2 else None
    base = clone(est).set_params(verbose=0)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            estimate = estimate_delay(base, X, tau, t, groups=groups)
            shifted = shift_input(tau, t, estimate.delay, groups)
    except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
        if verbose:
            print(f"[lagsindy] no input delay estimate: {exc}")
        return None
    if verbose:
        print(f"[lagsindy] {estimate}")
    size = abs(estimate.delay)
    if size < 0.1 * dt or (np.isfinite(estimate.std) and size <= 2 * estimate.std):
        return None
    return estimate, shifted


def _bootstrap_final(
    final, X, tau, groups, segments, n, n_resamples, random_state, verbose
):
    """:func:`lagsindy.bootstrap` of the final model's configuration.

    The groups are the trajectories (``groups``, else the segments diagnose found),
    so resamples never join pieces of different trajectories.
    """
    from .uncertainty import bootstrap as _bootstrap

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
