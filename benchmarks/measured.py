"""Measured data: Lagrangians of a real single, double and triple pendulum, loop closed.

Data: the MultiArm-Pendulum free-swing recordings (encoders, 1 kHz, no input; cart
locked) of Kaheman, Fasel, Bramburger, Strom, Kutz and Brunton, "The Experimental
Multi-Arm Pendulum on a Cart: A Benchmark System for Chaos, Learning, and Control",
arXiv:2205.06231 (2022), MIT license, shipped with lagsindy
(:func:`lagsindy.io.load_multiarm_pendulum`). The authors split each record into
identification and validation segments; we fit on the former only and report on both.

Per pendulum:

1. positions thinned to 100 Hz (``--step``), angles shifted to ``phi = theta - pi``
   (zero hanging down), velocities and accelerations estimated by the GCV P-spline
   (:mod:`lagsindy.differentiation`) over each split's record (the authors' segments
   of a split follow each other without a gap, so the spline runs across the cuts;
   identification and validation are differentiated separately); the segments are the
   groups of the fits, diagnosis folds and bootstrap resamples;
2. conservative fits, case III (no input), ``fixed_term=None`` (the search over the
   mass normalization and every candidate term), in the strong and in the weak form
   (``formulation=`` passed explicitly); libraries: degree 2 over
   ``{phi, phi_dot, cos phi, sin phi}`` (single), the paper's separated library
   (double, 63 terms), :meth:`CandidateLibrary.chain` (triple, 12 terms);
   the weak fit is then refined by the error of its 1 s rollouts on the
   identification segments (:func:`lagsindy.refine`, windows every 0.5 s from the
   estimated states; structure kept, one coefficient held): the "refined" rows
   (each window's initial state fitted too, the default) and the "refined, data
   states" rows (initial states held at the P-spline estimates, as the
   validation rollouts start);
3. :func:`lagsindy.diagnose` (default catalogue; on the triple also restricted to
   joint damping, ``catalogue=("viscous", "relative")``) started from the weak-form fit;
   the default diagnosis's model is then refined on rollouts like the conservative
   fit (the "diagnosed, refined" rows: the whole pipeline fit -> diagnose -> refine),
   and the diagnosed models' Lagrangians are also integrated alone, without their
   dissipation and forces ("Lagrangian only");
4. :func:`lagsindy.bootstrap` of the diagnosed model (single and triple pendulum);
5. before/after: R^2 of accelerations on the validation segments, and rollouts (the
   equations integrated from the estimated state at the start of each window) against
   the measured angles, beside the authors' own physical model (their fitted
   parameters, :func:`lagsindy.io.load_multiarm_parameters`) with and without their
   joint damping.

Rollout windows: the validation segments of each record are consecutive in time (the
authors cut one record), so they are joined; windows of 1 s and 5 s start every
``max(0.25 s, (T - horizon) / 19)`` (at most 20 windows), the initial state is the
P-spline estimate at the window's first sample, the error is the RMS over all angles
and samples of the window; the tables give the median over windows.

Passive data fix a Lagrangian only up to a factor, so the coefficients are compared as
ratios to the ``phi1_dot**2`` (``phi_dot**2``) coefficient, and a Rayleigh coefficient
``d`` (force ``-d * phi_dot``) in those units corresponds to ``k / c`` for the
authors' joint coefficient ``k`` (torque ``-k * phi_dot``) and ``c`` the authors'
``phi1_dot**2`` coefficient (half the first joint's inertia); the authors' joints
give ``viscous(phi1)`` (first joint) and ``relative(phi_i,phi_j)`` (later joints).

    python -m benchmarks.measured            # results/measured.md + measured_*.png
    python -m benchmarks.measured --quick    # fewer resamples and steps, *_quick
"""

from __future__ import annotations

import argparse
import os
import time
import warnings

import numpy as np
import pandas as pd

from . import _common
from ._common import header, write

SYSTEMS = ("single", "double", "triple")
HORIZONS = (1.0, 5.0)
N_DOF = {"single": 1, "double": 2, "triple": 3}


def coordinates(which: str) -> list:
    n = N_DOF[which]
    return ["phi"] if n == 1 else [f"phi{i + 1}" for i in range(n)]


def pivot_term(which: str) -> str:
    return f"{coordinates(which)[0]}_dot**2"


# ----------------------------------------------------------------------------- data
def load(which: str, split: str, step: int):
    """``(X, groups, frame)``: the recording thinned by ``step``, in phi = theta - pi."""
    from lagsindy.differentiation import derivatives
    from lagsindy.io import load_multiarm_pendulum

    frame = load_multiarm_pendulum(which=which, split=split)
    frame = frame[frame.groupby("trajectory").cumcount().to_numpy() % step == 0]
    names = coordinates(which)
    angles = [n.replace("phi", "theta") for n in names]
    q = frame[angles].to_numpy() - np.pi
    groups = frame["trajectory"].to_numpy()
    t = frame["t"].to_numpy()
    # The authors cut one continuous record into segments: differentiate each stretch
    # without a time gap as one (no spline end effects at the cuts); the segments stay
    # the groups of the fits, folds and resamples.
    gap = np.diff(t) > 1.5 * np.median(np.diff(t))
    stretches = np.concatenate([[0], np.cumsum(gap)])
    X = derivatives(q, t, groups=stretches, method="pspline")
    columns = names + [f"{n}_dot" for n in names] + [f"{n}_ddot" for n in names]
    return pd.DataFrame(X, columns=columns), groups, frame.reset_index(drop=True)


def library(which: str):
    from lagsindy import CandidateLibrary

    coords = coordinates(which)
    if which == "single":
        return CandidateLibrary.polynomial(
            coords, angles=coords, degree=2, raw_angles=True
        ), "degree 2 over {phi, phi_dot, cos phi, sin phi}"
    if which == "double":
        return CandidateLibrary.separated(
            coords, angles="all", degree=2
        ), "the paper's double-pendulum library (separated, degree 2)"
    return CandidateLibrary.chain(coords), "`CandidateLibrary.chain`"


def authors_parameters(which: str) -> dict:
    from lagsindy.io import load_multiarm_parameters

    return dict(load_multiarm_parameters(which))


def authors_model(which: str):
    """The authors' rigid-body model in phi = theta - pi, scaled so phi1_dot**2 has 1.

    Joint torques ``-k1 * phi1_dot`` and ``-k_i * (phi_i_dot - phi_{i-1}_dot)``
    (absolute angles, later joints between the links) enter as Rayleigh terms.
    Returns ``(damped MechanicalModel, ratios)`` with the ratios of its terms.
    """
    import sympy as sp

    from lagsindy import MechanicalModel

    p = authors_parameters(which)
    if which == "single":
        phi, phid = sp.symbols("phi phi_dot")
        J = p["I1"] + p["m1"] * p["a1"] ** 2
        s = 2.0 / J
        lag = phid**2 + s * p["m1"] * p["g"] * p["a1"] * sp.cos(phi)
        diss = s * p["k1"] * phid**2 / 2
        ratios = {
            "phi_dot**2": 1.0,
            "cos(phi)": s * p["m1"] * p["g"] * p["a1"],
            "viscous(phi)": s * p["k1"],
        }
        return MechanicalModel(lag, ["phi"], dissipation=diss, name="authors"), ratios
    if which == "triple":
        from lagsindy.systems import multiarm_triple_pendulum

        system = multiarm_triple_pendulum()
        lib = library("triple")[0]
        coef = lib.decompose(system.lagrangian)[0]
        c = coef[lib.index("phi1_dot**2")]
        ratios = {str(t): v / c for t, v in zip(lib.terms_, coef) if v != 0}
        ratios["viscous(phi1)"] = p["k1"] / c
        ratios["relative(phi1,phi2)"] = p["k2"] / c
        ratios["relative(phi2,phi3)"] = p["k3"] / c
        d1, d2, d3 = sp.symbols("phi1_dot phi2_dot phi3_dot")
        diss = (
            p["k1"] * d1**2 + p["k2"] * (d2 - d1) ** 2 + p["k3"] * (d3 - d2) ** 2
        ) / (2 * c)
        model = MechanicalModel(
            system.lagrangian / c,
            coordinates("triple"),
            dissipation=diss,
            name="authors",
        )
        return model, ratios
    p1, p2, d1, d2 = sp.symbols("phi1 phi2 phi1_dot phi2_dot")
    J1 = p["I1"] + p["m1"] * p["a1"] ** 2 + p["m2"] * p["L1"] ** 2
    J2 = p["I2"] + p["m2"] * p["a2"] ** 2
    c12 = p["m2"] * p["L1"] * p["a2"]
    s = 2.0 / J1
    ratios = {
        "phi1_dot**2": 1.0,
        "phi2_dot**2": s * J2 / 2,
        "phi1_dot*phi2_dot*cos(phi1)*cos(phi2)": s * c12,
        "phi1_dot*phi2_dot*sin(phi1)*sin(phi2)": s * c12,
        "cos(phi1)": s * (p["m1"] * p["a1"] + p["m2"] * p["L1"]) * p["g"],
        "cos(phi2)": s * p["m2"] * p["a2"] * p["g"],
    }
    lag = (
        d1**2
        + ratios["phi2_dot**2"] * d2**2
        + s * c12 * d1 * d2 * sp.cos(p1 - p2)
        + ratios["cos(phi1)"] * sp.cos(p1)
        + ratios["cos(phi2)"] * sp.cos(p2)
    )
    diss = s * (p["k1"] * d1**2 + p["k2"] * (d2 - d1) ** 2) / 2
    ratios["viscous(phi1)"] = s * p["k1"]
    ratios["relative(phi1,phi2)"] = s * p["k2"]
    model = MechanicalModel(lag, ["phi1", "phi2"], dissipation=diss, name="authors")
    return model, ratios


def authors_models(which: str):
    """``{"authors (damped)": ..., "authors (no damping)": ...}`` and the ratios."""
    from lagsindy import MechanicalModel

    damped, ratios = authors_model(which)
    conservative = MechanicalModel(
        damped.lagrangian, coordinates(which), name="authors, no damping"
    )
    return {"authors (damped)": damped, "authors (no damping)": conservative}, ratios


# ----------------------------------------------------------------------------- rollouts
def windows(frame, horizon: float, max_windows: int = 20, min_every: float = 0.25):
    """Row indices of rollout windows on the joined (time-ordered) record."""
    t = frame["t"].to_numpy()
    order = np.argsort(t, kind="stable")
    t = t[order]
    span = t[-1] - t[0]
    if span < horizon:
        return [order]
    every = max(min_every, (span - horizon) / (max_windows - 1))
    out = []
    for s in np.arange(t[0], t[-1] - horizon + 1e-9, every):
        i0 = int(np.searchsorted(t, s))
        i1 = int(np.searchsorted(t, t[i0] + horizon + 1e-9, side="right"))
        out.append(order[i0:i1])
    return out


def rollouts(models: dict, X: pd.DataFrame, frame, horizon: float, max_windows=20):
    """RMS angle error of each model over the windows; ``(errors, curves)``.

    A model whose integration fails gets ``nan`` for that window.
    """
    n = X.shape[1] // 3
    Xv = X.to_numpy()
    t_all = frame["t"].to_numpy()
    out = {name: [] for name in models}
    curves = []
    for idx in windows(frame, horizon, max_windows):
        tt = t_all[idx] - t_all[idx[0]]
        x0 = Xv[idx[0], : 2 * n]
        measured = Xv[idx, :n]
        sims = {}
        for name, model in models.items():
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    sim = model.simulate(x0, tt)[:, :n]
                err = float(np.sqrt(np.mean((sim - measured) ** 2)))
                if not np.isfinite(err):
                    raise FloatingPointError
            except Exception:  # noqa: BLE001 - a learned model may blow up
                sim, err = None, float("nan")
            out[name].append(err)
            sims[name] = sim
        curves.append((tt, measured, sims))
    return {k: np.asarray(v) for k, v in out.items()}, curves


# ----------------------------------------------------------------------------- report
def _ratios(est) -> dict:
    """Learned Lagrangian and dissipation coefficients over the pivot term's.

    The pivot is ``phi1_dot**2``; a fit without it is given relative to its own
    fixed term (its ``phi1_dot**2`` row then reads ``-``).
    """
    table = est.coef_table()
    table = table[table["coefficient"] != 0]
    pivot = f"{est.coordinates_[0]}_dot**2"
    coef = table.set_index("term")["coefficient"]
    if pivot not in coef.index:  # the fit dropped it: ratios to its own fixed term
        pivot = est.fixed_term_
    scale = float(coef.loc[pivot]) if pivot in coef.index else 1.0
    return {str(r.term): float(r.coefficient) / scale for r in table.itertuples()}


def _fmt(x, digits=4):
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    return f"{x:.{digits}g}"


def _pct(x) -> str:
    return "an authors' term missing" if not np.isfinite(x) else f"{100 * x:.2f} %"


def _timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def _lagrangian_keys(truth: dict) -> set:
    return {k for k in truth if not k.startswith(("viscous(", "relative("))}


def structure(ratios: dict, truth: dict):
    """``(exact, found, n_true, largest relative ratio error over the authors' terms)``."""
    lag = {
        k: v
        for k, v in ratios.items()
        if k in _lagrangian_keys(truth) or not _is_effect(k)
    }
    true = _lagrangian_keys(truth)
    found = set(lag) & true
    worst = max(
        (abs(lag[k] / truth[k] - 1) if k in lag else np.inf for k in true),
        default=np.nan,
    )
    return set(lag) == true, len(found), len(true), float(worst), len(lag)


def _is_effect(term: str) -> bool:
    return term.split("(", 1)[0] in (
        "viscous",
        "relative",
        "drag",
        "coulomb",
        "bias",
        "gain",
    )


def fit(which, formulation, X, groups, step, **kw):
    from lagsindy import LagrangianSINDy
    from lagsindy.formulation import make_formulation

    est = LagrangianSINDy(
        library(which)[0],
        formulation=make_formulation(formulation, dt=step / 1000),
        random_state=0,
        **kw,
    )
    return _timed(lambda: est.fit(X, groups=groups))


def _n_terms(model, truth):
    if hasattr(model, "coef_"):
        return int(np.count_nonzero(model.coef_)) + int(
            np.count_nonzero(getattr(model, "dissipation_coef_", []))
        )
    return len(truth)


def study(which: str, step: int, args):
    from lagsindy import bootstrap, diagnose

    coords = coordinates(which)
    X_id, g_id, f_id = load(which, "id", step)
    X_vad, g_vad, f_vad = load(which, "vad", step)
    authors, truth = authors_models(which)
    lib, lib_name = library(which)
    lines = [
        f"Identification: {len(np.unique(g_id))} segments, {len(X_id)} samples "
        f"(every {step}th of 1 kHz); validation: {len(np.unique(g_vad))} segments, "
        f"{len(X_vad)} samples. Largest |angle|: identification "
        f"{np.abs(X_id.iloc[:, : len(coords)].to_numpy()).max(0).round(2).tolist()} rad, "
        f"validation {np.abs(X_vad.iloc[:, : len(coords)].to_numpy()).max(0).round(2).tolist()}"
        f" rad. Library: {lib_name}, {len(lib.build().terms_)} terms.\n"
    ]
    summary = dict(system=which)

    # -- 1. conservative fits, both formulations
    fits, times = {}, {}
    for form in ("strong", "weak"):
        est, wall, cpu = fit(which, form, X_id, g_id, step)
        fits[form], times[form] = est, (wall, cpu)
    # output-error refinement of the weak fit (lagsindy.refine): 1 s windows of the
    # identification segments every 0.5 s, from the estimated states
    from lagsindy import refine

    t_id = f_id["t"].to_numpy()
    for label, states in (("refined", "fit"), ("refined, data states", "data")):
        refined, wall, cpu = _timed(
            lambda states=states: refine(
                fits["weak"],
                X_id,
                groups=g_id,
                t=t_id,
                horizon=int(1000 / step),
                initial_states=states,
            )
        )
        fits[label] = refined
        times[label] = (times["weak"][0] + wall, times["weak"][1] + cpu)
    lines.append("### Conservative fits (case III, `fixed_term=None`)\n")
    states_of = {"refined": "fit", "refined, data states": "data"}
    for form, est in fits.items():
        if form.startswith("refined"):
            lines.append(
                f"- {form} (the weak fit, then `lagsindy.refine`, "
                f"`initial_states={states_of[form]!r}`): "
                f"{est.refinement_}; "
                f"fit + refine {times[form][0]:.1f} s wall / {times[form][1]:.1f} s "
                f"CPU; `{est.equation()}`"
            )
            continue
        lines.append(
            f"- {form}: normalization `{est.normalization_}`"
            + (
                f'; test window {est.window_} samples (`window="auto"`)'
                if getattr(est, "window_", None)
                else ""
            )
            + "; fit time "
            f"{times[form][0]:.1f} s wall / {times[form][1]:.1f} s CPU; "
            f"`{est.equation()}`"
        )
    lines.append("")

    # -- diagnosis of the weak fit (default catalogue; triple: also joint damping only)
    variants = {"diagnosed": ("weak", {})}
    if which == "triple":
        variants["diagnosed, joint damping only"] = (
            "weak",
            dict(catalogue=("viscous", "relative")),
        )
    if args.diagnose_strong:
        variants["diagnosed from strong"] = ("strong", {})
    reports, diag_times = {}, {}
    for label, (form, kw) in variants.items():
        rep, wall, cpu = _timed(
            lambda form=form, kw=kw: diagnose(
                fits[form], X_id, groups=g_id, max_effects=args.max_effects, **kw
            )
        )
        reports[label], diag_times[label] = rep, (wall, cpu)

    # -- the whole pipeline: weak fit -> diagnose -> refine (fitted initial states)
    diag_final = reports["diagnosed"].final
    pipeline, pipe_times = {}, {}
    refined_diag, wall, cpu = _timed(
        lambda: refine(diag_final, X_id, groups=g_id, t=t_id, horizon=int(1000 / step))
    )
    pipeline["diagnosed, refined"] = refined_diag
    pipe_times["diagnosed, refined"] = (
        times["weak"][0] + diag_times["diagnosed"][0] + wall,
        times["weak"][1] + diag_times["diagnosed"][1] + cpu,
    )
    # the diagnosed models' Lagrangian alone (dissipation and forces dropped), the
    # counterpart of the authors' model without its joint damping
    from lagsindy import MechanicalModel

    lagrangian_only, n_lagrangian = {}, {}
    for label, est in (
        ("diagnosed", diag_final),
        ("diagnosed, refined", refined_diag),
    ):
        lagrangian_only[f"{label}, Lagrangian only"] = MechanicalModel(
            est.lagrangian_, coords
        )
        n_lagrangian[f"{label}, Lagrangian only"] = int(np.count_nonzero(est.coef_))

    models = {f"{f} fit": e for f, e in fits.items()}
    models.update({label: r.final for label, r in reports.items()})
    models.update(pipeline)
    models.update(lagrangian_only)
    models.update(authors)

    # coefficient table
    ratios = {name: _ratios(m) for name, m in models.items() if hasattr(m, "coef_")}
    keys = list(dict.fromkeys(list(truth) + [k for r in ratios.values() for k in r]))
    lines.append(
        f"### Coefficients (ratios to the `{pivot_term(which)}` coefficient)\n"
    )
    lines.append("| term | authors | " + " | ".join(ratios) + " |")
    lines.append("|---|---|" + "---|" * len(ratios))
    for k in keys:
        cells = []
        for r in ratios.values():
            v = r.get(k)
            if v is None:
                cells.append("-")
            elif k in truth and truth[k]:
                cells.append(f"{_fmt(v)} ({100 * (v / truth[k] - 1):+.2f} %)")
            else:
                cells.append(_fmt(v))
        lines.append(f"| `{k}` | {_fmt(truth.get(k))} | " + " | ".join(cells) + " |")
    lines.append(
        "\nIn brackets: the relative difference from the authors' ratio. The authors' "
        "parameters: "
        + ", ".join(f"{k}={v:.4g}" for k, v in authors_parameters(which).items())
        + ".\n"
    )
    for form, est in fits.items():
        exact, found, n_true, worst, n_lag = structure(ratios[f"{form} fit"], truth)
        summary[f"{form}_terms"] = n_lag
        summary[f"{form}_exact"] = exact
        summary[f"{form}_worst"] = worst
        lines.append(
            f"- {form} fit: {n_lag} Lagrangian terms, {found}/{n_true} of the authors' "
            f"terms, exactly the authors' terms: {'yes' if exact else 'no'}; largest "
            f"ratio difference over the authors' terms {_pct(worst)}"
        )
    lines.append("")

    # -- prediction
    errs, curves = {}, {}
    for h in HORIZONS:
        errs[h], curves[h] = rollouts(models, X_vad, f_vad, h, args.max_windows)
    n_win = {h: len(next(iter(errs[h].values()))) for h in HORIZONS}
    # conservative fits against the authors' conservative model, window by window (1 s)
    conservative = [f"{f} fit" for f in fits] + [
        f"{label}, Lagrangian only" for label in ("diagnosed", "diagnosed, refined")
    ]
    paired = {
        name: paired_comparison(errs[1.0][name], errs[1.0]["authors (no damping)"])
        for name in conservative
    }
    # the same 1 s rollouts on the identification segments (the data refine fits)
    ident, _ = rollouts(
        {name: models[name] for name in conservative + ["authors (no damping)"]},
        X_id,
        f_id,
        1.0,
        args.max_windows,
    )
    ident = {name: float(np.nanmedian(e)) for name, e in ident.items()}
    lines.append("### Prediction on the validation segments\n")
    lines.append(
        "| model | terms | R^2 accelerations (identification) | R^2 accelerations "
        "(validation) | "
        + " | ".join(
            f"median rollout error, {h:g} s ({n_win[h]} windows)" for h in HORIZONS
        )
        + " | time (wall / CPU) |"
    )
    lines.append("|---|---|---|---|" + "---|" * len(HORIZONS) + "---|")
    scores = {}
    for name, model in models.items():
        scores[name] = (_score(model, X_id), _score(model, X_vad))
        if name.endswith("fit"):
            w, c = times[name[: -len(" fit")]]
            tcell = f"{w:.1f} s / {c:.1f} s"
        elif name in reports:
            form = variants[name][0]
            w = times[form][0] + diag_times[name][0]
            c = times[form][1] + diag_times[name][1]
            tcell = f"{w:.1f} s / {c:.1f} s ({form} fit + diagnosis)"
        elif name in pipeline:
            w, c = pipe_times[name]
            tcell = f"{w:.1f} s / {c:.1f} s (weak fit + diagnosis + refine)"
        else:
            tcell = "-"
        lines.append(
            f"| {name} | {n_lagrangian.get(name) or _n_terms(model, truth)} | {_fmt(scores[name][0], 5)} "
            f"| {_fmt(scores[name][1], 5)} | "
            + " | ".join(
                f"{_fmt(float(np.nanmedian(errs[h][name])), 3)} rad" for h in HORIZONS
            )
            + f" | {tcell} |"
        )
    lines.append(
        "\nRollout failures (integration blew up) count as missing: "
        + ", ".join(
            f"{name} {int(np.isnan(errs[h][name]).sum())}/{n_win[h]} at {h:g} s"
            for h in HORIZONS
            for name in models
            if np.isnan(errs[h][name]).any()
        )
        + ".\n"
        if any(np.isnan(errs[h][m]).any() for h in HORIZONS for m in models)
        else ""
    )

    lines.append(
        "Conservative models against the authors' model without damping, window by "
        "window (1 s, validation): windows where the model's error is the smaller, the "
        "mean of the error ratios, and a 95 % bootstrap interval (2000 resamples of the "
        "windows) of the difference of the medians; last column: the median 1 s "
        "rollout on the identification segments (the data the fits and refine saw; "
        f"authors without damping {_fmt(ident['authors (no damping)'], 3)} rad).\n"
    )
    lines.append(
        "| model | windows better | mean error ratio | median difference (95 %) | "
        "identification, median 1 s |"
    )
    lines.append("|---|---|---|---|---|")
    for name, pc in paired.items():
        lines.append(
            f"| {name} | {pc['wins']}/{pc['n']} | {pc['ratio']:.3f} | "
            f"{pc['diff']:+.2g} rad [{pc['low']:+.2g}, {pc['high']:+.2g}] | "
            f"{_fmt(ident[name], 3)} rad |"
        )
    lines.append("")
    if which == "triple":
        lines.append(start_check(fits["weak"], truth, X_id, g_id, t_id, step))

    # -- diagnosis reports
    for label, rep in reports.items():
        form, kw = variants[label]
        call = f"diagnose({form} fit" + (
            f", catalogue={kw['catalogue']!r})" if kw else ")"
        )
        lines.append(f"### Diagnosis: `{call}`\n")
        lines.append("```text\n" + str(rep) + "\n```\n")
        lines.append(
            f"Diagnosis time {diag_times[label][0]:.1f} s wall / "
            f"{diag_times[label][1]:.1f} s CPU ({form} fit + diagnosis "
            f"{times[form][0] + diag_times[label][0]:.1f} s wall / "
            f"{times[form][1] + diag_times[label][1]:.1f} s CPU).\n"
        )
        summary.setdefault("diag", {})[label] = dict(
            start=form,
            effects=rep.effects,
            traj=(rep.heldout_error_before, rep.heldout_error_after),
            point=(rep.pointwise_before, rep.pointwise_after),
            r2=(scores[f"{form} fit"][1], scores[label][1]),
            roll5=(
                float(np.nanmedian(errs[5.0][f"{form} fit"])),
                float(np.nanmedian(errs[5.0][label])),
            ),
            time=(
                times[form][0] + diag_times[label][0],
                times[form][1] + diag_times[label][1],
            ),
        )

    # -- the diagnosed model, refined
    w, c = pipe_times["diagnosed, refined"]
    lines.append("### Diagnosed, then refined: `refine(diagnose(weak fit).final)`\n")
    lines.append(
        f"{refined_diag.refinement_}; weak fit + diagnosis + refine {w:.1f} s wall / "
        f"{c:.1f} s CPU.\n\n```text\n{refined_diag.equation()}\n```\n"
    )
    lines.append(
        'The rows "..., Lagrangian only" of the prediction table integrate the '
        "diagnosed models' Lagrangian without their dissipation and forces, as the "
        "authors' model without its joint damping.\n"
    )

    # -- bootstrap of the diagnosed model
    n_boot = args.resamples.get(which, 0)
    if n_boot:
        rep = reports["diagnosed"]
        boot, wall, cpu = _timed(
            lambda: bootstrap(
                rep.final, X_id, groups=g_id, n_resamples=n_boot, random_state=0
            )
        )
        frame = boot.to_frame()
        scale = 1.0
        piv = frame.index[frame["term"] == pivot_term(which)]
        if len(piv):
            scale = float(frame.loc[piv[0], "coefficient"])
        lines.append(
            f"### Bootstrap of the diagnosed model ({n_boot} resamples, 95 %)\n"
        )
        head = str(boot).splitlines()[0]
        lines.append(
            f"{head}. Bootstrap time {wall:.1f} s wall / {cpu:.1f} s CPU. Terms never "
            "selected (coefficient 0, inclusion 0) are left out.\n"
        )
        lines.append(
            "| term | kind | coefficient | 95 % interval | inclusion | authors |"
        )
        lines.append("|---|---|---|---|---|---|")
        for r in frame.itertuples():
            if r.coefficient == 0 and r.inclusion == 0:
                continue
            lines.append(
                f"| `{r.term}` | {r.kind} | {_fmt(r.coefficient / scale)} | "
                f"[{_fmt(r.low / scale)}, {_fmt(r.high / scale)}] | {r.inclusion:.2f} "
                f"| {_fmt(truth.get(str(r.term)))} |"
            )
        lines.append(
            f"\n(Coefficients and intervals divided by the fitted `{pivot_term(which)}` "
            "coefficient.)\n"
        )
    pipelines = {}
    for label in list(reports) + list(pipeline):
        if label in reports:
            form = variants[label][0]
            tm = (
                times[form][0] + diag_times[label][0],
                times[form][1] + diag_times[label][1],
            )
        else:
            tm = pipe_times[label]
        exact, _, _, worst, n_lag = structure(ratios[label], truth)
        pipelines[label] = dict(exact=exact, worst=worst, terms=n_lag, time=tm)
    summary.update(
        paired=paired,
        pipelines=pipelines,
        scores=scores,
        roll={
            h: {m: float(np.nanmedian(e)) for m, e in errs[h].items()} for h in HORIZONS
        },
        times=times,
        fits=fits,
        truth=truth,
        ratios=ratios,
    )
    return "\n".join(lines), reports, curves[5.0], coords, summary


def start_check(est, truth, X, groups, t, step) -> str:
    """Refine from the authors' parameters as well as from the fit: same optimum?

    A check of the benchmark, not a lagsindy workflow: the weak fit's coefficients are
    replaced by the authors' (scaled to its fixed term) through the estimator's
    private ``_publish``, then both starts are refined with held (data) initial states.
    """
    import copy
    import dataclasses

    from lagsindy import refine

    fitted = est.fitted_
    names = [str(n) for n in est.coef_table()["term"]][: len(fitted.coef)]
    pivot = str(fitted.fixed_term)  # the term the passive fit holds at 1
    scale = float(fitted.coef[names.index(pivot)]) / truth[pivot]
    start = copy.deepcopy(est)
    start._publish(
        dataclasses.replace(
            fitted, coef=np.array([truth.get(n, 0.0) * scale for n in names])
        )
    )
    out = []
    for label, e in (("the weak fit", est), ("the authors' parameters", start)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = refine(
                e,
                X,
                groups=groups,
                t=t,
                horizon=int(1000 / step),
                initial_states="data",
            )
        ratios = _ratios(r)
        worst = max(abs(ratios[k] / truth[k] - 1) for k in _lagrangian_keys(truth))
        out.append(
            f"- from {label}: {r.refinement_}; largest ratio difference from the "
            f"authors' {_pct(worst)}"
        )
    return (
        "Refinement with held (data) initial states started from the weak fit and from "
        "the authors' conservative parameters (scaled to the fit's fixed term): the "
        "identification rollout error each start reaches.\n\n" + "\n".join(out) + "\n"
    )


def paired_comparison(errors, reference, n_boot=2000, seed=0) -> dict:
    """Window-by-window comparison of two models' rollout errors.

    ``wins``: windows where ``errors`` is the smaller; ``ratio``: mean of
    ``errors / reference``; ``diff``: difference of the medians, with a percentile
    bootstrap interval (``low``, ``high``) over resampled windows.
    """
    e, r = np.asarray(errors, float), np.asarray(reference, float)
    keep = np.isfinite(e) & np.isfinite(r)
    e, r = e[keep], r[keep]
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, e.size, (n_boot, e.size))
    boot = np.median(e[idx], axis=1) - np.median(r[idx], axis=1)
    low, high = np.percentile(boot, [2.5, 97.5])
    return dict(
        wins=int(np.sum(e < r)),
        n=int(e.size),
        ratio=float(np.mean(e / r)),
        diff=float(np.median(e) - np.median(r)),
        low=float(low),
        high=float(high),
    )


def _score(model, X) -> float:
    """R^2 of accelerations (estimators and MechanicalModels alike)."""
    n = X.shape[1] // 3
    Xa = np.asarray(X, dtype=float)
    if hasattr(model, "predict_acceleration"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pred = np.asarray(model.predict_acceleration(Xa))
    else:
        pred = model.forward_dynamics(Xa[:, :n], Xa[:, n : 2 * n])
    true = Xa[:, 2 * n :]
    pred = pred.reshape(true.shape)
    return float(1 - np.sum((pred - true) ** 2) / np.sum((true - true.mean(0)) ** 2))


def plot_rollouts(curves, coords, path, title, n_windows=2):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(coords)
    shown = curves[:n_windows]
    fig, axes = plt.subplots(
        n, len(shown), figsize=(5.5 * len(shown), 2.6 * n), squeeze=False
    )
    styles = {
        "strong fit": ("tab:orange", "--"),
        "weak fit": ("tab:red", "--"),
        "diagnosed": ("tab:blue", "-"),
        "diagnosed, joint damping only": ("tab:purple", "-."),
        "authors (damped)": ("tab:green", ":"),
        "authors (no damping)": ("tab:olive", ":"),
    }
    for j, (tt, measured, sims) in enumerate(shown):
        for i in range(n):
            ax = axes[i, j]
            ax.plot(
                tt, measured[:, i], color="black", lw=2.2, alpha=0.35, label="measured"
            )
            for name, sim in sims.items():
                if sim is not None:
                    color, ls = styles.get(name, (None, "-"))
                    ax.plot(tt, sim[:, i], color=color, ls=ls, lw=1.2, label=name)
            ax.set_ylabel(f"{coords[i]} [rad]")
            if i == n - 1:
                ax.set_xlabel("time from the window start [s]")
            if i == 0:
                ax.set_title(f"validation window {j + 1}")
    axes[0, 0].legend(loc="lower left", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def window_sweep(step, windows_) -> str:
    """The double pendulum's weak-form conservative fit at several test-function windows."""
    X_id, g_id, _ = load("double", "id", step)
    X_vad, _, _ = load("double", "vad", step)
    _, truth = authors_models("double")
    rows = [
        "| window (samples) | Lagrangian terms | authors' terms found | exactly | largest "
        "ratio difference | validation R^2 | fit time (wall / CPU) |",
        "|---|---|---|---|---|---|---|",
    ]
    for w in windows_:
        est, wall, cpu = fit("double", "weak", X_id, g_id, step, window=w)
        exact, found, n_true, worst, n_lag = structure(_ratios(est), truth)
        rows.append(
            f"| {w} | {n_lag} | {found}/{n_true} | {'yes' if exact else 'no'} | "
            f"{_pct(worst)} | {_fmt(_score(est, X_vad), 5)} | "
            f"{wall:.1f} s / {cpu:.1f} s |"
        )
    return "\n".join(rows) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="reduced size")
    parser.add_argument(
        "--step", type=int, default=10, help="thinning of the 1 kHz record"
    )
    parser.add_argument("--systems", default=",".join(SYSTEMS))
    parser.add_argument("--max-effects", type=int, default=4)
    parser.add_argument(
        "--max-windows", type=int, default=20, help="rollout windows per horizon"
    )
    parser.add_argument(
        "--no-diagnose-strong",
        dest="diagnose_strong",
        action="store_false",
        help="diagnose the weak-form fit only (default: the strong-form fit too)",
    )
    parser.add_argument(
        "--resamples",
        default="single:100,triple:30",
        help="bootstrap resamples per system, e.g. single:100,triple:30",
    )
    parser.add_argument(
        "--windows",
        default="41,161",
        help="extra weak-form windows tried on the double pendulum ('' for none)",
    )
    args = parser.parse_args(argv)
    tiny = os.environ.get("LAGSINDY_BENCH_TINY", "") not in ("", "0")
    step = args.step
    systems = args.systems.split(",")
    resamples = dict(
        (k, int(v)) for k, v in (p.split(":") for p in args.resamples.split(",") if p)
    )
    sweep = [int(w) for w in args.windows.split(",") if w]
    if args.quick:
        args.max_effects = min(args.max_effects, 2)
        resamples = {k: min(v, 20) for k, v in resamples.items()}
        sweep = []
    if tiny:
        step, systems, sweep, args.max_windows = 20, ["single"], [], 6
        args.diagnose_strong = False
        args.max_effects = 1
        resamples = {"single": 4}
    args.resamples = resamples
    suffix = "_quick" if (args.quick or tiny) else ""
    load_avg = os.getloadavg()
    text = (
        header(
            "Measured pendulums: fit, diagnosis, prediction",
            _common.command("measured", argv),
        )
        + f"- load average at start: {load_avg[0]:.2f} (1 min), {load_avg[1]:.2f} (5 min); "
        "the machine is shared, so wall times vary: CPU times are the better guide\n\n"
        + __doc__.split("\n\n", 1)[1].rsplit("\n\n    python", 1)[0]
        + "\n\n"
    )
    run_start = time.perf_counter(), time.process_time()
    summaries, bodies = [], ""
    for which in systems:
        body, reports, curves, coords, summary = study(which, step, args)
        summaries.append(summary)
        bodies += f"## {which.capitalize()} pendulum\n\n" + body + "\n"
        if which == "double" and sweep:
            bodies += (
                "### Weak form at other test-function windows (conservative fit)\n\n"
                'The default, `window="auto"`, chose the window named in the fit '
                "lines above; here each row fixes the window.\n\n"
                + window_sweep(step, sweep)
                + "\n"
            )
        _common.RESULTS.mkdir(parents=True, exist_ok=True)
        png = _common.RESULTS / f"measured_{which}_rollout{suffix}.png"
        plot_rollouts(
            curves,
            coords,
            png,
            f"measured {which} pendulum: 5 s rollouts from estimated states (validation)",
        )
        bodies += f"![rollouts]({png.name})\n\n"
        import matplotlib.pyplot as plt

        diag = _common.RESULTS / f"measured_{which}_diagnosis{suffix}.png"
        plt.close(reports["diagnosed"].plot(diag))
        bodies += f"![diagnosis]({diag.name})\n\n"
    total = time.perf_counter() - run_start[0], time.process_time() - run_start[1]
    text += summary_tables(summaries) + "\n" + bodies
    text += (
        f"Whole run: {total[0]:.0f} s wall / {total[1]:.0f} s CPU (this process; "
        f"torch threads {_torch_threads()}).\n"
    )
    write(f"measured{suffix}.md", text)
    return 0


def _torch_threads():
    import torch

    return torch.get_num_threads()


def summary_tables(summaries) -> str:
    out = ["## Summary\n", "### Conservative fits\n"]
    out.append(
        "| system | formulation | Lagrangian terms | exactly the authors' terms | largest "
        "ratio difference | validation R^2 | median rollout 1 s | median rollout 5 s "
        "| authors damped 1 s / 5 s | authors no damping 1 s / 5 s | fit time (wall / CPU) |"
    )
    out.append("|---|---|---|---|---|---|---|---|---|---|---|")
    for s in summaries:
        roll = s["roll"]
        a = "authors (damped)"
        b = "authors (no damping)"
        for form in ("strong", "weak", "refined", "refined, data states"):
            m = f"{form} fit"
            out.append(
                f"| {s['system']} | {form} | {s[form + '_terms']} | "
                f"{'yes' if s[form + '_exact'] else 'no'} | {_pct(s[form + '_worst'])} "
                f"| {_fmt(s['scores'][m][1], 5)} | {_fmt(roll[1.0][m], 3)} rad "
                f"| {_fmt(roll[5.0][m], 3)} rad | {_fmt(roll[1.0][a], 3)} / "
                f"{_fmt(roll[5.0][a], 3)} rad | {_fmt(roll[1.0][b], 3)} / "
                f"{_fmt(roll[5.0][b], 3)} rad | {s['times'][form][0]:.1f} s / "
                f"{s['times'][form][1]:.1f} s |"
            )
    out.append("\n### Diagnosis\n")
    out.append(
        "| system | variant (started from) | effects found | held-out trajectory error before -> after "
        "| held-out pointwise error before -> after | validation R^2 before -> after "
        "| median 5 s rollout before -> after (authors damped) | fit + diagnosis (wall / CPU) |"
    )
    out.append("|---|---|---|---|---|---|---|---|")
    for s in summaries:
        for label, d in s.get("diag", {}).items():
            out.append(
                f"| {s['system']} | {label} ({d['start']} fit) "
                f"| {', '.join(d['effects']) or 'none'} "
                f"| {_fmt(d['traj'][0], 3)} -> {_fmt(d['traj'][1], 3)} "
                f"| {_fmt(d['point'][0], 3)} -> {_fmt(d['point'][1], 3)} "
                f"| {_fmt(d['r2'][0], 5)} -> {_fmt(d['r2'][1], 5)} "
                f"| {_fmt(d['roll5'][0], 3)} -> {_fmt(d['roll5'][1], 3)} "
                f"({_fmt(s['roll'][5.0]['authors (damped)'], 3)}) rad "
                f"| {d['time'][0]:.1f} s / {d['time'][1]:.1f} s |"
            )
    out.append("\n### Targets\n")
    by = {s["system"]: s for s in summaries}
    if "double" in by:
        s = by["double"]
        ok = s["weak_exact"] and s["weak_worst"] <= 0.01
        out.append(
            f"- double, weak form gives the authors' six terms with ratios within 1 %: "
            f"{'met' if ok else 'missed'} ({s['weak_terms']} terms, exact: "
            f"{'yes' if s['weak_exact'] else 'no'}, largest difference "
            f"{_pct(s['weak_worst'])})"
        )
        for label, d in s["diag"].items():
            out.append(
                f"- double, {label} ({d['start']} fit): validation R^2 after diagnosis "
                f">= before: {'met' if d['r2'][1] >= d['r2'][0] else 'missed'} "
                f"({_fmt(d['r2'][0], 6)} -> {_fmt(d['r2'][1], 6)})"
            )
    if "triple" in by:
        s = by["triple"]
        for form in ("strong", "weak", "refined", "refined, data states"):
            roll = s["roll"][1.0]
            met = roll[form + " fit"] <= roll["authors (no damping)"]
            out.append(
                f"- triple, chain library, {form}: the authors' 9 terms with ratios "
                f"within 5 %: "
                f"{'met' if s[form + '_exact'] and s[form + '_worst'] <= 0.05 else 'missed'}"
                f" ({s[form + '_terms']} terms, largest difference "
                f"{_pct(s[form + '_worst'])}); median 1 s rollout "
                f"{_fmt(s['roll'][1.0][form + ' fit'], 3)} rad vs the authors' "
                f"conservative {_fmt(s['roll'][1.0]['authors (no damping)'], 3)} rad "
                f"({'met' if met else 'missed'}; better in "
                f"{s['paired'][form + ' fit']['wins']}/{s['paired'][form + ' fit']['n']}"
                f" windows, median difference 95 % interval "
                f"[{s['paired'][form + ' fit']['low']:+.2g}, "
                f"{s['paired'][form + ' fit']['high']:+.2g}] rad); fit "
                f"time {s['times'][form][0]:.1f} s wall / {s['times'][form][1]:.1f} s CPU"
            )
        for label, d in s["pipelines"].items():
            roll = s["roll"][1.0]
            met = roll[label] <= roll["authors (no damping)"]
            out.append(
                f"- triple, chain library, {label} (the model with its dissipation): "
                f"the authors' 9 terms in its Lagrangian with ratios within 5 %: "
                f"{'met' if d['exact'] and d['worst'] <= 0.05 else 'missed'} "
                f"({d['terms']} Lagrangian terms, largest difference "
                f"{_pct(d['worst'])}); median 1 s rollout {_fmt(roll[label], 3)} rad vs "
                f"the authors' conservative {_fmt(roll['authors (no damping)'], 3)} rad "
                f"({'met' if met else 'missed'}; authors damped "
                f"{_fmt(roll['authors (damped)'], 3)} rad); time "
                f"{d['time'][0]:.1f} s wall / {d['time'][1]:.1f} s CPU"
            )
        for label in ("diagnosed", "diagnosed, refined"):
            roll = s["roll"][1.0]
            name = f"{label}, Lagrangian only"
            met = roll[name] <= roll["authors (no damping)"]
            out.append(
                f"- triple, {name} (dissipation dropped): median 1 s rollout "
                f"{_fmt(roll[name], 3)} rad vs the authors' conservative "
                f"{_fmt(roll['authors (no damping)'], 3)} rad "
                f"({'met' if met else 'missed'})"
            )
        for label, d in s["diag"].items():
            out.append(
                f"- triple, {label} ({d['start']} fit): median 5 s validation rollout "
                f"<= 0.007 rad: "
                f"{'met' if d['roll5'][1] <= 0.007 else 'missed'} "
                f"({_fmt(d['roll5'][1], 3)} rad; authors damped "
                f"{_fmt(s['roll'][5.0]['authors (damped)'], 3)} rad); joint damping "
                f"found: {', '.join(e for e in d['effects'] if e.startswith(('viscous', 'relative'))) or 'none'}"
            )
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    main()
