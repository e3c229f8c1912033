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

from ._checks import CLIError, check_csv_file, missing_column, state_names
from ._checks import check_out as _check_out
from ._checks import derivatives_estimated as _columns_say_estimated
from ._checks import input_columns as _header_inputs

__all__ = ["CLIError"]


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

    When derivatives are estimated, ``angles`` are unwrapped per trajectory (as
    ``Derivatives(angles=...)`` does in the API) and trajectories are cut at gaps in
    ``t`` (one warning says where); the labels returned are then the segments.
    ``ordered``: refuse a ``t`` that goes back within a trajectory also when the
    derivatives are given (fit and diagnose; ``predict`` takes rows one by one).
    """
    import pandas as pd

    names = state_names(coords)
    q = _numeric(df, coords, source)
    method = getattr(args, "derivatives", None)
    groups = df["trajectory"].to_numpy() if "trajectory" in df.columns else None
    if not _derivatives_estimated(df, coords, args):
        if ordered and "t" in df.columns:  # the weak form takes the rows in order
            _check_increasing(_numeric(df, ["t"], source)[:, 0], groups, source)
        X = pd.DataFrame(_numeric(df, names, source), columns=names, index=df.index)
        return X, groups
    from ..differentiation import derivatives

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
    _check_increasing(t, groups, source)
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


def _check_increasing(t, groups, source):
    for idx in _group_rows(groups, len(t)):
        if np.any(np.diff(t[idx]) <= 0):
            raise CLIError(
                f"'t' must increase within each trajectory in {source} (sort the rows, "
                "and give separate trajectories a 'trajectory' column)"
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
