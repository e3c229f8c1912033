"""Formulations as objects: data in, Gram statistics out.

A formulation turns samples ``X = [q, q_dot, q_ddot]`` (and forces ``tau``) into the
per-coordinate Gram statistics of the Euler-Lagrange regression, the one input of
every solve (:func:`lagsindy.pipeline.solve`):

* :class:`StrongForm`: the paper's pointwise residual (needs accelerations);
* :class:`WeakForm`: the equations integrated against test functions over windows of
  each trajectory (no accelerations; noise averaged, its bias corrected);
* :class:`AutoForm`: the weak form when the rows are time-ordered trajectories long
  enough, else the strong form with a warning that says why.

Each has two methods:

``statistics(operator, X, tau, groups)``
    the statistics of all rows, as a list of functions returning
    :class:`GramStatistics` (one per test-function window the weak form tries with
    ``window="auto"``; the others return one), so a window never tried costs nothing;
``trajectory_statistics(operator, X, tau, groups)``
    the same statistics kept apart per trajectory (:class:`TrajectoryStatistics`),
    so that the statistics of any set of trajectories (a fold, a bootstrap resample)
    are a weighted sum of them.

A new formulation is one class with these two methods (and ``name``); the estimator,
the bootstrap and the diagnosis call them and nothing else.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from numbers import Integral

import numpy as np
import torch
from sklearn.base import BaseEstimator

from .._params import cache_param_names
from .._stacklevel import outside_stacklevel
from .weak import trajectory_segments, weak_gram, window_stride

__all__ = [
    "AutoForm",
    "GramStatistics",
    "StrongForm",
    "TrajectoryStatistics",
    "WeakForm",
    "make_formulation",
]


@dataclass
class GramStatistics:
    """Per-coordinate Gram statistics of one fit and how they were made.

    Attributes
    ----------
    gram : Tensor of shape (n_dof, P, P)
        ``A_i^T A_i`` over the candidate columns followed by the target (tau).
    n_rows : int
        Samples (strong form) or windows (weak form) behind ``gram``.
    formulation : {"strong", "weak"}
    dt : float or None
        Sampling interval of the weak form.
    noise_cov : ndarray or None
        Noise covariance subtracted by the weak form (its Gram is then a corrected
        one and is projected onto the positive semi-definite cone when balanced).
    window : int or None
        Samples per test function of the weak form.
    probe_gram : Tensor of shape (n_dof, P + n_probes, P + n_probes) or None
        The Gram statistics with probe forces before the target (see
        :mod:`~lagsindy.formulation.probes`); ``gram`` is this without them.
    probe_names : tuple of str
        The probe forces' names.
    """

    gram: torch.Tensor
    n_rows: int
    formulation: str
    dt: float | None = None
    noise_cov: np.ndarray | None = None
    window: int | None = None
    probe_gram: torch.Tensor | None = None
    probe_names: tuple = ()

    @property
    def corrected(self) -> bool:
        return self.noise_cov is not None


@dataclass
class TrajectoryStatistics:
    """Gram statistics kept apart per trajectory (what folds and resamples sum).

    Attributes
    ----------
    grams : Tensor of shape (n_trajectories, n_dof, P, P)
        Uncorrected statistics of each trajectory.
    noise : Tensor of shape (n_trajectories, n_dof, P, P) or None
        The weak form's noise part of each trajectory (summed over every sample),
        subtracted by :meth:`total`; ``None`` without a noise correction.
    n_rows : ndarray of int, shape (n_trajectories,)
        Samples or windows of each trajectory.
    rows : list of ndarray
        The rows of ``X`` each trajectory holds.
    formulation, dt, noise_cov, window
        As in :class:`GramStatistics`.
    """

    grams: torch.Tensor
    noise: torch.Tensor | None
    n_rows: np.ndarray
    rows: list
    formulation: str
    dt: float | None = None
    noise_cov: np.ndarray | None = None
    window: int | None = None

    def __len__(self) -> int:
        return int(self.grams.shape[0])

    def total(self, weights=None, *, corrected: bool = True) -> GramStatistics:
        """The statistics of the trajectories taken ``weights[k]`` times each.

        Parameters
        ----------
        weights : array-like of shape (n_trajectories,), default=None
            Multiplicities (a bootstrap resample) or 0/1 (a fold); ``None``: all once.
        corrected : bool, default=True
            Subtract the noise part (the weak form's errors-in-variables
            correction); ``False`` gives the raw statistics.
        """
        w = np.ones(len(self)) if weights is None else np.asarray(weights, float)
        wt = torch.as_tensor(w, dtype=self.grams.dtype, device=self.grams.device)
        gram = torch.einsum("k,kipq->ipq", wt, self.grams)
        use_noise = corrected and self.noise is not None
        if use_noise:
            gram = gram - torch.einsum("k,kipq->ipq", wt, self.noise)
        return GramStatistics(
            gram,
            int(round(float(np.dot(w, self.n_rows)))),
            self.formulation,
            self.dt,
            self.noise_cov if use_noise else None,
            self.window,
        )


def _check_groups(groups, n):
    if groups is not None and len(groups) != n:
        raise ValueError(
            f"groups must have one label per row of X ({n}), got {len(groups)}"
        )


@cache_param_names
class StrongForm(BaseEstimator):
    """The pointwise Euler-Lagrange residual (the paper's formulation).

    Each sample gives one equation per coordinate,
    :math:`\\Theta(q, \\dot q, \\ddot q) c = \\tau`; rows are independent samples
    (any order), so measured or estimated accelerations are needed and their noise
    enters the regressors (biased under noise).
    """

    name = "strong"

    def statistics(self, operator, X, tau=None, groups=None, *, extra=None) -> list:
        """Statistics of every row, as a list of one function (see the module)."""
        _check_groups(groups, X.shape[0])
        stats = GramStatistics(operator.gram(X, tau, extra=extra), X.shape[0], "strong")
        return [lambda: stats]

    def trajectory_statistics(
        self, operator, X, tau=None, groups=None, *, extra=None
    ) -> TrajectoryStatistics:
        """Statistics per trajectory (``groups`` labels; ``None``: every row one
        trajectory of its own is not useful, so all rows form one)."""
        _check_groups(groups, X.shape[0])
        labels = np.zeros(X.shape[0]) if groups is None else np.asarray(groups)
        rows = group_rows(labels)
        # Columns once for all rows (one compiled evaluation), then one Gram each.
        width = operator.n_columns + (0 if extra is None else extra.shape[2])
        width += 0 if tau is None else 1
        grams = X.new_zeros((len(rows), operator.n_dof, width, width))
        for k, r in enumerate(rows):
            idx = torch.as_tensor(r, device=X.device)
            grams[k] = operator.gram(
                X[idx],
                None if tau is None else tau[idx],
                extra=None if extra is None else extra[idx],
            )
        counts = np.asarray([len(r) for r in rows], dtype=np.int64)
        return TrajectoryStatistics(grams, None, counts, rows, "strong")


def group_rows(labels) -> list:
    """Row indices of each label, labels in order of first appearance."""
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    order = np.argsort(first)
    return [np.flatnonzero(inverse.ravel() == k) for k in order]


@cache_param_names
class WeakForm(BaseEstimator):
    r"""The Euler-Lagrange equations integrated against test functions (weak form).

    Multiplying the equations by a smooth test function supported on a window of
    each trajectory and integrating by parts removes the accelerations; noise is
    averaged over the window and its first-order bias on the Gram statistics is
    subtracted (an errors-in-variables correction).

    Parameters
    ----------
    window : int or "auto", default="auto"
        Samples per test function (windows start every ``window // 4``).
        ``"auto"``: 81, or 161, 321, 641 when the longer window changes the
        coefficients by over 3 % and the next one confirms it (smoothed derivatives
        bias short windows); else 81 with a :class:`WindowWarning`.
    dt : float, default=None
        Sampling interval; ``None`` estimates it from
        ``q[s+1] - q[s] = dt (qd[s] + qd[s+1]) / 2``.
    noise_cov : "auto", array-like of shape (2 * n_dof, 2 * n_dof) or None, default="auto"
        Covariance of white noise on ``[q, qd]`` whose effect on the Gram matrix is
        subtracted; ``"auto"`` estimates it from fourth-order differences of the
        data; ``None`` applies no correction.

    Notes
    -----
    Rows must be time-ordered trajectories (pass ``groups``; without it, one record
    split where the positions jump).
    """

    name = "weak"

    def __init__(self, window="auto", dt=None, noise_cov="auto"):
        self.window = window
        self.dt = dt
        self.noise_cov = noise_cov

    def statistics(self, operator, X, tau=None, groups=None, *, extra=None) -> list:
        """Statistics of every row, one function per window tried (see the module)."""
        grams, dt, cov = weak_gram(
            operator,
            X,
            tau,
            groups,
            window=self.window,
            dt=self.dt,
            noise_cov=self.noise_cov,
            extra=extra,
        )
        return [_LazyWeak(build, dt, cov, w) for w, build in grams]

    def trajectory_statistics(
        self, operator, X, tau=None, groups=None, *, extra=None, dts=None
    ):
        """Statistics per trajectory: each trajectory's time-ordered segments (split
        where they jump) at least ``window`` samples long, summed per trajectory.

        ``window`` must be a number of samples and ``dt`` given here (use the values a
        fit chose: ``WeakForm(window=est.window_, dt=est.dt_,
        noise_cov=est.noise_cov_)``); the noise part is summed over every sample.
        ``dts``: several sampling intervals at once (the integrands are evaluated
        once): a list of :class:`TrajectoryStatistics`, one per value.
        """
        if not isinstance(self.window, Integral) or self.dt is None:
            raise ValueError(
                "trajectory_statistics needs a fixed window (samples) and dt: use "
                "the ones a fit chose (est.window_, est.dt_)"
            )
        window, dt, d = int(self.window), float(self.dt), operator.n_dof
        labels = np.zeros(X.shape[0]) if groups is None else np.asarray(groups)
        _check_groups(labels, X.shape[0])
        rows = group_rows(labels)
        segments, owner = [], []
        for k, r in enumerate(rows):
            idx = torch.as_tensor(r, device=X.device)
            for s in trajectory_segments(X[idx], d, np.zeros(len(r))):
                if len(s) >= window:
                    segments.append(idx[s])
                    owner.append(k)
        if not segments:
            raise ValueError(
                f"no trajectory is as long as the window ({window} samples)"
            )
        cov = None
        if self.noise_cov is not None and not isinstance(self.noise_cov, str):
            cov = torch.as_tensor(self.noise_cov, dtype=X.dtype, device=X.device)
        build = operator.weak_grams(
            X,
            tau,
            {window: segments},
            strides={window: window_stride(window)},
            dt=dt,
            noise_cov=cov,
            extra=extra,
            per_segment=True,
            return_noise=True,
            lazy=True,
        )[window]
        own = torch.as_tensor(owner, device=X.device)
        out = []
        for value in [dt] if dts is None else dts:
            gram, noise, n_win = build(dt=float(value))
            grams = gram.new_zeros((len(rows), *gram.shape[1:]))
            grams.index_add_(0, own, gram)
            noise_t = None
            if cov is not None:
                noise_t = torch.zeros_like(grams)
                noise_t.index_add_(0, own, noise)
            n_rows = np.bincount(np.asarray(owner), weights=n_win, minlength=len(rows))
            out.append(
                TrajectoryStatistics(
                    grams,
                    noise_t,
                    n_rows.astype(np.int64),
                    rows,
                    "weak",
                    float(value),
                    None if cov is None else cov.detach().cpu().numpy(),
                    window,
                )
            )
        return out[0] if dts is None else out


class _LazyWeak:
    """One window's weak statistics, summed when called."""

    def __init__(self, build, dt, cov, window):
        self.build, self.dt, self.cov, self.window = build, dt, cov, window

    def __call__(self) -> GramStatistics:
        gram, n_rows = self.build()
        return GramStatistics(gram, n_rows, "weak", self.dt, self.cov, self.window)


@cache_param_names
class AutoForm(WeakForm):
    """The weak form where it can run, else the strong form with a warning.

    The weak form needs time-ordered trajectories at least ``window`` samples long;
    when the rows are not that, the strong form (biased under noise) is used and a
    warning says why and what to pass instead.
    """

    name = "auto"

    def statistics(self, operator, X, tau=None, groups=None, *, extra=None) -> list:
        try:
            return super().statistics(operator, X, tau, groups, extra=extra)
        except ValueError as exc:
            self.warn_fallback(exc)
        return StrongForm().statistics(operator, X, tau, groups, extra=extra)

    @staticmethod
    def warn_fallback(why):
        """Say that the fit falls back to the strong form, and ``why`` (pointing at
        the user's line that called the fit)."""
        warnings.warn(
            "formulation='auto' fell back to the strong form, which is biased "
            f"when the data are noisy, because the weak form cannot run: {why}. "
            "Pass time-ordered trajectories (groups=trajectory labels, dt=) to "
            "get the weak form, or formulation='strong' to silence this.",
            UserWarning,
            stacklevel=outside_stacklevel(),
        )


_BY_NAME = {"strong": StrongForm, "weak": WeakForm, "auto": AutoForm}


def make_formulation(formulation, *, window="auto", dt=None, noise_cov="auto"):
    """The formulation object for a name (``"auto"``, ``"strong"``, ``"weak"``) and
    the weak form's settings, or ``formulation`` itself when it is an object."""
    if not isinstance(formulation, str):
        return formulation
    if formulation not in _BY_NAME:
        raise ValueError(
            f"formulation must be one of {sorted(_BY_NAME)} or a formulation object, "
            f"got {formulation!r}"
        )
    if formulation == "strong":
        return StrongForm()
    return _BY_NAME[formulation](window=window, dt=dt, noise_cov=noise_cov)


def with_window(formulation, window, dt=None):
    """A copy of a weak formulation with a fixed ``window`` (and ``dt``), as a
    fit chose them; any other formulation as it is."""
    if not isinstance(formulation, WeakForm):
        return formulation
    params = dict(formulation.get_params(), window=int(window))
    if dt is not None:
        params["dt"] = float(dt)
    return type(formulation)(**params)
