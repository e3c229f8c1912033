"""The argument parser of the ``lagsindy`` command: options, help texts, defaults.

Imports only the standard library: ``lagsindy --help`` needs neither numpy's
numerics nor torch, sympy, scikit-learn or pandas. Each subcommand's ``func`` looks
its handler up in :mod:`lagsindy.cli` when it runs, so a handler patched there (in a
test) is the one that runs.
"""

from __future__ import annotations

import argparse

# The built-in systems (lagsindy.systems.SYSTEMS), named here so that --help does not
# import sympy; tests/test_cli.py checks that the two lists agree.
SYSTEM_NAMES = (
    "cart_pendulum",
    "double_pendulum",
    "elastic_pendulum",
    "planar_chain",
    "single_pendulum",
    "spherical_pendulum",
    "spring_chain",
    "triple_pendulum",
)


def _catalogue_help() -> str:
    """``--catalogue``'s help: diagnose's default kinds and the other force kinds."""
    from ..force_kinds import kinds  # standard library only

    default = [k.name for k in kinds() if k.in_default_catalogue]
    other = [k.name for k in kinds() if not k.in_default_catalogue]
    return (
        "comma-separated candidate kinds (default: "
        + ", ".join(["delay", *default, "gain", "conservative"])
        + "; also "
        + ", ".join([*other, "joint_delay (a delay per driven coordinate)"])
        + ")"
    )


class _Formatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, except for flags and options without one."""

    def _get_help_string(self, action):
        text = action.help or ""
        if (
            "%(default)" in text
            or "default" in text
            or action.default is None
            or action.default is False
            or action.default == argparse.SUPPRESS
            or not action.option_strings
        ):
            return text
        return text + " (default: %(default)s)"


class _Parser(argparse.ArgumentParser):
    """argparse with usage errors on one line (exit status 2)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _Formatter)
        super().__init__(*args, **kwargs)

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _command(name):
    """The ``func`` of a subcommand: calls ``lagsindy.cli.<name>`` at run time."""

    def run(args):
        from .. import cli

        return getattr(cli, name)(args)

    run.__name__ = run.__qualname__ = name
    return run


_QUIET = "print nothing but errors"


def _finish(p, command, *, quiet=_QUIET, derivatives=False, **defaults):
    """The options every subcommand ends with (derivative estimation where it reads
    positions, ``--quiet``) and the function that runs it."""
    if derivatives:
        _add_derivative_options(p)
    p.add_argument("--quiet", action="store_true", help=quiet)
    p.set_defaults(func=_command(command), **defaults)


def _add_derivative_options(p):
    p.add_argument(
        "--derivatives",
        metavar="METHOD",
        default=None,
        help="estimate q_dot and q_ddot from q with this method of "
        "lagsindy.differentiation (e.g. savgol, finite_difference) even "
        "when derivative columns exist; by default they are estimated "
        "only when the CSV lacks <q>_dot/<q>_ddot columns",
    )
    p.add_argument(
        "--dt",
        type=float,
        default=None,
        help="sampling interval in seconds when the CSV has no time column (default: "
        "none; without one and --dt the command stops and asks for one)",
    )
    p.add_argument(
        "--time",
        metavar="COLUMN",
        default="t",
        help="the time column (stamps may be uneven: jitter, dropped frames and "
        "gaps are handled as derivatives() and LagrangianSINDy.fit(t=) do: the clock "
        "cleaned, trajectories cut at gaps, the weak form's rows put on an even "
        "clock)",
    )
    p.add_argument(
        "--gap-factor",
        metavar="FACTOR",
        type=float,
        default=5.0,
        help="a time step longer than FACTOR base steps is a gap: the trajectory is "
        "cut there (as derivatives(gap_factor=))",
    )


def _window(text):
    """``--window``: an integer number of samples, or ``auto``."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a whole number of samples or 'auto', got {text!r}"
        ) from None


def _add_fit_options(p, *, required):
    """Options of a fit from a CSV (shared by ``fit`` and ``diagnose``)."""
    p.add_argument(
        "--coordinates",
        required=required,
        default=None,
        help="position columns, e.g. x,theta"
        + ("" if required else " (default: the model's, with --model)"),
    )
    p.add_argument(
        "--angles",
        default="",
        help="coordinates that are angles (get sin/cos), e.g. theta, or 'all'",
    )
    p.add_argument(
        "--input",
        default=None,
        help="generalized-force columns, one per coordinate, e.g. tau_x,tau_theta; "
        "'-' or 0 for an undriven coordinate (zero force), e.g. force,- for a "
        "cart-pole driven on the cart only (an undriven first coordinate: "
        "--input=-,force or 0,force) (default: tau_<coordinate> when the CSV has all "
        "of them, else passive data)",
    )
    p.add_argument(
        "--conservative",
        action="store_true",
        help="keep the conservative fit even when friction or damping explains most "
        "of what it leaves (default: the Lagrangian is then fitted jointly with "
        "viscous and Coulomb friction candidates, and a warning says so)",
    )
    p.add_argument(
        "--undriven",
        default=None,
        help="coordinates that nothing drives (their force is zero), e.g. theta; "
        "--input then names the driven coordinates' columns (default tau_<q>)",
    )
    p.add_argument(
        "--passive", action="store_true", help="ignore input columns (case III)"
    )
    p.add_argument(
        "--library",
        default="poly3",
        help="candidate terms: polyN (all monomials of degree 1..N over q, q_dot and "
        "sin/cos of the angles), separatedN (the paper's trigonometric x "
        "non-trigonometric products), chain (a chain of links: each coordinate's "
        "kinetic and potential terms and their couplings, "
        "CandidateLibrary.chain(coordinates, angles=--angles); a cart-pole's four "
        "terms in 8) or terms (only --terms). poly3 holds a "
        "cart-pendulum's x_dot*theta_dot*cos(theta); two coupled angles (a double "
        "pendulum's cos(theta1 - theta2)) need poly4; a warning says when the "
        "library cannot couple the coordinates (default: poly3)",
    )
    p.add_argument(
        "--raw-angles",
        action="store_true",
        help="also use the angles themselves as polynomial variables",
    )
    p.add_argument(
        "--terms",
        default="",
        help="extra candidate terms, comma-separated, e.g. "
        "'x_dot*theta_dot*cos(theta)'",
    )
    p.add_argument(
        "--fixed-term",
        default=None,
        help="passive data: the term whose coefficient is fixed to 1, e.g. "
        "theta_dot**2, or 'mass' to fix the mean trace of the mass matrix "
        "(default: try both and every term)",
    )
    p.add_argument(
        "--unpenalized",
        default="",
        help="terms known to be present (never shrunk or thresholded), comma-separated",
    )
    p.add_argument(
        "--case",
        default="auto",
        choices=["auto", "forces", "fixed", "acceleration"],
        help="forces (case I, with inputs), fixed (case III: passive, one term fixed), "
        "acceleration (case II: passive, no prior), or auto from the input columns",
    )
    p.add_argument(
        "--lam",
        type=float,
        default=1e-3,
        help="L1 weight of the first stage on the scaled problem, >= 0 (default 1e-3)",
    )
    p.add_argument(
        "--threshold",
        type=float,
        default=0.05,
        help="relative hard threshold between stages (default 0.05)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="random seed (case III search, case II) (default 0)",
    )
    p.add_argument(
        "--precision",
        type=int,
        default=4,
        help="digits in the printed Lagrangian (default 4)",
    )
    p.add_argument(
        "--formulation",
        default="auto",
        choices=["auto", "strong", "weak"],
        help="auto: the weak form on time-ordered trajectories, else the strong form "
        "with a warning; strong: the paper's pointwise residual (biased when the data "
        "are noisy); weak: integral Euler-Lagrange equations with a noise correction "
        "(needs time-ordered trajectories; see LagrangianSINDy)",
    )
    p.add_argument(
        "--window",
        type=_window,
        metavar="SAMPLES|auto",
        default="auto",
        help="samples per test function of the weak form, >= 5, or 'auto' (default "
        "auto: 81 samples, doubled to 161, 321, 641 while the coefficients move by "
        "more than 3 %% and the next window confirms the longer one, since the "
        "smoothed derivatives' errors bias short windows; a warning says when no "
        "window settles)",
    )
    p.add_argument(
        "--delay",
        metavar="SECONDS|auto",
        default=None,
        help="input delay: the input recorded at t acts at t + SECONDS, so the inputs "
        "are shifted by it (linear interpolation per trajectory; the first SECONDS "
        "of each trajectory hold the first input). 'auto': estimate it by held-out "
        "fits over whole-sample shifts (lagsindy.delay.estimate_delay; slow: about "
        "40 fits) (default: none, the inputs act when recorded)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``lagsindy`` command."""
    from .._version import __version__

    systems = ", ".join(SYSTEM_NAMES)
    parser = _Parser(
        prog="lagsindy",
        description="Discover the Lagrangian of a mechanical system from trajectories "
        "(xL-SINDy). Run 'lagsindy COMMAND --help' for a command's options.",
    )
    parser.add_argument(
        "--version", action="version", version=f"lagsindy {__version__}"
    )
    parser.add_argument(
        "--debug", action="store_true", help="show the Python traceback of errors"
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    demo = sub.add_parser(
        "demo",
        help="simulate a built-in system with noise, fit it, print true vs learned",
        description="Simulate a built-in system, add noise, fit a Lagrangian, print "
        "the "
        "true and recovered terms side by side with their errors, and save a plot of "
        "true vs learned trajectories.",
    )
    demo.add_argument("--system", default="cart_pendulum", help=f"one of: {systems}")
    demo.add_argument(
        "--noise", type=float, default=0.01, help="noise sigma (default 0.01)"
    )
    demo.add_argument(
        "--protocol",
        default="paper",
        choices=["shared", "paper", "sensor"],
        help="noise protocol (default: paper, independent noise)",
    )
    demo.add_argument("--passive", action="store_true", help="no input (case III)")
    demo.add_argument(
        "--formulation",
        default="auto",
        choices=["auto", "strong", "weak"],
        help="auto (the library's default: the weak form on trajectories), strong "
        "(the paper's pointwise residual, biased by noise) or weak (integral form "
        "with noise correction: removes the noise bias of the coefficients)",
    )
    demo.add_argument(
        "--trajectories",
        type=int,
        default=100,
        help="number of trajectories (default 100, as in the paper)",
    )
    demo.add_argument(
        "--duration", type=float, default=5.0, help="seconds per trajectory (default 5)"
    )
    demo.add_argument(
        "--seed", type=int, default=0, help="random seed of the data and the fit"
    )
    demo.add_argument(
        "--plot",
        metavar="PNG",
        default="demo.png",
        help="where to save the trajectory comparison (default demo.png; "
        "needs matplotlib)",
    )
    demo.add_argument(
        "--no-plot",
        dest="plot",
        action="store_const",
        const=None,
        help="do not save a plot",
    )
    _finish(
        demo,
        "_demo",
        quiet="no progress output (stage lines, notes): results and errors only",
    )

    sim = sub.add_parser(
        "simulate",
        help="write a simulated data set (CSV) of a built-in system or a saved model",
        description="Simulate a built-in system from random initial states with the "
        "documented input and noise protocol and write one CSV (columns trajectory, t, "
        "q..., q_dot..., q_ddot..., tau_<q>...). With --model, integrate a saved model "
        "instead (same as simulate-model).",
    )
    sim.add_argument("--system", default=None, help=f"one of: {systems}")
    sim.add_argument("--model", default=None, help="a saved model (JSON) to integrate")
    sim.add_argument("--out", required=True, help="output CSV")
    sim.add_argument(
        "--trajectories",
        type=int,
        default=100,
        help="number of trajectories, each from a random initial state",
    )
    sim.add_argument(
        "--duration", type=float, default=5.0, help="seconds per trajectory"
    )
    sim.add_argument("--rate", type=float, default=100.0, help="samples per second")
    sim.add_argument("--noise", type=float, default=0.0, help="noise sigma (default 0)")
    sim.add_argument(
        "--protocol",
        default="paper",
        choices=["shared", "paper", "sensor"],
        help="shared: one sample per time step on every channel (the "
        "authors' code); paper: independent noise on q, q_dot, q_ddot; "
        "sensor: noise on q, derivatives estimated (default paper)",
    )
    sim.add_argument(
        "--excitation",
        default="sincos",
        choices=["sincos", "paper"],
        help="input: a sin(wt) + b cos(wt) (sincos) or the paper's form for the system",
    )
    sim.add_argument("--passive", action="store_true", help="no input")
    sim.add_argument(
        "--positions-only",
        action="store_true",
        help="write only trajectory, t, the positions (and tau columns)",
    )
    sim.add_argument(
        "--x0",
        action="append",
        default=None,
        help="with --model, and then required: initial state q...,q_dot... (repeat "
        "for more)",
    )
    sim.add_argument(
        "--seed",
        type=int,
        default=0,
        help="random seed of the initial states, inputs and noise",
    )
    _finish(sim, "_simulate")

    simm = sub.add_parser(
        "simulate-model",
        help="integrate a saved model from given initial states (unforced), write CSV",
        description="Integrate the equations of motion of a saved model (no input) and "
        "write trajectory, t, q..., q_dot..., q_ddot... as CSV.",
    )
    simm.add_argument("model", help="saved model (JSON)")
    simm.add_argument(
        "--x0",
        action="append",
        required=True,
        help="initial state q...,q_dot..., e.g. 0,1,0,0 (repeat for more)",
    )
    simm.add_argument(
        "--duration", type=float, default=5.0, help="seconds to integrate"
    )
    simm.add_argument(
        "--rate", type=float, default=100.0, help="output samples per second"
    )
    simm.add_argument("--out", required=True, help="output CSV")
    _finish(simm, "_simulate_model", system=None)

    fit = sub.add_parser(
        "fit",
        help="fit a Lagrangian to a CSV of trajectories and save the model (JSON)",
        description="Fit a Lagrangian to trajectories in a CSV file. Needed columns: "
        "one "
        "per coordinate (positions). Velocities <q>_dot and accelerations <q>_ddot are "
        "used when present, else estimated per trajectory (columns 't' and, for "
        "several "
        "trajectories, 'trajectory'). Input forces: --input, or columns tau_<q> when "
        "present; without them the data are treated as passive (case III).",
    )
    fit.add_argument("data", help="CSV file")
    _add_fit_options(fit, required=True)
    fit.add_argument("--out", required=True, help="where to save the model (JSON)")
    fit.add_argument(
        "--held-out",
        type=float,
        default=0.2,
        metavar="SHARE",
        help="share of the trajectories (of one trajectory: its final time block) "
        "held out to report R^2 on data the fit did not see, from a second fit on "
        "the rest (the saved model is the fit on all data); 0: no held-out score "
        "and no second fit (default: 0.2; skipped with --quiet)",
    )
    fit.add_argument(
        "--refine",
        type=int,
        default=None,
        metavar="SAMPLES",
        help="then refine the kept coefficients by the error of rollouts of SAMPLES "
        "samples from the measured states (lagsindy.refine; the saved model is the "
        "refined one, the held-out score is the sparse fit's) (default: no "
        "refinement)",
    )
    _finish(
        fit,
        "_fit",
        derivatives=True,
        quiet="print only the Lagrangian (and errors, and warnings that the result "
        "may be wrong)",
    )

    diag = sub.add_parser(
        "diagnose",
        help="find what a fitted model leaves unexplained (friction, damping, ...) "
        "and add it",
        description="Residual diagnosis: fit a Lagrangian (or load --model), test "
        "candidate missing effects (viscous, joint and quadratic damping, Coulomb "
        "friction, offsets, input gain errors, missing conservative terms) jointly "
        "with the Lagrangian's terms, keep those that improve the prediction of "
        "held-out trajectories, and report the errors before and after. Prints the "
        "report; --plot saves the residual figure.",
    )
    diag.add_argument("data", help="CSV file")
    diag.add_argument(
        "--model",
        default=None,
        help="a saved model (JSON) to diagnose (default: fit the CSV first, with the "
        "options below)",
    )
    _add_fit_options(diag, required=False)
    diag.add_argument(
        "--min-explained",
        type=float,
        default=0.05,
        help="smallest share of the held-out trajectory residual an effect must "
        "explain (default 0.05)",
    )
    diag.add_argument(
        "--max-effects", type=int, default=4, help="add at most this many effects"
    )
    diag.add_argument(
        "--splits",
        type=int,
        default=3,
        help="held-out folds of trajectories (time blocks when there are fewer)",
    )
    diag.add_argument(
        "--catalogue",
        default=None,
        help=_catalogue_help(),
    )
    diag.add_argument(
        "--bootstrap",
        type=int,
        default=None,
        metavar="N",
        help="bootstrap the final model with N resamples of whole trajectories (time "
        "blocks with fewer than 10) and print each term's and effect's interval "
        "(resamples seeded by --seed) (default: no bootstrap)",
    )
    diag.add_argument(
        "--plot", default=None, help="save the residual figure (PNG) (default: none)"
    )
    diag.add_argument(
        "--out-model",
        default=None,
        help="save the final model (JSON) (default: not saved)",
    )
    _finish(
        diag,
        "_diagnose",
        derivatives=True,
        quiet="print only the report (and errors, and warnings that the result may "
        "be wrong)",
    )

    pred = sub.add_parser(
        "predict",
        help="predict forces and accelerations of a CSV with a saved model",
        description="Write the generalized forces the model implies (tau_<q>, inverse "
        "dynamics) and the accelerations it predicts (<q>_ddot, forward dynamics with "
        "the "
        "input columns when present) for each row of a CSV.",
    )
    pred.add_argument("model", help="saved model (JSON)")
    pred.add_argument("data", help="CSV file with the model's coordinates")
    pred.add_argument(
        "--input",
        default=None,
        help="generalized-force columns (default tau_<q>); '-' for an undriven "
        "coordinate",
    )
    pred.add_argument(
        "--undriven",
        default=None,
        help="coordinates with zero force, e.g. theta (default: none)",
    )
    pred.add_argument("--passive", action="store_true", help="ignore input columns")
    pred.add_argument("--out", required=True, help="output CSV")
    _finish(pred, "_predict", derivatives=True)

    from ..export.command import add_export_command

    add_export_command(sub)
    return parser
