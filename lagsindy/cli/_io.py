"""Data in and out for the ``lagsindy`` command: CSV reading, states, model files.

Only the standard library and numpy are imported here at import time; pandas and the
estimator's modules are imported inside the functions that need them. The checks
that need no data (options, file names, the CSV's header) are in :mod:`._checks`.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from ._checks import CLIError, check_csv_file, missing_column, state_names, time_column
from ._checks import check_out as _check_out
from ._checks import derivatives_estimated as _columns_say_estimated
from ._checks import input_columns as _header_inputs

__all__ = ["CLIError"]

# Fewest samples per segment each derivative method takes (derivatives()).
_FEWEST = {None: 7, "pspline": 7, "spline": 5}


def _say(args, *parts):
    """Print progress output unless ``--quiet``."""
    if not getattr(args, "quiet", False):
        print(*parts, flush=True)


# ----------------------------------------------------------------------------- data in
def _read_csv(path):
    import pandas as pd

    p = check_csv_file(path)
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


def _line(i):
    """The file line of data row ``i`` (0-based; the header is line 1)."""
    return f"line {i + 2}"


def _numeric(df, columns, source):
    """The named columns as a float array; names the column and line of bad values.

    ``"-"`` (an undriven coordinate's input) is a column of zeros."""
    missing = [c for c in columns if c != "-" and c not in df.columns]
    if missing:
        raise missing_column(source, missing[0], df.columns)
    out = np.empty((len(df), len(columns)))
    for j, c in enumerate(columns):
        if c == "-":
            out[:, j] = 0.0
            continue
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
            fields = _short_row(df, row)
            short = (
                f" ({_line(row)} holds {fields} of the header's {df.shape[1]} fields: "
                "a row cut short?)"
                if fields is not None
                else ""
            )
            raise CLIError(
                f"column {c!r} of {source} has {int((~finite).sum())} NaN or infinite "
                f"value(s), the first on {_line(row)}{short}; drop or fill those rows"
            )
    return out


def _short_row(df, row):
    """The fields of data row ``row`` when it ends early (every column from some
    point on is empty while the header has more), else None."""
    empty = df.iloc[row].isna().to_numpy()
    if not empty[-1]:
        return None
    fields = int(np.flatnonzero(~empty)[-1]) + 1 if (~empty).any() else 0
    return fields if fields < df.shape[1] else None


def _is_float(v):
    try:
        float(v)
    except (TypeError, ValueError):
        return False
    return True


def _state_frame(df, coords, args, source):
    """X as a DataFrame ``[q, q_dot, q_ddot]``; derivatives estimated if absent."""
    return _state_and_groups(df, coords, args, source, ordered=False)[0]


def _derivatives_estimated(df, coords, args):
    """Whether q_dot and q_ddot are estimated from q (not read from the CSV)."""
    return _columns_say_estimated(df.columns, coords, args)


def _state_and_groups(df, coords, args, source, angles=(), ordered=True):
    """X ``[q, q_dot, q_ddot]`` and the trajectory labels to fit with.

    When derivatives are estimated, the clock is cleaned (as ``derivatives()`` does:
    stale and duplicate rows, a jittery clock over a regular cycle, gaps of
    ``--gap-factor`` steps), ``angles`` are unwrapped per trajectory (as
    ``Derivatives(angles=...)`` does in the API) and trajectories are cut at gaps
    (one warning says where); the labels returned are then the segments. A
    recorder's velocity columns ``<q>_dot`` (without ``<q>_ddot``) are used: to find
    the cycle of a jittery clock, and as the velocities. ``args._t`` is set to the
    time of each row (the cleaned clock; None without a time column).
    ``ordered``: refuse a time that goes back within a trajectory also when the
    derivatives are given (fit and diagnose; ``predict`` takes rows one by one).
    """
    import pandas as pd

    names = state_names(coords)
    time = time_column(args)
    q = _numeric(df, coords, source)
    method = getattr(args, "derivatives", None)
    groups = df["trajectory"].to_numpy() if "trajectory" in df.columns else None
    args._t = args._edge = None
    if not _derivatives_estimated(df, coords, args):
        if ordered and time in df.columns:  # the weak form takes the rows in order
            args._t = _numeric(df, [time], source)[:, 0]
            _check_increasing(args._t, groups, source, time)
        X = pd.DataFrame(_numeric(df, names, source), columns=names, index=df.index)
        return X, groups
    from ..differentiation import clean_clock, derivatives

    if time in df.columns:
        t = _numeric(df, [time], source)[:, 0]
    elif getattr(args, "dt", None):
        t = np.arange(len(df)) * float(args.dt)
    else:
        raise CLIError(
            f"{source} has positions only and no {time!r} column: add a time column "
            f"{time!r}, name it with --time COLUMN, or pass --dt SECONDS (the "
            "sampling interval)"
        )
    for idx in _group_rows(groups, len(df)):
        if idx.size < 5:
            raise CLIError(
                f"a trajectory in {source} has {idx.size} rows; derivative estimation "
                "needs at least 5 samples per trajectory"
            )
    _check_increasing(t, groups, source, time, slack=0.5)
    velocity_names = names[len(coords) : 2 * len(coords)]
    velocities = None
    if method is None and all(c in df.columns for c in velocity_names):
        velocities = _numeric(df, velocity_names, source)
    kwargs = {"groups": groups, "return_groups": True, "return_clock": True}
    if method is not None:
        kwargs["method"] = method
    mask = [c in angles for c in coords]
    if any(mask):
        kwargs["angles"] = mask
    gap_factor = float(getattr(args, "gap_factor", 5.0))
    what = "velocities and accelerations"
    _say(
        args,
        f"estimating {'accelerations' if velocities is not None else what} of {coords}"
        f" ({method or 'default method'}"
        + (f"; angles {list(angles)} unwrapped" if any(mask) else "")
        + (
            f"; the recorded velocities {velocity_names} used as the velocities and "
            "to check the clock"
            if velocities is not None
            else ""
        )
        + ") ...",
    )  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            clock = clean_clock(
                t, q, groups, gap_factor=gap_factor, angles=mask,
                velocities=velocities, min_samples=_FEWEST.get(method, 3),
            )  # fmt: skip
        except ValueError as exc:
            raise CLIError(f"{source}: {exc}") from None
        clock.warn()
        X, segments, clock = derivatives(q, t, clean=clock, **kwargs)
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
    if velocities is not None:
        X[:, len(coords) : 2 * len(coords)] = velocities
    args._t, args._edge = clock.t, clock.edge
    return pd.DataFrame(X, columns=names, index=df.index), groups


def _on_even_clock(args, X, tau, groups):
    """The rows put on an even clock when their times are uneven (as
    ``LagrangianSINDy.fit(t=)`` does); returns ``(X, tau, groups, dt)``, ``dt``
    None when nothing changed. One progress line says what was done."""
    t = getattr(args, "_t", None)
    if t is None:
        return X, tau, groups, None
    import pandas as pd

    from ..differentiation import edge_rows, to_even_clock

    # rows near a segment's end left out, as LagrangianSINDy.fit(t=) does
    factor = float(getattr(args, "gap_factor", 5.0))
    edge = getattr(args, "_edge", None)
    edge = edge_rows(t, groups, gap_factor=factor) if edge is None else edge
    if edge.any() and not edge.all():
        _say(
            args,
            f"{int(edge.sum())} of {edge.size} rows lie within 3 samples of a "
            "segment's end or in a segment too short to differentiate (one-sided "
            "derivative estimates): left out of the fit",
        )
        keep = np.flatnonzero(~edge)
        X = X.iloc[keep].reset_index(drop=True)
        tau = None if tau is None else tau[keep]
        groups = None if groups is None else np.asarray(groups)[keep]
        t = t[keep]
    if getattr(args, "formulation", "auto") == "strong":
        return X, tau, groups, None
    even = to_even_clock(
        np.asarray(X, dtype=float), t, groups, tau,
        gap_factor=float(getattr(args, "gap_factor", 5.0)),
    )  # fmt: skip
    if not even.changed:
        return X, tau, groups, None
    _say(args, even.report)
    X = pd.DataFrame(even.X, columns=list(X.columns))
    return X, even.tau, even.groups, even.dt


def _check_increasing(t, groups, source, name="t", slack=0.0):
    """Refuse a time that goes back within a trajectory (``slack``: by more than
    this many median steps; smaller steps back are a jittery clock, which the clock
    cleaning rebuilds)."""
    for idx in _group_rows(groups, len(t)):
        steps = np.diff(t[idx])
        limit = 0.0
        if slack and steps.size and np.any(steps > 0):
            limit = -slack * float(np.median(steps[steps > 0]))
        if np.any(steps <= limit if not slack else steps < limit):
            raise CLIError(
                f"{name!r} must increase within each trajectory in {source} (sort the "
                "rows, and give separate trajectories a 'trajectory' column)"
            )


def _group_rows(groups, n):
    if groups is None:
        return [np.arange(n)]
    _, first = np.unique(groups, return_index=True)
    return [np.flatnonzero(groups == groups[s]) for s in np.sort(first)]


def _input_columns(df, coords, args):
    """Names of the generalized-force columns, or None for passive data."""
    return _header_inputs(df.columns, coords, args)


def _write_csv(df, out):
    df.to_csv(_check_out(out), index=False, float_format="%.12g")


def _load(path):
    from ..io import load_model

    if not Path(path).is_file():
        raise CLIError(f"model file not found: {path}")
    return load_model(path)
