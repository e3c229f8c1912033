"""The :class:`System` type: a mechanical model with what a benchmark needs besides."""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence

import numpy as np
import sympy as sp
from sklearn.utils import check_random_state

from .._expr import canonical, state_names
from ..dynamics import MechanicalModel

# Coulomb friction is smoothed as mu * tanh(qdot / eps); eps is in the velocity's units.
COULOMB_EPS = 0.01


class System(MechanicalModel):
    """A benchmark system: a :class:`MechanicalModel` plus its experimental protocol.

    Parameters
    ----------
    lagrangian, coordinates, dissipation, forces, input_matrix, name
        As for :class:`~lagsindy.MechanicalModel`.
    angles : sequence of str
        Coordinates that are angles (for unwrapping and plots).
    initial_ranges : dict
        ``{state name: (low, high)}`` for every entry of ``[q..., q_dot...]``;
        initial states are drawn uniformly from these ranges (equal bounds fix a value).
    library : callable, optional
        Returns the system's paper library (a :class:`~lagsindy.CandidateLibrary`).
    paper_input : callable, optional
        ``paper_input(t, omega) -> array (n_trajectories, n_inputs)``: the input form
        the paper's authors used, for frequencies ``omega`` of shape (n_trajectories,).
    fixed_term : str, optional
        The term fixed to 1 for passive fits (case III), as in the paper.
    prior_terms : sequence of str
        Other terms known from a constituent system (the paper's single pendulum);
        case III leaves them unpenalised.
    description : str, optional
    """

    def __init__(
        self,
        lagrangian,
        coordinates: Sequence[str],
        *,
        angles: Sequence[str] = (),
        initial_ranges: dict,
        library: Callable | None = None,
        paper_input: Callable | None = None,
        fixed_term: str | None = None,
        prior_terms: Sequence[str] = (),
        description: str = "",
        dissipation=None,
        forces=None,
        input_matrix=None,
        name: str | None = None,
    ):
        super().__init__(
            lagrangian,
            coordinates,
            dissipation=dissipation,
            forces=forces,
            input_matrix=input_matrix,
            name=name,
        )
        self.angles = list(angles)
        names = state_names(self.coordinates, accelerations=False)
        missing = [n for n in names if n not in initial_ranges]
        if missing:
            raise ValueError(f"initial_ranges lacks {missing}")
        self.initial_ranges = {n: tuple(map(float, initial_ranges[n])) for n in names}
        self._library = library
        self._paper_input = paper_input
        self.fixed_term = fixed_term
        self.prior_terms = list(prior_terms)
        self.description = description

    def paper_library(self):
        """The candidate library the paper used for this system."""
        if self._library is None:
            raise ValueError(f"{self.name} has no paper library")
        return self._library()

    def paper_input(self, t, omega):
        """The authors' input ``u(t)`` for frequencies ``omega`` (n_trajectories, n_inputs)."""
        if self._paper_input is None:
            raise ValueError(f"{self.name} has no paper input form")
        return np.asarray(
            self._paper_input(float(t), np.asarray(omega, dtype=float)), dtype=float
        )

    def sample_initial_states(self, n: int, random_state=None) -> np.ndarray:
        """Draw ``n`` initial states ``[q..., q_dot...]`` from ``initial_ranges``."""
        rng = check_random_state(random_state)
        names = state_names(self.coordinates, accelerations=False)
        out = np.empty((n, len(names)))
        for j, name in enumerate(names):
            low, high = self.initial_ranges[name]
            out[:, j] = low if low == high else rng.uniform(low, high, n)
        return out

    def true_coefficients(self, library) -> np.ndarray:
        """The Lagrangian expressed in ``library``'s terms (see ``CandidateLibrary.decompose``)."""
        coef, residual = library.decompose(self.lagrangian)
        if residual > 1e-8:
            raise ValueError(
                f"the library cannot represent the Lagrangian of {self.name} "
                f"(relative residual {residual:.2g})"
            )
        return coef

    def terms(self) -> dict:
        """``{term string: coefficient}`` of the Lagrangian's additive terms."""
        out = {}
        for term in sp.Add.make_args(sp.expand(self.lagrangian)):
            coef, rest = term.as_coeff_Mul()
            out[str(rest)] = out.get(str(rest), 0.0) + float(coef)
        return out

    def with_damping(
        self, viscous=None, coulomb=None, *, eps: float = COULOMB_EPS
    ) -> System:
        """A copy with known dissipation added, for experiments.

        Parameters
        ----------
        viscous : dict, optional
            ``{coordinate: b}``: Rayleigh term ``b * q_dot**2 / 2`` (force ``-b q_dot``).
        coulomb : dict, optional
            ``{coordinate: mu}``: force ``-mu * tanh(q_dot / eps)`` (smoothed sign).
        eps : float, default=0.01
            Smoothing velocity of the Coulomb force.

        Returns
        -------
        System
        """
        new = copy.copy(self)
        new.__dict__.pop("_equations", None)
        new.__dict__.pop("_compiled", None)
        extra_d = sp.Integer(0)
        forces = list(self.forces)
        for name, b in (viscous or {}).items():
            self._index(name)
            qd = sp.Symbol(name + "_dot", real=True)
            extra_d += sp.Float(b) * qd**2 / 2
        for name, mu in (coulomb or {}).items():
            i = self._index(name)
            qd = sp.Symbol(name + "_dot", real=True)
            forces[i] = forces[i] - sp.Float(mu) * sp.tanh(qd / sp.Float(eps))
        new.dissipation = canonical(self.dissipation + extra_d, self.coordinates)
        new.forces = forces
        parts = [
            f"viscous {viscous}" if viscous else "",
            f"Coulomb {coulomb}" if coulomb else "",
        ]
        new.name = (
            f"{self.name} ({', '.join(p for p in parts if p)})"
            if any(parts)
            else self.name
        )
        return new

    def _index(self, name):
        if name not in self.coordinates:
            raise ValueError(
                f"{name!r} is not a coordinate of {self.name}: {self.coordinates}"
            )
        return self.coordinates.index(name)
