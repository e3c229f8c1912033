"""What a fitted robot model gives back: a URDF and a table of base parameters.

Both take a :class:`~lagsindy.LagrangianSINDy` fitted with a URDF library (its
``library_`` is a :class:`~lagsindy.robots.fitting.BaseParameterLibrary`).
"""

from __future__ import annotations

import numpy as np

from .export import to_urdf


def _base_library(est):
    library = getattr(est, "library_", None)
    if library is None:
        raise ValueError("the estimator is not fitted: call fit(X, tau) first")
    if not hasattr(library, "link_parameters"):
        raise ValueError(
            "this estimator was not fitted with a URDF library "
            "(CandidateLibrary.from_urdf): it has no link parameters to write"
        )
    return library


def joint_coefficients(est, kind: str) -> np.ndarray:
    """Per joint, the coefficient of the fitted dissipation term ``kind(joint)``
    (0 where the model has none)."""
    library = _base_library(est)
    out = np.zeros(len(library.coordinates_))
    for term, c in zip(est.dissipation_terms_, est.dissipation_coef_):
        for j, name in enumerate(library.coordinates_):
            if term.name == f"{kind}({name})":
                out[j] = c
    return out


def fitted_to_urdf(est, path):
    """Write a fitted robot model into a copy of its URDF.

    The link parameters are a physically consistent representative of the fitted
    base parameters (the constrained fit's own; after an unconstrained fit, the
    nearest consistent ones to the URDF's, with a warning if none reproduces them:
    :func:`lagsindy.robots.consistent_parameters`); the fitted viscous and Coulomb
    coefficients become each joint's ``<dynamics damping= friction=>``; rotor
    inertias a comment (see :func:`lagsindy.robots.to_urdf`). Offsets, springs and
    other fitted effects have no URDF element and are not written.

    Parameters
    ----------
    est : LagrangianSINDy
        Fitted with a URDF library.
    path : str or Path
        Where to write (the original file is not changed).

    Returns
    -------
    pathlib.Path
    """
    library = _base_library(est)
    parameters = library.link_parameters(est.coef_)
    return to_urdf(
        library.robot_,
        parameters,
        path,
        damping=joint_coefficients(est, "viscous"),
        friction=joint_coefficients(est, "coulomb"),
    )


def parameter_table(est, intervals=None):
    """The fitted base parameters as a table, with bootstrap intervals if given.

    Parameters
    ----------
    est : LagrangianSINDy
        Fitted with a URDF library.
    intervals : BootstrapReport, default=None
        :func:`lagsindy.bootstrap`'s report for this configuration: its ``low`` and
        ``high`` per base parameter are added.

    Returns
    -------
    pandas.DataFrame
        Columns ``parameter`` (the base parameter's name: its first link
        parameter), ``combination`` (the link parameters it combines), ``value``,
        ``urdf`` (the URDF's own value; rotor inertias 0) and, with ``intervals``,
        ``low`` and ``high``.
    """
    import pandas as pd

    library = _base_library(est)
    frame = pd.DataFrame(
        {
            "parameter": list(library.terms_),
            "combination": list(
                library.base_.labels if hasattr(library, "base_") else library.labels_
            ),
            "value": np.asarray(est.coef_, float),
            "urdf": np.asarray(library.nominal_, float),
        }
    )
    if intervals is not None:
        boot = intervals.to_frame().set_index("term")
        frame["low"] = [float(boot.loc[n, "low"]) for n in frame.parameter]
        frame["high"] = [float(boot.loc[n, "high"]) for n in frame.parameter]
    return frame
