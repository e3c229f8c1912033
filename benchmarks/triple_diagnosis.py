"""Diagnosis on the real MultiArm triple pendulum (issue 14): joint damping found?

Run: ``python -m benchmarks.triple_diagnosis [--step 10] [--horizon 5]``.

The 22 identification segments (and the 4 validation segments) join into one
continuous record each; both are thinned to 100 Hz, positions and velocities and
accelerations are re-estimated from the encoder angles (P-spline). The Lagrangian
library is the authors' 9 terms (``phi_i_dot**2``, ``phi_i_dot*phi_j_dot*cos(phi_i -
phi_j)``, ``cos(phi_i)``), fitted in the weak form on passive data with
``phi1_dot**2`` fixed to 1; then :func:`lagsindy.diagnose`. Validation: RMS angle
error of 5 s rollouts from the measured state, windows starting every 0.25 s.
Prints a markdown block (the lead integrates it into measured.md).
"""

from __future__ import annotations

import argparse
import platform
import time
import warnings
from datetime import date

import numpy as np
import pandas as pd
from scipy.io import loadmat

FILE = "/work/shared/data/multiarm_pendulum/TriplePendulumDataForParameterEstimation.mat"
COORDS = ["phi1", "phi2", "phi3"]


def load(split: str, step: int):
    from lagsindy.differentiation import derivatives

    mat = loadmat(FILE)
    Y = np.concatenate([np.asarray(y) for y in mat[f"Y_{split}"].ravel()], axis=1)
    Y = Y[:, ::step].T
    t = np.arange(Y.shape[0]) * float(np.ravel(mat["dt"])[0]) * step
    q = Y[:, :3] - np.pi
    X = derivatives(q, t, method="pspline")
    cols = COORDS + [f"{c}_dot" for c in COORDS] + [f"{c}_ddot" for c in COORDS]
    return pd.DataFrame(X, columns=cols), t


def library():
    from lagsindy import CandidateLibrary

    terms = [f"{c}_dot**2" for c in COORDS]
    terms += [
        f"{a}_dot*{b}_dot*cos({a} - {b})"
        for k, a in enumerate(COORDS)
        for b in COORDS[k + 1 :]
    ]
    terms += [f"cos({c})" for c in COORDS]
    return CandidateLibrary.from_terms(COORDS, terms)


def rollouts(model, X, t, horizon, every):
    n = 3
    errs = []
    starts = np.arange(0, t[-1] - horizon + 1e-9, every)
    for s in starts:
        i0 = int(np.searchsorted(t, s))
        i1 = int(np.searchsorted(t, s + horizon, side="right"))
        tt = t[i0:i1] - t[i0]
        x0 = X.iloc[i0, : 2 * n].to_numpy()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                sim = model.simulate(x0, tt)[:, :n]
            errs.append(float(np.sqrt(np.mean((sim - X.iloc[i0:i1, :n].to_numpy()) ** 2))))
        except Exception:  # noqa: BLE001 - a learned model may blow up
            errs.append(float("nan"))
    return np.asarray(errs)


def main(argv=None):
    from lagsindy import LagrangianSINDy, diagnose

    p = argparse.ArgumentParser()
    p.add_argument("--step", type=int, default=10)
    p.add_argument("--horizon", type=float, default=5.0)
    p.add_argument("--every", type=float, default=0.25)
    p.add_argument("--formulation", default="weak")
    p.add_argument("--catalogue", default=None, help="comma-separated kinds")
    args = p.parse_args(argv)
    X_id, t_id = load("id", args.step)
    X_vad, t_vad = load("vad", args.step)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est = LagrangianSINDy(
            library(), formulation=args.formulation, fixed_term="phi1_dot**2",
            unpenalized=[str(t) for t in library().build().terms_],
            dt=t_id[1] - t_id[0],
        ).fit(X_id)
    fit_time = time.perf_counter() - t0
    t0 = time.perf_counter()
    kw = {} if not args.catalogue else {"catalogue": tuple(args.catalogue.split(","))}
    report = diagnose(est, X_id, **kw)
    diag_time = time.perf_counter() - t0
    before = rollouts(est, X_vad, t_vad, args.horizon, args.every)
    after = rollouts(report.final, X_vad, t_vad, args.horizon, args.every)
    print(f"### Triple pendulum diagnosis ({date.today()}, {platform.processor() or 'CPU'}, "
          f"2-core CPU, no GPU)\n")
    print(f"command: python -m benchmarks.triple_diagnosis --step {args.step} "
          f"--horizon {args.horizon} --every {args.every} --formulation {args.formulation}"
          + (f" --catalogue {args.catalogue}" if args.catalogue else "") + "\n")
    print("```text\n" + str(report) + "\n```\n")
    print(f"fit {fit_time:.1f} s, diagnosis {diag_time:.1f} s")
    print(f"validation {args.horizon:g} s rollouts ({len(before)} windows): median RMS "
          f"angle error {np.nanmedian(before):.4f} rad before, "
          f"{np.nanmedian(after):.4f} rad after diagnosis")


if __name__ == "__main__":
    main()
