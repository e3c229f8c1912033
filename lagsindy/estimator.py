"""The :class:`LagrangianSINDy` estimator (scikit-learn API), a facade over the pipeline.

``fit`` reads as the data flow: validate the data (:mod:`lagsindy._validation`),
build the library and the dissipation candidates, compute the Gram statistics in the
chosen formulation (:mod:`lagsindy.formulation`), balance them, solve the case
(:mod:`lagsindy.cases`) and keep the result as a
:class:`~lagsindy.model.FittedLagrangian`, whose fields become the fitted attributes.
Prediction, scoring and simulation delegate to that state.
"""

from __future__ import annotations

from numbers import Integral, Real

import numpy as np
import sympy as sp
import torch
from sklearn.base import BaseEstimator, RegressorMixin, _fit_context, clone
from sklearn.metrics import r2_score
from sklearn.utils._param_validation import HasMethods, Interval, StrOptions
from sklearn.utils.validation import check_is_fitted

from . import _validation as val
from . import pipeline
from ._params import cache_param_names
from ._torch import resolve_device, resolve_dtype, to_tensor
from .dissipation import library_of
from .export import export_model, linearize, to_casadi
from .formulation.scaling import IdentifiabilityWarning  # noqa: F401 - 0.1 path
from .io.model_file import read_model_file, write_model_file
from .joint import JointDissipation
from .model import (  # noqa: F401 - MassCheck, mass_matrix_check: their 0.1 path
    FittedLagrangian,
    MassCheck,
    mass_matrix_check,
)

_CASES = {"auto", "forces", "fixed", "acceleration"}

_PARAMETER_CONSTRAINTS = {
    "library": [HasMethods(["build", "get_feature_names_out"]), None],
    "dissipation": [HasMethods(["build"]), None],
    "lam": [Interval(Real, 0, None, closed="left")],
    "alpha": [Interval(Real, 0, None, closed="neither"), None],
    "threshold": [Interval(Real, 0, 1, closed="left")],
    "dissipation_threshold": [Interval(Real, 0, 1, closed="left")],
    "lam_decay": [Interval(Real, 1, None, closed="left")],
    "step_growth": [Interval(Real, 0, None, closed="neither")],
    "max_stages": [Interval(Integral, 1, None, closed="left")],
    "max_iter": [Interval(Integral, 1, None, closed="left")],
    "tol": [Interval(Real, 0, None, closed="left")],
    "solver_tol": [Interval(Real, 0, None, closed="neither")],
    "fixed_term": [str, sp.Basic, None],
    "unpenalized": ["array-like", None],
    "case": [StrOptions(_CASES)],
    "formulation": [StrOptions({"auto", "strong", "weak"}), HasMethods(["statistics"])],
    "window": [Interval(Integral, 5, None, closed="left"), StrOptions({"auto"})],
    "dt": [Interval(Real, 0, None, closed="neither"), None],
    "noise_cov": [StrOptions({"auto"}), "array-like", None],
    "normalize": ["boolean"],
    "debias": ["boolean"],
    "device": [str, torch.device],
    "dtype": [StrOptions({"float64", "float32"})],
    "random_state": ["random_state"],
    "verbose": ["verbose"],
}


class LagrangianSINDy(RegressorMixin, BaseEstimator):
    r"""Sparse identification of a Lagrangian from trajectories (xL-SINDy).

    The Lagrangian is sought as :math:`L = \sum_k c_k \phi_k(q, \dot q)` over the
    candidate terms of ``library``. The Euler-Lagrange equations make the
    generalized forces linear in :math:`c`: :math:`\tau = \Theta(q, \dot q, \ddot q)
    c`. The coefficients minimise, in scaled variables :math:`w`,

    .. math::

        \frac{1}{2n}\|y - \Theta w\|_2^2 + \lambda \|w\|_1

    by FISTA in stages: after each stage terms below a relative ``threshold`` are
    removed, :math:`\lambda` is divided by ``lam_decay`` and the step raised, until
    the relative residual is below ``tol`` or ``max_stages`` have run; the final
    support is refitted without penalty (``debias``).

    Three cases, as in the paper:

    * ``fit(X, tau)``: case I, :math:`y = \tau` (external forces known);
    * ``fit(X)`` with ``fixed_term``: case III, one known term's coefficient is
      fixed to 1 and :math:`y = -\Theta_{fixed}`; without ``fixed_term`` every
      candidate is tried as the fixed term and the one whose model best predicts the
      measured accelerations is kept (``fixed_term_``);
    * ``case="acceleration"``: case II (passive data, no prior), non-convex,
      started from case III's search (:mod:`lagsindy.cases.acceleration`).

    Parameters
    ----------
    library : CandidateLibrary, default=None
        Candidate terms. ``None``: ``CandidateLibrary.polynomial(degree=2,
        angles="all", raw_angles=True)`` over the data's coordinates (the paper's
        single pendulum library, generalized). Its coordinates, when ``None``, are
        taken from the DataFrame columns (or named ``q0, q1, ...``).
    dissipation : DissipationLibrary, default=None
        Candidate non-conservative forces (Rayleigh dissipation, Coulomb friction,
        offsets) fitted together with the Lagrangian in one sparse regression; see
        :mod:`lagsindy.dissipation`. Its coordinates default to the library's.
    lam : float, default=1e-3
        The paper's :math:`\lambda`: L1 weight of the first stage, on the scaled
        problem (columns and target of unit mean square, so ``lam`` is unit-free and
        ``lam >= 1`` zeroes every coefficient). It plays the role of
        :class:`sklearn.linear_model.Lasso`'s ``alpha``.
    alpha : float, default=None
        The paper's step size. ``None``: ``1/L`` from the Lipschitz constant of the
        current stage (the largest safe step; it rises by itself as terms leave).
        A given ``alpha`` is multiplied by ``step_growth`` at each stage, as in the
        paper; a step that makes FISTA diverge is halved automatically.
    threshold : float, default=0.05
        Hard threshold between stages, relative to the largest scaled coefficient: a
        term contributing less than ``threshold`` times the dominant term is dropped;
        a link 100 times lighter than the rest needs e.g. 1e-3 (a fit with forces
        warns when a coordinate's accelerations are then predicted poorly).
    dissipation_threshold : float, default=1e-3
        The hard threshold for dissipation terms. Friction and damping forces are
        usually a few percent of the conservative ones, so they get a lower threshold;
        with noisy data prefer :func:`lagsindy.diagnose`, which adds an effect only when
        it improves held-out predictions.
    lam_decay : float, default=10.0
        Division of ``lam`` between stages.
    step_growth : float, default=2.0
        Multiplication of a given ``alpha`` between stages.
    max_stages : int, default=5
    max_iter : int, default=20000
        FISTA iterations per stage.
    tol : float, default=1e-3
        Stop the stages when the relative residual
        :math:`\|y - \Theta w\|^2 / \|y\|^2` is at most ``tol``.
    solver_tol : float, default=1e-7
        KKT tolerance of each FISTA stage (scaled problem).
    fixed_term : str, sympy.Expr, "mass" or None, default=None
        How passive data (case III) fix the Lagrangian's arbitrary scale. A term
        known to be in the Lagrangian (e.g. ``"theta_dot**2"``): its coefficient is
        fixed to 1, as in the paper. ``"mass"``: the data mean of the trace of the
        learned mass matrix is fixed instead (one convex problem, no prior
        knowledge; it cannot collapse to a Lagrangian that vanishes where the data
        lie, which fixing one coefficient can). ``None``: try the mass normalization
        and every candidate term, keep the model that best predicts the measured
        accelerations (``fixed_term_``, ``normalization_``).
    unpenalized : list of str, default=None
        Terms known to be present (Lagrangian terms, or dissipation names such as
        ``"viscous(theta)"``): they are not shrunk and never thresholded.
    case : {"auto", "forces", "fixed", "acceleration"}, default="auto"
        ``"auto"``: case I when ``tau`` is given, else case III.
    formulation : {"auto", "strong", "weak"}, default="auto"
        ``"strong"``: the paper's pointwise Euler-Lagrange residual (needs
        accelerations). ``"weak"``: the equations integrated against smooth test
        functions over windows of ``window`` samples (no accelerations; noise is
        averaged and its bias corrected); rows must be time-ordered trajectories
        (pass ``groups`` to ``fit``; without it, one record split where the positions
        jump). Cases I and III. ``"auto"``: the weak form whenever the rows are
        time-ordered trajectories long enough, else the strong form with a warning
        saying why (``formulation_``); case II always uses the strong form.
    window : int or "auto", default="auto"
        Samples per test function of the weak form (windows start every
        ``window // 4``). ``"auto"``: 81, or 161, 321, 641 when the longer window
        changes the coefficients by over 3 % and the next one confirms it (smoothed
        derivatives bias short windows); else 81 with a :class:`WindowWarning`.
    dt : float, default=None
        Sampling interval for the weak formulation; ``None`` estimates it from
        ``q[s+1] - q[s] = dt (qd[s] + qd[s+1]) / 2`` (``dt_``).
    noise_cov : "auto", array-like of shape (2 * n_dof, 2 * n_dof) or None, default="auto"
        Weak formulation only: covariance of white noise on ``[q, qd]`` whose effect on
        the Gram matrix is subtracted (errors-in-variables correction of the
        attenuation bias). ``"auto"`` estimates it from fourth-order differences of the
        data (``noise_cov_``); ``None`` applies no correction.
    normalize : bool, default=True
        Balance row (per coordinate) and column scales; see
        :class:`lagsindy.formulation.BalancedGram`.
    debias : bool, default=True
        Refit the final support without penalty (removes L1 shrinkage).
    device : str, default="cpu"
        Torch device for the Euler-Lagrange tensors (``"cuda"`` where available).
    dtype : {"float64", "float32"}, default="float64"
    random_state : int, RandomState instance or None, default=None
        Seeds the row subsamples drawn when the data are large: the rows used to
        rank candidate fixed terms in case III (above 4000 rows) and the rows of
        case II (above 20000 rows). ``None``: evenly spaced rows, so the fit is
        deterministic and never uses numpy's global random state. Fits are
        otherwise deterministic.
    verbose : int, default=0
        Print stage progress when positive.

    Attributes
    ----------
    coef_ : ndarray of shape (n_terms,)
        Coefficients over ``library_``'s terms (zero where pruned).
    dissipation_coef_ : ndarray of shape (n_dissipation_terms,)
        Coefficients of ``dissipation_terms_`` (empty without ``dissipation``).
    dissipation_terms_ : list of lagsindy.dissipation.ForceTerm
        The dissipation candidates (after removing those that duplicate a
        Lagrangian column, listed in ``dissipation_removed_``).
    dissipation_ : dict
        The learned non-conservative part: ``{"D": Rayleigh function (sympy),
        "forces": [direct generalized force per coordinate (sympy)]}``.
    support_ : ndarray of bool, shape (n_terms,)
    lagrangian_ : sympy.Expr
        The learned Lagrangian with numeric coefficients.
    model_ : MechanicalModel
        The learned model (equations of motion, simulation).
    library_ : CandidateLibrary
        The fitted copy of the library.
    coordinates_ : list of str
    n_dof_ : int
    term_names_ : ndarray of str
    fixed_term_ : str or None
        The term whose coefficient is 1 in the reported scale (passive data).
    normalization_ : {"term", "mass"} or None
        How the scale was fixed in case III.
    case_ : str
        ``"forces"`` (I), ``"fixed"`` (III) or ``"acceleration"`` (II).
    n_iter_ : int
        FISTA iterations over all stages.
    stages_ : list of lagsindy.solvers.Stage
        The sparsification path.
    residual_ : float
        Relative residual of the final fit (with forces: warns above 0.5).
    formulation_ : {"strong", "weak"}
        The formulation used (the choice of ``formulation="auto"``).
    window_ : int
        The weak form's window (the choice of ``window="auto"``).
    mass_check_ : MassCheck
        The learned mass matrix checked on (up to 500 of) the fitted samples:
        ``mass_check_.fraction`` of them have it singular or indefinite, along
        ``mass_check_.coordinates``; ``mass_check_.ok`` is False (and the fit warns)
        above 1 %; with forces, also where it is negative definite (``.negative``).
    dt_ : float or None
        Sampling interval used by the weak formulation.
    noise_cov_ : ndarray or None
        Noise covariance subtracted by the weak form (``None``: none or negligible).
    fitted_ : lagsindy.model.FittedLagrangian
        The fitted state these attributes come from (what a model file stores).
    n_features_in_ : int
    feature_names_in_ : ndarray of str
        Only when X was a DataFrame.

    See Also
    --------
    CandidateLibrary : candidate terms.
    MechanicalModel : equations of motion and simulation.

    References
    ----------
    A. Purnomo and M. Hayashibe, "Sparse identification of Lagrangian for nonlinear
    dynamical systems via proximal gradient method", 2023.

    Examples
    --------
    >>> import numpy as np
    >>> from lagsindy import LagrangianSINDy, CandidateLibrary
    >>> from lagsindy.systems import single_pendulum, make_dataset
    >>> data = make_dataset(single_pendulum(), n_trajectories=5, duration=2.0,
    ...                     excitation="paper", random_state=0)
    >>> est = LagrangianSINDy(single_pendulum().paper_library()).fit(data.X, data.tau)
    >>> print(est.equation(precision=3))
    L = 0.5*theta_dot**2 + 9.81*cos(theta)
    """

    _parameter_constraints: dict = _PARAMETER_CONSTRAINTS

    def __init__(
        self,
        library=None,
        *,
        dissipation=None,
        lam=1e-3,
        alpha=None,
        threshold=0.05,
        dissipation_threshold=1e-3,
        lam_decay=10.0,
        step_growth=2.0,
        max_stages=5,
        max_iter=20_000,
        tol=1e-3,
        solver_tol=1e-7,
        fixed_term=None,
        unpenalized=None,
        case="auto",
        formulation="auto",
        window="auto",
        dt=None,
        noise_cov="auto",
        normalize=True,
        debias=True,
        device="cpu",
        dtype="float64",
        random_state=None,
        verbose=0,
    ):
        self.library = library
        self.dissipation = dissipation
        self.lam = lam
        self.alpha = alpha
        self.threshold = threshold
        self.dissipation_threshold = dissipation_threshold
        self.lam_decay = lam_decay
        self.step_growth = step_growth
        self.max_stages = max_stages
        self.max_iter = max_iter
        self.tol = tol
        self.solver_tol = solver_tol
        self.fixed_term = fixed_term
        self.unpenalized = unpenalized
        self.case = case
        self.formulation = formulation
        self.window = window
        self.dt = dt
        self.noise_cov = noise_cov
        self.normalize = normalize
        self.debias = debias
        self.device = device
        self.dtype = dtype
        self.random_state = random_state
        self.verbose = verbose

    def __sklearn_is_fitted__(self):
        # model_ is set last in fit: a fit that raised leaves the estimator unfitted.
        return "model_" in self.__dict__

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.target_tags.required = False
        tags.target_tags.multi_output = True
        tags.target_tags.single_output = True
        return tags

    # ------------------------------------------------------------------ fit
    @_fit_context(prefer_skip_nested_validation=True)
    def fit(self, X, y=None, groups=None):
        """Fit the Lagrangian to trajectories.

        Parameters
        ----------
        X : array-like or DataFrame of shape (n_samples, 3 * n_dof)
            Rows ``[q..., q_dot..., q_ddot...]``. DataFrame columns are matched by
            name (``theta``, ``theta_dot``, ``theta_ddot``).
        y : array-like of shape (n_samples, n_dof) or (n_samples,), default=None
            Generalized forces tau (case I). ``None`` for passive data. A coordinate
            that is never driven (an undriven link) has a column of zeros.
        groups : array-like of shape (n_samples,), default=None
            Trajectory label of each row; used by the weak formulation only (the
            strong form treats rows independently). Without it, trajectories are split
            where the positions jump. In a grid search, route it with scikit-learn's
            metadata routing (``est.set_fit_request(groups=True)``).

        Returns
        -------
        self : LagrangianSINDy
        """
        # A refit starts from scratch: a failed fit leaves the estimator unfitted.
        for name in [k for k in vars(self) if k.endswith("_") and not k.endswith("__")]:
            delattr(self, name)
        device, dtype = resolve_device(self.device), resolve_dtype(self.dtype)
        Xa, tau, setup = self._setup(X, y)
        Xt = to_tensor(Xa, dtype=dtype, device=device)
        tau_t = None if tau is None else to_tensor(tau, dtype=dtype, device=device)
        formulation = pipeline.formulation_of(self.get_params(deep=False), setup.case)
        tau_1d = tau is not None and np.asarray(y).ndim == 1
        # dissipation dominating the conservative fit: refit jointly (lagsindy.joint)
        joint = JointDissipation(setup, self.get_params(deep=False))
        with joint.watch():
            ladder = pipeline.fit_statistics(formulation, setup, Xt, tau_t, groups)
            stats, solution = pipeline.solve_ladder(
                ladder, setup, Xt, tau, verbose=self.verbose
            )
            fitted = pipeline.fitted_state(setup, stats, solution, tau_1d=tau_1d)
            pipeline.check_fit(fitted, setup, stats, solution, Xt, tau)
        fitted = joint.result(
            fitted, stats, solution, formulation, Xt, tau_t, tau, groups,
            verbose=self.verbose, tau_1d=tau_1d,
        )  # fmt: skip
        return self._publish(fitted)

    def _setup(self, X, y):
        """Validated data and the :class:`~lagsindy.pipeline.FitSetup` of a fit."""
        coordinates = None if self.library is None else self.library.coordinates
        if isinstance(coordinates, str):
            coordinates = [coordinates]
        Xa, tau, coordinates = val.validate_state(
            self, X, reset=True, y=y, coordinates=coordinates
        )
        val.check_motion(Xa, coordinates)
        library = pipeline.build_library(self.library, coordinates, Xa.shape[0])
        case = pipeline.resolve_case(self.case, tau)
        dissipation = pipeline.build_dissipation(self.dissipation, library)
        params = self.get_params(deep=False)
        return Xa, tau, pipeline.make_setup(params, library, dissipation, case)

    @classmethod
    def from_fitted(cls, fitted: FittedLagrangian, **params):
        """A fitted estimator from a fitted state and hyperparameters.

        What :func:`lagsindy.io.load_model` and :func:`lagsindy.refine` use to turn a
        :class:`~lagsindy.model.FittedLagrangian` into an estimator that predicts,
        scores and simulates like the one it came from.

        Parameters
        ----------
        fitted : FittedLagrangian
        **params
            Hyperparameters (``lam``, ``fixed_term``, ...; ``get_params()`` of
            another estimator works); the library is the fitted state's, the
            dissipation library (unless given) the one its terms come from;
            ``feature_names_in`` sets ``feature_names_in_``.

        Returns
        -------
        LagrangianSINDy
        """
        params = dict(params)
        feature_names_in = params.pop("feature_names_in", None)
        params.pop("library", None)  # the fitted state's
        dissipation = params.pop("dissipation", None)
        est = _with_params(cls, fitted.library, params)
        est.n_features_in_ = 3 * fitted.n_dof
        if feature_names_in is not None:
            est.feature_names_in_ = np.asarray(feature_names_in, dtype=object)
        if dissipation is None and fitted.dissipation_terms:
            dissipation = fitted.dissipation_library or library_of(
                fitted.dissipation_terms, fitted.coordinates
            )
        if dissipation is not None:
            est.set_params(dissipation=clone(dissipation))
        return est._publish(fitted)

    def _publish(self, fitted: FittedLagrangian):
        """Expose the fitted state as the fitted attributes (``model_`` last)."""
        attributes = fitted.attributes()
        model = attributes.pop("model_")
        for name, value in attributes.items():
            setattr(self, name, value)
        self.fitted_ = fitted
        self._y_1d = fitted.tau_1d
        self.model_ = model
        return self

    # ------------------------------------------------------------------ predict
    def _prepare_predict(self, X):
        check_is_fitted(self)
        Xa, _, _ = val.validate_state(
            self, X, reset=False, coordinates=self.coordinates_
        )
        device, dtype = resolve_device(self.device), resolve_dtype(self.dtype)
        return Xa, to_tensor(Xa, dtype=dtype, device=device)

    def predict(self, X):
        """Generalized forces implied by the learned model (inverse dynamics).

        Parameters
        ----------
        X : array-like or DataFrame of shape (n_samples, 3 * n_dof)

        Returns
        -------
        ndarray of shape (n_samples, n_dof), or (n_samples,) when the model was fit
        with a 1-D tau. When ``X`` is a DataFrame: a DataFrame with X's index and
        columns ``tau_<coordinate>`` (a Series for a 1-D tau).
        """
        _, Xt = self._prepare_predict(X)
        out = self.fitted_.forces(Xt)
        out = out[:, 0] if self._y_1d else out
        return val.as_frame(out, X, [f"tau_{c}" for c in self.coordinates_])

    def predict_acceleration(self, X, tau=None):
        """Accelerations predicted by the learned model's forward dynamics.

        ``qdd = M(c)^+ (tau - h(c))`` with the pseudo-inverse of the learned mass
        matrix (paper eq. 10); the measured accelerations in ``X`` are not used.

        Parameters
        ----------
        X : array-like or DataFrame of shape (n_samples, 3 * n_dof)
        tau : array-like of shape (n_samples, n_dof), default=None
            Generalized forces; ``None`` for passive data. A DataFrame with columns
            ``tau_<coordinate>`` is matched by name.

        Returns
        -------
        ndarray of shape (n_samples, n_dof). When ``X`` is a DataFrame: a DataFrame
        with X's index and columns ``<coordinate>_ddot``.
        """
        Xa, Xt = self._prepare_predict(X)
        if tau is not None:
            tau = val.validate_tau(tau, Xa.shape[0], self.n_dof_, self.coordinates_)
        out = self.fitted_.accelerations(Xt, tau)
        return val.as_frame(out, X, [f"{c}_ddot" for c in self.coordinates_])

    def score(self, X, y=None, sample_weight=None):
        """R^2 of the model: of forces when ``y`` (tau) is given, else of accelerations.

        With ``y``: :math:`R^2` of :meth:`predict` against ``y``. Without: passive
        data, whose true forces are all zero, so the :math:`R^2` of the accelerations
        from :meth:`predict_acceleration` against the measured ``qddot`` in ``X`` is
        used (invariant to the Lagrangian's scale, so it ranks case III models).
        Outputs are variance weighted, so a coordinate that is never driven (zero
        force) does not count.

        Parameters
        ----------
        X : array-like or DataFrame of shape (n_samples, 3 * n_dof)
        y : array-like of shape (n_samples, n_dof), default=None
        sample_weight : array-like of shape (n_samples,), default=None

        Returns
        -------
        float
        """
        if y is None:
            Xa, Xt = self._prepare_predict(X)
            true, pred = Xa[:, 2 * self.n_dof_ :], self.fitted_.accelerations(Xt)
        else:
            pred = np.asarray(self.predict(X))
            true = val.validate_tau(y, pred.shape[0], self.n_dof_, self.coordinates_)
            true = true.reshape(pred.shape)
        weighted = "variance_weighted"
        return float(
            r2_score(true, pred, sample_weight=sample_weight, multioutput=weighted)
        )

    # ------------------------------------------------------------------ model
    def simulate(self, x0, t, tau=None, **kwargs):
        """Integrate the learned equations of motion (see :meth:`MechanicalModel.simulate`)."""
        check_is_fitted(self)
        if not np.any(self.coef_):
            raise ValueError(
                "the learned Lagrangian is zero (every term was thresholded away), so "
                "it has no equations of motion to integrate; refit with a lower lam or "
                "threshold"
            )
        return self.model_.simulate(x0, t, tau, **kwargs)

    def equation(self, precision: int = 4) -> str:
        """The learned Lagrangian as readable text, e.g. ``L = 0.5*theta_dot**2 + ...``."""
        check_is_fitted(self)
        return self.model_.equation(precision)

    def coef_table(self):
        """The coefficients as a table, one row per library term.

        Returns
        -------
        pandas.DataFrame
            Columns ``term`` (str), ``kind`` (``"lagrangian"`` or ``"dissipation"``),
            ``coefficient`` (float, 0 where pruned) and ``kept`` (bool: the term is in
            the learned model).
        """
        check_is_fitted(self)
        return self.fitted_.coef_table()

    # ------------------------------------------------------------------ use
    def export(self, path, format=None, *, input_matrix=None):
        """Write the model as standalone Python or C code (no lagsindy needed).

        See :func:`lagsindy.export.export_model`.
        """
        return export_model(self, path, format, input_matrix=input_matrix)

    def to_casadi(self, input_matrix=None):
        """CasADi functions of the model (see :func:`lagsindy.export.to_casadi`)."""
        return to_casadi(self, input_matrix)

    def linearize(self, x_eq, u_eq=None, dt=None, *, input_matrix=None):
        """A, B (and the discrete pair given ``dt``) at an equilibrium (see
        :func:`lagsindy.export.linearize`)."""
        return linearize(self, x_eq, u_eq, dt, input_matrix=input_matrix)

    def save(self, path):
        """Write the fitted model as a JSON file that is safe to share.

        See :func:`lagsindy.io.save_model`; read it back with :meth:`load`.
        Returns the :class:`pathlib.Path` written.
        """
        return write_model_file(self, path)

    @classmethod
    def load(cls, path):
        """Load a model written by :meth:`save` (no pickle; nothing is evaluated).

        See :func:`lagsindy.io.load_model`. Returns a fitted estimator that predicts
        like the saved one.
        """
        params, fitted, names = read_model_file(path)
        try:
            return cls.from_fitted(fitted, feature_names_in=names, **params)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None


def _with_params(cls, library, params):
    """``cls(library, **params)``, the parameters checked (they may come from a
    file written by another version)."""
    from sklearn.utils._param_validation import InvalidParameterError

    known = set(cls().get_params(deep=False)) - {"library", "dissipation"}
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(
            f"unknown hyperparameters {unknown[:5]} (a model file from a newer "
            "lagsindy version?)"
        )
    try:
        est = cls(clone(library), **params)
        est._validate_params()
    except (InvalidParameterError, TypeError) as exc:
        raise ValueError(f"the hyperparameters are not valid: {exc}") from None
    return est


# (set outside the class body: one line, not a step of the fit)
cache_param_names(LagrangianSINDy)
