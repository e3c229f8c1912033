"""The scikit-learn transformer :class:`Derivatives` around :func:`derivatives`."""

from __future__ import annotations

from numbers import Integral, Real

import numpy as np
import pandas as pd
from sklearn.base import BaseEstimator, TransformerMixin, _fit_context
from sklearn.utils._param_validation import Interval, StrOptions
from sklearn.utils.validation import check_is_fitted, validate_data

from .._expr import ACCELERATION_SUFFIX, VELOCITY_SUFFIX, state_names
from .._params import cache_param_names
from .core import METHODS, derivatives
from .methods import _check_savgol_params
from .records import _GAP_FACTOR, _angle_mask


# ----------------------------------------------------------------- transformer
@cache_param_names
class Derivatives(TransformerMixin, BaseEstimator):
    """Estimate velocities and accelerations: positions to ``[q, q_dot, q_ddot]``.

    A scikit-learn transformer around :func:`derivatives`, so that recorded
    positions go straight into a pipeline:
    ``make_pipeline(Derivatives(), LagrangianSINDy(...))``. Each row needs its time
    and its trajectory, so X carries them as columns:

    * **DataFrame** (recommended): a time column (``time``, default ``"t"``), a
      trajectory column (``trajectory``, default ``"trajectory"``) and the position
      columns (``coordinates``, default: every other column). The output is a
      DataFrame with the same index and the columns ``name, ..., name_dot, ...,
      name_ddot, ...``, which :class:`~lagsindy.LagrangianSINDy` reads by name.
      This is the layout of ``make_dataset(...).to_frame()`` restricted to
      ``["trajectory", "t", *coordinates]``.
    * **ndarray**: give column indices instead of names, e.g.
      ``Derivatives(time=1, trajectory=0)`` for columns ``[trajectory, t, q...]``,
      or ``Derivatives(time=None, dt=0.01, trajectory=None)`` for positions only
      (one trajectory sampled every ``dt``). The output is an ndarray
      ``[q..., q_dot..., q_ddot...]`` (coordinates named ``q0, q1, ...`` by
      :meth:`get_feature_names_out`), or a DataFrame after
      ``set_output(transform="pandas")``.

    Rows of one trajectory must be contiguous and in time order. ``transform`` uses
    only the rows it is given, trajectory by trajectory (nothing is learned in
    ``fit``), so cross-validation with ``GroupKFold`` over the trajectory labels
    never mixes training and test rows.

    Parameters
    ----------
    method : {"pspline", "spline", "savgol", "finite_difference"}, default="pspline"
        Estimator of the derivatives; see :func:`derivatives`. ``"pspline"`` needs
        no tuning (smoothing chosen by generalized cross-validation).
    window : int, default=11
        Savitzky-Golay window length in samples (odd); ``method="savgol"`` only.
    polyorder : int, default=4
        Savitzky-Golay polynomial degree (>= 2); ``method="savgol"`` only.
    smoothing : float, default=None
        Smoothing parameter of the spline methods; ``None``: chosen by GCV.
    angles : list of str or int, boolean mask, or "all", default=None
        Angular coordinates (by name, by index among the coordinates, or a mask
        over the coordinates), unwrapped per trajectory before differentiating;
        their output positions are the unwrapped angles.
    time : str, int or None, default="t"
        Column holding the time stamps (a name for a DataFrame, an index for an
        ndarray). ``None``: uniform sampling every ``dt`` from the start of each
        trajectory.
    trajectory : str, int or None, default="trajectory"
        Column holding the trajectory labels. ``None``: all rows are one trajectory.
    coordinates : list of str or int, default=None
        Position columns (names or indices). ``None``: every column that is not the
        time or trajectory column.
    dt : float, default=None
        Sampling interval, used only when ``time=None``.
    gap_factor : float or None, default=5.0
        Steps longer than this many median steps are gaps: each trajectory is
        differentiated segment by segment (a ``UserWarning`` says where). Fit with
        ``groups=split_gaps(t, trajectory)`` so that the estimator sees the
        segments too. ``None``: no gap detection.

    Attributes
    ----------
    coordinates_ : list of str
        Names of the coordinates (the position columns, or ``q0, q1, ...`` for an
        ndarray).
    angles_ : list of str
        Coordinates treated as angles.
    n_features_in_ : int
        Number of columns of X seen in ``fit``.
    feature_names_in_ : ndarray of str
        Column names of X seen in ``fit``; only when X was a DataFrame with string
        column names.

    See Also
    --------
    derivatives : the function doing the work.
    lagsindy.LagrangianSINDy : reads the output by column name.

    Examples
    --------
    >>> from sklearn.pipeline import make_pipeline
    >>> from lagsindy import Derivatives, LagrangianSINDy
    >>> from lagsindy.systems import make_dataset, single_pendulum
    >>> data = make_dataset(single_pendulum(), n_trajectories=4, duration=2.0,
    ...                     random_state=0)
    >>> positions = data.to_frame()[["trajectory", "t", "theta"]]
    >>> Derivatives().fit_transform(positions).columns.tolist()
    ['theta', 'theta_dot', 'theta_ddot']
    >>> pipe = make_pipeline(Derivatives(angles=["theta"]),
    ...                      LagrangianSINDy(single_pendulum().paper_library()))
    >>> print(pipe.fit(positions, data.tau)[-1].equation(precision=3))
    L = 0.5*theta_dot**2 + 9.81*cos(theta)
    """

    _parameter_constraints: dict = {
        "method": [StrOptions(set(METHODS))],
        "window": [Interval(Integral, 3, None, closed="left")],
        "polyorder": [Interval(Integral, 2, None, closed="left")],
        "smoothing": [Interval(Real, 0, None, closed="left"), None],
        "angles": ["array-like", StrOptions({"all"}), None],
        "time": [str, Interval(Integral, None, None, closed="neither"), None],
        "trajectory": [str, Interval(Integral, None, None, closed="neither"), None],
        "coordinates": ["array-like", None],
        "dt": [Interval(Real, 0, None, closed="neither"), None],
        "gap_factor": [Interval(Real, 1, None, closed="neither"), None],
    }

    def __init__(
        self,
        method="pspline",
        *,
        window=11,
        polyorder=4,
        smoothing=None,
        angles=None,
        time="t",
        trajectory="trajectory",
        coordinates=None,
        dt=None,
        gap_factor=_GAP_FACTOR,
    ):
        self.method = method
        self.window = window
        self.polyorder = polyorder
        self.smoothing = smoothing
        self.angles = angles
        self.time = time
        self.trajectory = trajectory
        self.coordinates = coordinates
        self.dt = dt
        self.gap_factor = gap_factor

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.input_tags.allow_nan = False
        tags.transformer_tags.preserves_dtype = ["float64"]
        return tags

    # ------------------------------------------------------------------ layout
    def _column(self, value, columns, frame: bool, what: str):
        """Position of the time / trajectory column, or None."""
        if value is None:
            return None
        if isinstance(value, str):
            if not frame:
                raise ValueError(
                    f"X is an array, so {what} must be a column index or None, got "
                    f"{what}={value!r}. With an array use e.g. Derivatives(time=1, "
                    "trajectory=0) for columns [trajectory, t, q...], or "
                    "Derivatives(time=None, dt=..., trajectory=None) for positions "
                    "only."
                )
            names = [str(c) for c in columns]
            if value not in names:
                hint = (
                    "pass time=None and dt=... for uniform sampling"
                    if what == "time"
                    else "pass trajectory=None if all rows are one trajectory"
                )
                raise ValueError(
                    f"X has no {what} column {value!r} (its columns are {names}); name "
                    f"the column with {what}='...', or {hint}"
                )
            return names.index(value)
        index = int(value)
        if not -len(columns) <= index < len(columns):
            raise ValueError(
                f"{what}={value} is not a column index of X, which has "
                f"n_features = {len(columns)} columns"
            )
        return index % len(columns)

    def _resolve_layout(self, X):
        frame = isinstance(X, pd.DataFrame)
        columns = list(X.columns) if frame else list(range(X.shape[1]))
        if self.time is not None and self.dt is not None:
            raise ValueError(
                f"give the time stamps either as a column (time={self.time!r}) or as a "
                f"sampling interval (dt={self.dt!r}), not both: set time=None to use dt"
            )
        if self.time is None and self.dt is None:
            raise ValueError("time=None needs dt, the sampling interval")
        t_col = self._column(self.time, columns, frame, "time")
        g_col = self._column(self.trajectory, columns, frame, "trajectory")
        if t_col is not None and t_col == g_col:
            raise ValueError("time and trajectory name the same column")
        taken = {t_col, g_col}
        if self.coordinates is None:
            pos = [i for i in range(len(columns)) if i not in taken]
        else:
            pos = []
            names = [str(c) for c in columns]
            for c in np.atleast_1d(np.asarray(self.coordinates, dtype=object)).tolist():
                i = self._column(c, columns, frame, "coordinates")
                if i in taken or i in pos:
                    raise ValueError(
                        f"coordinate column {names[i]!r} is listed twice or is the "
                        "time or trajectory column"
                    )
                pos.append(i)
        if not pos:
            raise ValueError(
                f"X has no position columns besides time and trajectory (columns: "
                f"{[str(c) for c in columns]})"
            )
        if frame:
            coords = [str(columns[i]) for i in pos]
            derived = [
                c for c in coords if c.endswith((VELOCITY_SUFFIX, ACCELERATION_SUFFIX))
            ]
            if derived:
                raise ValueError(
                    f"the position columns include {derived}, which look like "
                    "velocities or accelerations; Derivatives estimates those from the "
                    "positions. Keep only the trajectory, time and position columns "
                    "(e.g. df[['trajectory', 't', 'x', 'theta']]) or pass "
                    "coordinates=[...]"
                )
        else:
            coords = [f"q{k}" for k in range(len(pos))]
        return t_col, g_col, pos, coords

    def _check_input(self, X, *, reset: bool):
        """Validate X (sklearn conventions); return it as a DataFrame or float array."""
        if isinstance(X, pd.DataFrame):
            validate_data(self, X, reset=reset, skip_check_array=True)
            return X
        return validate_data(self, X, reset=reset, dtype=np.float64)

    @_fit_context(prefer_skip_nested_validation=True)
    def fit(self, X, y=None):
        """Check the layout of X (nothing is learned).

        Parameters
        ----------
        X : DataFrame or array-like of shape (n_samples, n_features)
            Time, trajectory and position columns (see the class docstring).
        y : None
            Ignored.

        Returns
        -------
        self : Derivatives
            The fitted transformer.
        """
        X = self._check_input(X, reset=True)
        t_col, g_col, pos, coords = self._resolve_layout(X)
        mask = _angle_mask(self.angles, len(coords), names=coords)
        if self.method == "savgol":
            _check_savgol_params(self.window, self.polyorder)
        self.coordinates_ = coords
        self.angles_ = [c for c, m in zip(coords, mask) if m]
        self._layout = (t_col, g_col, pos)
        return self

    def transform(self, X):
        """Estimate ``[q, q_dot, q_ddot]`` trajectory by trajectory.

        Parameters
        ----------
        X : DataFrame or array-like of shape (n_samples, n_features)
            Same layout as in ``fit``.

        Returns
        -------
        X_out : DataFrame or ndarray of shape (n_samples, 3 * n_dof)
            Columns ``[q..., q_dot..., q_ddot...]``; a DataFrame (same index, columns
            from :meth:`get_feature_names_out`) when X is a DataFrame.
        """
        check_is_fitted(self)
        X = self._check_input(X, reset=False)
        t_col, g_col, pos = self._layout
        frame = isinstance(X, pd.DataFrame)
        take = (lambda i: X.iloc[:, i]) if frame else (lambda i: X[:, i])
        names = self.coordinates_
        try:
            q = np.asarray(X.iloc[:, pos] if frame else X[:, pos], dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"the position columns {names} must be numeric") from None
        t = self.dt if t_col is None else np.asarray(take(t_col))
        groups = None if g_col is None else np.asarray(take(g_col))
        out = derivatives(
            q,
            t,
            groups=groups,
            method=self.method,
            window=self.window,
            polyorder=self.polyorder,
            smoothing=self.smoothing,
            angles=[names.index(a) for a in self.angles_],
            gap_factor=self.gap_factor,
        )
        if frame:
            return pd.DataFrame(
                out, columns=self.get_feature_names_out(), index=X.index
            )
        return out

    def get_feature_names_out(self, input_features=None):
        """Output column names: ``[q..., q_dot..., q_ddot...]``.

        Parameters
        ----------
        input_features : array-like of str, default=None
            Names of the input columns; the coordinates are the names of the
            position columns. ``None``: ``coordinates_``.

        Returns
        -------
        feature_names_out : ndarray of str objects
            ``name``, then ``name_dot``, then ``name_ddot`` for every coordinate.
        """
        check_is_fitted(self)
        coords = self.coordinates_
        if input_features is not None:
            input_features = np.asarray(input_features, dtype=object)
            if len(input_features) != self.n_features_in_:
                raise ValueError(
                    f"input_features has {len(input_features)} names but X had "
                    f"n_features = {self.n_features_in_} columns in fit"
                )
            names_in = getattr(self, "feature_names_in_", None)
            if names_in is not None and not np.array_equal(input_features, names_in):
                raise ValueError(
                    f"input_features {list(input_features)} differ from the columns "
                    f"seen in fit {list(names_in)}"
                )
            coords = [str(input_features[i]) for i in self._layout[2]]
        return np.asarray(state_names(coords), dtype=object)
