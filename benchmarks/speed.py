"""Fit time of LagrangianSINDy (case I, Gram-matrix FISTA).

Default: the cart-pendulum, 100 trajectories x 500 samples, the paper's 55-term
library, active (forced) data; the median of 5 fits after one warm-up fit (the first
fit in a process also pays torch's lazy imports, reported separately).

    python -m benchmarks.speed            # writes benchmarks/results/speed.md
    python -m benchmarks.speed --quick    # smaller, for a smoke check
"""

from __future__ import annotations

import argparse
import statistics
import time

from lagsindy import LagrangianSINDy
from lagsindy.systems import cart_pendulum, make_dataset

from ._common import header, write


def time_fits(X, tau, library, repeats):
    times = []
    est = None
    for _ in range(repeats):
        est = LagrangianSINDy(library)
        start = time.perf_counter()
        est.fit(X, tau)
        times.append(time.perf_counter() - start)
    return times, est


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    n_traj = 10 if args.quick else 100
    repeats = 2 if args.quick else args.repeats
    system = cart_pendulum()
    data = make_dataset(system, n_trajectories=n_traj, excitation="sincos", random_state=0)
    library = system.paper_library()
    start = time.perf_counter()
    LagrangianSINDy(library).fit(data.X, data.tau)
    first = time.perf_counter() - start
    times, est = time_fits(data.X, data.tau, library, repeats)
    median = statistics.median(times)
    text = header("Fit time: cart-pendulum, case I")
    text += (
        f"Data: {n_traj} trajectories x 500 samples ({data.X.shape[0]} rows), noise-free, "
        f"tau = a sin(wt) + b cos(wt) on the cart. Library: {len(library.candidates_)} "
        f"candidates ({len(library)} after removing trivial and dependent terms).\n\n"
        f"| quantity | value |\n|---|---|\n"
        f"| median fit time over {repeats} fits | **{median:.3f} s** |\n"
        f"| all fit times | {', '.join(f'{t:.3f}' for t in times)} s |\n"
        f"| first fit in the process (torch lazy imports included) | {first:.3f} s |\n"
        f"| FISTA iterations (all stages) | {est.n_iter_} |\n"
        f"| stages | {len(est.stages_)} |\n"
        f"| learned | `{est.equation(4)}` |\n\n"
        f"Target (core issue): under 1 s per fit: "
        f"{'met' if median < 1.0 else 'NOT met'}.\n"
    )
    write("speed_quick.md" if args.quick else "speed.md", text)
    print(text)


if __name__ == "__main__":
    main()
