"""The ``lagsindy export`` command: a saved model to standalone Python or C.

    lagsindy export model.json --format c --out build/cartpole.c --input-matrix "1;0"

Register it with :func:`add_export_command` on the ``lagsindy`` parser's
subparsers; :func:`run_export` runs it (returns the exit status, raises
``ValueError``/``OSError`` with a one-line message on bad input, as the other
commands do). It reads model files with :mod:`lagsindy.io.model_file` (a lower
layer) and imports it only when it runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def parse_matrix(text: str):
    """``"1;0"`` -> [[1.0], [0.0]]: rows separated by ``;``, entries by ``,``."""
    import numpy as np

    try:
        rows = [
            [float(v) for v in row.split(",")] for row in text.strip().split(";") if row
        ]
    except ValueError:
        raise ValueError(
            f"--input-matrix must be numbers, rows separated by ';' and entries by "
            f"',' (e.g. '1;0' for a force on the first of two coordinates), got "
            f"{text!r}"
        ) from None
    if not rows or len({len(r) for r in rows}) != 1:
        raise ValueError(
            f"--input-matrix must have rows of equal length (e.g. '1,0;0,1'), got "
            f"{text!r}"
        )
    return np.asarray(rows, dtype=float)


def add_export_command(subparsers):
    """Add the ``export`` subcommand to the ``lagsindy`` parser's subparsers.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        From ``parser.add_subparsers(...)``.

    Returns
    -------
    argparse.ArgumentParser
        The subcommand's parser (its ``func`` default is :func:`run_export`).
    """
    p = subparsers.add_parser(
        "export",
        help="write a saved model as standalone Python (numpy) or C code",
        description="Write a saved model's equations of motion as a Python module "
        "that needs numpy only, or as C99 (a .c and a .h): forward_dynamics(x, u), "
        "inverse_dynamics(q, q_dot, q_ddot), mass_matrix(q, q_dot) and "
        "energy(q, q_dot), with the model's provenance in the header.",
    )
    p.add_argument("model", help="saved model (JSON, from lagsindy fit or est.save)")
    p.add_argument(
        "--format",
        choices=("python", "c"),
        default="python",
        help="python: one .py module; c: a .c and a .h (cc -O2 -shared -fPIC)",
    )
    p.add_argument(
        "--out",
        default=None,
        help="file to write (default: the model file's name with .py or .c, in the "
        "current folder); its name prefixes the C functions",
    )
    p.add_argument(
        "--input-matrix",
        default=None,
        metavar="ROWS",
        help="how the inputs u enter: generalized forces B u, rows separated by ';' "
        "and entries by ',' (e.g. '1;0': one input on the first of two "
        "coordinates); default: the identity (u are the generalized forces)",
    )
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")
    p.set_defaults(func=run_export)
    return p


def run_export(args: argparse.Namespace) -> int:
    """Run ``lagsindy export`` with parsed arguments; returns the exit status 0.

    Raises
    ------
    ValueError
        For an invalid model file or option (the message says what to do).
    OSError
        When a file cannot be read or written.
    """
    from ..io.model_file import read_model_file
    from .c_code import c_sources
    from .equations import model_equations
    from .python_code import python_source

    model = Path(args.model)
    _, fitted, _ = read_model_file(model)
    matrix = None if args.input_matrix is None else parse_matrix(args.input_matrix)
    suffix = ".py" if args.format == "python" else ".c"
    out = Path(args.out) if args.out else Path(model.stem + suffix)
    if out.suffix == "":
        out = out.with_suffix(suffix)
    name = out.stem
    eq = model_equations(fitted, matrix)
    eq.provenance["source"] += f", read from {model.name}"
    if args.format == "python":
        out.write_text(python_source(eq, name), encoding="utf-8")
        written = [out]
    else:
        source, header = c_sources(eq, name)
        written = [out.with_suffix(".c"), out.with_suffix(".h")]
        written[0].write_text(source, encoding="utf-8")
        written[1].write_text(header, encoding="utf-8")
    if not getattr(args, "quiet", False):
        for path in written:
            print(f"wrote {path}")
    return 0


__all__ = ["add_export_command", "parse_matrix", "run_export"]
