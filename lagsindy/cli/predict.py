"""``lagsindy predict``: forces and accelerations of a CSV's rows by a saved model.

The output path, the model file's coordinates and the CSV's header are checked
before the fitting code loads (:mod:`._checks`).
"""

from __future__ import annotations

import warnings

import numpy as np

from . import _checks
from ._io import (
    _check_out,
    _input_columns,
    _load,
    _numeric,
    _read_csv,
    _say,
    _state_frame,
    _write_csv,
)


def _predict(args) -> int:
    _check_out(args.out)
    _checks.clock_options(args)
    coords, _ = _checks.peek_model(args.model)
    columns = _checks.csv_header(args.data)
    if coords is not None and columns is not None:
        _checks.data_columns(columns, coords, args, args.data)
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
        # scored without the rows near a segment's end (estimated derivatives:
        # one-sided there, several times less accurate), as fit and diagnose fit
        edge = getattr(args, "_edge", None)
        rows = (
            np.arange(len(X)) if edge is None or edge.all() else np.flatnonzero(~edge)
        )
        left = "" if rows.size == len(X) else (
            f" (the {len(X) - rows.size} rows within 3 samples of a segment's end "
            "left out)"
        )  # fmt: skip
        if tau is not None and est.case_ == "forces":
            quality = f"R^2 of forces: {est.score(X.iloc[rows], tau[rows]):.4f}{left}"
        elif tau is None:
            quality = f"R^2 of accelerations: {est.score(X.iloc[rows]):.4f}{left}"
        else:
            quality = None
    time = _checks.time_column(args)
    out = df[[c for c in ("trajectory", time) if c in df.columns]].copy()
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
