"""One long record at 1 kHz: the default (weak) fit's time and peak memory.

A single forced cart-pendulum trajectory sampled at 1 kHz (the simulator's states
with sensor noise 1e-4), paper library, estimator defaults. Each size runs in a
fresh process (``run_in``), so its peak resident set size (``ru_maxrss``) is its
own: data, imports and the fit. ``--baseline PATH`` times another checkout on the
sizes up to ``--baseline-max`` samples (older code built one dense band per
segment, whose memory grows with the square of its length).

    python -m benchmarks.long_record
    python -m benchmarks.long_record --baseline /tmp/before --baseline-max 50000
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time

from . import _common

SIZES = (20_000, 50_000, 100_000, 200_000)
QUICK_SIZES = (5_000, 20_000)
TINY_SIZES = (2_000,)  # LAGSINDY_BENCH_TINY=1: the tests


def measure(spec):
    """Simulate, fit once, and report time, peak RSS and coefficients' error."""
    import warnings

    import numpy as np

    from lagsindy import LagrangianSINDy
    from lagsindy.systems import cart_pendulum, make_dataset

    system = cart_pendulum()
    data = make_dataset(
        system,
        n_trajectories=1,
        duration=spec["samples"] / 1000.0,
        rate=1000,
        excitation="sincos",
        noise=1e-4,
        protocol="sensor",
        random_state=0,
    )
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    est = LagrangianSINDy(system.paper_library())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        start, cpu = time.perf_counter(), time.process_time()
        est.fit(data.X, data.tau)
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    truth = system.true_coefficients(est.library)
    error = float(np.linalg.norm(est.coef_ - truth) / np.linalg.norm(truth))
    return {
        **spec,
        "rows": len(data.X),
        "wall": wall,
        "cpu": cpu,
        "rss_before_mib": before,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "coef_error": error,
        "window": est.window_,
        "warnings": sorted({w.category.__name__ for w in caught}),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes only")
    parser.add_argument("--baseline", default=None, help="another checkout to time")
    parser.add_argument(
        "--baseline-max",
        type=int,
        default=50_000,
        help="largest record the baseline runs (default 50000)",
    )
    parser.add_argument("--_measure", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args._measure is not None:
        print(json.dumps(measure(json.loads(args._measure))))
        return 0
    sizes = QUICK_SIZES if args.quick else SIZES
    if os.environ.get("LAGSINDY_BENCH_TINY", "") not in ("", "0"):
        sizes = TINY_SIZES
    codes = [("this", None)]
    if args.baseline:
        codes.append(("baseline", args.baseline))
    rows = []
    for n in sizes:
        for label, root in codes:
            if label == "baseline" and n > args.baseline_max:
                continue
            r = _common.run_in("long_record", "--_measure", {"samples": n}, root)
            print(label, r, flush=True)
            rows.append((label, r))
    text = _common.header("One long record at 1 kHz: time and memory of a fit")
    text += (
        "A single forced cart-pendulum trajectory (`make_dataset(cart_pendulum(), "
        "n_trajectories=1, duration=N/1000, rate=1000, excitation='sincos', "
        "noise=1e-4, protocol='sensor', random_state=0)`), paper library (39 "
        "terms), `LagrangianSINDy` defaults (weak form, window chosen "
        "automatically). One fresh process per row; peak RSS includes Python, "
        "torch, the simulation and the fit; 'RSS before' is the peak before the fit."
        + (f" 'baseline' imports lagsindy from `{args.baseline}`." if codes[1:] else "")
        + "\n\n| samples | code | fit wall | fit CPU | RSS before | peak RSS | "
        "coefficient error | window | warnings |\n"
        "|---|---|---|---|---|---|---|---|---|\n"
    )
    for label, r in rows:
        if "error" in r:
            text += f"| {r['samples']} | {label} | error: {r['error']} | | | | | | |\n"
            continue
        text += (
            f"| {r['rows']} | {label} | {r['wall']:.2f} s | {r['cpu']:.2f} s | "
            f"{r['rss_before_mib']:.0f} MiB | **{r['peak_rss_mib']:.0f} MiB** | "
            f"{r['coef_error']:.2e} | {r['window']} | "
            f"{', '.join(r['warnings']) or '-'} |\n"
        )
    name = "long_record_quick.md" if args.quick else "long_record.md"
    _common.write(name, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
