"""Derivative estimation from sampled positions q(t), per trajectory.

Encoders and cameras record positions; the Euler-Lagrange regression also needs
q_dot and q_ddot. :func:`derivatives` estimates them trajectory by trajectory and
returns ``[q, q_dot, q_ddot]``; :class:`Derivatives` is the same as a scikit-learn
transformer, so ``make_pipeline(Derivatives(), LagrangianSINDy(...))`` fits recorded
positions directly (and cross-validates with ``GroupKFold`` over trajectories).

Methods (``method=``):

* ``"pspline"`` (default): a quintic B-spline with knots every two samples (on
  records of any length: no cap on the number of knots) and a penalty on
  differences of its coefficients (a P-spline). The amount of smoothing,
  and whether 3rd or 4th differences are penalised, are chosen per trajectory and
  coordinate by generalized cross-validation (GCV), so nothing needs tuning and the
  result does not depend on the units of q or t. q_dot and q_ddot are the spline's
  derivatives (q_ddot is a smooth piecewise cubic).
* ``"spline"``: scipy's cubic smoothing spline
  (:func:`scipy.interpolate.make_smoothing_spline`, also GCV). Its q_ddot is only
  piecewise linear and is forced to 0 at both ends of every trajectory (natural
  spline), and it is about 100x slower (scipy computes GCV in a Python loop).
* ``"savgol"``: Savitzky-Golay local polynomials (``window``, ``polyorder``). Good
  when the window suits the noise level; the default 11-sample window is fine for
  noise-free data and far too short for q_ddot once q is noisy.
* ``"finite_difference"``: second-order central differences (one-sided at the ends),
  no smoothing: exact enough without noise, useless with it (noise of standard
  deviation sigma becomes ``sqrt(6) sigma / dt**2`` in q_ddot).

Time stamps may be non-uniform: every method uses them directly (no resampling).
Angles can be unwrapped per trajectory before differentiating (``angles=``). Real
clocks are cleaned first (:func:`clean_clock`, on by default; module
:mod:`~lagsindy.differentiation.clock`): stale repeated rows and near-duplicate
stamps dropped, a jittery clock over a regular cycle rebuilt on it when the motion
says so, trajectories cut at gaps of ``gap_factor`` (5) base periods, single dropped
frames kept, the rows near every segment's end flagged, each defect reported once
in one line. :func:`resample` puts an uneven record on an even clock through the
P-spline, :func:`to_even_clock` puts estimated states there (what
``LagrangianSINDy.fit(..., t=)`` does on an uneven clock); :func:`time_test_functions` gives the weak form's test functions on a
segment's actual sample times.

Cost of the P-spline: uniformly sampled trajectories of up to ~1190 samples share
one eigendecomposition per sampling pattern; longer or irregularly sampled ones use
banded solves with an exact GCV trace, linear in the number of samples (measured
1.1-1.4 s of CPU per 1e5 samples on one trajectory, 13 s for 1e6;
``python -m benchmarks.differentiation --long``).

Accuracy, measured by ``python -m benchmarks.differentiation`` on
``make_dataset(cart_pendulum(), n_trajectories=20, excitation="sincos",
random_state=0)`` (20 x 5 s at 100 Hz; RMS of the exact signals: x_dot 0.72 m/s,
theta_dot 2.9 rad/s, x_ddot 4.1 m/s^2, theta_ddot 8.0 rad/s^2), Gaussian noise of
standard deviation sigma added to the exact x and theta; RMS error against the exact
derivatives over all samples, mean of 3 noise draws. The last column excludes the 10
first and last samples of each trajectory, where every method is one-sided::

    | sigma | method | x_dot | theta_dot | x_ddot | theta_ddot | theta_ddot inner |
    |---|---|---|---|---|---|---|
    | 0 | pspline | 3.9e-07 | 5.3e-07 | 1.3e-04 | 1.7e-04 | 1.3e-04 |
    | 0 | spline (cubic) | 4.0e-03 | 9.7e-03 | 0.26 | 0.64 | 2.8e-02 |
    | 0 | savgol 11, 4 | 2.2e-04 | 3.0e-04 | 1.0e-02 | 1.4e-02 | 5.6e-03 |
    | 0 | finite_difference | 6.6e-04 | 8.2e-04 | 5.8e-03 | 7.6e-03 | 6.7e-03 |
    | 1e-3 | pspline | 6.4e-03 | 6.9e-03 | 0.20 | 0.22 | 0.19 |
    | 1e-3 | spline (cubic) | 1.1e-02 | 1.7e-02 | 0.54 | 0.97 | 0.69 |
    | 1e-3 | savgol 11, 4 | 2.7e-02 | 2.6e-02 | 2.7 | 2.7 | 2.6 |
    | 1e-3 | savgol 21, 4 | 1.1e-02 | 1.1e-02 | 0.53 | 0.54 | 0.47 |
    | 1e-3 | finite_difference | 7.2e-02 | 7.2e-02 | 25 | 25 | 24 |
    | 1e-2 | pspline | 3.6e-02 | 4.1e-02 | 0.75 | 0.92 | 0.75 |
    | 1e-2 | spline (cubic) | 4.3e-02 | 5.8e-02 | 1.1 | 1.6 | 1.3 |
    | 1e-2 | savgol 11, 4 | 0.27 | 0.26 | 27 | 27 | 26 |
    | 1e-2 | savgol 41, 4 | 4.7e-02 | 5.1e-02 | 1.2 | 1.3 | 0.98 |
    | 1e-2 | finite_difference | 0.72 | 0.72 | 2.5e+02 | 2.5e+02 | 2.4e+02 |

Time for the 20 trajectories: pspline 0.1-0.2 s, savgol and finite differences
< 0.1 s, spline (cubic) 13-16 s. The P-spline was also the most accurate on the
other paper systems (single, double and spherical pendulum, active and passive; 8
trajectories each) at sigma = 1e-3 and 1e-2: its relative RMS error of q_ddot was
below that of Savitzky-Golay with the best window (of 11 to 61 samples) chosen
knowing the truth, in all 16 cases. It is not best on every signal: on a pure sum of
two sines (``tests/test_differentiation.py``) a 31-sample Savitzky-Golay window beats
it at sigma = 1e-3 (RMS q_ddot error 0.21 against 0.32), mostly because of the
trajectory ends. ``make_dataset(..., protocol="sensor")`` uses the P-spline.
"""

from __future__ import annotations

# Names of the former single module ``differentiation.py``, kept importable from here
# (tests and user code reach some of them, e.g. ``_BandedPSpline`` and
# ``solve_triangular``). Layout: ``core`` (:func:`derivatives`, ``METHODS``),
# ``transformer`` (:class:`Derivatives`), ``pspline`` (the P-spline), ``methods``
# (finite differences, Savitzky-Golay, cubic spline), ``records`` (time stamps,
# trajectories, gaps).
import math  # noqa: F401
import warnings  # noqa: F401
from numbers import Integral, Real  # noqa: F401

import numpy as np  # noqa: F401
import pandas as pd  # noqa: F401
from scipy.interpolate import BSpline, make_smoothing_spline  # noqa: F401
from scipy.linalg import eigh, solve_triangular, solveh_banded  # noqa: F401
from scipy.linalg.lapack import dpbtrf, dpbtrs, zgbtrf, zgbtrs  # noqa: F401
from scipy.signal import savgol_filter  # noqa: F401
from sklearn.base import BaseEstimator, TransformerMixin, _fit_context  # noqa: F401
from sklearn.utils._param_validation import Interval, StrOptions  # noqa: F401
from sklearn.utils.validation import check_is_fitted, validate_data  # noqa: F401
from threadpoolctl import ThreadpoolController  # noqa: F401

from .._expr import ACCELERATION_SUFFIX, VELOCITY_SUFFIX, state_names  # noqa: F401
from ._timegrid import (  # noqa: F401
    TimeWindows,
    quadrature_weights,
    time_test_functions,
    trapezoid_weights,
)
from .clock import EDGE_SAMPLES, CleanedClock, ClockWarning, clean_clock  # noqa: F401
from .core import (  # noqa: F401
    _CONTROLLER,
    _MIN_SAMPLES,
    METHODS,
    _blas_controller,
    derivatives,
)
from .methods import (  # noqa: F401
    _check_savgol_params,
    _cubic_spline,
    _fd_weights,
    _finite_difference,
    _local_polynomial,
    _savgol,
)
from .pspline import (  # noqa: F401
    _COMPLEX_STEP,
    _PSPLINE_COARSE_STEP,
    _PSPLINE_DEGREE,
    _PSPLINE_DENSE_MAX,
    _PSPLINE_FD_MAX_COND,
    _PSPLINE_FD_MIN,
    _PSPLINE_FD_STEP,
    _PSPLINE_MAX_LOG_LAMBDA,
    _PSPLINE_ORDERS,
    _band_quadratic,
    _BandedBasis,
    _BandedPSpline,
    _difference_coefficients,
    _penalty_band,
    _PSpline,
    _pspline,
    _pspline_knots,
    _pspline_spans,
    _upper_banded,
)
from .records import (  # noqa: F401
    _GAP_FACTOR,
    _GLITCH_FRACTION,
    _UNIFORM_RTOL,
    _angle_mask,
    _check_times,
    _describe_rows,
    _is_uniform,
    _segments,
    _split_at_gaps,
    _warn_gaps,
    _warn_glitches,
    check_weak_form_segments,
    split_gaps,
)
from .evenclock import EvenClock, edge_rows, to_even_clock  # noqa: F401
from .resample import Resampled, resample  # noqa: F401
from .transformer import Derivatives  # noqa: F401
