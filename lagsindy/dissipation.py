r"""Non-conservative force candidates: Rayleigh dissipation and direct generalized forces.

The Euler-Lagrange equations with a Rayleigh dissipation function :math:`D(\dot q)` and
extra generalized forces :math:`Q(q, \dot q)` read

.. math::

    \frac{d}{dt} \frac{\partial L}{\partial \dot q} - \frac{\partial L}{\partial q}
    = \tau - \frac{\partial D}{\partial \dot q} + Q .

Each candidate here carries its generalized force vector (``-dD/dqdot`` for a Rayleigh
term), so it enters the regression linearly beside the Lagrangian's terms: a learned
coefficient ``d_j`` contributes ``d_j * force_j`` to the right-hand side.

=================  ============================  ==================================
kind               Rayleigh term / force         coefficient (units)
=================  ============================  ==================================
``viscous``        ``qd_i**2 / 2``               b, force per velocity
``relative``       ``(qd_i - qd_j)**2 / 2``      b between coordinates i and j
``drag``           ``|qd_i|**3 / 3``             c, force per velocity squared
``coulomb``        force ``-tanh(qd_i / eps)``   mu, force (smoothed sign)
``bias``           force ``+1`` on q_i           constant offset force
=================  ============================  ==================================

Coulomb friction ``-mu * sign(qdot)`` is smoothed as ``-mu * tanh(qdot / eps)``;
``eps`` (default 0.01, in the coordinate's velocity units) is the velocity below which
the friction force fades linearly to zero. It keeps the regression and the simulation
smooth; choose it well below the typical speeds of the data.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import sympy as sp
from sklearn.base import BaseEstimator

from ._expr import check_coordinate_names, symbols_for
from ._params import cache_param_names

KINDS = ("viscous", "relative", "drag", "coulomb", "bias")
# Kinds whose force opposes the motion for a positive coefficient: a negative one
# would feed energy in, so the fit constrains them to be non-negative.
DISSIPATIVE_KINDS = ("viscous", "relative", "drag", "coulomb")
DEFAULT_EPS = 0.01


@dataclass(frozen=True)
class ForceTerm:
    """One non-conservative candidate.

    Attributes
    ----------
    name : str
        e.g. ``"viscous(theta)"``, ``"relative(theta1,theta2)"``.
    kind : str
        One of ``KINDS`` (or ``"custom"``).
    coordinates : tuple of str
        The coordinate(s) it acts on.
    forces : tuple of sympy.Expr
        Generalized force per coordinate for a unit coefficient.
    rayleigh : sympy.Expr or None
        Its Rayleigh function for a unit coefficient (``forces = -dD/dqdot``), if it
        has one.
    """

    name: str
    kind: str
    coordinates: tuple
    forces: tuple
    rayleigh: sp.Expr | None = None

    @property
    def eps(self) -> float | None:
        """Smoothing velocity of a Coulomb term (from its force); ``None`` otherwise."""
        if self.kind != "coulomb":
            return None
        force = next(f for f in self.forces if f != 0)
        arg = next(iter(force.atoms(sp.tanh))).args[0]
        return float(1 / arg.as_coeff_Mul()[0])

    @property
    def dissipative(self) -> bool:
        """Whether the coefficient must be non-negative (the force opposes motion)."""
        return self.kind in DISSIPATIVE_KINDS

    def units(self, coordinate_units: dict) -> str:
        """Units of its coefficient, from ``{coordinate: (q unit, force unit)}``."""
        q_unit, f_unit = coordinate_units.get(self.coordinates[0], ("[q]", "[F]"))
        if self.kind in ("viscous", "relative"):
            return f"{f_unit}*s/{q_unit}"
        if self.kind == "drag":
            return f"{f_unit}*s^2/{q_unit}^2"
        if self.kind in ("coulomb", "bias"):
            return f_unit
        return "(force per unit coefficient)"


def make_term(
    kind: str, coordinates, all_coordinates, *, eps: float = DEFAULT_EPS
) -> ForceTerm:
    """Build one candidate of ``kind`` on ``coordinates`` (one name, or two for relative)."""
    names = list(all_coordinates)
    _, qd, _ = symbols_for(names)
    coords = (coordinates,) if isinstance(coordinates, str) else tuple(coordinates)
    for c in coords:
        if c not in names:
            raise ValueError(f"{c!r} is not one of the coordinates {names}")
    idx = [names.index(c) for c in coords]
    zero = [sp.Integer(0)] * len(names)
    if kind == "relative":
        if len(coords) != 2 or coords[0] == coords[1]:
            raise ValueError(
                f"a relative term needs two different coordinates, got {coords}"
            )
        rel = qd[idx[0]] - qd[idx[1]]
        rayleigh = rel**2 / 2
    elif len(coords) != 1:
        raise ValueError(f"a {kind} term acts on one coordinate, got {coords}")
    v = qd[idx[0]]
    if kind == "viscous":
        rayleigh = v**2 / 2
    elif kind == "drag":
        rayleigh = sp.Abs(v) ** 3 / 3
        forces = list(zero)
        forces[idx[0]] = -sp.Abs(v) * v  # -dD/dqdot, written without sign()
        return ForceTerm(f"drag({coords[0]})", kind, coords, tuple(forces), rayleigh)
    elif kind == "coulomb":
        if not eps > 0:
            raise ValueError(f"eps must be positive, got {eps}")
        forces = list(zero)
        forces[idx[0]] = -sp.tanh(v / sp.Float(eps))
        return ForceTerm(f"coulomb({coords[0]})", kind, coords, tuple(forces), None)
    elif kind == "bias":
        forces = list(zero)
        forces[idx[0]] = sp.Integer(1)
        return ForceTerm(f"bias({coords[0]})", kind, coords, tuple(forces), None)
    elif kind != "relative":
        raise ValueError(f"unknown dissipation kind {kind!r}; use one of {KINDS}")
    # The Rayleigh functions left here are quadratic polynomials: expanding gives
    # the same expressions as simplify, at a hundredth of its cost.
    forces = tuple(sp.expand(-sp.diff(rayleigh, s)) for s in qd)
    name = f"{kind}({','.join(coords)})"
    return ForceTerm(name, kind, coords, forces, rayleigh)


@cache_param_names
class DissipationLibrary(BaseEstimator):
    """Candidate non-conservative forces, fitted together with the Lagrangian.

    Parameters
    ----------
    kinds : sequence of str, default=("viscous",)
        Kinds applied to every coordinate: ``"viscous"``, ``"drag"``, ``"coulomb"``,
        ``"bias"``, and ``"relative"`` (viscous between every pair of coordinates, or
        the pairs in ``pairs``).
    coordinates : list of str, default=None
        ``None``: filled in from the Lagrangian library by the estimator.
    terms : list of tuple, default=None
        Extra single terms, each ``(kind, coordinate)`` or ``("relative", (a, b))``.
    pairs : list of tuple of str, default=None
        Pairs for ``"relative"`` (default: all pairs).
    eps : float or dict, default=0.01
        Smoothing velocity of Coulomb friction, in the coordinate's velocity units:
        one value for every coordinate, or ``{coordinate: eps}`` (coordinates not
        named get 0.01). Choose it well below the data's typical speeds (about 1 %
        of the top speed): a larger value biases the fitted viscous friction.

    Attributes
    ----------
    terms_ : list of ForceTerm
        After :meth:`build`.

    Examples
    --------
    >>> from lagsindy.dissipation import DissipationLibrary
    >>> lib = DissipationLibrary(["viscous", "coulomb"], coordinates=["x", "theta"]).build()
    >>> [t.name for t in lib.terms_]
    ['viscous(x)', 'viscous(theta)', 'coulomb(x)', 'coulomb(theta)']
    """

    def __init__(
        self,
        kinds=("viscous",),
        coordinates=None,
        *,
        terms=None,
        pairs=None,
        eps=DEFAULT_EPS,
    ):
        self.kinds = kinds
        self.coordinates = coordinates
        self.terms = terms
        self.pairs = pairs
        self.eps = eps

    def build(self):
        """Create the candidate terms; returns ``self``."""
        if self.coordinates is None:
            raise ValueError(
                "the dissipation library has no coordinates; pass coordinates=[...]"
            )
        names = check_coordinate_names(
            [self.coordinates]
            if isinstance(self.coordinates, str)
            else self.coordinates
        )
        kinds = [self.kinds] if isinstance(self.kinds, str) else list(self.kinds or [])
        unknown = [k for k in kinds if k not in KINDS]
        if unknown:
            raise ValueError(
                f"unknown dissipation kinds {unknown}; use some of {KINDS}"
            )
        out = []
        eps = self._eps_for
        for kind in kinds:
            if kind == "relative":
                pairs = self.pairs or list(itertools.combinations(names, 2))
                out += [make_term(kind, pair, names) for pair in pairs]
            else:
                out += [make_term(kind, c, names, eps=eps(c)) for c in names]
        for spec in self.terms or []:
            try:
                kind, coords = spec
            except (TypeError, ValueError):
                raise ValueError(
                    f"a dissipation term is (kind, coordinate) or ('relative', (a, b)), got {spec!r}"
                ) from None
            first = coords if isinstance(coords, str) else None
            out.append(make_term(kind, coords, names, eps=eps(first)))
        unique, seen = [], set()
        for t in out:
            if t.name not in seen:
                seen.add(t.name)
                unique.append(t)
        self.coordinates_ = names
        self.terms_ = unique
        return self

    def _eps_for(self, coordinate) -> float:
        """The Coulomb smoothing velocity of ``coordinate``."""
        if isinstance(self.eps, dict):
            unknown = set(self.eps) - set(
                [self.coordinates]
                if isinstance(self.coordinates, str)
                else self.coordinates
            )
            if unknown:
                raise ValueError(
                    f"eps names coordinates {sorted(unknown)} that are not among "
                    f"{list(self.coordinates)}"
                )
            return float(self.eps.get(coordinate, DEFAULT_EPS))
        return float(self.eps)

    def get_feature_names_out(self, input_features=None) -> np.ndarray:
        if not hasattr(self, "terms_"):
            self.build()
        return np.asarray([t.name for t in self.terms_], dtype=object)

    def __len__(self) -> int:
        if not hasattr(self, "terms_"):
            self.build()
        return len(self.terms_)


def library_of(terms, coordinates) -> DissipationLibrary:
    """A :class:`DissipationLibrary` that builds exactly ``terms`` (kinds, eps)."""
    eps = {t.coordinates[0]: t.eps for t in terms if t.kind == "coulomb"}
    return DissipationLibrary(
        kinds=(),
        coordinates=list(coordinates),
        eps=eps or DEFAULT_EPS,
        terms=[
            (t.kind, t.coordinates if t.kind == "relative" else t.coordinates[0])
            for t in terms
        ],
    )


def assemble(terms, coefficients, coordinates):
    """Rayleigh function and direct forces of learned terms, for a MechanicalModel.

    Returns
    -------
    rayleigh : sympy.Expr
        ``sum d_j D_j`` over the Rayleigh terms.
    forces : list of sympy.Expr
        ``sum d_j Q_j`` per coordinate over the terms without a Rayleigh function.
    """
    rayleigh = sp.Integer(0)
    forces = [sp.Integer(0)] * len(coordinates)
    for term, d in zip(terms, coefficients):
        if d == 0:
            continue
        if term.rayleigh is not None:
            rayleigh += sp.Float(d) * term.rayleigh
        else:
            forces = [f + sp.Float(d) * g for f, g in zip(forces, term.forces)]
    return rayleigh, forces


# reduce_forces' outcome by its inputs (``diagnose`` refits the same library and
# dissipation candidates several times; each reduction builds an operator).
_REDUCED: dict = {}
_REDUCED_SIZE = 32


def reduce_forces(lagrangian_terms, force_terms, coordinates, *, tol: float = 1e-7):
    """Drop force candidates whose regression column duplicates earlier columns.

    A constant ``bias`` force on ``x`` has the same Euler-Lagrange column as a linear
    potential term ``x`` in the Lagrangian; keeping both would make the split between
    them arbitrary. Columns are compared at random states (as the Lagrangian library's
    own reduction does); Lagrangian terms come first, so they are kept.

    Returns
    -------
    kept : list of ForceTerm
    removed : list of (name, reason)
    """
    if not force_terms:
        return [], []
    # The outcome depends on the expressions only (the columns are compared at
    # fixed random states): kept as the indices of the removed candidates.
    key = (
        tuple(coordinates),
        tuple(lagrangian_terms),
        tuple(tuple(t.forces) for t in force_terms),
        float(tol),
    )
    if key not in _REDUCED:
        if len(_REDUCED) >= _REDUCED_SIZE:
            _REDUCED.pop(next(iter(_REDUCED)))
        _REDUCED[key] = _reduce_forces(lagrangian_terms, force_terms, coordinates, tol)
    removed = _REDUCED[key]
    kept = [t for j, t in enumerate(force_terms) if j not in removed]
    return kept, [(force_terms[j].name, removed[j]) for j in sorted(removed)]


def _reduce_forces(lagrangian_terms, force_terms, coordinates, tol) -> dict:
    """:func:`reduce_forces` computed: {index of a removed candidate: reason}."""
    import torch

    from .euler_lagrange import EulerLagrangeOperator

    n_dof = len(coordinates)
    rng = np.random.default_rng(0)
    n_points = int(np.ceil(3 * (len(lagrangian_terms) + len(force_terms)) / n_dof)) + 24
    X = np.concatenate(
        [
            rng.uniform(-np.pi, np.pi, (n_points, n_dof)),
            rng.uniform(-2.0, 2.0, (n_points, 2 * n_dof)),
        ],
        axis=1,
    )
    op = EulerLagrangeOperator(
        coordinates, lagrangian_terms, forces=[t.forces for t in force_terms]
    )
    cols = op.columns(torch.as_tensor(X, dtype=torch.float64)).numpy()
    cols = cols.reshape(-1, cols.shape[2])  # (n_points * n_dof, p + f)
    n_l = len(lagrangian_terms)
    basis = np.zeros((cols.shape[0], 0))
    for k in range(n_l):
        c = cols[:, k]
        r = c - basis @ (basis.T @ c)
        if np.linalg.norm(r) > 1e-9 * max(np.linalg.norm(c), 1e-300):
            basis = np.concatenate([basis, (r / np.linalg.norm(r))[:, None]], axis=1)
    removed = {}
    for j in range(len(force_terms)):
        c = cols[:, n_l + j]
        norm = np.linalg.norm(c)
        unit = c / norm if norm > 0 else c
        r = unit - basis @ (basis.T @ unit)
        r = r - basis @ (basis.T @ r)
        if norm == 0 or np.linalg.norm(r) < tol:
            removed[j] = (
                "its regression column duplicates Lagrangian or earlier "
                "dissipation columns (e.g. a constant force equals a linear potential)"
            )
            continue
        basis = np.concatenate([basis, (r / np.linalg.norm(r))[:, None]], axis=1)
    return removed
