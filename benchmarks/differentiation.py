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
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from lagsindy.differentiation import derivatives
from lagsindy.systems import cart_pendulum, make_dataset

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


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="one seed (--seeds 1)")
    args = parser.parse_args(argv)
    if args.quick:
        args.seeds = 1
    data = make_dataset(
        cart_pendulum(), n_trajectories=20, excitation="sincos", random_state=0
    )
    n = len(data.coordinates)
    rms = np.sqrt(np.mean(data.X_clean**2, axis=0))
    x, th = data.coordinates
    print(
        f"RMS of the exact signals: {x}_dot {rms[n]:.3g}, {th}_dot {rms[n + 1]:.3g}, "
        f"{x}_ddot {rms[2 * n]:.3g}, {th}_ddot {rms[2 * n + 1]:.3g}\n"
    )
    print(
        f"| sigma | method | {x}_dot | {th}_dot | {x}_ddot | {th}_ddot | "
        f"{x}_ddot inner | {th}_ddot inner | time (s) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for sigma in SIGMAS:
        for name, kwargs in METHODS.items():
            e1, e2, e2i, el = measure(data, kwargs, sigma, args.seeds)
            print(
                f"| {sigma:g} | {name} | {e1[0]:.2e} | {e1[1]:.2e} | {e2[0]:.2e} | "
                f"{e2[1]:.2e} | {e2i[0]:.2e} | {e2i[1]:.2e} | {el:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
