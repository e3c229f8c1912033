"""Parameter names of the package's scikit-learn estimators, read once per class."""

from __future__ import annotations

from sklearn.base import BaseEstimator


def _param_names(cls) -> list:
    """The parameter names of ``cls``, read once per class (its ``_get_param_names``).

    scikit-learn reads them from ``inspect.signature(__init__)`` on every
    ``get_params`` (0.3-0.5 ms); a fit, ``clone`` and the parameter validation call
    it many times (``diagnose``: about 80, most of them on the libraries). A
    subclass reads its own.
    """
    names = cls.__dict__.get("_param_names")
    if names is None:
        names = BaseEstimator._get_param_names.__func__(cls)
        cls._param_names = names
    return list(names)


def cache_param_names(cls):
    """Give ``cls`` (a scikit-learn estimator) the cached :func:`_param_names`."""
    cls._get_param_names = classmethod(_param_names)
    return cls
