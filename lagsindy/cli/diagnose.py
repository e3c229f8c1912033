"""``lagsindy diagnose``: what a fitted model leaves unexplained, found and added.

With ``--model``, the saved model is diagnosed on the CSV; otherwise the CSV is
fitted first with the options of ``fit`` (:func:`.fit._fit_csv`). The options, the
model file's coordinates and the CSV's header are checked before the fitting code
loads.
"""

from __future__ import annotations

import time
import warnings

from . import _checks
from ._checks import CLIError
from ._io import (
    _check_out,
    _input_columns,
    _load,
    _numeric,
    _on_even_clock,
    _read_csv,
    _say,
    _state_and_groups,
)
from .fit import _apply_delay, _fit_csv, _with_dt


def _diagnose(args) -> int:
    for out in (args.plot, args.out_model):
        if out:
            _check_out(out)
    _checks.diagnose_numbers(args)
    if args.model:
        est, X, tau, groups = _saved_model_and_data(args)
    else:
        if not args.coordinates:
            raise CLIError("give --model model.json, or --coordinates to fit one first")
        est, X, tau, _, _ = _fit_csv(args)
        groups = args._groups
        _say(args, f"fitted: {est.equation(args.precision).splitlines()[0]}")
    from ..diagnostics import diagnose

    catalogue = (
        {"catalogue": tuple(k.strip() for k in args.catalogue.split(","))}
        if args.catalogue
        else {}
    )
    _say(
        args,
        "diagnosing: testing candidate missing effects ("
        + (", ".join(catalogue["catalogue"]) if catalogue else "every kind")
        + f") on {args.splits} held-out folds, refitting with each kept one ...",
    )
    start = time.perf_counter()
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
            **catalogue,
        )
    _say(args, f"diagnosis took {time.perf_counter() - start:.1f} s\n")
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


def _saved_model_and_data(args):
    """``--model``: the loaded model, X, tau and the trajectories of the CSV."""
    _checks.fit_numbers(args)
    coords, case = _checks.peek_model(args.model)
    columns = _checks.csv_header(args.data)
    if coords is not None and columns is not None:
        inputs = _checks.data_columns(columns, coords, args, args.data)
        _checks.check_model_data(case, inputs)
    if getattr(args, "delay", None) == "auto":
        raise CLIError(
            "--delay auto estimates the delay by refitting; with --model give the "
            "delay in seconds (e.g. the one `lagsindy fit --delay auto` printed)"
        )
    _say(
        args,
        f"reading {args.model} and {args.data}, loading the fitting code (torch, "
        "sympy, scikit-learn) ...",
    )
    est = _load(args.model)
    df = _read_csv(args.data)
    coords = list(est.coordinates_)
    angles = _model_angles(est, coords)
    inputs = _input_columns(df, coords, args)
    tau = None if inputs is None else _numeric(df, inputs, args.data)
    _checks.check_model_data(est.case_, inputs)
    X, groups = _state_and_groups(df, coords, args, args.data, angles)
    tau = _apply_delay(args, df, X, tau, groups, None)
    X, tau, groups, dt = _on_even_clock(args, X, tau, groups)
    _with_dt(est, dt)
    return est, X, tau, groups


def _model_angles(est, coords):
    """The coordinates a model's library treats as angles (unwrapped with them)."""
    angles = getattr(est.library, "angles", None)
    if angles == "all":
        return list(coords)
    if isinstance(angles, str):
        return [angles]
    return [a for a in (angles or []) if a in coords]
