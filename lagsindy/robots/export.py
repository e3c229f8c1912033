r"""Physically consistent link parameters, and writing them back into a URDF.

A body's 10 parameters are *physically consistent* when its pseudo-inertia

.. math::

    J = \begin{bmatrix} \tfrac12 \operatorname{tr}(I) \mathbb 1 - I & h \\
        h^\top & m \end{bmatrix}

is positive semidefinite (Wensing, Kim and Slotine, 2018): a mass distribution
exists with these moments. Identified *base* parameters fix only combinations;
:func:`consistent_parameters` picks full parameters that reproduce them exactly,
each body's ``J`` positive semidefinite and rotor inertias non-negative, as close as
possible to a reference (the URDF's own values by default): the projection onto the
intersection of an affine set and a product of semidefinite cones, by Dykstra's
alternating projections (both projections are closed-form: a weighted least squares
and an eigenvalue clip).
"""

from __future__ import annotations

import dataclasses
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from sklearn.base import clone

from .urdf import inertia_matrix

# Smallest eigenvalue kept in the scaled pseudo-inertias (relative to the mean mass):
# the last, affine step moves the parameters by about the stopping tolerance (1e-10
# relative), so a margin 1e4 times larger keeps them positive definite (with 1e-8 an
# inconsistent reference ended at -1e-10).
MARGIN = 1e-6


def pseudo_inertia(params) -> np.ndarray:
    """The 4 x 4 pseudo-inertia of a 10-vector ``[m, h, Ixx, Ixy, Iyy, Ixz, Iyz, Izz]``."""
    params = np.asarray(params, dtype=float)
    i = inertia_matrix(params)
    out = np.zeros((4, 4))
    out[:3, :3] = 0.5 * np.trace(i) * np.eye(3) - i
    out[:3, 3] = out[3, :3] = params[1:4]
    out[3, 3] = params[0]
    return out


def feasibility(params, n_bodies: int) -> np.ndarray:
    """Smallest eigenvalue of each body's pseudo-inertia (>= 0: consistent)."""
    params = np.asarray(params, dtype=float)
    return np.array(
        [
            np.linalg.eigvalsh(pseudo_inertia(params[10 * b : 10 * b + 10]))[0]
            for b in range(n_bodies)
        ]
    )


def _scaled_map(length):
    """``A`` with ``vec(D J D) = A @ params``, ``D = diag(1/length, 1/length, 1/length, 1)``."""
    a = np.zeros((16, 10))
    for k in range(10):
        e = np.zeros(10)
        e[k] = 1.0
        d = np.diag([1.0 / length] * 3 + [1.0])
        a[:, k] = (d @ pseudo_inertia(e) @ d).ravel()
    return a


@dataclasses.dataclass
class ConsistentParameters:
    """Full parameters reproducing identified base parameters, physically consistent.

    Attributes
    ----------
    parameters : ndarray of shape (n_terms,)
        Link parameters (10 per body) then rotor inertias.
    violation : float
        ``max |matrix @ parameters - beta|`` relative to ``max |beta|`` (0 when the
        base parameters are reproduced exactly).
    min_eigenvalue : ndarray of shape (n_bodies,)
        Smallest eigenvalue of each body's pseudo-inertia (> 0).
    success : bool
        Consistent parameters reproducing the base parameters were found.
    """

    parameters: np.ndarray
    violation: float
    min_eigenvalue: np.ndarray
    success: bool


def consistent_parameters(
    library, base, beta, reference=None, max_iter=20000, tol=1e-10
):
    """Physically consistent full parameters whose base parameters are ``beta``.

    The projection of ``reference`` onto the intersection of the affine set
    ``base.matrix @ pi = beta`` and the consistent set (every body's pseudo-inertia
    positive semidefinite, rotor inertias non-negative), by Dykstra's alternating
    projections; the distance is the Frobenius norm of the pseudo-inertias with
    lengths in units of the reference's radius of gyration (so masses, first moments
    and inertias weigh alike), rotor inertias in the same units.

    Parameters
    ----------
    library : RobotLibrary
    base : BaseParameters
        From :func:`lagsindy.robots.base_parameters` for this library.
    beta : array-like of shape (n_base,)
        Identified base parameter values.
    reference : array-like of shape (n_terms,), default=None
        Values to stay close to; default the URDF's (``library.nominal_``).
    max_iter : int, default=20000
    tol : float, default=1e-10
        Stop when the two projections agree to this (relative).

    Returns
    -------
    ConsistentParameters
        Its ``parameters`` are consistent and reproduce ``beta`` to round-off (the
        last projection is the affine one). When ``beta`` is outside the consistent
        set they are the consistent point found, ``violation`` says how far its base
        parameters are from ``beta``, and a ``UserWarning`` is raised.
    """
    library._ensure_built()
    n_bodies = len(library.tree_.bodies)
    n_terms = len(library)
    n_link = 10 * n_bodies
    ref = np.asarray(library.nominal_ if reference is None else reference, dtype=float)
    beta = np.asarray(beta, dtype=float)
    k_mat = base.matrix
    masses = ref[0:n_link:10]
    traces = np.array(
        [np.trace(inertia_matrix(ref[10 * b : 10 * b + 10])) for b in range(n_bodies)]
    )
    heavy = masses > 0
    usable = heavy & (traces > 0)
    # a typical radius of gyration (median: one inconsistent reference body must not
    # decide the units)
    length = (
        float(np.sqrt(np.median(traces[usable] / masses[usable])))
        if usable.any()
        else 1.0
    )
    a = _scaled_map(length)
    g_body = a.T @ a
    metric = np.zeros((n_terms, n_terms))
    for b in range(n_bodies):
        metric[10 * b : 10 * b + 10, 10 * b : 10 * b + 10] = g_body
    metric[n_link:, n_link:] = np.eye(n_terms - n_link) / length**4
    g_inv_kt = np.linalg.solve(metric, k_mat.T)
    gram = k_mat @ g_inv_kt

    def to_affine(x):
        return x - g_inv_kt @ np.linalg.solve(gram, k_mat @ x - beta)

    a_pinv = np.linalg.pinv(a)
    mass_scale = max(masses.max(initial=0.0), 1e-300)
    # clip at a small margin, so that the final (affine) step keeps J positive definite
    margin = MARGIN * (masses[heavy].mean() if heavy.any() else 1.0)

    def to_consistent(x):
        out = x.copy()
        js = np.einsum("ij,bj->bi", a, x[:n_link].reshape(n_bodies, 10)).reshape(
            -1, 4, 4
        )
        w, v = np.linalg.eigh(0.5 * (js + js.transpose(0, 2, 1)))
        low = w[:, 0] < margin
        if low.any():
            clipped = np.einsum(
                "bij,bj,bkj->bik", v[low], np.maximum(w[low], margin), v[low]
            )
            out[:n_link].reshape(n_bodies, 10)[low] = clipped.reshape(-1, 16) @ a_pinv.T
        out[n_link:] = np.maximum(x[n_link:], 0.0)
        return out

    def norm(x):
        return float(np.sqrt(x @ metric @ x))

    scale = max(norm(ref), 1e-300)
    x, p, q = ref.copy(), np.zeros(n_terms), np.zeros(n_terms)
    for _ in range(int(max_iter)):
        y = to_affine(x + p)
        p = x + p - y
        x_new = to_consistent(y + q)
        q = y + q - x_new
        gap = norm(x_new - y)
        x = x_new
        if gap <= tol * scale:
            break
    pi = to_affine(x)
    # the affine step's last correction (about the stopping tolerance times the base
    # parameters, measured 1e-11) on rotor inertias that sit at their bound 0
    tiny = 1e-9 * max(np.abs(beta).max(initial=0.0), mass_scale * length**2)
    pi[n_link:] = np.where(
        pi[n_link:] > -tiny, np.maximum(pi[n_link:], 0.0), pi[n_link:]
    )
    lam = feasibility(pi, n_bodies)
    success = bool(lam.min() > 0 and np.all(pi[n_link:] >= 0))
    if not success:  # keep the consistent point; it misses the base parameters
        pi = x
        lam = feasibility(pi, n_bodies)
    violation = float(
        np.abs(k_mat @ pi - beta).max() / max(np.abs(beta).max(initial=0.0), 1e-300)
    )
    if not success:
        warnings.warn(
            "no physically consistent parameters reproduce these base parameters: "
            f"the nearest consistent ones miss them by {violation:.2g} (relative); the "
            "base parameters are outside the consistent set (fit them with the "
            "consistency constraint)",
            UserWarning,
            stacklevel=2,
        )
    return ConsistentParameters(
        parameters=pi, violation=violation, min_eigenvalue=lam, success=success
    )


def _fmt(x: float) -> str:
    return f"{x:.12g}"


def to_urdf(library, parameters, path, *, damping=None, friction=None):
    """Write link parameters and joint friction into a copy of the library's URDF.

    Each moving body's 10 parameters go into its own link's ``<inertial>`` (centre of
    mass as the origin, no rotation, inertia about the centre of mass); links that
    were merged into it (fixed joints, locked joints) lose their ``<inertial>``, since
    the body's values already include them. Reading the written file back with the
    same joints and locked positions gives the same parameters. Rotor inertias have
    no URDF element: they are written as an XML comment in each joint.

    Parameters
    ----------
    library : RobotLibrary
    parameters : array-like of shape (n_terms,)
        Full parameters (10 per body, then rotor inertias if the library has them),
        physically consistent (see :func:`consistent_parameters`).
    path : str or Path
        Where to write the new URDF (the original is not changed).
    damping, friction : array-like of shape (n_dof,), default=None
        Viscous and Coulomb coefficients per coordinate, written as the joints'
        ``<dynamics damping= friction=>``; ``None`` keeps the file's.

    Returns
    -------
    Path
        ``path``.
    """
    library._ensure_built()
    tree = library.tree_
    parameters = np.asarray(parameters, dtype=float)
    if parameters.shape != (len(library),):
        raise ValueError(
            f"parameters must have shape ({len(library)},), got {parameters.shape}"
        )
    doc = ET.parse(tree.path)
    root = doc.getroot()
    links = {el.get("name"): el for el in root.findall("link")}
    joints = {el.get("name"): el for el in root.findall("joint")}
    for b, body in enumerate(tree.bodies):
        p = parameters[10 * b : 10 * b + 10]
        m = p[0]
        if m <= 0:
            if np.any(p[1:] != 0):
                raise ValueError(
                    f"body {body.name!r} has mass {m:.3g} with non-zero moments: not "
                    "physically consistent; use consistent_parameters first"
                )
            c = np.zeros(3)
        else:
            c = p[1:4] / m
        inertia_c = inertia_matrix(p) - m * (np.dot(c, c) * np.eye(3) - np.outer(c, c))
        for name in body.links[1:]:
            old = links[name].find("inertial")
            if old is not None:
                links[name].remove(old)
                links[name].insert(
                    0, ET.Comment(f" lagsindy: inertia merged into {body.name} ")
                )
        el = links[body.name]
        old = el.find("inertial")
        if old is not None:
            el.remove(old)
        inertial = ET.Element("inertial")
        ET.SubElement(inertial, "origin", xyz=" ".join(_fmt(v) for v in c), rpy="0 0 0")
        ET.SubElement(inertial, "mass", value=_fmt(m))
        ET.SubElement(
            inertial,
            "inertia",
            ixx=_fmt(inertia_c[0, 0]),
            ixy=_fmt(inertia_c[0, 1]),
            ixz=_fmt(inertia_c[0, 2]),
            iyy=_fmt(inertia_c[1, 1]),
            iyz=_fmt(inertia_c[1, 2]),
            izz=_fmt(inertia_c[2, 2]),
        )
        inertial.tail = "\n"
        el.insert(0, inertial)
    n_link = 10 * len(tree.bodies)
    for k, name in enumerate(tree.coordinates):
        el = joints[name]
        if len(parameters) > n_link:
            el.append(
                ET.Comment(f" lagsindy: armature {_fmt(parameters[n_link + k])} ")
            )
        if damping is None and friction is None:
            continue
        dyn = el.find("dynamics")
        if dyn is None:
            dyn = ET.SubElement(el, "dynamics")
        if damping is not None:
            dyn.set("damping", _fmt(np.asarray(damping, dtype=float)[k]))
        if friction is not None:
            dyn.set("friction", _fmt(np.asarray(friction, dtype=float)[k]))
    path = Path(path)
    doc.write(path, encoding="utf-8", xml_declaration=True)
    return path


def reread(library, path):
    """The library over another URDF file, with the same joints, locks and gravity."""
    return clone(library).set_params(path=str(path)).build()
