"""The model file: a fitted model as JSON (safe to share) and back.

A fitted :class:`~lagsindy.LagrangianSINDy` is written as a small JSON document:
the coordinates, the fitted library's terms as text, one coefficient per term, the
case and fixed term, the hyperparameters, and a ``dissipation`` list. Loading never
uses pickle, ``eval``, ``sympify`` or ``parse_expr`` on the file's text: every term
goes through :func:`lagsindy._expr.parse_expression`, a recursive-descent parser over
an allow-list (the declared coordinate and velocity names, numbers, ``+ - * / **``,
parentheses and a fixed set of functions), and every field is type-checked first. A
tampered file raises ``ValueError`` and runs nothing.

Document layout (``schema_version`` 1)::

    {
      "format": "lagsindy-model",
      "schema_version": 1,
      "lagsindy_version": "0.1.0",
      "coordinates": ["x", "theta"],
      "terms": ["x_dot**2", "cos(theta)", ...], # the fitted library's terms
      "coefficients": [0.75, 4.905, ...],    # one per term, 0.0 = pruned
      "case": "forces",                      # or "fixed", "acceleration"
      "fixed_term": null,                    # a term string in case III
      "unpenalized": [],                     # term strings
      "hyperparameters": {"lam": 0.001, ...}, # get_params() without library
      "n_features_in": 6,
      "feature_names_in": null,              # or the 3*n_dof column names
      "tau_1d": false,                       # true: fit with a 1-D tau
      "n_iter": 812,
      "residual": 2.1e-05,
      "dissipation": [],                     # see below
      "normalization": null                  # case III: "term" or "mass"
    }

``normalization`` (optional, added in 0.1.0) says how a case III fit fixed the
Lagrangian's scale: by the coefficient of ``fixed_term`` or by the mean trace of
the mass matrix (``fixed_term`` is then the term whose coefficient is 1).

Schema version 2 (a URDF library's model; others are still written as version 1):
``terms`` are base parameter names, and a ``robot`` object rebuilds the library
(:mod:`lagsindy.robots.document`: the URDF's text, settings and grouping).

``dissipation`` lists the candidate non-conservative terms of the fit (see
:mod:`lagsindy.dissipation`), each ``{"name": "viscous(theta)", "kind": "viscous",
"coordinates": ["theta"], "forces": [generalized force per coordinate for a unit
coefficient], "rayleigh": Rayleigh function or null, "coefficient": float}``. On
load each entry is rebuilt from its kind and coordinates and must match the stored
expressions, so a tampered entry cannot smuggle in other forces.

This module converts between the document and a
:class:`~lagsindy.model.FittedLagrangian` plus the hyperparameters; it never imports
the estimator (:mod:`lagsindy.io` turns the pair into one).
"""

from __future__ import annotations

import json
import math
import re
import warnings
from numbers import Integral, Real
from pathlib import Path

import numpy as np
import sympy as sp
import torch
from sympy.printing.str import StrPrinter

from .._expr import (
    MAX_EXPRESSION_LENGTH,
    ExpressionError,
    check_coordinate_names,
    parse_expression,
    state_names,
)
from ..settings import flat_settings

FORMAT = "lagsindy-model"
SCHEMA_VERSION = 1
#: The version of a model fitted with a URDF library (the ``robot`` field).
ROBOT_SCHEMA_VERSION = 2
SCHEMA_VERSIONS = (1, 2)
#: Largest number of library terms (or dissipation entries) in a model file.
MAX_TERMS = 20_000
_MAX_NAME_LENGTH = 200

_FIELDS = {
    # name: (JSON types accepted, description used in messages)
    "format": ((str,), "a string"),
    "schema_version": ((int,), "an integer"),
    "lagsindy_version": ((str,), "a string"),
    "coordinates": ((list,), "a list of strings"),
    "terms": ((list,), "a list of strings"),
    "coefficients": ((list,), "a list of numbers"),
    "case": ((str,), "a string"),
    "fixed_term": ((str, type(None)), "a string or null"),
    "unpenalized": ((list,), "a list of strings"),
    "hyperparameters": ((dict,), "an object"),
    "n_features_in": ((int,), "an integer"),
    "feature_names_in": ((list, type(None)), "a list of strings or null"),
    "tau_1d": ((bool,), "true or false"),
    "n_iter": ((int,), "an integer"),
    "residual": ((int, float, type(None)), "a number or null"),
    "dissipation": ((list,), "a list of objects"),
    "normalization": ((str, type(None)), "a string or null"),
    "robot": ((dict, type(None)), "an object or null"),
}
#: Fields added after schema version 1 was published: absent in older files.
_OPTIONAL = {"normalization": None, "robot": None}
_NORMALIZATIONS = ("term", "mass")
_CASES = ("forces", "fixed", "acceleration")


# ----------------------------------------------------------------------------- text
class _ExactPrinter(StrPrinter):
    """sympy's ``str`` but with floats written as Python's shortest exact repr."""

    def _print_Float(self, expr):
        return repr(float(expr))


def expression_to_string(expr) -> str:
    """Text of a sympy expression that :func:`parse_expression` reads back exactly.

    Floats are written with Python's ``repr`` (17 significant digits at most), so a
    float64 coefficient inside a term survives the round trip bit for bit.
    """
    if not isinstance(expr, sp.Basic | int | float):
        raise TypeError(f"expected a sympy expression, got {type(expr).__name__}")
    return _ExactPrinter().doprint(sp.sympify(expr))


def _to_text(expr, allowed, what):
    """Serialise ``expr`` and check that the safe parser reads it back unchanged."""
    if isinstance(expr, str):  # parsed safely, never sympified
        try:
            expr = parse_expression(expr, allowed)
        except ExpressionError as exc:
            raise ValueError(f"{what} {expr[:80]!r} is not valid: {exc}") from None
    text = expression_to_string(expr)
    try:
        back = parse_expression(text, allowed)
    except ExpressionError as exc:
        raise ValueError(
            f"{what} {text!r} cannot be saved in the safe model format: {exc}"
        ) from None
    if expression_to_string(back) != text:
        raise ValueError(
            f"{what} {text!r} does not survive the text round trip (it reads back as "
            f"{expression_to_string(back)!r}); it cannot be saved in the safe format"
        )
    return text


def _plain(value):
    """A hyperparameter as a JSON value (numbers, strings, lists, null)."""
    if value is None or isinstance(value, bool | str):
        return value
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, Integral):
        return int(value)
    if isinstance(value, Real):
        return float(value)
    if isinstance(value, sp.Basic):
        return expression_to_string(value)
    if isinstance(value, list | tuple | np.ndarray):
        return [_plain(v) for v in value]
    # torch.device and the like: their text is what the constructor accepts
    text = str(value)
    return text


# ----------------------------------------------------------------------------- save
def model_to_dict(est) -> dict:
    """The JSON document of a fitted estimator (see the module docstring).

    Reads the estimator's hyperparameters (``get_params``), its fitted state
    (``fitted_``, a :class:`~lagsindy.model.FittedLagrangian`) and the column names
    it was fitted on.
    """
    from sklearn.utils.validation import check_is_fitted

    from .._version import __version__

    check_is_fitted(est)
    fitted = est.fitted_
    coords = list(fitted.coordinates)
    allowed = state_names(coords, accelerations=False)
    robot = hasattr(fitted.library, "torch_terms")  # (library_document checks it)
    text = (lambda t, a, w: str(t)) if robot else _to_text
    names_ = fitted.library.terms_ if robot else fitted.terms
    terms = [text(t, allowed, "term") for t in names_]
    coef = np.asarray(fitted.coef, dtype=float)
    if not np.all(np.isfinite(coef)):
        raise ValueError("the model has non-finite coefficients; it cannot be saved")
    # the settings objects as flat values, which every version reads (loading turns
    # them back into the objects: LagrangianSINDy.from_fitted)
    params = flat_settings(est.get_params(deep=False))
    params.pop("library", None)
    params.pop("dissipation", None)  # its terms are stored under "dissipation"
    params.pop("verbose", None)  # how chatty a session was is not part of the model
    if not isinstance(params.get("random_state"), Integral | type(None)):
        params["random_state"] = None  # a RandomState instance has no JSON form
    hyper = {k: _plain(v) for k, v in sorted(params.items())}
    dissipation_names = {t.name for t in fitted.dissipation_terms}
    unpenalized = [
        t
        if isinstance(t, str) and t in dissipation_names
        else text(names_[fitted.library.index(t)], allowed, "unpenalized term")
        for t in (params["unpenalized"] or [])
    ]
    if hyper.get("unpenalized") is not None:
        hyper["unpenalized"] = unpenalized
    fixed = fitted.fixed_term
    if fixed is not None:
        fixed = terms[fitted.library.index(fixed)]
    names = getattr(est, "feature_names_in_", None)
    residual = fitted.residual
    residual = (
        None if residual is None or not math.isfinite(residual) else float(residual)
    )
    dissipation = []
    for term, d in zip(fitted.dissipation_terms, fitted.dissipation_coef):
        dissipation.append(
            {
                "name": term.name,
                "kind": term.kind,
                "coordinates": list(term.coordinates),
                "forces": [
                    _to_text(f, allowed, "dissipation force") for f in term.forces
                ],
                "rayleigh": None
                if term.rayleigh is None
                else _to_text(term.rayleigh, allowed, "Rayleigh function"),
                "coefficient": float(d),
            }
        )
    out = {
        "format": FORMAT,
        "schema_version": ROBOT_SCHEMA_VERSION if robot else SCHEMA_VERSION,
        "lagsindy_version": __version__,
        "coordinates": coords,
        "terms": terms,
        "coefficients": [float(c) for c in coef],
        "case": fitted.case,
        "fixed_term": fixed,
        "unpenalized": unpenalized,
        "hyperparameters": hyper,
        "n_features_in": int(est.n_features_in_),
        "feature_names_in": None if names is None else [str(n) for n in names],
        "tau_1d": bool(fitted.tau_1d),
        "n_iter": int(fitted.n_iter),
        "residual": residual,
        "dissipation": dissipation,
        "normalization": fitted.normalization,
    }
    if robot:
        from ..robots.document import library_document

        out["robot"] = library_document(fitted.library)
    return out


# ----------------------------------------------------------------------------- load
def _reject_constant(name):
    raise ValueError(
        f"the model file contains {name}, which is not allowed (use numbers)"
    )


def _unique_keys(pairs):
    out = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(f"the model file repeats the key {key!r}")
        out[key] = value
    return out


def _is_number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _check_field(doc, name):
    if name not in doc and name in _OPTIONAL:
        return _OPTIONAL[name]
    if name not in doc:
        raise ValueError(f"the model file lacks the field {name!r}")
    types, desc = _FIELDS[name]
    value = doc[name]
    ok = isinstance(value, types) and not (
        isinstance(value, bool) and bool not in types
    )
    if not ok:
        raise ValueError(
            f"field {name!r} of the model file must be {desc}, "
            f"got {type(value).__name__}"
        )
    return value


def _check_strings(values, name, *, limit=MAX_EXPRESSION_LENGTH):
    for i, v in enumerate(values):
        if not isinstance(v, str):
            raise ValueError(
                f"{name}[{i}] in the model file must be a string, "
                f"got {type(v).__name__}"
            )
        if len(v) > limit:
            raise ValueError(
                f"{name}[{i}] in the model file has {len(v)} characters (limit {limit})"
            )
    return values


def _check_numbers(values, name):
    out = []
    for i, v in enumerate(values):
        if not _is_number(v):
            raise ValueError(
                f"{name}[{i}] in the model file must be a number, "
                f"got {type(v).__name__}"
            )
        v = float(v)
        if not math.isfinite(v):
            raise ValueError(f"{name}[{i}] in the model file is not finite ({v})")
        out.append(v)
    return out


def _parse(text, allowed, what):
    try:
        expr = parse_expression(text, allowed)
    except ExpressionError as exc:
        raise ValueError(
            f"{what} {text[:80]!r} in the model file is not valid: {exc}"
        ) from None
    if expr.has(sp.I):
        raise ValueError(f"{what} {text[:80]!r} in the model file is complex")
    for number in expr.atoms(sp.Number):
        if not math.isfinite(abs(complex(number))):
            raise ValueError(
                f"{what} {text[:80]!r} contains a number beyond float range"
            )
    return expr


def _hyperparameters(hyper: dict) -> dict:
    """Check the saved hyperparameters' JSON values (their names are checked by the
    estimator that receives them)."""
    for key, value in hyper.items():
        if isinstance(value, dict) or (
            isinstance(value, str) and len(value) > MAX_EXPRESSION_LENGTH
        ):
            raise ValueError(
                f"hyperparameter {key!r} in the model file has an invalid value"
            )
        if isinstance(value, list):
            _check_strings(value, f"hyperparameters[{key!r}]")
        if _is_number(value) and not math.isfinite(float(value)):
            raise ValueError(f"hyperparameter {key!r} in the model file is not finite")
    hyper = dict(hyper)
    # Files written before 0.2 store the verbose of the session that fitted them; a
    # loaded model is quiet (set est.verbose to see its refits' stages).
    hyper.pop("verbose", None)
    device = hyper.get("device", "cpu")
    if not isinstance(device, str) or not re.fullmatch(
        r"(cpu|cuda|mps)(:\d{1,3})?", device
    ):
        raise ValueError(
            "hyperparameter 'device' in the model file must be 'cpu', 'cuda' or "
            "'mps', "
            f"got {str(device)[:40]!r}"
        )
    if device.startswith("cuda") and not torch.cuda.is_available():
        warnings.warn(
            f"the model was saved with device={device!r}, but no CUDA device is "
            "available here; it will compute on the CPU",
            UserWarning,
            stacklevel=4,
        )
        hyper["device"] = "cpu"
    return hyper


def model_from_dict(doc: dict):
    """Hyperparameters, fitted state and column names from a model document.

    Raises ``ValueError`` naming the first problem (unknown schema, missing field,
    wrong JSON type, invalid coordinate name or term, inconsistent lengths, non-finite
    number). Nothing in the document is evaluated as code.

    Returns
    -------
    params : dict
        The hyperparameters (``library`` and ``dissipation`` excluded).
    fitted : FittedLagrangian
    feature_names_in : list of str or None
    """
    from ..library import CandidateLibrary
    from ..model import FittedLagrangian

    if not isinstance(doc, dict):
        raise ValueError(
            f"a model file must hold a JSON object, got {type(doc).__name__}"
        )
    if doc.get("format") != FORMAT:
        raise ValueError(
            "not a lagsindy model file (field 'format' is "
            f"{str(doc.get('format'))[:40]!r}, "
            f"expected {FORMAT!r})"
        )
    version = _check_field(doc, "schema_version")
    if version not in SCHEMA_VERSIONS:
        raise ValueError(
            f"model file schema version {version} is not supported (this lagsindy "
            "reads "
            f"{list(SCHEMA_VERSIONS)}); upgrade lagsindy"
        )
    values = {name: _check_field(doc, name) for name in _FIELDS}
    extra = sorted(set(doc) - set(_FIELDS))
    if extra:
        raise ValueError(f"the model file has unknown fields {extra[:5]}")
    robot = values["robot"]
    if (robot is None) == (version == ROBOT_SCHEMA_VERSION):
        raise ValueError(
            f"a model file of schema version {ROBOT_SCHEMA_VERSION} (a URDF "
            "library's) has a 'robot' object, and no other version has one"
        )
    if len(values["lagsindy_version"]) > _MAX_NAME_LENGTH:
        raise ValueError("field 'lagsindy_version' of the model file is too long")

    coords = _check_strings(
        values["coordinates"], "coordinates", limit=_MAX_NAME_LENGTH
    )
    try:
        coords = check_coordinate_names(coords)
    except ValueError as exc:
        raise ValueError(f"the model file's coordinates are not valid: {exc}") from None
    n_dof = len(coords)
    allowed = state_names(coords, accelerations=False)

    terms = _check_strings(values["terms"], "terms")
    coefs = _check_numbers(values["coefficients"], "coefficients")
    if not terms:
        raise ValueError("the model file has no terms")
    if len(terms) > MAX_TERMS:
        raise ValueError(f"the model file has {len(terms)} terms (limit {MAX_TERMS})")
    if len(coefs) != len(terms):
        raise ValueError(
            f"the model file has {len(terms)} terms but {len(coefs)} coefficients"
        )
    library = None if robot is None else _robot_library(robot, coords, terms)
    exprs = [] if robot is not None else [_parse(t, allowed, "term") for t in terms]
    seen = {}
    for text, expr in zip(terms, exprs):
        if expr.is_number:
            raise ValueError(f"term {text!r} in the model file is a constant")
        if expr in seen:
            raise ValueError(
                f"terms {seen[expr]!r} and {text!r} in the model file are the same term"
            )
        seen[expr] = text

    case = values["case"]
    if case not in _CASES:
        raise ValueError(
            f"field 'case' of the model file must be one of {_CASES}, got {case[:40]!r}"
        )
    fixed = values["fixed_term"]
    if case == "fixed" and fixed is None:
        raise ValueError("the model file has case 'fixed' but no fixed_term")
    unpenalized = _check_strings(values["unpenalized"], "unpenalized")
    named = {e.get("name") for e in values["dissipation"] if isinstance(e, dict)}
    for text in ([fixed] if fixed is not None else []) + list(unpenalized):
        if text not in named:  # a dissipation name, or else a term
            _term(library, text, allowed, "term")
    hyper = _hyperparameters(values["hyperparameters"])
    normalization = values["normalization"]
    if normalization is not None and normalization not in _NORMALIZATIONS:
        raise ValueError(
            f"field 'normalization' of the model file must be one of {_NORMALIZATIONS} "
            f"or null, got {normalization[:40]!r}"
        )
    fixed_hyper = hyper.get("fixed_term")
    for text in [fixed_hyper] + list(hyper.get("unpenalized") or []):
        if text == "mass" and text is fixed_hyper:
            continue
        if isinstance(text, str) and text not in named:
            _term(library, text, allowed, "hyperparameter term")

    n_features = values["n_features_in"]
    if n_features != 3 * n_dof:
        raise ValueError(
            f"field 'n_features_in' of the model file is {n_features}, but "
            f"{n_dof} coordinate(s) need 3 * {n_dof} = {3 * n_dof}"
        )
    names = values["feature_names_in"]
    if names is not None:
        _check_strings(names, "feature_names_in", limit=_MAX_NAME_LENGTH)
        if list(names) != state_names(coords):
            raise ValueError(
                "field 'feature_names_in' of the model file does not match its "
                f"coordinates: expected {state_names(coords)}"
            )
    if values["tau_1d"] and n_dof != 1:
        raise ValueError(
            "the model file says tau was 1-D, but it has several coordinates"
        )
    if values["n_iter"] < 0:
        raise ValueError("field 'n_iter' of the model file is negative")
    residual = values["residual"]
    if residual is not None and not math.isfinite(float(residual)):
        raise ValueError("field 'residual' of the model file is not finite")

    dissipation_terms, dissipation_coef = _dissipation_entries(
        values["dissipation"], coords, allowed
    )

    if library is None:
        library = CandidateLibrary.from_terms(
            coords, list(terms), remove_trivial=False, remove_dependent=False
        ).build()
    if len(library.terms_) != len(terms):
        raise ValueError("the model file's terms do not form a valid library")
    for text in unpenalized:
        if text not in {t.name for t in dissipation_terms}:
            _index(library, text)
    fitted = FittedLagrangian(
        library=library,
        coef=np.asarray(coefs, dtype=float),
        case=case,
        dissipation_terms=dissipation_terms,
        dissipation_coef=np.asarray(dissipation_coef, dtype=float),
        fixed_term=(
            None if fixed is None else str(library.terms_[_index(library, fixed)])
        ),
        normalization=normalization if case == "fixed" else None,
        # The weak form's sampling interval and noise covariance are not saved:
        # refits (e.g. by diagnose) estimate them again from their data (dt from
        # the `dt` hyperparameter when it was given).
        dt=float(hyper["dt"]) if _is_number(hyper.get("dt")) else None,
        n_iter=int(values["n_iter"]),
        residual=None if residual is None else float(residual),
        tau_1d=bool(values["tau_1d"]),
    )
    return hyper, fitted, names


def _robot_library(doc, coords, terms):
    from ..robots.document import library_from_document

    return library_from_document(doc, coords, terms)


def _term(library, text, allowed, what):
    """A term named in the file: an expression, or a URDF library's term name."""
    if library is None:
        return _parse(text, allowed, what)
    if text not in library.terms_:
        raise ValueError(
            f"{what} {text[:80]!r} in the model file is not among its terms"
        )
    return text


def _same_forces(a, b, coords) -> bool:
    """Whether two force vectors agree (to float rounding of a saved eps) at test states."""
    if all(sp.simplify(x - y) == 0 for x, y in zip(a, b)):
        return True
    names = [sp.Symbol(f"{c}_dot", real=True) for c in coords]
    names += [sp.Symbol(c, real=True) for c in coords]
    rng = np.random.default_rng(0)
    for _ in range(5):
        point = dict(zip(names, rng.uniform(-1, 1, len(names)) * 1e-3))
        for x, y in zip(a, b):
            vx, vy = float(x.subs(point)), float(y.subs(point))
            if not math.isclose(vx, vy, rel_tol=1e-9, abs_tol=1e-12):
                return False
    return True


def _dissipation_entries(entries, coords, allowed):
    """Validate the ``dissipation`` field and rebuild its terms from kind and coordinates."""
    from ..dissipation import rebuild_term
    from ..force_kinds import names as kind_names

    if len(entries) > MAX_TERMS:
        raise ValueError(f"the model file has {len(entries)} dissipation entries")
    fields = {"name", "kind", "coordinates", "forces", "rayleigh", "coefficient"}
    terms, coefs = [], []
    for i, entry in enumerate(entries):
        where = f"dissipation[{i}]"
        if not isinstance(entry, dict) or set(entry) != fields:
            got = sorted(entry)[:6] if isinstance(entry, dict) else type(entry).__name__
            raise ValueError(
                f"{where} in the model file must be an object with exactly the fields "
                f"{sorted(fields)}, got {got}"
            )
        kind = entry["kind"]
        if kind not in kind_names():
            raise ValueError(
                f"{where}['kind'] must be one of {kind_names()}, got {str(kind)[:40]!r}"
            )
        on = _check_strings(
            entry["coordinates"], f"{where}['coordinates']", limit=_MAX_NAME_LENGTH
        )
        if not on or any(c not in coords for c in on):
            raise ValueError(
                f"{where}['coordinates'] must name coordinates of the model"
            )
        forces = entry["forces"]
        if not isinstance(forces, list) or len(forces) != len(coords):
            raise ValueError(
                f"{where}['forces'] must be a list of {len(coords)} expressions "
                "(one generalized force per coordinate)"
            )
        _check_strings(forces, f"{where}['forces']")
        parsed = [_parse(f, allowed, f"{where} force") for f in forces]
        rayleigh = entry["rayleigh"]
        if rayleigh is not None and not isinstance(rayleigh, str):
            raise ValueError(f"{where}['rayleigh'] must be a string or null")
        (coefficient,) = _check_numbers(
            [entry["coefficient"]], f"{where}['coefficient']"
        )
        try:  # the kind's parameters (Coulomb's eps) are read from the forces
            term = rebuild_term(kind, on, coords, parsed)
        except ValueError as exc:
            raise ValueError(
                f"{where} is not a valid dissipation term: {exc}"
            ) from None
        same = _same_forces(term.forces, parsed, coords)
        if not same or entry["name"] != term.name:
            raise ValueError(
                f"{where} does not match its kind and coordinates (expected name "
                f"{term.name!r} and forces {[str(f) for f in term.forces]})"
            )
        terms.append(term)
        coefs.append(coefficient)
    return terms, coefs


def _index(library, text):
    try:
        return library.index(text)
    except ValueError as exc:
        raise ValueError(
            f"the model file names a term that is not among its terms: {exc}"
        ) from None


# ----------------------------------------------------------------------------- files
#: Largest model file :func:`read_model_file` reads, in bytes.
MAX_FILE_BYTES = 20_000_000


def write_model_file(est, path) -> Path:
    """Write the model document of a fitted estimator (:func:`model_to_dict`) as a
    JSON file, one field per line (readable and diff-friendly); the path written."""
    doc = model_to_dict(est)
    path = Path(path)
    lines = [
        f" {json.dumps(k)}: {json.dumps(v, allow_nan=False)}" for k, v in doc.items()
    ]
    path.write_text("{\n" + ",\n".join(lines) + "\n}\n", encoding="utf-8")
    return path


def read_model_file(path):
    """Read a model file: hyperparameters, fitted state and column names.

    Raises ``FileNotFoundError`` when the file does not exist and ``ValueError``
    (naming the file and the problem) when it is not a valid model file; nothing
    in it is evaluated as code. See :func:`model_from_dict` for what is returned.
    """
    path = Path(path)
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise ValueError(
            f"{path} has {size} bytes, more than a model file may have "
            f"({MAX_FILE_BYTES})"
        )
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
        doc = json.loads(
            text, parse_constant=_reject_constant, object_pairs_hook=_unique_keys
        )
    except UnicodeDecodeError:
        raise ValueError(f"{path} is not a text (UTF-8) model file") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc}") from None
    except RecursionError:
        raise ValueError(f"{path} is nested too deeply to be a model file") from None
    except ValueError as exc:  # NaN/Infinity, repeated keys, oversized integers
        raise ValueError(f"{path}: {exc}") from None
    try:
        return model_from_dict(doc)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
