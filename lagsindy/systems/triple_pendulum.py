"""Triple pendulum (not in the paper): point masses on rods, or compound links."""

from __future__ import annotations

import numpy as np

from ..library import CandidateLibrary
from .base import System
from .planar_chain import chain_description, chain_lagrangian, chain_system

#: Order of the authors' parameter vector in ``EstimatedParameters_TriplePendulum.mat``.
MULTIARM_TRIPLE_KEYS = (
    "m1", "m2", "m3", "a1", "a2", "a3", "L1", "L2", "I1", "I2", "I3", "k1", "k2", "k3", "g",
)  # fmt: skip


def n_link_lagrangian(masses, lengths, g=9.81, names=None, *, com=None, inertia=None):
    """Lagrangian of a planar chain of rigid links (absolute angles, 0 hanging down).

    Point masses at the link ends by default; ``com`` (centre-of-mass distances) and
    ``inertia`` (about the centres of mass) make compound links (see
    :func:`~lagsindy.systems.planar_chain.chain_lagrangian`). Cosines of angle
    differences are expanded into products of sines and cosines, so the separated
    library can represent every term.

    Returns
    -------
    lagrangian : sympy.Expr
    names : list of str
    """
    lag, _, names = chain_lagrangian(
        masses, lengths, com=com, inertia=inertia, g=g, names=names, compact=False
    )
    return lag, names


def triple_pendulum(
    masses=(1.0, 1.0, 1.0),
    lengths=(1.0, 1.0, 1.0),
    g: float = 9.81,
    *,
    com=None,
    inertia=None,
    damping=None,
) -> System:
    """Three links on revolute joints; all joints driven for active runs.

    By default three point masses on massless rods. Compound links: ``com`` (distance
    ``a_i`` from joint ``i`` to the centre of mass of link ``i``), ``inertia`` (``I_i``
    about the centre of mass) and ``damping`` (joint coefficients ``k_i``, acting on the
    relative joint velocities ``q_i_dot - q_{i-1}_dot``); see
    :func:`~lagsindy.systems.planar_chain.chain_lagrangian` for the Lagrangian.
    :func:`multiarm_triple_pendulum` builds the authors' model of the MultiArm rig.

    Initial angles ``U(-pi/2, pi/2)``, velocities zero. Library: the separated
    construction of degree 2 over the three angles (222 terms); the chain library
    (``CandidateLibrary.chain``, 12 terms) is the natural one for this system.
    """
    lagrangian, diss, names = chain_lagrangian(
        masses,
        lengths,
        com=com,
        inertia=inertia,
        damping=damping,
        g=g,
        compact=False,
    )
    if len(names) != 3:
        raise ValueError(f"a triple pendulum has 3 links, got {len(names)} masses")
    simple = (
        com is None
        and inertia is None
        and damping is None
        and tuple(masses) == (1.0,) * 3
        and tuple(lengths) == (1.0,) * 3
        and g == 9.81
    )
    return chain_system(
        lagrangian,
        diss,
        names,
        library=lambda: CandidateLibrary.separated(names, angles="all", degree=2),
        paper_input=lambda t, w: np.stack(
            [np.cos(w * t), np.sin(w * t), np.cos(w * t) - np.sin(w * t)], 1
        ),
        name="triple pendulum",
        description="three 1 kg point masses on 1 m rods, g = 9.81"
        if simple
        else chain_description(masses, lengths, g, com, inertia, damping),
    )


def multiarm_triple_pendulum(parameters=None, path=None) -> System:
    """The authors' model of the MultiArm triple pendulum, with their fitted parameters.

    Kaheman et al., "The Experimental Multi-Arm Pendulum on a Cart" (arXiv:2205.06231,
    MIT license): three compound links with joint damping, equations of motion in
    their ``TriplePendulumODE_Mounted.m``. Coordinates ``phi1..phi3`` are the recorded
    angles minus pi (0 hanging down; the recordings use pi).

    Parameters
    ----------
    parameters : sequence of 15 floats or dict, optional
        ``[m1, m2, m3, a1, a2, a3, L1, L2, I1, I2, I3, k1, k2, k3, g]`` (the order of
        ``EstimatedParameters_TriplePendulum.mat``) or a dict with these keys.
        Default: read from that file.
    path : str or path-like, optional
        Folder of the data (default: :func:`lagsindy.io.find_multiarm_pendulum`).

    Returns
    -------
    System
        With ``system.parameters`` the dict of the parameters used.
    """
    if parameters is None:
        from pathlib import Path

        from scipy.io import loadmat

        from ..io import find_multiarm_pendulum

        folder = find_multiarm_pendulum() if path is None else Path(path)
        mat = loadmat(folder / "EstimatedParameters_TriplePendulum.mat")
        parameters = np.asarray(mat["EstimatedParameters"], dtype=float).ravel()
    if isinstance(parameters, dict):
        missing = [k for k in MULTIARM_TRIPLE_KEYS if k not in parameters]
        if missing:
            raise ValueError(f"parameters lacks {missing}")
        p = {k: float(parameters[k]) for k in MULTIARM_TRIPLE_KEYS}
    else:
        values = np.asarray(parameters, dtype=float).ravel()
        if values.size != len(MULTIARM_TRIPLE_KEYS):
            raise ValueError(
                f"parameters needs {len(MULTIARM_TRIPLE_KEYS)} values "
                f"{list(MULTIARM_TRIPLE_KEYS)}, got {values.size}"
            )
        p = dict(zip(MULTIARM_TRIPLE_KEYS, map(float, values)))
    names = ["phi1", "phi2", "phi3"]
    lag, diss, _ = chain_lagrangian(
        [p["m1"], p["m2"], p["m3"]],
        [p["L1"], p["L2"], p["a3"]],
        com=[p["a1"], p["a2"], p["a3"]],
        inertia=[p["I1"], p["I2"], p["I3"]],
        damping=[p["k1"], p["k2"], p["k3"]],
        g=p["g"],
        names=names,
        compact=True,
    )
    system = chain_system(
        lag,
        diss,
        names,
        library=lambda: CandidateLibrary.chain(names),
        name="MultiArm triple pendulum (authors' model)",
        description="the authors' fitted compound-link model, angles 0 hanging down",
        prior=False,
    )
    system.parameters = p
    return system
