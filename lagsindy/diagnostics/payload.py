"""The ``"payload"`` candidate of :func:`~lagsindy.diagnose`: a load the URDF lacks.

A robot fitted with its URDF's link parameters held (``RobotLibrary(inertia="urdf")``,
whose regression library has ``payload=None``) cannot absorb a load on its end body:
the rigid-body torques are known. The candidate adds the end body's identifiable
inertial parameters (``payload_m``, ``payload_mx``, ..., found with the other links
held: :class:`lagsindy.robots.known.Payload`) as free Lagrangian terms, and is kept
under the rule of the other effects: on held-out folds, with the other terms refitted
on the rest, it must explain ``min_explained`` of the criterion (squared), improve
every fold and both the trajectory and the pointwise criterion by
``min_improvement``; then the model refitted with it must predict held-out data better
by ``min_improvement`` too. It is tried first, before a delay and the friction kinds
(an offset or a spring would otherwise absorb part of the load's gravity torque), and
the rest of the diagnosis starts from the model with the payload.

With the link parameters estimated (``inertia="base"``, the default) a payload is part
of the end link's base parameters: nothing to propose, and the report says so in a
note.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import pandas as pd
from sklearn.base import clone

from .._stacklevel import outside_stacklevel
from ..formulation.operator import EulerLagrangeOperator
from ..formulation.probes import without_probes
from .report import Candidate, Step
from .scoring import (
    _fit_model,
    _mass_definite,
    _mass_samples,
    _NoWindows,
    _residual,
    _Statistics,
    _support_in,
    _weighted_scorer,
)

NOT_HELD = (
    "payload: not tried: the fit estimates the link parameters (inertia='base'), "
    "so a payload is already part of the end link's base parameters; fit with "
    "CandidateLibrary.from_urdf(..., inertia='urdf') to identify one"
)


@dataclass
class PayloadFound:
    """The outcome of the payload candidate.

    ``model`` is the refitted estimator with the payload (None when not kept),
    ``estimate`` its :meth:`~lagsindy.robots.known.Payload.estimate` (mass, centre
    of mass and their standard errors), ``candidate`` the report's candidate,
    ``heldout`` the criterion ``(without, with)`` and ``note`` why it was not kept.
    """

    model: object = None
    estimate: dict | None = None
    candidate: Candidate | None = None
    heldout: tuple = (np.nan, np.nan)
    explained: float = np.nan
    note: str = ""


def payload_applies(est) -> str | None:
    """``None`` when ``est``'s library can take payload terms; otherwise the note
    saying why not (an empty string: it has them already)."""
    library = est.library_
    if not hasattr(library, "payload_estimate"):
        robot = getattr(library, "robot_", None)
        return (
            NOT_HELD
            if robot is not None
            else ("payload: not tried: the library is not a robot's (from_urdf)")
        )
    return "" if library.payload is not None else None


def propose_payload(search, second=False) -> PayloadFound:
    """Try the payload candidate on the starting model of ``search`` (a
    :class:`~lagsindy.diagnostics.loop.Search` over case I data). ``second``: the
    second path of :func:`lagsindy.diagnose`, where a spring beside the load leaves
    the load alone explaining little (and its refit taking up the spring): kept when
    it lowers the held-out criteria at all; that path's final model must then
    predict held-out data better than the first path's."""
    est, st = search.est, search.settings
    note = payload_applies(est)
    if note is not None:
        return PayloadFound(note=note)
    extended = clone(est.library_).set_params(payload="end").build()
    names = list(extended.terms_)
    payload_names = extended.payload_.names
    if not payload_names:
        return PayloadFound(note="payload: the data identify no payload parameter")
    forces = list(est.dissipation_terms_)
    op = EulerLagrangeOperator(
        search.coords, extended.torch_terms(), forces=[f.forces for f in forces]
    )
    index = {n: k for k, n in enumerate(names)}
    index.update({f.name: len(names) + k for k, f in enumerate(forces)})
    n_features = len(names) + len(forces)
    nonneg = np.zeros(n_features, dtype=bool)
    for k, f in enumerate(forces):
        nonneg[len(names) + k] = f.dissipative
    for name in extended.nonnegative_:  # rotor inertias, the payload's mass
        nonneg[index[name]] = True
    tau_t = search.Xt.new_tensor(search.tau_a)
    strong = _Statistics(op, search.Xt, tau_t, None, search.folds, "strong")
    weak = None
    if search.stats_w is not None:
        try:
            weak = _Statistics(
                op, search.Xt, tau_t, None, search.folds, "weak",
                window=search.win, dt=float(search.dt),
            )  # fmt: skip
        except _NoWindows:
            weak = None
    start = np.zeros(n_features)
    for name, c in zip(est.library_.get_feature_names_out(), est.coef_):
        start[index[name]] = c
    for f, c in zip(forces, est.dissipation_coef_):
        start[index[f.name]] = c
    known = {index[n]: v for n, v in est.library_.known_terms_.items()}
    n_lib = len(names)
    mass_folds, mass_all = _mass_samples(op, search.Xt, search.folds)

    def scorer(stats):
        return _weighted_scorer(
            stats, start, n_features, n_features, None, nonneg, mass_folds, known
        )

    sc_s = scorer(strong)
    sc = scorer(weak) if weak is not None else sc_s
    s0 = _support_in(index, est)
    s1 = s0 | {index[n] for n in payload_names}
    j0, folds0, _ = sc.score(s0)
    j1, folds1, _ = sc.score(s1)
    p0, p1 = sc_s.score(s0)[0], sc_s.score(s1)[0]
    cand = Candidate("payload", f"payload({extended.payload_.link})",
                     tuple(search.coords), tuple(payload_names))  # fmt: skip
    explained = float(1 - j1**2 / j0**2) if np.isfinite(j0) and j0 > 0 else 0.0
    ok = np.isfinite(folds0) & np.isfinite(folds1)
    better = (j1 < j0 and p1 < p0) if second else (
        explained >= st.min_explained
        and bool(ok.any() and np.all(folds1[ok] < folds0[ok]))
        and j1 < (1 - st.min_improvement) * j0
        and p1 < (1 - st.min_improvement) * p0
    )
    if st.verbose:
        print(
            f"[lagsindy] payload({extended.payload_.link}): held-out {j0:.4g} -> "
            f"{j1:.4g}, pointwise {p0:.4g} -> {p1:.4g}"
        )
    if not better:
        return PayloadFound(
            candidate=cand, heldout=(j0, j1), explained=explained,
            note=f"payload({extended.payload_.link}) was tried and not kept: "
            f"held-out {j0:.4g} -> {j1:.4g} (explains {explained:.1%}), pointwise "
            f"{p0:.4g} -> {p1:.4g}",
        )  # fmt: skip
    new = _fit_model(est, search.Xf, search.tau_a, search.groups, fit=False)
    new.set_params(library=clone(est.library_).set_params(payload="end"))
    with warnings.catch_warnings(), without_probes():
        warnings.simplefilter("ignore")
        new.fit(search.Xf, search.tau_a, groups=search.groups)
    new.set_params(verbose=est.verbose)
    sr = _support_in(index, new)
    jr = sc.score(sr)[0]
    coef = np.zeros(n_lib)
    for k, c in enumerate(new.coef_):
        coef[k] = c
    better = jr < (1 - st.min_improvement) * j0
    if not (better and (second or _mass_definite(mass_all, coef))):
        why = (
            f"the refitted model does not predict held-out data better ({j0:.4g} "
            f"-> {jr:.4g})"
            if not better
            else f"the refitted model's mass matrix is singular or indefinite on the "
            f"data (held-out {j0:.4g} -> {jr:.4g}): the load's terms took up "
            "something else"
        )
        return PayloadFound(
            candidate=cand, heldout=(j0, jr), explained=explained,
            note=f"payload({extended.payload_.link}) explains {explained:.1%} of the "
            f"held-out criterion but {why}",
        )  # fmt: skip
    cov = _covariance(sc_s, sr, [index[n] for n in payload_names], strong, search)
    estimate = new.library_.payload_estimate(new.coef_, cov)
    return PayloadFound(
        model=new, estimate=estimate, candidate=cand, heldout=(j0, jr),
        explained=explained,
    )  # fmt: skip


def _covariance(scorer, support, columns, stats, search):
    """Covariance of the payload coefficients (``columns``) of the full-data least
    squares over ``support`` (the known columns held), weighted as the scorer weighs
    the equations: ``s^2 G^{-1}`` with ``s^2`` the weighted residual sum of squares
    over the pointwise rows less the coefficients; None when singular."""
    free = scorer._free(support)
    g = scorer._combine(scorer.stats.fit.sum(0))
    active, coef = scorer._solve(g, free)
    t = scorer.target
    sse = g[t, t] - 2 * coef @ g[active, t] + coef @ g[np.ix_(active, active)] @ coef
    n_rows = sum(len(b) for blocks in search.folds for b in blocks) * search.d
    dof = max(n_rows - len(active), 1)
    try:
        inv = np.linalg.inv(g[np.ix_(active, active)])
    except np.linalg.LinAlgError:
        return None
    cov_scaled = max(sse, 0.0) / dof * inv
    col = scorer.col[active]
    cov = cov_scaled / np.outer(col, col)
    where = {j: k for k, j in enumerate(active)}
    if not all(c in where for c in columns):
        return None
    pick = [where[c] for c in columns]
    return cov[np.ix_(pick, pick)]


def _describe(estimate) -> str:
    """The payload step's units column: the mass's error and the centre of mass."""
    std = estimate["mass_std"]
    com = ", ".join("?" if not np.isfinite(v) else f"{v:.4g}" for v in estimate["com"])
    err = f" +- {std:.2g}" if np.isfinite(std) else ""
    return f"kg{err}; centre ({com}) m in {estimate['link']}"


# Effects a load's gravity resembles on small swings (sin q ~ q, cos q ~ 1).
STAND_INS = ("spring", "bias")


def _final_estimate(final, found):
    """The payload of the ``final`` model: ``found`` (with its standard errors)
    when the later steps left its terms as they were, else the final model's values
    (refitted beside the effects added after it: a spring beside the load; their
    standard errors are not estimated, ``nan``)."""
    lib = final.library_
    names = list(lib.terms_)
    values = {n: float(final.coef_[names.index(n)]) for n in found["terms"]}
    if all(np.isclose(values[n], v, rtol=1e-9, atol=0) for n, v in
           found["terms"].items()):  # fmt: skip
        return found
    return lib.payload_estimate(final.coef_)


def add_payload(report, found, first, search):
    """Put the payload into the report of the diagnosis that started from its
    model: the step ``payload(<link>)`` first (coefficient: the mass; units: its
    standard error and the centre of mass in the link's frame), ``report.payload``,
    and the starting model, criteria and residuals of the first search (the model
    without the payload); a note when it was not kept."""
    if found.note:
        report.settings.setdefault("notes", []).append(found.note)
    if found.model is None:
        stand_ins = [
            s.candidate.name
            for s in report.steps
            if s.how != "start" and s.candidate.kind in STAND_INS
        ]
        if stand_ins:
            warnings.warn(
                f"diagnose kept {stand_ins} after the payload of the end link was "
                "tried first and not kept: on small swings a load's gravity acts on "
                "the joints like springs and offsets, so these may stand in for a "
                "load (or the load for them: with a spring beside a load the "
                "payload alone explains too little). Compare fits with "
                "from_urdf(..., inertia='urdf', payload='end') and with these "
                "effects declared",
                UserWarning,
                stacklevel=outside_stacklevel(),
            )
        return report
    est = first.est
    names = found.candidate.term
    without = search.support - {search.index[n] for n in names}
    v_without = search.J(without)[0]
    value = report.heldout_error_after
    explained = (
        float(1 - value**2 / v_without**2)
        if np.isfinite(v_without) and v_without > 0
        else 1.0
    )
    residual_before = _residual(est, first.Xf, first.tau_recorded)
    report.steps.insert(
        0,
        Step(
            candidate=found.candidate,
            coefficient=found.estimate["mass"],
            units=_describe(found.estimate),
            explained=explained,
            fold_explained=[],
            residual_rms=report.residual_rms_after,
            heldout_error=found.heldout[1],
            equation=report.final.equation(4),
            ranking=pd.DataFrame(),
            how="added",
        ),
    )
    report.payload = _final_estimate(report.final, found.estimate)
    report.steps[0].coefficient = report.payload["mass"]
    report.steps[0].units = _describe(report.payload)
    report.initial = est
    report.heldout_error_before = float(first.j0)
    report.pointwise_before = float(first.p0)
    report.residual_rms_before = np.sqrt(np.mean(residual_before**2, axis=0))
    report._data["residual_before"] = residual_before
    added = set(report.lagrangian_changes.get("added", [])) | set(names)
    report.lagrangian_changes["added"] = sorted(added)
    return report
