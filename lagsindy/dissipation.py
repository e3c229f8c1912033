r"""Non-conservative force candidates: Rayleigh dissipation and direct forces.

The Euler-Lagrange equations with a Rayleigh dissipation function :math:`D(\dot q)` and
extra generalized forces :math:`Q(q, \dot q)` read

.. math::

    \frac{d}{dt} \frac{\partial L}{\partial \dot q} - \frac{\partial L}{\partial q}
    = \tau - \frac{\partial D}{\partial \dot q} + Q .

Each candidate here carries its generalized force vector (``-dD/dqdot`` for a Rayleigh
term), so it enters the regression linearly beside the Lagrangian's terms: a learned
coefficient ``d_j`` contributes ``d_j * force_j`` to the right-hand side.

The kinds of candidates (viscous, relative, drag, coulomb, bias, and any added with
:func:`lagsindy.force_kinds.register`) are records of :mod:`lagsindy.force_kinds`,
which lists their forces and units; this module builds terms from them.

Coulomb friction ``-mu * sign(qdot)`` is smoothed as ``-mu * tanh(qdot / eps)``;
``eps`` (default 0.01, in the coordinate's velocity units) is the velocity below which
the friction force fades linearly to zero. It keeps the regression and the simulation
smooth; choose it well below the typical speeds of the data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sympy as sp
from sklearn.base import BaseEstimator

from ._expr import check_coordinate_names, symbols_for
from ._params import cache_param_names
from .force_kinds import DEFAULT_EPS
from .force_kinds import get as get_kind
from .force_kinds import kinds as registered_kinds
from .force_kinds import names as kind_names


def __getattr__(name):
    # KINDS and DISSIPATIVE_KINDS read the registry (lagsindy.force_kinds) when
    # asked, so they include kinds registered later.
    if name == "KINDS":
        return kind_names()
    if name == "DISSIPATIVE_KINDS":
        # kinds whose force opposes the motion for a positive coefficient: a
        # negative one would feed energy in, so the fit constrains them to be
        # non-negative
        return tuple(k.name for k in registered_kinds() if k.dissipative)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@dataclass(frozen=True)
class ForceTerm:
    """One non-conservative candidate.

    Attributes
    ----------
    name : str
        e.g. ``"viscous(theta)"``, ``"relative(theta1,theta2)"``.
    kind : str
        A registered force kind (:mod:`lagsindy.force_kinds`), or ``"custom"``.
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

    def _record(self):
        """The term's :class:`~lagsindy.force_kinds.ForceKind`, or None (custom)."""
        return get_kind(self.kind) if self.kind in kind_names() else None

    @property
    def parameters(self) -> dict:
        """The kind's parameters of this term (Coulomb's ``eps``), from its forces."""
        record = self._record()
        if record is None or not record.parameters:
            return {}
        return _read_parameters(record, self.coordinates, self.forces)

    @property
    def eps(self) -> float | None:
        """Smoothing velocity of a term that has one (Coulomb); ``None`` otherwise."""
        return self.parameters.get("eps")

    @property
    def dissipative(self) -> bool:
        """Whether the coefficient must be non-negative (the force opposes motion)."""
        record = self._record()
        return record is not None and record.dissipative

    def units(self, coordinate_units: dict) -> str:
        """Units of its coefficient, from ``{coordinate: (q unit, force unit)}``."""
        q_unit, f_unit = coordinate_units.get(self.coordinates[0], ("[q]", "[F]"))
        record = self._record()
        if record is None:
            return "(force per unit coefficient)"
        return record.coefficient_units(q_unit, f_unit)


def _read_parameters(record, on, forces) -> dict:
    """``record``'s parameters of a term on ``on``, from its forces."""
    q, qd, _ = symbols_for(list(on))
    try:
        values = record.read_parameters(tuple(forces), tuple(q), tuple(qd))
    except (TypeError, AttributeError, IndexError, ArithmeticError) as exc:
        # a reader meeting a force of another shape (e.g. from a model file)
        raise ValueError(
            f"the parameters of a {record.name} term cannot be read from its forces "
            f"{[str(f) for f in forces]}: {exc!r}"
        ) from None
    return dict(values)


def make_term(
    kind: str, coordinates, all_coordinates, *, eps: float = DEFAULT_EPS, **parameters
) -> ForceTerm:
    """Build one candidate of ``kind`` on ``coordinates`` (one, or two for relative).

    Parameters
    ----------
    kind : str
        A registered force kind (:func:`lagsindy.force_kinds.names`).
    coordinates : str or tuple of str
        The coordinate the term acts on, or the kind's ``arity`` coordinates.
    all_coordinates : list of str
        The model's coordinates (the force vector has one entry per coordinate).
    eps : float, default=0.01
        Smoothing velocity, for kinds that have one (Coulomb); ignored by the others.
    **parameters
        The kind's other parameters (their defaults otherwise).

    Returns
    -------
    ForceTerm
    """
    record = get_kind(kind)
    names = list(all_coordinates)
    q, qd, _ = symbols_for(names)
    coords = (coordinates,) if isinstance(coordinates, str) else tuple(coordinates)
    for c in coords:
        if c not in names:
            raise ValueError(f"{c!r} is not one of the coordinates {names}")
    coords = record.check_coordinates(coords)
    if "eps" in record.parameter_names:
        parameters = {"eps": eps, **parameters}
    values = record.resolve(parameters)
    idx = [names.index(c) for c in coords]
    own, rayleigh = record.build(
        tuple(q[i] for i in idx), tuple(qd[i] for i in idx), **values
    )
    if own is None:
        if rayleigh is None:
            raise ValueError(
                f"the {kind} kind's builder returned neither forces nor a Rayleigh "
                "function"
            )
        # The built-in Rayleigh functions are polynomials in the velocities
        # (quadratic, or |v|**3 with its force given): expanding gives the same
        # expressions as simplify, at a hundredth of its cost.
        forces = tuple(sp.expand(-sp.diff(rayleigh, s)) for s in qd)
    else:
        own = tuple(own)
        if len(own) != len(coords):
            raise ValueError(
                f"the {kind} kind's builder returned {len(own)} forces for "
                f"{len(coords)} coordinate(s)"
            )
        forces = [sp.Integer(0)] * len(names)
        for i, f in zip(idx, own):
            forces[i] = sp.sympify(f)
        forces = tuple(forces)
    name = f"{kind}({','.join(coords)})"
    return ForceTerm(name, kind, coords, forces, rayleigh)


def rebuild_term(kind: str, coordinates, all_coordinates, forces) -> ForceTerm:
    """The term of ``kind`` on ``coordinates`` whose parameters ``forces`` show.

    For a saved term (a model file stores the forces, not the parameters): the
    kind's ``read_parameters`` recovers them and the term is built again; compare
    its forces with ``forces`` to check the entry.

    Raises
    ------
    ValueError
        Unknown kind, wrong coordinates, or forces without the kind's shape.
    """
    record = get_kind(kind)
    names = list(all_coordinates)
    coords = (coordinates,) if isinstance(coordinates, str) else tuple(coordinates)
    for c in coords:
        if c not in names:
            raise ValueError(f"{c!r} is not one of the coordinates {names}")
    coords = record.check_coordinates(coords)
    values = {}
    if record.parameters:
        try:
            values = _read_parameters(record, coords, list(forces))
        except ValueError as exc:
            raise ValueError(f"a {kind} term: {exc}") from None
    return make_term(kind, record.target(coords), names, **values)


@cache_param_names
class DissipationLibrary(BaseEstimator):
    """Candidate non-conservative forces, fitted together with the Lagrangian.

    Parameters
    ----------
    kinds : sequence of str, default=("viscous",)
        Kinds applied to every coordinate: ``"viscous"``, ``"drag"``, ``"coulomb"``,
        ``"bias"``, ``"relative"`` (viscous between every pair of coordinates, or
        the pairs in ``pairs``), and any registered with
        :func:`lagsindy.force_kinds.register` (:func:`lagsindy.force_kinds.names`
        lists them).
    coordinates : list of str, default=None
        ``None``: filled in from the Lagrangian library by the estimator.
    terms : list of tuple, default=None
        Extra single terms, each ``(kind, coordinate)`` or ``("relative", (a, b))``,
        optionally with a third item, a dict of the term's own parameters
        (``("coulomb", "x", {"eps": 0.02})``).
    pairs : list of tuple of str, default=None
        Pairs for ``"relative"`` and other kinds of two coordinates (default: all
        pairs).
    eps : float or dict, default=0.01
        Smoothing velocity of Coulomb friction (and of any kind with an ``eps``
        parameter), in the coordinate's velocity units: one value for every
        coordinate, or ``{coordinate: eps}`` (coordinates not named get 0.01).
        Choose it well below the data's typical speeds (about 1 % of the top
        speed): a larger value biases the fitted viscous friction.
    parameters : dict, default=None
        Other parameters of the kinds, ``{name: value}`` or ``{name: {coordinate:
        value}}`` (coordinates not named get the kind's default). ``None``: every
        kind's defaults.

    Attributes
    ----------
    terms_ : list of ForceTerm
        After :meth:`build`.

    Examples
    --------
    >>> from lagsindy.dissipation import DissipationLibrary
    >>> lib = DissipationLibrary(["viscous", "coulomb"], coordinates=["x", "theta"])
    >>> [t.name for t in lib.build().terms_]
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
        parameters=None,
    ):
        self.kinds = kinds
        self.coordinates = coordinates
        self.terms = terms
        self.pairs = pairs
        self.eps = eps
        self.parameters = parameters

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
        unknown = [k for k in kinds if k not in kind_names()]
        if unknown:
            raise ValueError(
                f"unknown dissipation kinds {unknown}; use some of {kind_names()} "
                "(or register one with lagsindy.force_kinds.register)"
            )
        self._check_parameters()
        out = []
        for kind in kinds:
            record = get_kind(kind)
            for target in record.targets(names, self.pairs):
                out.append(
                    make_term(
                        kind,
                        record.target(target),
                        names,
                        **self.parameters_for(kind, target[0]),
                    )
                )
        for spec in self.terms or []:
            try:
                kind, coords, *own = spec
                if len(own) > 1 or (own and not isinstance(own[0], dict)):
                    raise ValueError
            except (TypeError, ValueError):
                raise ValueError(
                    "a dissipation term is (kind, coordinate), ('relative', (a, b)) "
                    f"or either with a dict of parameters, got {spec!r}"
                ) from None
            first = coords if isinstance(coords, str) else tuple(coords)[:1]
            first = first if isinstance(first, str) else (first[0] if first else None)
            values = self.parameters_for(kind, first)
            values.update(own[0] if own else {})
            out.append(make_term(kind, coords, names, **values))
        unique, seen = [], set()
        for t in out:
            if t.name not in seen:
                seen.add(t.name)
                unique.append(t)
        self.coordinates_ = names
        self.terms_ = unique
        return self

    def parameters_for(self, kind: str, coordinate) -> dict:
        """The parameters a term of ``kind`` on ``coordinate`` gets from this library.

        ``eps`` from :attr:`eps`, the others from :attr:`parameters`, else the kind's
        defaults (:attr:`lagsindy.force_kinds.ForceKind.parameters`).
        """
        record = get_kind(kind)
        out = {}
        for name, default in record.parameters:
            if name == "eps":
                out[name] = self._eps_for(coordinate)
                continue
            value = (self.parameters or {}).get(name, default)
            if isinstance(value, dict):
                value = value.get(coordinate, default)
            out[name] = float(value)
        return out

    def _check_parameters(self):
        """``eps`` and ``parameters`` name known coordinates and parameters."""
        self._check_coordinate_keys("eps", self.eps)
        params = self.parameters or {}
        if not isinstance(params, dict):
            raise ValueError(
                "parameters must be a dict {name: value or {coordinate: value}}, got "
                f"{params!r}"
            )
        if "eps" in params:
            raise ValueError("set the smoothing velocity with eps=..., not parameters")
        known = {n for k in registered_kinds() for n in k.parameter_names}
        unknown = sorted(set(params) - known)
        if unknown:
            raise ValueError(
                f"parameters names {unknown}, which no force kind has; the kinds' "
                f"parameters are {sorted(known - {'eps'})}"
            )
        for name, value in params.items():
            self._check_coordinate_keys(f"parameters[{name!r}]", value)

    def _check_coordinate_keys(self, what, value):
        """A per-coordinate dict ``value`` names only the library's coordinates."""
        if not isinstance(value, dict) or self.coordinates is None:
            return
        coords = (
            [self.coordinates]
            if isinstance(self.coordinates, str)
            else self.coordinates
        )
        unknown = set(value) - set(coords)
        if unknown:
            raise ValueError(
                f"{what} names coordinates {sorted(unknown)} that are not among "
                f"{list(coords)}"
            )

    def _eps_for(self, coordinate) -> float:
        """The Coulomb smoothing velocity of ``coordinate``."""
        if isinstance(self.eps, dict):
            self._check_coordinate_keys("eps", self.eps)
            return float(self.eps.get(coordinate, DEFAULT_EPS))
        return float(self.eps)

    def get_feature_names_out(self, input_features=None) -> np.ndarray:
        """Names of the force candidates (``input_features`` is ignored)."""
        if not hasattr(self, "terms_"):
            self.build()
        return np.asarray([t.name for t in self.terms_], dtype=object)

    def __len__(self) -> int:
        if not hasattr(self, "terms_"):
            self.build()
        return len(self.terms_)


def library_of(terms, coordinates) -> DissipationLibrary:
    """A :class:`DissipationLibrary` that builds exactly ``terms`` (kinds, parameters).

    Each coordinate's ``eps`` (and other parameters) come from the first term that
    has them; a term whose parameters differ from those is listed with its own.
    """
    eps, params, specs = {}, {}, []
    for t in terms:
        values = t.parameters
        for name, value in values.items():
            shared = eps if name == "eps" else params.setdefault(name, {})
            shared.setdefault(t.coordinates[0], value)
        record = get_kind(t.kind)
        spec = (t.kind, record.target(t.coordinates))
        if any(
            (eps if name == "eps" else params[name])[t.coordinates[0]] != value
            for name, value in values.items()
        ):
            spec += (values,)
        specs.append(spec)
    return DissipationLibrary(
        kinds=(),
        coordinates=list(coordinates),
        eps=eps or DEFAULT_EPS,
        terms=specs,
        parameters=params or None,
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
    from .evaluator import is_term_function

    key = (
        tuple(coordinates),
        (lagrangian_terms,)  # a torch term function: the object itself
        if is_term_function(lagrangian_terms)
        else tuple(lagrangian_terms),
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

    from .evaluator import TermEvaluator

    n_dof = len(coordinates)
    rng = np.random.default_rng(0)
    from .evaluator import is_term_function

    n_l = (
        len(lagrangian_terms.names)
        if is_term_function(lagrangian_terms)
        else len(lagrangian_terms)
    )
    n_points = int(np.ceil(3 * (n_l + len(force_terms)) / n_dof)) + 24
    X = np.concatenate(
        [
            rng.uniform(-np.pi, np.pi, (n_points, n_dof)),
            rng.uniform(-2.0, 2.0, (n_points, 2 * n_dof)),
        ],
        axis=1,
    )
    ev = TermEvaluator(
        coordinates, lagrangian_terms, forces=[t.forces for t in force_terms]
    )
    Xt = torch.as_tensor(X, dtype=torch.float64)
    cols = ev.columns(*torch.split(Xt, n_dof, dim=1)).numpy()
    cols = cols.reshape(-1, cols.shape[2])  # (n_points * n_dof, p + f)
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
