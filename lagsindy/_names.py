"""Coordinate naming rules, with no heavy imports (the command line checks names
before it loads sympy or torch)."""

from __future__ import annotations

import re

VELOCITY_SUFFIX = "_dot"
ACCELERATION_SUFFIX = "_ddot"
# Names a term string reads as functions or constants (lagsindy._expr maps them).
FUNCTION_NAMES = (
    "sin",
    "cos",
    "tan",
    "sinh",
    "cosh",
    "tanh",
    "exp",
    "log",
    "sqrt",
    "Abs",
    "abs",
    "sign",
)
CONSTANT_NAMES = ("pi", "E")
NAME_RE = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")


def name_problem(name) -> str | None:
    """What is wrong with ``name`` as a coordinate name (``None``: nothing)."""
    if not isinstance(name, str) or not NAME_RE.match(name):
        return (
            f"coordinate name {name!r} is not valid: use letters, digits and '_', "
            "starting with a letter (e.g. 'theta', 'x1')"
        )
    if name in FUNCTION_NAMES or name in CONSTANT_NAMES:
        return (
            f"coordinate name {name!r} is reserved (a function or constant name); "
            "choose another name"
        )
    if name.endswith(VELOCITY_SUFFIX) or name.endswith(ACCELERATION_SUFFIX):
        return (
            f"coordinate name {name!r} ends in '{VELOCITY_SUFFIX}' or "
            f"'{ACCELERATION_SUFFIX}', which are reserved for its derivatives"
        )
    return None


def repeated_name(names) -> str | None:
    """The first name that appears twice in ``names``, as a message (or ``None``)."""
    seen = set()
    for name in names:
        if name in seen:
            return f"coordinate name {name!r} appears twice"
        seen.add(name)
    return None
