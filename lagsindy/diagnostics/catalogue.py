"""The candidate effects :func:`~lagsindy.diagnose` can try.

The force kinds of :mod:`lagsindy.force_kinds` (by default those marked
``in_default_catalogue``: viscous damping, relative (joint) damping, quadratic drag,
Coulomb friction and a constant offset force, on every coordinate or pair), an input
gain error (when several coordinates are driven), missing conservative terms and an
input delay.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import sympy as sp

from .._expr import canonical, symbols_for
from ..dissipation import DEFAULT_EPS, DissipationLibrary, make_term
from ..force_kinds import get as get_kind
from ..force_kinds import kinds as registered_kinds
from ..force_kinds import names as kind_names
from .report import Candidate

# Candidate kinds that are not force kinds: tried before the forces (delay) and
# after them (gain, conservative).
_BEFORE_FORCES = ("delay",)
_AFTER_FORCES = ("gain", "conservative")
# Delay kinds: one for the whole input (in the default catalogue), one per input
# column (named: a robot's joints; lagsindy.robots.ROBOT_CATALOGUE).
_DELAYS = ("delay", "joint_delay")


class _DefaultCatalogue(Sequence):
    """``diagnose``'s default kinds, read from the force-kind registry when used.

    ``("delay", <force kinds in the default catalogue>, "gain", "conservative")``:
    a kind registered later with ``in_default_catalogue=True`` is included.
    """

    def _kinds(self) -> tuple:
        forces = tuple(k.name for k in registered_kinds() if k.in_default_catalogue)
        return _BEFORE_FORCES + forces + _AFTER_FORCES

    def __getitem__(self, index):
        return self._kinds()[index]

    def __len__(self) -> int:
        return len(self._kinds())

    def __eq__(self, other):
        return tuple(self) == (tuple(other) if isinstance(other, Sequence) else other)

    def __hash__(self):
        return hash(self._kinds())

    def __repr__(self) -> str:
        return repr(self._kinds())


DEFAULT_CATALOGUE = _DefaultCatalogue()


class _KindSet:
    """Names of the registered force kinds that pass ``test``, read when used."""

    def __init__(self, test):
        self._test = test

    def __contains__(self, name) -> bool:
        return name in kind_names() and self._test(get_kind(name))

    def __iter__(self):
        return iter([k.name for k in registered_kinds() if self._test(k)])


# Candidates that are force kinds (built by the dissipation library), and those
# whose coefficient must be non-negative (dissipative: they only remove energy;
# bias, a constant offset, is a force kind but not dissipative).
_DISSIPATIVE = _KindSet(lambda kind: True)
_NONNEGATIVE = _KindSet(lambda kind: kind.dissipative)
# Coulomb smoothing velocity, relative to the 99th percentile of |q_dot|.
_EPS_FRACTION = 0.01


def velocity_eps(X, n_dof, coordinates) -> dict:
    """Coulomb smoothing velocity per coordinate from the data's velocity scale.

    ``eps = 0.01 * (99th percentile of |q_dot|)``: the smoothed sign reaches 76 % of
    its full value at 1 % of the top speed, so a viscous coefficient fitted beside it
    is not biased (a fixed ``eps=0.01`` biased it by -6 % on an axis whose top speed
    was 0.1 m/s).
    """
    qd = np.abs(np.asarray(X, dtype=float)[:, n_dof : 2 * n_dof])
    top = np.quantile(qd, 0.99, axis=0)
    return {
        c: float(f"{_EPS_FRACTION * t:.3g}") if t > 0 else DEFAULT_EPS
        for c, t in zip(coordinates, top)
    }


def same_kind(pair, angles, units=None) -> bool:
    """Whether the coordinates of ``pair`` are of one kind, so that a force on their
    relative velocity (``relative(a,b)``) is physical: both angles or both not, and,
    with ``units`` (``{coordinate: (position unit, force unit)}``), in one position
    unit (a cart in pixels and an angle in radians never are)."""
    if len(pair) < 2:
        return True
    if len({c in angles for c in pair}) > 1:
        return False
    if units:
        found = {
            units[c][0] if isinstance(units[c], (tuple, list)) else units[c]
            for c in pair
            if c in units
        }
        if len(found) > 1:
            return False
    return True


def _catalogue(est, kinds, extra_terms, angles, tau, eps, units=None):
    """Candidate effects not already in the model's candidate set.

    Kinds of two coordinates (``relative``) are proposed only for pairs of the same
    kind (:func:`same_kind`)."""
    coords = est.coordinates_
    present_forces = {t.name for t in est.dissipation_terms_}
    present_terms = set(est.library_.get_feature_names_out())
    out = []
    # the kinds' parameters other than eps: the refits' (scoring._fit_model)
    source = est.dissipation
    if not isinstance(source, DissipationLibrary):
        source = DissipationLibrary((), coordinates=coords)
    for kind in kinds:
        if kind in kind_names():
            record = get_kind(kind)
            for tgt in record.targets(coords):
                if not same_kind(tuple(tgt), angles, units):
                    continue  # a relative velocity of an angle and a length
                params = source.parameters_for(kind, tgt[0])
                params.pop("eps", None)
                term = make_term(
                    kind,
                    record.target(tgt),
                    coords,
                    eps=eps.get(tgt[0], DEFAULT_EPS),
                    **params,
                )
                if term.name not in present_forces:
                    out.append(Candidate(kind, term.name, tuple(tgt), term))
        elif kind in _DELAYS or kind == "payload":
            continue  # tried before the other effects (see diagnose)
        elif kind == "gain":
            if tau is None:
                continue
            driven = [i for i in range(len(coords)) if np.any(tau[:, i] != 0)]
            if len(driven) < 2:
                continue  # one input: a gain error is the Lagrangian's own scale
            for i in driven:
                out.append(Candidate("gain", f"gain({coords[i]})", (coords[i],), i))
        elif kind == "conservative":
            q, _, _ = symbols_for(coords)
            terms = []
            for c, s in zip(coords, q):
                terms.append(s**2)
                if c in angles:
                    terms += [sp.cos(s), sp.sin(s)]
            terms += [canonical(t, coords) for t in (extra_terms or [])]
            seen = set()
            for t in terms:
                if str(t) in present_terms or str(t) in seen:
                    continue
                seen.add(str(t))
                names = {str(s) for s in t.free_symbols}
                own = tuple(c for c in coords if c in names or f"{c}_dot" in names)
                out.append(Candidate("conservative", str(t), own or (coords[0],), t))
        else:
            raise ValueError(
                f"unknown candidate kind {kind!r}; use some of "
                f"{_DELAYS + ('payload',) + kind_names() + _AFTER_FORCES}"
            )
    return out


def _effect_coefficient(est, cand, gains):
    """Coefficient of the effect ``cand`` in the fitted ``est`` (0 when absent).

    A gain is read from ``gains`` (coordinate index -> factor - 1).
    """
    if cand.kind == "gain":
        return float(gains[cand.term])
    if cand.kind == "conservative":
        names = list(est.library_.get_feature_names_out())
        return (
            float(est.coef_[names.index(str(cand.term))])
            if str(cand.term) in names
            else 0.0
        )
    for t, d in zip(est.dissipation_terms_, est.dissipation_coef_):
        if t.name == cand.name:
            return float(d)
    return 0.0
