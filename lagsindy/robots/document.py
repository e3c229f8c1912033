"""A fitted robot library as plain JSON values, for the model file.

:func:`library_document` writes what rebuilds a
:class:`~lagsindy.robots.fitting.BaseParameterLibrary`: the URDF's text (embedded, so
the model file needs no other file), the library's settings (``joints``, ``locked``
as given: the other joints' positions follow from the URDF; ``armature``,
``gravity``, ``penalize``, ``consistent``, ``random_state``) and the base-parameter
grouping as fitted (``independent`` columns and the ``matrix`` ``beta = K pi``), so
that a file read back has the same columns whatever a later reduction would choose.
:func:`library_from_document` checks every value and rebuilds the library from
them; nothing in the document is evaluated. The URDF text is parsed by the same
reader as a URDF file (the standard library's ``xml.etree``), after refusing
document type declarations (no entities can expand), from a copy written once per
distinct text into a cache folder (:func:`urdf_cache_dir`), which the rebuilt
library's ``path`` names.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import tempfile
from pathlib import Path

import numpy as np

from .base_parameters import BaseParameters, _label

#: Largest embedded URDF text, in characters.
MAX_URDF_CHARS = 5_000_000
#: Environment variable naming the folder embedded URDFs are written to.
CACHE_ENV = "LAGSINDY_CACHE_DIR"

FIELDS = (
    "urdf",
    "urdf_name",
    "joints",
    "locked",
    "armature",
    "gravity",
    "penalize",
    "consistent",
    "random_state",
    "independent",
    "matrix",
)
#: Fields of a library with the URDF's link parameters held (``inertia="urdf"``):
#: ``inertia`` and ``payload`` (the payload's body as given, or null); its
#: ``independent`` are then the payload's link-parameter columns, ``matrix`` empty.
HELD_FIELDS = ("inertia", "payload")


def library_document(library) -> dict:
    """The JSON values of a built base-parameter library (see the module docstring).

    Parameters
    ----------
    library : BaseParameterLibrary
        A fitted estimator's ``library_``.

    Returns
    -------
    dict
    """
    held = hasattr(library, "known_terms_")
    if not hasattr(library, "base_") and not held:
        raise ValueError(
            "a model file stores sympy terms or a URDF library; this model's terms "
            f"are another torch term function ({type(library).__name__}): keep it "
            "with pickle or joblib"
        )
    library._ensure_built()
    robot = library.robot_
    path = Path(robot.tree_.path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(
            f"the model's URDF {path} cannot be read to embed it in the model file "
            f"({exc}); restore the file, or keep the model with pickle or joblib"
        ) from None
    _check_urdf_text(text)
    random_state = library.random_state
    if not isinstance(random_state, int | np.integer):
        random_state = None  # the stored grouping does not need it
    if held:
        payload = library.payload_
        independent = [] if payload is None else payload.columns
        matrix = []
    else:
        independent, matrix = library.base_.independent, library.base_.matrix
    out = {
        "urdf": text,
        "urdf_name": path.name,
        "joints": list(robot.coordinates_),
        "locked": None
        if robot.locked is None
        else {str(k): float(v) for k, v in dict(robot.locked).items()},
        "armature": bool(robot.armature),
        "gravity": [float(g) for g in robot.gravity],
        "penalize": bool(robot.penalize),
        "consistent": bool(robot.consistent),
        "random_state": None if random_state is None else int(random_state),
        "independent": [int(i) for i in independent],
        "matrix": [[float(v) for v in row] for row in matrix],
    }
    if held:
        out.update(inertia="urdf", payload=library.payload)
    return out


def _check_urdf_text(text):
    if len(text) > MAX_URDF_CHARS:
        raise ValueError(
            f"the URDF has {len(text)} characters, more than a model file embeds "
            f"({MAX_URDF_CHARS})"
        )
    if re.search(r"<!\s*(DOCTYPE|ENTITY)", text, re.IGNORECASE):
        raise ValueError(
            "the URDF has a document type declaration (<!DOCTYPE or <!ENTITY), which "
            "a model file does not embed (entities could expand); expand it "
            "(xacro) into a plain URDF and fit with that"
        )


def urdf_cache_dir() -> Path:
    """Where embedded URDFs are written: ``$LAGSINDY_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/lagsindy/urdf`` (``~/.cache/lagsindy/urdf``), else a folder in
    the temporary directory."""
    env = os.environ.get(CACHE_ENV)
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "lagsindy" / "urdf"


def _materialize(text, name) -> Path:
    """The path of a file holding ``text`` (written once per distinct text)."""
    digest = hashlib.sha256(text.encode("utf-8")).hexdigest()[:24]
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(name).stem)[:60] or "robot"
    candidates = [urdf_cache_dir()]
    candidates.append(
        Path(tempfile.gettempdir())
        / f"lagsindy-urdf-{getattr(os, 'getuid', lambda: 0)()}"
    )
    last = None
    for folder in candidates:
        target = folder / f"{stem}-{digest}.urdf"
        try:
            if target.is_file() and target.read_text(encoding="utf-8") == text:
                return target
            folder.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=folder, suffix=".tmp")
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                fh.write(text)
            os.replace(tmp, target)
            return target
        except (OSError, UnicodeDecodeError) as exc:
            last = exc
    raise ValueError(
        f"cannot write the model's embedded URDF to {candidates[0]} ({last}); set "
        f"{CACHE_ENV} to a writable folder"
    )


def _fail(what):
    raise ValueError(f"the model file's robot field: {what}")


def _strings(value, what):
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        _fail(f"{what!r} must be a list of strings")
    return value


def _number(value, what):
    if isinstance(value, bool) or not isinstance(value, int | float):
        _fail(f"{what} must be a number")
    if not math.isfinite(float(value)):
        _fail(f"{what} is not finite")
    return float(value)


def library_from_document(doc, coordinates=None, terms=None):
    """The built :class:`~lagsindy.robots.fitting.BaseParameterLibrary` of
    :func:`library_document`'s values (each checked; ``ValueError`` naming the
    first problem), and, when given, with these ``coordinates`` and ``terms`` (the
    base parameters' names the model file lists)."""
    from .fitting import BaseParameterLibrary
    from .library import RobotLibrary

    held = isinstance(doc, dict) and "inertia" in doc
    fields = set(FIELDS) | (set(HELD_FIELDS) if held else set())
    if not isinstance(doc, dict) or set(doc) != fields:
        got = sorted(doc)[:12] if isinstance(doc, dict) else type(doc).__name__
        _fail(f"must be an object with exactly the fields {sorted(fields)}, got {got}")
    text, name = doc["urdf"], doc["urdf_name"]
    if not isinstance(text, str) or not isinstance(name, str) or len(name) > 200:
        _fail("'urdf' and 'urdf_name' must be strings")
    _check_urdf_text(text)
    joints = _strings(doc["joints"], "joints")
    locked = doc["locked"]
    if locked is not None and not isinstance(locked, dict):
        _fail("'locked' must be an object of joint positions or null")
    if locked is not None:
        locked = {str(k): _number(v, f"locked[{k!r}]") for k, v in locked.items()}
    flags = {}
    for key in ("armature", "penalize", "consistent"):
        if not isinstance(doc[key], bool):
            _fail(f"{key!r} must be true or false")
        flags[key] = doc[key]
    gravity = doc["gravity"]
    if not isinstance(gravity, list) or len(gravity) != 3:
        _fail("'gravity' must be a list of 3 numbers")
    gravity = tuple(_number(g, "gravity") for g in gravity)
    random_state = doc["random_state"]
    if random_state is not None and (
        isinstance(random_state, bool) or not isinstance(random_state, int)
    ):
        _fail("'random_state' must be an integer or null")
    independent = doc["independent"]
    if not isinstance(independent, list) or not all(
        isinstance(i, int) and not isinstance(i, bool) for i in independent
    ):
        _fail("'independent' must be a list of integers")
    matrix = doc["matrix"]
    if not isinstance(matrix, list) or not all(isinstance(r, list) for r in matrix):
        _fail("'matrix' must be a list of rows")
    rows = [[_number(v, "matrix entry") for v in r] for r in matrix]
    path = _materialize(text, name)
    robot = RobotLibrary(str(path), joints, locked=locked, gravity=gravity, **flags)
    try:
        robot.build()
    except (ValueError, KeyError, TypeError) as exc:
        _fail(f"its URDF does not rebuild the library: {exc}")
    if held:
        return _held_library(doc, robot, independent, random_state, coordinates, terms)
    names = list(robot.terms_)
    k_mat = np.asarray(rows, dtype=float).reshape(len(rows), -1)
    idx = np.asarray(independent, dtype=int)
    if (
        k_mat.shape != (len(idx), len(names))
        or len(idx) == 0
        or idx.min() < 0
        or idx.max() >= len(names)
        or np.any(np.diff(idx) <= 0)
        or not np.array_equal(k_mat[:, idx], np.eye(len(idx)))
    ):
        _fail(
            f"the base-parameter grouping does not fit the library's {len(names)} "
            "link parameters (a matrix of one row per independent column, the "
            "identity on those columns)"
        )
    zero = np.flatnonzero(np.abs(k_mat).sum(axis=0) == 0)  # in no base parameter
    base = BaseParameters(
        names=names,
        independent=idx,
        unidentifiable=zero,
        matrix=k_mat,
        labels=[_label(names, k_mat[i], idx[i]) for i in range(len(idx))],
        rank_qr=len(idx),
    )
    library = BaseParameterLibrary(
        robot, random_state=0 if random_state is None else random_state, base=base
    ).build()
    _check_same(library, coordinates, terms)
    return library


def _held_library(doc, robot, independent, random_state, coordinates, terms):
    """The :class:`~lagsindy.robots.known.KnownInertiaLibrary` of a document with
    ``inertia="urdf"``; its payload's columns must be the stored ones."""
    from .known import KnownInertiaLibrary

    payload = doc["payload"]
    if doc["inertia"] != "urdf" or not (payload is None or isinstance(payload, str)):
        _fail("'inertia' must be 'urdf' and 'payload' a link name, 'end' or null")
    robot.set_params(inertia="urdf")
    library = KnownInertiaLibrary(
        robot, payload=payload, random_state=0 if random_state is None else random_state
    ).build()
    found = [] if library.payload_ is None else list(library.payload_.columns)
    if found != list(independent):
        _fail(
            f"the payload's identifiable parameters rebuilt ({found}) are not the "
            f"stored ones ({independent})"
        )
    _check_same(library, coordinates, terms)
    return library


def _check_same(library, coordinates, terms):
    if (coordinates is not None and library.coordinates_ != list(coordinates)) or (
        terms is not None and library.terms_ != list(terms)
    ):
        raise ValueError(
            "the model file's coordinates and terms are not those of the robot "
            f"library it describes (coordinates {library.coordinates_}, "
            f"{len(library.terms_)} terms {library.terms_[:3]}...)"
        )
