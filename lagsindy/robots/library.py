"""A candidate library whose terms are a robot arm's energy regressor."""

from __future__ import annotations

import numpy as np
import torch
from sklearn.base import BaseEstimator

from .._expr import check_coordinate_names
from .energy import GRAVITY, RobotTerms, euler_lagrange_columns
from .urdf import build_tree


class _BuiltOnDemand:
    """What the robot libraries share: the fitted attributes named in ``_BUILT`` are
    made by ``build()`` on first use, and the library's length and feature names are
    its terms'."""

    _BUILT: tuple = ()

    def __getattr__(self, name):
        if name in type(self)._BUILT:
            self.build()
            return self.__dict__[name]
        raise AttributeError(
            f"{type(self).__name__!r} object has no attribute {name!r}"
        )

    def __len__(self) -> int:
        return len(self._ensure_built().terms_)

    def get_feature_names_out(self, input_features=None) -> np.ndarray:
        """Names of the terms (``terms_``) as an object array."""
        return np.asarray(self._ensure_built().terms_, dtype=object)

    def index(self, term: str) -> int:
        """Position of a term given by its name (``"m_panda_link3"``,
        ``"Ia_panda_joint1"``; for base parameters also a link parameter that is
        one)."""
        names = self._ensure_built().terms_
        if term in names:
            return names.index(term)
        return self._other_term(term)

    def torch_terms(self):
        """The term function (``names``, ``fn(q, qd)`` for one sample, and the
        batched forms the pipeline uses)."""
        return self._ensure_built()._terms

    def to_torch(self):
        """Alias of :meth:`torch_terms` (the name :class:`CandidateLibrary` uses)."""
        return self.torch_terms()


class RobotLibrary(_BuiltOnDemand, BaseEstimator):
    """Lagrangian terms of a robot arm from its URDF: link inertial parameters.

    The Lagrangian of the arm is ``L = sum_j pi_j * phi_j(q, qd)`` where ``pi`` are
    the 10 inertial parameters of every moving body (mass ``m``, first moment
    ``mx, my, mz`` = mass times centre of mass, rotational inertia
    ``Ixx, Ixy, Iyy, Ixz, Iyz, Izz`` about the body frame's origin; pinocchio's order)
    and, with ``armature=True``, a rotor inertia ``Ia`` per joint. The terms are
    evaluated in torch (see :class:`lagsindy.robots.energy.RobotTerms`), so their
    Euler-Lagrange columns are the classical joint torque regressor's.

    Same duck-typed interface as :class:`lagsindy.CandidateLibrary`
    (``coordinates_``, ``terms_``, ``get_feature_names_out``, ``build``, ``index``),
    plus :meth:`torch_terms` for the term function. Usually made by
    :meth:`lagsindy.CandidateLibrary.from_urdf`.

    Parameters
    ----------
    path : str or Path, default=None
        The URDF file (``xacro`` expanded).
    joints : list of str, default=None
        The coordinate joints in the order the robot reports them (the order of the
        columns of ``q``). ``None``: every revolute, continuous and prismatic joint
        that is not a mimic joint, in file order.
    armature : bool, default=True
        Add a rotor (armature) inertia term ``0.5 * qd_j**2`` per joint.
    locked : dict of str to float, default=None
        Positions of moving joints that are not coordinates (fingers, a gripper).
        Joints neither in ``joints`` nor here are locked at 0 clipped into their
        limits (``locked_`` lists every position used); a mimic joint follows the
        joint it mimics. Their links are merged into the body that carries them.
    gravity : sequence of 3 float, default=(0, 0, -9.81)
        Gravity in the URDF's root link frame (the URDF convention: z up).
    penalize : bool, default=False
        In a :class:`~lagsindy.LagrangianSINDy` fit (which regresses on the base
        parameters, :meth:`regression_library`): ``False`` leaves the base parameters
        out of the L1 penalty and the hard threshold, so that the sparse regression
        selects only among the dissipation candidates; ``True`` makes them ordinary
        candidates.
    consistent : bool, default=True
        In a fit with forces (case I): refit the coefficients, after the sparse solve
        chose the dissipation terms, with physically consistent link parameters
        (every body's pseudo-inertia positive semidefinite, rotor inertias and
        dissipative coefficients non-negative; see
        :mod:`lagsindy.robots.consistency`). ``False``: the unconstrained least
        squares, with a warning saying how far its base parameters are from
        consistent ones (``library_.violation_``).
    inertia : {"base", "urdf"}, default="base"
        ``"base"``: the fit estimates the link parameters (on their base parameters,
        :meth:`regression_library`). ``"urdf"``: the URDF's link parameters are
        trusted (a CAD model, an earlier identification): the fit holds the URDF's
        rigid-body Lagrangian as a known term ``urdf`` at coefficient 1 and
        estimates only rotor inertias, friction and effects
        (:class:`lagsindy.robots.known.KnownInertiaLibrary`); consistency then
        means non-negative rotor inertias and dissipative coefficients. Needs
        forces (case I). This is where :func:`lagsindy.diagnose` can propose a
        payload (candidate kind ``"payload"``).
    payload : {None, "end"} or str, default=None
        With ``inertia="urdf"``: also fit a payload's inertial parameters on the end
        body (``"end"``) or on the named link's body, the identifiable ones given
        the other links held (:class:`lagsindy.robots.known.Payload`).

    Attributes
    ----------
    coordinates_ : list of str
        The coordinate joints.
    terms_ : list of str
        Term names: ``m_<link>``, ``mx_<link>``, ..., ``Izz_<link>`` per moving body
        (named after the joint's child link), then ``Ia_<joint>``.
    tree_ : lagsindy.robots.urdf.RobotTree
        The reduced kinematic tree.
    locked_ : dict of str to float
        Position of every moving joint that is not a coordinate.
    nominal_ : ndarray of shape (n_terms,)
        The URDF's own parameters (armature 0): ``L = nominal_ @ phi``.

    Examples
    --------
    >>> from lagsindy.robots import RobotLibrary
    >>> lib = RobotLibrary("tests/robots/data/planar2.urdf")  # doctest: +SKIP
    >>> lib.terms_[:3]  # doctest: +SKIP
    ['m_upper_arm', 'mx_upper_arm', 'my_upper_arm']
    """

    _BUILT = ("terms_", "coordinates_", "tree_", "locked_", "nominal_")

    def __init__(
        self,
        path=None,
        joints=None,
        *,
        armature=True,
        locked=None,
        gravity=GRAVITY,
        penalize=False,
        consistent=True,
        inertia="base",
        payload=None,
    ):
        self.path = path
        self.joints = joints
        self.armature = armature
        self.locked = locked
        self.gravity = gravity
        self.penalize = penalize
        self.consistent = consistent
        self.inertia = inertia
        self.payload = payload

    def _key(self):
        return repr(
            sorted((k, repr(v)) for k, v in self.get_params(deep=False).items())
        )

    def build(self):
        """Read the URDF and make the term function; returns ``self``."""
        if self.path is None:
            raise ValueError("RobotLibrary needs path= (a URDF file)")
        tree = build_tree(self.path, self.joints, self.locked)
        try:
            check_coordinate_names(tree.coordinates)
        except ValueError as exc:
            raise ValueError(
                f"{exc}. The URDF's joint names are the coordinate names; rename the "
                "joint in a copy of the URDF"
            ) from None
        self.tree_ = tree
        self.coordinates_ = list(tree.coordinates)
        self._terms = RobotTerms(tree, armature=self.armature, gravity=self.gravity)
        self.terms_ = list(self._terms.names)
        self.locked_ = dict(tree.locked)
        nominal = tree.parameters()
        if self.armature:
            nominal = np.concatenate([nominal, np.zeros(tree.n_dof)])
        self.nominal_ = nominal
        self._built_key = self._key()
        return self

    @property
    def coordinates(self):
        """The coordinate joints (read from the URDF; what the data's columns are
        named after)."""
        return None if self.path is None else list(self._ensure_built().coordinates_)

    def regression_library(self, random_state=0):
        """The library a :class:`~lagsindy.LagrangianSINDy` fit regresses on, built:
        the base parameters (:class:`lagsindy.robots.fitting.BaseParameterLibrary`),
        or with ``inertia="urdf"`` the URDF's model as a known term
        (:class:`lagsindy.robots.known.KnownInertiaLibrary`)."""
        from .fitting import BaseParameterLibrary
        from .known import KnownInertiaLibrary

        if self.inertia not in ("base", "urdf"):
            raise ValueError(f"inertia must be 'base' or 'urdf', got {self.inertia!r}")
        if self.inertia == "urdf":
            return KnownInertiaLibrary(
                self, payload=self.payload, random_state=random_state
            ).build()
        if self.payload is not None:
            raise ValueError(
                "payload= needs inertia='urdf': with the link parameters estimated "
                "(inertia='base'), a payload is part of the end link's base parameters"
            )
        return BaseParameterLibrary(self, random_state=random_state).build()

    def _ensure_built(self):
        if self.__dict__.get("_built_key") != self._key():
            self.build()
        return self

    def _other_term(self, term):
        raise ValueError(
            f"term {term!r} is not in the library; names are <kind>_<link> with kind in "
            f"m, mx, my, mz, Ixx, Ixy, Iyy, Ixz, Iyz, Izz (links: "
            f"{[b.name for b in self.tree_.bodies]}) and Ia_<joint>"
        )

    def euler_lagrange_columns(self, q, qd, qdd, method="recursive") -> np.ndarray:
        """Joint torque regressor: ``tau = columns @ pi``, shape (n_samples, n_dof, n_terms).

        Parameters
        ----------
        q, qd, qdd : array-like of shape (n_samples, n_dof)
        method : {"recursive", "autograd"}, default="recursive"
            ``"recursive"``: the Newton-Euler recursion (:meth:`RobotTerms.columns`);
            ``"autograd"``: ``torch.func`` on the term function (slower, the same
            numbers to round-off).
        """
        t = [
            torch.as_tensor(np.ascontiguousarray(a, dtype=float)) for a in (q, qd, qdd)
        ]
        for a in t:
            if a.ndim != 2 or a.shape[1] != len(self.coordinates_):
                raise ValueError(
                    f"q, qd, qdd must have shape (n_samples, {len(self.coordinates_)}), "
                    f"got {tuple(a.shape)}"
                )
        if method == "recursive":
            return self.torch_terms().columns(*t).numpy()
        if method == "autograd":
            return euler_lagrange_columns(self.torch_terms().fn, *t).numpy()
        raise ValueError(f"method must be 'recursive' or 'autograd', got {method!r}")

    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop("_terms", None)
        state.pop("_built_key", None)
        return state
