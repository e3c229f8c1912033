"""Layout checks for X = [q, qdot, qddot] and tau, with messages that say what to do.

Every check raises a ``ValueError`` that names what is wrong (the column, the row, the
shape received) and what to do about it, so bad input never surfaces as a numpy,
pandas or torch traceback.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import scipy.sparse as sps

from ._expr import ACCELERATION_SUFFIX, VELOCITY_SUFFIX, state_names

_LAYOUT_HINT = "[q..., q_dot..., q_ddot...]"


def is_frame(X) -> bool:
    return isinstance(X, pd.DataFrame)


def coordinates_from_columns(columns) -> list[str]:
    """Infer coordinate names from DataFrame columns ``[q..., q_dot..., q_ddot...]``."""
    columns = [str(c) for c in columns]
    qs = [
        c
        for c in columns
        if not c.endswith(VELOCITY_SUFFIX) and not c.endswith(ACCELERATION_SUFFIX)
    ]
    missing = [c for c in state_names(qs) if c not in columns]
    if not qs or missing:
        gap = f"; missing {missing}" if missing else ""
        raise ValueError(
            "could not read coordinates from the DataFrame columns "
            f"{columns}: expected columns named like 'theta', 'theta_dot', "
            f"'theta_ddot' for each coordinate{gap}. "
            "Rename the columns, or pass a library with coordinates=[...]."
        )
    return qs


def _check_unique_columns(frame: pd.DataFrame, what: str):
    names = [str(c) for c in frame.columns]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(
            f"the {what} DataFrame has repeated column names {repeated}; each column "
            "must appear once. Drop or rename the duplicates."
        )


def select_state_columns(X: pd.DataFrame, coordinates) -> pd.DataFrame:
    """Columns of ``X`` in the order ``[q..., q_dot..., q_ddot...]``."""
    wanted = state_names(coordinates)
    _check_unique_columns(X, "X")
    present = {str(c): c for c in X.columns}
    missing = [w for w in wanted if w not in present]
    if missing:
        raise ValueError(
            f"the DataFrame is missing the columns {missing} (it has {list(present)}); "
            f"for the library's coordinates {list(coordinates)} X needs {wanted}: "
            "positions, velocities ('<name>_dot') and accelerations ('<name>_ddot'). "
            "Rename the columns to match the library's coordinates, or estimate "
            "derivatives with lagsindy.differentiation first."
        )
    return X[[present[w] for w in wanted]]


def select_tau_columns(tau: pd.DataFrame, coordinates) -> pd.DataFrame:
    """Columns of a tau DataFrame in coordinate order.

    Columns are matched by name, ``tau_<coordinate>`` (as written by
    ``Dataset.to_frame``) or ``<coordinate>``. Unnamed (default integer) columns and
    a single column for a single coordinate are taken in order; any other naming is
    ambiguous and raises.
    """
    _check_unique_columns(tau, "tau")
    coordinates = list(coordinates)
    present = {str(c): c for c in tau.columns}
    for prefix in ("tau_", ""):
        wanted = [prefix + c for c in coordinates]
        if all(w in present for w in wanted):
            return tau[[present[w] for w in wanted]]
    positional = isinstance(tau.columns, pd.RangeIndex) or (
        len(coordinates) == 1 and tau.shape[1] == 1
    )
    if positional:
        return tau
    want = [f"tau_{c}" for c in coordinates]
    raise ValueError(
        f"cannot match the tau DataFrame's columns {list(present)} to the coordinates "
        f"{coordinates}: name them {want} (or {coordinates}), or pass a numpy array "
        "with one column per coordinate in that order"
    )


def _first_unconvertible(values: np.ndarray):
    """Index and value of the first entry that does not convert to float."""
    for idx, v in np.ndenumerate(values):
        try:
            np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            return idx, v
    return None, None


def _conversion_error(what: str, values: np.ndarray, names, exc) -> ValueError:
    idx, v = _first_unconvertible(values)
    if idx is None:
        where = ""
    elif len(idx) == 2:
        col = (
            names[idx[1]]
            if names is not None and idx[1] < len(names)
            else f"column {idx[1]}"
        )
        where = f"; the first is {v!r} at row {idx[0]}, column {col!r}"
    else:
        where = f"; the first is {v!r} at row {idx[0]}"
    return ValueError(
        f"{what} could not be converted to floating point numbers ({exc}){where}. "
        "Pass numeric data: convert or drop non-numeric columns and entries."
    )


def as_float_array(X, what: str, *, ndims=(2,), names=None) -> np.ndarray:
    """Convert array-like input to float64, with clear errors for what cannot be.

    Parameters
    ----------
    X : array-like
    what : str
        Name used in messages (``"X"``, ``"tau"``).
    ndims : tuple of int, default=(2,)
        Accepted numbers of dimensions.
    names : list of str, optional
        Column names for messages.
    """
    if X is None:
        raise ValueError(f"{what} is None; pass an array of numbers")
    if sps.issparse(X):
        raise ValueError(
            f"{what} is a sparse matrix, but dense data is required: "
            f"use {what}.toarray()"
        )
    if isinstance(X, (str, bytes, dict, set)):
        raise ValueError(
            f"{what} must be an array of numbers, got a {type(X).__name__}"
        )
    try:
        arr = np.asarray(X)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"{what} could not be read as an array ({exc}); pass a numeric array whose "
            "rows all have the same length"
        ) from None
    if arr.ndim not in ndims:
        expected = " or ".join(f"{n}-D" for n in ndims)
        shape_hint = (
            f". Reshape your data: for a single sample use {what}.reshape(1, -1)"
            if arr.ndim == 1 and 2 in ndims
            else ""
        )
        got = (
            "a scalar"
            if arr.ndim == 0
            else f"a {arr.ndim}-D array of shape {arr.shape}"
        )
        raise ValueError(
            f"{what} must be a {expected} array"
            f"{' ' + _LAYOUT_HINT if what == 'X' else ''}, got {got}{shape_hint}"
        )
    if np.iscomplexobj(arr):
        raise ValueError(
            f"Complex data not supported: {what} has complex values; pass real numbers"
        )
    if arr.dtype.kind in "fiub":
        return arr.astype(np.float64, copy=False)
    if arr.dtype.kind in "Mm":
        raise ValueError(
            f"{what} holds dates or time spans (dtype {arr.dtype}); pass numbers "
            "(convert times to seconds)"
        )
    try:
        out = arr.astype(np.float64)
    except (TypeError, ValueError) as exc:
        raise _conversion_error(what, arr, names, exc) from None
    if np.iscomplexobj(out):  # pragma: no cover - astype(float) never returns complex
        raise ValueError(f"Complex data not supported: {what} has complex values")
    return out


def frame_as_float(frame: pd.DataFrame, what: str) -> np.ndarray:
    """Convert a DataFrame to float64 column by column, naming a column that fails."""
    columns = []
    for name in frame.columns:
        col = frame[name]
        if isinstance(col, pd.DataFrame):  # repeated names; select_* rejects them first
            raise ValueError(
                f"the {what} DataFrame has the column {name!r} more than once"
            )
        kind = getattr(col.dtype, "kind", "O")
        if kind in "Mm":
            raise ValueError(
                f"{what} column {str(name)!r} holds dates or time spans (dtype "
                f"{col.dtype}); pass numbers (convert times to seconds)"
            )
        if kind == "c":
            raise ValueError(
                f"Complex data not supported: {what} column {str(name)!r} is complex"
            )
        try:
            values = col.to_numpy(dtype=np.float64, na_value=np.nan)
        except (TypeError, ValueError) as exc:
            raw = np.asarray(col.to_numpy(dtype=object))
            idx, v = _first_unconvertible(raw)
            where = "" if idx is None else f"; the first is {v!r} at row {idx[0]}"
            raise ValueError(
                f"{what} column {str(name)!r} could not be converted to floating point "
                f"numbers ({exc}){where}. Pass numeric data: convert or drop "
                "non-numeric columns and entries."
            ) from None
        columns.append(values)
    if not columns:
        return np.empty((len(frame), 0))
    return np.stack(columns, axis=1)


def check_finite(array: np.ndarray, names, what: str):
    """Raise a ValueError naming the first row and column that is NaN or infinite."""
    bad = ~np.isfinite(array)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        kind = "NaN" if np.isnan(array[row, col]) else "infinite"
        count = int(bad.sum())
        name = names[col] if names is not None and col < len(names) else f"column {col}"
        raise ValueError(
            f"{what} contains {count} NaN or infinite value(s); the first is {kind} at "
            f"row {row}, column {name!r}. Drop or interpolate those rows."
        )


def check_motion(X: np.ndarray, coordinates):
    """Raise when the data show no motion, so no Lagrangian can be identified."""
    n = len(coordinates)
    if X.shape[0] > 1 and np.all(X == X[0]):
        raise ValueError(
            f"X is constant: all {X.shape[0]} rows are the same sample, so nothing "
            "can be identified. Record trajectories in which the system moves."
        )
    if not np.any(X[:, n : 2 * n]):
        raise ValueError(
            f"all velocities in X ({state_names(coordinates)[n : 2 * n]}) are zero: "
            "the system never moves, so no kinetic energy (and no Lagrangian) can be "
            "identified. Record trajectories with motion, and check that the columns "
            f"are in the order {_LAYOUT_HINT}."
        )


def n_features_message(n_features: int, n_dof: int | None) -> str:
    if n_dof is None:
        return (
            f"X must have 3 * n_dof columns {_LAYOUT_HINT}, but "
            f"n_features = {n_features} is not divisible by 3"
        )
    return (
        f"X must have 3 * n_dof = {3 * n_dof} columns {_LAYOUT_HINT} for the "
        f"library's {n_dof} coordinate(s), got n_features = {n_features}"
    )


def validate_state(est, X, *, reset: bool, y=None, coordinates=None):
    """Validate X (and y) for ``est``; float64 arrays with columns [q, qd, qdd].

    DataFrame columns are selected by name first, so ``feature_names_in_`` is in
    the canonical order; conversion errors name the column and row; then
    scikit-learn's ``validate_data`` gives its usual messages (empty, too few
    samples) and sets ``est.n_features_in_`` (when ``reset``); the layout and
    finiteness checks here name the offending column and row.

    Returns
    -------
    X : ndarray of shape (n_samples, 3 * n_dof)
    y : ndarray of shape (n_samples, n_dof) or None
    coordinates : list of str
    """
    from sklearn.utils.validation import validate_data

    if is_frame(X):
        if coordinates is None:
            coordinates = coordinates_from_columns(X.columns)
        X = select_state_columns(X, coordinates)
        values = frame_as_float(X, "X")
        X = X.__class__(values, columns=X.columns, index=X.index)
    else:
        names = None if coordinates is None else state_names(coordinates)
        X = as_float_array(X, "X", names=names)
    if not reset and coordinates is not None and X.shape[1] != 3 * len(coordinates):
        raise ValueError(n_features_message(X.shape[1], len(coordinates)))
    Xa = validate_data(
        est,
        X,
        dtype=np.float64,
        ensure_all_finite=False,
        reset=reset,
        ensure_min_samples=2 if reset else 1,
    )
    if coordinates is None:
        if Xa.shape[1] % 3:
            raise ValueError(n_features_message(Xa.shape[1], None))
        coordinates = [f"q{i}" for i in range(Xa.shape[1] // 3)]
    n_dof = len(coordinates)
    if Xa.shape[1] != 3 * n_dof:
        raise ValueError(n_features_message(Xa.shape[1], n_dof))
    check_finite(Xa, state_names(coordinates), "X")
    ya = None
    if y is not None:
        ya = validate_tau(y, Xa.shape[0], n_dof, coordinates)
    return np.asarray(Xa, dtype=np.float64), ya, list(coordinates)


def validate_tau(tau, n_samples, n_dof, coordinates=None) -> np.ndarray:
    """Validate generalized forces: an array of shape (n_samples, n_dof)."""
    names = (
        [f"tau_{c}" for c in coordinates]
        if coordinates is not None
        else [f"tau[{i}]" for i in range(n_dof)]
    )
    if is_frame(tau):
        if coordinates is not None:
            tau = select_tau_columns(tau, coordinates)
        arr = frame_as_float(tau, "tau")
    else:
        arr = as_float_array(tau, "tau", ndims=(1, 2), names=names)
    if arr.ndim == 1:
        if n_dof != 1:
            raise ValueError(
                f"tau must have shape (n_samples, n_dof={n_dof}), got a 1-D array; "
                "give one generalized force column per coordinate (zeros where "
                "nothing drives it)"
            )
        arr = arr[:, None]
    if arr.shape[1] != n_dof:
        raise ValueError(
            f"tau must have shape (n_samples, n_dof={n_dof}), one generalized "
            f"force column per coordinate {names}, got shape {arr.shape}"
        )
    if arr.shape[0] != n_samples:
        raise ValueError(
            f"X and tau have different numbers of rows: {n_samples} and "
            f"{arr.shape[0]}; give one tau row per sample of X"
        )
    check_finite(arr, names, "tau")
    return arr


def raise_not_finite(gram, terms, X, tau):
    """Explain non-finite Euler-Lagrange statistics: undefined terms or overflow.

    ``X`` and ``tau`` (arrays or tensors) are the data; the message names the
    gram's precision.
    """
    import torch

    dtype = str(gram.dtype).replace("torch.", "")
    Xa = X.detach().cpu().numpy() if torch.is_tensor(X) else np.asarray(X)
    if torch.is_tensor(tau):
        tau = tau.detach().cpu().numpy()
    diag = torch.diagonal(gram, dim1=1, dim2=2)
    bad = ~torch.isfinite(diag).all(dim=0).cpu().numpy()
    bad_terms = [str(t) for t, b in zip(terms, bad[: len(terms)]) if b]
    sizes = f"largest |X| = {np.abs(Xa).max():.3g}"
    if tau is not None:
        sizes += f", largest |tau| = {np.abs(tau).max():.3g}"
    if bad_terms:
        raise ValueError(
            f"the Euler-Lagrange columns of the term(s) {bad_terms[:8]} are not "
            f"finite on this data ({sizes}): a term may be undefined there (log or "
            "sqrt of a negative number, division by zero) or its values overflow "
            f"{dtype}. Remove those terms, or change units so that the values "
            "are moderate."
        )
    raise ValueError(
        f"the Euler-Lagrange regression overflows in {dtype} for this data "
        f"({sizes}): change units so that the values are moderate"
    )


def as_frame(out, X, columns):
    """``out`` as a DataFrame (a Series when 1-D) indexed like ``X`` if X is one."""
    if not is_frame(X):
        return out
    if out.ndim == 1:
        return pd.Series(out, index=X.index, name=columns[0])
    return pd.DataFrame(out, index=X.index, columns=columns)
