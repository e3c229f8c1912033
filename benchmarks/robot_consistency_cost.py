"""What physical consistency in the bootstrap's resamples costs, and what it changes.

Run from two checkouts (the one with the constraint in the batched resamples and one
without) on the same machine and compare::

    PYTHONPATH=<checkout> python -m benchmarks.robot_consistency_cost [--resamples N]
    python -m benchmarks.robot_consistency_cost --quick   # 10 resamples

Writes ``results/robot_consistency_cost.md`` (``_quick`` with ``--quick``).

Prints, for the shipped two-link arm and the seven-joint arm (torques from lagsindy's
own regressor with rotor inertias, viscous and Coulomb friction, an offset and 5 %
noise), the fit's and the
bootstrap's wall time and the resamples whose base parameters have no consistent
link parameters (checked with the constrained refit's representatives), and writes
the intervals to ``--out`` (``.npz``) for the comparison.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy, bootstrap
from lagsindy.robots import example_urdf, feasibility, multisine

from ._common import header, write
from ._evaluate import tiny

ARM7_JOINTS = [f"joint{i}" for i in range(1, 8)]


def _data(name, duration, rate, seed=0):
    joints = ARM7_JOINTS if name == "arm7" else None
    lib = CandidateLibrary.from_urdf(example_urdf(name), joints)
    n = lib.tree_.n_dof
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, 1.0 / rate)
    q, qd, qdd = multisine(t, n, random_state=rng)
    truth = lib.nominal_.copy()
    truth[-n:] = np.linspace(0.02, 0.0005, n)  # rotor inertias down to 5e-4
    tau = lib.euler_lagrange_columns(q, qd, qdd) @ truth + 0.3 * qd
    tau += 0.2 * np.tanh(qd / 0.01) + 0.05  # Coulomb friction and an offset
    tau += 0.05 * rng.standard_normal(tau.shape) * tau.std(0)
    return lib, np.hstack([q, qd, qdd]), tau


def _infeasible(library, samples):
    n = len(library.terms_)
    nb = len(library.robot_.tree_.bodies)
    bad = 0
    for s in samples:
        if not np.all(np.isfinite(s)):
            continue
        beta = s[:n]
        pi = library.__dict__.get("_representatives", {}).get(beta.tobytes())
        if pi is None:  # no constrained refit made it: check it
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                pi = library.link_parameters(beta)
        miss = np.abs(library.base_.values(pi) - beta).max() / np.abs(beta).max()
        if (
            miss > 1e-9
            or feasibility(pi, nb).min() < -1e-12
            or pi[10 * nb :].min(initial=0) < 0
        ):
            bad += 1
    return bad


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resamples", type=int, default=30)
    parser.add_argument("--quick", action="store_true", help="10 resamples")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    if args.quick or tiny():
        args.resamples = min(args.resamples, 3 if tiny() else 10)
    saved, lines = {}, []
    for name, duration, rate in (("planar2", 2.0, 500.0), ("arm7", 2.0, 250.0)):
        lib, X, tau = _data(name, duration, rate)
        kinds = DissipationLibrary(["viscous", "coulomb", "bias"])
        est = LagrangianSINDy(lib, dissipation=kinds, formulation="strong")
        free = LagrangianSINDy(
            CandidateLibrary.from_urdf(lib.path, lib.joints, consistent=False),
            dissipation=kinds,
            formulation="strong",
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t0 = time.perf_counter()
            est.fit(X, tau)
            t_fit = time.perf_counter() - t0
            free.fit(X, tau)  # the full fit consistent on its own: same coefficients
            own = bool(np.allclose(free.coef_, est.coef_, rtol=1e-9, atol=0))
            t0 = time.perf_counter()
            report = bootstrap(
                est,
                X,
                tau,
                n_resamples=args.resamples,
                method="percentile",
                random_state=0,
            )
            t_boot = time.perf_counter() - t0
        bad = _infeasible(report.estimator.library_, report.samples[-40:])
        lines.append(
            f"- {name}: {len(X)} samples, {len(est.coef_)} base parameters; fit "
            f"{t_fit:.2f} s, bootstrap of {args.resamples} {t_boot:.2f} s; "
            f"infeasible resamples (last 40 checked): {bad}; the unconstrained full "
            f"fit is consistent: {own}"
        )
        print(lines[-1], flush=True)
        saved[f"{name}_low"], saved[f"{name}_high"] = report.low, report.high
        saved[f"{name}_coef"] = report.coefficient
        saved[f"{name}_times"] = np.array([t_fit, t_boot])
    if args.out:
        np.savez(args.out, **saved)
    name = "robot_consistency_cost" + ("_quick" if (args.quick or tiny()) else "")
    write(f"{name}.md", header(__doc__.splitlines()[0]) + "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
