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

# Relative change within which the report counts two values of a criterion as equal
# when it says whether the criteria agree (held-out trajectory vs pointwise error, and
# each coordinate's residual).
CRITERIA_TOLERANCE = 0.01

# How each row of the step table came into the final model.
_HOW_TEXT = {
    "joint": "kept by the joint search with the Lagrangian (step 1)",
    "added": "added alone (step 2)",
    "swapped": "replaced another effect of its coordinates",
    "refit": "kept by a refit of the model's own dissipation terms",
    "start": "in the starting model already",
}

# The wording of the candidates that are not force kinds (a force kind's is its
# record's, lagsindy.force_kinds).
_KIND_TEXT = {
    "gain": "input gain error",
    "conservative": "missing conservative term",
    "delay": "input delay",
    "joint_delay": "input delay of one joint",
    "payload": "payload on the end body",
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
        ``"joint"`` (kept by the joint sparse search of step 1), ``"added"``,
        ``"swapped"`` (replaced another effect of the same coordinates, step 2b),
        ``"refit"`` (a term of the model's own dissipation library that a refit
        kept) or ``"start"`` (in the starting model already).
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
        Every effect of the final model: those found, in the order they were found,
        then those of the starting model and of its own dissipation library
        (``how`` ``"start"`` and ``"refit"``).
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
    settings : dict
        The diagnosis' settings; ``settings["units"]`` holds ``diagnose(units=)``,
        which labels the residuals in the text and the figure.
    input_delays : dict of str to float
        The delays accepted (``"delay"``, ``"joint_delay"``): seconds per
        coordinate (the single delay on every driven one); empty when none.
        :meth:`shift_input` applies them.
    payload : dict or None
        With ``"payload"`` in the catalogue and a payload kept (a robot fitted with
        ``inertia="urdf"``): ``link``, ``mass`` (kg), ``com`` (centre of mass in the
        link's frame, m; ``nan`` where the data cannot identify it), ``mass_std``,
        ``com_std`` (standard errors: weighted least squares, delta method) and the
        fitted payload ``terms``; also the first step ``payload(<link>)``.
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
    input_delays: dict = field(default_factory=dict)
    payload: dict | None = None
    _data: dict = field(default_factory=dict, repr=False)

    def shift_input(self, tau, t, groups=None):
        """The input acting at each sample under the delays the diagnosis found:
        what ``final`` was fitted on, and what to predict or simulate it with.

        ``tau`` (n_samples, n_dof) shifted per column by ``input_delays`` (seconds
        per coordinate; 0 where none) with :func:`lagsindy.delay.shift_input`
        (``method="fourier"`` for per-joint delays, as diagnose applied them); a
        copy when no delay was found.
        """
        from ..delay import shift_input

        delays = [self.input_delays.get(c, 0.0) for c in self.coordinates]
        # per-joint delays are applied by the band-limited shift (see
        # lagsindy.diagnostics.joint_delay), the single delay by interpolation
        per_joint = any(s.candidate.kind == "joint_delay" for s in self.steps)
        tau = np.asarray(tau, dtype=float)
        if tau.ndim != 2 or tau.shape[1] != len(delays):
            raise ValueError(
                f"tau must have shape (n_samples, {len(delays)}) (one column per "
                f"coordinate {self.coordinates}), got {tau.shape}"
            )
        return shift_input(
            tau, t, delays, groups, method="fourier" if per_joint else "linear"
        )

    @property
    def effects(self) -> list:
        """Names of the effects the diagnosis added, in order (not those of the
        starting model)."""
        return [s.candidate.name for s in self.steps if s.how != "start"]

    def _force_unit(self, coordinate):
        """The force unit of ``coordinate`` from ``diagnose(units=...)``, or None."""
        units = self.settings.get("units") or {}
        return units[coordinate][1] if coordinate in units else None

    def disagreements(self) -> list:
        """Sentences saying where the criteria disagree: the held-out trajectory
        error fell while the pointwise one did not (or the reverse), or a
        coordinate's residual rose while the criterion fell. Changes within
        ``CRITERIA_TOLERANCE`` (relative) count as equal."""
        tol, out = CRITERIA_TOLERANCE, []

        def change(a, b):
            return (b - a) / a if np.isfinite(a) and np.isfinite(b) and a > 0 else 0.0

        dh = change(self.heldout_error_before, self.heldout_error_after)
        dp = change(self.pointwise_before, self.pointwise_after)

        def said(d):
            return (
                f"rose {d:.1%}"
                if d > tol
                else f"stayed within {tol:.0%}"
                if d >= -tol
                else f"fell {-d:.1%}"
            )

        if self.criterion.startswith("trajectory"):
            if dh < -tol and dp >= -tol:
                out.append(
                    f"the criteria disagree: the held-out trajectory error fell "
                    f"{-dh:.1%} while the pointwise error {said(dp)}: the change "
                    "shows over seconds of trajectory rather than sample by sample "
                    "(small damping does this, and so does fitting the held-out "
                    "windows' noise); check the effects' intervals (bootstrap=)"
                )
            elif dp < -tol and dh >= -tol:
                out.append(
                    f"the criteria disagree: the pointwise error fell {-dp:.1%} while "
                    f"the held-out trajectory error {said(dh)}"
                )
        if self.residual_rms_after is not None and (dh < -tol or dp < -tol):
            for c, b, a in zip(
                self.coordinates, self.residual_rms_before, self.residual_rms_after
            ):
                if a > (1 + tol) * b:
                    unit = self._force_unit(c)
                    out.append(
                        f"the residual on {c} rose ({b:.3g} -> {a:.3g}"
                        + (f" {unit}" if unit else "")
                        + ") while the held-out errors fell: the final model fits the "
                        f"other coordinates better at {c}'s expense"
                    )
        return out

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
        lines.append("residual RMS per coordinate (share of its force scale*):")
        for label, rms in (
            ("before: ", self.residual_rms_before),
            ("after:  ", self.residual_rms_after),
        ):
            if rms is None:
                continue
            lines.append(
                f"  {label}"
                + ", ".join(
                    f"{c} {r:.3g}"
                    + (f" {self._force_unit(c)}" if self._force_unit(c) else "")
                    + f" ({r / max(f, 1e-300):.1%})"
                    for c, r, f in zip(self.coordinates, rms, self.force_rms)
                )
            )
        lines.append(
            "  * force scale: the RMS of the model's forces on the coordinate "
            "(passive data fix no force unit)"
            if self.passive
            else "  * force scale: the RMS of the measured force on the coordinate, "
            "or of the model's forces there if larger (an undriven coordinate)"
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
        lines.extend(f"note: {text}" for text in self.disagreements())
        changes = self.lagrangian_changes or {}
        if changes.get("removed") or changes.get("added"):
            lines.append(
                "the Lagrangian was revised jointly with the effects: "
                f"removed {changes.get('removed') or 'nothing'}, "
                f"added {changes.get('added') or 'nothing'}"
            )
        if not [s for s in self.steps if s.how != "start"]:
            lines.append("no effect improves the held-out criterion")
        if self.steps:
            lines.append("effects of the final model:")
            lines.extend(self._step_table())
        if self.degenerate_folds:
            lines.append(
                "excluded degenerate folds (refit mass matrix singular or indefinite, "
                "cannot predict accelerations): "
                + "; ".join(self.degenerate_folds)
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

    def _step_table(self) -> list:
        """The step table's lines: every effect of the final model, and a legend."""
        boot = self.bootstrap
        level = f"{boot.level:.0%} interval" if boot is not None else ""
        head = (
            f"{'step':>4}  {'effect':<26} {'term':<24} {'final coef.':>12} "
            + (f"{level:>27} " if boot is not None else "")
            + f"{'units':<24} {'explained':>9}  {'held-out error':>14}  found"
        )
        lines = [head, "-" * len(head)]
        k = 0
        for s in self.steps:
            interval = ""
            if boot is not None:
                interval = (
                    f"[{s.low:>12.5g}, {s.high:>12.5g}] "
                    if np.isfinite(s.low) and np.isfinite(s.high)
                    else f"{'-':>27} "
                )
            found = s.how != "start"
            k += found
            lines.append(
                f"{k if found else '-':>4}  {s.candidate.description:<26} "
                f"{s.candidate.name:<24} {s.coefficient:>12.5g} {interval}"
                f"{s.units:<24} {s.explained:>9.1%}  "
                + (f"{s.heldout_error:>14.4g}" if found else f"{'-':>14}")
                + f"  {s.how}"
            )
        lines.append(
            "  explained: share of the final model's held-out residual (squared) "
            "that removing the effect would add back"
        )
        hows = dict.fromkeys(s.how for s in self.steps)
        lines.append(
            "  found: " + "; ".join(f"{h} = {_HOW_TEXT.get(h, h)}" for h in hows)
        )
        return lines

    def plot(self, path=None):
        """Residual against the identified variable of each effect, before and after.

        The starting model's residual is drawn in grey dots, the final model's in
        coloured crosses, each with its binned mean as a line (dashed before, solid
        after). Axes carry the units given to :func:`diagnose` (``units=``).

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
        units = self.settings.get("units") or {}

        def unit(c, k):  # k = 0: position unit, 1: force unit
            return units[c][k] if c in units else None

        def label(text, u):
            return text if u is None else f"{text} ({u})"

        # Nothing found: one panel per coordinate, its residual against its velocity.
        panels = self.steps or [(None, i) for i in range(n)]
        fig, axes = plt.subplots(
            1, len(panels), figsize=(4.5 * len(panels), 3.6), squeeze=False
        )
        rng = np.random.default_rng(0)
        idx = rng.choice(X.shape[0], size=min(X.shape[0], 4000), replace=False)
        changed = self.final is not self.initial
        for ax, step in zip(axes[0], panels):
            if isinstance(step, tuple):
                step, i = step
                c = self.coordinates[i]
                var, xlabel = X[:, n + i], label(f"{c}_dot", _rate(unit(c, 0)))
            else:
                cand = step.candidate
                c = cand.coordinates[0]
                i = self.coordinates.index(c)
                if cand.kind == "relative":
                    j = self.coordinates.index(cand.coordinates[1])
                    var = X[:, n + i] - X[:, n + j]
                    xlabel = label(
                        f"{c}_dot - {cand.coordinates[1]}_dot", _rate(unit(c, 0))
                    )
                elif cand.kind == "conservative":
                    var, xlabel = X[:, i], label(c, unit(c, 0))
                elif cand.kind == "payload":  # inertial: against an acceleration
                    var, xlabel = X[:, 2 * n + i], label(f"{c}_ddot", None)
                elif cand.kind in ("gain", "delay", "joint_delay"):
                    var, xlabel = self._data["tau"][:, i], label(f"tau_{c}", unit(c, 1))
                else:
                    var, xlabel = X[:, n + i], label(f"{c}_dot", _rate(unit(c, 0)))
            ax.scatter(
                var[idx], before[idx, i], s=3, marker=".", color="0.6", alpha=0.5,
                label="before (starting model)",
            )  # fmt: skip
            _binned_mean(ax, var, before[:, i], color="0.25", ls="--")
            if changed:
                ax.scatter(
                    var[idx], after[idx, i], s=6, marker="x", linewidths=0.6,
                    color="C3", alpha=0.5, label="after (final model)",
                )  # fmt: skip
                _binned_mean(ax, var, after[:, i], color="C3", ls="-")
            ax.axhline(0.0, color="k", lw=0.6)
            ax.set_xlabel(xlabel)
            ax.set_ylabel(
                label(
                    f"force residual on {c}",
                    "relative to the model's scale" if self.passive else unit(c, 1),
                )
            )
            ax.set_title(
                step.candidate.name if step is not None else f"residual on {c}",
                fontsize="small",
            )
            ax.legend(markerscale=3, fontsize="small")
        fig.tight_layout()
        if path is not None:
            fig.savefig(path, dpi=120)
        return fig


def _rate(u):
    return None if u is None else f"{u}/s"


def _binned_mean(ax, x, y, **style):
    """The mean of ``y`` in 20 bins of ``x`` (bins with at least 5 points)."""
    finite = np.isfinite(x) & np.isfinite(y)
    x, y = x[finite], y[finite]
    if x.size < 10 or not np.ptp(x) > 0:
        return
    edges = np.linspace(x.min(), x.max(), 21)
    which = np.clip(np.digitize(x, edges) - 1, 0, 19)
    count = np.bincount(which, minlength=20)
    total = np.bincount(which, weights=y, minlength=20)
    keep = count >= 5
    centre = 0.5 * (edges[:-1] + edges[1:])
    ax.plot(centre[keep], total[keep] / count[keep], lw=1.8, **style)


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
    if cand.kind == "conservative":
        return "energy units"
    return "force per unit coefficient"  # a custom force term
