"""The weak form's noise correction on the measured pendulums (issue 16).

On real recordings the weak form corrects its Gram statistics for the noise on
``[q, q_dot]`` (an errors-in-variables correction: the first-order noise part,
summed over samples, is subtracted). This measures what that costs, per recording of
``benchmarks.measured`` (single, double, triple; positions thinned to 100 Hz,
P-spline derivatives, the same libraries):

* the Gram statistics alone (``EulerLagrangeOperator.weak_gram`` at the default
  fit's window and noise covariance), with and without the correction;
* the estimator's default fit (``formulation="auto"``, passive: case III's search);
* ``diagnose`` of that fit (its default catalogue, ``max_effects=4``).

Each code runs in fresh processes, alternating ("after": this checkout; "before":
``--baseline PATH``, another checkout), one torch thread; best CPU time
(``time.process_time``) of ``--repeats`` runs per process and of all processes.

    python -m benchmarks.noise_correction --baseline /tmp/base  # results/*.md
    python -m benchmarks.noise_correction --quick  # single only, 1 repeat
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings

from ._common import command, header, run_in, write
from ._evaluate import tiny

STEP = 10  # every 10th sample of 1 kHz, as benchmarks.measured


def measure(spec):
    """CPU seconds of the steps above for one recording, best of ``repeats``."""
    import numpy as np
    import torch

    from benchmarks import measured
    from lagsindy import LagrangianSINDy, diagnose
    from lagsindy.formulation import AutoForm, EulerLagrangeOperator, window_stride

    torch.set_num_threads(1)
    warnings.simplefilter("ignore")
    which = spec["system"]
    X, groups, _ = measured.load(which, "id", STEP)
    if spec.get("segments"):
        keep = np.isin(groups, np.unique(groups)[: spec["segments"]])
        X, groups = X[keep].reset_index(drop=True), groups[keep]
    lib = measured.library(which)[0]

    def fit():
        est = LagrangianSINDy(lib, random_state=0, formulation=AutoForm(dt=STEP / 1000))
        return est.fit(X, groups=groups)

    est = fit()  # warm-up; its window and noise covariance set the Gram's
    built = lib.build() if hasattr(lib, "build") else lib
    op = EulerLagrangeOperator(built.coordinates_, built.terms_)
    Xt = torch.tensor(X.to_numpy())
    segs = [torch.as_tensor(np.flatnonzero(groups == g)) for g in np.unique(groups)]
    segs = [s for s in segs if len(s) >= est.window_]
    cov = est.noise_cov_
    kw = dict(window=est.window_, stride=window_stride(est.window_), dt=STEP / 1000)

    def gram(noise_cov):
        return lambda: op.weak_gram(Xt, None, segs, noise_cov=noise_cov, **kw)

    runs = {
        "Gram, with the correction": gram(
            None if cov is None else torch.as_tensor(cov, dtype=torch.float64)
        ),
        "Gram, without": gram(None),
        "default fit": fit,
        "diagnose": lambda: diagnose(est, X, groups=groups, max_effects=4),
    }
    best = {}
    for _ in range(spec["repeats"]):
        for name, run in runs.items():
            if name == "diagnose" and name in best and spec["repeats"] > 2:
                continue  # seconds each: two runs are enough
            start = time.process_time()
            run()
            seconds = time.process_time() - start
            best[name] = min(best.get(name, np.inf), seconds)
    import lagsindy

    return {
        **spec,
        "rows": int(len(X)),
        "terms": op.n_terms,
        "corrected": cov is not None,
        "window": int(est.window_),
        "cpu": best,
        "lagsindy": os.path.dirname(lagsindy.__file__),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="single only, 1 repeat")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--baseline", default=None, help="checkout timed as 'before'")
    parser.add_argument("--_measure", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args._measure is not None:
        print(json.dumps(measure(json.loads(args._measure))))
        return 0
    import torch

    torch.set_num_threads(1)  # as in the measuring processes (the header says so)
    quick = args.quick or tiny()
    systems = ("single",) if quick else ("single", "double", "triple")
    repeats, processes = (1, 1) if quick else (args.repeats, args.processes)
    codes = [("after", None)] + ([("before", args.baseline)] if args.baseline else [])
    results = {}  # (system, code) -> list of process results
    load = os.getloadavg()[0]
    for which in systems:
        spec = {"system": which, "repeats": repeats}
        if tiny():
            spec["segments"] = 3
        for _ in range(processes):
            for label, root in codes:
                res = run_in(
                    "noise_correction",
                    "--_measure",
                    spec,
                    root,
                    env={"OMP_NUM_THREADS": "1"},
                )
                print(label, res, flush=True)
                results.setdefault((which, label), []).append(res)
    steps = ["Gram, with the correction", "Gram, without", "default fit", "diagnose"]
    text = header(
        "The weak form's noise correction on the measured pendulums (issue 16)",
        command("noise_correction", argv),
    )
    text += (
        f"Recordings of `benchmarks.measured` (identification split, every {STEP}th "
        "sample of 1 kHz, P-spline derivatives, its libraries); one torch thread; "
        f"best CPU time of {repeats} runs in each of {processes} fresh process(es) "
        "per code, the codes alternating. 'Gram' is `weak_gram` alone at the default "
        "fit's window and noise covariance; the correction's own cost is the "
        "difference of its two rows. Load average (1 min) at the start: "
        f"{load:.1f}.\n\n"
        "| recording | rows x terms | code | "
        + " | ".join(steps)
        + " |\n|---|---|---|"
        + "---|" * len(steps)
        + "\n"
    )
    for which in systems:
        for label, _ in codes:
            runs = [r for r in results[(which, label)] if "error" not in r]
            if not runs:
                err = results[(which, label)][0].get("error", "?")
                text += f"| {which} | - | {label} | error: {err} |\n"
                continue
            best = {s: min(r["cpu"][s] for r in runs) for s in steps}
            r0 = runs[0]
            shape = f"{r0['rows']} x {r0['terms']}"
            if not r0["corrected"]:
                shape += " (noise negligible: no correction)"
            text += (
                f"| {which} | {shape} | {label} | "
                + " | ".join(f"{best[s]:.3f} s" for s in steps)
                + " |\n"
            )
    if args.baseline:
        text += "\nRatios before / after (best CPU):\n\n"
        for which in systems:
            after = [r for r in results[(which, "after")] if "error" not in r]
            before = [r for r in results[(which, "before")] if "error" not in r]
            if not (after and before):
                continue
            parts = []
            for s in steps:
                a = min(r["cpu"][s] for r in after)
                b = min(r["cpu"][s] for r in before)
                parts.append(f"{s} {b / a:.2f}x")
            text += f"- {which}: " + ", ".join(parts) + "\n"
    text += f"\nLoad average (1 min) at the end: {os.getloadavg()[0]:.1f}.\n"
    write("noise_correction_quick.md" if quick else "noise_correction.md", text)
    return 0


if __name__ == "__main__":
    main()
