r"""Force kinds: one record per kind of non-conservative candidate force.

A *force kind* (``"viscous"``, ``"coulomb"``, ...) says everything the package needs
to know about one family of candidate forces: how to build its force for a unit
coefficient, whether it only removes energy (its coefficient is then constrained
non-negative), the units of its coefficient, how reports name it, its parameters
(Coulomb's smoothing velocity ``eps``) and how they are read back from a model file,
whether :func:`~lagsindy.diagnose` proposes it by default, and how many coordinates
it acts on. :class:`~lagsindy.dissipation.DissipationLibrary`, ``diagnose``'s
catalogue, its report and scoring, the model file and the command line all iterate
this registry, so a new kind is one :class:`ForceKind` passed to :func:`register`.

=================  ===================================  =========================
kind               force for a unit coefficient         coefficient (units)
=================  ===================================  =========================
``viscous``        ``-qd_i`` (Rayleigh ``qd_i**2/2``)   force per velocity
``relative``       Rayleigh ``(qd_i - qd_j)**2 / 2``    force per velocity
``drag``           ``-|qd_i| qd_i``                     force per velocity squared
``coulomb``        ``-tanh(qd_i / eps)``                force
``bias``           ``+1``                               force
``stribeck``       ``-exp(-(qd_i/v_s)**2)``             force
                   ``* tanh(qd_i/eps)``
=================  ===================================  =========================

Stribeck friction, ``-(mu_c + (mu_s - mu_c) exp(-(qd/v_s)**2)) tanh(qd/eps)``, is
nonlinear in its parameters; with the Stribeck velocity ``v_s`` fixed it is Coulomb
friction (coefficient ``mu_c``) plus the Stribeck *bump* (coefficient
``mu_s - mu_c``, static friction above the kinetic, constrained >= 0). The
``stribeck`` kind is the bump alone, fitted beside ``coulomb`` with the same ``eps``
(``DissipationLibrary(["coulomb", "stribeck"], parameters={"v_s": 0.05})``);
``diagnose`` proposes it only when named in its ``catalogue``.

Only this module's records decide which kinds are *dissipative*: ``viscous``,
``relative``, ``drag``, ``coulomb`` and ``stribeck`` oppose the motion for a positive
coefficient, so fits constrain their coefficients to be non-negative; ``bias`` (a
constant offset force) can feed energy in and is free in sign.

This module imports only the standard library (the command line's ``--help`` lists
the kinds without importing sympy); the builders import sympy when they run.

Examples
--------
A cubic damping force ``-b qd**3`` (Rayleigh function ``qd**4 / 4``):

>>> from lagsindy.force_kinds import ForceKind, register, unregister
>>> cubic = register(ForceKind(
...     "cubic",
...     build=lambda q, qd: (None, qd[0] ** 4 / 4),
...     dissipative=True,
...     units="{F}*s^3/{q}^3",
...     units_text="per unit of {0}_dot^3",
...     wording="cubic damping",
... ))
>>> from lagsindy import DissipationLibrary
>>> DissipationLibrary(["viscous", "cubic"], coordinates=["x"]).build().terms_[1].forces
(-x_dot**3,)
>>> unregister("cubic")
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Callable
from dataclasses import dataclass

#: Default smoothing velocity of Coulomb friction (and of the Stribeck bump).
DEFAULT_EPS = 0.01
#: Default Stribeck velocity of the ``stribeck`` kind, in the coordinate's velocity
#: units.
DEFAULT_STRIBECK_VELOCITY = 0.1

# Candidate kinds of diagnose's catalogue that are not forces; a force kind cannot
# take these names (nor "custom", the kind of a hand-made ForceTerm).
RESERVED_NAMES = ("gain", "conservative", "delay", "joint_delay", "custom")
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_NUMBERS = {1: "one", 2: "two", 3: "three", 4: "four"}


@dataclass(frozen=True)
class ForceKind:
    """One kind of candidate non-conservative force.

    Parameters
    ----------
    name : str
        The kind's name, e.g. ``"viscous"``; terms are named ``"name(x)"`` or
        ``"name(a,b)"``. A Python identifier, not one of :data:`RESERVED_NAMES`.
    build : callable
        ``build(q, qd, **parameters) -> (forces, rayleigh)`` for a unit coefficient:
        ``q`` and ``qd`` are tuples of the sympy symbols of the term's coordinates and
        their velocities (``arity`` of each); ``forces`` is a tuple of the generalized
        force on each of those coordinates (zero on the others), or ``None`` to take
        ``-dD/dqd`` of ``rayleigh``; ``rayleigh`` is the Rayleigh function ``D`` or
        ``None`` (a direct force). Raise ``ValueError`` on a bad parameter.
    arity : int, default=1
        Number of (different) coordinates a term acts on: 1, or 2 for forces between
        pairs of coordinates (``relative``). A library's kind of arity 2 is applied to
        its ``pairs``, by default every pair.
    dissipative : bool, default=False
        Whether the force opposes the motion for a positive coefficient, so that the
        fit constrains the coefficient to be non-negative (a negative one would feed
        energy in). A kind that may feed energy in (``bias``) is not dissipative.
    units : str, default="(force per unit coefficient)"
        Units of the coefficient, a template over ``{q}`` and ``{F}``, the units of
        the (first) coordinate and of its generalized force: viscous ``"{F}*s/{q}"``.
    units_text : str, default="per unit coefficient"
        The coefficient's units in words when no units are given, a template over the
        coordinate names ``{0}``, ``{1}``: viscous ``"per unit of {0}_dot"``.
    wording : str, default=""
        How reports name the effect (``"viscous damping"``); the name when empty.
    parameters : tuple of (str, float), default=()
        The builder's keyword parameters and their defaults, e.g.
        ``(("eps", 0.01),)``. A parameter named ``eps`` is the coordinate's smoothing
        velocity: :class:`~lagsindy.dissipation.DissipationLibrary`'s ``eps`` and
        ``diagnose``'s ``eps`` set it for every kind that has one.
    read_parameters : callable, default=None
        ``read_parameters(forces, q, qd) -> dict``: the parameters of a term from its
        generalized force on every coordinate of the model (sympy expressions, zero
        on the coordinates it does not act on; as built, or as read from a model
        file, which stores the forces and not the parameters); ``q`` and ``qd`` as
        for ``build``. Raise ``ValueError`` when the forces do not have the kind's
        shape. Required when ``parameters`` is not empty.
    in_default_catalogue : bool, default=False
        Whether :func:`~lagsindy.diagnose` proposes this kind when no ``catalogue`` is
        given (a kind can always be named in ``catalogue``).
    probe : bool, default=False
        Whether a fit without a dissipation library adds this kind as a probe force
        (:mod:`lagsindy.formulation.probes`). Read once, when that module is imported:
        meant for the built-in kinds.

    See Also
    --------
    register : add a kind to the registry.
    lagsindy.dissipation.make_term : build one term of a kind.
    """

    name: str
    build: Callable
    arity: int = 1
    dissipative: bool = False
    units: str = "(force per unit coefficient)"
    units_text: str = "per unit coefficient"
    wording: str = ""
    parameters: tuple = ()
    read_parameters: Callable | None = None
    in_default_catalogue: bool = False
    probe: bool = False

    def __post_init__(self):
        if not isinstance(self.name, str) or not _NAME.match(self.name):
            raise ValueError(
                f"a force kind's name must be a Python identifier, got {self.name!r}"
            )
        if self.name in RESERVED_NAMES:
            raise ValueError(
                f"{self.name!r} is reserved (one of {RESERVED_NAMES}); choose another "
                "name for the force kind"
            )
        if not callable(self.build):
            raise ValueError(f"force kind {self.name!r}: build must be callable")
        if not isinstance(self.arity, int) or not 1 <= self.arity <= 4:
            raise ValueError(
                f"force kind {self.name!r}: arity must be 1 to 4, got {self.arity!r}"
            )
        params = tuple(tuple(p) for p in self.parameters)
        if any(len(p) != 2 or not _NAME.match(str(p[0])) for p in params):
            raise ValueError(
                f"force kind {self.name!r}: parameters must be (name, default) pairs, "
                f"got {self.parameters!r}"
            )
        object.__setattr__(self, "parameters", params)
        if params and not callable(self.read_parameters):
            raise ValueError(
                f"force kind {self.name!r} has parameters "
                f"{[p[0] for p in params]}: give read_parameters(forces, q, qd), which "
                "recovers them from a term's forces (model files store the forces)"
            )
        for field, template, args in (
            ("units", self.units, {"q": "m", "F": "N"}),
            ("units_text", self.units_text, {}),
        ):
            try:
                template.format(*(["a"] * self.arity), **args)
            except (KeyError, IndexError, ValueError, AttributeError) as exc:
                raise ValueError(
                    f"force kind {self.name!r}: {field} {template!r} is not a valid "
                    f"template ({exc!r}); see ForceKind's documentation"
                ) from None

    @property
    def nonnegative(self) -> bool:
        """Whether fits constrain the coefficient to be non-negative (= dissipative)."""
        return self.dissipative

    @property
    def parameter_names(self) -> tuple:
        """Names of the builder's parameters."""
        return tuple(name for name, _ in self.parameters)

    @property
    def defaults(self) -> dict:
        """The parameters' default values."""
        return dict(self.parameters)

    def target(self, coordinates):
        """A term's coordinates as a library term spec takes them.

        One name for a kind of arity 1, a tuple of names otherwise.
        """
        coords = (coordinates,) if isinstance(coordinates, str) else tuple(coordinates)
        return coords[0] if self.arity == 1 and len(coords) == 1 else coords

    def targets(self, coordinates, pairs=None) -> list:
        """The coordinate tuples a library applies this kind to.

        Every coordinate for arity 1; for arity 2, ``pairs`` or else every pair; for
        a larger arity every combination.
        """
        coords = list(coordinates)
        if self.arity == 1:
            return [(c,) for c in coords]
        if self.arity == 2 and pairs:
            return [tuple(p) for p in pairs]
        return list(itertools.combinations(coords, self.arity))

    def check_coordinates(self, coordinates) -> tuple:
        """The term's coordinates as a tuple; ``ValueError`` for a wrong number."""
        coords = (coordinates,) if isinstance(coordinates, str) else tuple(coordinates)
        if self.arity == 1:
            if len(coords) != 1:
                raise ValueError(
                    f"a {self.name} term acts on one coordinate, got {coords}"
                )
        elif len(coords) != self.arity or len(set(coords)) != self.arity:
            raise ValueError(
                f"a {self.name} term needs "
                f"{_NUMBERS.get(self.arity, self.arity)} different coordinates, "
                f"got {coords}"
            )
        return coords

    def resolve(self, parameters: dict) -> dict:
        """The builder's parameters: ``parameters`` over the defaults, checked."""
        unknown = sorted(set(parameters) - set(self.parameter_names))
        if unknown:
            raise ValueError(
                f"a {self.name} term has no parameters {unknown}; its parameters are "
                f"{list(self.parameter_names)}"
            )
        return {**self.defaults, **parameters}

    def coefficient_units(self, q_unit: str, f_unit: str) -> str:
        """Units of the coefficient from the coordinate's and its force's units."""
        return self.units.format(q=q_unit, F=f_unit)

    def unit_words(self, coordinates) -> str:
        """The coefficient's units in words, without units (``units_text``)."""
        return self.units_text.format(*coordinates)

    @property
    def description(self) -> str:
        """How reports name the effect."""
        return self.wording or self.name


_REGISTRY: dict = {}
_BUILT_IN: set = set()
# Every record a name has had in this process: fits cache the terms they built by
# the library's parameters (the kinds' names), so a name never changes meaning.
_EVER: dict = {}


def register(kind: ForceKind) -> ForceKind:
    """Add ``kind`` to the registry; returns it.

    A name keeps its meaning for the whole session (fits cache the terms built from
    it): registering another record under a name used before raises; the same
    record may be registered again after :func:`unregister`.

    Parameters
    ----------
    kind : ForceKind

    Returns
    -------
    ForceKind
        ``kind``.
    """
    if not isinstance(kind, ForceKind):
        raise TypeError(f"register takes a ForceKind, got {type(kind).__name__}")
    if kind.name in _REGISTRY:
        raise ValueError(
            f"force kind {kind.name!r} is already registered"
            + (" (a built-in kind)" if kind.name in _BUILT_IN else "")
        )
    if _EVER.get(kind.name, kind) is not kind:
        raise ValueError(
            f"a different force kind was registered as {kind.name!r} earlier in this "
            "session, and fits may have cached terms built from it: give the new "
            "kind another name (or restart the interpreter)"
        )
    _REGISTRY[kind.name] = _EVER[kind.name] = kind
    return kind


def unregister(name: str) -> None:
    """Remove a kind added with :func:`register` (built-in kinds stay)."""
    if name in _BUILT_IN:
        raise ValueError(f"{name!r} is a built-in force kind; it cannot be removed")
    if name not in _REGISTRY:
        raise ValueError(f"no force kind {name!r} is registered")
    del _REGISTRY[name]


def get(name: str) -> ForceKind:
    """The registered kind ``name``; ``ValueError`` naming the known kinds if none."""
    try:
        return _REGISTRY[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown dissipation kind {name!r}; use one of {names()} or register a "
            "ForceKind (lagsindy.force_kinds.register)"
        ) from None


def names() -> tuple:
    """Names of the registered kinds, built-in ones first, in registration order."""
    return tuple(_REGISTRY)


def kinds() -> tuple:
    """The registered :class:`ForceKind` records, in registration order."""
    return tuple(_REGISTRY.values())


# -- the built-in kinds ------------------------------------------------------------


def _positive(name, value) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be positive, got {value}")
    return value


def _velocity_scale(expr, func, qd, what: str, power: int = 1) -> tuple:
    """The velocity scale in the single ``func`` atom of ``expr``.

    The atom's argument must be ``c * qd**power`` (``ValueError`` naming ``what``
    otherwise); returns ``(|c| ** (-1/power), c)``.
    """
    atoms = list(expr.atoms(func))
    if len(atoms) != 1:
        raise ValueError(f"its force needs exactly one {what}")
    coeff, rest = atoms[0].args[0].as_coeff_Mul()
    if rest != qd**power or coeff == 0:
        raise ValueError(f"its force needs exactly one {what}")
    scale = float(1 / abs(coeff))  # sympy's division, as the files were always read
    return (scale if power == 1 else scale ** (1.0 / power)), float(coeff)


def _viscous(q, qd):
    return None, qd[0] ** 2 / 2


def _relative(q, qd):
    return None, (qd[0] - qd[1]) ** 2 / 2


def _drag(q, qd):
    import sympy as sp

    v = qd[0]
    return (-sp.Abs(v) * v,), sp.Abs(v) ** 3 / 3  # -dD/dqdot, written without sign()


def _coulomb(q, qd, *, eps):
    import sympy as sp

    return (-sp.tanh(qd[0] / sp.Float(_positive("eps", eps))),), None


def _read_coulomb(forces, q, qd):
    import sympy as sp

    eps, _ = _velocity_scale(sp.Add(*forces), sp.tanh, qd[0], "tanh(qdot/eps)")
    return {"eps": _positive("the Coulomb smoothing velocity eps", eps)}


def _bias(q, qd):
    import sympy as sp

    return (sp.Integer(1),), None


def _stribeck(q, qd, *, eps, v_s):
    import sympy as sp

    v = qd[0]
    eps, v_s = _positive("eps", eps), _positive("v_s", v_s)
    return (-sp.exp(-((v / sp.Float(v_s)) ** 2)) * sp.tanh(v / sp.Float(eps)),), None


def _read_stribeck(forces, q, qd):
    import sympy as sp

    force = sp.Add(*forces)
    eps, _ = _velocity_scale(force, sp.tanh, qd[0], "tanh(qdot/eps)")
    v_s, coeff = _velocity_scale(force, sp.exp, qd[0], "exp(-(qdot/v_s)**2)", 2)
    if coeff >= 0:
        raise ValueError("its force needs exactly one exp(-(qdot/v_s)**2)")
    return {
        "eps": _positive("the smoothing velocity eps", eps),
        "v_s": _positive("the Stribeck velocity v_s", v_s),
    }


for _kind in (
    ForceKind(
        "viscous",
        _viscous,
        dissipative=True,
        units="{F}*s/{q}",
        units_text="per unit of {0}_dot",
        wording="viscous damping",
        in_default_catalogue=True,
        probe=True,
    ),
    ForceKind(
        "relative",
        _relative,
        arity=2,
        dissipative=True,
        units="{F}*s/{q}",
        units_text="per unit of {0}_dot-{1}_dot",
        wording="relative (joint) damping",
        in_default_catalogue=True,
    ),
    ForceKind(
        "drag",
        _drag,
        dissipative=True,
        units="{F}*s^2/{q}^2",
        units_text="per unit of {0}_dot^2",
        wording="quadratic drag",
        in_default_catalogue=True,
    ),
    ForceKind(
        "coulomb",
        _coulomb,
        dissipative=True,
        units="{F}",
        units_text="force units of {0}",
        wording="Coulomb friction",
        parameters=(("eps", DEFAULT_EPS),),
        read_parameters=_read_coulomb,
        in_default_catalogue=True,
        probe=True,
    ),
    ForceKind(
        "bias",
        _bias,
        dissipative=False,  # a constant offset can feed energy in: free in sign
        units="{F}",
        units_text="force units of {0}",
        wording="constant offset force",
        in_default_catalogue=True,
    ),
    # The Stribeck bump mu_s - mu_c >= 0 (static friction at least the kinetic).
    ForceKind(
        "stribeck",
        _stribeck,
        dissipative=True,
        units="{F}",
        units_text="force units of {0}",
        wording="Stribeck friction",
        parameters=(("eps", DEFAULT_EPS), ("v_s", DEFAULT_STRIBECK_VELOCITY)),
        read_parameters=_read_stribeck,
    ),
):
    register(_kind)
    _BUILT_IN.add(_kind.name)
del _kind
