r"""Rigid-body parameters taken from the URDF: the library of ``inertia="urdf"``.

``RobotLibrary(path, inertia="urdf")`` trusts the URDF's link inertial parameters (a
CAD model, an earlier identification). A :class:`~lagsindy.LagrangianSINDy` fit then
regresses on :class:`KnownInertiaLibrary`: one *known* term ``urdf``, the URDF's
rigid-body Lagrangian ``nominal @ phi``, whose coefficient is held at 1 (not fitted,
not penalized: :func:`lagsindy.cases.forces.hold_known` moves its column to the
right-hand side of every solve's Gram statistics, in the strong and the weak form),
and the rotor inertias ``Ia_<joint>`` as free terms. Friction and other effects
come from the dissipation library as usual.

With ``payload=`` (``"end"`` or a link name), the library also has the *payload*
terms: the inertial parameters of one body added to the URDF's, reduced to those
the data can identify given the other links held (see :class:`Payload`). This is
what :func:`lagsindy.diagnose`'s candidate kind ``"payload"`` adds.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
from sklearn.base import BaseEstimator

from .._stacklevel import outside_stacklevel
from .base_parameters import base_parameters_from_columns, exciting_states
from .fitting import BaseTerms, _OnRobot

#: The known term's name in :class:`KnownInertiaLibrary`.
KNOWN = "urdf"
#: Names of a body's 10 inertial parameters (pinocchio's order).
KINDS = ("m", "mx", "my", "mz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")


class MappedTerms(BaseTerms):
    """A term function whose terms are fixed linear combinations of a
    :class:`~lagsindy.robots.RobotTerms`' terms: ``phi_new = phi_robot @ matrix``.

    Evaluated like :class:`~lagsindy.robots.BaseTerms` (the recursion computes every
    robot column, then the matrix combines them), so ``columns``,
    ``mass_matrices`` and ``bias`` are the Newton-Euler ones.
    """

    def __init__(self, terms, matrix, names):
        self.terms = terms
        self.matrix = np.asarray(matrix, dtype=float)
        self.names = list(names)
        self.indices = list(range(len(self.names)))
        self._matrix = torch.as_tensor(self.matrix)

    def subset(self, indices) -> MappedTerms:
        idx = [int(k) for k in indices]
        return MappedTerms(
            self.terms, self.matrix[:, idx], [self.names[k] for k in idx]
        )

    def _pick(self, out):
        return out @ self._matrix.to(device=out.device, dtype=out.dtype)

    def numpy_dynamics(self, coef):
        """``(M, h)`` of ``sum_k coef[k] phi_k`` as a NumPy function of the states:
        the robot terms' model with coefficients ``matrix @ coef``
        (:meth:`RobotTerms.numpy_dynamics`)."""
        return self.terms.numpy_dynamics(self.matrix @ np.asarray(coef, float))

    def __repr__(self) -> str:
        return f"MappedTerms({len(self.names)} combinations of robot terms)"


def end_body(tree) -> int:
    """Index of the body a payload rides on: the moving body farthest from the root
    (most joints above it); among several such leaves, the one of the last
    coordinate."""
    depth = []
    for b in tree.bodies:
        d, p = 0, b.parent
        while p >= 0:
            d, p = d + 1, tree.bodies[p].parent
        depth.append(d)
    parents = {b.parent for b in tree.bodies}
    leaves = [i for i in range(len(tree.bodies)) if i not in parents]
    deepest = max(depth[i] for i in leaves)
    return max(
        (i for i in leaves if depth[i] == deepest),
        key=lambda i: (tree.bodies[i].coordinate, i),
    )


class Payload:
    """The payload terms of one body: its identifiable inertial parameters.

    A payload adds ``delta`` (10 inertial parameters about the body frame's origin)
    to one body's URDF parameters; its torques are linear in ``delta``. With every
    other link held, only some combinations of ``delta`` move the torques (on a
    planar arm about ``y``: ``m``, ``mx``, ``mz`` and ``Iyy``): they are found, as the
    base parameters are, from the regressor's columns of the body at random
    exciting states, together with the rotor inertias' columns (kept first, so a
    payload combination never stands in for a rotor inertia).

    Attributes
    ----------
    link : str
        The body (its joint's child link).
    body : int
        Its index in the robot's tree.
    columns : ndarray of int
        The robot parameters (positions in the robot library's terms) that are
        payload terms: the identifiable ones of the body.
    kinds : list of str
        Their kinds (``"m"``, ``"mx"``, ...).
    matrix : ndarray of shape (n_terms, 10)
        ``terms = matrix @ delta``: which parameters of ``delta`` each term
        combines.
    labels : list of str
        The combinations, in words.
    """

    def __init__(self, robot, body: int, random_state=0):
        tree = robot.tree_
        self.body = int(body)
        self.link = tree.bodies[self.body].name
        own = np.arange(10 * self.body, 10 * self.body + 10)
        rotor = [i for i, n in enumerate(robot.terms_) if n.startswith("Ia_")]
        rng = np.random.default_rng(random_state)
        n = int(4 * (10 + len(rotor)) / tree.n_dof) + 20
        q, qd, qdd = exciting_states(tree.lower, tree.upper, n, rng)
        t = [torch.as_tensor(x) for x in (q, qd, qdd)]
        cols = robot.torch_terms().columns(*t).numpy()
        names = [robot.terms_[i] for i in rotor] + list(KINDS)
        base = base_parameters_from_columns(cols[..., rotor + list(own)], names)
        keep = [j - len(rotor) for j in base.independent if j >= len(rotor)]
        rows = [k for k, j in enumerate(base.independent) if j >= len(rotor)]
        self.columns = own[keep]
        self.kinds = [KINDS[j] for j in keep]
        self.matrix = base.matrix[rows][:, len(rotor) :]
        self.labels = [base.labels[k] for k in rows]

    def parameters(self, values) -> np.ndarray:
        """The payload's 10 parameters from fitted terms: a point mass at the
        fitted centre (unidentified coordinates 0; no mass when the mass is not
        identified), corrected on the identified columns so that the terms are the
        fitted ones (the torques are; what the data do not identify is the point
        mass's)."""
        values = np.asarray(values, dtype=float)
        estimate = self.estimate(values)
        m = estimate["mass"] if np.isfinite(estimate["mass"]) else 0.0
        c = np.nan_to_num(estimate["com"])
        inertia = m * (c @ c * np.eye(3) - np.outer(c, c))
        point = np.array(
            [m, *(m * c), inertia[0, 0], inertia[0, 1], inertia[1, 1],
             inertia[0, 2], inertia[1, 2], inertia[2, 2]]
        )  # fmt: skip
        out = point.copy()
        keep = [KINDS.index(k) for k in self.kinds]
        out[keep] += values - self.matrix @ point
        return out

    @property
    def names(self) -> list:
        """The payload terms' names: ``payload_<kind>``."""
        return [f"payload_{k}" for k in self.kinds]

    def alone(self, kind: str) -> bool:
        """Whether the term of ``kind`` is that parameter alone (no other of the
        body's parameters regrouped into it)."""
        if kind not in self.kinds:
            return False
        row = self.matrix[self.kinds.index(kind)]
        return int(np.count_nonzero(np.abs(row) > 1e-9)) == 1

    def estimate(self, values, covariance=None) -> dict:
        """Mass and centre of mass of fitted payload terms.

        Parameters
        ----------
        values : array-like of shape (n_terms,)
            The fitted payload terms (in :attr:`names` order).
        covariance : ndarray of shape (n_terms, n_terms), default=None
            Their covariance: standard errors by the delta method.

        Returns
        -------
        dict
            ``link``, ``mass``, ``com`` (3 coordinates in the body frame, ``nan``
            where the data cannot identify it), ``mass_std``, ``com_std`` (``nan``
            without ``covariance``), ``terms`` (``{name: value}``) and ``labels``.
        """
        values = np.asarray(values, dtype=float)
        cov = None if covariance is None else np.asarray(covariance, dtype=float)
        k_m = self.kinds.index("m") if self.alone("m") else None
        mass = values[k_m] if k_m is not None else float("nan")
        mass_std = (
            float(np.sqrt(max(cov[k_m, k_m], 0.0)))
            if cov is not None and k_m is not None
            else float("nan")
        )
        com, com_std = np.full(3, np.nan), np.full(3, np.nan)
        for a, kind in enumerate(("mx", "my", "mz")):
            if k_m is None or not self.alone(kind) or mass == 0:
                continue
            k = self.kinds.index(kind)
            com[a] = values[k] / mass
            if cov is not None:  # d(c)/d(mc) = 1/m, d(c)/d(m) = -mc/m^2
                g = np.zeros(len(values))
                g[k], g[k_m] = 1.0 / mass, -values[k] / mass**2
                com_std[a] = float(np.sqrt(max(g @ cov @ g, 0.0)))
        return {
            "link": self.link,
            "mass": float(mass),
            "com": com,
            "mass_std": mass_std,
            "com_std": com_std,
            "terms": dict(zip(self.names, values.tolist())),
            "labels": dict(zip(self.names, self.labels)),
        }


class KnownInertiaLibrary(_OnRobot, BaseEstimator):
    """The library a fit regresses on when the URDF's link parameters are trusted.

    Terms: ``urdf`` (the URDF's rigid-body Lagrangian, known: coefficient 1), the
    rotor inertias ``Ia_<joint>`` (with ``armature=True``) and, with ``payload``,
    the payload terms ``payload_<kind>`` of one body (:class:`Payload`).

    Parameters
    ----------
    robot : RobotLibrary
        The link-level library (``inertia="urdf"``), built or not.
    payload : {None, "end"} or str, default=None
        ``"end"``: payload terms on the end body (:func:`end_body`); a link name:
        on that body.
    random_state : int, default=0
        Seeds the exciting states the payload's identifiable terms are found at.

    Attributes
    ----------
    robot_ : RobotLibrary
    terms_ : list of str
    coordinates_ : list of str
    known_terms_ : dict
        ``{"urdf": 1.0}``: the terms every solve holds at their value.
    unpenalized_ : list of str
        Terms the sparse regression leaves alone (all, unless the robot library has
        ``penalize=True``).
    nominal_ : ndarray of shape (n_terms,)
        The URDF's model: 1 for ``urdf``, 0 for the others.
    payload_ : Payload or None
    nonnegative_ : list of str
        Terms physically non-negative (rotor inertias, a payload's mass): the
        consistent fit and :func:`lagsindy.diagnose`'s held-out refits keep them so.
    matrix_ : ndarray of shape (n_robot_terms, n_terms)
        Each term as a combination of the robot library's terms (link parameters
        and rotor inertias): full parameters ``pi = matrix_ @ coef``.
    """

    _BUILT = (
        "terms_",
        "coordinates_",
        "robot_",
        "known_terms_",
        "unpenalized_",
        "nominal_",
        "payload_",
        "matrix_",
        "n_terms_",
        "nonnegative_",
    )

    def __init__(self, robot=None, payload=None, random_state=0):
        self.robot = robot
        self.payload = payload
        self.random_state = random_state

    def build(self):
        """Build the robot library and the terms; returns ``self``."""
        if self.robot is None:
            raise ValueError("KnownInertiaLibrary needs robot= (a RobotLibrary)")
        robot = self.robot._ensure_built()
        n_full = len(robot.terms_)
        nominal = np.asarray(robot.nominal_, dtype=float).copy()
        columns, names = [nominal], [KNOWN]
        for i, name in enumerate(robot.terms_):
            if name.startswith("Ia_"):
                unit = np.zeros(n_full)
                unit[i] = 1.0
                columns.append(unit)
                names.append(name)
        payload = None
        if self.payload is not None:
            payload = Payload(robot, self._payload_body(robot), self.random_state)
            for j in payload.columns:
                unit = np.zeros(n_full)
                unit[j] = 1.0
                columns.append(unit)
            names += payload.names
        self.robot_ = robot
        self.payload_ = payload
        self.matrix_ = np.stack(columns, axis=1)
        self.coordinates_ = list(robot.coordinates_)
        self.terms_ = names
        self._terms = MappedTerms(robot.torch_terms(), self.matrix_, names)
        self.known_terms_ = {KNOWN: 1.0}
        penalize = bool(getattr(robot, "penalize", False))
        self.unpenalized_ = [] if penalize else [n for n in names if n != KNOWN]
        self.nominal_ = np.r_[1.0, np.zeros(len(names) - 1)]
        self.n_terms_ = len(names)
        self.nonnegative_ = [n for n in names if n.startswith("Ia_")]
        self.nonnegative_ += [n for n in names if n == "payload_m"]
        return self

    def _payload_body(self, robot) -> int:
        tree = robot.tree_
        if self.payload == "end":
            return end_body(tree)
        names = [b.name for b in tree.bodies]
        for i, b in enumerate(tree.bodies):
            if self.payload in b.links:
                return i
        raise ValueError(
            f"payload={self.payload!r} is not a link of a moving body; use 'end' or "
            f"one of {names}"
        )

    def _other_term(self, term):
        raise ValueError(
            f"term {term!r} is not in this library; its terms are {self.terms_} "
            "(the URDF's link parameters are held: inertia='urdf')"
        )

    def parameters(self, coef) -> np.ndarray:
        """Full robot parameters (link parameters, then rotor inertias) of fitted
        coefficients: the URDF's, the rotor inertias and the payload added to its
        body (:meth:`Payload.parameters`: what the data do not identify completed
        as a point mass at the fitted centre)."""
        coef = np.asarray(coef, dtype=float)[: self.n_terms_]
        n = 0 if self.payload_ is None else len(self.payload_.names)
        out = self.matrix_[:, : self.n_terms_ - n] @ coef[: self.n_terms_ - n]
        if n:
            body = self.payload_.body
            out[10 * body : 10 * body + 10] += self.payload_.parameters(coef[-n:])
        return out

    def link_parameters(self, coef) -> np.ndarray:
        """Alias of :meth:`parameters` (the name :func:`lagsindy.robots.fitted_to_urdf`
        calls)."""
        return self.parameters(coef)

    @property
    def labels_(self) -> list:
        """What each term is, in words (:func:`lagsindy.robots.parameter_table`)."""
        self._ensure_built()
        out = []
        for name in self.terms_:
            if name == KNOWN:
                out.append("the URDF's link parameters (held at 1)")
            elif name.startswith("payload_"):
                label = self.payload_.labels[self.payload_.names.index(name)]
                out.append(f"payload on {self.payload_.link}: {label}")
            else:
                out.append(name)
        return out

    def payload_estimate(self, coef, covariance=None):
        """:meth:`Payload.estimate` of the payload terms of ``coef`` (None without
        payload terms); ``covariance`` over the payload terms."""
        if self.payload_ is None:
            return None
        n = len(self.payload_.names)
        values = np.asarray(coef, dtype=float)[self.n_terms_ - n : self.n_terms_]
        return self.payload_.estimate(values, covariance)

    def constrain(self, problem, solution):
        """The pipeline's hook after the sparse solve (case I): with the link
        parameters held, physical consistency leaves rotor inertias and dissipative
        coefficients non-negative (and a payload's mass): when the solve's are not,
        the kept terms are refitted by bounded least squares on the same
        statistics (the known term is already on the right-hand side)."""
        if not getattr(self.robot_, "consistent", True):
            return solution
        coef = np.asarray(solution.coef, dtype=float)
        lower = np.full(len(coef), -np.inf)
        for name in self.nonnegative_:
            lower[self.terms_.index(name)] = 0.0
        n = self.n_terms_
        for k, t in enumerate(problem.dissipation_terms):
            if t.dissipative:
                lower[n + k] = 0.0
        free = np.flatnonzero((coef != 0) & np.asarray(problem.identifiable, bool))
        if not np.any(coef[free] < lower[free]):
            return solution
        gram = problem.balanced.gram.detach().cpu().numpy()
        keep = list(range(len(coef))) + [len(coef)]  # features, then the target
        gram = gram[np.ix_(keep, keep)]
        solution.coef = bounded_refit(gram, coef, free, lower)
        return solution

    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop("_terms", None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        if "robot_" in state and "matrix_" in state:
            self._terms = MappedTerms(
                self.robot_.torch_terms(), self.matrix_, self.terms_
            )


def bounded_refit(gram, coef, free, lower) -> np.ndarray:
    """``coef`` with the ``free`` coefficients refitted on the quadratic objective
    ``x^T G x / 2 - g^T x`` (``gram``: features then target, last) with
    ``x >= lower``; the others unchanged."""
    from scipy.optimize import lsq_linear

    target = gram.shape[-1] - 1
    g_ff = gram[np.ix_(free, free)]
    g_ft = gram[free, target]
    scale = np.sqrt(np.clip(np.diag(g_ff), 1e-300, None))
    a = g_ff / np.outer(scale, scale)
    b = g_ft / scale
    evals, evecs = np.linalg.eigh((a + a.T) / 2)
    keep = evals > 1e-12 * max(evals[-1], 1e-300)
    root = np.sqrt(evals[keep])[:, None] * evecs[:, keep].T  # a = root^T root
    rhs = (evecs[:, keep].T @ b) / np.sqrt(evals[keep])
    found = lsq_linear(root, rhs, bounds=(lower[free] * scale, np.inf))
    out = np.asarray(coef, dtype=float).copy()
    out[free] = found.x / scale
    if not found.success:
        warnings.warn(
            f"the bounded refit of the rotor inertias and friction did not converge "
            f"({found.message})",
            UserWarning,
            stacklevel=outside_stacklevel(),
        )
    return out
