"""Case II (passive data, no prior knowledge): how far it goes with the library size.

Case II fits accelerations through the learned mass matrix (``case="acceleration"``,
the paper's eq. 10-11), a non-convex problem the paper found hard beyond about 20
candidates. Here it runs on noise-free passive data (20 trajectories x 5 s x 100 Hz,
``make_dataset(..., excitation=None, random_state=0)``) with libraries of growing
size: the single pendulum's paper library (12 candidates) and polynomial libraries of
degree 3, 4 and 5 over {theta, theta_dot, sin, cos}, then the cart-pendulum's and the
double pendulum's paper libraries. Per row: the number of terms after the library's
reduction, whether the structure is exactly right (up to scale), the relative
coefficient error of the ratios, and the fit time. Each fit runs in its own process and
is stopped after ``--limit`` seconds.

    python -m benchmarks.case2            # results/case2.md
    python -m benchmarks.case2 --quick    # two smallest rows, results/case2_quick.md
"""

from __future__ import annotations

import argparse
import time

from ._common import header, write
from ._evaluate import compare_structure, short, timed_fit, tiny


def cases():
    from lagsindy import CandidateLibrary
    from lagsindy.systems import cart_pendulum, double_pendulum, single_pendulum

    single = single_pendulum()
    return [
        ("single pendulum, paper library", single, single.paper_library()),
        (
            "single pendulum, polynomial degree 3",
            single,
            CandidateLibrary.polynomial(
                ["theta"], angles=["theta"], degree=3, raw_angles=True
            ),
        ),
        (
            "single pendulum, polynomial degree 4",
            single,
            CandidateLibrary.polynomial(
                ["theta"], angles=["theta"], degree=4, raw_angles=True
            ),
        ),
        (
            "single pendulum, polynomial degree 5",
            single,
            CandidateLibrary.polynomial(
                ["theta"], angles=["theta"], degree=5, raw_angles=True
            ),
        ),
        (
            "cart-pendulum, paper library",
            cart_pendulum(),
            cart_pendulum().paper_library(),
        ),
        (
            "double pendulum, paper library",
            double_pendulum(),
            double_pendulum().paper_library(),
        ),
    ]


def main(argv=None):
    from lagsindy import LagrangianSINDy
    from lagsindy.systems import make_dataset

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--limit", type=float, default=600.0, help="seconds per fit")
    parser.add_argument("--trajectories", type=int, default=20)
    args = parser.parse_args(argv)
    rows = cases()
    n_traj, duration, limit = args.trajectories, 5.0, args.limit
    if args.quick:
        rows, limit = rows[:2], min(limit, 120.0)
    if tiny():
        rows, n_traj, duration, limit = rows[:1], 3, 2.0, 60.0
    table = [
        "| library | candidates | terms after reduction | correct structure "
        "| ratio error | fit time | learned |",
        "|---|---|---|---|---|---|---|",
    ]
    start = time.perf_counter()
    for label, system, library in rows:
        data = make_dataset(
            system,
            n_trajectories=n_traj,
            duration=duration,
            excitation=None,
            random_state=0,
        )
        library.build()
        est = LagrangianSINDy(library, case="acceleration", random_state=0)
        fitted, seconds, warned, error = timed_fit(est, data.X, time_limit=limit)
        print(f"[case2] {label}: {seconds:.1f} s {error or ''}", flush=True)
        if fitted is None:
            table.append(
                f"| {label} | {len(library.candidates_)} | {len(library)} | - | - "
                f"| {seconds:.0f} s | {short(error or '', 120)} |"
            )
            continue
        res = compare_structure(system, fitted, up_to_scale=True)
        table.append(
            f"| {label} | {len(library.candidates_)} | {len(library)} "
            f"| {'yes' if res['correct'] else 'no'} | {res['coef_error']:.2g} "
            f"| {seconds:.1f} s | `{short(fitted.equation(), 200)}` |"
        )
    total = time.perf_counter() - start
    text = (
        header("Case II against the library size")
        + __doc__.split("\n\n", 1)[1].rsplit("\n\n    python", 1)[0]
        + "\n\n"
    )
    text += (
        f"Data: {n_traj} trajectories x {duration:g} s x 100 Hz per row; fit limit "
        f"{limit:g} s; total run time {total / 60:.1f} min.\n\n"
    )
    text += "\n".join(table) + "\n"
    suffix = "_quick" if (args.quick or tiny()) else ""
    write(f"case2{suffix}.md", text)
    return 0


if __name__ == "__main__":
    main()
