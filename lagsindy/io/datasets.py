"""Loaders for the measured data that ship with lagsindy (the MultiArm pendulums)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd

# ----------------------------------------------------------------------------- data
MULTIARM_ENV = "LAGSINDY_MULTIARM_DIR"
_MULTIARM_FILES = {
    "single": "SinglePendulumDataForParameterEstimation.mat",
    "double": "DoublePendulumDataForParameterEstimation.mat",
    "triple": "TriplePendulumDataForParameterEstimation.mat",
}
_MULTIARM_PARAMETER_FILES = {
    "single": "EstimatedParameters_SinglePendulum.mat",
    "double": "EstimatedParameters_DoublePendulum.mat",
    "triple": "EstimatedParameters_TriplePendulum.mat",
}
# The order of the authors' parameter vectors (see the data README).
MULTIARM_PARAMETER_NAMES = {
    "single": ("a1", "m1", "I1", "k1", "g"),
    "double": ("m1", "m2", "a1", "a2", "L1", "I1", "I2", "k1", "k2", "g"),
    "triple": (
        *("m1", "m2", "m3", "a1", "a2", "a3", "L1", "L2"),
        *("I1", "I2", "I3", "k1", "k2", "k3", "g"),
    ),
}
_MULTIARM_SHIPPED = (
    Path(__file__).resolve().parent.parent / "data" / "multiarm_pendulum"
)


def find_multiarm_pendulum(start=None) -> Path:
    """Locate the MultiArm-Pendulum recordings.

    The recordings ship with lagsindy (``lagsindy/data/multiarm_pendulum``, MIT
    license, see its ``README.md`` and ``LICENSE``), so this normally returns that
    folder. Order: ``$LAGSINDY_MULTIARM_DIR`` if set (an override, e.g. for a newer
    download); then ``shared/data/multiarm_pendulum`` in ``start`` or one of its
    parents, when ``start`` is given; then the shipped folder.

    Parameters
    ----------
    start : str or path-like, default=None
        A folder whose parents hold ``shared/data/multiarm_pendulum``.

    Returns
    -------
    pathlib.Path
        The folder holding the ``.mat`` files.

    Raises
    ------
    FileNotFoundError
        With a message saying where the data were looked for and how to get them.
    """
    env = os.environ.get(MULTIARM_ENV)
    if env:
        p = Path(env)
        if p.is_dir():
            return p
        raise FileNotFoundError(
            f"${MULTIARM_ENV} is set to {env}, which is not a folder; unset it to use "
            "the recordings shipped with lagsindy, or point it at the folder holding "
            "the .mat files"
        )
    tried = []
    if start is not None:
        s = Path(start).resolve()
        for folder in [s, *s.parents]:
            candidate = folder / "shared" / "data" / "multiarm_pendulum"
            tried.append(str(candidate))
            if candidate.is_dir():
                return candidate
    tried.append(str(_MULTIARM_SHIPPED))
    if (_MULTIARM_SHIPPED / _MULTIARM_FILES["single"]).is_file():
        return _MULTIARM_SHIPPED
    raise FileNotFoundError(
        f"the MultiArm-Pendulum recordings were not found (looked in {tried}); this "
        "lagsindy installation lacks its data files. Reinstall lagsindy, or download "
        "ParameterEstimation/ from github.com/dynamicslab/MultiArm-Pendulum and set "
        f"${MULTIARM_ENV} to that folder"
    )


def _multiarm_file(path, which: str, files: dict) -> Path:
    if which not in files:
        raise ValueError(f"which must be 'single', 'double' or 'triple', got {which!r}")
    p = find_multiarm_pendulum() if path is None else Path(path)
    if p.is_dir():
        p = p / files[which]
    if not p.is_file():
        raise FileNotFoundError(
            f"no MultiArm-Pendulum file at {p}; pass the folder holding "
            f"{files[which]}, or path=None for the recordings shipped with lagsindy"
        )
    return p


def load_multiarm_pendulum(
    path=None, which: str = "single", split: str = "id"
) -> pd.DataFrame:
    """Load the MultiArm-Pendulum free-swing recordings (Kaheman et al., 2022).

    Encoder recordings of a real single, double or triple pendulum (cart locked, no
    input), sampled at 1 kHz, split by the authors into consecutive identification
    (``"id"``) and validation (``"vad"``) segments. Angles are absolute joint angles
    in radians with ``pi`` meaning hanging straight down; the velocities were
    filtered by the authors. Accelerations are not recorded. The recordings ship
    with lagsindy (MIT license); :func:`load_multiarm_parameters` gives the authors'
    fitted parameters.

    Parameters
    ----------
    path : str or path-like, default=None
        The ``.mat`` file, or the folder holding it. ``None``: the shipped
        recordings (or ``$LAGSINDY_MULTIARM_DIR``); see
        :func:`find_multiarm_pendulum`.
    which : {"single", "double", "triple"}, default="single"
        Which pendulum.
    split : {"id", "vad"}, default="id"
        The authors' identification or validation segments.

    Returns
    -------
    pandas.DataFrame
        Columns ``trajectory`` (segment index), ``t`` (seconds, continuous over the
        record), the angles ``theta`` (single), ``theta1, theta2`` (double) or
        ``theta1, theta2, theta3`` (triple), and the authors' filtered velocities
        ``theta_dot_filtered`` (``theta1_dot_filtered``, ...).

    Raises
    ------
    ValueError
        If ``which`` or ``split`` is unknown, or the file is not a MultiArm-Pendulum
        data file.
    FileNotFoundError
        If the file is missing (the message says where it was looked for).

    References
    ----------
    E. Kaheman, U. Fasel, J. J. Bramburger, B. Strom, J. N. Kutz and S. L. Brunton,
    "The Experimental Multi-Arm Pendulum on a Cart: A Benchmark System for Chaos,
    Learning, and Control", arXiv:2205.06231, 2022. Data: MIT license.

    Examples
    --------
    >>> from lagsindy.io import load_multiarm_pendulum
    >>> df = load_multiarm_pendulum(which="triple")
    >>> [c for c in df.columns if not c.endswith("filtered")]
    ['trajectory', 't', 'theta1', 'theta2', 'theta3']
    """
    from scipy.io import loadmat

    if split not in ("id", "vad"):
        raise ValueError(
            f"split must be 'id' (identification) or 'vad' (validation), got {split!r}"
        )
    p = _multiarm_file(path, which, _MULTIARM_FILES)
    mat = loadmat(p)
    key_y, key_t = f"Y_{split}", f"Time_{split}"
    if key_y not in mat or key_t not in mat:
        raise ValueError(
            f"{p} lacks {key_y!r}/{key_t!r}: not a MultiArm-Pendulum data file"
        )
    segments = mat[key_y].ravel()
    times = mat[key_t].ravel()
    n = {"single": 1, "double": 2, "triple": 3}[which]
    angles = ["theta"] if n == 1 else [f"theta{i + 1}" for i in range(n)]
    frames = []
    for k, (y, t) in enumerate(zip(segments, times)):
        y = np.asarray(y, dtype=float)
        t = np.asarray(t, dtype=float).ravel()
        if y.shape != (2 * n, t.size):
            raise ValueError(
                f"segment {k} of {p} has shape {y.shape}, expected ({2 * n}, {t.size})"
            )
        cols = {"trajectory": np.full(t.size, k), "t": t}
        for i, a in enumerate(angles):
            cols[a] = y[i]
        for i, a in enumerate(angles):
            cols[f"{a}_dot_filtered"] = y[n + i]
        frames.append(pd.DataFrame(cols))
    return pd.concat(frames, ignore_index=True)


def load_multiarm_parameters(which: str = "single", path=None) -> dict:
    """The MultiArm-Pendulum authors' fitted parameters, by name.

    Per joint ``j``: mass ``mj`` (kg), distance ``aj`` from the joint to the centre
    of mass (m), inertia ``Ij`` about the centre of mass (kg m^2), joint
    coefficient ``kj``; arm lengths ``Lj`` (m) between joints; gravity ``g``. For
    the triple pendulum the joint coefficients act on relative joint velocities
    (see ``TriplePendulumODE_Mounted.m`` next to the data, the authors' equations
    of motion).

    Parameters
    ----------
    which : {"single", "double", "triple"}, default="single"
        Which pendulum.
    path : str or path-like, default=None
        The parameter ``.mat`` file or its folder; ``None``: the shipped data.

    Returns
    -------
    dict of str to float
        ``single``: a1, m1, I1, k1, g; ``double``: m1, m2, a1, a2, L1, I1, I2, k1,
        k2, g; ``triple``: m1, m2, m3, a1, a2, a3, L1, L2, I1, I2, I3, k1, k2, k3, g
        (the authors' order).

    Examples
    --------
    >>> from lagsindy.io import load_multiarm_parameters
    >>> round(load_multiarm_parameters("triple")["g"], 2)
    9.81
    """
    from scipy.io import loadmat

    p = _multiarm_file(path, which, _MULTIARM_PARAMETER_FILES)
    mat = loadmat(p)
    if "EstimatedParameters" not in mat:
        raise ValueError(f"{p} lacks 'EstimatedParameters': not a parameter file")
    values = np.asarray(mat["EstimatedParameters"], dtype=float).ravel()
    names = MULTIARM_PARAMETER_NAMES[which]
    if values.size != len(names):
        raise ValueError(
            f"{p} holds {values.size} parameters, expected {len(names)} ({names})"
        )
    return {name: float(v) for name, v in zip(names, values)}


__all__ = [
    "find_multiarm_pendulum",
    "load_multiarm_parameters",
    "load_multiarm_pendulum",
]
