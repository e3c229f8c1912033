"""Saved models (JSON, safe to share) and loaders for measured data.

* :mod:`~lagsindy.io.model_file`: the model document (format, validation, parsing)
  and its conversion to and from a :class:`~lagsindy.model.FittedLagrangian`;
* :mod:`~lagsindy.io.datasets`: the MultiArm pendulum recordings that ship with
  lagsindy.

:func:`save_model` and :func:`load_model` are the entry points. The model document
is read into a :class:`~lagsindy.model.FittedLagrangian` and hyperparameters
(:mod:`~lagsindy.io.model_file` never imports the estimator); :func:`load_model`
turns them into an estimator through the public
:meth:`LagrangianSINDy.from_fitted <lagsindy.LagrangianSINDy.from_fitted>`.
"""

from __future__ import annotations

from pathlib import Path

from .datasets import (
    MULTIARM_ENV,
    MULTIARM_PARAMETER_NAMES,
    find_multiarm_pendulum,
    load_multiarm_parameters,
    load_multiarm_pendulum,
)
from .model_file import (
    FORMAT,
    MAX_FILE_BYTES,
    MAX_TERMS,
    SCHEMA_VERSION,
    SCHEMA_VERSIONS,
    expression_to_string,
    model_from_dict,
    model_to_dict,
    read_model_file,
    write_model_file,
)

__all__ = [
    "FORMAT",
    "MAX_FILE_BYTES",
    "MAX_TERMS",
    "MULTIARM_ENV",
    "MULTIARM_PARAMETER_NAMES",
    "SCHEMA_VERSION",
    "SCHEMA_VERSIONS",
    "expression_to_string",
    "find_multiarm_pendulum",
    "load_model",
    "load_multiarm_parameters",
    "load_multiarm_pendulum",
    "model_from_dict",
    "model_to_dict",
    "read_model",
    "save_model",
]


def save_model(est, path) -> Path:
    """Write a fitted :class:`~lagsindy.LagrangianSINDy` as a JSON model file.

    The file holds text and numbers only (no pickle), so it is safe to share; load
    it with :func:`load_model` or :meth:`LagrangianSINDy.load`. Coefficients are
    written with Python's exact float repr, so predictions of the loaded model agree
    with the original's to rounding.

    Parameters
    ----------
    est : LagrangianSINDy
        A fitted estimator.
    path : str or path-like
        Destination (conventionally ``*.json``).

    Returns
    -------
    pathlib.Path
        The path written.
    """
    return write_model_file(est, path)


def read_model(path):
    """Read a model file: hyperparameters, fitted state and column names.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    params : dict
    fitted : FittedLagrangian
    feature_names_in : list of str or None

    Raises
    ------
    FileNotFoundError
        When the file does not exist.
    ValueError
        When the file is not a valid model file (the message names the problem).
    """
    return read_model_file(path)


def load_model(path):
    """Load a model saved by :func:`save_model` (no pickle, nothing evaluated).

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    LagrangianSINDy
        A fitted estimator: ``predict``, ``predict_acceleration``, ``score``,
        ``simulate``, ``equation`` and ``coef_table`` work as on the original;
        ``stages_`` is empty (the sparsification path is not saved) and the
        ``library`` parameter is the fitted library's terms (a refit searches them).

    Raises
    ------
    FileNotFoundError
        When the file does not exist.
    ValueError
        When the file is not a valid model file (the message names the problem).
    """
    from ..estimator import LagrangianSINDy

    return LagrangianSINDy.load(path)
