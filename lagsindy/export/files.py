"""Writing exports to files: :func:`export_model` and :func:`export_source`."""

from __future__ import annotations

from pathlib import Path

from .c_code import c_sources
from .equations import model_equations
from .python_code import python_source

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


__all__ = ["FORMATS", "export_model", "export_source"]
