"""Library bagging against a single fit: triple pendulum, separated library (222 terms).

A planar triple pendulum (three 1 kg point masses on 1 m rods, all joints driven by the
paper-style inputs) is simulated, its positions measured with noise (``protocol=
"sensor"``, derivatives by P-splines), and the Lagrangian sought over the separated
library of degree 2 (279 candidates, 222 after removing trivial and dependent terms;
12 true terms). One :class:`lagsindy.LagrangianSINDy` fit on the whole library is
compared with :class:`lagsindy.LibraryBaggingLagrangianSINDy` (fits on random halves
of a quarter of the library, terms kept above an inclusion threshold, refit), for the structure
recovered (true and false positives) and the coefficient error.

    python -m benchmarks.bagging            # results/bagging.md
    python -m benchmarks.bagging --quick    # fewer fits, results/bagging_quick.md
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from ._common import command, header, write


def _structure(coef, truth):
    kept, true = coef != 0, truth != 0
    err = np.linalg.norm(coef - truth) / np.linalg.norm(truth)
    return (
        int((kept & true).sum()),
        int((kept & ~true).sum()),
        int((~kept & true).sum()),
        err,
    )


def run(n_trajectories, n_estimators, noise, formulation, seed=0):
    from lagsindy import LagrangianSINDy, LibraryBaggingLagrangianSINDy
    from lagsindy.systems import make_dataset, triple_pendulum

    system = triple_pendulum()
    library = system.paper_library()
    library.build()
    truth = system.true_coefficients(library)
    data = make_dataset(
        system,
        n_trajectories=n_trajectories,
        duration=3.0,
        excitation="paper",
        noise=noise,
        protocol="sensor",
        random_state=seed,
    )
    base = LagrangianSINDy(library, formulation=formulation)
    rows = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = time.perf_counter()
        single = base.fit(data.X, data.tau, groups=data.groups)
        rows.append(("single fit", single.coef_, time.perf_counter() - t, None))
        for fraction in (0.25,):
            t = time.perf_counter()
            bag = LibraryBaggingLagrangianSINDy(
                base,
                n_estimators=n_estimators,
                max_terms=fraction,
                inclusion_threshold=0.5,
                random_state=seed,
            ).fit(data.X, data.tau, groups=data.groups)
            rows.append(
                (
                    f"bagging ({n_estimators} fits of {fraction:.0%} of the terms)",
                    bag.coef_,
                    time.perf_counter() - t,
                    bag,
                )
            )
    return len(library), int((truth != 0).sum()), data.X.shape[0], truth, rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    n_traj = 12 if args.quick else 20
    n_est = 6 if args.quick else 16
    text = header(
        "Library bagging: triple pendulum, separated library", command("bagging", argv)
    )
    verdicts = []
    for noise, formulation in [(0.0, "strong"), (0.01, "weak")]:
        n_terms, n_true, n_rows, truth, rows = run(n_traj, n_est, noise, formulation)
        text += (
            f"\n## noise sd {noise} rad on positions, formulation={formulation!r}\n\n"
            f"{n_traj} trajectories x 3 s x 100 Hz ({n_rows} rows), case I, "
            f"{n_terms} candidate terms, {n_true} true.\n\n"
            "| method | true terms kept | false terms kept | true terms missed | "
            "relative coefficient error | time |\n|---|---|---|---|---|---|\n"
        )
        wrong = []
        for name, coef, seconds, _ in rows:
            tp, fp, fn, err = _structure(coef, truth)
            wrong.append(fp + fn)
            text += f"| {name} | {tp} | {fp} | {fn} | {err:.3g} | {seconds:.1f} s |\n"
        verdicts.append(min(wrong[1:]) < wrong[0])
        print(text, flush=True)
    text += "\n## Reading\n\n" + (
        "Bagging recovered the structure better than the single fit in "
        f"{sum(verdicts)} of {len(verdicts)} settings. "
        if any(verdicts)
        else "Bagging did not help here: the single fit on the whole library is at "
        "least as close to the true structure in every setting. "
    )
    text += (
        "Each bagged fit sees a random part of the library, so most fits miss some of "
        "the 12 true terms (the kinetic couplings of the three links among them); a "
        "Lagrangian cannot be fitted with part of its terms, and the sub-fits make up "
        "for the missing ones with correlated substitutes, which then collect inclusion "
        "across the fits. Library bagging is meant for libraries too large or too "
        "ill-conditioned for one fit; with enough data, as here, the single fit wins.\n"
    )
    write("bagging_quick.md" if args.quick else "bagging.md", text)


if __name__ == "__main__":
    main()
