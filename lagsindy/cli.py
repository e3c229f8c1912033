"""The ``lagsindy`` command (also ``python -m lagsindy``)."""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


class CLIError(Exception):
    """A user error: printed as one line, exit status 2."""


def _demo(args) -> int:
    from .estimator import LagrangianSINDy
    from .systems import get_system, make_dataset

    system = get_system(args.system)
    active = not args.passive
    data = make_dataset(
        system,
        n_trajectories=args.trajectories,
        excitation="sincos" if active else None,
        noise=args.noise,
        protocol=args.protocol,
        random_state=args.seed,
    )
    library = system.paper_library()
    est = LagrangianSINDy(
        library,
        fixed_term=None if active else system.fixed_term,
        unpenalized=None if active else system.prior_terms,
        random_state=args.seed,
        verbose=0 if args.quiet else 1,
    )
    if not args.quiet:
        print(
            f"{system.name}: {args.trajectories} trajectories x 5 s at 100 Hz, "
            f"{'forced' if active else 'passive'}, noise sigma={args.noise} "
            f"({args.protocol} protocol); library of {len(library)} terms"
        )
    start = time.perf_counter()
    est.fit(data.X, data.tau)
    elapsed = time.perf_counter() - start
    truth = system.true_coefficients(est.library_)
    learned = est.coef_
    if not active:  # passive data fix the scale by the fixed term
        truth = truth / truth[est.library_.index(est.fixed_term_)]
    names = est.term_names_
    rows = [k for k in range(len(names)) if truth[k] != 0 or learned[k] != 0]
    width = max(len(str(names[k])) for k in rows)
    print(f"\n{'term':<{width}}  {'true':>10}  {'learned':>10}  {'error':>8}")
    for k in rows:
        err = (
            f"{abs(learned[k] - truth[k]) / abs(truth[k]):8.2%}" if truth[k] != 0 else "   extra"
        )
        if truth[k] != 0 and learned[k] == 0:
            err = " missing"
        print(f"{names[k]:<{width}}  {truth[k]:10.4f}  {learned[k]:10.4f}  {err}")
    correct = np.array_equal(truth != 0, learned != 0)
    print(f"\nrecovered: {est.equation(4)}")
    print(f"structure {'correct' if correct else 'NOT correct'}; fit took {elapsed:.2f} s")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lagsindy",
        description="Discover the Lagrangian of a mechanical system from trajectories.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser(
        "demo",
        help="simulate a built-in system with noise, fit it, print true vs learned",
        description="Simulate a built-in system, add noise, fit a Lagrangian and print "
        "the true and recovered terms side by side.",
    )
    demo.add_argument("--system", default="cart_pendulum",
                      help="single_pendulum, cart_pendulum, double_pendulum, spherical_pendulum")
    demo.add_argument("--noise", type=float, default=0.01, help="noise sigma (default 0.01)")
    demo.add_argument("--protocol", default="paper", choices=["shared", "paper", "sensor"],
                      help="noise protocol (default: paper, independent noise)")
    demo.add_argument("--passive", action="store_true", help="no input (case III)")
    demo.add_argument("--trajectories", type=int, default=100)
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--quiet", action="store_true", help="no progress output")
    demo.set_defaults(func=_demo)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (CLIError, ValueError, FileNotFoundError) as exc:
        print(f"lagsindy: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
