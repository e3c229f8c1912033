"""Chain libraries: the paper's systems and the real MultiArm triple pendulum.

Part 1, robustness. For the paper's single, cart and double pendulum (the spherical
pendulum is not a planar chain: ``phi_dot**2*sin(theta)**2`` is not a chain term), active
and passive, the same data sets are fitted with the paper's library
(``system.paper_library()``) and with :meth:`CandidateLibrary.chain` over the same
coordinates, side by side. Noise protocols ``sensor`` (noise on the positions only,
derivatives by the GCV P-spline) and ``paper`` (independent noise on q, q_dot, q_ddot),
a grid of sigma, a few seeds. Per cell: the fraction of seeds with exactly the true
terms and the median relative coefficient error (passive: of the ratios to the fixed
term). Passive fits use the paper's fixed term and prior (case III). Weak form
(``formulation="weak"``, ``dt=0.01``, trajectories as groups) unless ``--formulation``.

Part 2, the MultiArm triple pendulum (real encoder data, Kaheman et al.,
arXiv:2205.06231, MIT license, ``shared/data/multiarm_pendulum``): the recording read
with ``scipy.io.loadmat``, thinned to 100 Hz, angles ``phi = theta - pi``, derivatives
by the GCV P-spline per segment; conservative fits (case III, ``fixed_term=None``,
weak and strong form) and a weak fit with a viscous term per coordinate, with the
12-term chain library on the identification segments; their coefficients as ratios
beside the authors' fitted model; median RMS angle error of 1 s rollouts on the
validation segments against the authors' model with and without its joint damping.

    python -m benchmarks.chains            # results/chains.md
    python -m benchmarks.chains --quick    # fewer seeds and levels: results/chains_quick.md
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time
import warnings

import numpy as np

from . import _common
from ._common import header, write
from ._evaluate import compare_structure, fmt_sigma, tiny

SYSTEMS = ("single_pendulum", "cart_pendulum", "double_pendulum")
PROTOCOLS = ("sensor", "paper")
SIGMAS = (1e-3, 1e-2, 2e-2, 4e-2, 1e-1)
LIBRARIES = ("paper", "chain")


def chain_library(system):
    """The chain library over a system's coordinates (its angles revolute)."""
    from lagsindy import CandidateLibrary

    return CandidateLibrary.chain(system.coordinates, angles=system.angles)


def _cell(task):
    import torch

    torch.set_num_threads(1)
    from lagsindy import LagrangianSINDy
    from lagsindy.formulation import make_formulation
    from lagsindy.systems import SYSTEMS as REGISTRY
    from lagsindy.systems import make_dataset

    name, mode, protocol, sigma, seed, n_traj, duration, formulation = task
    system = REGISTRY[name]()
    passive = mode == "passive"
    data = make_dataset(
        system,
        n_trajectories=n_traj,
        duration=duration,
        excitation=None if passive else "paper",
        noise=sigma,
        protocol=protocol,
        random_state=1000 * seed + 23,
    )
    out = []
    for which in LIBRARIES:
        library = system.paper_library() if which == "paper" else chain_library(system)
        kw = (
            dict(fixed_term=system.fixed_term, unpenalized=system.prior_terms)
            if passive
            else {}
        )
        est = LagrangianSINDy(
            library,
            formulation=make_formulation(formulation, dt=0.01),
            random_state=0,
            **kw,
        )
        start = time.perf_counter()
        error = None
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                est.fit(data.X, data.tau, groups=data.groups)
            cmp = compare_structure(system, est, up_to_scale=passive)
            correct, err = cmp["correct"], cmp["coef_error"]
        except (ValueError, FloatingPointError, RuntimeError) as exc:
            correct, err, error = False, np.inf, str(exc)[:160]
        out.append(
            dict(
                system=name,
                mode=mode,
                protocol=protocol,
                sigma=sigma,
                seed=seed,
                library=which,
                n_terms=len(library),
                correct=correct,
                coef_error=err,
                time=time.perf_counter() - start,
                error=error,
            )
        )
    return out


def robustness(sigmas, seeds, n_traj, duration, formulation, processes):
    tasks = [
        (name, mode, protocol, s, seed, n_traj, duration, formulation)
        for name in SYSTEMS
        for mode in ("active", "passive")
        for protocol in PROTOCOLS
        for s in sigmas
        for seed in range(seeds)
    ]
    if processes > 1:
        with mp.get_context("spawn").Pool(processes) as pool:
            rows = [r for cell in pool.map(_cell, tasks) for r in cell]
    else:
        rows = [r for t in tasks for r in _cell(t)]
    return rows


def robustness_table(rows, sigmas) -> str:
    import pandas as pd

    df = pd.DataFrame(rows)
    lines = [
        "| system | mode | protocol | library (terms) | "
        + " | ".join(f"sigma {fmt_sigma(s)}" for s in sigmas)
        + " | largest sigma, all seeds correct | median fit time |",
        "|---|---|---|---|" + "---|" * len(sigmas) + "---|---|",
    ]
    for (name, mode, protocol), group in df.groupby(
        ["system", "mode", "protocol"], sort=False
    ):
        for which in LIBRARIES:
            sub = group[group["library"] == which]
            cells, best = [], None
            ok_so_far = True
            for s in sigmas:
                c = sub[sub["sigma"] == s]
                frac = c["correct"].mean()
                if c["error"].notna().all():
                    cells.append("fit failed")
                else:
                    med = 100 * c["coef_error"].median()
                    cells.append(f"{frac:.0%}, {med:.2g} %")
                ok_so_far = ok_so_far and frac == 1.0
                if ok_so_far:
                    best = s
            size = int(sub["n_terms"].max())
            lines.append(
                f"| {name} | {mode} | {protocol} | {which} ({size}) | "
                + " | ".join(cells)
                + f" | {'none' if best is None else fmt_sigma(best)} "
                f"| {sub['time'].median():.2f} s |"
            )
    failures = df[df["error"].notna()]
    if len(failures):
        lines.append("\nFailed fits (counted as wrong):\n")
        for msg, group in failures.groupby("error"):
            lines.append(f"- {len(group)} x: {msg}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- MultiArm
def load_triple(split: str, step: int = 10):
    """``(X, groups, t)`` of the MultiArm triple pendulum, ``phi = theta - pi``."""
    import pandas as pd
    from scipy.io import loadmat

    from lagsindy.differentiation import derivatives
    from lagsindy.io import find_multiarm_pendulum

    path = find_multiarm_pendulum() / "TriplePendulumDataForParameterEstimation.mat"
    mat = loadmat(path)
    segments = zip(mat["Y_" + split].ravel(), mat["Time_" + split].ravel())
    qs, ts, gs = [], [], []
    for g, (y, t) in enumerate(segments):
        y = np.asarray(y, dtype=float)[:3, ::step].T
        t = np.asarray(t, dtype=float).ravel()[::step]
        qs.append(y - np.pi)
        ts.append(t)
        gs.append(np.full(len(t), g))
    q, t, groups = np.concatenate(qs), np.concatenate(ts), np.concatenate(gs)
    X = derivatives(q, t, groups=groups, method="pspline")
    names = ["phi1", "phi2", "phi3"]
    cols = names + [n + "_dot" for n in names] + [n + "_ddot" for n in names]
    return pd.DataFrame(X, columns=cols), groups, t


def rollout_errors(models, X, groups, t_all, horizon):
    """RMS angle error of each model over consecutive windows of ``horizon`` s."""
    n = X.shape[1] // 3
    out = {name: [] for name in models}
    Xv = X.to_numpy()
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
            for name, model in models.items():
                try:
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        sim = model.simulate(Xv[idx[0], : 2 * n], tt)[:, :n]
                    err = float(np.sqrt(np.mean((sim - Xv[idx, :n]) ** 2)))
                except Exception:  # noqa: BLE001 - a learned model may blow up
                    err = float("nan")
                out[name].append(err)
            start = stop
    return {k: np.asarray(v) for k, v in out.items()}


def multiarm(formulation: str, horizon: float = 1.0) -> str:
    from lagsindy import CandidateLibrary, LagrangianSINDy, MechanicalModel, refine
    from lagsindy.dissipation import DissipationLibrary
    from lagsindy.systems import multiarm_triple_pendulum

    X_id, g_id, t_id = load_triple("id")
    X_vad, g_vad, t_vad = load_triple("vad")
    names = ["phi1", "phi2", "phi3"]
    library = CandidateLibrary.chain(names)
    variants = {
        formulation: dict(formulation=formulation),
        "strong": dict(formulation="strong"),
        f"{formulation} + viscous": dict(
            formulation=formulation, dissipation=DissipationLibrary(["viscous"])
        ),
    }
    fits, times = {}, {}
    for label, kw in variants.items():
        durations = []
        for _ in range(2):  # the first fit in a process pays torch's one-time set-up
            start, cpu = time.perf_counter(), time.process_time()
            est = LagrangianSINDy(library, random_state=0, **kw)
            est.fit(X_id, groups=g_id)
            durations.append((time.perf_counter() - start, time.process_time() - cpu))
        fits[label], times[label] = est, durations
    # Output-error refinement (lagsindy.refine) of the weak fits: 1 s windows of the
    # identification segments, every 0.5 s, from the estimated states.
    refined = {}
    variants = [
        (label, states, tag)
        for label in (formulation, f"{formulation} + viscous")
        for states, tag in (("fit", "refined"), ("data", "refined, data states"))
    ]
    for label, states, tag in variants:
        start, cpu = time.perf_counter(), time.process_time()
        refined[f"{label}, {tag}"] = refine(
            fits[label], X_id, groups=g_id, t=t_id, horizon=100, initial_states=states
        )
        times[f"{label}, {tag}"] = [
            (
                times[label][-1][0] + time.perf_counter() - start,
                times[label][-1][1] + time.process_time() - cpu,
            )
        ] * 2
    fits.update(refined)
    authors = multiarm_triple_pendulum()
    conservative = MechanicalModel(
        authors.lagrangian, names, name="authors, no damping"
    )
    truth = library.decompose(authors.lagrangian)[0]
    lines = [
        f"Identification: {len(np.unique(g_id))} segments, {len(X_id)} samples "
        f"(100 Hz); validation: {len(np.unique(g_vad))} segments, {len(X_vad)} samples. "
        f"Library: `CandidateLibrary.chain({names})`, {len(library)} terms. "
        "Fits of case III with `fixed_term=None`: conservative (weak and strong "
        "form), and the weak form with a viscous term per coordinate "
        '(`DissipationLibrary(["viscous"])`); the two weak fits also refined by '
        "the error of their 1 s rollouts on the identification segments "
        "(`lagsindy.refine(est, X_id, groups=..., t=..., horizon=100)`: windows of "
        "100 samples every 50, structure kept, one coefficient held; 'refined': "
        "each window's initial state fitted too (the default), 'refined, data "
        "states': held at the P-spline estimates, as the validation rollouts "
        "start).\n",
        "| term | authors' model | "
        + " | ".join(f"{f} fit" for f in fits)
        + " | "
        + " | ".join(f"{f} error" for f in fits)
        + " |",
        "|---|---|" + "---|" * (2 * len(fits)),
    ]
    piv = library.index("phi1_dot**2")
    ratios = {f: e.coef_ / e.coef_[piv] for f, e in fits.items()}
    true_r = truth / truth[piv]
    for k, term in enumerate(library.terms_):
        if true_r[k] == 0 and all(r[k] == 0 for r in ratios.values()):
            continue
        errs = [
            f"{100 * (r[k] / true_r[k] - 1):+.2f} %" if true_r[k] else "extra"
            for r in ratios.values()
        ]
        lines.append(
            f"| `{term}` | {true_r[k]:.4g} | "
            + " | ".join(f"{r[k]:.4g}" for r in ratios.values())
            + " | "
            + " | ".join(errs)
            + " |"
        )
    lines.append(
        "\nRatios to the `phi1_dot**2` coefficient; the authors' model from their fitted "
        "parameters (`EstimatedParameters_TriplePendulum.mat`, compound links, "
        "`lagsindy.systems.multiarm_triple_pendulum`).\n"
    )
    for f, e in fits.items():
        r, t = ratios[f], true_r
        same = np.array_equal(r != 0, t != 0)
        worst = np.max(np.abs(r[t != 0] / t[t != 0] - 1))
        if "viscous" in f:
            d = ", ".join(
                f"{t.name} {c / e.coef_[piv]:.4g}"
                for t, c in zip(e.dissipation_terms_, e.dissipation_coef_)
            )
            lines.append(f"- {f}: dissipation (same units): {d}")
        if "refined" in f:
            timing = (
                f"fit (second) + refine {times[f][0][0]:.2f} s wall / "
                f"{times[f][0][1]:.2f} s CPU; {e.refinement_}"
            )
        else:
            timing = (
                f"fit time {times[f][0][0]:.2f} s wall / {times[f][0][1]:.2f} s CPU "
                f"(first fit in the process), {times[f][1][0]:.2f} s / "
                f"{times[f][1][1]:.2f} s (second)"
            )
        lines.append(
            f"- {f}: exact 9-term structure: {same}; largest ratio error "
            f"{100 * worst:.2f} %; {timing}"
        )
    models = {f"{f} fit": e for f, e in fits.items()}
    for f, e in fits.items():
        if "viscous" in f:
            models[f"{f} fit, Lagrangian only"] = MechanicalModel(
                e.model_.lagrangian, names, name=f"{f}, no damping"
            )
    models["authors' model"] = authors
    models["authors' model without damping"] = conservative
    err = rollout_errors(models, X_vad, g_vad, t_vad, horizon)
    lines.append(
        f"\nRollouts of {horizon:g} s from the estimated state at the start of each "
        "window of the validation segments, RMS angle error against the measured "
        "angles (rad):\n"
    )
    lines.append("| model | windows | median | mean |")
    lines.append("|---|---|---|---|")
    for name, e in err.items():
        lines.append(
            f"| {name} | {len(e)} | {np.nanmedian(e):.5f} | {np.nanmean(e):.5f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--formulation", default="weak", choices=["weak", "strong"])
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--no-multiarm", action="store_true")
    parser.add_argument(
        "--multiarm-only",
        action="store_true",
        help="rerun the MultiArm section only, replacing it in chains.md",
    )
    args = parser.parse_args(argv)
    if args.multiarm_only:
        path = _common.RESULTS / "chains.md"
        old = path.read_text()
        cut = old.index("## MultiArm triple pendulum")
        section = (
            "## MultiArm triple pendulum (real data)\n\n"
            f"(This section rerun alone: `{_common.command('chains', argv)}`, "
            f"{time.strftime('%Y-%m-%d')}.)\n\n" + multiarm(args.formulation)
        )
        write("chains.md", old[:cut] + section)
        return section
    if tiny():
        sigmas, seeds, n_traj, duration = (1e-2,), 1, 3, 3.0
    elif args.quick:
        sigmas, seeds, n_traj, duration = (1e-3, 2e-2, 1e-1), 1, 10, 4.0
    else:
        sigmas, seeds, n_traj, duration = SIGMAS, 2, 10, 4.0
    start = time.perf_counter()
    rows = robustness(sigmas, seeds, n_traj, duration, args.formulation, args.processes)
    elapsed = time.perf_counter() - start
    text = header("Chain libraries", _common.command("chains", argv))
    text += (
        "## The paper's systems: paper library vs chain library\n\n"
        f"{n_traj} trajectories x {duration:g} s x 100 Hz per data set, {seeds} seed(s) "
        f"per cell, formulation `{args.formulation}`. Cells: fraction of seeds with "
        "exactly the true terms, median relative coefficient error (passive: after "
        "the least-squares scale). The spherical pendulum is left out: it is not a "
        "planar chain (`phi_dot**2*sin(theta)**2` is no chain term). "
        f"Wall time {elapsed:.0f} s on {args.processes} process(es).\n\n"
    )
    text += robustness_table(rows, sigmas) + "\n\n"
    if not args.no_multiarm and not tiny():
        text += "## MultiArm triple pendulum (real data)\n\n"
        text += multiarm(args.formulation)
    suffix = "_quick" if args.quick else ""
    name = "chains_tiny.md" if tiny() else f"chains{suffix}.md"
    write(name, text)
    return text


if __name__ == "__main__":
    main()
