"""The estimator's settings objects, and the flat parameters they replace.

:class:`~lagsindy.LagrangianSINDy` takes its settings in two objects:
``solver=`` a :class:`~lagsindy.solvers.StagedFISTA` (thresholds, stages,
iterations, tolerances, debiasing) and ``formulation=`` a formulation object
(:class:`~lagsindy.formulation.WeakForm` with its ``window``, ``dt`` and
``noise_cov``) or a formulation's name. The flat parameters of earlier versions
(``threshold=``, ``window=``, ...) still work; they default to :data:`DEPRECATED`
and, when set, the fit warns (``FutureWarning``) naming the object to use.

Every reader of an estimator's parameters goes through :func:`solver_settings` and
:func:`formulation_settings`, so a flat parameter and its object never disagree;
model files store the flat values (:func:`flat_settings`, readable by every
version) and load into the objects (:func:`as_objects`).
"""

from __future__ import annotations

import warnings
from numbers import Integral, Real

import numpy as np
import sympy as sp
import torch
from sklearn.base import clone
from sklearn.utils._param_validation import (
    HasMethods,
    Hidden,
    Interval,
    InvalidParameterError,
    StrOptions,
    validate_parameter_constraints,
)

from ._stacklevel import outside_stacklevel
from .formulation.forms import AutoForm, StrongForm, WeakForm, make_formulation
from .solvers import StagedFISTA

__all__ = [
    "DEPRECATED",
    "FORMULATION_PARAMS",
    "PARAMETER_CONSTRAINTS",
    "SOLVER_PARAMS",
    "as_objects",
    "checked_params",
    "flat_settings",
    "formulation_settings",
    "solver_settings",
    "warn_deprecated",
]

#: The default of a deprecated flat parameter (not set).
DEPRECATED = "deprecated"
# The estimator's flat parameters that default to DEPRECATED, in its signature's order.
DEPRECATED_FLAT = (
    "threshold", "dissipation_threshold", "lam_decay", "step_growth", "max_stages",
    "max_iter", "tol", "solver_tol", "debias", "window", "dt", "noise_cov",
)  # fmt: skip
#: The flat parameters that :class:`~lagsindy.solvers.StagedFISTA` holds.
SOLVER_PARAMS = tuple(StagedFISTA().get_params())
#: The flat parameters that :class:`~lagsindy.formulation.WeakForm` holds.
FORMULATION_PARAMS = tuple(WeakForm().get_params())
_CASES = {"auto", "forces", "fixed", "acceleration"}
_DEPRECATED = [Hidden(StrOptions({DEPRECATED}))]
#: The constraints of :class:`~lagsindy.LagrangianSINDy`'s parameters (scikit-learn's
#: parameter validation), the deprecated flat settings included.
PARAMETER_CONSTRAINTS = {
    "library": [HasMethods(["build", "get_feature_names_out"]), None],
    "dissipation": [HasMethods(["build"]), None],
    "lam": [Interval(Real, 0, None, closed="left")],
    "alpha": [Interval(Real, 0, None, closed="neither"), None],
    "solver": [StagedFISTA, None],
    "fixed_term": [str, sp.Basic, None],
    "unpenalized": ["array-like", None],
    "case": [StrOptions(_CASES)],
    "formulation": [StrOptions({"auto", "strong", "weak"}), HasMethods(["statistics"])],
    "normalize": ["boolean"],
    "device": [str, torch.device],
    "dtype": [StrOptions({"float64", "float32"})],
    "random_state": ["random_state"],
    "verbose": ["verbose"],
    # the deprecated flat settings
    **{
        k: [*StagedFISTA._parameter_constraints[k], *_DEPRECATED] for k in SOLVER_PARAMS
    },
    "window": [
        Interval(Integral, 5, None, closed="left"),
        StrOptions({"auto"}),
        *_DEPRECATED,
    ],
    "dt": [Interval(Real, 0, None, closed="neither"), None, *_DEPRECATED],
    "noise_cov": [StrOptions({"auto"}), "array-like", None, *_DEPRECATED],
}
_SOLVER_DEFAULTS = StagedFISTA().get_params()
_FORM_DEFAULTS = WeakForm().get_params()
_FORM_CLASSES = {"auto": AutoForm, "weak": WeakForm, "strong": StrongForm}


def _is_set(value) -> bool:
    return not (isinstance(value, str) and value == DEPRECATED)


def _flat(params: dict, names) -> dict:
    """The flat parameters among ``names`` that ``params`` sets."""
    return {k: params[k] for k in names if k in params and _is_set(params[k])}


def _is_default(value, default) -> bool:
    if isinstance(default, str) or default is None:
        return isinstance(value, type(default)) and value == default
    if isinstance(value, bool | np.bool_) or isinstance(default, bool):
        return isinstance(value, bool | np.bool_) and bool(value) == default
    return isinstance(value, int | float | np.number) and float(value) == default


def solver_settings(params: dict) -> StagedFISTA:
    """The solver settings of an estimator's parameters (``get_params()``).

    ``params["solver"]`` when given, else :class:`~lagsindy.solvers.StagedFISTA`
    with the flat parameters that are set (deprecated); both given is an error.
    """
    solver, flat = params.get("solver"), _flat(params, SOLVER_PARAMS)
    if solver is None:
        return StagedFISTA(**flat)
    if flat:
        raise ValueError(
            f"solver= is given and so are {sorted(flat)}, which it holds: set them "
            f"on the solver only, e.g. solver=StagedFISTA({_call(flat)})"
        )
    return solver


def formulation_settings(params: dict):
    """The formulation of an estimator's parameters (``get_params()``): the
    ``formulation`` object, or the object of its name with the flat ``window``,
    ``dt`` and ``noise_cov`` that are set (deprecated); an object and flat
    parameters both given is an error."""
    form, flat = params.get("formulation", "auto"), _flat(params, FORMULATION_PARAMS)
    if flat and not isinstance(form, str):
        raise ValueError(
            f"formulation={type(form).__name__}(...) is given and so are "
            f"{sorted(flat)}: set them on the formulation object only"
        )
    return make_formulation(form, **flat)


def _call(values: dict) -> str:
    return ", ".join(f"{k}={v!r}" for k, v in values.items())


def warn_deprecated(params: dict) -> None:
    """Warn (``FutureWarning``, at the user's line) about the flat parameters
    ``params`` sets, naming the settings object that replaces them (an object and
    its flat parameters both set: the error first)."""
    solver_settings(params)
    formulation_settings(params)
    solver = _flat(params, SOLVER_PARAMS)
    if solver:
        warnings.warn(
            f"LagrangianSINDy({_call(solver)}) is deprecated and will stop working "
            f"in a future version: pass solver=StagedFISTA({_call(solver)}) "
            "(from lagsindy.solvers import StagedFISTA).",
            FutureWarning,
            stacklevel=outside_stacklevel(),
        )
    form = _flat(params, FORMULATION_PARAMS)
    if form:
        name = params.get("formulation", "auto")
        cls = _FORM_CLASSES.get(name, WeakForm) if isinstance(name, str) else WeakForm
        warnings.warn(
            f"LagrangianSINDy({_call(form)}) is deprecated and will stop working in "
            f"a future version: pass formulation={cls.__name__}({_call(form)}) "
            f"(from lagsindy.formulation import {cls.__name__}).",
            FutureWarning,
            stacklevel=outside_stacklevel(),
        )


def as_objects(params: dict) -> dict:
    """``params`` with the flat parameters folded into the settings objects.

    The flat parameters become :data:`DEPRECATED` (where ``params`` has them), the
    solver a :class:`~lagsindy.solvers.StagedFISTA` (``None`` when every value is
    the default) and the formulation an object (its name when the weak form's values
    are the defaults). What ``set_params`` of a copy that must not warn takes, and
    what a model file's flat values load into.
    """
    solver_settings(params)  # an object and its flat parameters both set: an error
    formulation_settings(params)
    out = dict(params)
    solver = _flat(params, SOLVER_PARAMS)
    if params.get("solver") is None and solver:
        changed = {
            k: v for k, v in solver.items() if not _is_default(v, _SOLVER_DEFAULTS[k])
        }
        out["solver"] = StagedFISTA(**solver) if changed else None
    form = _flat(params, FORMULATION_PARAMS)
    name = params.get("formulation", "auto")
    if isinstance(name, str) and form:
        changed = {
            k: v for k, v in form.items() if not _is_default(v, _FORM_DEFAULTS[k])
        }
        out["formulation"] = make_formulation(name, **form) if changed else name
    for k in SOLVER_PARAMS + FORMULATION_PARAMS:
        if k in out:
            if k in DEPRECATED_FLAT:
                out[k] = DEPRECATED
            else:  # a setting with no flat estimator parameter (equation_threshold)
                del out[k]
    return out


def checked_params(params: dict) -> dict:
    """Hyperparameters from elsewhere (a model file, another version's estimator),
    checked, with the flat settings folded into their objects (:func:`as_objects`).

    Raises ``ValueError`` naming an unknown name or an invalid value (``library``
    and ``dissipation`` are not hyperparameters here).
    """
    known = set(PARAMETER_CONSTRAINTS) | set(SOLVER_PARAMS) | set(FORMULATION_PARAMS)
    known -= {"library", "dissipation"}
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(
            f"unknown hyperparameters {unknown[:5]} (a model file from a newer "
            "lagsindy version?)"
        )
    try:
        validate_parameter_constraints(
            PARAMETER_CONSTRAINTS, params, caller_name="LagrangianSINDy"
        )
        return as_objects(params)
    except (InvalidParameterError, TypeError, ValueError) as exc:
        raise ValueError(f"the hyperparameters are not valid: {exc}") from None


def flat_settings(params: dict) -> dict:
    """``params`` with the settings objects written out as flat values.

    The solver becomes its parameters; a formulation object its ``name`` and its
    parameters (the weak form's defaults for a formulation without them). How model
    files store them, so that every version reads them.
    """
    params = dict(params)
    solver = solver_settings(params)
    form = formulation_settings(params)
    params.pop("solver", None)
    params.update(solver.get_params(deep=False))
    params["formulation"] = form.name
    params.update(_FORM_DEFAULTS)
    params.update(form.get_params(deep=False))
    return params


# ------------------------------------------------------- the fit's case and library
def resolve_case(case, tau):
    """``"auto"``: case I (``"forces"``) when forces are given, else III."""
    if case == "auto":
        return "forces" if tau is not None else "fixed"
    if case == "forces" and tau is None:
        raise ValueError("case='forces' needs tau: call fit(X, tau)")
    if case in ("fixed", "acceleration") and tau is not None:
        raise ValueError(
            f"case={case!r} is for passive data; call fit(X) without tau, or "
            "use case='forces'"
        )
    return case


def build_library(library, coordinates, n_samples):
    """The built copy of ``library`` (``None``: the default degree-2 polynomials,
    with a warning when the coordinates may be coupled)."""
    from .library import CandidateLibrary

    library = clone(library) if library is not None else None
    if library is None:
        library = CandidateLibrary.polynomial(
            coordinates, angles="all", degree=2, raw_angles=True
        )
        if len(coordinates) > 1:
            _warn_default_library(coordinates)
    elif library.coordinates is None:
        library.set_params(coordinates=coordinates)
    library.build()
    if callable(getattr(library, "regression_library", None)):  # a robot's base
        library = library.regression_library()  # parameters (lagsindy.robots)
    n_dof, n_terms = len(library.coordinates_), len(library.terms_)
    if n_samples * n_dof < n_terms:
        raise ValueError(
            f"too few samples: {n_samples} sample(s) x {n_dof} coordinate(s) "
            f"give {n_samples * n_dof} equations for {n_terms} candidate "
            "terms; record more data or use a smaller library"
        )
    return library


def _warn_default_library(coordinates):
    """The default library's products of two factors cannot couple velocities through
    an angle (a double pendulum fitted with it returned 27 meaningless terms)."""
    a, b = coordinates[:2]
    warnings.warn(
        f"library=None fits degree-2 polynomials of {coordinates}, which have no term "
        "coupling two coordinates' velocities through an angle (a cart-pendulum's "
        f"x_dot*theta_dot*cos(theta), a double pendulum's {a}_dot*{b}_dot*cos({a} - "
        f"{b})): if these coordinates are coupled, the fit returns a wrong Lagrangian. "
        f"Pass a library: CandidateLibrary.chain({list(coordinates)}) for a chain of "
        "links, CandidateLibrary.polynomial(coordinates, angles=[...], degree=3 or 4), "
        "or a system's paper_library().",
        UserWarning,
        stacklevel=outside_stacklevel(),
    )
