"""``lagsindy fit``: a Lagrangian from a CSV of trajectories, saved as JSON.

The order of the work is the order in which things can go wrong cheaply: options,
file names and the CSV's header first (:mod:`._checks`, standard library only), then
the data's values (pandas), then the library (sympy), the derivatives and the fit
(torch). Each step that can take seconds prints a line first, unless ``--quiet``.
:func:`_fit_csv` is shared with ``diagnose``; the held-out score is in
:mod:`.scoring`.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from . import _checks
from ._checks import CLIError, split
from ._io import (
    _check_out,
    _derivatives_estimated,
    _input_columns,
    _numeric,
    _on_even_clock,
    _read_csv,
    _say,
    _state_and_groups,
)
from .scoring import held_out_score, score


def _fit(args) -> int:
    _check_out(args.out)
    est, X, tau, inputs, elapsed = _fit_csv(args)
    if args.refine is not None:
        from ..refine import refine

        _say(args, f"refining by rollouts of {args.refine} samples ...")
        sparse = est
        est = refine(est, X, tau, groups=args._groups, horizon=args.refine)
        _say(args, str(est.refinement_))
    est.save(args.out)
    print(est.equation(args.precision))
    if args.quiet:  # nothing more is printed, so the held-out refit is skipped
        return 0
    kept = int(est.support_.sum())
    form = f"{est.formulation_} form"
    if getattr(est, "window_", None) is not None:
        form += f", test window {est.window_} samples"
    _say(
        args,
        f"{kept} of {len(est.coef_)} terms kept ({form}); fit took {elapsed:.1f} s; "
        f"saved the model to {args.out}",
    )
    fitted, target = score(est, X, tau, args._groups)
    if args.held_out == 0:
        _say(args, f"R^2 of {target} on the fitted data {fitted:.4f} (--held-out 0)")
        return 0
    _say(args, "scoring on held-out data (a second fit on the rest) ...")
    try:
        held, held_target, where, seconds = held_out_score(
            sparse if args.refine is not None else est,
            X,
            tau,
            args._groups,
            args.held_out,
        )
    except (ValueError, RuntimeError, FloatingPointError, np.linalg.LinAlgError) as e:
        _say(
            args,
            f"R^2 of {target} on the fitted data {fitted:.4f}; no held-out score: "
            f"the refit on the rest failed ({' '.join(str(e).split())[:300]})",
        )
        return 0
    _say(
        args,
        f"R^2 of {held_target} on held-out data {held:.4f} ({where}, scored by a "
        f"refit on the rest, {seconds:.1f} s); "
        + (
            f"on the fitted data {fitted:.4f}"
            if held_target == target
            else f"of {target} on the fitted data {fitted:.4f}"
        ),
    )
    return 0


# ----------------------------------------------------------------------------- checks
def check_fit(args):
    """Every check of a fit from a CSV that needs neither the data's values nor a
    heavy import; returns ``(coordinates, angles, input columns or None)``.

    The input columns are None also when the header could not be read cheaply
    (:func:`._checks.csv_header`); the data's reader then checks them.
    """
    coords = _checks.coordinates(args.coordinates)
    angles = _checks.angles(args.angles, coords)
    _checks.fit_numbers(args)
    kind, _ = _checks.library_spec(args.library)
    if kind == "terms" and not split(args.terms):
        raise CLIError("--library terms needs --terms 'a,b,...'")
    columns = _checks.csv_header(args.data)
    inputs = _checks.data_columns(columns, coords, args, args.data)
    if columns is not None:
        _check_inputs_fit(args, inputs)
        if (
            getattr(args, "delay", None) is not None
            and _checks.time_column(args) not in columns
            and not getattr(args, "dt", None)
        ):
            raise CLIError(
                "--delay needs a time column ('t' or --time COLUMN) or --dt SECONDS"
            )
    return coords, angles, inputs


def _check_inputs_fit(args, inputs):
    """Options that contradict the presence or absence of input columns."""
    if inputs is not None and args.fixed_term is not None:
        raise CLIError(
            "--fixed-term is for passive data (case III), but the input columns "
            f"{inputs} "
            "were found; pass --passive to ignore them, or drop --fixed-term"
        )
    if inputs is None and getattr(args, "delay", None) is not None:
        raise CLIError(
            "--delay shifts the input columns, but the data have none (passive data); "
            "drop --delay or give the input with --input"
        )


def _library(args, coords, angles):
    """The candidate library ``--library`` (and ``--terms``) name, unbuilt."""
    from ..library import CandidateLibrary

    kind, degree = _checks.library_spec(args.library)
    extra = split(args.terms)
    if kind == "terms":
        if not extra:
            raise CLIError("--library terms needs --terms 'a,b,...'")
        return CandidateLibrary.from_terms(coords, extra)
    if kind == "chain":
        chain = CandidateLibrary.chain(coords, angles=list(angles or []))
        if extra:
            chain = chain + CandidateLibrary.from_terms(coords, extra)
        return chain
    builder = (
        CandidateLibrary.polynomial if kind == "poly" else CandidateLibrary.separated
    )
    return builder(
        coords,
        angles=angles or None,
        degree=degree,
        raw_angles=args.raw_angles,
        terms=extra or None,
    )


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


def _warn_strong_form(est, args):
    """One warning when the strong form was fitted to estimated derivatives."""
    if est.formulation_ != "strong":
        return
    if getattr(args, "formulation", "auto") == "auto" and est.case_ != "acceleration":
        return  # the estimator has warned why the weak form could not run
    advice = (
        "case II (--case acceleration) has no weak form; --case fixed (case III) can "
        "use it"
        if est.case_ == "acceleration"
        else "prefer --formulation weak or auto"
    )
    warnings.warn(
        "the strong form was fitted to velocities and accelerations estimated from "
        "the positions: noise on these derivatives biases the coefficients "
        f"(typically toward zero); {advice}",
        UserWarning,
        stacklevel=2,
    )


# ----------------------------------------------------------------------------- the fit
def _fit_csv(args):
    """Read the CSV named in ``args`` and fit a model as the options say.

    Returns ``(estimator, X, tau, input columns, seconds of the fit)`` and sets
    ``args._groups`` (the trajectories or segments fitted).
    """
    coords, angles, inputs = check_fit(args)
    _say(
        args,
        f"reading {args.data} and loading the fitting code (torch, sympy, "
        "scikit-learn) ...",
    )
    df = _read_csv(args.data)
    inputs = _input_columns(df, coords, args)
    _check_inputs_fit(args, inputs)
    tau = None if inputs is None else _numeric(df, inputs, args.data)
    _numeric(df, coords, args.data)

    from .._expr import check_coordinate_names
    from ..estimator import LagrangianSINDy
    from ..formulation import make_formulation
    from ..solvers import StagedFISTA

    check_coordinate_names(coords)  # the names the library's parser reserves
    library = _library(args, coords, angles)
    _say(args, f"building the candidate library {args.library} over {coords} ...")
    start = time.perf_counter()
    n_terms = len(library)  # generates, parses and reduces the terms
    n_candidates = len(library.candidates_)
    _say(
        args,
        f"library {args.library}: {n_terms} terms"
        + (
            f" ({n_candidates - n_terms} of {n_candidates} candidates removed as "
            "trivial or dependent)"
            if n_candidates > n_terms
            else ""
        )
        + f", {time.perf_counter() - start:.1f} s",
    )
    _warn_missing_coupling(library, coords, angles, args)
    X, groups = _state_and_groups(df, coords, args, args.data, angles)
    est = LagrangianSINDy(
        library,
        lam=args.lam,
        solver=StagedFISTA(threshold=args.threshold),
        fixed_term=args.fixed_term,
        unpenalized=split(args.unpenalized) or None,
        case=args.case,
        formulation=make_formulation(
            getattr(args, "formulation", "auto"), window=getattr(args, "window", "auto")
        ),
        random_state=args.seed,
        verbose=0 if args.quiet else 1,
    )
    tau = _apply_delay(args, df, X, tau, groups, est)
    X, tau, groups, dt = _on_even_clock(args, X, tau, groups)
    _with_dt(est, dt)
    n_groups = 1 if groups is None else len(np.unique(groups))
    _say(
        args,
        f"fitting {len(X)} samples ({n_groups} trajectories) of {coords}: "
        + (f"forces from {inputs}" if inputs else "passive (no input columns)")
        + f", library {args.library} ({n_terms} terms) ...",
    )
    start = time.perf_counter()
    if getattr(args, "conservative", False):
        from ..joint import conservative_fits

        with conservative_fits():  # no joint refit: the probes' warning instead
            est.fit(X, tau, groups=groups)
    else:
        est.fit(X, tau, groups=groups)
    elapsed = time.perf_counter() - start
    if _derivatives_estimated(df, coords, args):
        _warn_strong_form(est, args)
    args._groups = groups  # the segments, for the held-out score and diagnose
    return est, X, tau, inputs, elapsed


def _apply_delay(args, df, X, tau, groups, est):
    """Shift the inputs by ``--delay`` (seconds, or ``auto``: estimated by ``est``)."""
    value = getattr(args, "delay", None)
    if value is None:
        return tau
    if tau is None:
        raise CLIError(
            "--delay shifts the input columns, but the data have none (passive data); "
            "drop --delay or give the input with --input"
        )
    from ..delay import estimate_delay, shift_input, worth_trying

    time = _checks.time_column(args)
    if getattr(args, "_t", None) is not None:
        t = args._t  # the cleaned clock
    elif time in df.columns:
        t = _numeric(df, [time], args.data)[:, 0]
    elif getattr(args, "dt", None):
        t = np.arange(len(df)) * float(args.dt)
    else:
        raise CLIError(
            "--delay needs a time column ('t' or --time COLUMN) or --dt SECONDS"
        )
    if value == "auto":
        if est is None:
            raise CLIError(
                "--delay auto estimates the delay by refitting; with --model give the "
                "delay in seconds (e.g. the one `lagsindy fit --delay auto` printed)"
            )
        _say(args, "estimating the input delay (held-out fits over sample shifts) ...")
        import warnings

        from sklearn.base import clone

        # the configuration the fit will use: with the dissipation a joint fit adds
        # (lagsindy.joint), which the delay search's refits (without probes) keep
        start_fit = clone(est).set_params(verbose=0)
        if not getattr(args, "conservative", False):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                start_fit.fit(X, tau, groups=groups)
        result = estimate_delay(start_fit, X, tau, t, groups=groups)
        steps = np.diff(t)
        dt = float(np.median(steps[steps > 0])) if np.any(steps > 0) else 0.0
        if not worth_trying(result, dt):
            # an estimate within twice its spread (or under a tenth of a sample)
            # is not told from no delay: reported, not applied
            warnings.warn(
                f"--delay auto: {result}, which is not significant (it must exceed "
                "twice its standard error and a tenth of the sampling interval "
                f"{1e3 * dt:.3g} ms): the inputs are NOT shifted; give --delay "
                "SECONDS to apply a delay anyway",
                UserWarning,
                stacklevel=2,
            )
            return tau
        _say(args, f"{result}; the inputs are shifted by it")
        delay = result.delay
    else:
        delay = float(value)
    return shift_input(tau, t, delay, groups)


def _with_dt(est, dt):
    """Give ``est``'s formulation the even clock's step ``dt`` (when it takes one)."""
    if dt is None:
        return
    from sklearn.base import clone

    from ..formulation.forms import make_formulation

    form = est.formulation
    form = make_formulation(form) if isinstance(form, str) else clone(form)
    if "dt" in form.get_params():
        est.set_params(formulation=form.set_params(dt=dt))
