"""Compile an exported C model and call it from Python (ctypes).

The exported ``.c`` needs nothing from lagsindy; these helpers are a convenience
(and what the tests and ``benchmarks/export.py`` use): :func:`compile_c` runs the
build line the header states, :class:`CModel` calls the functions on numpy arrays.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np

from .c_code import c_identifier


def find_compiler() -> str | None:
    """The C compiler to use: ``$CC``, else ``cc``, ``gcc`` or ``clang`` on the PATH."""
    env = os.environ.get("CC")
    if env and shutil.which(env):
        return env
    for name in ("cc", "gcc", "clang"):
        if shutil.which(name):
            return name
    return None


def compile_c(
    source, output=None, *, compiler: str | None = None, flags=("-O2",)
) -> Path:
    """Build a shared library from an exported ``.c`` file.

    Runs ``<compiler> -O2 -shared -fPIC -o <output> <source> -lm``.

    Parameters
    ----------
    source : str or path-like
        The ``.c`` file (its ``.h`` beside it).
    output : str or path-like, optional
        Default: ``lib<stem>.so`` beside the source.
    compiler : str, optional
        Default: :func:`find_compiler`.
    flags : sequence of str, default=("-O2",)

    Returns
    -------
    pathlib.Path
        The shared library.

    Raises
    ------
    RuntimeError
        When no compiler is found or the build fails (with the compiler's message).
    """
    source = Path(source)
    output = (
        Path(output) if output is not None else source.with_name(f"lib{source.stem}.so")
    )
    compiler = compiler or find_compiler()
    if compiler is None:
        raise RuntimeError(
            "no C compiler found (set $CC or install cc, gcc or clang); the exported "
            f"{source.name} builds with: cc -O2 -shared -fPIC -o {output.name} "
            f"{source.name} -lm"
        )
    cmd = [compiler, *flags, "-shared", "-fPIC", "-o", str(output), str(source), "-lm"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(
            f"building {source} failed ({' '.join(cmd)}):\n{done.stderr[-4000:]}"
        )
    return output


def _pointer(a):
    return ctypes.c_void_p(a.ctypes.data)


class CModel:
    """An exported model compiled to a shared library, called through ctypes.

    Parameters
    ----------
    library : str or path-like
        The shared library (see :func:`compile_c`).
    name : str
        The name the model was exported under (its functions' prefix).

    Attributes
    ----------
    n_dof, n_inputs : int
    functions : dict
        The raw ctypes functions by short name (``"forward_dynamics"``...), whose
        arguments are pointers to doubles (``ctypes.c_void_p``).

    Notes
    -----
    A process loads a shared library once per path: a library rebuilt at the same
    path is not reloaded (the dynamic loader returns the first one). Build each
    version of a model under its own file name.
    """

    def __init__(self, library, name: str):
        self.path = Path(library).resolve()  # a bare name would search the system
        self._lib = ctypes.CDLL(str(self.path))
        p = c_identifier(name)
        self.n_dof = int(getattr(self._lib, f"{p}_n_dof")())
        self.n_inputs = int(getattr(self._lib, f"{p}_n_inputs")())
        void = ctypes.c_void_p
        signatures = {
            "forward_dynamics": (ctypes.c_int, [void, void, void]),
            "forward_dynamics_batch": (
                ctypes.c_int,
                [ctypes.c_size_t, void, void, void],
            ),
            "state_derivative": (ctypes.c_int, [void, void, void]),
            "inverse_dynamics": (None, [void, void, void, void]),
            "mass_matrix": (None, [void, void, void]),
            "energy": (ctypes.c_double, [void, void]),
        }
        self.functions = {}
        for short, (restype, argtypes) in signatures.items():
            f = getattr(self._lib, f"{p}_{short}")
            f.restype, f.argtypes = restype, argtypes
            self.functions[short] = f

    def _rows(self, a, width, what):
        a = np.ascontiguousarray(a, dtype=float)
        if a.ndim == 0 or a.shape[-1] != width:
            raise ValueError(f"{what} must have shape (..., {width}), got {a.shape}")
        return a.reshape(-1, width), a.shape[:-1]

    def forward_dynamics(self, x, u=None) -> np.ndarray:
        """Accelerations at states ``x`` (..., 2 n_dof) under inputs ``u``."""
        n = self.n_dof
        x, shape = self._rows(x, 2 * n, "x")
        if u is not None:
            u = np.asarray(u, dtype=float)
            if self.n_inputs == 1 and (u.ndim == 0 or u.ndim == len(shape)):
                u = u[..., None]
            if u.shape[-1] != self.n_inputs:
                raise ValueError(
                    f"u must have shape (..., {self.n_inputs}), got {u.shape}"
                )
            u = np.ascontiguousarray(np.broadcast_to(u, shape + (self.n_inputs,)))
            u = u.reshape(-1, self.n_inputs)
        out = np.empty((x.shape[0], n))
        status = self.functions["forward_dynamics_batch"](
            x.shape[0], _pointer(x), None if u is None else _pointer(u), _pointer(out)
        )
        if status != 0:
            raise np.linalg.LinAlgError("singular mass matrix at some of the states")
        return out.reshape(shape + (n,))

    def _each(self, function, arrays, width_out):
        n = self.n_dof
        rows = [
            self._rows(a, n, "q, q_dot and q_ddot")[0]
            for a in np.broadcast_arrays(*arrays)
        ]
        shape = np.broadcast_shapes(*(np.shape(a)[:-1] for a in arrays))
        out = np.empty((rows[0].shape[0], width_out))
        for s in range(rows[0].shape[0]):
            function(*[_pointer(r[s]) for r in rows], _pointer(out[s]))
        return out, shape

    def inverse_dynamics(self, q, q_dot, q_ddot) -> np.ndarray:
        """Generalized forces ``M q_ddot + r``, shape (..., n_dof)."""
        out, shape = self._each(
            self.functions["inverse_dynamics"], [q, q_dot, q_ddot], self.n_dof
        )
        return out.reshape(shape + (self.n_dof,))

    def mass_matrix(self, q, q_dot) -> np.ndarray:
        """Mass matrices, shape (..., n_dof, n_dof)."""
        n = self.n_dof
        out, shape = self._each(self.functions["mass_matrix"], [q, q_dot], n * n)
        return out.reshape(shape + (n, n))

    def energy(self, q, q_dot) -> np.ndarray:
        """Energy function, shape (...)."""
        n = self.n_dof
        q, qd = np.broadcast_arrays(np.asarray(q, float), np.asarray(q_dot, float))
        qr, shape = self._rows(q, n, "q")
        qdr, _ = self._rows(qd, n, "q_dot")
        f = self.functions["energy"]
        out = np.array([f(_pointer(a), _pointer(b)) for a, b in zip(qr, qdr)])
        return out.reshape(shape)


__all__ = ["CModel", "compile_c", "find_compiler"]
