"""The candidate effects :func:`~lagsindy.diagnose` can try.

Viscous damping, relative (joint) damping, quadratic drag and Coulomb friction on
every coordinate, a constant offset force, an input gain error (when several
coordinates are driven), missing conservative terms and an input delay.
"""

from __future__ import annotations

import numpy as np
import sympy as sp

from .._expr import canonical, symbols_for
from ..dissipation import DEFAULT_EPS, make_term
from .report import Candidate

DEFAULT_CATALOGUE = (
    "delay",
    "viscous",
    "relative",
    "drag",
    "coulomb",
    "bias",
    "gain",
    "conservative",
)
_DISSIPATIVE = ("viscous", "relative", "drag", "coulomb", "bias")
# Kinds whose coefficient must be non-negative (they only remove energy).
_NONNEGATIVE = ("viscous", "relative", "drag", "coulomb")
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


def _pairs(coords):
    return [(a, b) for k, a in enumerate(coords) for b in coords[k + 1 :]]


def _catalogue(est, kinds, extra_terms, angles, tau, eps):
    """Candidate effects not already in the model's candidate set."""
    coords = est.coordinates_
    present_forces = {t.name for t in est.dissipation_terms_}
    present_terms = set(est.library_.get_feature_names_out())
    out = []
    for kind in kinds:
        if kind in _DISSIPATIVE:
            targets = _pairs(coords) if kind == "relative" else [(c,) for c in coords]
            for tgt in targets:
                term = make_term(
                    kind,
                    tgt if kind == "relative" else tgt[0],
                    coords,
                    eps=eps.get(tgt[0], DEFAULT_EPS),
                )
                if term.name not in present_forces:
                    out.append(Candidate(kind, term.name, tuple(tgt), term))
        elif kind == "delay":
            continue  # estimated before the other effects (see diagnose)
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
                f"unknown candidate kind {kind!r}; use some of {DEFAULT_CATALOGUE}"
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
