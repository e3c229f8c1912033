"""Library bagging (Ensemble-SINDy) for large candidate libraries."""

from __future__ import annotations

import math
import warnings
from numbers import Integral, Real

import numpy as np
from joblib import Parallel, delayed
from sklearn.base import BaseEstimator, MetaEstimatorMixin, RegressorMixin, clone
from sklearn.utils import check_random_state
from sklearn.utils.validation import check_is_fitted

from .. import pipeline
from .._params import cache_param_names
from .._validation import validate_state
from ..estimator import LagrangianSINDy
from ..formulation.probes import without_probes
from ..library import CandidateLibrary

__all__ = ["LibraryBaggingLagrangianSINDy"]


@cache_param_names
class LibraryBaggingLagrangianSINDy(MetaEstimatorMixin, RegressorMixin, BaseEstimator):
    """Library bagging (Ensemble-SINDy) for large candidate libraries.

    Each of ``n_estimators`` fits sees a random subset of the Lagrangian candidate
    terms (the dissipation library, the ``fixed_term`` and ``unpenalized`` terms are
    always offered). A term's inclusion is the fraction of the fits that offered it
    and kept it. Terms whose inclusion exceeds ``inclusion_threshold`` form the final
    library, on which the base estimator is refitted.

    Parameters
    ----------
    estimator : LagrangianSINDy, default=None
        The base configuration; its ``library`` is the full candidate set. ``None``:
        ``LagrangianSINDy()``.
    n_estimators : int, default=50
    max_terms : int or float, default=0.5
        Terms offered to each fit: an integer count, or a fraction of the library.
    inclusion_threshold : float, default=0.5
    random_state : int, RandomState instance or None, default=None
    n_jobs : int, default=None
        Parallel fits (joblib).
    verbose : int, default=0

    Attributes
    ----------
    estimator_ : LagrangianSINDy
        The refit on the kept terms.
    library_ : CandidateLibrary
        The full candidate library (built).
    inclusion_ : ndarray of shape (n_terms,)
        Per term of ``library_``; NaN for a term never offered.
    n_offered_ : ndarray of shape (n_terms,)
        Fits that offered each term.
    kept_ : ndarray of bool, shape (n_terms,)
    coef_ : ndarray of shape (n_terms,)
        Final coefficients over ``library_``'s terms.
    lagrangian_ : sympy.Expr
    n_failed_ : int
        Bagged fits that raised (left out).

    References
    ----------
    U. Fasel, J. N. Kutz, B. W. Brunton and S. L. Brunton, "Ensemble-SINDy: Robust
    sparse model discovery in the low-data, high-noise limit, with active learning
    and control", Proc. R. Soc. A 478, 2022.
    """

    def __init__(
        self,
        estimator=None,
        *,
        n_estimators=50,
        max_terms=0.5,
        inclusion_threshold=0.5,
        random_state=None,
        n_jobs=None,
        verbose=0,
    ):
        self.estimator = estimator
        self.n_estimators = n_estimators
        self.max_terms = max_terms
        self.inclusion_threshold = inclusion_threshold
        self.random_state = random_state
        self.n_jobs = n_jobs
        self.verbose = verbose

    def _base(self):
        if self.estimator is not None:
            return clone(self.estimator)
        return LagrangianSINDy()

    def fit(self, X, y=None, groups=None):
        """Fit the bagged ensemble, then the base estimator on the kept terms.

        Parameters
        ----------
        X : array-like or DataFrame of shape (n_samples, 3 * n_dof)
        y : array-like of shape (n_samples, n_dof), default=None
        groups : array-like of shape (n_samples,), default=None

        Returns
        -------
        self
        """
        if not (isinstance(self.n_estimators, Integral) and self.n_estimators >= 1):
            raise ValueError(
                f"n_estimators must be a positive integer, got {self.n_estimators!r}"
            )
        if not 0 <= self.inclusion_threshold < 1:
            raise ValueError(
                f"inclusion_threshold must be in [0, 1), got {self.inclusion_threshold!r}"
            )
        base = self._base()
        lib_coords = None if base.library is None else base.library.coordinates
        if isinstance(lib_coords, str):
            lib_coords = [lib_coords]
        Xa, _, coordinates = validate_state(
            clone(base), X, reset=True, coordinates=lib_coords
        )
        library = pipeline.build_library(base.library, coordinates, Xa.shape[0])
        self.library_ = library
        terms = list(library.terms_)
        n_terms = len(terms)
        if isinstance(self.max_terms, Integral):
            k = int(self.max_terms)
        elif isinstance(self.max_terms, Real) and 0 < self.max_terms <= 1:
            k = int(math.ceil(self.max_terms * n_terms))
        else:
            raise ValueError(
                f"max_terms must be a positive integer or a fraction in (0, 1], got "
                f"{self.max_terms!r}"
            )
        always = set()
        fixed = base.fixed_term
        if fixed is not None and not (isinstance(fixed, str) and fixed == "mass"):
            always.add(library.index(fixed))
        for t in base.unpenalized if base.unpenalized is not None else []:
            try:
                always.add(library.index(t))
            except (ValueError, TypeError):
                pass  # a dissipation term: always offered anyway
        k = min(max(k, 1), n_terms)
        rng = check_random_state(self.random_state)
        pool = np.array([j for j in range(n_terms) if j not in always])
        subsets = []
        for _ in range(self.n_estimators):
            pick = rng.choice(
                pool, size=min(max(k - len(always), 0), len(pool)), replace=False
            )
            subsets.append(np.sort(np.concatenate([sorted(always), pick]).astype(int)))

        def one(subset):
            lib = CandidateLibrary.from_terms(
                library.coordinates_,
                [terms[j] for j in subset],
                remove_trivial=False,
                remove_dependent=False,
            )
            with warnings.catch_warnings(), without_probes():
                warnings.simplefilter("ignore")
                try:
                    est = clone(base).set_params(library=lib).fit(X, y, groups=groups)
                except (ValueError, FloatingPointError, RuntimeError):
                    return None
            return est.coef_ != 0

        if self.verbose:
            print(
                f"[lagsindy] library bagging: {self.n_estimators} fits of {k} of "
                f"{n_terms} terms"
            )
        kept_lists = Parallel(n_jobs=self.n_jobs, verbose=max(0, self.verbose - 1))(
            delayed(one)(s) for s in subsets
        )
        offered = np.zeros(n_terms)
        chosen = np.zeros(n_terms)
        failed = 0
        for subset, kept in zip(subsets, kept_lists):
            if kept is None:
                failed += 1
                continue
            offered[subset] += 1
            chosen[subset[kept]] += 1
        self.n_failed_ = failed
        if failed == len(subsets):
            raise ValueError(
                "every bagged fit failed; check that the base estimator fits the full "
                "library, or offer more terms per fit (max_terms)"
            )
        if failed:
            warnings.warn(
                f"{failed} of {len(subsets)} bagged fits failed and are left out",
                UserWarning,
                stacklevel=2,
            )
        with np.errstate(invalid="ignore", divide="ignore"):
            self.inclusion_ = np.where(
                offered > 0, chosen / np.maximum(offered, 1), np.nan
            )
        self.n_offered_ = offered
        kept = np.nan_to_num(self.inclusion_, nan=0.0) > self.inclusion_threshold
        kept[list(always)] = True
        if not kept.any():
            raise ValueError(
                f"no term has inclusion above {self.inclusion_threshold}; lower "
                "inclusion_threshold"
            )
        self.kept_ = kept
        final = CandidateLibrary.from_terms(
            library.coordinates_,
            [terms[j] for j in np.flatnonzero(kept)],
            remove_trivial=False,
            remove_dependent=False,
        )
        self.estimator_ = clone(base).set_params(library=final).fit(X, y, groups=groups)
        coef = np.zeros(n_terms)
        coef[np.flatnonzero(kept)] = self.estimator_.coef_
        self.coef_ = coef
        self.lagrangian_ = self.estimator_.lagrangian_
        self.term_names_ = library.get_feature_names_out()
        self.n_features_in_ = self.estimator_.n_features_in_
        return self

    def __sklearn_is_fitted__(self):
        return "estimator_" in self.__dict__

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.target_tags.required = False
        return tags

    def predict(self, X):
        """Generalized forces of the refitted model (see ``LagrangianSINDy.predict``)."""
        check_is_fitted(self)
        return self.estimator_.predict(X)

    def predict_acceleration(self, X, tau=None):
        """Accelerations of the refitted model."""
        check_is_fitted(self)
        return self.estimator_.predict_acceleration(X, tau)

    def score(self, X, y=None, sample_weight=None):
        """R^2 of the refitted model (see ``LagrangianSINDy.score``)."""
        check_is_fitted(self)
        return self.estimator_.score(X, y, sample_weight=sample_weight)

    def equation(self, precision: int = 4) -> str:
        """The refitted Lagrangian as text (see ``LagrangianSINDy.equation``)."""
        check_is_fitted(self)
        return self.estimator_.equation(precision)
