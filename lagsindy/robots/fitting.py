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
# Dissipation candidates the sparse solve dropped are refitted with the constraint
# when a consistent fit leaves more than RESIDUAL_RATIO times the unconstrained
# residual: each is kept if removing it raises the residual by READMIT_GAIN of it
# (a column of pure noise lowers it by about 1/n_rows: this is a strict test), and
# they are kept only together if the residual falls to READMIT_FACTOR of the
# consistent fit's without them.
READMIT_GAIN = 0.01
READMIT_FACTOR = 0.5
# Any fit: a dissipation candidate the sparse solve dropped is re-admitted when, in
# least squares with every candidate and no penalty, removing it raises the residual
# by READMIT_T2 times the noise variance (a t statistic of 5 for independent rows),
# by READMIT_SHARE of the residual and by READMIT_FLOOR of the torques' sum of
# squares. Measured on the two-link arm along multi-sines, 3 % torque noise, true
# offsets of 0.1 and -0.05 N m: dropped and re-admitted in 6 s (t^2 = 60 and 121,
# 1.0 % and 2.0 % of the residual) and 3 s (the elbow's: t^2 = 42, 1.4 %), not
# detectable in 2 s (t^2 = 1 and 7); without noise (docs/robots.md's 8 s record) the
# shoulder's explains 8.6e-7 of the torques' sum of squares. No candidate was
# re-admitted in five records without offsets (noise 0 or 1 %, Coulomb smoothing
# 0.005 to 0.02 against the library's data-driven one). On the 7-joint benchmark
# (torques filtered at 20 Hz from 1 kHz: residuals correlated over ~25 samples)
# springs on joints without one had t^2 = 30 to 199 but 0.02 to 0.14 % of the
# residual (a true offset there: 0.2 %): the share keeps them out.
READMIT_T2 = 25.0
READMIT_SHARE = 0.005
READMIT_FLOOR = 1e-8
# ADMM iterations of the refits that test one candidate's removal (only their
# residual is used: measured on the docs' 2 s two-link record, within 1e-7 of the
# torques' energy of 5,000 iterations' for the candidates dropped, 1.9e-4 against
# 1.7e-4 for the one kept, each far from the 1 % test).
PROBE_ITER = 500


def _residual(gram, x):
    """The torque residual sum of squares of coefficients ``x`` (a Gram matrix of
    features and target), relative to the target's."""
    g, h, yy = gram[:-1, :-1], gram[:-1, -1], max(float(gram[-1, -1]), 1e-300)
    return float((x @ g @ x - 2 * h @ x + yy) / yy)


def _significant(gram, coef, n_terms, n_rows, dissipative) -> list:
    """Dissipation candidates the sparse solve dropped that least squares without
    the L1 penalty finds significant: each, removed from the fit with every
    candidate, raises the residual by ``READMIT_T2`` times the noise variance (the
    residual over ``n_rows`` minus the number of features), by ``READMIT_SHARE`` of
    the residual and by ``READMIT_FLOOR`` of the torques' sum of squares, with a
    sign its kind allows. (The noise variance assumes independent rows; filtered
    records are correlated over many samples, so the relative gain is what decides
    there.)"""
    coef = np.asarray(coef, float)
    dropped = np.flatnonzero(coef[n_terms:] == 0)
    p = len(coef)
    if not len(dropped) or n_rows <= p:
        return []
    every = np.ones(p, bool)
    x = _least_squares(gram, every)
    rss = _residual(gram, x)
    noise = max(rss, 0.0) / (n_rows - p)  # an exact fit's rss rounds below 0
    out = []
    for k in dropped:
        if dissipative[k] and x[n_terms + k] <= 0:
            continue
        mask = every.copy()
        mask[n_terms + k] = False
        gain = _residual(gram, _least_squares(gram, mask)) - rss
        material = gain >= READMIT_SHARE * rss and gain >= READMIT_FLOOR
        if material and gain >= READMIT_T2 * noise:
            out.append(int(k))
    return out


def _least_squares(gram, mask):
    """Unconstrained least-squares coefficients of the features in ``mask`` (0 for
    the others)."""
    mask = np.asarray(mask, bool)
    out = np.zeros(mask.size)
    sub = gram[:-1, :-1][np.ix_(mask, mask)]
    out[mask] = np.linalg.lstsq(sub, gram[:-1, -1][mask], rcond=None)[0]
    return out


class _OnRobot(_BuiltOnDemand):
    """What the libraries a fit regresses on instead of a :class:`RobotLibrary`
    share: the robot's coordinates, and building on first use."""

    @property
    def coordinates(self):
        """The coordinate joints (the robot library's)."""
        return None if self.robot is None else self.robot.coordinates

    def _ensure_built(self):
        if "_terms" not in self.__dict__:
            self.build()
        return self


class BaseParameterLibrary(_OnRobot, BaseEstimator):
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
        n_rows = problem.balanced.n_samples * len(self.coordinates_)
        dissipative = [t.dissipative for t in problem.dissipation_terms]
        significant = _significant(gram, coef, n, n_rows, dissipative)
        if significant:
            mask = coef != 0
            mask[n + np.asarray(significant)] = True
            coef = _least_squares(gram, mask)
            solution.coef = coef.copy()
            if problem.solver.verbose:
                names = [problem.dissipation_terms[k].name for k in significant]
                print(
                    f"[lagsindy] re-admitted {names}: dropped by the sparse solve, "
                    "significant in least squares without the L1 penalty (t > "
                    f"{READMIT_T2 ** 0.5:g})"
                )
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
        found, readmitted = self._constrained(gram, coef, dissipative)
        if readmitted:
            names = [problem.dissipation_terms[k].name for k in readmitted]
            warnings.warn(
                f"the physically consistent refit re-admitted {names}: the "
                "sparse solve had dropped them while the unconstrained fit "
                "absorbed them into infeasible inertial parameters, and with "
                "consistent parameters they halve the torque residual at "
                "least. The record excites the arm poorly: check the result "
                "on a more exciting trajectory",
                UserWarning,
                stacklevel=outside_stacklevel(),
            )
        if found.stalled:
            from .consistency import MAX_ITER

            warnings.warn(
                f"the physically consistent refit stopped at its {MAX_ITER}-iteration "
                "cap before converging (its residual still fell by "
                f"{found.progress:.1e} over the last iterations): the link "
                "parameters are feasible but may "
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
        solution.coef = found.coef.copy()
        return solution

    def _constrained(self, gram, coef, dissipative):
        """The consistent refit of ``coef``, with dropped friction re-admitted
        (:meth:`_readmit`) when it leaves more than ``RESIDUAL_RATIO`` times the
        unconstrained residual: ``(ConsistentFit, re-admitted indices)``.

        Remembered for the last few statistics: a fit whose accelerations are
        predicted poorly solves again with every term judged per equation, which
        often returns the same solution on the same statistics (the docs' 2 s
        two-link record: every refit twice)."""
        key = (gram.tobytes(), coef.tobytes(), tuple(bool(d) for d in dissipative))
        memo = self.__dict__.setdefault("_refits", {})
        if key in memo:
            return memo[key]
        found = self.consistent_refit(gram, coef, dissipative)
        readmitted = []
        if found.residual_ratio > RESIDUAL_RATIO:
            found, readmitted = self._readmit(gram, coef, dissipative, found)
        memo[key] = (found, readmitted)
        if len(memo) > 8:
            memo.pop(next(iter(memo)))
        return found, readmitted

    def _readmit(self, gram, coef, dissipative, found):
        """The dissipation candidates the sparse solve dropped, selected again under
        the consistency constraint: ``(fit, re-admitted indices)``.

        Unconstrained base parameters can mimic a friction term with infeasible
        inertias (a negative link inertia plays a shoulder's viscous friction on a
        poorly exciting record), so the sparse solve drops the term and the
        consistent refit, which cannot mimic it, leaves a large residual. Every
        dropped candidate is refitted with the constraint; each whose removal raises
        the torque residual by less than ``READMIT_GAIN`` of it is dropped again;
        the rest are kept when the residual is at most ``READMIT_FACTOR`` of
        ``found``'s.
        """
        n = self.n_terms_
        coef = np.asarray(coef, float)
        kept = coef[n:] != 0
        if kept.all():
            return found, []

        def fit(support, max_iter=None):
            mask = np.concatenate([np.ones(n, bool), support])
            start = _least_squares(gram, mask)
            return self.consistent_refit(gram, start, dissipative, max_iter)

        every = fit(np.ones_like(kept))
        base_rss = _residual(gram, every.coef)
        chosen = np.ones_like(kept)
        for k in np.flatnonzero(~kept):
            if every.coef[n + k] == 0:
                chosen[k] = False
                continue
            without = chosen.copy()
            without[k] = False
            probe = fit(without, PROBE_ITER).coef
            if _residual(gram, probe) - base_rss < READMIT_GAIN * base_rss:
                chosen[k] = False
        readmitted = list(np.flatnonzero(chosen & ~kept))
        if not readmitted:
            return found, []
        again = fit(chosen) if not chosen.all() else every
        if _residual(gram, again.coef) > READMIT_FACTOR * _residual(gram, found.coef):
            return found, []
        return again, readmitted

    def consistent_refit(self, gram, coef, dissipative, max_iter=None):
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
            self.robot_,
            self.base_,
            gram,
            coef,
            n,
            dissipative,
            coef[n:] != 0,
            **({} if max_iter is None else {"max_iter": max_iter}),
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
        state.pop("_refits", None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        if "robot_" in state and "base_" in state:
            self._terms = BaseTerms(self.robot_.torch_terms(), self.base_.independent)
