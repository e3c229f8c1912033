"""The defaults issue's acceptance figures: the estimator as a user gets it.

Everything here is ``LagrangianSINDy(system.paper_library())`` with nothing set, fitted
with the trajectories as ``groups`` (so ``formulation="auto"`` picks the weak form and
estimates the sampling interval and the noise from the data):

1. the forced cart-pendulum, 20 trajectories, independent noise 0.02 on q, q_dot and
   q_ddot (protocol ``paper``): target, coefficients within 1 %;
2. noise on the positions only at 1e-2 rad, the derivatives by the default P-spline
   (protocol ``sensor``), each of the paper's four systems, forced, 20 trajectories:
   target, exactly the true terms and coefficients within 3 %.

Beside each, the strong form on the same data (the 0.1 default) for comparison.

    python -m benchmarks.defaults            # results/defaults.md
    python -m benchmarks.defaults --quick    # results/defaults_quick.md
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from ._common import header, write
from ._evaluate import tiny

SYSTEMS = ("single_pendulum", "cart_pendulum", "double_pendulum", "spherical_pendulum")


def _fit(system, data, formulation):
    from lagsindy import LagrangianSINDy

    kw = {} if formulation == "defaults" else {"formulation": formulation}
    est = LagrangianSINDy(system.paper_library(), **kw)
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        est.fit(data.X, data.tau, groups=data.groups)
    seconds = time.perf_counter() - start
    true = system.true_coefficients(est.library_)
    coef = np.asarray(est.coef_, dtype=float)
    kept = true != 0
    return {
        "formulation": formulation,
        "used": est.formulation_
        + (f", window {est.window_}" if getattr(est, "window_", None) else ""),
        "correct": bool(np.array_equal(coef != 0, kept)),
        "n_terms": int((coef != 0).sum()),
        "coef_error": float(np.linalg.norm(coef - true) / np.linalg.norm(true)),
        "max_term_error": float(np.max(np.abs(coef[kept] / true[kept] - 1))),
        "seconds": seconds,
        "warnings": sorted({str(w.message)[:70] for w in caught}),
    }


def _data(name, protocol, sigma, seed, n_traj, duration):
    """The system and one forced data set (cart and spherical: a sin + b cos)."""
    from lagsindy.systems import SYSTEMS as REGISTRY
    from lagsindy.systems import make_dataset

    system = REGISTRY[name]()
    excitation = (
        "sincos" if name in ("cart_pendulum", "spherical_pendulum") else "paper"
    )
    data = make_dataset(
        system,
        n_trajectories=n_traj,
        duration=duration,
        excitation=excitation,
        noise=sigma,
        protocol=protocol,
        random_state=seed,
    )
    return system, data


def _cell(name, protocol, sigma, seed, n_traj, duration):
    system, data = _data(name, protocol, sigma, seed, n_traj, duration)
    rows = []
    for form in ("defaults", "strong"):
        row = _fit(system, data, form)
        row.update(system=name, protocol=protocol, sigma=sigma, seed=seed)
        rows.append(row)
    return rows


def _table(rows):
    text = (
        "| system | protocol | sigma | seed | estimator (form, window used) | exact terms | "
        "terms | coef. error (norm) | largest term error | fit time |\n"
        "|---|---|---|---|---|---|---|---|---|---|\n"
    )
    for r in rows:
        text += (
            f"| {r['system']} | {r['protocol']} | {r['sigma']:g} | {r['seed']} | "
            f"{r['formulation']} ({r['used']}) | {'yes' if r['correct'] else 'no'} | "
            f"{r['n_terms']} | {100 * r['coef_error']:.2f} % | "
            f"{100 * r['max_term_error']:.2f} % | {r['seconds']:.1f} s |\n"
        )
    return text


def _verdict(rows, target):
    d = [r for r in rows if r["formulation"] == "defaults"]
    exact = sum(r["correct"] for r in d)
    norm = max(r["coef_error"] for r in d)
    worst = max(r["max_term_error"] for r in d)
    ok_norm = exact == len(d) and norm <= target
    ok_term = exact == len(d) and worst <= target
    return (
        f"Defaults: exact terms in {exact} of {len(d)} fits; "
        f"target {100 * target:g} %: "
        f"largest coefficient error (norm) {100 * norm:.2f} %, "
        f"**{'met' if ok_norm else 'NOT met'}**; largest single-term error "
        f"{100 * worst:.2f} %, **{'met' if ok_term else 'NOT met'}**.\n"
    )


def _window_rows(name, protocol, sigma, n_traj, duration, windows):
    """Coefficient error of the defaults against the test-function window."""
    from lagsindy import LagrangianSINDy
    from lagsindy.formulation import AutoForm

    system, data = _data(name, protocol, sigma, 0, n_traj, duration)
    cells = []
    for w in windows:
        est = LagrangianSINDy(system.paper_library(), formulation=AutoForm(window=w))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            est.fit(data.X, data.tau, groups=data.groups)
        true = system.true_coefficients(est.library_)
        coef = np.asarray(est.coef_, dtype=float)
        err = np.linalg.norm(coef - true) / np.linalg.norm(true)
        mark = "" if np.array_equal(coef != 0, true != 0) else " (wrong terms)"
        cells.append(f"{100 * err:.2f} %{mark}")
    return f"| {name} | {protocol} | {sigma:g} | " + " | ".join(cells) + " |\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer seeds")
    parser.add_argument("--seeds", type=int, default=3)
    args = parser.parse_args(argv)
    seeds, n_traj, duration, systems = args.seeds, 20, 5.0, SYSTEMS
    if args.quick:
        seeds = 1
    if tiny():
        seeds, n_traj, duration, systems = 1, 4, 2.0, SYSTEMS[:1]
    start = time.perf_counter()
    part1 = []
    for seed in range(seeds):
        part1 += _cell("cart_pendulum", "paper", 0.02, seed, n_traj, duration)
    part2 = []
    for name in systems:
        for seed in range(seeds):
            part2 += _cell(name, "sensor", 1e-2, seed, n_traj, duration)
            print(f"[defaults] {name} seed {seed}", flush=True)
    windows = (41, 81, 121, 161, 241)
    part3 = ""
    for name, protocol, sigma in (
        ("cart_pendulum", "sensor", 1e-2),
        ("double_pendulum", "sensor", 1e-2),
        ("cart_pendulum", "sensor", 1e-3),
        ("cart_pendulum", "paper", 0.02),
    )[: 1 if tiny() else 4]:
        part3 += _window_rows(name, protocol, sigma, n_traj, duration, windows)
    elapsed = time.perf_counter() - start
    text = header("Defaults on noisy data (issue 12 acceptance)")
    text += (
        f"`LagrangianSINDy(system.paper_library())` with nothing set, "
        f'`fit(X, tau, groups=trajectories)`; beside it `formulation="strong"` on the '
        f"same data. Data: `make_dataset(system, n_trajectories={n_traj}, "
        f"duration={duration:g}, excitation=..., noise=sigma, protocol=..., "
        f"random_state=seed)`, forced (the authors' inputs; cart and spherical "
        f"pendulum a sin(wt) + b cos(wt)). Coefficient error: |c - c_true| / |c_true|; "
        f"largest term error: the largest |c_k / c_k,true - 1| over the true terms. "
        f"Total run time {elapsed / 60:.1f} min.\n\n"
    )
    text += "## 1. Forced cart-pendulum, independent noise 0.02 on q, q_dot, q_ddot\n\n"
    text += _table(part1) + "\n" + _verdict(part1, 0.01) + "\n"
    text += (
        "## 2. Noise on positions only (1e-2 rad), derivatives by the default "
        "P-spline, forced\n\n"
    )
    text += _table(part2) + "\n" + _verdict(part2, 0.03) + "\n"
    text += (
        "## 3. The test-function window (seed 0)\n\n"
        "Coefficient error (norm) of `LagrangianSINDy(library, window=w)`, otherwise "
        "defaults. With noise on the positions only, the derivatives come from the "
        "P-spline and their errors are smooth (correlated over many samples): the "
        "white-noise correction does not see them (its estimate is 0) and short "
        "windows do not average them out. The default, `window=\"auto\"`, fits 81 "
        "and 161 samples (then 321) when the velocities carry no white noise, and "
        "keeps the first window the next one confirms within 3 % (the window used "
        "is in the tables above).\n\n"
        "| system | protocol | sigma | "
        + " | ".join(f"window {w}" for w in windows)
        + " |\n|---|---|---|"
        + "---|" * len(windows)
        + "\n"
        + part3
        + "\n"
    )
    notes = sorted({w for r in part1 + part2 for w in r["warnings"]})
    if notes:
        text += "Warnings raised by these fits (first 70 characters):\n\n"
        text += "".join(f"- {w}\n" for w in notes)
    write("defaults_quick.md" if (args.quick or tiny()) else "defaults.md", text)
    return 0


if __name__ == "__main__":
    main()
