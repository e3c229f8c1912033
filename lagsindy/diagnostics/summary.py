"""The end of :func:`~lagsindy.diagnose`: never worse, and the report."""

from __future__ import annotations

import numpy as np
import pandas as pd

from .catalogue import _DISSIPATIVE, _effect_coefficient
from .report import Candidate, DiagnosisReport, Step, _units
from .scoring import _adjusted_tau, _force_scale, _kept_terms, _residual

__all__ = ["summarize"]


def summarize(search, units, bootstrap, random_state) -> DiagnosisReport:
    """Step 3 of a :class:`~.loop.Search`: keep the starting model unless the final
    one is better, and make the report."""
    est, J, index, coords = search.est, search.J, search.index, search.coords
    final = search.current
    if search.current is not est and not search.value < search.value0:
        final, search.support, search.effects, search.gains = est, search.s0, [], {}
        search.stop_reason = (
            "the diagnosed model does not beat the starting one held out"
        )
        if search.delay is not None:
            search.delay = None
            search.scorer, search.scorer_s = search.scorer_rec, search.scorer_s_rec
            search.tau_a = search.tau_recorded
    if final is est:
        search.value = search.j0
    support, effects, gains = search.support, search.effects, search.gains
    value = search.value
    p1 = search.scorer_s.score(support)[0]
    lib_before, lib_after = _kept_terms(est), _kept_terms(final)
    effect_terms = {e.name for e in effects if e.kind == "conservative"}
    changes = {
        "removed": sorted(lib_before - lib_after),
        "added": sorted(lib_after - lib_before - effect_terms),
    }

    tau_recorded, Xf = search.tau_recorded, search.Xf
    tau_final = _adjusted_tau(search.tau_a, gains)
    residual_before = _residual(est, Xf, tau_recorded)
    residual_after = _residual(final, Xf, tau_final)
    # The scale a residual is compared with: the measured force, or the model's
    # force contributions where they are larger (an undriven coordinate).
    # (the final model's too: an undriven coordinate whose terms the starting model
    # lacked has neither a measured force nor a starting model's force)
    force_rms = np.maximum(_force_scale(est, search.Xt), _force_scale(final, search.Xt))
    if not search.passive:
        force_rms = np.maximum(force_rms, np.sqrt(np.mean(tau_recorded**2, axis=0)))
    steps = []
    v_without = search.scorer_rec.score(support)[0] if search.delay else None
    for cand, delay, std in search.delay or []:
        steps.append(
            Step(
                candidate=cand,
                coefficient=1e3 * delay,
                units=f"ms (+- {1e3 * std:.2g} ms)",
                explained=float(1 - value**2 / v_without**2)
                if np.isfinite(v_without) and v_without > 0
                else 1.0,
                fold_explained=[],
                residual_rms=np.sqrt(np.mean(residual_after**2, axis=0)),
                heldout_error=search.history[cand.name][1],
                equation=final.equation(4),
                ranking=pd.DataFrame(),
                how="added",
            )
        )
    all_effects = list(effects) + [search.by_name[f"gain({coords[i]})"] for i in gains]
    for e in all_effects:
        how, after = search.history.get(e.name, ("added", value))
        without = support - {index[e.name]}
        v_without = J(without)[0]
        explained = (
            float(1 - value**2 / v_without**2) if np.isfinite(v_without) else 1.0
        )
        steps.append(
            Step(
                candidate=e,
                coefficient=_effect_coefficient(final, e, gains),
                units=_units(e, units, search.passive),
                explained=explained,
                fold_explained=[],
                residual_rms=np.sqrt(np.mean(residual_after**2, axis=0)),
                heldout_error=after,
                equation=final.equation(4),
                ranking=search.rankings[-1] if search.rankings else pd.DataFrame(),
                how=how,
            )
        )
    steps += _model_effects(search, final, support, value, units, residual_after)
    boot, boot_error = None, None
    if bootstrap is not None:
        try:
            boot = _bootstrap_final(
                final,
                Xf,
                tau_final,
                search.groups,
                search.segments,
                search.Xa.shape[0],
                int(bootstrap),
                random_state,
                search.verbose,
            )
        except (ValueError, FloatingPointError, RuntimeError) as exc:
            # the report is not lost for it (np.linalg.LinAlgError is a ValueError)
            boot_error = f"{type(exc).__name__}: {exc}"
    if boot is not None:
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
        f"fold {k + 1} ({sum(len(b) for b in search.folds[k])} samples)"
        for k in sorted(search.degenerate)
    ]
    final_bad = search.scorer.score(support)[2]
    return DiagnosisReport(
        initial=est,
        final=final,
        residual_rms_before=np.sqrt(np.mean(residual_before**2, axis=0)),
        residual_rms_after=np.sqrt(np.mean(residual_after**2, axis=0)),
        force_rms=force_rms,
        heldout_error_before=float(search.j0),
        heldout_error_after=float(value),
        pointwise_before=float(search.p0),
        pointwise_after=float(p1),
        criterion=search.criterion,
        steps=steps,
        rankings=search.rankings,
        coordinates=coords,
        passive=search.passive,
        lagrangian_changes=changes,
        degenerate_folds=fold_names,
        stop_reason=search.stop_reason,
        bootstrap=boot,
        settings={
            "units": dict(units) if units else None,
            "n_splits": search.n_splits,
            "fold_kind": search.fold_kind,
            "min_explained": search.min_explained,
            "catalogue": tuple(search.catalogue),
            "eps": dict(search.eps),
            "window": search.win if search.stats_w is not None else None,
            "start_valid": search.start_valid,
            "final_degenerate": [int(k) for k in final_bad],
            "notes": _notes(est, search, steps)
            + (
                [f"the bootstrap failed ({boot_error}); no intervals"]
                if boot_error
                else []
            ),
            "swaps": search.swaps,
        },
        input_delays=_input_delays(search),
        _data={
            "X": search.Xa,
            "tau": tau_recorded,
            "residual_before": residual_before,
            "residual_after": residual_after,
        },
    )


def _input_delays(search) -> dict:
    """Seconds per coordinate of the accepted delay(s) (a single delay: on every
    driven coordinate); empty when none was accepted."""
    out = {}
    for cand, delay, _ in search.delay or []:
        for c in cand.coordinates:
            out[c] = delay
    return out


def _model_effects(search, final, support, value, units, residual_after) -> list:
    """Steps for the final model's forces that no step of the search added: those
    of the starting model (``how="start"``) and those its own dissipation library
    kept in a refit (``how="refit"``), so the table lists every effect of the final
    model."""
    listed = {e.name for e in search.effects}
    start = {
        f.name
        for f, c in zip(search.est.dissipation_terms_, search.est.dissipation_coef_)
        if c
    }
    out = []
    for f, c in zip(final.dissipation_terms_, final.dissipation_coef_):
        if not c or f.name in listed:
            continue
        cand = search.by_name.get(f.name) or Candidate(
            f.kind, f.name, tuple(f.coordinates), f
        )
        v_without = search.J(support - {search.index[f.name]})[0]
        out.append(
            Step(
                candidate=cand,
                coefficient=float(c),
                units=_units(cand, units, search.passive),
                explained=float(1 - value**2 / v_without**2)
                if np.isfinite(v_without) and v_without > 0
                else 1.0,
                fold_explained=[],
                residual_rms=np.sqrt(np.mean(residual_after**2, axis=0)),
                heldout_error=value,
                equation=final.equation(4),
                ranking=pd.DataFrame(),
                how="start" if f.name in start else "refit",
            )
        )
    return out


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


def _notes(est, search, steps) -> list:
    """Lines that tie the report to what the fit said: a fit redone jointly with
    dissipation, a fit's warning of missing damping that the diagnosis did not
    follow (and why), a degenerate starting model revised jointly, folds excluded
    only from other models' scores."""
    fitted = getattr(est, "fitted_", None)
    notes = []
    joint = getattr(fitted, "joint_dissipation", None)
    if joint:
        named = ", ".join(f"{k} = {v:.3g}" for k, v in joint["named"].items())
        notes.append(
            f"the starting model was fitted jointly with {joint['kinds']} dissipation "
            f"(the fit's probes: friction or damping explained {joint['share']:.0%} "
            f"of what a conservative fit left, {named})"
        )
    unmodelled = getattr(fitted, "unmodelled", None)
    dissipative = [
        s.candidate.name for s in steps if s.candidate.kind in _DISSIPATIVE
    ] + [
        f.name
        for f, c in zip(search.current.dissipation_terms_,
                        search.current.dissipation_coef_)
        if c
    ]  # fmt: skip
    if unmodelled and not dissipative:
        named = ", ".join(f"{k} = {v:.3g}" for k, v in unmodelled["named"].items())
        why = (
            (search.stop_reason or "no refit with it predicted held-out data better")
            if search.diss
            else "the catalogue holds no friction or damping kind"
        )
        notes.append(
            f"the fit warned that friction or damping ({named}) explains "
            f"{unmodelled['share']:.0%} of what it leaves; the diagnosis adds none: "
            f"{why}"
        )
    if not search.start_valid:
        notes.append(
            "the starting model cannot predict accelerations (singular or indefinite "
            "mass matrix), so its held-out score is infinite: it was revised jointly "
            "with the dissipative candidates"
            + ("" if search.diss else " (none in the catalogue: nothing to revise)")
        )
    return notes
