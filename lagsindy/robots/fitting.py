r"""A robot's base parameters as the columns of a :class:`~lagsindy.LagrangianSINDy` fit.

A :class:`~lagsindy.robots.RobotLibrary` has one term per link parameter, and its
regressor's columns are dependent (:mod:`lagsindy.robots.base_parameters`). The fit
regresses on the base parameters instead: :class:`BaseParameterLibrary` keeps the
independent columns, one term per base parameter, named after the first link
parameter it combines (``base_.labels`` says which others it regroups). Its Lagrangian
``sum_k beta_k phi_k`` (``phi_k`` the kept link terms) has the torques of any full
parameter vector ``pi`` with ``beta = base_.matrix @ pi``.

The estimator gets this library from :meth:`RobotLibrary.regression_library`, which
the pipeline calls on any library that has it (``library_`` of a fitted estimator is
then the base library; ``library_.robot_`` the link-level one).

Sparsity: base parameters depend on the kinematics, not on their values (real ones
span 1e-3 to 3 kg m^2 on an arm), so by default they are neither shrunk by the L1
penalty nor removed by the hard ``threshold`` (``unpenalized_`` lists them): the
sparse regression selects only among the dissipation candidates (friction kinds,
extra effects), whose ``dissipation_threshold`` applies as usual.
``RobotLibrary(penalize=True)`` makes the base parameters ordinary candidates
(shrunk, and thresholded at ``threshold`` relative to the largest scaled
coefficient).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
from sklearn.base import BaseEstimator

from .._stacklevel import outside_stacklevel
from .base_parameters import base_parameters
from .export import consistent_parameters
from .library import _BuiltOnDemand


class BaseTerms:
    """The term function of a subset of a :class:`RobotTerms`' terms.

    ``fn``/``fn_batch``/``columns`` evaluate the whole regressor and keep the
    ``indices`` (the recursion computes every column at once, so this costs no more
    than one column).
    """

    def __init__(self, terms, indices):
        self.terms = terms
        self.indices = [int(i) for i in indices]
        self.names = [terms.names[i] for i in self.indices]
        self._index = torch.as_tensor(self.indices, dtype=torch.long)

    @property
    def n_terms(self) -> int:
        return len(self.indices)

    def __len__(self) -> int:
        return len(self.indices)

    def subset(self, indices) -> BaseTerms:
        """The term function of some of these terms (positions in ``names``)."""
        return BaseTerms(self.terms, [self.indices[int(k)] for k in indices])

    def _pick(self, out):
        return out.index_select(-1, self._index.to(out.device))

    def fn_batch(self, q, qd):
        return self._pick(self.terms.fn_batch(q, qd))

    def fn(self, q, qd):
        return self.fn_batch(q, qd)

    __call__ = fn

    def columns(self, q, qd, qdd):
        """Euler-Lagrange columns (n_samples, n_dof, n_terms) by the recursion."""
        if not self.indices:
            return q.new_zeros((q.shape[0], q.shape[1], 0))
        return self._pick(self.terms.columns(q, qd, qdd))

    def mass_matrices(self, q, qd):
        """``M_k`` of every term, (n_samples, n_terms, n_dof, n_dof), by the recursion:
        column ``j`` of ``M_k`` is the torque of a unit acceleration of joint ``j``
        (velocity and gravity parts removed)."""
        n, d = q.shape
        zero = torch.zeros_like(qd)
        rest = self.columns(q, zero, zero)  # gravity only
        eye = torch.eye(d, dtype=q.dtype, device=q.device)
        qq = q.repeat_interleave(d, dim=0)
        acc = eye.repeat(n, 1)
        cols = self.columns(qq, torch.zeros_like(qq), acc).reshape(n, d, d, -1)
        cols = cols - rest[:, None]  # (n, j (accelerated), i (row), k)
        return cols.permute(0, 3, 2, 1)

    def bias(self, q, qd):
        """``h_k = N_k qd - O_k`` of every term, (n_samples, n_terms, n_dof)."""
        return self.columns(q, qd, torch.zeros_like(qd)).transpose(1, 2)

    def numpy_dynamics(self, coef):
        """``(M, h)`` of ``sum_k coef[k] phi_k`` as a NumPy function of the states
        (:meth:`RobotTerms.numpy_dynamics`: the rigid-body algorithms)."""
        return self.terms.numpy_dynamics(coef, self.indices)

    def __repr__(self) -> str:
        return f"BaseTerms({len(self.indices)} of {len(self.terms.names)} robot terms)"


# A consistent refit that leaves more than this many times the unconstrained
# residual sum of squares is reported (measured: 1.0 on well-excited two-link
# records, 1.09 on 2 s of the seven-joint arm, 5.8 on the poorly exciting 2 s
# two-link record of docs/robots.md, whose fit dropped the shoulder's friction).
RESIDUAL_RATIO = 2.0


class BaseParameterLibrary(_BuiltOnDemand, BaseEstimator):
    """The base parameters of a :class:`RobotLibrary` as a candidate library.

    Parameters
    ----------
    robot : RobotLibrary
        The link-level library (built or not).
    random_state : int, default=0
        Seeds the exciting states the base parameters are computed at.
    base : BaseParameters, default=None
        A grouping to use instead of computing one (a model file's, so that the
        library read back has the fitted columns); its ``names`` must be the robot
        library's terms.

    Attributes
    ----------
    robot_ : RobotLibrary
        The built link-level library.
    base_ : BaseParameters
        The reduction: ``labels`` (which link parameters each base parameter
        combines), ``matrix`` (``beta = matrix @ pi``), ``unidentifiable``.
    terms_ : list of str
        One name per base parameter: its first link parameter's name.
    coordinates_ : list of str
    unpenalized_ : list of str
        The terms the sparse regression leaves alone (all of them unless the robot
        library has ``penalize=True``).
    nominal_ : ndarray of shape (n_base,)
        The URDF's base parameter values (rotor inertias 0).
    """

    _BUILT = ("terms_", "coordinates_", "base_", "robot_", "unpenalized_", "n_terms_")

    def __init__(self, robot=None, random_state=0, base=None):
        self.robot = robot
        self.random_state = random_state
        self.base = base

    def build(self):
        """Build the robot library, reduce it to base parameters; returns ``self``."""
        if self.robot is None:
            raise ValueError("BaseParameterLibrary needs robot= (a RobotLibrary)")
        robot = self.robot._ensure_built()
        base = self.base
        if base is None:
            base = base_parameters(robot, random_state=self.random_state)
        elif list(base.names) != list(robot.terms_):
            raise ValueError(
                "base= was computed for another robot library (its parameter names "
                "differ from this library's terms); leave base=None to compute it"
            )
        self.robot_ = robot
        self.base_ = base
        self.coordinates_ = list(robot.coordinates_)
        self.terms_ = [robot.terms_[i] for i in base.independent]
        self._terms = BaseTerms(robot.torch_terms(), base.independent)
        penalize = bool(getattr(robot, "penalize", False))
        self.unpenalized_ = [] if penalize else list(self.terms_)
        self.nominal_ = base.values(robot.nominal_)
        self.n_terms_ = len(self.terms_)
        self._representatives = {}
        return self

    @property
    def coordinates(self):
        """The coordinate joints (the robot library's)."""
        return None if self.robot is None else self.robot.coordinates

    def _ensure_built(self):
        if "_terms" not in self.__dict__:
            self.build()
        return self

    def _other_term(self, term):
        """The base parameter a link parameter stands in alone."""
        names = self.terms_
        robot_names = self.robot_.terms_
        if term in robot_names:
            j = robot_names.index(term)
            rows = np.flatnonzero(self.base_.matrix[:, j])
            if len(rows) == 1:
                return int(rows[0])
            why = (
                "it moves no torque (unidentifiable)"
                if not len(rows)
                else f"it enters {len(rows)} base parameters"
            )
            raise ValueError(f"link parameter {term!r} is not a base parameter: {why}")
        raise ValueError(
            f"term {term!r} is not a base parameter of this robot; they are "
            f"{names[:4]}... (see library_.base_.labels)"
        )

    def constrain(self, problem, solution):
        """The pipeline's hook after the sparse solve (case I): the constrained refit
        of :func:`lagsindy.robots.consistency.constrained_refit` when the robot library
        has ``consistent=True``; otherwise a warning when the fitted base parameters
        are not physically consistent (with the violation)."""
        from .consistency import VIOLATION_TOL, violation

        n = self.n_terms_
        coef = np.asarray(solution.coef, float)
        n_features = len(coef)
        gram = problem.balanced.gram.detach().cpu().numpy()
        keep = list(range(n_features)) + [n_features]
        gram = gram[np.ix_(keep, keep)]
        if not getattr(self.robot_, "consistent", True):
            gap = violation(self.robot_, self.base_, coef[:n])
            self.violation_ = gap
            if gap > VIOLATION_TOL:
                warnings.warn(
                    "the fitted base parameters are not physically consistent: the "
                    f"nearest consistent link parameters miss them by {gap:.2g} "
                    "(relative); fit with consistent=True (the default) to constrain "
                    "them",
                    UserWarning,
                    stacklevel=outside_stacklevel(),
                )
            return solution
        dissipative = [t.dissipative for t in problem.dissipation_terms]
        found = self.consistent_refit(gram, coef, dissipative)
        if not found.converged:
            from .consistency import MAX_ITER

            warnings.warn(
                f"the physically consistent refit stopped at its {MAX_ITER}-iteration "
                "cap before converging: the link parameters are feasible but may "
                "not be the best consistent ones (the constrained optimum is on the "
                "edge of the feasible set); compare est.score with "
                "consistent=False",
                UserWarning,
                stacklevel=outside_stacklevel(),
            )
        if found.residual_ratio > RESIDUAL_RATIO:
            warnings.warn(
                f"the physically consistent link parameters leave "
                f"{found.residual_ratio:.1f} times the torque residual of "
                "unconstrained ones: the unconstrained fit absorbs into infeasible "
                "inertial parameters something the model lacks (a friction term "
                "dropped as small, a spring, a payload) or the record does not "
                "excite the arm enough. Run lagsindy.diagnose, record a more "
                "exciting trajectory, or compare with consistent=False",
                UserWarning,
                stacklevel=outside_stacklevel(),
            )
        solution.coef = found.coef
        return solution

    def consistent_refit(self, gram, coef, dissipative):
        """``coef`` refitted with physically consistent link parameters on the
        quadratic objective of ``gram``: the constrained refit of every consumer
        (the fit's :meth:`constrain`, the bootstrap's resamples through it,
        :func:`lagsindy.refine` on its Gauss-Newton model of the rollouts).

        Parameters
        ----------
        gram : ndarray of shape (P + 1, P + 1)
            Gram matrix of the features and the target (last), coefficient units:
            the objective is ``x^T G x / 2 - g^T x``.
        coef : ndarray of shape (P,)
            The unconstrained coefficients (base parameters, then dissipation); the
            dissipation terms they keep (non-zero) are the ones refitted.
        dissipative : sequence of bool, shape (P - ``n_terms_``,)
            Which dissipation coefficients must be non-negative.

        Returns
        -------
        ConsistentFit or None
            ``None`` when the robot library has ``consistent=False``.
        """
        from .consistency import constrained_refit

        if not getattr(self.robot_, "consistent", True):
            return None
        n = self.n_terms_
        coef = np.asarray(coef, float)
        found = constrained_refit(
            self.robot_, self.base_, gram, coef, n, dissipative, coef[n:] != 0
        )
        cache = self.__dict__.setdefault("_representatives", {})
        cache[found.coef[:n].tobytes()] = found.parameters
        if len(cache) > 64:
            cache.pop(next(iter(cache)))
        return found

    def link_parameters(self, beta):
        """Consistent full link parameters whose base parameters are ``beta``: the
        constrained fit's own, else :func:`lagsindy.robots.consistent_parameters`
        (a ``ConsistentParameters``'s ``parameters``)."""
        beta = np.asarray(beta, float)
        known = self.__dict__.get("_representatives", {}).get(beta.tobytes())
        if known is not None:
            return known
        return consistent_parameters(self.robot_, self.base_, beta).parameters

    def table(self, values=None) -> list:
        """``(name, combination, value)`` per base parameter."""
        self._ensure_built()
        vals = [None] * len(self.terms_) if values is None else list(values)
        return [
            (n, lab, None if v is None else float(v))
            for n, lab, v in zip(self.terms_, self.base_.labels, vals)
        ]

    def __getstate__(self):
        state = self.__dict__.copy()
        state.pop("_terms", None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        if "robot_" in state and "base_" in state:
            self._terms = BaseTerms(self.robot_.torch_terms(), self.base_.independent)
