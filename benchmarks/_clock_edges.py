"""Edge rows in fits and scores (issue #40, item 2): ``python -m benchmarks.clocks
--edges`` writes ``results/clocks_edges.md`` (section 5 of ``clocks.md``).

Camera records as in section 1 of :mod:`benchmarks.clocks` (double pendulum,
unequal links, 100 Hz nominal, 20 % jitter, 5 % dropped frames, noise 1e-3 rad) with
2, 6 or 10 gaps of 0.12-0.2 s per record: the more gaps, the more segment ends.
Each record is fitted by the documented path (``derivatives(...,
return_clock=True)``, ``fit(X, tau, t=clock)``), in the weak form (default,
``formulation="auto"``) and the strong form, twice: with the edge rows (the former
default, emulated by a clock whose ``edge`` is all False) and without (the
default now). Reported: the formulation the fit used, the number of terms, whether
they are exactly the true ones, the largest relative coefficient error against the
true coefficients (passive: ratios to ``theta1_dot**2``), and the pointwise R^2
(``est.score``: forces, or accelerations for passive data) on all rows and on the
rows away from the edges.
"""

from __future__ import annotations

import dataclasses
import time
import warnings

import numpy as np
import pandas as pd

from . import clocks as C

GAPS = (2, 6, 10)


def _true(sys_, est, passive):
    names = [str(t) for t in est.library_.terms_]
    coef = dict(zip(names, sys_.true_coefficients(est.library_)))
    ref = {k: v for k, v in coef.items() if v != 0}
    if passive:
        ref = {k: v / ref["theta1_dot**2"] for k, v in ref.items()}
    return pd.Series(ref)


def edge_fit_study(sizes=(6, 6.0), gaps=GAPS, seed=0):
    """Rows of the table (dicts)."""
    from lagsindy import LagrangianSINDy
    from lagsindy.differentiation import derivatives

    n_traj, duration = sizes
    n = int(round(duration * C.RATE))
    sys_ = C.system()
    library = sys_.paper_library()
    rows = []
    for n_gaps in gaps:
        for forced in (False, True):

            def clock(k, rng, n_gaps=n_gaps):
                return C.camera_clock(n, rng, 0.2, 0.05, n_gaps, duration)

            rec = C.records(sys_, n_traj, duration, forced, seed, clock)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                X, clk = derivatives(
                    rec["q"], rec["t"], groups=rec["groups"], angles="all",
                    return_clock=True,
                )  # fmt: skip
            kept = dataclasses.replace(clk, edge=np.zeros_like(clk.edge))
            segments = np.bincount(clk.groups[clk.keep])
            every = np.flatnonzero(clk.keep)
            inner = np.flatnonzero(clk.keep & ~clk.edge)
            tau = rec["tau"]
            for form in ("auto", "strong"):
                for label, c in (("kept (former)", kept), ("left out (now)", clk)):
                    t0 = time.perf_counter()
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        est = LagrangianSINDy(library, formulation=form)
                        est.fit(X, tau, t=c)
                        wall = time.perf_counter() - t0
                        got = C.coefficients(est, not forced)
                        same, err = C.compare(got, _true(sys_, est, not forced))

                        def r2(idx, est=est):
                            return est.score(X[idx], None if tau is None else tau[idx])

                        r2_all, r2_inner = r2(every), r2(inner)
                    rows.append(
                        dict(
                            gaps=n_gaps, system="forced" if forced else "passive",
                            segments=segments.size,
                            median=float(np.median(segments)),
                            edge=float(np.mean(clk.edge[clk.keep])),
                            formulation=form, edges=label,
                            used=est.formulation_, terms=len(got),
                            exact=set(got.index) == C.true_terms(sys_, est.library_),
                            err=err, r2_all=r2_all, r2_inner=r2_inner, wall=wall,
                        )
                    )  # fmt: skip
                    print(rows[-1], flush=True)
    return rows


def edge_table(rows, sizes=(6, 6.0)) -> str:
    n_traj, duration = sizes
    out = [
        "## 5. Edge rows in the fit and its scores (camera records, many gaps)\n",
        f"{n_traj} trajectories x {duration:g} s, 100 Hz nominal, 20 % jitter, 5 % "
        "dropped frames, noise 0.001 rad, 2 / 6 / 10 gaps of 0.12-0.2 s per record. "
        "`fit(X, tau, t=clock)` with the edge rows (`clock.edge`: 3 rows at each "
        "segment end and every row of a segment too short to differentiate) kept "
        "(the former default) or left out (the default now). `err`: the largest "
        "relative coefficient error against the true coefficients (passive: ratios "
        "to theta1_dot**2); R^2: `est.score` (forces; passive: accelerations) on "
        "every row and on the rows away from the edges.\n",
        "| gaps | system | segments (median length) | edge rows | formulation | "
        "edge rows in the fit | used | terms | true terms | err | R^2 all rows | "
        "R^2 interior | time |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {r['gaps']} | {r['system']} | {r['segments']} ({r['median']:.0f}) | "
            f"{r['edge']:.1%} | {r['formulation']} | {r['edges']} | {r['used']} | "
            f"{r['terms']} | {r['exact']} | {r['err']:.2%} | {r['r2_all']:.3g} | "
            f"{r['r2_inner']:.3g} | {r['wall']:.0f} s |"
        )
    return "\n".join(out) + "\n"
