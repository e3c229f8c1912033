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
Angles can be unwrapped per trajectory before differentiating (``angles=``). A step
longer than ``gap_factor`` (5) median steps is a gap: the trajectory is cut there
and each segment differentiated on its own, with one warning saying where
(:func:`split_gaps` gives the segment labels to fit with); rows far closer than the
median step (duplicated or mistimed frames) are reported by row.

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
first and last samples of each trajectory, where every method is one-sided.

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

import math
import warnings
from numbers import Integral, Real

import numpy as np
import pandas as pd
from scipy.interpolate import BSpline, make_smoothing_spline
from scipy.linalg import eigh, solve_triangular, solveh_banded
from scipy.linalg.lapack import dpbtrf, dpbtrs, zgbtrf, zgbtrs
from scipy.signal import savgol_filter
from sklearn.base import BaseEstimator, TransformerMixin, _fit_context
from sklearn.utils._param_validation import Interval, StrOptions
from sklearn.utils.validation import check_is_fitted, validate_data
from threadpoolctl import ThreadpoolController

from ._expr import ACCELERATION_SUFFIX, VELOCITY_SUFFIX, state_names

# Relative tolerance on the spacing of time stamps under which a trajectory counts as
# uniformly sampled (np.arange(n) / rate varies by about 1e-13 relative).
_UNIFORM_RTOL = 1e-6


# ----------------------------------------------------------------- finite differences
def _fd_weights(offsets: np.ndarray, order: int) -> np.ndarray:
    """Finite-difference weights for the ``order``-th derivative at offset 0.

    ``offsets`` has shape (m, k): the k stencil nodes of m evaluation points, relative
    to the point. The weights solve the Taylor (Vandermonde) conditions
    ``sum_j w_j d_j**p / p! = [p == order]`` for ``p < k``.
    """
    m, k = offsets.shape
    scale = np.max(np.abs(offsets), axis=1, keepdims=True)
    d = offsets / scale
    powers = np.arange(k)
    A = d[:, None, :] ** powers[None, :, None]  # (m, p, j)
    A = A / np.array([math.factorial(p) for p in powers])[None, :, None]
    rhs = np.zeros((m, k, 1))
    rhs[:, order, 0] = 1.0
    w = np.linalg.solve(A, rhs)[..., 0]
    return w / scale**order


def _finite_difference(q: np.ndarray, t: np.ndarray):
    """Second-order finite differences on possibly non-uniform time stamps.

    Interior points: three-point central stencils (i-1, i, i+1) for both derivatives
    (second order for the first derivative on any grid; second order for the second
    derivative on a uniform or smoothly varying grid). End points: one-sided stencils,
    three points for the first derivative and four for the second (second order).
    """
    n = len(t)
    idx = np.arange(n)
    d1 = np.empty_like(q)
    d2 = np.empty_like(q)
    # first derivative: 3-point stencils, centred inside, one-sided at the ends
    start = np.clip(idx - 1, 0, n - 3)
    nodes = start[:, None] + np.arange(3)[None, :]
    w1 = _fd_weights(t[nodes] - t[:, None], 1)
    d1[:] = np.einsum("ij,ijk->ik", w1, q[nodes])
    # second derivative: 3-point centred inside, 4-point one-sided at the ends
    inner = idx[1:-1]
    nodes = inner[:, None] + np.arange(-1, 2)[None, :]
    w2 = _fd_weights(t[nodes] - t[inner, None], 2)
    d2[1:-1] = np.einsum("ij,ijk->ik", w2, q[nodes])
    k = min(4, n)
    for i, nodes in ((0, np.arange(k)), (n - 1, np.arange(n - k, n))):
        w = _fd_weights((t[nodes] - t[i])[None, :], 2)[0]
        d2[i] = w @ q[nodes]
    return q, d1, d2


# ----------------------------------------------------------------- Savitzky-Golay
def _local_polynomial(q: np.ndarray, t: np.ndarray, window: int, polyorder: int):
    """Savitzky-Golay on arbitrary time stamps (``polyorder >= 2``).

    Each sample gets the polynomial of degree ``polyorder`` fitted to the ``window``
    samples centred on it (shifted inwards at the ends, as ``savgol_filter``'s
    ``mode="interp"`` does); value, slope and curvature at the sample's own time are
    returned. On a uniform grid this equals ``scipy.signal.savgol_filter``.
    """
    n = len(t)
    half = window // 2
    start = np.clip(np.arange(n) - half, 0, n - window)
    nodes = start[:, None] + np.arange(window)[None, :]
    d = t[nodes] - t[:, None]
    scale = np.max(np.abs(d), axis=1, keepdims=True)
    V = (d / scale)[..., None] ** np.arange(polyorder + 1)  # (n, window, p+1)
    coef = np.linalg.pinv(V) @ q[nodes]  # (n, p+1, n_cols)
    return coef[:, 0], coef[:, 1] / scale, 2.0 * coef[:, 2] / scale**2


def _savgol(q, t, window, polyorder, uniform):
    if uniform:
        dt = (t[-1] - t[0]) / (len(t) - 1)
        kw = dict(window_length=window, polyorder=polyorder, axis=0, delta=dt)
        return (
            savgol_filter(q, **kw),
            savgol_filter(q, deriv=1, **kw),
            savgol_filter(q, deriv=2, **kw),
        )
    return _local_polynomial(q, t, window, polyorder)


# ----------------------------------------------------------------- cubic spline
def _cubic_spline(q, t, lam):
    """scipy's cubic smoothing spline, column by column (GCV when ``lam`` is None)."""
    q0 = np.empty_like(q)
    q1 = np.empty_like(q)
    q2 = np.empty_like(q)
    for j in range(q.shape[1]):
        spl = make_smoothing_spline(t, q[:, j], lam=lam)
        q0[:, j] = spl(t)
        q1[:, j] = spl(t, nu=1)
        q2[:, j] = spl(t, nu=2)
    return q0, q1, q2


# ----------------------------------------------------------------- quintic P-spline
def _pspline_spans(n: int) -> int:
    """Knot spans for ``n`` samples: one per two samples, on records of any length.

    ``n_spans + degree`` coefficients stay below ``n`` so the unpenalized fit is a
    regression (GCV is then finite as the penalty goes to zero).
    """
    return int(max(1, min(round((n - 1) / 2), n - _PSPLINE_DEGREE - 1)))


def _pspline_knots(t: np.ndarray) -> np.ndarray:
    """Equally spaced knots of the quintic P-spline over ``t`` (exact end knots)."""
    degree = _PSPLINE_DEGREE
    n_spans = _pspline_spans(len(t))
    h = (t[-1] - t[0]) / n_spans
    knots = t[0] + h * np.arange(-degree, n_spans + degree + 1)
    knots[degree] = t[0]  # exact ends, so design_matrix accepts t[0] and t[-1]
    knots[-degree - 1] = t[-1]
    return knots


class _PSpline:
    r"""Penalized quintic spline (P-spline) on fixed sample times, fitted by GCV.

    Minimises :math:`\|y - B c\|^2 + \lambda \|\Delta^m c\|^2` over the coefficients of
    a quintic B-spline basis with uniform knots, ``Delta^m`` being m-th differences
    (the discrete analogue of the integral of the squared m-th derivative, so the
    penalty's null space is the polynomials of degree < m, and for m >= 3 the second
    derivative is not pulled to zero at the ends). The knots continue past both ends
    with the same spacing (not repeated), so every basis function is a shift of the
    same bump and coefficient differences approximate derivatives everywhere, ends
    included.

    With ``smoothing=None`` each column's lambda minimises
    :math:`\mathrm{GCV}(\lambda) = n\,\mathrm{RSS} / (n - \mathrm{tr}\,H)^2` over a
    log grid, all evaluated at once in the Demmler-Reinsch basis: with
    :math:`B^T B = L L^T` and :math:`L^{-1} D^T D L^{-T} = U \mathrm{diag}(s) U^T` the
    hat matrix has eigenvalues :math:`1 / (1 + \lambda s_i)`. The fit itself is then
    solved directly from the banded normal equations, which stays accurate where the
    eigenbasis does not (large lambda: polynomials are reproduced to ~1e-8). The
    factorisation depends on the times only, so trajectories with the same sampling
    share it.
    """

    def __init__(self, t: np.ndarray, penalty_order: int):
        n = len(t)
        degree = _PSPLINE_DEGREE
        knots = _pspline_knots(t)
        B = BSpline.design_matrix(t, knots, degree).toarray()
        nb = B.shape[1]
        basis = BSpline(knots, np.eye(nb), degree)
        self.B = B
        self.B1 = basis(t, nu=1)
        self.B2 = basis(t, nu=2)
        D = np.diff(np.eye(nb), penalty_order, axis=0)
        G = B.T @ B
        # tiny ridge: basis functions reaching only slightly into the data are nearly
        # unseen by it (G is then ill-conditioned but stays positive definite)
        G[np.diag_indices(nb)] += 1e-12 * np.trace(G) / nb
        P = D.T @ D
        self.G_banded = _upper_banded(G, degree)
        self.P_banded = _upper_banded(P, degree)
        L = np.linalg.cholesky(G)
        self.L = L
        LiDt = solve_triangular(L, D.T, lower=True)
        s, self.U = eigh(LiDt @ LiDt.T)
        # D has rank nb - penalty_order: the smallest eigenvalues (the polynomials of
        # degree < penalty_order) are zero, whatever rounding makes of them
        s[:penalty_order] = 0.0
        self.s = np.clip(s, 0.0, None)
        lo = np.log10(1e-4 / self.s[-1])  # essentially no smoothing
        hi = min(np.log10(1e4 / self.s[penalty_order]), _PSPLINE_MAX_LOG_LAMBDA)
        self.grid = np.logspace(lo, hi, int(np.ceil(10 * (hi - lo))) + 1)
        ls = self.grid[:, None] * self.s[None, :]
        self.shrink = ls / (1.0 + ls)  # 1 - eigenvalues of the hat matrix
        self.edf = nb - self.shrink.sum(axis=1)  # trace of the hat matrix
        self.n = n

    def fit(self, q: np.ndarray, smoothing=None):
        """Fit and its first two derivatives at the times; lambda, GCV per column."""
        n_cols = q.shape[1]
        Bty = self.B.T @ q
        if smoothing is None:
            z = solve_triangular(self.L, Bty, lower=True)
            b = self.U.T @ z  # data in the Demmler-Reinsch basis
            c0 = solve_triangular(self.L, z, lower=True, trans="T")
            rss0 = np.sum((q - self.B @ c0) ** 2, axis=0)  # unpenalized residual
            rss = rss0[None, :] + (self.shrink**2) @ (b**2)
            gcv = self.n * rss / (self.n - self.edf[:, None]) ** 2
            best = np.argmin(gcv, axis=0)
            lam = self.grid[best]
            score = gcv[best, np.arange(n_cols)]
        else:
            lam = np.full(n_cols, float(smoothing))
            score = np.full(n_cols, np.nan)
        coef = np.empty_like(Bty)
        for value in np.unique(lam):
            cols = lam == value
            ab = self.G_banded + value * self.P_banded
            coef[:, cols] = solveh_banded(ab, Bty[:, cols], check_finite=False)
        return self.B @ coef, self.B1 @ coef, self.B2 @ coef, lam, score


class _BandedBasis:
    """Quintic B-spline basis of :class:`_PSpline` on given times, in banded form.

    Holds what does not depend on the penalty: the knots, the sparse design matrix
    ``B`` (``degree + 1`` consecutive non-zeros per row) and the banded Gram matrix
    :math:`G = B^T B` plus the ridge of :class:`_PSpline`, built directly from the
    rows of ``B`` (no sparse product). Shared by both penalty orders.
    """

    def __init__(self, t: np.ndarray):
        n = len(t)
        degree = _PSPLINE_DEGREE
        knots = _pspline_knots(t)
        B = BSpline.design_matrix(t, knots, degree).tocsr()
        nb = B.shape[1]
        width = degree + 1
        if np.all(np.diff(B.indptr) == width):
            values = B.data.reshape(n, width)
            first = B.indices[::width]
            ok = np.all(np.diff(B.indices.reshape(n, width), axis=1) == 1)
        else:  # pragma: no cover - design_matrix stores degree + 1 entries per row
            ok = False
        Gb = np.zeros((degree + 1, nb))
        if ok:
            for k in range(degree + 1):  # entries (i, i + k) of G
                for a in range(width - k):
                    Gb[degree - k, k:] += np.bincount(
                        first + a, values[:, a] * values[:, a + k], minlength=nb
                    )[: nb - k]
        else:  # pragma: no cover
            G = (B.T @ B).tocsr()
            for k in range(degree + 1):
                Gb[degree - k, k:] = G.diagonal(k)
        Gb[degree] += 1e-12 * Gb[degree].sum() / nb  # the ridge of _PSpline
        self.B = B
        self.knots = knots
        self.times = t
        self.G_banded = Gb
        self.n = n
        self.nb = nb


def _penalty_band(order: int, nb: int) -> np.ndarray:
    """Upper band (width ``_PSPLINE_DEGREE``) of :math:`D^T D`, D the order-th
    difference matrix of ``nb`` coefficients (exact small integers)."""
    p = _PSPLINE_DEGREE
    c = _difference_coefficients(order)
    rows = nb - order
    Pb = np.zeros((p + 1, nb))
    for k in range(order + 1):  # entries (i, i + k): sum over rows r of D
        for j in range(order + 1 - k):  # D[r, r + j] D[r, r + j + k], i = r + j
            Pb[p - k, k + j : k + j + rows] += c[j] * c[j + k]
    return Pb


def _band_quadratic(upper: np.ndarray, x: np.ndarray) -> float:
    """x^T A x for a symmetric A in upper banded storage."""
    p = upper.shape[0] - 1
    total = float(upper[p] @ (x * x))
    for k in range(1, p + 1):
        total += 2.0 * float(upper[p - k, k:] @ (x[:-k] * x[k:]))
    return total


class _BandedPSpline:
    r"""The P-spline of :class:`_PSpline` at a cost linear in the number of samples.

    Same basis, penalty and GCV criterion; used for records longer than
    ``_PSPLINE_DENSE_MAX`` coefficients and for non-uniform time stamps (where no
    factorisation can be shared between trajectories). The basis matrix is sparse
    and the normal equations are banded (bandwidth 5); the basis and the Gram
    matrix :math:`G = B^T B` are shared by the penalty orders (``basis``).

    The trace of the hat matrix, :math:`\mathrm{tr}\,H = \mathrm{tr}((G + \lambda
    P)^{-1} G)`, equals :math:`n_b - \partial \log\det(G + \lambda P) / \partial
    \log\lambda`. Two ways are used, both deterministic and O(n) per lambda:

    * exact (:meth:`gcv`): a complex step through LAPACK's banded LU (``zgbtrf``):
      the pivots of :math:`G + \lambda P + i h G` are :math:`u_{ii} + i h\,u'_{ii}`
      and :math:`\mathrm{tr}\,H = \sum_i u'_{ii} / u_{ii}` (truncation error of
      order :math:`h^2`, nothing at ``h = 1e-30``);
    * fast (:meth:`gcv_fast`, on records of more than ``_PSPLINE_FD_MIN``
      coefficients): a one-sided difference in :math:`\log\lambda` (step
      ``_PSPLINE_FD_STEP``) of the log-determinants from two real banded Cholesky
      factorisations (``dpbtrf``, the first also solves), about 2x cheaper than one
      complex LU. Measured on 1e5 samples: GCV within a relative 1e-6 of the exact
      one while :math:`\lambda s_{max}` (roughly the condition number of
      :math:`G + \lambda P`) stays below 1e10, and 1e-4 to 2e-2 beyond, where
      rounding in the log-determinants dominates. So the chosen grid point is
      rescored exactly, with an exact descent to a local minimum, whenever
      :math:`\lambda s_{max}` > ``_PSPLINE_FD_MAX_COND`` or the fast scores of it
      and a neighbour are within 1e-6 of each other.

    Lambda is searched on the same kind of log grid as :class:`_PSpline` (10 points
    per decade): every 20th point first (2 decades apart), then a golden-section
    search over the grid points within 2 decades of each column's best coarse point.
    This finds the grid minimum whenever GCV has a single minimum in that window;
    about 17 evaluations per penalty order and trajectory.
    """

    def __init__(self, t: np.ndarray, penalty_order: int, basis=None):
        if basis is None:
            basis = _BandedBasis(t)
        self.basis = basis
        self.B = basis.B
        self.knots = basis.knots
        self.times = basis.times
        self.G_banded = basis.G_banded
        self.n = basis.n
        self.nb = nb = basis.nb
        self.P_banded = _penalty_band(penalty_order, nb)
        self._bands = None  # complex general-band G (1 + ih) and P, built on demand
        self._real_bands = None  # G and P in Fortran order, built on demand
        # Grid as in _PSpline, from 1e-4 / s_max (essentially no smoothing) to the
        # largest lambda the banded solve resolves. s_max, the largest eigenvalue of
        # G^-1 P, is taken as the Rayleigh quotient of the alternating vector (the
        # roughest coefficients, its eigenvector away from the ends).
        alt = (-1.0) ** np.arange(nb)
        s_max = _band_quadratic(self.P_banded, alt) / _band_quadratic(
            self.G_banded, alt
        )
        self.s_max = s_max
        lo = np.log10(1e-4 / s_max)
        hi = max(_PSPLINE_MAX_LOG_LAMBDA, lo + 1.0)
        self.grid = np.logspace(lo, hi, int(np.ceil(10 * (hi - lo))) + 1)

    def _general_band(self, upper: np.ndarray) -> np.ndarray:
        """A symmetric upper band in LAPACK general band storage (for zgbtrf)."""
        p = _PSPLINE_DEGREE
        nb = self.nb
        ab = np.zeros((3 * p + 1, nb), dtype=np.complex128)
        for k in range(p + 1):
            diag = upper[p - k, k:]
            ab[2 * p - k, k:] = diag  # entry (i, i + k)
            if k:
                ab[2 * p + k, : nb - k] = diag  # entry (i + k, i)
        return ab

    def gcv(self, lam: float, q: np.ndarray, Bty: np.ndarray) -> np.ndarray:
        """GCV score of every column at one lambda (exact trace, O(n))."""
        p = _PSPLINE_DEGREE
        if self._bands is None:
            self._bands = (
                self._general_band(self.G_banded * (1.0 + 1j * _COMPLEX_STEP)),
                self._general_band(self.P_banded),
            )
        G, P = self._bands
        lu, piv, info = zgbtrf(G + lam * P, p, p, overwrite_ab=1)
        if info != 0:  # pragma: no cover - G + lam P is positive definite
            return np.full(q.shape[1], np.inf)
        pivots = lu[2 * p]
        edf = float(np.sum(pivots.imag / pivots.real)) / _COMPLEX_STEP
        coef, info = zgbtrs(lu, p, p, Bty, piv)
        rss = np.sum((q - self.B @ coef.real) ** 2, axis=0)
        return self.n * rss / (self.n - edf) ** 2

    def _logdet(self, lam: float):
        """Upper Cholesky factor of G + lam P and its log-determinant."""
        if self._real_bands is None:  # Fortran order: what dpbtrf works on
            self._real_bands = (
                np.asfortranarray(self.G_banded),
                np.asfortranarray(self.P_banded),
            )
        G, P = self._real_bands
        ab = np.multiply(P, lam, order="F")
        ab += G
        factor, info = dpbtrf(ab, lower=0, overwrite_ab=1)
        if info != 0:  # pragma: no cover - G + lam P is positive definite
            return None, np.nan
        return factor, 2.0 * float(np.sum(np.log(factor[-1])))

    def gcv_fast(self, lam: float, q: np.ndarray, Bty: np.ndarray) -> np.ndarray:
        """GCV score of every column at one lambda, O(n): the trace by a real
        one-sided difference of log-determinants (see the class docstring)."""
        step = _PSPLINE_FD_STEP
        factor, here = self._logdet(lam)
        _, up = self._logdet(lam * math.exp(step))
        if factor is None or not np.isfinite(up):  # pragma: no cover
            return self.gcv(lam, q, Bty.astype(np.complex128))
        edf = self.nb - (up - here) / step
        coef, _ = dpbtrs(factor, Bty, lower=0)
        rss = np.sum((q - self.B @ coef) ** 2, axis=0)
        return self.n * rss / (self.n - edf) ** 2

    def search(self, q: np.ndarray, Bty: np.ndarray):
        """Grid index of the GCV minimum per column, and the scores there."""
        if self.nb > _PSPLINE_FD_MIN:
            return self._search_fast(q, Bty)
        n_cols = q.shape[1]
        last = len(self.grid) - 1
        scores: dict[int, np.ndarray] = {}
        Btyc = Bty.astype(np.complex128)

        def score(i: int) -> np.ndarray:
            if i not in scores:
                scores[i] = self.gcv(float(self.grid[i]), q, Btyc)
            return scores[i]

        step = _PSPLINE_COARSE_STEP
        coarse = sorted(set(range(0, last + 1, step)) | {last})
        table = np.stack([score(i) for i in coarse])
        best = np.empty(n_cols, dtype=int)
        for j in range(n_cols):
            k = coarse[int(np.argmin(table[:, j]))]
            a, b = max(k - step, 0), min(k + step, last)
            while b - a > 3:  # golden-section search over the integers a..b
                m1 = a + int(round(0.382 * (b - a)))
                m2 = a + int(round(0.618 * (b - a)))
                if score(m1)[j] <= score(m2)[j]:
                    b = m2
                else:
                    a = m1
            cand = list(range(a, b + 1)) + [k]
            best[j] = min(cand, key=lambda i: (score(i)[j], i))
        return best, np.array([scores[int(best[j])][j] for j in range(n_cols)])

    def _search_fast(self, q: np.ndarray, Bty: np.ndarray):
        """:meth:`search` for long records, with the fast trace: the coarse scan
        and the golden-section search with :meth:`gcv_fast`; the result is rescored exactly when the fast trace may
        decide it (see the class docstring)."""
        n_cols = q.shape[1]
        last = len(self.grid) - 1
        scores: dict[int, np.ndarray] = {}
        exact: dict[int, np.ndarray] = {}

        def score(i: int) -> np.ndarray:
            if i not in scores:
                scores[i] = self.gcv_fast(float(self.grid[i]), q, Bty)
            return scores[i]

        def exact_score(i: int) -> np.ndarray:
            if i not in exact:
                exact[i] = self.gcv(float(self.grid[i]), q, Bty.astype(np.complex128))
            return exact[i]

        step = _PSPLINE_COARSE_STEP
        coarse = sorted(set(range(0, last + 1, step)) | {last})
        table = np.stack([score(i) for i in coarse])
        best = np.empty(n_cols, dtype=int)
        final = np.empty(n_cols)
        for j in range(n_cols):
            c = int(np.argmin(table[:, j]))
            k = coarse[c]
            a, b = max(k - step, 0), min(k + step, last)
            while b - a > 3:  # golden-section search over the integers a..b
                m1 = a + int(round(0.382 * (b - a)))
                m2 = a + int(round(0.618 * (b - a)))
                if score(m1)[j] <= score(m2)[j]:
                    b = m2
                else:
                    a = m1
            i = min(range(a, b + 1), key=lambda m: (score(m)[j], m))
            near = [m for m in (i - 1, i, i + 1) if 0 <= m <= last]
            values = sorted(score(m)[j] for m in near)
            close = len(values) > 1 and values[1] - values[0] <= 1e-6 * values[0]
            if close or self.grid[i] * self.s_max > _PSPLINE_FD_MAX_COND:
                while True:  # exact descent to a local minimum of the grid
                    m = min(near, key=lambda m: (exact_score(m)[j], m))
                    if m == i:
                        break
                    i = m
                    near = [m for m in (i - 1, i, i + 1) if 0 <= m <= last]
                final[j] = exact_score(i)[j]
            else:
                final[j] = score(i)[j]
            best[j] = i
        return best, final

    def coefficients(self, q: np.ndarray, smoothing=None):
        """Spline coefficients per column; lambda and GCV score per column."""
        n_cols = q.shape[1]
        Bty = np.asarray(self.B.T @ q)
        if smoothing is None:
            best, score = self.search(q, Bty)
            lam = self.grid[best]
        else:
            lam = np.full(n_cols, float(smoothing))
            score = np.full(n_cols, np.nan)
        coef = np.empty_like(Bty)
        for value in np.unique(lam):
            cols = lam == value
            ab = self.G_banded + value * self.P_banded
            coef[:, cols] = solveh_banded(ab, Bty[:, cols], check_finite=False)
        return coef, lam, score

    def evaluate(self, coef: np.ndarray):
        """The spline of the given coefficients and its first two derivatives."""
        spline = BSpline(self.knots, coef, _PSPLINE_DEGREE)
        t = self.times
        return spline(t), spline(t, nu=1), spline(t, nu=2)

    def fit(self, q: np.ndarray, smoothing=None):
        """Fit and its first two derivatives at the times; lambda, GCV per column."""
        coef, lam, score = self.coefficients(q, smoothing)
        return (*self.evaluate(coef), lam, score)


def _difference_coefficients(order: int) -> list[float]:
    """Coefficients of the ``order``-th forward difference, e.g. [-1, 3, -3, 1]."""
    return [float(c) for c in np.diff(np.eye(order + 1), order, axis=0)[0]]


def _upper_banded(A: np.ndarray, bandwidth: int) -> np.ndarray:
    """Upper banded storage of a symmetric matrix, as ``solveh_banded`` reads it."""
    n = A.shape[0]
    ab = np.zeros((bandwidth + 1, n))
    for k in range(bandwidth + 1):
        ab[bandwidth - k, k:] = np.diagonal(A, k)
    return ab


def _pspline(q, t, smoothing=None, cache=None):
    """Quintic P-spline fit with the penalty order chosen per column by GCV.

    Both third- and fourth-difference penalties are fitted (each with its GCV
    lambda) and each column keeps the one with the lower GCV score. With a fixed
    ``smoothing`` the fourth-difference penalty is used. Factorisations are shared
    through ``cache`` between trajectories with the same uniform sampling.
    """
    orders = _PSPLINE_ORDERS if smoothing is None else _PSPLINE_ORDERS[-1:]
    uniform = _is_uniform(t)
    dense = uniform and _pspline_spans(len(t)) + _PSPLINE_DEGREE <= _PSPLINE_DENSE_MAX
    if not dense:
        basis = _BandedBasis(t)
        factors = {m: _BandedPSpline(t, m, basis) for m in orders}
        fits = [factors[m].coefficients(q, smoothing) for m in orders]
        coef = fits[0][0]
        if len(fits) > 1:  # each column keeps the order with the lower GCV score
            best = np.argmin(np.stack([f[2] for f in fits]), axis=0)
            coef = np.stack([f[0] for f in fits])[best, :, np.arange(q.shape[1])].T
        return factors[orders[0]].evaluate(coef)  # same basis for both orders
    # Uniform to _UNIFORM_RTOL (float jitter in the time stamps included): fitted on
    # the unit grid 0, 1, ..., n - 1 (the basis, the penalty and the lambda grid do
    # not depend on the sampling step) and the derivatives scaled by the mean step,
    # so jittered and exact time stamps give the same derivatives (to the relative
    # difference of their mean steps) and every trajectory of n samples shares one
    # factorisation.
    step = (t[-1] - t[0]) / (len(t) - 1)
    factors = None if cache is None else cache.get(len(t))
    if factors is None:
        factors = {m: _PSpline(np.arange(len(t), dtype=float), m) for m in orders}
        if cache is not None:
            cache[len(t)] = factors
    scale = (1.0, 1.0 / step, 1.0 / step**2)
    fits = [factors[m].fit(q, smoothing) for m in orders]
    fits = [tuple(f[k] * scale[k] for k in range(3)) + tuple(f[3:]) for f in fits]
    if len(fits) == 1:
        return fits[0][:3]
    best = np.argmin(np.stack([f[4] for f in fits]), axis=0)  # (n_cols,)
    cols = np.arange(q.shape[1])
    return tuple(np.stack([f[k] for f in fits])[best, :, cols].T for k in range(3))


_PSPLINE_DEGREE = 5
# Largest lambda tried (the banded solve loses accuracy beyond; by then the fit is
# close to the penalty's polynomial limit on any trajectory of up to ~1000 samples).
_PSPLINE_MAX_LOG_LAMBDA = 10.0
# Penalty orders tried (differences of the coefficients): 3 pulls towards quadratics,
# 4 towards cubics. GCV picks per trajectory and coordinate; on the paper's systems
# it chose 4 for most coordinates at sigma = 1e-3 and mixed at 1e-2.
_PSPLINE_ORDERS = (3, 4)
# Uniformly sampled trajectories with up to this many coefficients (about 1190
# samples) use the Demmler-Reinsch eigenbasis (O(n_basis^3) once, shared by all
# trajectories with the same sampling, then every lambda of the grid at once);
# longer or non-uniformly sampled ones the banded O(n) path (_BandedPSpline).
_PSPLINE_DENSE_MAX = 600
# _BandedPSpline's coarse lambda scan: every 20th grid point (2 decades).
_PSPLINE_COARSE_STEP = 20
# Complex step of _BandedPSpline's exact trace (relative to G; error ~ step**2).
_COMPLEX_STEP = 1e-30
# _BandedPSpline scores lambda with the fast real trace (one-sided difference of
# banded Cholesky log-determinants) above this many coefficients (~4000 samples);
# below, every score is exact (complex step).
_PSPLINE_FD_MIN = 2000
# Step in log(lambda) of that one-sided difference: truncation error
# step / 2 * |d tr H / d log lambda| (smooth in lambda, so it barely moves the GCV
# minimum), rounding error ~1e-10 / step.
_PSPLINE_FD_STEP = 1e-5
# Above this lambda * s_max (condition number of G + lambda P, roughly) the fast
# trace loses digits: the final choice is then rescored exactly.
_PSPLINE_FD_MAX_COND = 1e9


# ----------------------------------------------------------------- validation helpers
METHODS = ("pspline", "spline", "savgol", "finite_difference")
# Fewest samples per trajectory each method accepts.
_MIN_SAMPLES = {"pspline": 7, "spline": 5, "savgol": 3, "finite_difference": 3}


def _segments(groups, n: int) -> list[tuple[object, slice]]:
    """Contiguous blocks of equal labels, checking that no label appears twice."""
    if groups is None:
        return [(None, slice(0, n))]
    labels = np.asarray(groups)
    if labels.ndim != 1 or labels.shape[0] != n:
        raise ValueError(
            f"groups must be 1-D with one trajectory label per row ({n} rows), got "
            f"shape {labels.shape}"
        )
    if n == 0:
        return []
    change = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    starts = np.r_[0, change]
    stops = np.r_[change, n]
    seen = {}
    out = []
    for a, b in zip(starts, stops):
        key = labels[a].item() if hasattr(labels[a], "item") else labels[a]
        if key in seen:
            raise ValueError(
                f"the rows of trajectory {key!r} are not contiguous: it occupies "
                f"rows {seen[key][0]}-{seen[key][1] - 1} and again from row {a}. Rows "
                "of one trajectory must be contiguous and in time order; sort them, "
                "e.g. df.sort_values(['trajectory', 't'])."
            )
        seen[key] = (int(a), int(b))
        out.append((key, slice(int(a), int(b))))
    return out


def _angle_mask(angles, n_dof: int, names=None) -> np.ndarray:
    """Boolean mask over the coordinates from indices, names, a mask, or ``"all"``."""
    mask = np.zeros(n_dof, dtype=bool)
    if angles is None:
        return mask
    if isinstance(angles, str):
        if angles == "all":
            return ~mask
        angles = [angles]
    arr = np.asarray(angles)
    if arr.dtype == bool:
        if arr.shape != (n_dof,):
            raise ValueError(
                f"angles as a boolean mask needs one entry per coordinate ({n_dof}), "
                f"got shape {arr.shape}"
            )
        return arr.copy()
    for a in arr.ravel().tolist():
        if isinstance(a, str):
            if names is None or a not in names:
                raise ValueError(
                    f"angles names {a!r}, which is not a coordinate; the coordinates "
                    f"are {list(names) if names is not None else list(range(n_dof))}. "
                    "Pass "
                    "names of position columns, their indices, or a boolean mask."
                )
            mask[list(names).index(a)] = True
        elif isinstance(a, (int, np.integer)) and -n_dof <= a < n_dof:
            mask[a] = True
        else:
            raise ValueError(
                f"angles must hold coordinate indices in [0, {n_dof}) (or names, or "
                f"be a boolean mask), got {a!r}"
            )
    return mask


def _check_times(t, n: int, segments) -> np.ndarray:
    if np.ndim(t) == 0:
        dt = float(t)
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(
                f"t as a sampling interval must be finite and > 0, got {t!r}"
            )
        times = np.empty(n)
        for _, sl in segments:
            times[sl] = dt * np.arange(sl.stop - sl.start)
        return times
    try:
        times = np.asarray(t, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError("t must hold numeric time stamps, one per row") from None
    if times.ndim != 1 or times.shape[0] != n:
        raise ValueError(
            f"t must be 1-D with one time stamp per row ({n} rows), got shape "
            f"{times.shape}"
        )
    bad = np.flatnonzero(~np.isfinite(times))
    if bad.size:
        raise ValueError(
            f"t contains {bad.size} NaN or infinite time stamp(s), the first at row "
            f"{bad[0]}; drop or repair those rows"
        )
    for key, sl in segments:
        steps = np.diff(times[sl])
        wrong = np.flatnonzero(steps <= 0)
        if wrong.size:
            r = sl.start + wrong[0]
            where = "" if key is None else f" (trajectory {key!r})"
            hint = (
                " If several trajectories are stacked, pass groups= (their labels)."
                if key is None
                else ""
            )
            raise ValueError(
                "t must be strictly increasing within each trajectory, but row "
                f"{r + 1}{where} has t = {float(times[r + 1])!r} after "
                f"t = {float(times[r])!r} at row {r}. Rows of one trajectory must be "
                f"contiguous and in time order.{hint}"
            )
    return times


def _is_uniform(t: np.ndarray) -> bool:
    steps = np.diff(t)
    mean = (t[-1] - t[0]) / (len(t) - 1)
    return bool(np.max(np.abs(steps - mean)) <= _UNIFORM_RTOL * mean)


# ----------------------------------------------------------------- gaps and glitches
# A step longer than this many times the median step of its trajectory is a gap.
_GAP_FACTOR = 5.0
# A step shorter than this fraction of the median step is a timing glitch.
_GLITCH_FRACTION = 0.25


def _split_at_gaps(times, segments, factor):
    """Cut segments at gaps; returns (new segments, gaps, glitches).

    ``gaps`` lists ``(key, row, step, median)`` for each step longer than ``factor``
    median steps (the row is the first after the gap); ``glitches`` the rows that
    come less than ``_GLITCH_FRACTION`` median steps after the previous row, in
    trajectories on a regular clock (90 % of the steps within 10 % of the median).
    """
    out, gaps, glitches = [], [], []
    for key, sl in segments:
        steps = np.diff(times[sl])
        if steps.size == 0:
            out.append((key, sl))
            continue
        median = float(np.median(steps))
        # glitches only mean something on a regular clock (most steps near the median)
        if np.mean(np.abs(steps - median) <= 0.1 * median) >= 0.9:
            short = np.flatnonzero(steps < _GLITCH_FRACTION * median)
            glitches.extend((sl.start + 1 + short).tolist())
        if factor is None:
            out.append((key, sl))
            continue
        cut = np.flatnonzero(steps > factor * median)
        if cut.size == 0:
            out.append((key, sl))
            continue
        bounds = [sl.start, *(sl.start + cut + 1).tolist(), sl.stop]
        for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
            out.append(((key, k), slice(a, b)))
        for c in cut:
            gaps.append((key, sl.start + int(c) + 1, float(steps[c]), median))
    return out, gaps, glitches


def _describe_rows(rows, times, limit=5):
    shown = ", ".join(f"{r} (t = {times[r]:.6g})" for r in rows[:limit])
    return shown + (f" and {len(rows) - limit} more" if len(rows) > limit else "")


def _warn_gaps(gaps, times, factor, stacklevel=3):
    rows = [g[1] for g in gaps]
    worst = max(gaps, key=lambda g: g[2] / g[3])
    warnings.warn(
        f"{len(gaps)} gap(s) in the time stamps (a step longer than {factor:g} times "
        f"the trajectory's median step) before row(s) {_describe_rows(rows, times)}; "
        f"the longest is {worst[2]:.4g} s against a median step of {worst[3]:.4g} s. "
        f"Derivatives were estimated on the {len(gaps)} extra segment(s) separately. "
        "Fit with the segments as trajectories, so that the weak form and "
        "cross-validation never span a gap: groups = split_gaps(t, groups) "
        "(lagsindy.differentiation), or derivatives(..., return_groups=True)",
        UserWarning,
        stacklevel=stacklevel,
    )


def _warn_glitches(glitches, times, stacklevel=3):
    warnings.warn(
        f"{len(glitches)} row(s) come less than {_GLITCH_FRACTION:g} median steps after "
        f"the previous row: {_describe_rows(glitches, times)}. Duplicated or "
        "mistimed frames? Their derivatives are kept (the time stamps are used as "
        "given), but check those rows and drop them or repair their time stamps",
        UserWarning,
        stacklevel=stacklevel,
    )


def split_gaps(t, groups=None, *, gap_factor: float = _GAP_FACTOR) -> np.ndarray:
    """Trajectory labels with every trajectory cut at its gaps in time.

    A gap is a time step longer than ``gap_factor`` times the median step of its
    trajectory. Pass the result as ``groups`` to :func:`derivatives`,
    :meth:`LagrangianSINDy.fit <lagsindy.LagrangianSINDy.fit>` and cross-validation,
    so that no estimate (splines, the weak form's integrals) spans a gap.

    Parameters
    ----------
    t : array-like of shape (n_samples,)
        Time stamps, strictly increasing within each trajectory.
    groups : array-like of shape (n_samples,), default=None
        Trajectory labels (rows of a trajectory contiguous); ``None``: one trajectory.
    gap_factor : float, default=5.0
        Steps longer than this many median steps are gaps.

    Returns
    -------
    ndarray of int of shape (n_samples,)
        Segment number of each row, 0, 1, ... in row order (a trajectory without
        gaps keeps one number).

    Examples
    --------
    >>> import numpy as np
    >>> from lagsindy.differentiation import split_gaps
    >>> t = np.r_[np.arange(5), np.arange(10, 14)] * 0.01
    >>> split_gaps(t).tolist()
    [0, 0, 0, 0, 0, 1, 1, 1, 1]
    """
    if not (isinstance(gap_factor, Real) and gap_factor > 1):
        raise ValueError(f"gap_factor must be a number > 1, got {gap_factor!r}")
    n = np.shape(t)[0] if np.ndim(t) else 0
    segments = _segments(groups, n)
    times = _check_times(t, n, segments)
    cut, _, _ = _split_at_gaps(times, segments, gap_factor)
    labels = np.empty(n, dtype=int)
    for k, (_, sl) in enumerate(cut):
        labels[sl] = k
    return labels


def check_weak_form_segments(X, n_dof: int, segments, dt: float) -> None:
    """Refuse trajectories that jump in time, for the weak form (uniform ``dt``).

    The weak form integrates over windows of consecutive rows as if they were
    ``dt`` apart. Where a trajectory has a gap, the positions jump between two rows:
    ``|q[s+1] - q[s]|`` exceeds 4 times ``|dt (qd[s] + qd[s+1]) / 2|`` plus 10 times
    the robust spread of that mismatch (the noise).

    Parameters
    ----------
    X : ndarray of shape (n_samples, >= 2 * n_dof)
        ``[q, q_dot, ...]``.
    n_dof : int
        Number of coordinates.
    segments : list of integer arrays
        Rows of each trajectory, in time order.
    dt : float
        The sampling interval the weak form assumes.

    Raises
    ------
    ValueError
        Naming the trajectory and row of the first jump, and what to do.
    """
    X = np.asarray(X, dtype=float)
    q, qd = X[:, :n_dof], X[:, n_dof : 2 * n_dof]
    for k, rows in enumerate(segments):
        rows = np.asarray(rows).astype(np.intp)
        if rows.size < 3:
            continue
        step = np.diff(q[rows], axis=0)
        expected = dt * (qd[rows][1:] + qd[rows][:-1]) / 2
        mismatch = np.abs(step - expected)
        spread = 1.4826 * np.median(
            np.abs(mismatch - np.median(mismatch, axis=0)), axis=0
        )
        jump = np.abs(step) > 4 * np.abs(expected) + 10 * spread + 1e-12
        if jump.any():
            s = int(np.flatnonzero(jump.any(axis=1))[0])
            raise ValueError(
                "formulation='weak' integrates over consecutive rows as if they were "
                f"dt = {dt:.4g} s apart, but trajectory {k} (rows {rows[0]}-"
                f"{rows[-1]}) jumps between rows {rows[s]} and {rows[s + 1]}: the "
                "positions change far more than the velocities allow, as across a gap "
                "in the time stamps. Cut the trajectories at their gaps and pass the "
                "segments as groups (groups = lagsindy.differentiation.split_gaps(t, "
                "groups), or derivatives(..., return_groups=True)), or fit with "
                "formulation='strong'"
            )


# ----------------------------------------------------------------- public function
def derivatives(
    q,
    t,
    *,
    groups=None,
    method: str = "pspline",
    window: int = 11,
    polyorder: int = 4,
    smoothing: float | None = None,
    angles=None,
    gap_factor: float | None = _GAP_FACTOR,
    return_groups: bool = False,
):
    """Estimate ``[q, q_dot, q_ddot]`` from sampled positions, trajectory by trajectory.

    Parameters
    ----------
    q : array-like of shape (n_samples, n_dof) or (n_samples,)
        Measured positions; several trajectories may be stacked (see ``groups``).
    t : array-like of shape (n_samples,) or float
        Time of each row, strictly increasing within a trajectory (it may restart at
        each trajectory); spacing may be non-uniform. A float is a uniform sampling
        interval: each trajectory then starts at 0 with that step.
    groups : array-like of shape (n_samples,), default=None
        Trajectory label of each row (any hashable labels, as for scikit-learn's
        ``GroupKFold``). Rows of one trajectory must be contiguous and in time order.
        Derivatives never use samples of another trajectory. ``None``: one trajectory.
    method : {"pspline", "spline", "savgol", "finite_difference"}, default="pspline"
        ``"pspline"``: quintic penalized spline, smoothing chosen by generalized
        cross-validation (GCV) per trajectory and coordinate; needs no tuning and was
        the most accurate method on the paper's systems at every noise level
        measured (see the module docstring).
        ``"spline"``: scipy's cubic smoothing spline
        (:func:`scipy.interpolate.make_smoothing_spline`, GCV); its second derivative
        is piecewise linear and zero at both ends of each trajectory (natural
        spline), and it is slow (a Python loop inside scipy).
        ``"savgol"``: Savitzky-Golay local polynomials (``window``, ``polyorder``).
        ``"finite_difference"``: second-order central differences, one-sided at the
        ends; no smoothing (noise in q is amplified by about ``1/dt**2`` in q_ddot).
    window : int, default=11
        Savitzky-Golay window length in samples (odd, >= 3). A trajectory shorter
        than the window uses the longest odd window it holds, with ``polyorder``
        lowered below it if needed (a ``UserWarning`` says so).
    polyorder : int, default=4
        Savitzky-Golay polynomial degree (>= 2, so that q_ddot is estimated).
    smoothing : float, default=None
        Fixed smoothing parameter lambda instead of GCV (``None``, recommended). For
        ``"pspline"`` it weighs the sum of squared 4th differences of the B-spline
        coefficients against the sum of squared residuals; for ``"spline"`` it is
        scipy's ``lam``. Ignored by the other methods.
    angles : list of int, boolean mask of shape (n_dof,), or "all", default=None
        Angular coordinates (radians). They are unwrapped with :func:`numpy.unwrap`
        per trajectory before differentiating, so a jump from pi to -pi is read as
        continued rotation; the returned positions of these coordinates are the
        unwrapped (continuous) angles, not reduced to (-pi, pi].
    gap_factor : float or None, default=5.0
        A time step longer than ``gap_factor`` times the median step of its
        trajectory is a gap: the trajectory is cut there and each segment is
        differentiated on its own (nothing is interpolated across a gap), with one
        ``UserWarning`` saying where. Fit with the segments as trajectories
        (``return_groups=True`` or :func:`split_gaps`). ``None``: no gap detection.
        Rows less than a quarter of the median step after the previous one
        (duplicated or mistimed frames) are reported by a ``UserWarning`` naming
        them.
    return_groups : bool, default=False
        Also return the segment labels (see :func:`split_gaps`).

    Returns
    -------
    X : ndarray of shape (n_samples, 3 * n_dof)
        Columns ``[q..., q_dot..., q_ddot...]``, rows in the input order. The first
        block is the smoothed fit of q for the smoothing methods and q itself
        (unwrapped) for ``"finite_difference"``.
    groups : ndarray of int of shape (n_samples,)
        Only with ``return_groups=True``: the segment number of each row (the
        trajectories cut at their gaps), to pass as ``groups`` to ``fit``.

    Raises
    ------
    ValueError
        If q or t contain NaN or infinite values, t is not strictly increasing
        within a trajectory, a trajectory's rows are not contiguous, a trajectory
        is shorter than the method needs (7 samples for ``"pspline"``, 5 for
        ``"spline"``, 3 otherwise), or a parameter is invalid.

    See Also
    --------
    Derivatives : the same as a scikit-learn transformer.

    Notes
    -----
    Non-uniform time stamps are used directly by every method, with no resampling:
    finite differences use the exact non-uniform stencil weights (the interior
    second derivative is then first order where consecutive steps differ); the
    splines are fitted at the given times; Savitzky-Golay fits its local polynomial
    by least squares at the given times (on a uniform grid this is exactly
    :func:`scipy.signal.savgol_filter`, which is then used).

    Examples
    --------
    >>> import numpy as np
    >>> from lagsindy.differentiation import derivatives
    >>> t = np.linspace(0, 2, 201)
    >>> X = derivatives(np.sin(3 * t), t, method="pspline")
    >>> X.shape
    (201, 3)
    >>> bool(np.max(np.abs(X[:, 2] + 9 * np.sin(3 * t))) < 1e-2)
    True
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    try:
        q = np.asarray(q, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError("q must hold numeric positions (n_samples, n_dof)") from None
    if q.ndim == 1:
        q = q[:, None]
    if q.ndim != 2:
        raise ValueError(f"q must be 2-D (n_samples, n_dof), got shape {q.shape}")
    n, n_dof = q.shape
    bad = np.argwhere(~np.isfinite(q))
    if bad.size:
        raise ValueError(
            f"q contains {len(bad)} NaN or infinite value(s), the first at row "
            f"{bad[0][0]}, column {bad[0][1]}; drop or interpolate those rows first"
        )
    if method == "savgol":
        _check_savgol_params(window, polyorder)
    if smoothing is not None and not (
        isinstance(smoothing, (int, float, np.floating, np.integer))
        and math.isfinite(smoothing)
        and smoothing >= 0
    ):
        raise ValueError(
            f"smoothing must be None (GCV) or a float >= 0, got {smoothing!r}"
        )
    mask = _angle_mask(angles, n_dof)
    if gap_factor is not None and not (isinstance(gap_factor, Real) and gap_factor > 1):
        raise ValueError(f"gap_factor must be a number > 1 or None, got {gap_factor!r}")
    segments = _segments(groups, n)
    times = _check_times(t, n, segments)
    segments, gaps, glitches = _split_at_gaps(times, segments, gap_factor)
    if gaps:
        _warn_gaps(gaps, times, gap_factor)
    if glitches:
        _warn_glitches(glitches, times)
    need = _MIN_SAMPLES[method]
    for key, sl in segments:
        if sl.stop - sl.start < need:
            if isinstance(key, tuple):
                where = (
                    f"segment {key[1]} of "
                    + ("the data" if key[0] is None else f"trajectory {key[0]!r}")
                    + " (between gaps in t) has"
                )
            else:
                where = "the data have" if key is None else f"trajectory {key!r} has"
            raise ValueError(
                f"method={method!r} needs at least {need} samples per trajectory, but "
                f"{where} {sl.stop - sl.start}; use a method that needs fewer "
                "(finite_difference needs 3) or drop the short trajectory"
            )
    out = np.empty((n, 3 * n_dof))
    shortened = []
    cache = {}
    # The per-trajectory problems are small: BLAS threads only add overhead (and
    # stall badly when cores are shared), so run them single-threaded.
    with _blas_controller().limit(limits=1, user_api="blas"):
        for key, sl in segments:
            qs = q[sl].copy()
            if mask.any():
                qs[:, mask] = np.unwrap(qs[:, mask], axis=0)
            ts = times[sl]
            if method == "finite_difference":
                parts = _finite_difference(qs, ts)
            elif method == "savgol":
                m = sl.stop - sl.start
                w = window if window <= m else m - (1 - m % 2)
                p = min(polyorder, w - 1)
                if w != window:
                    shortened.append((key, m))
                parts = _savgol(qs, ts, w, p, _is_uniform(ts))
            elif method == "spline":
                parts = _cubic_spline(qs, ts, smoothing)
            else:
                parts = _pspline(qs, ts, smoothing, cache)
            out[sl] = np.concatenate(parts, axis=1)
    if shortened:
        warnings.warn(
            f"{len(shortened)} trajectory(ies) are shorter than window={window} (the "
            f"shortest has {min(m for _, m in shortened)} samples); they used the "
            "longest odd window they hold, so their derivatives are less smoothed",
            UserWarning,
            stacklevel=2,
        )
    if return_groups:
        labels = np.empty(n, dtype=int)
        for k, (_, sl) in enumerate(segments):
            labels[sl] = k
        return out, labels
    return out


def _blas_controller() -> ThreadpoolController:
    """One threadpoolctl controller per process (finding the libraries takes ms)."""
    global _CONTROLLER
    if _CONTROLLER is None:
        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER


_CONTROLLER = None


def _check_savgol_params(window, polyorder):
    if not isinstance(window, (int, np.integer)) or window < 3 or window % 2 == 0:
        raise ValueError(f"window must be an odd integer >= 3, got {window!r}")
    if not isinstance(polyorder, (int, np.integer)) or polyorder < 2:
        raise ValueError(
            f"polyorder must be an integer >= 2 (q_ddot needs a quadratic), got "
            f"{polyorder!r}"
        )
    if polyorder >= window:
        raise ValueError(
            f"polyorder must be less than window, got polyorder={polyorder}, "
            f"window={window}"
        )


# ----------------------------------------------------------------- transformer
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
