"""Candidate libraries of Lagrangian terms.

A :class:`CandidateLibrary` is a parameter object (scikit-learn style: its constructor
only stores parameters, so ``LagrangianSINDy(library=...)`` can be cloned and grid
searched through ``library__degree``). Building it produces sympy terms over the named
coordinates, with two reductions that make the sparse answer unique:

* trivial terms, whose Euler-Lagrange expression vanishes identically (``qdot``,
  ``q*qdot``, ``qdot*sin(q)``: total time derivatives), are removed;
* terms whose Euler-Lagrange column is a linear combination of earlier terms' columns
  (``sin(q)**2`` once ``cos(q)**2`` is in: their sum is a constant) are removed and
  reported with the combination, keeping the earlier term as the representative
  (both in :mod:`lagsindy.reduction`).
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Sequence

import numpy as np
import sympy as sp
from sklearn.base import BaseEstimator

from ._batched import compile_terms
from ._expr import canonical, check_coordinate_names, symbols_for
from ._params import cache_param_names
from .reduction import (  # noqa: F401 - euler_lagrange_expressions: its public path
    euler_lagrange_expressions,
    reduce_terms,
    sample_columns,
)

_KINDS = ("polynomial", "separated", "chain")


def _positive(term: sp.Expr) -> sp.Expr:
    """``term`` without a leading numeric factor (sympy may pull out a minus sign)."""
    _, rest = sp.sympify(term).as_coeff_Mul()
    return rest


def _chain_terms(names, angles, sin_coupling, degree, relative=False) -> list[sp.Expr]:
    """The candidate terms of :meth:`CandidateLibrary.chain`, in documented order.

    With ``relative``, each angle is measured from the previous angle's link (in the
    order of ``names``), so the absolute angle of link ``k`` is the sum of the angles
    up to ``k`` and its angular velocity the sum of their velocities.
    """
    q, qd, _ = symbols_for(names)
    rev = [i for i, n in enumerate(names) if n in angles]
    pri = [i for i, n in enumerate(names) if n not in angles]
    theta, omega = {}, {}
    for k, i in enumerate(rev):
        upto = rev[: k + 1] if relative else [i]
        theta[i] = sp.Add(*[q[j] for j in upto])
        omega[i] = sp.Add(*[qd[j] for j in upto])
    out = [omega[i] ** 2 if i in omega else qd[i] ** 2 for i in range(len(names))]
    for i, j in itertools.combinations(rev, 2):
        out.append(_positive(omega[i] * omega[j] * sp.cos(theta[i] - theta[j])))
        if sin_coupling:
            out.append(_positive(omega[i] * omega[j] * sp.sin(theta[i] - theta[j])))
    for i in pri:
        for j in rev:
            out.append(qd[i] * omega[j] * sp.cos(theta[j]))
            out.append(qd[i] * omega[j] * sp.sin(theta[j]))
    for i, j in itertools.combinations(pri, 2):
        out.append(qd[i] * qd[j])
    for i in range(len(names)):
        if i in rev:
            out += [sp.cos(theta[i]), sp.sin(theta[i])]
        else:
            out += [q[i] ** d for d in range(1, degree + 1)]
    return out


def _monomials(base: Sequence[sp.Expr], degree: int) -> list[sp.Expr]:
    out = []
    for d in range(1, degree + 1):
        for combo in itertools.combinations_with_replacement(base, d):
            out.append(sp.Mul(*combo))
    return out


@cache_param_names
class CandidateLibrary(BaseEstimator):
    """A library of candidate Lagrangian terms over named coordinates.

    Use the builders :meth:`polynomial`, :meth:`separated`, :meth:`chain` and
    :meth:`from_terms` rather than setting ``kind`` by hand. Libraries over the same
    coordinates add up: ``lib_a + lib_b`` is a library of the terms of both.

    Parameters
    ----------
    coordinates : list of str, default=None
        Coordinate names, e.g. ``["x", "theta"]``; velocities are ``x_dot``,
        ``theta_dot``. ``None`` lets :class:`~lagsindy.LagrangianSINDy` fill them in
        from the data at fit time.
    terms : list of str or sympy.Expr, default=None
        Extra candidate terms (strings are parsed safely, without ``eval``), added
        after the generated ones.
    kind : {"polynomial", "separated", "chain"} or None, default=None
        Generated part of the library (``"chain"``: the terms of serial planar
        chains, see :meth:`chain`). ``"polynomial"``: all monomials of degree
        1..``degree`` over the base set (per coordinate: the coordinate itself unless
        it is an angle, its velocity, and ``sin``/``cos`` of angles). ``"separated"``:
        the paper's construction for the double and spherical pendulum, with the
        trigonometric set ``{sin q, cos q}`` of the angles and the non-trigonometric
        set ``{q (non-angles), qdot}`` each expanded to ``degree`` and all cross
        products of the two added. ``None``: only ``terms``.
    degree : int, default=2
        Polynomial degree of the generated part.
    angles : list of str or "all", default=None
        Coordinates that get ``sin``/``cos`` functions. ``None``: no angles.
    raw_angles : bool, default=False
        Also use the angles themselves as polynomial variables (the paper's single
        pendulum library does; the others do not).
    sin_coupling : bool, default=False
        ``kind="chain"`` only: also the couplings ``q_i_dot*q_j_dot*sin(q_i - q_j)``
        of every pair of angles (see :meth:`chain`).
    relative : bool, default=False
        ``kind="chain"`` only: the angles are relative joint angles, each measured
        from the previous link (see :meth:`chain`).
    remove_trivial : bool, default=True
        Drop terms whose Euler-Lagrange expression is identically zero.
    remove_dependent : bool, default=True
        Drop terms whose Euler-Lagrange column is a linear combination of earlier
        terms' columns, recording the combination in ``removed_``.

    Attributes
    ----------
    terms_ : list of sympy.Expr
        Candidate terms after the reductions (available after :meth:`build`; the
        methods below build on demand).
    candidates_ : list of sympy.Expr
        All generated and given terms before the reductions.
    removed_ : list of tuple (str, str)
        ``(term, reason)`` for every removed candidate.

    Examples
    --------
    >>> from lagsindy import CandidateLibrary
    >>> lib = CandidateLibrary.polynomial(["theta"], angles=["theta"], degree=2,
    ...                                   raw_angles=True)
    >>> len(lib.candidates_), len(lib)
    (14, 9)
    >>> lib.removed_[0]
    ('theta_dot', 'trivial: its Euler-Lagrange expression is identically zero')
    """

    def __init__(
        self,
        coordinates=None,
        terms=None,
        *,
        kind=None,
        degree=2,
        angles=None,
        raw_angles=False,
        sin_coupling=False,
        relative=False,
        remove_trivial=True,
        remove_dependent=True,
    ):
        self.coordinates = coordinates
        self.terms = terms
        self.kind = kind
        self.degree = degree
        self.angles = angles
        self.raw_angles = raw_angles
        self.sin_coupling = sin_coupling
        self.relative = relative
        self.remove_trivial = remove_trivial
        self.remove_dependent = remove_dependent

    # ------------------------------------------------------------------ builders
    @classmethod
    def polynomial(
        cls, coordinates=None, angles=None, degree=2, *, raw_angles=False, **kwargs
    ):
        """All monomials of degree 1..``degree`` over ``{q, qdot, sin q, cos q}``.

        Angles contribute ``sin``/``cos`` (and themselves only if ``raw_angles``);
        other coordinates contribute themselves. Velocities always enter.
        The paper's single pendulum library is
        ``polynomial(["theta"], angles=["theta"], degree=2, raw_angles=True)``
        (14 monomials, 12 after removing the trivial ``theta_dot`` and
        ``theta*theta_dot``), its cart-pendulum library
        ``polynomial(["x", "theta"], angles=["theta"], degree=3)`` (55 monomials).
        """
        return cls(
            coordinates,
            kind="polynomial",
            degree=degree,
            angles=angles,
            raw_angles=raw_angles,
            **kwargs,
        )

    @classmethod
    def separated(
        cls, coordinates=None, angles=None, degree=2, *, raw_angles=False, **kwargs
    ):
        """Trigonometric and non-trigonometric sets expanded separately, plus cross terms.

        The paper's double pendulum library is
        ``separated(["theta1", "theta2"], angles="all", degree=2)`` (14 + 5 + 70 = 89
        candidates), its spherical pendulum library
        ``separated(["theta", "phi"], angles=["theta"], degree=2)`` (5 + 9 + 45 = 59).
        """
        return cls(
            coordinates,
            kind="separated",
            degree=degree,
            angles=angles,
            raw_angles=raw_angles,
            **kwargs,
        )

    @classmethod
    def chain(
        cls,
        coordinates=None,
        angles="all",
        degree=2,
        *,
        sin_coupling=False,
        relative=False,
        **kwargs,
    ):
        """Terms of serial planar chains of revolute and prismatic joints.

        The kinetic energy of a planar chain of rigid links, with every joint angle
        measured from a fixed direction (absolute angles), is a sparse sum of
        ``q_i_dot**2`` and ``q_i_dot*q_j_dot*cos(q_i - q_j)``; a rail or gantry
        (prismatic coordinate ``x``) adds ``x_dot**2`` and, per angle,
        ``x_dot*theta_dot*cos(theta)`` and ``x_dot*theta_dot*sin(theta)``. Gravity and
        springs add ``cos``/``sin`` of the angles and powers of the prismatic
        coordinates. This builder generates exactly these families, so a multi-link
        Lagrangian is a few terms of a short library (the generic builders split
        ``cos(q_i - q_j)`` into ``cos*cos + sin*sin`` products and bury it among
        hundreds of look-alikes). The printed Lagrangian keeps ``cos(q_i - q_j)``.

        Generated, in this order:

        * ``q_dot**2`` of every coordinate;
        * ``q_i_dot*q_j_dot*cos(q_i - q_j)`` for every pair of angles ``i < j``
          (and ``q_i_dot*q_j_dot*sin(q_i - q_j)`` if ``sin_coupling``);
        * ``x_dot*theta_dot*cos(theta)`` and ``x_dot*theta_dot*sin(theta)`` for
          every prismatic coordinate ``x`` and angle ``theta``;
        * ``x_i_dot*x_j_dot`` for every pair of prismatic coordinates;
        * potential terms: ``cos(theta)``, ``sin(theta)`` of every angle and
          ``x, x**2, ..., x**degree`` of every prismatic coordinate.

        Sizes (all revolute, measured by building them; none is removed by the
        reductions): 3 links 12 terms (15 with ``sin_coupling``), 7 links 42 (63).

        **Relative angles** (``relative=True``): encoders report each joint's angle
        relative to the previous link (an elbow's angle relative to the upper arm).
        The angles, in the order of ``coordinates``, then form one serial chain:
        link ``k``'s absolute angle is ``theta_k = q_1 + ... + q_k`` and its angular
        velocity ``omega_k = q_1_dot + ... + q_k_dot``, and the families above are
        written in them: ``omega_k**2``, ``omega_i*omega_j*cos(q_{i+1} + ... + q_j)``,
        ``cos(theta_k)``, ``sin(theta_k)`` (and ``x_dot*omega_k*cos(theta_k)`` for a
        prismatic coordinate). A two-link arm with a relative elbow is then 5 terms
        (``(q1_dot + q2_dot)**2``, ``q1_dot*(q1_dot + q2_dot)*cos(q2)``, ...) of a
        7-term library, where the generic degree-3 library needs 55.
        A cart-pole (``["x", "theta"]``, ``angles=["theta"]``) has 8 terms, a cart
        with a double pendulum 14.

        Parameters
        ----------
        coordinates : list of str, default=None
        angles : list of str or "all", default="all"
            The revolute coordinates (absolute angles); the others are prismatic.
        degree : int, default=2
            Highest power of a prismatic coordinate in the potential terms.
        sin_coupling : bool, default=False
            Add ``q_i_dot*q_j_dot*sin(q_i - q_j)`` for every pair of angles (chains
            whose angle zeros are not aligned along the links, e.g. a link bent at a
            joint).
        relative : bool, default=False
            The angles are relative joint angles, each measured from the previous
            link in the order of ``coordinates`` (see above).
        **kwargs
            Other parameters of :class:`CandidateLibrary` (``terms`` for extra
            candidates, ``remove_trivial``, ``remove_dependent``).

        Examples
        --------
        >>> from lagsindy import CandidateLibrary
        >>> lib = CandidateLibrary.chain(["theta1", "theta2"])
        >>> [str(t) for t in lib.terms_]  # doctest: +NORMALIZE_WHITESPACE
        ['theta1_dot**2', 'theta2_dot**2', 'theta1_dot*theta2_dot*cos(theta1 - theta2)',
         'cos(theta1)', 'sin(theta1)', 'cos(theta2)', 'sin(theta2)']
        """
        return cls(
            coordinates,
            kind="chain",
            degree=degree,
            angles=angles,
            sin_coupling=sin_coupling,
            relative=relative,
            **kwargs,
        )

    @classmethod
    def from_urdf(cls, path, joints=None, **kwargs):
        """The energy regressor of a robot arm from its URDF (a :class:`RobotLibrary`).

        Terms: the 10 inertial parameters of every moving link (``m_<link>``,
        ``mx_<link>``, ..., ``Izz_<link>``) and a rotor inertia ``Ia_<joint>`` per
        joint, evaluated in torch; keywords (``armature=True``, ``locked=None``,
        ``gravity=(0, 0, -9.81)``, ``penalize=False``) and fitting: see
        :class:`lagsindy.robots.RobotLibrary`; identifiable combinations:
        :func:`lagsindy.robots.base_parameters`.
        """
        from .robots.library import RobotLibrary

        return RobotLibrary(path, joints, **kwargs)

    @classmethod
    def from_terms(cls, coordinates, terms, **kwargs):
        """A library of the given terms only (strings or sympy expressions)."""
        return cls(coordinates, list(terms), kind=None, **kwargs)

    # ------------------------------------------------------------------ building
    def _angle_names(self, names):
        if self.angles is None:
            return []
        if isinstance(self.angles, str):
            if self.angles == "all":
                return list(names)
            angles = [self.angles]
        else:
            angles = list(self.angles)
        unknown = [a for a in angles if a not in names]
        if unknown:
            raise ValueError(
                f"angles {unknown} are not among the coordinates {names}; "
                "list angles by coordinate name"
            )
        return angles

    def _generate(self, names):
        if self.kind is None:
            return []
        if self.kind not in _KINDS:
            raise ValueError(f"kind must be one of {_KINDS} or None, got {self.kind!r}")
        if not isinstance(self.degree, (int, np.integer)) or self.degree < 1:
            raise ValueError(f"degree must be a positive integer, got {self.degree!r}")
        angles = self._angle_names(names)
        q, qd, _ = symbols_for(names)
        if self.kind == "chain":
            return _chain_terms(
                names, angles, bool(self.sin_coupling), self.degree, bool(self.relative)
            )
        raw = [q[i] for i, n in enumerate(names) if n not in angles or self.raw_angles]
        trig = [
            f(q[i])
            for i, n in enumerate(names)
            if n in angles
            for f in (sp.sin, sp.cos)
        ]
        if self.kind == "polynomial":
            base = []
            for i, n in enumerate(names):
                if n not in angles or self.raw_angles:
                    base.append(q[i])
            base += list(qd)
            base += trig
            return _monomials(base, self.degree)
        poly = _monomials(raw + list(qd), self.degree)
        trig_monomials = _monomials(trig, self.degree) if trig else []
        cross = [t * p for t in trig_monomials for p in poly]
        return poly + trig_monomials + cross

    def _params_key(self):
        params = self.get_params(deep=False)
        return repr(sorted((k, repr(v)) for k, v in params.items()))

    def build(self):
        """Generate, parse and reduce the candidate terms; returns ``self``."""
        if self.coordinates is None:
            raise ValueError(
                "the library has no coordinates; pass coordinates=[...] or let "
                "LagrangianSINDy fill them in from the data"
            )
        names = check_coordinate_names(
            [self.coordinates]
            if isinstance(self.coordinates, str)
            else self.coordinates
        )
        candidates = self._generate(names)
        for term in self.terms or []:
            candidates.append(canonical(term, names))
        unique, seen = [], set()
        for c in candidates:
            c = sp.sympify(c)
            if c.is_number:
                continue  # constants are trivial and carry no information
            if c not in seen:
                seen.add(c)
                unique.append(c)
        if not unique:
            raise ValueError(
                "the library is empty: give kind='polynomial' or terms=[...]"
            )
        kept, removed = reduce_terms(
            unique, names, self.remove_trivial, self.remove_dependent
        )
        kept, removed = list(kept), list(removed)
        if not kept:
            raise ValueError(
                "every candidate term is trivial (its Euler-Lagrange expression is zero); "
                f"removed: {removed}"
            )
        self.coordinates_ = names
        self.candidates_ = unique
        self.terms_ = kept
        self.removed_ = removed
        self._built_key = self._params_key()
        self._compiled = None
        return self

    def _ensure_built(self):
        if getattr(self, "_built_key", None) != self._params_key():
            self.build()
        return self

    def __getattr__(self, name):
        # Build lazily on first access of a built attribute.
        if name in ("terms_", "candidates_", "removed_", "coordinates_"):
            self.build()
            return self.__dict__[name]
        raise AttributeError(
            f"{type(self).__name__!r} object has no attribute {name!r}"
        )

    def __add__(self, other):
        """A library of the terms of both (``self``'s first), reduced together.

        Both must name the same coordinates. The sum is a :meth:`from_terms` library
        of the two libraries' candidate terms (its parameters are those terms, so it
        clones and pickles like any library); it takes ``self``'s
        ``remove_trivial`` and ``remove_dependent``.

        Examples
        --------
        >>> from lagsindy import CandidateLibrary
        >>> lib = CandidateLibrary.chain(["theta1", "theta2"]) + CandidateLibrary.from_terms(
        ...     ["theta1", "theta2"], ["theta1_dot*theta2_dot"])
        >>> len(lib)
        8
        """
        if not isinstance(other, CandidateLibrary):
            return NotImplemented
        a, b = self._ensure_built(), other._ensure_built()
        if list(a.coordinates_) != list(b.coordinates_):
            raise ValueError(
                "libraries over different coordinates cannot be added: "
                f"{a.coordinates_} and {b.coordinates_}; build both over the same "
                "coordinate list"
            )
        return type(self).from_terms(
            list(a.coordinates_),
            list(a.candidates_) + list(b.candidates_),
            remove_trivial=self.remove_trivial,
            remove_dependent=self.remove_dependent,
        )

    def __len__(self) -> int:
        return len(self._ensure_built().terms_)

    def get_feature_names_out(self, input_features=None) -> np.ndarray:
        """Names of the candidate terms, as strings (sympy's ``str``).

        The strings are cached per tuple of built terms (printing with sympy costs
        about 0.1 ms a term, and a fit asks several times); a new array each call.
        """
        return np.asarray(_term_names(tuple(self._ensure_built().terms_)), dtype=object)

    def euler_lagrange(self) -> list[list[sp.Expr]]:
        """Symbolic Euler-Lagrange expressions, ``[term][coordinate]``."""
        self._ensure_built()
        return [euler_lagrange_expressions(t, self.coordinates_) for t in self.terms_]

    def to_torch(self):
        """Compile the terms into ``f(q, qd) -> Tensor (n_terms,)`` for one sample.

        The returned :class:`lagsindy._batched.TermKernels` is callable per sample
        (composable with ``torch.func``) and also evaluates the Euler-Lagrange columns
        of many samples as batched kernels (see :mod:`lagsindy._batched`).
        """
        self._ensure_built()
        if self.__dict__.get("_compiled") is None:
            self._compiled = compile_terms(self.terms_, self.coordinates_)
        return self._compiled

    def index(self, term) -> int:
        """Position of ``term`` (string or sympy) among the kept terms.

        Raises ``ValueError`` naming the closest reason when the term is not there
        (never generated, or removed as trivial or dependent).
        """
        self._ensure_built()
        expr = canonical(term, self.coordinates_)
        for k, t in enumerate(self.terms_):
            if t == expr or sp.expand(t - expr) == 0:
                return k
        for name, reason in self.removed_:
            if name == str(expr):
                raise ValueError(f"term {str(expr)!r} is not in the library: {reason}")
        raise ValueError(
            f"term {str(expr)!r} is not in the library; its terms are "
            f"{[str(t) for t in self.terms_][:12]}{' ...' if len(self.terms_) > 12 else ''}"
        )

    def decompose(self, lagrangian) -> tuple[np.ndarray, float]:
        """Express a Lagrangian in this library's terms (up to trivial terms).

        Solves ``EL(lagrangian) = sum_k c_k EL(term_k)`` in least squares over random
        points, so an equivalent Lagrangian written with other representatives
        (``1 - cos(q)**2`` for ``sin(q)**2``, added constants, total derivatives) maps
        to the library's own coefficients.

        Returns
        -------
        coef : ndarray of shape (n_terms,)
        residual : float
            Relative residual; near zero when the library can represent the Lagrangian.
        """
        self._ensure_built()
        expr = canonical(lagrangian, self.coordinates_)
        rng = np.random.default_rng(12345)
        a = sample_columns(self.terms_ + [expr], self.coordinates_, rng)
        coef = self._match_terms(expr)
        if coef is None:
            coef, *_ = np.linalg.lstsq(a[:, :-1], a[:, -1], rcond=None)
            coef[np.abs(coef) < 1e-10 * max(1.0, np.abs(coef).max(initial=0))] = 0.0
        resid = np.linalg.norm(a[:, :-1] @ coef - a[:, -1]) / max(
            np.linalg.norm(a[:, -1]), 1e-300
        )
        return coef, float(resid)

    def _match_terms(self, expr):
        """Coefficients when every non-constant term of ``expr`` is a library term.

        The common case (a true Lagrangian written in the library's own terms) needs
        no numerical solve: in a wide, ill-conditioned library (theta**3 * sin(theta)
        beside theta on [-pi, pi]) least squares leaves round-off on terms the
        Lagrangian lacks. ``None`` when some term is not in the library.
        """
        coef = np.zeros(len(self.terms_))
        for term in sp.Add.make_args(sp.expand(expr)):
            c, rest = term.as_coeff_Mul()
            if rest.is_number:
                continue  # constants do not change the equations of motion
            try:
                coef[self.index(rest)] += float(c)
            except (ValueError, TypeError):
                return None
        return coef

    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop("_compiled", None)
        return state

    def __repr__(self, N_CHAR_MAX=700):
        return super().__repr__(N_CHAR_MAX=N_CHAR_MAX)


@functools.lru_cache(maxsize=64)
def _term_names(terms: tuple) -> tuple:
    """``str`` of each term (cached: equal terms print alike)."""
    return tuple(str(t) for t in terms)
