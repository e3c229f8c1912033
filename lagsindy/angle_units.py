"""Angles that may be in degrees: the hint a failing fit adds.

A pendulum recorded in degrees looks, to a Lagrangian library in radians, like a
link spinning many turns. A fit that goes wrong on such data asks whether the angles
are in degrees, but only when the data read as degrees: the accelerations of the
angles follow sin/cos of them read as degrees better than read as radians (a link
that really spins turn after turn is no hint).
"""

from __future__ import annotations

import numpy as np
import sympy as sp
import torch

from ._torch import to_numpy
from .cases.fixed import SCORING_ROWS
from .evaluator import is_term_function, library_terms

# Rows used to judge the reading (as the fit's acceleration checks use).
ACCELERATION_ROWS = SCORING_ROWS


def _even_rows(Xt, limit: int):
    """Indices of at most ``limit`` evenly spaced rows of ``Xt`` (all when fewer)."""
    n = Xt.shape[0]
    return torch.linspace(0, n - 1, min(n, limit), device=Xt.device).long()


# Angles inside sin/cos beyond this many turns make a failing fit ask whether they
# are in degrees. Driven pendulums of the tests that flip over reach 1.3-1.5 turns
# in radians; a swing of +-13 degrees, given in degrees, already reaches 2.
DEGREES_TURNS = 2
# ... and only when the data read as degrees: the accelerations of such an angle follow
# sin/cos of it read as degrees (times pi/180) better than read as radians, by at
# least this R^2 (least squares on a constant and the sin and cos of each such
# angle). Measured: pendulums recorded in degrees (single, double, cart-pole,
# passive or driven) gained 0.52-1.0; a pendulum spinning 4 to 22 turns in radians
# lost 0.78-1.0 (a spinning link is no hint); a pendulum driven hard enough that its
# input dominates gained 0.12 in degrees (both readings then explain little: no
# hint).
DEGREES_R2_GAIN = 0.25


def trig_coordinates(library) -> set:
    """Names of the coordinates that appear inside a ``sin`` or ``cos`` term."""
    inside = set()
    if is_term_function(library_terms(library)):  # not sympy: no sin/cos to read
        return inside
    for term in library.terms_:
        for atom in term.atoms(sp.sin, sp.cos):
            inside |= {str(s_) for s_ in atom.free_symbols}
    return inside


def beyond_turns(library, Xt, names) -> dict:
    """``{name: peak}`` of the coordinates ``names`` whose values in ``Xt`` go
    beyond ``DEGREES_TURNS`` turns."""
    out = {}
    for j, name in enumerate(library.coordinates_):
        if name in names:
            peak = float(Xt[:, j].abs().max())
            if peak > DEGREES_TURNS * 2 * np.pi:
                out[name] = peak
    return out


def degree_reading_gain(library, Xt, names) -> dict:
    """``{name: gain}``: how much better (in R^2) the accelerations of each angle in
    ``names`` follow sin/cos of those angles read as degrees than read as radians.

    Least squares of each angle's acceleration on a constant and the sin and cos of
    every angle in ``names`` (all read as degrees, then all as radians) on at most
    ``ACCELERATION_ROWS`` evenly spaced rows. Angles in degrees of a link under
    gravity gain (the radian reading's sin/cos alias); a link that really spins
    loses. Without accelerations in ``Xt`` (zeros, or no columns) the gain is 0.
    """
    coords = list(library.coordinates_)
    n, cols = len(coords), [coords.index(name) for name in names]
    if not cols or Xt.shape[1] < 3 * n:
        return {name: 0.0 for name in names}
    X = to_numpy(Xt[_even_rows(Xt, ACCELERATION_ROWS)]).astype(float)
    fits = []
    for scale in (np.pi / 180.0, 1.0):
        angle = X[:, cols] * scale
        F = np.column_stack([np.ones(X.shape[0]), np.sin(angle), np.cos(angle)])
        y = X[:, [2 * n + j for j in cols]]
        c = np.linalg.lstsq(F, y, rcond=None)[0]
        fits.append(np.mean((y - F @ c) ** 2, axis=0))
    var = np.var(X[:, [2 * n + j for j in cols]], axis=0)
    ok = var > 0
    gain = np.where(ok, (fits[1] - fits[0]) / np.where(ok, var, 1.0), 0.0)
    return dict(zip(names, map(float, gain)))


def read_as_degrees(library, Xt, names) -> dict:
    """``{name: peak}`` of the coordinates ``names`` that go beyond
    ``DEGREES_TURNS`` turns and whose accelerations read as degrees
    (:func:`degree_reading_gain` at least ``DEGREES_R2_GAIN``)."""
    big = beyond_turns(library, Xt, names)
    if not big:
        return {}
    gain = degree_reading_gain(library, Xt, list(big))
    return {name: peak for name, peak in big.items() if gain[name] >= DEGREES_R2_GAIN}


def degrees_hint(library, Xt) -> str:
    """A sentence naming the coordinates inside ``sin``/``cos`` terms whose values
    in ``Xt`` go beyond ``DEGREES_TURNS`` turns and whose accelerations follow the
    angles read as degrees (:func:`read_as_degrees`); ``""`` if none (a link that
    really spins turn after turn is no hint)."""
    big = [
        f"{name} reaches {peak:.3g}"
        for name, peak in read_as_degrees(
            library, Xt, trig_coordinates(library)
        ).items()
    ]
    if not big:
        return ""
    return (
        f" The angles inside sin/cos go beyond {DEGREES_TURNS} turns "
        f"({', '.join(big)}) and their accelerations follow them read as degrees: "
        "if they are in degrees, convert them to radians (numpy.deg2rad), with their "
        "velocities and accelerations."
    )
