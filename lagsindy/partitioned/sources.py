"""Partitioned data: where the rows come from, and the map-reduce over them.

:class:`PartitionedData` wraps a Dask DataFrame or array, a Parquet dataset (read
with Dask) or an iterable of chunks (pandas DataFrames or ``(X, tau, groups)``
tuples, no Dask needed), and knows which columns are positions, velocities,
accelerations, forces and trajectory labels. :meth:`PartitionedData.map_reduce`
applies a function to every partition (a :class:`Chunk` of whole trajectories) and
sums the results: on Dask's scheduler for Dask inputs (the local one, or the
``dask.distributed`` cluster a ``Client`` connected; nothing here schedules by
hand), one chunk after the other for iterables (memory bounded by one chunk).
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass

import numpy as np
import pandas as pd

from .._expr import ACCELERATION_SUFFIX, VELOCITY_SUFFIX

__all__ = ["Chunk", "PartitionedData", "as_partitioned", "collect", "is_partitioned"]


@dataclass
class Chunk:
    """The rows of one partition.

    Attributes
    ----------
    X : ndarray of shape (n_rows, 3 * n_dof)
        ``[q, q_dot, q_ddot]`` (derivatives already estimated when only positions
        were given).
    tau : ndarray of shape (n_rows, n_dof) or None
    labels : ndarray of shape (n_rows,)
        Trajectory label of each row.
    """

    X: np.ndarray
    tau: np.ndarray | None
    labels: np.ndarray
    index: int = 0

    @property
    def trajectories(self) -> list:
        """The labels in order of first appearance."""
        _, first = np.unique(self.labels, return_index=True)
        return [self.labels[i].item() for i in np.sort(first)]


def _dask_kind(data):
    """``"frame"``, ``"array"`` or None: what kind of Dask collection ``data`` is
    (checked by module name, so that Dask is imported only when it is used)."""
    module = type(data).__module__ or ""
    if not module.startswith("dask"):
        return None
    if hasattr(data, "to_delayed") and hasattr(data, "columns"):
        return "frame"
    if hasattr(data, "to_delayed") and hasattr(data, "chunks"):
        return "array"
    return None


def _is_parquet_path(data) -> bool:
    if not isinstance(data, (str, os.PathLike)):
        return False
    path = os.fspath(data)
    return path.endswith(".parquet") or os.path.isdir(path)


def is_partitioned(data) -> bool:
    """Whether ``fit`` should read ``data`` partition by partition.

    Parameters
    ----------
    data : object
        What was passed as ``X``.

    Returns
    -------
    bool
        True for a :class:`PartitionedData`, a Dask DataFrame or array, a Parquet
        path, a function returning chunks, or an iterable of chunks (a list or
        tuple of DataFrames or ``(X, tau, groups)`` tuples, a generator); False
        for one in-memory table (arrays, DataFrames, tensors, nested lists).
    """
    if isinstance(data, PartitionedData) or _dask_kind(data) is not None:
        return True
    if _is_parquet_path(data):
        return True
    if isinstance(data, (np.ndarray, pd.DataFrame, pd.Series, str, bytes, dict)):
        return False
    if hasattr(data, "__array__") or hasattr(data, "shape"):
        return False  # array-likes (tensors, sparse matrices) are in memory
    if isinstance(data, (list, tuple)):
        # chunks, not rows: DataFrames, or (X, tau, groups) of arrays (a row of
        # three numbers is a tuple of length 3 too)
        return len(data) > 0 and all(
            isinstance(c, pd.DataFrame)
            or (
                isinstance(c, tuple)
                and len(c) == 3
                and (hasattr(c[0], "shape") or isinstance(c[0], list))
            )
            for c in data
        )
    if callable(data) and not isinstance(data, type):
        return True  # a function returning a new iterator of chunks each call
    return hasattr(data, "__iter__") and hasattr(data, "__next__")


def as_partitioned(data, groups=None, y=None) -> PartitionedData:
    """``data`` as a :class:`PartitionedData`.

    Parameters
    ----------
    data : PartitionedData or what :func:`is_partitioned` accepts
    groups : str or int, default=None
        The trajectory column (``fit``'s ``groups``); ``None``: ``"trajectory"``.
    y : str, list of str or "auto", default=None
        The force columns (``fit``'s ``y``); ``None`` or ``"auto"``: the columns
        ``tau_<coordinate>`` when present.

    Returns
    -------
    PartitionedData
    """
    if isinstance(data, PartitionedData):
        if groups is not None or y is not None:
            raise ValueError(
                "with PartitionedData, give the trajectory and force columns to "
                "PartitionedData(trajectory=..., tau=...), not to fit()"
            )
        return data
    kwargs = {}
    if groups is not None:
        if not isinstance(groups, (str, int)):
            raise ValueError(
                "with partitioned data, groups= names the trajectory column (a "
                f"string, or an index for arrays), got {type(groups).__name__}: put "
                "the labels into a column of the data"
            )
        kwargs["trajectory"] = groups
    if y is not None and not (isinstance(y, str) and y == "auto"):
        if isinstance(y, str) or (
            isinstance(y, (list, tuple)) and all(isinstance(c, (str, int)) for c in y)
        ):
            kwargs["tau"] = [y] if isinstance(y, str) else list(y)
        else:
            raise ValueError(
                "with partitioned data, y= names the force columns (a list of "
                "column names), or is left out: columns named tau_<coordinate> are "
                "read as forces"
            )
    return PartitionedData(data, **kwargs)


class PartitionedData:
    """Rows held in partitions of whole trajectories, for ``fit`` and ``bootstrap``.

    Parameters
    ----------
    data : Dask DataFrame, Dask array, str or path, iterable or callable
        * a Dask DataFrame with columns ``theta, theta_dot, theta_ddot`` per
          coordinate (or only ``theta`` with ``derivatives=``), forces
          ``tau_theta`` and a trajectory column;
        * a path to a Parquet dataset of such columns (read with
          ``dask.dataframe.read_parquet``);
        * a Dask array whose columns are ``[q, q_dot, q_ddot]`` (or ``q`` with
          ``derivatives=``) then forces (``tau=`` their indices) and trajectory
          labels (``trajectory=`` its index); row blocks are the partitions;
        * an iterable of chunks, pandas DataFrames as above or ``(X, tau, groups)``
          tuples of arrays; a list (or a function returning a new iterator each
          call) can be read several times, a one-shot iterator only once (enough
          for the strong form with forces).
    trajectory : str, int or None, default="trajectory"
        The column of trajectory labels (an index for arrays). ``None``: each
        partition is one trajectory. A trajectory must lie in one partition.
    tau : "auto", list or None, default="auto"
        Force columns. ``"auto"``: the columns ``tau_<coordinate>`` when present
        (none for arrays); ``None``: passive data.
    coordinates : list of str, default=None
        Coordinate names; ``None``: from the columns (``q0, q1, ...`` for arrays).
    derivatives : dict, default=None
        Only positions are given: estimate ``q_dot`` and ``q_ddot`` per partition,
        trajectory by trajectory, with :func:`lagsindy.differentiation.derivatives`
        and these options (e.g. ``{"method": "pspline"}``); ``time`` gives the
        sampling times.
    time : str, int or float, default=None
        With ``derivatives``: the time column, or a uniform sampling interval.
    """

    def __init__(
        self,
        data,
        *,
        trajectory="trajectory",
        tau="auto",
        coordinates=None,
        derivatives=None,
        time=None,
    ):
        self.data = data
        self.trajectory = trajectory
        self.tau = tau
        self.coordinates = None if coordinates is None else list(coordinates)
        self.derivatives = derivatives
        self.time = time
        if derivatives is not None and time is None:
            raise ValueError(
                "derivatives= needs time=: the time column, or the sampling interval"
            )
        self._kind = _dask_kind(data)
        if self._kind is None and _is_parquet_path(data):
            dd = _import_dask_dataframe()
            self.data = dd.read_parquet(os.fspath(data))
            self._kind = "frame"
        if self._kind == "array" and len(data.shape) != 2:
            raise ValueError(f"a Dask array of data must be 2-D, got {data.shape}")
        self._first = None  # the first chunk of a one-shot iterator, peeked
        self._passes = 0
        self.layout = self._layout()

    # ----------------------------------------------------------------- layout
    def _columns(self):
        if self._kind == "frame":
            return [str(c) for c in self.data.columns]
        if self._kind == "array":
            return list(range(self.data.shape[1]))
        first = self._peek()
        if isinstance(first, pd.DataFrame):
            return [str(c) for c in first.columns]
        X = np.asarray(first[0])
        return list(range(X.shape[1])) if X.ndim == 2 else [0]

    def _peek(self):
        if callable(self.data):
            return next(iter(self.data()))
        if iter(self.data) is self.data:
            if self._first is None:
                try:
                    self._first = next(self.data)
                except StopIteration:
                    raise ValueError("the iterable of chunks is empty") from None
                self.data = itertools.chain([self._first], self.data)
                self._one_shot = True
            return self._first
        for chunk in self.data:
            return chunk
        raise ValueError("the iterable of chunks is empty")

    def _layout(self) -> dict:
        columns = self._columns()
        tuples = self._kind is None and not isinstance(self._peek(), pd.DataFrame)
        if tuples:  # (X, tau, groups): the columns are positional
            X, tau, _ = self._peek()
            n = np.asarray(X).shape[1] if np.asarray(X).ndim == 2 else 1
            blocks = 1 if self.derivatives is not None else 3
            d = n // blocks
            if d * blocks != n:
                raise ValueError(f"X chunks must have 3 * n_dof columns, got {n}")
            coords = self.coordinates or [f"q{i}" for i in range(d)]
            return {
                "tuples": True,
                "positional": self.coordinates is None,
                "coordinates": coords,
                "forces": tau is not None,
            }
        positional = self._kind == "array"
        traj = self.trajectory
        if traj is not None and traj not in columns:
            raise ValueError(
                f"no trajectory column {traj!r} among {columns[:12]}: name it with "
                "trajectory= (groups= in fit), or trajectory=None when each "
                "partition is one trajectory"
            )
        skip = {traj, self.time if isinstance(self.time, (str, int)) else None}
        rest = [c for c in columns if c not in skip]
        if self.tau == "auto":
            tau_cols = [] if positional else [c for c in rest if c.startswith("tau_")]
        else:
            tau_cols = [] if self.tau is None else list(self.tau)
        missing = [c for c in tau_cols if c not in columns]
        if missing:
            raise ValueError(f"no force columns {missing} among {columns[:12]}")
        rest = [c for c in rest if c not in tau_cols]
        blocks = 1 if self.derivatives is not None else 3
        if positional:
            d = len(rest) // blocks
            if d * blocks != len(rest) or d == 0:
                raise ValueError(
                    f"{len(rest)} data columns (besides forces and trajectory) are "
                    f"not {blocks} * n_dof"
                )
            coords = self.coordinates or [f"q{i}" for i in range(d)]
            state = rest
        else:
            # coordinates: the columns with a velocity column (other columns, e.g.
            # a time stamp, are ignored); positions only: every other column
            coords = self.coordinates or [
                c
                for c in rest
                if not c.endswith(VELOCITY_SUFFIX)
                and not c.endswith(ACCELERATION_SUFFIX)
                and (self.derivatives is not None or c + VELOCITY_SUFFIX in rest)
            ]
            if not coords:
                raise ValueError(
                    f"no coordinates found among the columns {rest[:12]}: expected "
                    "'theta', 'theta_dot', 'theta_ddot' per coordinate (or pass "
                    "coordinates=[...])"
                )
            names = list(coords)
            if self.derivatives is None:
                names += [c + VELOCITY_SUFFIX for c in coords]
                names += [c + ACCELERATION_SUFFIX for c in coords]
            absent = [c for c in names if c not in columns]
            if absent:
                hint = (
                    "; give only positions with derivatives={...} and time=..."
                    if self.derivatives is None
                    else ""
                )
                raise ValueError(
                    f"missing columns {absent} (coordinates {coords}); expected "
                    f"'theta', 'theta_dot', 'theta_ddot' per coordinate{hint}"
                )
            state = names
            if tau_cols and self.tau == "auto":
                wanted = [f"tau_{c}" for c in coords]
                if sorted(wanted) != sorted(tau_cols):
                    raise ValueError(
                        f"force columns {tau_cols} do not match the coordinates "
                        f"{coords} (expected {wanted}); pass tau=[...]"
                    )
                tau_cols = wanted
        return {
            "tuples": False,
            "positional": positional and self.coordinates is None,
            "coordinates": list(coords),
            "state": state,
            "tau": tau_cols,
            "forces": bool(tau_cols),
        }

    @property
    def n_dof(self) -> int:
        return len(self.layout["coordinates"])

    @property
    def has_forces(self) -> bool:
        return self.layout["forces"]

    @property
    def feature_names(self):
        """State column names (``None`` for positional data)."""
        if self.layout["tuples"] or self._kind == "array":
            return None
        return (
            [str(c) for c in self.layout["state"]] if self.derivatives is None else None
        )

    # ----------------------------------------------------------------- chunks
    @property
    def reader(self) -> _Reader:
        """What turns a partition into a :class:`Chunk` (small, picklable: it
        travels with every task, the data do not)."""
        return _Reader(
            dict(self.layout),
            self._kind,
            self.trajectory,
            self.time,
            self.derivatives,
        )

    def read(self, part, index: int) -> Chunk:
        """One partition (a DataFrame, array or tuple) as a :class:`Chunk`."""
        return self.reader(part, index)

    def _delayed_parts(self):
        if self._kind == "frame":
            return list(self.data.to_delayed())
        data = self.data
        if len(data.chunks[1]) > 1:
            data = data.rechunk({1: -1})
        return list(data.to_delayed().ravel())

    def _iterate(self):
        if callable(self.data):
            return iter(self.data())
        if getattr(self, "_one_shot", False) and self._passes > 1:
            raise ValueError(
                "this fit reads the data more than once (the weak form, passive "
                "data or a bootstrap take several passes), but the chunks came from "
                "a one-shot iterator: pass a list of chunks, or a function that "
                "returns a new iterator each call"
            )
        return iter(self.data)

    @property
    def n_partitions(self) -> int | None:
        if self._kind == "frame":
            return self.data.npartitions
        if self._kind == "array":
            return len(self.data.chunks[0])
        return len(self.data) if isinstance(self.data, (list, tuple)) else None

    def map_reduce(self, func, combine):
        """``combine`` of ``func(chunk)`` over every partition, in their order.

        ``combine(a, b)`` must be associative (a sum, or a concatenation of ``a``
        then ``b``). Dask inputs: one task per partition and a tree of combine
        tasks, computed by ``dask.compute`` (Dask's default scheduler, or the
        connected ``dask.distributed`` client); iterables: one chunk at a time.
        """
        self._passes += 1
        if self._kind is None:
            total = None
            read = self.reader
            for k, part in enumerate(self._iterate()):
                out = func(read(part, k))
                total = out if total is None else combine(total, out)
            if total is None:
                raise ValueError("the iterable of chunks is empty")
            return total
        import dask

        read, tasks = self.reader, []
        for k, part in enumerate(self._delayed_parts()):
            tasks.append(dask.delayed(_apply)(func, read, part, k))
        while len(tasks) > 1:
            pairs = [tasks[i : i + 2] for i in range(0, len(tasks), 2)]
            tasks = [dask.delayed(combine)(*p) if len(p) == 2 else p[0] for p in pairs]
        (total,) = dask.compute(tasks[0])
        return total


@dataclass
class _Reader:
    """A partition (DataFrame, array block or ``(X, tau, groups)``) as a Chunk."""

    layout: dict
    kind: str | None
    trajectory: object
    time: object
    derivatives: dict | None

    def __call__(self, part, index: int) -> Chunk:
        lay = self.layout
        time = self.time
        if lay["tuples"]:
            X, tau, groups = part
            X = np.asarray(X, dtype=np.float64)
            X = X.reshape(-1, 1) if X.ndim == 1 else X
            tau = None if tau is None else np.asarray(tau, dtype=np.float64)
            if tau is not None and tau.ndim == 1:
                tau = tau.reshape(-1, 1)
            labels = (
                np.full(X.shape[0], index) if groups is None else np.asarray(groups)
            )
        else:
            if self.kind == "array":
                part = np.asarray(part)

                def get(cols):
                    return part[:, cols]
            else:

                def get(cols):
                    return part[cols].to_numpy()

            X = np.asarray(get(lay["state"]), dtype=np.float64)
            tau = np.asarray(get(lay["tau"]), dtype=np.float64) if lay["tau"] else None
            traj = self.trajectory
            labels = (
                np.full(X.shape[0], index)
                if traj is None
                else np.asarray(get([traj])).ravel()
            )
            if isinstance(time, (str, int)) and not isinstance(time, bool):
                time = np.asarray(get([time]), dtype=np.float64).ravel()
        X = X if X.flags.writeable else X.copy()  # torch wants writable arrays
        if tau is not None and not tau.flags.writeable:
            tau = tau.copy()
        if tau is not None and tau.shape[0] != X.shape[0]:
            raise ValueError(
                f"a chunk has {X.shape[0]} rows of X but {tau.shape[0]} of tau"
            )
        if labels.shape[0] != X.shape[0]:
            raise ValueError(
                f"a chunk has {X.shape[0]} rows of X but {labels.shape[0]} labels"
            )
        if self.derivatives is not None and X.shape[0]:
            from ..differentiation import derivatives

            X = derivatives(X, time, groups=labels, **self.derivatives)
        return Chunk(X, tau, labels, index)


def _rows(chunk):
    return {"labels": chunk.trajectories, "rows": [(chunk.X, chunk.tau, chunk.labels)]}


def collect(data, groups=None, y=None):
    """Partitioned data read into memory, in partition order.

    For the consumers that need every row at once (:func:`lagsindy.diagnose`);
    the trajectories must not be split across partitions.

    Parameters
    ----------
    data, groups, y
        As for :func:`as_partitioned`.

    Returns
    -------
    X : ndarray of shape (n_samples, 3 * n_dof)
        ``[q, q_dot, q_ddot]``.
    tau : ndarray of shape (n_samples, n_dof) or None
    groups : ndarray of shape (n_samples,)
    """
    from .statistics import combine

    data = as_partitioned(data, groups=groups, y=y)
    parts = data.map_reduce(_rows, combine)["rows"]
    X = np.concatenate([x for x, _, _ in parts])
    tau = None if parts[0][1] is None else np.concatenate([t for _, t, _ in parts])
    return X, tau, np.concatenate([g for _, _, g in parts])


def _apply(func, read, part, index):
    return func(read(part, index))


def _import_dask_dataframe():
    try:
        import dask.dataframe as dd
    except ImportError:
        raise ImportError(
            "reading a Parquet dataset needs Dask: pip install 'lagsindy[dask]' "
            "(or pass an iterable of DataFrame chunks)"
        ) from None
    return dd
