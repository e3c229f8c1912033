"""Models you can use: standalone code, CasADi functions and linearizations.

A fitted :class:`~lagsindy.LagrangianSINDy` (or a model loaded from a file, its
``fitted_`` state, or any :class:`~lagsindy.MechanicalModel` such as a benchmark
system) becomes

* :func:`export_model`: a Python module (numpy only) or a C file and header with
  ``forward_dynamics(x, u)``, ``inverse_dynamics(q, q_dot, q_ddot)``,
  ``mass_matrix(q, q_dot)`` and ``energy(q, q_dot)``, numerically equal to the
  estimator, recording the model's provenance;
* :func:`to_casadi`: the same quantities as differentiable ``casadi.Function``
  objects (optional dependency);
* :func:`linearize`: continuous and zero-order-hold discrete ``A``, ``B`` at an
  equilibrium, which it checks.

States are ``x = [q..., q_dot...]``; the inputs ``u`` enter as generalized forces
``B u``. A learned model's ``B`` is the identity (``u`` are the generalized forces
the estimator was fitted with); pass ``input_matrix`` to say that, for example,
only a cart is driven.
"""

from __future__ import annotations

from pathlib import Path

from .c_code import BUILD_LINE, c_identifier, c_sources
from .casadi_model import CasadiModel, to_casadi
from .command import add_export_command, run_export
from .compiled import CModel, compile_c, find_compiler
from .equations import ModelEquations, model_equations
from .linearize import EQUILIBRIUM_RTOL, Linearization, discretize, linearize
from .python_code import load_python, python_source

FORMATS = ("python", "c")


def export_source(
    source, format: str = "python", *, name: str = "model", input_matrix=None, date=None
):
    """The text of an export, without writing files (see :func:`export_model`).

    Returns
    -------
    str (``format="python"``) or (str, str) (``format="c"``: source and header)
    """
    if format not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {format!r}")
    eq = model_equations(source, input_matrix, date=date)
    if format == "python":
        return python_source(eq, name)
    return c_sources(eq, name)


def export_model(
    source, path, format: str | None = None, *, input_matrix=None, date=None
):
    """Write a model's equations of motion as standalone Python or C.

    Parameters
    ----------
    source : LagrangianSINDy, FittedLagrangian or MechanicalModel
        A fitted (or loaded) estimator, its ``fitted_`` state, or a model.
    path : str or path-like
        The file to write: ``model.py`` for Python; ``model.c`` (or ``model``) for
        C, which also writes ``model.h`` beside it. The file's stem names the
        module and prefixes the C functions (``model_forward_dynamics``).
    format : {"python", "c"}, optional
        Default: from the suffix (``.c``/``.h``: C; otherwise Python).
    input_matrix : array-like of shape (n_dof, n_inputs), optional
        How the inputs ``u`` enter (generalized force ``B u``); default: the
        model's own (the identity for a learned model).
    date : str, optional
        The date recorded in the header (default: today).

    Returns
    -------
    pathlib.Path or tuple of pathlib.Path
        The Python file, or the C ``(source, header)``.

    Notes
    -----
    The Python module needs numpy only: ``forward_dynamics(x, u=None)``,
    ``state_derivative(x, u=None)``, ``inverse_dynamics(q, q_dot, q_ddot)``,
    ``mass_matrix(q, q_dot)`` and ``energy(q, q_dot)``, vectorized over leading
    axes. The C file builds with ``cc -O2 -shared -fPIC -o libmodel.so model.c -lm``
    (see :func:`compile_c` and :class:`CModel`). Both record the library, the
    coefficients, the lagsindy version and the date in their header.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from lagsindy.systems import cart_pendulum
    >>> from lagsindy.export import export_model
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> export_model(cart_pendulum(), folder / "cartpole.py").name
    'cartpole.py'
    """
    path = Path(path)
    if format is None:
        format = "c" if path.suffix in (".c", ".h") else "python"
    if format not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {format!r}")
    name = path.stem if path.suffix else path.name
    if format == "python":
        if not path.suffix:
            path = path.with_suffix(".py")
        path.write_text(
            export_source(
                source, "python", name=name, input_matrix=input_matrix, date=date
            ),
            encoding="utf-8",
        )
        return path
    c_path = path.with_name(name + ".c")
    h_path = path.with_name(name + ".h")
    text, header = export_source(
        source, "c", name=name, input_matrix=input_matrix, date=date
    )
    c_path.write_text(text, encoding="utf-8")
    h_path.write_text(header, encoding="utf-8")
    return c_path, h_path


__all__ = [
    "BUILD_LINE",
    "CModel",
    "CasadiModel",
    "EQUILIBRIUM_RTOL",
    "FORMATS",
    "Linearization",
    "ModelEquations",
    "add_export_command",
    "c_identifier",
    "compile_c",
    "discretize",
    "export_model",
    "export_source",
    "find_compiler",
    "linearize",
    "load_python",
    "model_equations",
    "run_export",
    "to_casadi",
]
