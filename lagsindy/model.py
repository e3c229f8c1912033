"""The fitted state of a Lagrangian model, defined once.

:class:`FittedLagrangian` holds what a fit (or a model file) determines: the library,
the coefficients of its terms and of the dissipation terms, how the scale was fixed,
and what the formulation measured. From these it assembles the readable model
(:class:`~lagsindy.dynamics.MechanicalModel`) and evaluates it (forces, accelerations,
the learned mass matrix). :class:`~lagsindy.LagrangianSINDy` produces one in ``fit``
and exposes its fields as fitted attributes; :mod:`lagsindy.io` writes and reads it
without knowing the estimator.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import sympy as sp
import torch

from ._torch import to_numpy, to_tensor
from .angle_units import (  # noqa: F401  (re-exported: the fit's checks use them)
    DEGREES_R2_GAIN,
    DEGREES_TURNS,
    beyond_turns,
    trig_coordinates,
    degree_reading_gain,
    degrees_hint,
    read_as_degrees,
)
from .cases.fixed import SCORING_ROWS, r2_scores
from .dissipation import library_of
from .dynamics import MechanicalModel
from .evaluator import is_term_function, library_terms
from .formulation import feature_operator
from .formulation.forms import WeakForm
from .formulation.operator import forward_accelerations
from .formulation.weak import WINDOW_FIRST

# Fraction of samples with a singular or indefinite learned mass matrix above which
# the fit warns.
MASS_BAD_FRACTION = 0.01
# Relative residual (the unexplained share of the forces' sum of squares) above which
# a fit with forces warns. Right models on simulated data with sensor noise 0.03 on
# positions left 0.26 (cart-pendulum) and 0.33 (double pendulum); a flipped sign of
# one force 0.91, swapped force columns 0.73, a library without the double
# pendulum's coupling 0.87.
UNEXPLAINED_FORCES = 0.5
# In-sample R^2 of the accelerations below which a passive (case III) fit warns.
# Right models of simulated single, double and cart pendulums (sensor noise up to
# 0.03 and the paper's noise up to 0.1, 3 seeds each) scored 0.83-1.0, the real
# single, double and triple pendulum recordings 0.9994-0.9999; a single pendulum
# recorded in degrees -0.09 (and no other warning but the test windows'). Fits with
# forces score each coordinate (accelerations from the forces): right models 0.60
# (double pendulum, sensor noise 0.1) to 1.0, a double pendulum whose 100 times
# lighter link the threshold dropped 0.10 on the other joint.
POOR_ACCELERATIONS = 0.5
# Rows (evenly spaced) on which that R^2 is computed: as many as case III's search
# scores its candidate models on.
ACCELERATION_ROWS = SCORING_ROWS
# ... counting the terms whose part of the Euler-Lagrange residual (|c_k| times their
# column's norm) is at least this share of the largest term's (an unpenalized term
# kept at 1e-6 is not one).
ANGLE_POLYNOMIAL_SHARE = 0.01


@dataclass
class MassCheck:
    """Where the learned mass matrix :math:`M = \\partial^2 L / \\partial\\dot q^2`
    fails to be definite on the data (the model then predicts no accelerations).

    Attributes
    ----------
    fraction : float
        Fraction of the checked samples where M is singular or indefinite (a
        negative definite M counts as definite here: without forces the model's
        overall sign is a convention; see ``negative``).
    coordinates : list of str
        The coordinates along which M degenerates there (largest components of the
        eigenvectors of its wrong-signed or near-zero eigenvalues), most often first.
    n_samples : int
        Samples checked (at most 500, evenly spaced).
    negative : float
        Fraction of the checked samples where M is negative definite: a negative
        kinetic energy, which the fit reports where forces fix the scale's sign.
    """

    fraction: float
    coordinates: list
    n_samples: int
    negative: float = 0.0

    @property
    def ok(self) -> bool:
        """True when M is definite at all but at most 1 % of the samples."""
        return self.fraction <= MASS_BAD_FRACTION


def _even_rows(Xt, limit: int):
    """Indices of at most ``limit`` evenly spaced rows of ``Xt`` (all when fewer)."""
    n = Xt.shape[0]
    return torch.linspace(0, n - 1, min(n, limit), device=Xt.device).long()


def mass_matrix_check(mass, coordinates, rtol: float = 1e-10) -> MassCheck:
    """Check mass matrices of shape (n_samples, n_dof, n_dof); see :class:`MassCheck`.

    An eigenvalue counts as zero below ``rtol`` times the largest at that sample.
    """
    mass = torch.as_tensor(mass)
    sym = (mass + mass.transpose(1, 2)) / 2
    eig, vec = torch.linalg.eigh(sym)
    big = eig.abs().max(dim=1).values.clamp(min=1e-300)
    sign = torch.where(eig.sum(dim=1) < 0, -1.0, 1.0).to(eig)
    good = eig * sign[:, None] > rtol * big[:, None]
    bad_rows = ~good.all(dim=1)
    n = int(mass.shape[0])
    fraction = float(bad_rows.double().mean()) if n else 0.0
    below = (eig < -rtol * big[:, None]).all(dim=1)
    negative = float(below.double().mean()) if n else 0.0
    counts = np.zeros(len(coordinates))
    if bool(bad_rows.any()):
        # weight of each coordinate in the bad directions
        weight = (vec**2) * (~good)[:, None, :].to(vec)
        counts = to_numpy(weight[bad_rows].sum(dim=2).gt(0.25).sum(dim=0)).astype(float)
    order = np.argsort(-counts, kind="stable")
    names = [coordinates[i] for i in order if counts[i] > 0]
    return MassCheck(fraction, names, n, negative)


@dataclass(eq=False)
class FittedLagrangian:
    """A learned Lagrangian (and dissipation) over a built candidate library.

    Parameters
    ----------
    library : CandidateLibrary
        The built library (``library.terms_``, ``library.coordinates_``).
    coef : ndarray of shape (n_terms,)
        Coefficients of the library's terms (zero where pruned).
    case : {"forces", "fixed", "acceleration"}
    dissipation_terms : list of ForceTerm
    dissipation_coef : ndarray of shape (n_dissipation_terms,)
    dissipation_removed : list of (name, reason)
        Dissipation candidates dropped because a Lagrangian column covers them.
    dissipation_library : DissipationLibrary or None
        The built dissipation library the terms came from.
    fixed_term : str or None
        The term whose coefficient is 1 in the reported scale (case III).
    normalization : {"term", "mass"} or None
    formulation : {"strong", "weak"} or None
        ``None`` for a model read from a file (the file does not say).
    dt, noise_cov, window : float, ndarray, int or None
        What the weak formulation used.
    stages : list of Stage
    n_iter : int
    residual : float or None
    tau_1d : bool
        The forces were given as a 1-D array (predictions are then 1-D).
    mass_check : MassCheck or None
    joint_dissipation : dict or None
        Set when the fit found friction or damping dominating what a conservative
        fit left and fitted it jointly with the Lagrangian
        (:func:`lagsindy.pipeline.fit_model`): ``kinds``, the probes' ``share`` and
        ``named`` forces, the conservative fit's ``residual``.
    unmodelled : dict or None
        Set when the fit warned that friction or damping it lacks explains much of
        its residual (:class:`~lagsindy.formulation.probes.UnmodelledForceWarning`):
        ``share`` and the ``named`` forces; :func:`lagsindy.diagnose` reports on it.
    equation_threshold : float or None
        Set when the fit solved again with every term judged within each
        coordinate's equation (:func:`lagsindy.pipeline.judge_each_equation`): the
        ``equation_threshold`` that solve used, which refits of the configuration
        (bootstrap, diagnosis, delay search) use too. ``None``: the solver settings'
        own rule.
    clock : dict or None
        Set when the fit was given time stamps (``fit(X, tau, t=...)``): the
        ``rows`` given, the ``edge_rows`` left out (near a segment's end), the
        ``fit_rows`` fitted, the even clock's ``dt`` (None: rows fitted as given)
        and a one-line ``report``
        (:func:`~lagsindy.formulation.clocked.rows_on_even_clock`). Refits of the
        same rows (:func:`lagsindy.bootstrap`, :func:`lagsindy.diagnose`) need the
        same ``t=``.
    """

    library: object
    coef: np.ndarray
    case: str
    dissipation_terms: list = field(default_factory=list)
    dissipation_coef: np.ndarray = field(default_factory=lambda: np.zeros(0))
    dissipation_removed: list = field(default_factory=list)
    dissipation_library: object = None
    fixed_term: str | None = None
    normalization: str | None = None
    formulation: str | None = None
    dt: float | None = None
    noise_cov: np.ndarray | None = None
    window: int | None = None
    stages: list = field(default_factory=list)
    n_iter: int = 0
    residual: float | None = None
    tau_1d: bool = False
    mass_check: MassCheck | None = None
    joint_dissipation: dict | None = None
    unmodelled: dict | None = None
    equation_threshold: float | None = None
    clock: dict | None = None

    def __post_init__(self):
        from .dissipation import assemble

        self.coef = np.asarray(self.coef, dtype=float)
        self.dissipation_coef = np.asarray(self.dissipation_coef, dtype=float)
        self.coordinates = list(self.library.coordinates_)
        terms = library_terms(self.library)
        provider = is_term_function(terms)
        # a torch term function's terms print as symbols named after them
        shown = [sp.Symbol(n) for n in terms.names] if provider else terms
        self.lagrangian = sp.Add(
            *[sp.Float(c) * t for c, t in zip(self.coef, shown) if c != 0]
        )
        rayleigh, forces = assemble(
            self.dissipation_terms, self.dissipation_coef, self.coordinates
        )
        self.dissipation = {"D": rayleigh, "forces": forces}
        if provider:
            self.model = MechanicalModel.from_terms(
                self.coordinates,
                terms,
                self.coef,
                dissipation=rayleigh,
                forces=forces,
                name="learned model",
            )
        else:
            self.model = MechanicalModel(
                self.lagrangian,
                self.coordinates,
                dissipation=rayleigh,
                forces=forces,
                name="learned model",
            )
        self._cache = None

    # ------------------------------------------------------------------ names
    @property
    def n_dof(self) -> int:
        return len(self.coordinates)

    @property
    def terms(self) -> list:
        return library_terms(self.library)

    @property
    def feature_names(self) -> np.ndarray:
        """Lagrangian term names, then dissipation term names."""
        names = list(self.library.get_feature_names_out())
        return np.asarray(
            names + [t.name for t in self.dissipation_terms], dtype=object
        )

    def candidates(self):
        """The dissipation library of the candidates (rebuilt from their terms when
        the state does not hold it, as after loading a file); ``None`` without any."""
        if self.dissipation_library is not None or not self.dissipation_terms:
            return self.dissipation_library
        return library_of(self.dissipation_terms, self.coordinates)

    def all_coef(self) -> np.ndarray:
        """Coefficients of the Lagrangian terms followed by the dissipation terms."""
        return np.concatenate([self.coef, self.dissipation_coef])

    def feature_index(self, name) -> int:
        """Index of a Lagrangian term or a dissipation term name among all features."""
        return feature_index(
            self.library, self.dissipation_terms, self.dissipation_removed, name
        )

    def attributes(self) -> dict:
        """The fitted attributes of :class:`~lagsindy.LagrangianSINDy` (``coef_``...)."""
        out = {
            "library_": self.library,
            "coordinates_": list(self.coordinates),
            "n_dof_": self.n_dof,
            "term_names_": self.library.get_feature_names_out(),
            "feature_names_": self.feature_names,
            "coef_": self.coef,
            "support_": self.coef != 0,
            "dissipation_terms_": self.dissipation_terms,
            "dissipation_coef_": self.dissipation_coef,
            "dissipation_removed_": self.dissipation_removed,
            "case_": self.case,
            "fixed_term_": self.fixed_term,
            "normalization_": self.normalization,
            "dt_": self.dt,
            "noise_cov_": self.noise_cov,
            "stages_": self.stages,
            "n_iter_": self.n_iter,
            "residual_": self.residual,
            "lagrangian_": self.lagrangian,
            "dissipation_": self.dissipation,
            "model_": self.model,
        }
        optional = {
            "dissipation_library_": self.dissipation_library,
            "formulation_": self.formulation,
            "window_": self.window,
            "mass_check_": self.mass_check,
            "joint_dissipation_": self.joint_dissipation,
            "equation_threshold_": self.equation_threshold,
            "clock_": self.clock,
        }
        out.update({k: v for k, v in optional.items() if v is not None})
        return out

    # ------------------------------------------------------------------ evaluation
    def feature_operator(self, indices, device, dtype):
        """Euler-Lagrange operator of the features at ``indices``."""
        return feature_operator(
            self.coordinates, self.terms, self.dissipation_terms, indices, device, dtype
        )

    def support_operator(self, device, dtype):
        """Compiled operator of the support and its coefficients (cached, not pickled)."""
        key = (str(device), str(dtype))
        if self._cache is None or self._cache[0] != key:
            all_coef = self.all_coef()
            support = np.flatnonzero(all_coef)
            op = self.feature_operator(support, device, dtype)
            coef = torch.as_tensor(all_coef[support], dtype=dtype, device=device)
            self._cache = (key, op, coef)
        return self._cache[1], self._cache[2]

    def support_columns(self, Xt):
        """The Euler-Lagrange columns of the model's terms at the rows of ``Xt``.

        Returns
        -------
        columns : ndarray of shape (n_samples, n_dof, n_support)
            The generalized force of each kept term (Lagrangian, then dissipation)
            for a unit coefficient: ``columns @ coef`` is :meth:`forces`.
        coef : ndarray of shape (n_support,)
        """
        op, coef = self.support_operator(Xt.device, Xt.dtype)
        if coef.numel() == 0:
            return np.zeros((Xt.shape[0], self.n_dof, 0)), np.zeros(0)
        return to_numpy(op.columns(Xt)), to_numpy(coef)

    def forces(self, Xt) -> np.ndarray:
        """Generalized forces (inverse dynamics) at the rows of ``Xt``."""
        op, coef = self.support_operator(Xt.device, Xt.dtype)
        if coef.numel() == 0:
            return np.zeros((Xt.shape[0], self.n_dof))
        return to_numpy(op.columns(Xt) @ coef)

    def weak_r2(self, Xt, tau, groups=None) -> float:
        """R^2 of the forces integrated against the weak form's test functions.

        What a weak-form fit minimises: per window and coordinate, ``int psi tau dt``
        against the model's ``int psi (d/dt dL/dqd - dL/dq - Q) dt`` (by parts: no
        accelerations, so the pointwise noise of estimated accelerations does not
        count against a right model). The total is relative to the best constant
        force (centred), summed over coordinates; no noise correction.

        Parameters
        ----------
        Xt : Tensor of shape (n_samples, >= 2 * n_dof)
        tau : array-like of shape (n_samples, n_dof)
        groups : array-like of shape (n_samples,), optional
            Trajectory labels (time-ordered rows, as for the fit).

        Returns
        -------
        float
        """
        op, coef = self.support_operator(Xt.device, Xt.dtype)
        tau_t = to_tensor(
            np.asarray(tau).reshape(Xt.shape[0], -1), dtype=Xt.dtype, device=Xt.device
        )
        ones = Xt.new_ones((Xt.shape[0], self.n_dof, 1))
        window = self.window if self.window is not None else WINDOW_FIRST
        form = WeakForm(window=window, dt=self.dt, noise_cov=None)
        (build,) = form.statistics(op, Xt, tau_t, groups, extra=ones)
        gram = build().gram  # columns: support, constant, tau
        v = torch.cat([coef, coef.new_zeros(1), coef.new_full((1,), -1.0)])
        res = torch.einsum("p,ipq,q->i", v, gram, v)
        const = gram[:, -2, -2].clamp_min(torch.finfo(gram.dtype).tiny)
        tot = gram[:, -1, -1] - gram[:, -2, -1] ** 2 / const
        return float(1.0 - res.sum() / tot.sum())

    def accelerations(self, Xt, tau=None) -> np.ndarray:
        """Forward dynamics ``M(c)^+ (tau - h(c))`` at the rows of ``Xt``."""
        op, coef = self.support_operator(Xt.device, Xt.dtype)
        if coef.numel() == 0:
            return np.zeros((Xt.shape[0], self.n_dof))
        tau_t = (
            None if tau is None else to_tensor(tau, dtype=Xt.dtype, device=Xt.device)
        )
        return to_numpy(forward_accelerations(op, coef, Xt, tau_t))

    def check_mass(self, Xt) -> MassCheck:
        """The learned mass matrix checked on (up to 500 evenly spaced) rows of ``Xt``."""
        op, coef = self.support_operator(Xt.device, Xt.dtype)
        d = self.n_dof
        if op.n_terms == 0:
            return MassCheck(1.0, list(self.coordinates), 0)
        rows = _even_rows(Xt, 500)
        q, qd = Xt[rows, :d], Xt[rows, d : 2 * d]
        mass = torch.einsum("skij,k->sij", op.mass_matrices(q, qd), coef[: op.n_terms])
        return mass_matrix_check(mass, self.coordinates)

    def checked_mass(self, Xt, stacklevel: int = 2) -> MassCheck:
        """:meth:`check_mass`, with a warning when the mass matrix is singular or
        indefinite at more than ``MASS_BAD_FRACTION`` of the rows (after a fit or a
        refinement: the model cannot predict those accelerations); with forces, also
        when it is negative definite there."""
        if not self.coef.any():
            return MassCheck(1.0, list(self.coordinates), 0)
        check = self.check_mass(Xt)
        if check.fraction > MASS_BAD_FRACTION:
            velocities = {str(v) for v in self.lagrangian.free_symbols}
            absent = [c for c in self.coordinates if f"{c}_dot" not in velocities]
            if is_term_function(self.terms):  # its symbols are the terms' names
                absent = []
            hint = (
                f"; no learned term contains the velocity of {absent}" if absent else ""
            )
            advice = (
                " In case III try another fixed term, or fixed_term=None to search "
                "them all."
                if self.case == "fixed"
                else ""
            )
            warnings.warn(
                "the learned mass matrix d2L/dqdot2 is singular or indefinite at "
                f"{check.fraction:.0%} of the samples, along coordinate(s) "
                f"{check.coordinates}{hint}, so the model cannot predict those "
                "accelerations there (rollouts fail)."
                + advice
                + " With forces, check that the data excite every coordinate. "
                "Test est.mass_check_.ok." + degrees_hint(self.library, Xt),
                UserWarning,
                stacklevel=stacklevel + 1,
            )
        if self.case == "forces" and check.negative > MASS_BAD_FRACTION:
            warnings.warn(
                "the learned mass matrix d2L/dqdot2 is negative definite at "
                f"{check.negative:.0%} of the samples: the learned kinetic energy is "
                "negative, which no mechanical system has. With forces, this "
                "usually means that tau's sign convention is the opposite of the "
                "model's (tau is the generalized force that does positive work on "
                "q: d/dt dL/dqdot - dL/dq = tau), or that tau's columns are not in "
                f"the order of the coordinates {self.coordinates}. Check tau. Test "
                "est.mass_check_.negative.",
                UserWarning,
                stacklevel=stacklevel + 1,
            )
        return check

    def warn_unexplained(self, stacklevel: int = 2, Xt=None):
        """Warn when a fit with forces leaves most of them unexplained (with the
        data ``Xt``, the message says whether its angles look like degrees)."""
        if self.case != "forces" or self.residual is None:
            return
        if self.residual > UNEXPLAINED_FORCES:
            warnings.warn(
                f"the learned model leaves {self.residual:.0%} of the measured "
                "forces' sum of squares unexplained (relative residual of the "
                f"{self.formulation or 'fitted'} form): it is not a model of these "
                "data. Check that tau's columns follow the coordinates' order "
                f"{self.coordinates} with the sign of positive work on q, that the "
                "library holds the terms the system needs, and run "
                "lagsindy.diagnose for friction or damping; very noisy accelerations "
                "also do this."
                + ("" if Xt is None else degrees_hint(self.library, Xt)),
                UserWarning,
                stacklevel=stacklevel + 1,
            )

    def acceleration_r2(self, Xt) -> float | None:
        """Variance-weighted R^2 of the passive model's accelerations on (up to
        ``ACCELERATION_ROWS`` evenly spaced) rows of ``Xt``, against its measured
        ``qddot``; ``None`` where those do not vary, ``-inf`` where the
        predictions are not finite."""
        d = self.n_dof
        rows = _even_rows(Xt, ACCELERATION_ROWS)
        true = to_numpy(Xt[rows, 2 * d : 3 * d])
        if not np.any(true != true[0]):
            return None
        pred = self.accelerations(Xt[rows])
        if not np.all(np.isfinite(pred)):
            return -np.inf
        return float(r2_scores(true, pred[None])[0])

    def coordinate_acceleration_r2(self, Xt, tau) -> dict:
        """``{coordinate: R^2}`` of the forced model's accelerations ``M(c)^+ (tau -
        h(c))`` on (up to ``ACCELERATION_ROWS`` evenly spaced) rows of ``Xt``,
        against its measured ``qddot``, one coordinate at a time; coordinates whose
        ``qddot`` does not vary are left out, ``-inf`` where the predictions are
        not finite."""
        d = self.n_dof
        rows = _even_rows(Xt, ACCELERATION_ROWS)
        true = to_numpy(Xt[rows, 2 * d : 3 * d])
        varies = np.any(true != true[0], axis=0)
        if not varies.any():
            return {}
        tau = np.asarray(tau, dtype=float).reshape(-1, d)[rows.cpu().numpy()]
        pred = self.accelerations(Xt[rows], tau)
        if not np.all(np.isfinite(pred)):
            return {self.coordinates[i]: -np.inf for i in np.flatnonzero(varies)}
        return {
            self.coordinates[i]: float(r2_scores(true[:, [i]], pred[None, :, [i]])[0])
            for i in np.flatnonzero(varies)
        }

    def warn_poor_accelerations(self, Xt, r2=None, stacklevel: int = 2, tau=None):
        """Warn when a fit predicts its own data's accelerations poorly.

        Passive fits (cases III and II): the variance-weighted R^2 (``r2`` when
        already known, as case III's search scores its models, else
        :meth:`acceleration_r2`, with the R^2 case III's search uses). Case I
        (with ``tau``): each coordinate's R^2 (:meth:`coordinate_acceleration_r2`),
        since a light link's large accelerations can hide another coordinate's
        failure in a weighted one. Not where the mass check already warned (the
        model then predicts no accelerations at all). Returns the R^2 (case I: the
        dict; ``None`` when not computed).
        """
        if not self.coef.any():
            return None
        if self.mass_check is not None and not self.mass_check.ok:
            return None
        if self.case == "forces" and tau is not None:
            return self._warn_poor_forced(Xt, tau, stacklevel + 1)
        if self.case not in ("fixed", "acceleration"):
            return None
        if r2 is None:
            r2 = self.acceleration_r2(Xt)
        if r2 is not None and r2 < POOR_ACCELERATIONS:
            warnings.warn(
                f"the learned model predicts the measured accelerations with R^2 = "
                f"{r2:.2f} on its own data (a right model of a noisy recording "
                f"scores above {POOR_ACCELERATIONS}): it is likely not a model of "
                "these data. Check that the library holds the terms the system "
                "needs, run lagsindy.diagnose for friction or damping, and check "
                "the accelerations in X (very noisy ones also do this)."
                + degrees_hint(self.library, Xt),
                UserWarning,
                stacklevel=stacklevel + 1,
            )
        return r2

    def _warn_poor_forced(self, Xt, tau, stacklevel):
        """:meth:`warn_poor_accelerations` of case I."""
        scores = self.coordinate_acceleration_r2(Xt, tau)
        poor = {name: r2 for name, r2 in scores.items() if r2 < POOR_ACCELERATIONS}
        if poor:
            which = ", ".join(
                f"{name} with R^2 = {r2:.2f}" for name, r2 in poor.items()
            )
            warnings.warn(
                f"the learned model predicts the measured accelerations of {which} "
                f"on its own data, from the measured forces (a right model of noisy "
                f"data scores above {POOR_ACCELERATIONS} on each coordinate): it is "
                "likely not a model of these data. A term that the data need may "
                "have been dropped as small next to the largest (a link much lighter "
                "than the others, a weak coupling): refit with a lower threshold, "
                "e.g. threshold=1e-3. Also check that the library holds the terms "
                "the system needs, run lagsindy.diagnose for friction or damping, "
                "and check the accelerations in X (very noisy ones also do this)."
                + degrees_hint(self.library, Xt),
                UserWarning,
                stacklevel=stacklevel + 1,
            )
        return scores

    def warn_angle_polynomials(self, Xt, norms=None, stacklevel: int = 2):
        """Warn when the learned Lagrangian uses an angle (a coordinate inside
        ``sin``/``cos`` in the library) outside ``sin``/``cos`` while its values
        go beyond ``DEGREES_TURNS`` turns, as angles in degrees make a pendulum
        look like a harmonic oscillator. With ``norms`` (the terms'
        Euler-Lagrange column norms), only terms whose part ``|c_k| norms_k`` is at
        least ``ANGLE_POLYNOMIAL_SHARE`` of the largest count. Returns the names
        flagged."""
        # The data first: the library's trig atoms (sympy) only when needed.
        big = beyond_turns(self.library, Xt, set(self.library.coordinates_))
        if big:
            trig = trig_coordinates(self.library)
            big = {name: peak for name, peak in big.items() if name in trig}
        if not big:
            return []
        size = np.abs(self.coef) * (1.0 if norms is None else np.asarray(norms))
        counted = (size > 0) & (size >= ANGLE_POLYNOMIAL_SHARE * size.max())
        outside = set()
        for term, c in zip(self.library.terms_, counted):
            if c:
                bare = term.xreplace(
                    {a: sp.Dummy() for a in term.atoms(sp.sin, sp.cos)}
                )
                outside |= {str(s_) for s_ in bare.free_symbols}
        flagged = [name for name in big if name in outside]
        if flagged:
            shown = ", ".join(f"{n} (reaches {big[n]:.3g})" for n in flagged)
            degrees = read_as_degrees(self.library, Xt, flagged)
            hint = (
                " Angles in degrees give this (a pendulum then looks like a harmonic "
                f"oscillator about its mean angle), and the accelerations of "
                f"{', '.join(degrees)} follow it read as degrees: if they are in "
                "degrees, convert them to radians (numpy.deg2rad), with their "
                "velocities and accelerations, and fit again. Otherwise the term"
                if degrees
                else " The term"
            )
            warnings.warn(
                f"the learned Lagrangian uses {shown} outside sin/cos, as a "
                f"polynomial, while it goes beyond {DEGREES_TURNS} turns: such a "
                f"potential is not periodic in the angle.{hint} likely stands in "
                "for an effect the model misses (friction, a spring): run "
                "lagsindy.diagnose.",
                UserWarning,
                stacklevel=stacklevel + 1,
            )
        return flagged

    def coef_table(self):
        """The coefficients as a DataFrame (see ``LagrangianSINDy.coef_table``)."""
        import pandas as pd

        extra = [t.name for t in self.dissipation_terms]
        names = [str(t) for t in self.library.get_feature_names_out()]
        coef = self.all_coef()
        return pd.DataFrame(
            {
                "term": names + extra,
                "kind": ["lagrangian"] * len(names) + ["dissipation"] * len(extra),
                "coefficient": np.asarray(coef, dtype=float),
                "kept": coef != 0,
            }
        )

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_cache"] = None  # compiled torch functions are not picklable
        return state


def feature_index(library, dissipation_terms, removed, name) -> int:
    """Index of a Lagrangian term or a dissipation term name among all features."""
    if isinstance(name, str):
        key = name.replace(" ", "")
        for j, t in enumerate(dissipation_terms):
            if t.name == key:
                return len(library.terms_) + j
        for t_name, reason in removed:
            if t_name == key:
                raise ValueError(f"dissipation term {name!r} was removed: {reason}")
    return library.index(name)
