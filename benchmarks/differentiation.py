"""Accuracy of the derivative estimators of lagsindy.differentiation.

Data: ``make_dataset(cart_pendulum(), n_trajectories=20, excitation="sincos",
random_state=0)`` (20 trajectories x 5 s at 100 Hz). Gaussian noise of standard
deviation sigma is added to the exact positions ``X_clean[:, :2]`` (x in m, theta in
rad) with ``numpy.random.default_rng(seed)``; q_dot and q_ddot are estimated from the
noisy positions and compared with the exact columns of ``X_clean``. Reported: the RMS
error over all samples (ends included), averaged over the noise seeds, per coordinate;
the RMS error of q_ddot without the first and last ``EDGE`` samples of each trajectory
(one-sided estimates at the ends are the least accurate); and the time of one call on
the 20 trajectories.

    python -m benchmarks.differentiation             # prints a markdown table
    python -m benchmarks.differentiation --seeds 1   # quicker
    python -m benchmarks.differentiation --quick     # long records only, up to 1e5
    python -m benchmarks.differentiation --long      # long records only, up to 1e6

The second part times the P-spline on one long trajectory (a 1 kHz record of 12 Hz
and 25 Hz content with noise of standard deviation 1e-4, one coordinate) of 1e4,
1e5 and 1e6 samples, with the relative RMS error of q_ddot away from the ends, and
writes everything to ``benchmarks/results/differentiation.md`` (``--out``).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from datetime import datetime, timezone

import numpy as np

from lagsindy.differentiation import derivatives
from lagsindy.systems import cart_pendulum, make_dataset

from . import _common

METHODS = {
    "pspline": dict(method="pspline"),
    "spline (cubic)": dict(method="spline"),
    "savgol w=11 p=4": dict(method="savgol", window=11, polyorder=4),
    "savgol w=21 p=4": dict(method="savgol", window=21, polyorder=4),
    "savgol w=41 p=4": dict(method="savgol", window=41, polyorder=4),
    "finite_difference": dict(method="finite_difference"),
}
SIGMAS = (0.0, 1e-3, 1e-2)
EDGE = 10


def measure(data, kwargs, sigma, seeds):
    n = len(data.coordinates)
    exact = data.X_clean
    e1, e2, e2_inner, times = [], [], [], []
    position = np.concatenate(
        [np.arange(np.sum(data.groups == g)) for g in np.unique(data.groups)]
    )
    length = np.concatenate(
        [
            np.full(np.sum(data.groups == g), np.sum(data.groups == g))
            for g in np.unique(data.groups)
        ]
    )
    inner = (position >= EDGE) & (position < length - EDGE)
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        q = exact[:, :n] + sigma * rng.normal(size=(exact.shape[0], n))
        start = time.perf_counter()
        X = derivatives(q, data.t, groups=data.groups, **kwargs)
        times.append(time.perf_counter() - start)
        e1.append(
            np.sqrt(np.mean((X[:, n : 2 * n] - exact[:, n : 2 * n]) ** 2, axis=0))
        )
        err2 = X[:, 2 * n :] - exact[:, 2 * n :]
        e2.append(np.sqrt(np.mean(err2**2, axis=0)))
        e2_inner.append(np.sqrt(np.mean(err2[inner] ** 2, axis=0)))
    return (
        np.mean(e1, axis=0),
        np.mean(e2, axis=0),
        np.mean(e2_inner, axis=0),
        min(times),
    )


LONG_SIZES = (10_000, 100_000, 1_000_000)


def long_record(n, seed=0):
    """One 1 kHz trajectory of n samples: q with 12 Hz and 25 Hz content, q_ddot."""
    t = np.arange(n) / 1000.0
    w1, w2 = 2 * np.pi * 12, 2 * np.pi * 25
    noise = 1e-4 * np.random.default_rng(seed).normal(size=n)
    q = np.sin(w1 * t) + 0.2 * np.sin(w2 * t) + noise
    qdd = -(w1**2) * np.sin(w1 * t) - 0.2 * w2**2 * np.sin(w2 * t)
    return t, q, qdd


def scaling(sizes, lines):
    lines.append(
        "\n## P-spline on one long trajectory (cost linear in samples)\n\n"
        "Wall time depends on what else runs on the machine; CPU time (this process, "
        "one BLAS thread) is the cost.\n\n"
        "| samples | wall time (s) | CPU time (s) | CPU time per 1e5 samples (s) | "
        "q_ddot relative RMS error (interior) |\n|---|---|---|---|---|"
    )
    print(lines[-1], flush=True)
    for n in sizes:
        t, q, qdd = long_record(n)
        start, cpu = time.perf_counter(), time.process_time()
        X = derivatives(q, t)
        elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
        inner = slice(100, n - 100)
        err = np.sqrt(
            np.mean((X[inner, 2] - qdd[inner]) ** 2) / np.mean(qdd[inner] ** 2)
        )
        lines.append(
            f"| {n:.0e} | {elapsed:.2f} | {cpu:.2f} | {cpu / n * 1e5:.2f} | "
            f"{100 * err:.3f} % |"
        )
        print(lines[-1], flush=True)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument(
        "--quick", action="store_true", help="long-record timing only, up to 1e5"
    )
    parser.add_argument(
        "--long", action="store_true", help="long-record timing only (1e4 to 1e6)"
    )
    parser.add_argument(
        "--out",
        default=None,
        help="output file (default: results/differentiation.md, or "
        "differentiation_quick.md with --quick, so a smoke check never overwrites "
        "the committed full result)",
    )
    args = parser.parse_args(argv)
    if args.out is None:
        name = "differentiation_quick.md" if args.quick else "differentiation.md"
        args.out = str(_common.RESULTS / name)
    lines = [
        "# Derivative estimation: accuracy and cost\n",
        f"Command: `python -m benchmarks.differentiation {' '.join(argv or sys.argv[1:])}`"
        f"  \nDate: {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC  \n"
        f"Machine: {platform.machine()}, {os.cpu_count()} CPU cores (shared), no GPU; "
        f"Python {platform.python_version()}, numpy {np.__version__}  \n"
        "Load average (1 min) at the start: " + f"{os.getloadavg()[0]:.2f}",
    ]
    if args.quick or args.long:
        scaling(LONG_SIZES[:2] if args.quick else LONG_SIZES, lines)
    else:
        accuracy(args, lines)
        scaling(LONG_SIZES, lines)
    if args.out:
        with open(args.out, "w") as fh:
            fh.write("\n".join(lines) + "\n")
        print(f"wrote {args.out}")


def accuracy(args, lines):
    data = make_dataset(
        cart_pendulum(), n_trajectories=20, excitation="sincos", random_state=0
    )
    n = len(data.coordinates)
    rms = np.sqrt(np.mean(data.X_clean**2, axis=0))
    x, th = data.coordinates
    lines.append(
        "\n## Accuracy on the cart-pendulum data set (20 x 5 s at 100 Hz)\n\n"
        f"RMS of the exact signals: {x}_dot {rms[n]:.3g}, {th}_dot {rms[n + 1]:.3g}, "
        f"{x}_ddot {rms[2 * n]:.3g}, {th}_ddot {rms[2 * n + 1]:.3g}\n\n"
        f"| sigma | method | {x}_dot | {th}_dot | {x}_ddot | {th}_ddot | "
        f"{x}_ddot inner | {th}_ddot inner | time (s) |\n"
        "|---|---|---|---|---|---|---|---|---|"
    )
    print(lines[-1], flush=True)
    for sigma in SIGMAS:
        for name, kwargs in METHODS.items():
            e1, e2, e2i, el = measure(data, kwargs, sigma, args.seeds)
            lines.append(
                f"| {sigma:g} | {name} | {e1[0]:.2e} | {e1[1]:.2e} | {e2[0]:.2e} | "
                f"{e2[1]:.2e} | {e2i[0]:.2e} | {e2i[1]:.2e} | {el:.2f} |"
            )
            print(lines[-1], flush=True)


if __name__ == "__main__":
    main()
