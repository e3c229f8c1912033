"""Fits from partitioned data: Dask DataFrames and arrays, Parquet, chunks.

Every lagsindy fit reduces the data to sums of Gram statistics, so data beyond one
machine's memory are fitted by mapping each partition (whole trajectories) to its
statistics and summing them: with Dask's scheduler (the local one by default, or
any ``dask.distributed`` cluster a ``Client`` connects, without code changes), or
chunk after chunk from an iterable without Dask. The solve on the summed statistics
is the in-memory pipeline's (:mod:`lagsindy.pipeline`), so the model equals the
in-memory fit of the same rows up to rounding.

``LagrangianSINDy.fit``, :func:`lagsindy.bootstrap` accept what
:func:`is_partitioned` recognizes; :class:`PartitionedData` names the columns when
the defaults (a ``trajectory`` column, forces ``tau_<coordinate>``) do not fit.
"""

from .fit import fit_state, partitioned_setup
from .sources import Chunk, PartitionedData, as_partitioned, collect, is_partitioned
from .statistics import combine, stack_trajectories, trajectory_pass

__all__ = [
    "Chunk",
    "PartitionedData",
    "as_partitioned",
    "collect",
    "combine",
    "fit_state",
    "is_partitioned",
    "partitioned_setup",
    "stack_trajectories",
    "trajectory_pass",
]
