"""The :class:`LagrangianSINDy` estimator (scikit-learn API), a facade.

``fit`` reads as the data flow of :mod:`lagsindy.pipeline` (data validated, library
and dissipation built, Gram statistics of the formulation, the case solved, a
:class:`~lagsindy.model.FittedLagrangian` kept, whose fields become the fitted
attributes); its parameters are checked against :mod:`lagsindy.settings`. Prediction,
scoring and simulation delegate to the fitted state.
"""

from __future__ import annotations

import numpy as np
from sklearn.base import BaseEstimator, RegressorMixin, _fit_context, clone
from sklearn.metrics import r2_score
from sklearn.utils.validation import check_is_fitted

from . import _validation as val
from . import joint, partitioned, pipeline, settings
from ._params import cache_param_names
from ._torch import resolve_device, resolve_dtype, to_tensor
from .export.methods import ModelUseMixin
from .formulation.clocked import rows_on_even_clock
from .formulation.scaling import IdentifiabilityWarning  # noqa: F401 - 0.1 path
from .io.model_file import read_model_file, write_model_file
from .model import FittedLagrangian, MassCheck, mass_matrix_check  # noqa: F401


class LagrangianSINDy(ModelUseMixin, RegressorMixin, BaseEstimator):
    r"""Sparse identification of a Lagrangian from trajectories (xL-SINDy).

    The Lagrangian is sought as :math:`L = \sum_k c_k \phi_k(q, \dot q)` over the
    candidate terms of ``library``. The Euler-Lagrange equations make the
    generalized forces linear in :math:`c`: :math:`\tau = \Theta(q, \dot q, \ddot q)
    c`. The coefficients minimise, in scaled variables :math:`w`,

    .. math::

        \frac{1}{2n}\|y - \Theta w\|_2^2 + \lambda \|w\|_1

    by FISTA in stages: after each stage the terms below a relative threshold are
    removed and :math:`\lambda` lowered, and the final support is refitted without
    penalty (the schedule's settings: ``solver``, a
    :class:`~lagsindy.solvers.StagedFISTA`).

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
    solver : StagedFISTA, default=None
        Settings of the staged sparse solve: hard thresholds of Lagrangian and
        dissipation terms, stages, iterations, tolerances, debiasing; see
        :class:`lagsindy.solvers.StagedFISTA`. ``None``: its defaults. Grid searches
        reach them as ``solver__threshold`` and so on.
    fixed_term : str, sympy.Expr, "mass" or None, default=None
        How passive data (case III) fix the Lagrangian's arbitrary scale: a term known
        to be in the Lagrangian (e.g. ``"theta_dot**2"``) gets coefficient 1, as in
        the paper; ``"mass"`` fixes the data mean of the trace of the learned mass
        matrix (no prior knowledge; it cannot collapse to a Lagrangian that vanishes
        where the data lie); ``None`` tries both and keeps the model that best
        predicts the measured accelerations (``fixed_term_``, ``normalization_``).
    unpenalized : list of str, default=None
        Terms known to be present (Lagrangian terms, or dissipation names such as
        ``"viscous(theta)"``): they are not shrunk and never thresholded.
    case : {"auto", "forces", "fixed", "acceleration"}, default="auto"
        ``"auto"``: case I when ``tau`` is given, else case III.
    formulation : {"auto", "strong", "weak"} or formulation object, default="auto"
        ``"strong"``: the paper's pointwise residual (needs accelerations);
        ``"weak"``: the equations integrated against test functions over windows of
        each time-ordered trajectory (no accelerations; noise averaged, its bias
        corrected); ``"auto"``: weak where it can run, else strong with a warning.
        Case II always uses the strong form. Objects and their settings (``window``,
        ``dt``, ``noise_cov``): :mod:`lagsindy.formulation` (``WeakForm``).
    normalize : bool, default=True
        Balance row (per coordinate) and column scales; see
        :class:`lagsindy.formulation.BalancedGram`.
    device : str, default="cpu"
        Torch device for the Euler-Lagrange tensors (``"cuda"`` where available).
    dtype : {"float64", "float32"}, default="float64"
    random_state : int, RandomState instance or None, default=None
        Seeds the row subsamples of large data (case III's ranking of fixed terms
        above 4000 rows, case II above 20000); ``None``: evenly spaced rows, so fits
        are deterministic and never use numpy's global random state.
    verbose : int, default=0
        Print stage progress when positive.
    threshold, dissipation_threshold, lam_decay, step_growth : deprecated
    max_stages, max_iter, tol, solver_tol, debias : deprecated
        Use ``solver=StagedFISTA(...)``; set, they warn (``FutureWarning``) and work.
    window, dt, noise_cov : deprecated
        Use ``formulation=WeakForm(...)`` (or ``AutoForm``); set, they warn.

    Attributes
    ----------
    coef_, support_ : ndarray of shape (n_terms,)
        Coefficients over ``library_``'s terms (zero where pruned); the kept ones.
    lagrangian_ : sympy.Expr
        The learned Lagrangian with numeric coefficients; ``model_``, a
        :class:`MechanicalModel`, gives its equations of motion and simulation.
    dissipation_coef_, dissipation_terms_, dissipation_removed_ : ndarray, list
        The coefficients of the dissipation candidates
        (:class:`~lagsindy.dissipation.ForceTerm`), the candidates, and those
        removed as duplicates of a Lagrangian column. ``dissipation_``: the learned
        part, ``{"D": Rayleigh function, "forces": [force per coordinate]}``.
    library_, coordinates_, n_dof_, term_names_
        The fitted copy of the library, its coordinates, their number, term names.
    case_, fixed_term_, normalization_
        ``"forces"`` (I), ``"fixed"`` (III) or ``"acceleration"`` (II); in case III
        the term whose coefficient is 1 and how the scale was fixed (``"term"``,
        ``"mass"``).
    formulation_, window_, dt_, noise_cov_
        The formulation used (``"strong"`` or ``"weak"``: the choice of ``"auto"``),
        the weak form's window (the choice of ``window="auto"``), sampling interval
        and subtracted noise covariance (``None``: none or negligible).
    n_iter_, stages_, residual_
        FISTA iterations over all stages, the sparsification path (a list of
        :class:`lagsindy.solvers.Stage`), the final relative residual (with forces:
        warns above 0.5).
    mass_check_ : MassCheck
        The learned mass matrix checked on (up to 500 of) the fitted samples:
        ``mass_check_.fraction`` of them have it singular or indefinite, along
        ``mass_check_.coordinates``; ``mass_check_.ok`` is False (and the fit warns)
        above 1 %; with forces, also where it is negative definite (``.negative``).
    fitted_ : lagsindy.model.FittedLagrangian
        The fitted state these attributes come from (what a model file stores).
    n_features_in_, feature_names_in_
        The number of columns of X; their names when X was a DataFrame.

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
    >>> from lagsindy import LagrangianSINDy
    >>> from lagsindy.systems import single_pendulum, make_dataset
    >>> data = make_dataset(single_pendulum(), n_trajectories=5, duration=2.0,
    ...                     excitation="paper", random_state=0)
    >>> est = LagrangianSINDy(single_pendulum().paper_library()).fit(data.X, data.tau)
    >>> print(est.equation(precision=3))
    L = 0.5*theta_dot**2 + 9.81*cos(theta)
    """

    _parameter_constraints: dict = settings.PARAMETER_CONSTRAINTS

    def __init__(
        self,
        library=None,
        *,
        dissipation=None,
        lam=1e-3,
        alpha=None,
        solver=None,
        fixed_term=None,
        unpenalized=None,
        case="auto",
        formulation="auto",
        normalize=True,
        device="cpu",
        dtype="float64",
        random_state=None,
        verbose=0,
        threshold=settings.DEPRECATED,
        dissipation_threshold=settings.DEPRECATED,
        lam_decay=settings.DEPRECATED,
        step_growth=settings.DEPRECATED,
        max_stages=settings.DEPRECATED,
        max_iter=settings.DEPRECATED,
        tol=settings.DEPRECATED,
        solver_tol=settings.DEPRECATED,
        debias=settings.DEPRECATED,
        window=settings.DEPRECATED,
        dt=settings.DEPRECATED,
        noise_cov=settings.DEPRECATED,
    ):
        self.library = library
        self.dissipation = dissipation
        self.lam = lam
        self.alpha = alpha
        self.solver = solver
        self.fixed_term = fixed_term
        self.unpenalized = unpenalized
        self.case = case
        self.formulation = formulation
        self.normalize = normalize
        self.device = device
        self.dtype = dtype
        self.random_state = random_state
        self.verbose = verbose
        given = locals()  # the deprecated flat settings, stored as given
        for name in settings.DEPRECATED_FLAT:
            setattr(self, name, given[name])

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
    def fit(self, X, y=None, groups=None, t=None):
        """Fit the Lagrangian to trajectories.

        Parameters
        ----------
        X : array-like or DataFrame of shape (n_samples, 3 * n_dof), or partitioned data
            Rows ``[q..., q_dot..., q_ddot...]``. DataFrame columns are matched by
            name (``theta``, ``theta_dot``, ``theta_ddot``). A Dask DataFrame or
            array, a Parquet path or an iterable of chunks is fitted partition by
            partition (:mod:`lagsindy.partitioned`; ``y`` and ``groups`` then name
            the force and trajectory columns).
        y : array-like of shape (n_samples, n_dof) or (n_samples,), default=None
            Generalized forces tau (case I). ``None`` for passive data. A coordinate
            that is never driven (an undriven link) has a column of zeros.
        groups : array-like of shape (n_samples,), default=None
            Trajectory label of each row; used by the weak formulation only (the
            strong form treats rows independently). Without it, trajectories are split
            where the positions jump. In a grid search, route it with scikit-learn's
            metadata routing (``est.set_fit_request(groups=True)``).
        t : array-like of shape (n_samples,) or CleanedClock, default=None
            Time of each row (or the ``CleanedClock`` of ``derivatives(...,
            return_clock=True)``). Rows within 3 samples of a segment's end are left
            out (``clock_`` counts them); on an uneven clock the weak form's rows
            are put on an even clock per gap-free segment (``to_even_clock``; ``dt``
            unless given: its step). ``bootstrap`` and ``diagnose`` need the same
            ``t=``. ``None``: rows are taken as evenly spaced, every row fitted.

        Returns
        -------
        self : LagrangianSINDy
        """
        # A refit starts from scratch: a failed fit leaves the estimator unfitted.
        for name in [k for k in vars(self) if k.endswith("_") and not k.endswith("__")]:
            delattr(self, name)
        params = self.get_params(deep=False)
        settings.warn_deprecated(params)
        if partitioned.is_partitioned(X):  # Dask, Parquet, chunks: map-reduce
            fitted, names = partitioned.fit_state(params, X, y, groups)
            self.n_features_in_ = 3 * fitted.n_dof
            if names is not None:
                self.feature_names_in_ = np.asarray(names, dtype=object)
            return self._publish(fitted)
        device, dtype = resolve_device(self.device), resolve_dtype(self.dtype)
        Xa, tau, setup = self._setup(X, y, params)
        formulation = pipeline.formulation_of(params, setup.case)
        clock = None
        if t is not None:
            Xa, tau, groups, formulation, clock = rows_on_even_clock(
                formulation, Xa, tau, groups, t, verbose=self.verbose
            )
        Xt = to_tensor(Xa, dtype=dtype, device=device)
        tau_1d = tau is not None and np.asarray(y).ndim == 1
        fitted = joint.fit(
            setup,
            params,
            formulation,
            Xt,
            tau,
            groups,
            tau_1d=tau_1d,
            verbose=self.verbose,
        )
        fitted.clock = clock  # what the time stamps changed (None: no t)
        return self._publish(fitted)

    def _setup(self, X, y, params):
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
            ``feature_names_in`` sets ``feature_names_in_``. Flat settings (a
            file's ``threshold``, ``window``) become ``solver``/``formulation``.

        Returns
        -------
        LagrangianSINDy
        """
        params = dict(params)
        feature_names_in = params.pop("feature_names_in", None)
        params.pop("library", None)  # the fitted state's
        dissipation = params.pop("dissipation", None)
        if dissipation is None:
            dissipation = fitted.candidates()
        est = cls(clone(fitted.library), **settings.checked_params(params))
        est.n_features_in_ = 3 * fitted.n_dof
        if feature_names_in is not None:
            est.feature_names_in_ = np.asarray(feature_names_in, dtype=object)
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


# (set outside the class body: one line, not a step of the fit)
cache_param_names(LagrangianSINDy)
