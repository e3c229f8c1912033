"""Old module path of :mod:`lagsindy.formulation.operator` (and the trajectory
helpers now in :mod:`lagsindy.formulation.weak`), kept so that imports written for
0.1 keep working."""

from .formulation.operator import (  # noqa: F401
    DEFAULT_CHUNK_SIZE,
    NOISE_ROWS,
    EulerLagrangeOperator,
    forward_accelerations,
    lagrangian_columns,
    lagrangian_components,
    lagrangian_gradients,
)
from .formulation.weak import (  # noqa: F401
    bump_function,
    check_time_order,
    estimate_noise_covariance,
    estimate_sampling_interval,
    trajectory_segments,
)
