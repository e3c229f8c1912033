"""What :func:`~lagsindy.diagnose` returns: the candidates, the steps and the report.

:class:`DiagnosisReport` prints as a table (``str``), converts to a DataFrame
(:meth:`DiagnosisReport.to_frame`) and draws the residual before and after each
effect (:meth:`DiagnosisReport.plot`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from ..force_kinds import get as get_kind
from ..force_kinds import names as kind_names

# The wording of the candidates that are not force kinds (a force kind's is its
# record's, lagsindy.force_kinds).
_KIND_TEXT = {
    "gain": "input gain error",
    "conservative": "missing conservative term",
    "delay": "input delay",
}


def _kind_text(kind: str) -> str:
    """How the report names an effect of ``kind``."""
    if kind in kind_names():
        return get_kind(kind).description
    return _KIND_TEXT.get(kind, kind)


@dataclass
class Candidate:
    """A candidate missing effect (see :func:`diagnose`)."""

    kind: str
    name: str
    coordinates: tuple
    term: object  # ForceTerm, sympy.Expr (conservative) or int (gain: coordinate index)

    @property
    def description(self) -> str:
        return _kind_text(self.kind)


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
            f"Residual diagnosis over {self.settings.get('n_splits')} held-out folds "
            f"of {self.settings.get('fold_kind', 'trajectories')}; criterion: held-out "
            f"{self.criterion} residual{scale}"
        )
        of = (
            "the model's forces"
            if self.passive
            else "the force scale (measured force, or the model's forces if larger)"
        )
        for label, rms in (
            ("before: ", self.residual_rms_before),
            ("after:  ", self.residual_rms_after),
        ):
            if rms is None:
                continue
            lines.append(
                f"{label}residual RMS "
                + ", ".join(
                    f"{c}: {r:.3g} ({r / max(f, 1e-300):.1%} of {of})"
                    for c, r, f in zip(self.coordinates, rms, self.force_rms)
                )
            )
        if not self.settings.get("start_valid", True):
            lines.append(
                "the starting model's mass matrix is singular or indefinite on the "
                "data: it cannot predict some accelerations"
            )
        lines.append(
            "held-out trajectory (weak-form) error: "
            f"{self.heldout_error_before:.4g} -> {self.heldout_error_after:.4g}"
            if self.criterion.startswith("trajectory")
            else "held-out trajectory (weak-form) error: not available (rows are not "
            "time-ordered trajectories long enough for the windows)"
        )
        lines.append(
            f"held-out pointwise error:              {self.pointwise_before:.4g} -> "
            f"{self.pointwise_after:.4g}   "
            "(relative RMS, every coordinate weighted equally)"
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
                + (
                    " (from other models' scores; the final model's uses every fold)"
                    if not self.settings.get("final_degenerate", True)
                    else ""
                )
            )
        for old, new in self.settings.get("swaps", []):
            lines.append(f"swapped {old} for {new} (better held-out criterion)")
        if self.stop_reason:
            lines.append(f"stopped: {self.stop_reason}")
        lines.extend(f"note: {n}" for n in self.settings.get("notes", []))
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
    if cand.kind in kind_names():
        return get_kind(cand.kind).unit_words(cand.coordinates)
    return "energy units"
