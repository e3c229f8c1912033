"""Measured data: Lagrangians of a real single and double pendulum, then the loop closed.

Data: the MultiArm-Pendulum free-swing recordings (encoders, 1 kHz, no input; cart
locked) of Kaheman, Fasel, Bramburger, Strom, Kutz and Brunton, "The Experimental
Multi-Arm Pendulum on a Cart: A Benchmark System for Chaos, Learning, and Control",
arXiv:2205.06231 (2022), MIT license; in ``../shared/data/multiarm_pendulum``. The
authors split each record into identification and validation segments; we fit on the
former only and report on both.

Per pendulum:

1. positions thinned to 100 Hz (``--step``), angles shifted to ``phi = theta - pi``
   (zero hanging down), velocities and accelerations estimated per segment by the
   GCV P-spline (:mod:`lagsindy.differentiation`);
2. a conservative fit, case III (no input), ``fixed_term=None``: the search over the
   mass normalization and every candidate term;
3. :func:`lagsindy.diagnose` on the identification data: which missing effects the
   residual points to, their coefficients, the held-out acceleration error after each;
4. before/after: R^2 of accelerations on the validation segments, and rollouts (the
   learned equations integrated from the measured state at the start of each
   validation window) against the measured angles, beside the authors' own physical
   model (their fitted parameters, read from the ``EstimatedParameters_*.mat`` files).

Passive data fix a Lagrangian only up to a factor, so the coefficients are compared as
ratios to the ``phi1_dot**2`` (``phi_dot**2``) coefficient, and a Rayleigh coefficient
``d`` (force ``-d * phi_dot``) in those units corresponds to ``2 k / J`` for the
authors' joint coefficient ``k`` (torque ``-k * phi_dot``) and inertia ``J``.

    python -m benchmarks.measured            # results/measured.md + measured_*.png
    python -m benchmarks.measured --quick    # fewer diagnosis steps, *_quick
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

G_NOTE = "g as fitted by the authors"


# ----------------------------------------------------------------------------- data
def load(which: str, split: str, step: int):
    """``(X, groups, frame)``: the recording thinned by ``step``, in phi = theta - pi."""
    from lagsindy.differentiation import derivatives
    from lagsindy.io import load_multiarm_pendulum

    frame = load_multiarm_pendulum(which=which, split=split)
    frame = frame[frame.groupby("trajectory").cumcount().to_numpy() % step == 0]
    angles = ["theta"] if which == "single" else ["theta1", "theta2"]
    names = [a.replace("theta", "phi") for a in angles]
    q = frame[angles].to_numpy() - np.pi
    groups = frame["trajectory"].to_numpy()
    X = derivatives(q, frame["t"].to_numpy(), groups=groups, method="pspline")
    columns = names + [f"{n}_dot" for n in names] + [f"{n}_ddot" for n in names]
    return pd.DataFrame(X, columns=columns), groups, frame


def authors_parameters(which: str) -> dict:
    from scipy.io import loadmat

    from lagsindy.io import find_multiarm_pendulum

    name = "Single" if which == "single" else "Double"
    values = loadmat(
        find_multiarm_pendulum() / f"EstimatedParameters_{name}Pendulum.mat"
    )
    values = np.asarray(values["EstimatedParameters"], dtype=float).ravel()
    keys = (
        ["a1", "m1", "I1", "k1", "g"]
        if which == "single"
        else ["m1", "m2", "a1", "a2", "L1", "I1", "I2", "k1", "k2", "g"]
    )
    return dict(zip(keys, values))


def authors_model(which: str):
    """The authors' rigid-body model in phi = theta - pi, scaled so phi1_dot**2 has 1.

    Joint torques ``-k1 * phi1_dot`` and ``-k2 * (phi2_dot - phi1_dot)`` (absolute
    angles, the second joint between the links) enter as Rayleigh terms.
    Returns ``(MechanicalModel, ratios)`` with the ratios of its Lagrangian terms.
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


# ----------------------------------------------------------------------------- rollouts
def rollouts(models: dict, X: pd.DataFrame, groups, frame, horizon: float):
    """RMS angle error of each model over windows of ``horizon`` s of every segment.

    Each window starts from the estimated state (P-spline positions and velocities) at
    its first sample; the error is against the measured angles. A model whose
    integration fails gets ``nan`` for that window.
    """
    n = X.shape[1] // 3
    t_all = frame["t"].to_numpy()
    out = {name: [] for name in models}
    curves = []
    for g in np.unique(groups):
        rows = np.flatnonzero(groups == g)
        t = t_all[rows] - t_all[rows[0]]
        start = 0
        while start < len(rows) - 1:
            stop = np.searchsorted(t, t[start] + horizon, side="right")
            idx = rows[start:stop]
            if len(idx) < 10:
                break
            tt = t_all[idx] - t_all[idx[0]]
            x0 = X.iloc[idx[0], : 2 * n].to_numpy()
            measured = X.iloc[idx, :n].to_numpy()
            sims = {}
            for name, model in models.items():
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        sim = model.simulate(x0, tt)[:, :n]
                    err = float(np.sqrt(np.mean((sim - measured) ** 2)))
                except Exception:  # noqa: BLE001 - a learned model may blow up
                    sim, err = None, float("nan")
                out[name].append(err)
                sims[name] = sim
            curves.append((tt, measured, sims))
            start = stop
    return {k: np.asarray(v) for k, v in out.items()}, curves


# ----------------------------------------------------------------------------- report
def _ratios(est) -> dict:
    """Learned Lagrangian and dissipation coefficients over the pivot term's."""
    table = est.coef_table()
    table = table[table["coefficient"] != 0]
    pivot = est.fixed_term_
    scale = float(table.set_index("term").loc[pivot, "coefficient"]) if pivot else 1.0
    return {str(r.term): float(r.coefficient) / scale for r in table.itertuples()}


def _fmt(x, digits=4):
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    return f"{x:.{digits}g}"


def sampling_sensitivity(which, library, steps, truth) -> str:
    """The conservative fit at several thinnings of the 1 kHz record, both formulations."""
    from lagsindy import LagrangianSINDy

    rows = [
        "| sampling | formulation | terms | normalization | authors' terms found "
        "| validation R^2 | fit time |",
        "|---|---|---|---|---|---|---|",
    ]
    physical = {k for k in truth if not k.startswith(("viscous(", "relative("))}
    for step in steps:
        X_id, g_id, _ = load(which, "id", step)
        X_vad, _, _ = load(which, "vad", step)
        for form in ("strong", "weak"):
            est = LagrangianSINDy(
                library, formulation=form, dt=step / 1000, random_state=0
            )
            start = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                est.fit(X_id, groups=g_id)
            elapsed = time.perf_counter() - start
            found = set(_ratios(est))
            exact = (
                "exactly"
                if found == physical
                else f"{len(found & physical)}/{len(physical)}"
            )
            rows.append(
                f"| {1000 // step} Hz | {form} | {len(found)} | {est.normalization_} | {exact} "
                f"| {_fmt(_score(est, X_vad), 5)} | {elapsed:.1f} s |"
            )
    return "\n".join(rows) + "\n"


def study(which: str, step: int, max_effects: int, horizon: float, quick: bool):
    from lagsindy import CandidateLibrary, LagrangianSINDy, diagnose

    X_id, g_id, f_id = load(which, "id", step)
    X_vad, g_vad, f_vad = load(which, "vad", step)
    coords = ["phi"] if which == "single" else ["phi1", "phi2"]
    if which == "single":
        library = CandidateLibrary.polynomial(
            coords, angles=coords, degree=2, raw_angles=True
        )
        pivot_term = "phi_dot**2"
    else:  # the paper's double-pendulum library, in phi1, phi2
        library = CandidateLibrary.separated(coords, angles="all", degree=2)
        pivot_term = "phi1_dot**2"
    lines = []
    start = time.perf_counter()
    est = LagrangianSINDy(library, random_state=0).fit(X_id, groups=g_id)
    fit_time = time.perf_counter() - start
    # The paper's normalization (one fixed term) on the same data, for comparison.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        pinned = LagrangianSINDy(library, fixed_term=pivot_term, random_state=0)
        pinned.fit(X_id, groups=g_id)
    start = time.perf_counter()
    report = diagnose(est, X_id, groups=g_id, max_effects=max_effects)
    diag_time = time.perf_counter() - start
    final = report.final
    authors, truth = authors_model(which)

    lines.append(
        f"Identification: {len(np.unique(g_id))} segments, {len(X_id)} samples "
        f"(every {step}th of 1 kHz); validation: {len(np.unique(g_vad))} segments, "
        f"{len(X_vad)} samples. Largest |angle|: identification "
        f"{np.abs(X_id.iloc[:, : len(coords)].to_numpy()).max(0).round(2).tolist()} rad, "
        f"validation {np.abs(X_vad.iloc[:, : len(coords)].to_numpy()).max(0).round(2).tolist()}"
        " rad (the validation segments are the end of a decaying record, so they test "
        f"smaller motion). Library: {len(est.term_names_)} terms "
        f"({'degree 2 over {phi, phi_dot, cos phi, sin phi}' if which == 'single' else 'the paper double-pendulum library (separated, degree 2)'}).\n"
    )
    lines.append("#### Conservative fit (case III, `fixed_term=None`)\n")
    lines.append(
        f"- chosen normalization: `{est.normalization_}` "
        f"(term with coefficient 1: `{est.fixed_term_}`); fit time {fit_time:.1f} s"
    )
    lines.append(f"- learned: `{est.equation()}`")
    lines.append(
        f'- with the paper\'s normalization (`fixed_term="{pivot_term}"`): '
        f"{int(np.count_nonzero(pinned.coef_))} terms, validation R^2 "
        f"{_fmt(_score(pinned, X_vad))}: `{pinned.equation()}`\n"
    )
    lines.append("#### Residual diagnosis (`lagsindy.diagnose`)\n")
    lines.append("```text\n" + str(report) + "\n```\n")
    lines.append(f"Diagnosis time {diag_time:.1f} s.\n")

    lines.append("#### Coefficients (ratios to the `" + pivot_term + "` coefficient)\n")
    before, after = _ratios(est), _ratios(final)
    keys = list(dict.fromkeys(list(truth) + list(before) + list(after)))
    lines.append("| term | authors' model | conservative fit | after diagnosis |")
    lines.append("|---|---|---|---|")
    for k in keys:
        lines.append(
            f"| `{k}` | {_fmt(truth.get(k))} | {_fmt(before.get(k))} | {_fmt(after.get(k))} |"
        )
    lines.append(
        "\nThe authors' coefficients: their fitted parameters "
        f"({', '.join(f'{k}={v:.4g}' for k, v in authors_parameters(which).items())}) "
        "in the same units (scaled by 2/J).\n"
    )

    models = {
        "conservative fit": est,
        "after diagnosis": final,
        "authors' model": authors,
    }
    err_id, _ = rollouts(models, X_id, g_id, f_id, horizon)
    err_vad, curves = rollouts(models, X_vad, g_vad, f_vad, horizon)
    lines.append(
        f"#### Prediction (validation segments unless noted; rollouts of {horizon:g} s)\n"
    )
    lines.append(
        "| model | terms | R^2 accelerations (identification) | R^2 accelerations "
        "(validation) | rollout RMS angle error, median (identification) "
        "| rollout RMS angle error, median (validation) |"
    )
    lines.append("|---|---|---|---|---|---|")
    for name, model in models.items():
        n_terms = (
            int(np.count_nonzero(model.coef_))
            + int(np.count_nonzero(getattr(model, "dissipation_coef_", [])))
            if hasattr(model, "coef_")
            else len(truth)
        )
        lines.append(
            f"| {name} | {n_terms} | {_fmt(_score(model, X_id))} | {_fmt(_score(model, X_vad))} "
            f"| {_fmt(np.nanmedian(err_id[name]), 3)} rad | {_fmt(np.nanmedian(err_vad[name]), 3)} rad |"
        )
    lines.append(
        f"\n({len(err_vad[next(iter(models))])} validation windows, "
        f"{len(err_id[next(iter(models))])} identification windows.)\n"
    )
    steps = (
        ()
        if os.environ.get("LAGSINDY_BENCH_TINY", "") not in ("", "0")
        else ((10, 20) if quick else (5, 10, 20))
    )
    if steps:
        lines.append(
            "#### Sensitivity to the sampling rate and the formulation (conservative fit)\n\n"
            'The weak form (`formulation="weak"`, window 81 samples, noise correction '
            '`noise_cov="auto"`) is the one that removes the noise bias on synthetic '
            "data (`robustness.md`); its noise correction assumes white noise on q and "
            "q_dot, which spline-smoothed encoder data do not have.\n"
        )
        lines.append(sampling_sensitivity(which, library, steps, truth))
    summary = dict(
        system=which,
        normalization=est.normalization_,
        equation=est.equation(),
        effects=[s.candidate.name for s in report.steps],
        heldout_before=report.heldout_error_before,
        heldout_after=report.steps[-1].heldout_error
        if report.steps
        else report.heldout_error_before,
        r2_before=_score(est, X_vad),
        r2_after=_score(final, X_vad),
        r2_authors=_score(authors, X_vad),
        rollout_before=float(np.nanmedian(err_vad["conservative fit"])),
        rollout_after=float(np.nanmedian(err_vad["after diagnosis"])),
        rollout_authors=float(np.nanmedian(err_vad["authors' model"])),
        fit_time=fit_time,
    )
    return "\n".join(lines), report, curves, coords, summary


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
        "conservative fit": ("tab:red", "--"),
        "after diagnosis": ("tab:blue", "-"),
        "authors' model": ("tab:green", ":"),
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


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="reduced size")
    parser.add_argument(
        "--step", type=int, default=10, help="thinning of the 1 kHz record"
    )
    parser.add_argument("--systems", default="single,double")
    args = parser.parse_args(argv)
    tiny = os.environ.get("LAGSINDY_BENCH_TINY", "") not in ("", "0")
    step, max_effects = args.step, 3
    systems = args.systems.split(",")
    if args.quick:
        max_effects = 2
    if tiny:
        step, max_effects, systems = 20, 1, ["single"]
    suffix = "_quick" if (args.quick or tiny) else ""
    horizons = {"single": 5.0, "double": 0.5}
    text = (
        header("Measured pendulums: fit, diagnosis, prediction")
        + __doc__.split("\n\n", 1)[1].rsplit("\n\n    python", 1)[0]
        + "\n\n"
    )
    summaries = []
    for which in systems:
        body, report, curves, coords, summary = study(
            which, step, max_effects, horizons[which], args.quick or tiny
        )
        summaries.append(summary)
        text += f"## {which.capitalize()} pendulum\n\n" + body + "\n"
        _common.RESULTS.mkdir(parents=True, exist_ok=True)
        png = _common.RESULTS / f"measured_{which}_rollout{suffix}.png"
        plot_rollouts(
            curves,
            coords,
            png,
            f"measured {which} pendulum: rollouts from measured states",
        )
        text += f"![rollouts]({png.name})\n\n"
        import matplotlib.pyplot as plt

        diag = _common.RESULTS / f"measured_{which}_diagnosis{suffix}.png"
        plt.close(report.plot(diag))
        text += f"![diagnosis]({diag.name})\n\n"
    rows = [
        "| system | normalization | effects found | held-out accel. error before -> after "
        "| validation R^2 before -> after (authors) | rollout error before -> after "
        "(authors) |",
        "|---|---|---|---|---|---|",
    ]
    for s in summaries:
        rows.append(
            f"| {s['system']} | {s['normalization']} | {', '.join(s['effects']) or 'none'} "
            f"| {_fmt(s['heldout_before'], 3)} -> {_fmt(s['heldout_after'], 3)} "
            f"| {_fmt(s['r2_before'], 5)} -> {_fmt(s['r2_after'], 5)} ({_fmt(s['r2_authors'], 5)}) "
            f"| {_fmt(s['rollout_before'], 3)} -> {_fmt(s['rollout_after'], 3)} "
            f"({_fmt(s['rollout_authors'], 3)}) rad |"
        )
    text = text.replace("\n## ", "\n## Summary\n\n" + "\n".join(rows) + "\n\n## ", 1)
    write(f"measured{suffix}.md", text)
    return 0


if __name__ == "__main__":
    main()
