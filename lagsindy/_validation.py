"""Layout checks for X = [q, qdot, qddot] and tau, with messages that say what to do."""

from __future__ import annotations

import numpy as np
import pandas as pd

from ._expr import ACCELERATION_SUFFIX, VELOCITY_SUFFIX, state_names


def is_frame(X) -> bool:
    return isinstance(X, pd.DataFrame)


def coordinates_from_columns(columns) -> list[str]:
    """Infer coordinate names from DataFrame columns ``[q..., q_dot..., q_ddot...]``."""
    columns = [str(c) for c in columns]
    qs = [c for c in columns if not c.endswith(VELOCITY_SUFFIX) and not c.endswith(ACCELERATION_SUFFIX)]
    missing = [c for c in state_names(qs) if c not in columns]
    if not qs or missing:
        raise ValueError(
            "could not read coordinates from the DataFrame columns "
            f"{columns}: expected columns named like 'theta', 'theta_dot', 'theta_ddot' "
            f"for each coordinate{'; missing ' + str(missing) if missing else ''}. "
            "Rename the columns, or pass a library with coordinates=[...]."
        )
    return qs


def select_state_columns(X: pd.DataFrame, coordinates) -> pd.DataFrame:
    """Columns of ``X`` in the order ``[q..., q_dot..., q_ddot...]`` for ``coordinates``."""
    wanted = state_names(coordinates)
    present = {str(c): c for c in X.columns}
    missing = [w for w in wanted if w not in present]
    if missing:
        raise ValueError(
            f"the DataFrame is missing the columns {missing} (it has {list(present)}); "
            f"X needs {wanted}: positions, velocities ('<name>_dot') and accelerations "
            "('<name>_ddot'). Estimate derivatives with lagsindy.differentiation first."
        )
    return X[[present[w] for w in wanted]]


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
            f"row {row}, column {name!r}. Drop or interpolate those rows before fitting."
        )


def as_float_array(X, what: str) -> np.ndarray:
    """Convert to a 2-D float64 array with a clear error for unconvertible dtypes."""
    try:
        arr = np.asarray(X, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"{what} could not be converted to floating point numbers ({exc}); "
            "pass numeric data"
        ) from None
    return arr


def n_features_message(n_features: int, n_dof: int | None) -> str:
    if n_dof is None:
        return (
            f"X must have 3 * n_dof columns [q..., q_dot..., q_ddot...], but "
            f"n_features = {n_features} is not divisible by 3"
        )
    return (
        f"X must have 3 * n_dof = {3 * n_dof} columns [q..., q_dot..., q_ddot...] for the "
        f"library's {n_dof} coordinate(s), got n_features = {n_features}"
    )
