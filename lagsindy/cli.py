"""The ``lagsindy`` command (also ``python -m lagsindy``).

Subcommands: ``demo``, ``simulate``, ``simulate-model``, ``fit`` and ``predict``; each
has ``--help``. Bad input (a missing file, an unknown column, a wrong shape, NaN, an
invalid model file) ends with ONE line on stderr and exit status 2, never a traceback
(``--debug`` shows it).

The module imports only the standard library and numpy at import time: torch, sympy,
scikit-learn and pandas are imported inside the commands that need them, so
``lagsindy --help`` answers at once.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
import warnings
from pathlib import Path

import numpy as np

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

# Warnings that are information, not a doubt about the result: --quiet drops them.
_INFO_WARNINGS = (
    "it will compute on the CPU",
    "they used the longest odd window they hold",
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


class CLIError(Exception):
    """A user error: printed as one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    """argparse with usage errors on one line (exit status 2)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _Formatter)
        super().__init__(*args, **kwargs)

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _say(args, *parts):
    if not getattr(args, "quiet", False):
        print(*parts, flush=True)


# ----------------------------------------------------------------------------- data in
def _read_csv(path):
    import pandas as pd

    p = Path(path)
    if not p.exists():
        raise CLIError(f"file not found: {path}")
    if p.is_dir():
        raise CLIError(f"{path} is a folder, not a CSV file")
    try:
        df = pd.read_csv(p)
    except pd.errors.EmptyDataError:
        raise CLIError(f"{path} is empty") from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise CLIError(f"{path} is not a readable CSV file: {exc}") from None
    if df.shape[1] == 1 and ";" in str(df.columns[0]):
        # A semicolon-separated file (common where the decimal mark is a comma).
        try:
            df = pd.read_csv(p, sep=";")
        except (pd.errors.ParserError, UnicodeDecodeError) as exc:
            raise CLIError(
                f"{path} looks semicolon-separated but could not be read as such: "
                f"{exc}; save it with commas as separators"
            ) from None
        warnings.warn(
            f"{path} is semicolon-separated; read it with ';' as the separator "
            "(decimal marks must be dots)",
            UserWarning,
            stacklevel=2,
        )
    if df.shape[0] == 0:
        raise CLIError(f"{path} has a header but no rows")
    df.columns = [str(c).strip() for c in df.columns]
    return df


def _split(text):
    return [s.strip() for s in text.split(",") if s.strip()] if text else []


def _line(i):
    """The file line of data row ``i`` (0-based; the header is line 1)."""
    return f"line {i + 2}"


def _numeric(df, columns, source):
    """The named columns as a float array; names the column and line of bad values."""
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise CLIError(
            f"{source} has no column {missing[0]!r} (its columns: "
            f"{', '.join(map(str, df.columns[:20]))}"
            f"{' ...' if len(df.columns) > 20 else ''})"
        )
    out = np.empty((len(df), len(columns)))
    for j, c in enumerate(columns):
        values = df[c]
        try:
            out[:, j] = values.to_numpy(dtype=float)
        except (TypeError, ValueError):
            bad = next((i for i, v in enumerate(values) if not _is_float(v)), 0)
            value = values.iloc[bad]
            hint = (
                "; decimal commas are not supported: use a dot (1.5, not 1,5)"
                if re.fullmatch(r"\s*[-+]?\d*,\d+\s*", str(value))
                else ""
            )
            raise CLIError(
                f"column {c!r} of {source} is not numeric: {_line(bad)} holds "
                f"{value!r}{hint}"
            ) from None
        finite = np.isfinite(out[:, j])
        if not finite.all():
            row = int(np.flatnonzero(~finite)[0])
            raise CLIError(
                f"column {c!r} of {source} has {int((~finite).sum())} NaN or infinite "
                f"value(s), the first on {_line(row)}; drop or fill those rows"
            )
    return out


def _is_float(v):
    try:
        float(v)
    except (TypeError, ValueError):
        return False
    return True


def _state_frame(df, coords, args, source):
    """X as a DataFrame ``[q, q_dot, q_ddot]``; derivatives estimated if absent."""
    return _state_and_groups(df, coords, args, source)[0]


def _state_and_groups(df, coords, args, source, angles=()):
    """X ``[q, q_dot, q_ddot]`` and the trajectory labels to fit with.

    When derivatives are estimated, ``angles`` are unwrapped per trajectory (as
    ``Derivatives(angles=...)`` does in the API) and trajectories are cut at gaps in
    ``t`` (one warning says where); the labels returned are then the segments.
    """
    import pandas as pd

    from ._expr import state_names

    names = state_names(coords)
    q = _numeric(df, coords, source)
    have_derivatives = all(n in df.columns for n in names)
    method = getattr(args, "derivatives", None)
    groups = df["trajectory"].to_numpy() if "trajectory" in df.columns else None
    if have_derivatives and method is None:
        X = pd.DataFrame(_numeric(df, names, source), columns=names, index=df.index)
        return X, groups
    from .differentiation import derivatives

    if "t" in df.columns:
        t = _numeric(df, ["t"], source)[:, 0]
    elif getattr(args, "dt", None):
        t = np.arange(len(df)) * float(args.dt)
    else:
        raise CLIError(
            f"{source} has positions only and no 't' column: add a time column 't' or "
            "pass --dt SECONDS (the sampling interval)"
        )
    for idx in _group_rows(groups, len(df)):
        if idx.size < 5:
            raise CLIError(
                f"a trajectory in {source} has {idx.size} rows; derivative estimation "
                "needs at least 5 samples per trajectory"
            )
        if np.any(np.diff(t[idx]) <= 0):
            raise CLIError(
                f"'t' must increase within each trajectory in {source} (sort the rows, "
                "and give separate trajectories a 'trajectory' column)"
            )
    kwargs = {"groups": groups, "return_groups": True}
    if method is not None:
        kwargs["method"] = method
    mask = [c in angles for c in coords]
    if any(mask):
        kwargs["angles"] = mask
    _say(
        args,
        f"estimating velocities and accelerations of {coords} "
        f"({method or 'default method'}"
        + (f"; angles {list(angles)} unwrapped" if any(mask) else "")
        + ") ...",
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        X, segments = derivatives(q, t, **kwargs)
    for w in caught:
        text = str(w.message)
        if "gap(s) in the time stamps" in text:
            text = (
                text.split(" Fit with the segments")[0]
                + " The fit uses these segments as separate trajectories."
            )
        warnings.warn_explicit(text, w.category, w.filename, w.lineno)
    n_segments = len(np.unique(segments))
    n_before = 1 if groups is None else len(np.unique(groups))
    if n_segments > n_before:
        groups = segments
    X = np.asarray(X, dtype=float)
    if X.shape != (len(df), 3 * len(coords)):
        raise CLIError(
            f"derivative estimation returned shape {X.shape}, expected "
            f"{(len(df), 3 * len(coords))}"
        )
    return pd.DataFrame(X, columns=names, index=df.index), groups


def _group_rows(groups, n):
    if groups is None:
        return [np.arange(n)]
    _, first = np.unique(groups, return_index=True)
    return [np.flatnonzero(groups == groups[s]) for s in np.sort(first)]


def _input_columns(df, coords, args):
    """Names of the generalized-force columns, or None for passive data."""
    if getattr(args, "passive", False):
        return None
    if args.input:
        cols = _split(args.input)
        if len(cols) != len(coords):
            raise CLIError(
                f"--input names {len(cols)} column(s) but there are {len(coords)} "
                f"coordinate(s) {coords}: give one generalized-force column per "
                "coordinate"
            )
        return cols
    named = [f"tau_{c}" for c in coords]
    if all(c in df.columns for c in named):
        return named
    return None


# ----------------------------------------------------------------------------- demo
def _demo(args) -> int:
    from .dynamics import rollout_error
    from .estimator import LagrangianSINDy
    from .systems import get_system, make_dataset

    system = get_system(args.system)
    if args.trajectories < 1:
        raise CLIError("--trajectories must be at least 1")
    active = not args.passive
    data = make_dataset(
        system,
        n_trajectories=args.trajectories,
        duration=args.duration,
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
        formulation=args.formulation,
        dt=0.01,
    )
    _say(
        args,
        f"{system.name}: {args.trajectories} trajectories x {args.duration:g} s "
        "at 100 Hz, "
        f"{'forced' if active else 'passive'}, noise sigma={args.noise} "
        f"({args.protocol} protocol); library of {len(library)} terms; "
        f"{args.formulation} form",
    )
    start = time.perf_counter()
    est.fit(data.X, data.tau, groups=data.groups)
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
            f"{abs(learned[k] - truth[k]) / abs(truth[k]):8.2%}"
            if truth[k] != 0
            else "   extra"
        )
        if truth[k] != 0 and learned[k] == 0:
            err = " missing"
        print(f"{names[k]:<{width}}  {truth[k]:10.4f}  {learned[k]:10.4f}  {err}")
    correct = np.array_equal(truth != 0, learned != 0)
    print(f"\ntrue:      {system.equation(4)}")
    print(f"recovered: {est.equation(4)}")
    if not active:
        print(
            f"(passive data fix the scale: {est.fixed_term_} has coefficient 1, "
            "and the "
            "'true' column above is scaled to match)"
        )
    print(
        f"structure {'correct' if correct else 'NOT correct'}; fit took {elapsed:.2f} s"
    )

    # Trajectory check: both models, unforced, from a fresh initial state.
    x0 = system.sample_initial_states(1, np.random.RandomState(args.seed + 1))[0]
    t = np.arange(int(round(args.duration * 100)) + 1) / 100.0
    try:
        check = rollout_error(system, est.model_, x0, t)
    except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
        print(
            f"trajectory check skipped: the true system could not be integrated ({exc})"
        )
        return 0
    if "error" in check:
        print(
            "trajectory check: the learned model could not be integrated: "
            f"{check['error']}"
        )
    else:
        print(
            f"trajectory check (unforced, {t[-1]:g} s from a new initial state): "
            f"max |q_true - q_learned| = {check['max_abs_q']:.3g}"
        )
    if args.plot is not None:
        try:
            from .plotting import plot_trajectories

            plot_trajectories(
                t,
                check["states_a"],
                check["states_b"],
                system.coordinates,
                velocities=True,
                units=[
                    "rad" if c in system.angles else "m" for c in system.coordinates
                ],
                title=f"{system.name}: true vs learned (unforced)",
                path=args.plot,
            )
        except ImportError as exc:
            print(f"no plot: {exc}")
        else:
            print(f"saved the trajectory comparison to {args.plot}")
    return 0


# ----------------------------------------------------------------------------- simulate
def _simulate(args) -> int:
    if args.model is not None:
        if args.system is not None:
            raise CLIError("give either --system or --model, not both")
        if not args.x0:
            raise CLIError("simulating a saved model needs --x0 (the initial state)")
        return _simulate_model(args)
    if args.system is None:
        raise CLIError(
            "give --system NAME (a built-in system) or --model FILE (a saved model)"
        )
    from .systems import get_system, make_dataset

    system = get_system(args.system)
    if args.trajectories < 1:
        raise CLIError("--trajectories must be at least 1")
    if not (args.duration > 0 and args.rate > 0 and args.noise >= 0):
        raise CLIError("--duration and --rate must be positive, --noise >= 0")
    _check_out(args.out)
    excitation = None if args.passive else args.excitation
    data = make_dataset(
        system,
        n_trajectories=args.trajectories,
        duration=args.duration,
        rate=args.rate,
        excitation=excitation,
        noise=args.noise,
        protocol=args.protocol,
        random_state=args.seed,
    )
    df = data.to_frame()
    if args.positions_only:
        keep = ["trajectory", "t", *system.coordinates]
        keep += [c for c in df.columns if c.startswith("tau_")]
        df = df[keep]
    _write_csv(df, args.out)
    _say(
        args,
        f"wrote {args.out}: {system.name}, {args.trajectories} trajectories x "
        f"{args.duration:g} s at {args.rate:g} Hz ({len(df)} rows), "
        f"{'passive' if excitation is None else f'input {excitation!r}'}, noise "
        f"sigma={args.noise} ({args.protocol} protocol); "
        f"columns: {', '.join(df.columns)}",
    )
    return 0


def _check_out(out):
    """Fail early (before a long fit) when the output cannot be written."""
    out = Path(out)
    if out.is_dir():
        raise CLIError(f"--out {out} is a folder; give a file name")
    if not out.parent.is_dir():
        raise CLIError(f"cannot write {out}: the folder {out.parent} does not exist")
    return out


def _write_csv(df, out):
    df.to_csv(_check_out(out), index=False, float_format="%.12g")


def _load(path):
    from .io import load_model

    if not Path(path).is_file():
        raise CLIError(f"model file not found: {path}")
    return load_model(path)


def _simulate_model(args) -> int:
    import pandas as pd

    from ._expr import state_names

    _check_out(args.out)
    est = _load(args.model)
    n = est.n_dof_
    x0 = []
    for text in args.x0:
        try:
            values = [float(v) for v in _split(text)]
        except ValueError:
            raise CLIError(
                f"--x0 {text!r} is not a comma-separated list of numbers"
            ) from None
        if len(values) != 2 * n:
            raise CLIError(
                f"--x0 {text!r} has {len(values)} value(s); the model's state "
                f"{state_names(est.coordinates_, accelerations=False)} has {2 * n}"
            )
        if not np.all(np.isfinite(values)):
            raise CLIError(f"--x0 {text!r} contains NaN or infinite values")
        x0.append(values)
    if args.duration <= 0 or args.rate <= 0:
        raise CLIError("--duration and --rate must be positive")
    t = np.arange(int(round(args.duration * args.rate)) + 1) / args.rate
    frames = []
    for k, start in enumerate(x0):
        states = est.simulate(np.asarray(start), t)
        X = est.model_.trajectory_to_X(states)
        frame = pd.DataFrame(X, columns=state_names(est.coordinates_))
        frame.insert(0, "t", t)
        frame.insert(0, "trajectory", k)
        frames.append(frame)
    df = pd.concat(frames, ignore_index=True)
    _write_csv(df, args.out)
    _say(
        args,
        f"wrote {args.out}: {len(x0)} trajectory(ies) x {t[-1]:g} s of "
        f"{est.equation(4)} (unforced)",
    )
    return 0


# ----------------------------------------------------------------------------- fit
_LIBRARY_RE = re.compile(r"(poly|polynomial|sep|separated)(\d+)\Z")


def _library(args, coords, angles):
    from .library import CandidateLibrary

    spec = args.library.strip().lower()
    extra = _split(args.terms)
    if spec == "terms":
        if not extra:
            raise CLIError("--library terms needs --terms 'a,b,...'")
        return CandidateLibrary.from_terms(coords, extra)
    m = _LIBRARY_RE.match(spec)
    if not m:
        raise CLIError(
            f"--library {args.library!r} is not known: use polyN (all monomials of "
            "degree 1..N over q, q_dot, sin/cos of angles), separatedN (the paper's "
            "trigonometric x non-trigonometric construction) or terms (only --terms)"
        )
    degree = int(m.group(2))
    if not 1 <= degree <= 6:
        raise CLIError(f"--library degree must be between 1 and 6, got {degree}")
    builder = (
        CandidateLibrary.polynomial
        if m.group(1).startswith("poly")
        else CandidateLibrary.separated
    )
    return builder(
        coords,
        angles=angles or None,
        degree=degree,
        raw_angles=args.raw_angles,
        terms=extra or None,
    )


def _check_numbers(args):
    """Range checks of the numeric fit options (cheap, before any data work)."""
    if not (np.isfinite(args.lam) and args.lam >= 0):
        raise CLIError(f"--lam must be a number >= 0 (the L1 weight), got {args.lam}")
    if not (np.isfinite(args.threshold) and 0 <= args.threshold < 1):
        raise CLIError(
            f"--threshold must be in [0, 1) (relative to the largest coefficient), "
            f"got {args.threshold}"
        )
    if getattr(args, "dt", None) is not None and not (
        np.isfinite(args.dt) and args.dt > 0
    ):
        raise CLIError(f"--dt must be a positive number of seconds, got {args.dt}")


def _warn_missing_coupling(library, coords, angles, args):
    """Warn when no candidate term can couple an angle with another coordinate.

    A cart-pendulum's kinetic energy holds ``x_dot*theta_dot*cos(theta)``; a double
    pendulum's ``theta1_dot*theta2_dot*cos(theta1 - theta2)``, which expands into
    products of both angles' sin/cos. A library without such a term (``poly2`` has
    none; ``poly3`` lacks the double pendulum's) cannot express the coupling, and the
    fit returns a wrong Lagrangian without any other sign.
    """
    import sympy as sp

    trig = (sp.sin, sp.cos)
    found = []
    for term in library.terms_:
        names = {str(v) for v in term.free_symbols}
        trig_of = {str(v) for f in term.atoms(*trig) for v in f.args[0].free_symbols}
        found.append((names, trig_of))
    missing = []
    for i, a in enumerate(coords):
        for b in coords[i + 1 :]:
            need = [c for c in (a, b) if c in angles]
            if not need:
                continue
            if not any(
                f"{a}_dot" in names and f"{b}_dot" in names and set(need) <= trig_of
                for names, trig_of in found
            ):
                missing.append((a, b, need))
    if not missing:
        return
    a, b, need = missing[0]
    example = (
        f"{a}_dot*{b}_dot*cos({need[0]})"
        if len(need) == 1
        else f"{a}_dot*{b}_dot*cos({a} - {b})"
    )
    degree = 3 if len(need) == 1 else 4
    warnings.warn(
        f"the library {args.library} has no term coupling the velocities of {a} and "
        f"{b} with the angle(s) {need} (such as {example}, as in a cart-pendulum or "
        f"a double pendulum), so it cannot express that coupling"
        + (f" ({len(missing)} such pairs)" if len(missing) > 1 else "")
        + f"; use --library poly{degree} or add it with --terms '{example}' if the "
        "coordinates are coupled",
        UserWarning,
        stacklevel=2,
    )


def _fit(args) -> int:
    _check_out(args.out)
    est, X, tau, inputs, elapsed = _fit_csv(args)
    est.save(args.out)
    print(est.equation(args.precision))
    kept = int(est.support_.sum())
    if tau is not None:
        quality = f"R^2 of forces {est.score(X, tau):.4f}"
    else:
        quality = f"R^2 of accelerations {est.score(X):.4f}"
    _say(
        args,
        f"{kept} of {len(est.coef_)} terms kept, {quality}; fit took "
        f"{elapsed:.1f} s; saved the model to {args.out}",
    )
    return 0


def _fit_csv(args):
    """Read the CSV named in ``args`` and fit a model as the options say."""
    from ._expr import check_coordinate_names
    from .estimator import LagrangianSINDy

    coords = _split(args.coordinates)
    if not coords:
        raise CLIError("--coordinates needs at least one column name, e.g. x,theta")
    check_coordinate_names(coords)
    angles = coords if args.angles == "all" else _split(args.angles)
    unknown = [a for a in angles if a not in coords]
    if unknown:
        raise CLIError(f"--angles {unknown} are not among --coordinates {coords}")
    _check_numbers(args)
    # Everything cheap is checked before the (slow) derivative estimation.
    library = _library(args, coords, angles)
    df = _read_csv(args.data)
    inputs = _input_columns(df, coords, args)
    if inputs is not None and args.fixed_term is not None:
        raise CLIError(
            "--fixed-term is for passive data (case III), but the input columns "
            f"{inputs} "
            "were found; pass --passive to ignore them, or drop --fixed-term"
        )
    tau = None if inputs is None else _numeric(df, inputs, args.data)
    _numeric(df, coords, args.data)
    _warn_missing_coupling(library, coords, angles, args)
    X, groups = _state_and_groups(df, coords, args, args.data, angles)
    est = LagrangianSINDy(
        library,
        lam=args.lam,
        threshold=args.threshold,
        fixed_term=args.fixed_term,
        unpenalized=_split(args.unpenalized) or None,
        case=args.case,
        formulation=getattr(args, "formulation", "auto"),
        random_state=args.seed,
        verbose=0 if args.quiet else 1,
    )
    tau = _apply_delay(args, df, X, tau, groups, est)
    _say(
        args,
        f"fitting {len(X)} samples of {coords}: "
        + (f"forces from {inputs}" if inputs else "passive (no input columns)")
        + f", library {args.library} ({len(library)} terms after reduction)",
    )
    start = time.perf_counter()
    est.fit(X, tau, groups=groups)
    elapsed = time.perf_counter() - start
    args._groups = groups  # the segments, for diagnose
    return est, X, tau, inputs, elapsed


def _apply_delay(args, df, X, tau, groups, est):
    """Shift the inputs by ``--delay`` (seconds, or ``auto``: estimated with ``est``)."""
    value = getattr(args, "delay", None)
    if value is None:
        return tau
    if tau is None:
        raise CLIError(
            "--delay shifts the input columns, but the data have none (passive data); "
            "drop --delay or give the input with --input"
        )
    from .delay import estimate_delay, shift_input

    if "t" in df.columns:
        t = _numeric(df, ["t"], args.data)[:, 0]
    elif getattr(args, "dt", None):
        t = np.arange(len(df)) * float(args.dt)
    else:
        raise CLIError("--delay needs a 't' column or --dt SECONDS")
    if value == "auto":
        if est is None:
            raise CLIError(
                "--delay auto estimates the delay by refitting; with --model give the "
                "delay in seconds (e.g. the one `lagsindy fit --delay auto` printed)"
            )
        _say(args, "estimating the input delay (held-out fits over sample shifts) ...")
        result = estimate_delay(est, X, tau, t, groups=groups)
        _say(args, f"{result}; the inputs are shifted by it")
        delay = result.delay
    else:
        try:
            delay = float(value)
        except ValueError:
            raise CLIError(
                f"--delay must be a number of seconds or 'auto', got {value!r}"
            ) from None
    return shift_input(tau, t, delay, groups)


# ----------------------------------------------------------------------------- diagnose
def _diagnose(args) -> int:
    from .diagnostics import diagnose

    for out in (args.plot, args.out_model):
        if out:
            _check_out(out)
    if args.model:
        est = _load(args.model)
        df = _read_csv(args.data)
        coords = list(est.coordinates_)
        angles = est.library._angle_names(coords) if est.library is not None else []
        inputs = _input_columns(df, coords, args)
        tau = None if inputs is None else _numeric(df, inputs, args.data)
        if (tau is None) != (est.case_ != "forces"):
            raise CLIError(
                "the model was fitted "
                + ("with" if est.case_ == "forces" else "without")
                + " input forces; diagnose it on data of the same kind (--input or "
                "tau_<q> columns for forced data, --passive for passive data)"
            )
        # The cheap checks above run before the (slow) derivative estimation.
        X, groups = _state_and_groups(df, coords, args, args.data, angles)
        tau = _apply_delay(args, df, X, tau, groups, None)
    else:
        if not args.coordinates:
            raise CLIError("give --model model.json, or --coordinates to fit one first")
        est, X, tau, inputs, _ = _fit_csv(args)
        groups = args._groups
        _say(args, f"fitted: {est.equation(args.precision).splitlines()[0]}")
    est.set_params(verbose=0)  # diagnose's refits print no stage lines
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="X has feature names")
        report = diagnose(
            est,
            X,
            tau,
            groups=groups,
            min_explained=args.min_explained,
            max_effects=args.max_effects,
            n_splits=args.splits,
            bootstrap=args.bootstrap,
            random_state=args.seed,
            **(
                {"catalogue": tuple(k.strip() for k in args.catalogue.split(","))}
                if args.catalogue
                else {}
            ),
        )
    print(report)
    if args.plot:
        try:
            report.plot(args.plot)
            _say(args, f"saved the residual figure to {args.plot}")
        except ImportError as exc:
            _say(args, f"note: no figure ({exc})")
    if args.out_model:
        report.final.save(args.out_model)
        _say(args, f"saved the final model to {args.out_model}")
    return 0


# ----------------------------------------------------------------------------- predict
def _predict(args) -> int:
    _check_out(args.out)
    est = _load(args.model)
    df = _read_csv(args.data)
    coords = list(est.coordinates_)
    inputs = _input_columns(df, coords, args)
    tau = None if inputs is None else _numeric(df, inputs, args.data)
    X = _state_frame(df, coords, args, args.data)
    with warnings.catch_warnings():
        # Columns are matched by name even for a model fit on arrays, so sklearn's
        # "fitted without feature names" warning says nothing useful here.
        warnings.filterwarnings("ignore", message="X has feature names")
        forces = est.predict(X)
        acc = est.predict_acceleration(X, tau)
        if tau is not None and est.case_ == "forces":
            quality = f"R^2 of forces: {est.score(X, tau):.4f}"
        elif tau is None:
            quality = f"R^2 of accelerations: {est.score(X):.4f}"
        else:
            quality = None
    out = df[[c for c in ("trajectory", "t") if c in df.columns]].copy()
    forces = forces.to_frame() if forces.ndim == 1 else forces
    out = out.join(forces).join(acc)
    _write_csv(out, args.out)
    lines = [
        f"wrote {args.out}: predicted forces {list(forces.columns)} (inverse "
        f"dynamics) and accelerations {list(acc.columns)} (forward dynamics"
        f"{', with the input columns ' + str(inputs) if inputs else ', unforced'})"
    ]
    if est.case_ != "forces":
        lines.append(
            "note: a model fit on passive data is known up to scale, so its "
            "forces are too (accelerations are not)"
        )
    if quality:
        lines.append(quality)
    _say(args, "\n".join(lines))
    return 0


# ----------------------------------------------------------------------------- parser
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
        help="sampling interval in seconds when the CSV has no 't' column",
    )


def _add_fit_options(p, *, required):
    """Options of a fit from a CSV (shared by ``fit`` and ``diagnose``)."""
    p.add_argument(
        "--coordinates",
        required=required,
        default=None,
        help="position columns, e.g. x,theta",
    )
    p.add_argument(
        "--angles",
        default="",
        help="coordinates that are angles (get sin/cos), e.g. theta, or 'all'",
    )
    p.add_argument(
        "--input",
        default=None,
        help="generalized-force columns, one per coordinate, e.g. tau_x,tau_theta",
    )
    p.add_argument(
        "--passive", action="store_true", help="ignore input columns (case III)"
    )
    p.add_argument(
        "--library",
        default="poly3",
        help="candidate terms: polyN (all monomials of degree 1..N over q, q_dot and "
        "sin/cos of the angles), separatedN (the paper's trigonometric x "
        "non-trigonometric products) or terms (only --terms). poly3 holds a "
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
        "--seed", type=int, default=0, help="random seed (case III search, case II)"
    )
    p.add_argument(
        "--precision", type=int, default=4, help="digits in the printed Lagrangian"
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
        "--delay",
        metavar="SECONDS|auto",
        default=None,
        help="input delay: the input recorded at t acts at t + SECONDS, so the inputs "
        "are shifted by it (linear interpolation per trajectory; the first SECONDS "
        "of each trajectory hold the first input). 'auto': estimate it by held-out "
        "fits over whole-sample shifts (lagsindy.delay.estimate_delay; slow: about "
        "40 fits)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``lagsindy`` command."""
    from . import __version__

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
    demo.add_argument(
        "--quiet",
        action="store_true",
        help="no progress output (stage lines, notes): results and errors only",
    )
    demo.set_defaults(func=_demo)

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
        help="with --model: initial state q...,q_dot... (repeat for more)",
    )
    sim.add_argument(
        "--seed",
        type=int,
        default=0,
        help="random seed of the initial states, inputs and noise",
    )
    sim.add_argument("--quiet", action="store_true", help="print nothing but errors")
    sim.set_defaults(func=_simulate)

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
    simm.add_argument("--quiet", action="store_true", help="print nothing but errors")
    simm.set_defaults(func=_simulate_model, system=None)

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
    _add_derivative_options(fit)
    fit.add_argument(
        "--quiet",
        action="store_true",
        help="print only the Lagrangian (and errors, and warnings that the result "
        "may be wrong)",
    )
    fit.set_defaults(func=_fit)

    diag = sub.add_parser(
        "diagnose",
        help="find what a fitted model leaves unexplained (friction, damping, ...) "
        "and add it",
        description="Residual diagnosis: fit a Lagrangian (or load --model), test "
        "candidate missing effects (viscous, joint and quadratic damping, Coulomb "
        "friction, offsets, input gain errors, missing conservative terms) jointly with "
        "the Lagrangian's terms, keep those that improve the prediction of held-out "
        "trajectories, and report the errors before and after. Prints the report; --plot saves the residual figure.",
    )
    diag.add_argument("data", help="CSV file")
    diag.add_argument("--model", default=None, help="a saved model (JSON) to diagnose")
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
        help="comma-separated candidate kinds (default: all): viscous, relative, "
        "drag, coulomb, bias, gain, conservative, delay",
    )
    diag.add_argument(
        "--bootstrap",
        type=int,
        default=None,
        metavar="N",
        help="bootstrap the final model with N resamples of whole trajectories (time "
        "blocks with fewer than 10) and print each term's and effect's interval "
        "(resamples seeded by --seed)",
    )
    diag.add_argument("--plot", default=None, help="save the residual figure (PNG)")
    diag.add_argument("--out-model", default=None, help="save the final model (JSON)")
    _add_derivative_options(diag)
    diag.add_argument(
        "--quiet",
        action="store_true",
        help="print only the report (and errors, and warnings that the result may "
        "be wrong)",
    )
    diag.set_defaults(func=_diagnose)

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
        "--input", default=None, help="generalized-force columns (default tau_<q>)"
    )
    pred.add_argument("--passive", action="store_true", help="ignore input columns")
    pred.add_argument("--out", required=True, help="output CSV")
    _add_derivative_options(pred)
    pred.add_argument("--quiet", action="store_true", help="print nothing but errors")
    pred.set_defaults(func=_predict)
    return parser


def _one_line(exc) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 600 else text[:597] + "..."


def main(argv=None) -> int:
    """Run the ``lagsindy`` command; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, usage errors
        return int(exc.code or 0)
    prog = f"lagsindy {args.command}"

    quiet = getattr(args, "quiet", False)

    def show(message, category, filename, lineno, file=None, line=None):
        text = _one_line(message)
        if quiet and any(s in text for s in _INFO_WARNINGS):
            return
        print(f"{prog}: warning: {text}", file=sys.stderr)

    try:
        with warnings.catch_warnings():
            warnings.showwarning = show
            return args.func(args)
    except (CLIError, ValueError, OSError) as exc:
        if args.debug:
            raise
        if isinstance(exc, FileNotFoundError) and exc.filename:
            message = f"file not found: {exc.filename}"
        else:
            message = _one_line(exc)
        print(f"{prog}: error: {message}", file=sys.stderr)
        return 2
    except RuntimeError as exc:  # an integration that failed
        if args.debug:
            raise
        print(f"{prog}: error: {_one_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
