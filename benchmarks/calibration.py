"""Calibration of the bootstrap intervals (issue 19): coverage of the true values.

Over repeated noise draws (each a fresh data set: initial states, inputs and noise
from ``random_state=seed``), the forced cart-pendulum, 20 trajectories x 5 s
(``excitation="sincos"``), the paper library (39 terms), the default estimator
``LagrangianSINDy(system.paper_library())`` (the weak form, ``window="auto"``), and
``bootstrap(est, X, tau, groups=groups, n_resamples=200, random_state=seed)``.
Noise protocols:

- ``forces``: exact states, white noise of sd 0.05 on the measured forces;
- ``paper``: independent noise 0.02 on q, q_dot and q_ddot (``protocol="paper"``);
- ``sensor``: noise 1e-2 on q alone, derivatives by the default P-spline
  (``protocol="sensor"``).

For each: the coverage of the true terms' 95 % intervals (BCa, the default; percentile
and basic from the same resamples), per term; the fit's bias (mean relative error over
draws, with its standard error) against the spread of the fits over draws and the
bootstrap's own spread; inclusion of true and spurious terms.

    python -m benchmarks.calibration            # results/calibration.md
    python -m benchmarks.calibration --quick    # 4 draws, 50 resamples
"""

from __future__ import annotations

import argparse
import os
import time
import warnings

import numpy as np

from ._common import header, write
from ._evaluate import tiny

PROTOCOLS = {
    "forces": "exact states, white noise sd 0.05 on the forces",
    "paper": "independent noise 0.02 on q, q_dot, q_ddot (protocol `paper`)",
    "sensor": "noise 1e-2 on q, P-spline derivatives (protocol `sensor`)",
}


def _data(system, protocol, seed, n_traj, duration):
    from lagsindy.systems import make_dataset

    kw = {"paper": {"noise": 0.02, "protocol": "paper"}}.get(protocol, {})
    if protocol == "sensor":
        kw = {"noise": 1e-2, "protocol": "sensor"}
    data = make_dataset(
        system,
        n_trajectories=n_traj,
        duration=duration,
        excitation="sincos",
        random_state=seed,
        **kw,
    )
    tau = data.tau
    if protocol == "forces":
        rng = np.random.default_rng(10_000 + seed)
        tau = tau + 0.05 * rng.standard_normal(tau.shape)
    return data, tau


def _quantile_intervals(samples, coef, level):
    """Percentile and basic intervals from a report's resamples."""
    a = (1 - level) / 2
    lo, hi = np.nanquantile(samples, [a, 1 - a], axis=0)
    return (lo, hi), (2 * coef - hi, 2 * coef - lo)


def measure(protocol, n_draws, n_traj, duration, n_resamples, level=0.95):
    """Coverage and bias figures of one protocol over ``n_draws`` data sets."""
    from lagsindy import LagrangianSINDy, bootstrap
    from lagsindy.systems import cart_pendulum

    system = cart_pendulum()
    rows = []
    start = time.perf_counter()
    for seed in range(n_draws):
        data, tau = _data(system, protocol, seed, n_traj, duration)
        est = LagrangianSINDy(system.paper_library())
        rep = bootstrap(
            est,
            data.X,
            tau,
            groups=data.groups,
            n_resamples=n_resamples,
            level=level,
            random_state=seed,
        )
        full = rep.estimator
        truth = system.true_coefficients(full.library_)
        true = np.flatnonzero(truth)
        t = truth[true]
        pct, basic = _quantile_intervals(rep.samples, rep.coefficient, level)

        def covers(lo, hi, t=t, true=true):
            return (lo[true] <= t) & (t <= hi[true])

        spurious = np.delete(rep.inclusion, true)
        rows.append(
            {
                "bca": covers(rep.low, rep.high),
                "percentile": covers(*pct),
                "basic": covers(*basic),
                "error": rep.coefficient[true] / t - 1,
                "boot_sd": np.nanstd(rep.samples[:, true], axis=0) / np.abs(t),
                "half_width": (rep.high[true] - rep.low[true]) / 2 / np.abs(t),
                "incl_true": rep.inclusion[true].min(),
                "incl_spurious": spurious.max() if spurious.size else 0.0,
                "window": full.window_,
                "fast": rep.fast_path,
                "terms": [str(full.feature_names_[k]) for k in true],
            }
        )
    return rows, time.perf_counter() - start


def _section(protocol, rows, seconds, n_resamples):
    terms = rows[0]["terms"]
    n = len(rows)
    text = f"## {protocol}: {PROTOCOLS[protocol]}\n\n"
    cov = {m: np.array([r[m] for r in rows]) for m in ("bca", "percentile", "basic")}
    err = np.array([r["error"] for r in rows])
    sd_draws = err.std(axis=0, ddof=1) if n > 1 else np.full(len(terms), np.nan)
    bias_se = sd_draws / np.sqrt(n)
    boot_sd = np.array([r["boot_sd"] for r in rows]).mean(axis=0)
    half = np.array([r["half_width"] for r in rows]).mean(axis=0)
    windows = sorted({int(r["window"]) for r in rows})
    text += (
        f"{n} draws x {len(terms)} true terms = {cov['bca'].size} intervals; "
        f"{n_resamples} resamples; windows used: {windows}; fast path in "
        f"{sum(r['fast'] for r in rows)} of {n} draws; {seconds:.0f} s.\n\n"
        "| interval | coverage (all terms) | "
        + " | ".join(f"`{t}`" for t in terms)
        + " |\n|---|---|"
        + "---|" * len(terms)
        + "\n"
    )
    for m, c in cov.items():
        text += (
            f"| {m} | **{c.mean():.3f}** ({int(c.sum())} of {c.size}) | "
            + " | ".join(f"{v:.2f}" for v in c.mean(axis=0))
            + " |\n"
        )
    text += "\n| per term (relative to the true value) | " + " | ".join(
        f"`{t}`" for t in terms
    )
    text += " |\n|---|" + "---|" * len(terms) + "\n"
    for label, vals in (
        ("bias: mean error over draws", err.mean(axis=0)),
        ("standard error of that mean", bias_se),
        ("sd of the fits over draws", sd_draws),
        ("bootstrap sd (mean over draws)", boot_sd),
        ("interval half-width (mean)", half),
    ):
        sign = "+" if label.startswith("bias") else ""
        text += f"| {label} | " + " | ".join(f"{v:{sign}.3%}" for v in vals) + " |\n"
    incl_true = min(r["incl_true"] for r in rows)
    incl_spur = max(r["incl_spurious"] for r in rows)
    text += (
        f"\nInclusion: true terms at least {incl_true:.2f} in every draw; spurious "
        f"terms at most {incl_spur:.2f} in any draw.\n\n"
    )
    return text


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="reduced size")
    parser.add_argument(
        "--protocols", nargs="+", default=list(PROTOCOLS), choices=list(PROTOCOLS)
    )
    parser.add_argument("--draws", type=int, default=30)
    parser.add_argument("--resamples", type=int, default=200)
    args = parser.parse_args(argv)
    quick = args.quick or tiny()
    n_draws, n_resamples, n_traj, duration = args.draws, args.resamples, 20, 5.0
    if args.quick:
        n_draws, n_resamples = 4, 50
    if tiny():
        n_draws, n_resamples, n_traj, duration = 2, 10, 10, 2.0
    warnings.simplefilter("ignore")
    load = os.getloadavg()[0]
    text = header("Calibration of the bootstrap intervals (issue 19)")
    text += (
        'Forced cart-pendulum (`excitation="sincos"`), '
        f"{n_traj} trajectories x {duration:g} s at 100 Hz, a fresh data set per "
        "draw (`random_state=seed`), paper library (39 terms), "
        '`LagrangianSINDy(system.paper_library())` (weak form, `window="auto"`), '
        f"`bootstrap(..., n_resamples={n_resamples}, random_state=seed)`, 95 % "
        "intervals of the true terms. Coverage is the fraction of intervals that "
        "hold the true value (target: at least 0.85). Bias, spreads and widths are "
        "relative to the true coefficient. Load average (1 min) at the start: "
        f"{load:.1f}.\n\n"
    )
    for protocol in args.protocols:
        rows, seconds = measure(protocol, n_draws, n_traj, duration, n_resamples)
        text += _section(protocol, rows, seconds, n_resamples)
        print(f"[calibration] {protocol}: {seconds:.0f} s", flush=True)
    write("calibration_quick.md" if quick else "calibration.md", text)
    return 0


if __name__ == "__main__":
    main()
