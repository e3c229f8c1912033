""":func:`~lagsindy.diagnose`: its parameters, then the steps of
:class:`~.loop.Search` and the report of :func:`~.summary.summarize`.

See :mod:`lagsindy.diagnostics` for the loop and the criterion.
"""

from __future__ import annotations

import warnings

import numpy as np
from sklearn.utils.validation import check_is_fitted

from .._validation import validate_state, validate_tau
from ..formulation.operator import reuse_weak_columns
from ..partitioned import collect, is_partitioned
from ..pipeline import on_fit_clock
from .catalogue import DEFAULT_CATALOGUE, velocity_eps
from .loop import DiagnosisSettings, Search
from .payload import STAND_INS, add_payload, propose_payload
from .report import DiagnosisReport
from .summary import summarize


def diagnose(
    est,
    X,
    tau=None,
    groups=None,
    *,
    catalogue=DEFAULT_CATALOGUE,
    extra_terms=None,
    angles=None,
    units=None,
    n_splits: int = 3,
    min_explained: float = 0.05,
    max_effects: int = 4,
    min_improvement: float = 0.01,
    eps="auto",
    revise: bool = True,
    window=None,
    bootstrap=None,
    random_state=None,
    verbose: int = 0,
    t=None,
) -> DiagnosisReport:
    """Find the missing effects a fitted model leaves in its residual, add and refit.

    See the module documentation for the loop and the criterion.

    Parameters
    ----------
    est : LagrangianSINDy
        A fitted estimator (not modified).
    X : array-like or DataFrame of shape (n_samples, 3 * n_dof), or partitioned data
        Data in the estimator's layout: time-ordered trajectories (the held-out
        trajectory criterion integrates along them). Partitioned data (a Dask
        DataFrame, a Parquet path, chunks: see :mod:`lagsindy.partitioned`) are
        read into memory (``tau`` and ``groups`` then name their columns): diagnose
        a subset of the trajectories when all of them do not fit.
    tau : array-like of shape (n_samples, n_dof), default=None
        Generalized forces; ``None`` for passive data (the model's scale is then set by
        its fixed term).
    groups : array-like of shape (n_samples,), default=None
        Trajectory labels; folds hold out whole trajectories. Without them,
        trajectories are split where the positions jump. With fewer trajectories
        than ``n_splits``, each is cut into ``n_splits`` time blocks.
    catalogue : sequence of str, default=all kinds
        Candidate kinds: ``"viscous"``, ``"relative"``, ``"drag"``, ``"coulomb"``,
        ``"bias"``, ``"gain"``, ``"conservative"``, ``"delay"``, ``"joint_delay"``
        (and registered force kinds such as ``"spring"``). ``"delay"`` (forced
        data only) estimates a delay between the recorded input and the positions
        first (:func:`lagsindy.delay.estimate_delay`, up to 10 sampling intervals);
        it is kept, as the step ``"delay"`` with its estimate in ms, when the model
        refitted on the shifted input (:func:`lagsindy.delay.shift_input`) predicts
        held-out trajectories better; the other effects are then searched with the
        shifted input, and ``report.final`` is fitted on it (predict with
        ``report.shift_input(tau, t)``, which applies it as
        :func:`lagsindy.delay.shift_input` does). ``"joint_delay"`` (not in the
        default catalogue; in :data:`lagsindy.robots.ROBOT_CATALOGUE`) estimates
        one delay per driven input column instead (a robot's joints, whose drives
        lag differently; up to 20 sampling intervals): each is kept when it is at
        least a tenth of a sampling interval and twice its standard error, the
        delays together under the single delay's rule, and each only while setting
        it back to 0 worsens the held-out criterion by ``min_improvement``; the
        report has a step ``"delay(<joint>)"`` per delay kept (in ms) and
        ``report.input_delays`` (seconds per coordinate). With both named, the
        per-joint search runs instead of the single one. ``"payload"`` (in
        :data:`lagsindy.robots.ROBOT_CATALOGUE`; robots fitted with
        ``inertia="urdf"``) tries the end body's inertial parameters first
        (:mod:`lagsindy.diagnostics.payload`): the step ``"payload(<link>)"`` and
        ``report.payload``.
    extra_terms : list of str or sympy.Expr, default=None
        More conservative candidates (Lagrangian terms), beside ``q**2`` for every
        coordinate and ``cos``/``sin`` of angles.
    angles : list of str, default=None
        Angular coordinates (for candidates); default: the library's ``angles``.
    units : dict, default=None
        ``{coordinate: (position unit, force unit)}``, e.g. ``{"x": ("m", "N")}``,
        to print coefficient units; without it units are given in words ("per unit
        of x_dot").
    n_splits : int, default=3
        Held-out folds.
    min_explained : float, default=0.05
        Smallest share of the held-out criterion (squared) a candidate must explain
        to be tried (it must also improve every fold).
    max_effects : int, default=4
    min_improvement : float, default=0.01
        A revision or an effect is kept only if the refitted model's held-out
        criterion falls by at least this fraction.
    eps : "auto", float or dict, default="auto"
        Coulomb smoothing velocity of the candidates: ``"auto"`` takes 1 % of each
        coordinate's top speed (99th percentile of ``|q_dot|``).
    revise : bool, default=True
        First run the Lagrangian's sparse search jointly with the dissipative
        catalogue (step 1), so damping absorbed into wrong Lagrangian terms can be
        undone. A starting model whose mass matrix is singular or indefinite on the
        data (a link's terms pruned) is always revised so.
    window : int, default=None
        Samples per test function of the trajectory criterion; ``None``: the
        estimator's ``window`` (at most half the shortest time block).
    bootstrap : int, default=None
        When an integer, the final model's configuration is bootstrapped with that
        many resamples (:func:`lagsindy.bootstrap`, whole trajectories as groups, or
        time blocks with fewer than 10): ``report.bootstrap`` holds the intervals and
        inclusion of every term, and each step's ``low`` and ``high`` the interval of
        its effect (shown in the report's table). Costs about one fit per 10
        resamples on the fast path, one fit per resample otherwise.
    random_state : int, RandomState instance or None, default=None
        Seeds the bootstrap's resamples (the diagnosis itself is deterministic).
    verbose : int, default=0
    t : array-like of shape (n_samples,) or CleanedClock, default=None
        The time stamps ``est`` was fitted with (``est.fit(X, tau, t=t)``): the
        diagnosis then runs on the rows that fit used (edge rows left out, the weak
        form's rows on an even clock). Required when ``est`` was fitted with ``t=``.

    Returns
    -------
    DiagnosisReport
        Printable (``print(report)``), with ``report.final`` the refitted model,
        ``report.steps`` the effects found and ``report.plot()`` a figure.

    Examples
    --------
    >>> from lagsindy import LagrangianSINDy, diagnose
    >>> from lagsindy.systems import single_pendulum, make_dataset
    >>> system = single_pendulum().with_damping(viscous={"theta": 0.2})
    >>> data = make_dataset(system, n_trajectories=12, duration=3.0,
    ...                     excitation="sincos", random_state=0)
    >>> est = LagrangianSINDy(system.paper_library(), formulation="strong")
    >>> est = est.fit(data.X, data.tau)
    >>> report = diagnose(est, data.X, data.tau, groups=data.groups)
    >>> report.effects
    ['viscous(theta)']
    >>> round(report.steps[0].coefficient, 3)
    0.2
    """
    check_is_fitted(est)
    if is_partitioned(X):  # its folds integrate whole trajectories: in memory
        X, tau, groups = collect(X, groups=groups, y=tau)
    # the rows a fit given t= used (t=None: as given)
    est, X, tau, groups = on_fit_clock(
        est, X, tau, groups, t, what="diagnose", even=True
    )
    Xa, _, _ = validate_state(est, X, reset=False, coordinates=est.coordinates_)
    tau_a = (
        None
        if tau is None
        else validate_tau(tau, Xa.shape[0], est.n_dof_, est.coordinates_)
    )
    if (tau_a is None) != (est.case_ != "forces"):
        raise ValueError(
            "diagnose the model with the kind of data it was fitted on: tau for a "
            "model fitted with tau (case I), no tau for a passive model"
        )
    if not 0 < min_explained < 1:
        raise ValueError(f"min_explained must be in (0, 1), got {min_explained}")
    if bootstrap is not None and not (
        isinstance(bootstrap, (int, np.integer))
        and not isinstance(bootstrap, bool)
        and bootstrap >= 2
    ):
        raise ValueError(
            f"bootstrap must be None or a number of resamples >= 2, got {bootstrap!r}"
        )
    if groups is not None:
        groups = np.asarray(groups)
        if groups.shape != (Xa.shape[0],):
            raise ValueError(
                f"groups must have one label per row of X ({Xa.shape[0]}), got "
                f"{groups.shape}"
            )
    coords = list(est.coordinates_)
    d = est.n_dof_
    lib_angles = getattr(est.library_, "angles", None)
    if angles is None:
        angles = coords if lib_angles == "all" else list(lib_angles or [])
    if isinstance(eps, str):
        if eps != "auto":
            raise ValueError(f"eps must be 'auto', a number or a dict, got {eps!r}")
        eps = velocity_eps(Xa, d, coords)
    elif not isinstance(eps, dict):
        eps = {c: float(eps) for c in coords}

    # The refits share their features' weak-form statistics: each later refit's
    # features are among the joint revision's (the library and the dissipative
    # candidates), so only its input is integrated again.
    settings = DiagnosisSettings(
        catalogue=tuple(catalogue),
        extra_terms=tuple(extra_terms or ()),
        angles=tuple(angles),
        eps=eps,
        n_splits=n_splits,
        window=window,
        min_explained=min_explained,
        min_improvement=min_improvement,
        verbose=verbose,
        units=tuple(sorted((units or {}).items())),
    )
    with reuse_weak_columns():
        search = first = Search(est, Xa, tau_a, groups, settings)
        payload = None
        if "payload" in catalogue and tau_a is not None:  # the rigid body first
            payload = propose_payload(search)
            if payload.model is not None:
                search = Search(payload.model, Xa, tau_a, groups, settings)
        delays = [k for k in ("joint_delay", "delay") if k in catalogue]
        _search_effects(search, delays, revise, max_effects)
        if payload is not None and payload.model is None and _stand_ins(search):
            # Springs or offsets were kept where the payload, tried first, was not:
            # a load beside a spring explains too little alone. Second path: the
            # payload first, then the same search; kept when its final model
            # predicts held-out data better.
            forced = propose_payload(first, second=True)
            if forced.model is not None:
                other = Search(forced.model, Xa, tau_a, groups, settings)
                _search_effects(other, delays, revise, max_effects)
                if other.value < (1 - min_improvement) * search.value:
                    search, payload = other, forced
    # outside the block: a bootstrap's refits of resampled rows would only add
    # statistics that nothing reuses
    report = summarize(search, units, bootstrap, random_state)  # step 3
    if payload is not None:
        add_payload(report, payload, first, search)
    if report.degenerate_folds:
        warnings.warn(
            "diagnose excluded degenerate folds from some models' held-out scores "
            "(their refits have a singular or indefinite mass matrix): "
            + ", ".join(report.degenerate_folds)
            + (
                "; the final model's score uses every fold"
                if not report.settings.get("final_degenerate")
                else ""
            ),
            UserWarning,
            stacklevel=2,
        )
    return report


def _search_effects(search, delays, revise, max_effects):
    """Steps 0 to 2 of :func:`diagnose` on ``search``."""
    if delays and search.tau_a is not None and search.dt and search.dt > 0:
        # step 0 (a delay per joint, when named, in place of one for all)
        search.input_delay(per_joint=delays[0] == "joint_delay")
    search.total_ref = float(
        sum(search.scorer.w @ r for r in search.scorer.reference)
    )
    # A starting model that cannot predict accelerations (singular mass matrix:
    # a link's terms pruned) is revised jointly whatever ``revise`` says.
    if (revise or not search.start_valid) and search.diss:
        search.revise()  # step 1
    search.swap_pass()  # step 2b
    search.add_effects(max_effects)  # step 2
    search.swap_pass()


def _stand_ins(search) -> bool:
    """Whether the search kept a spring or an offset (what a load's gravity
    resembles on small swings)."""
    return any(e.kind in STAND_INS for e in search.effects)
