"""Joint fits when dissipation dominates: the Lagrangian and the damping together.

A conservative fit of strongly damped data explains the damping force with wrong
Lagrangian terms; on a light link under a damped cart it prunes the link's terms
altogether (a 0.02 kg pole on a 2 kg cart with viscous damping 3: only
``x_dot**2`` kept, held-out cart-force R^2 0.66). The fit's probe forces (see
:mod:`lagsindy.formulation.probes`) see this: friction or damping explains most of
what the conservative fit leaves. When they do, and every force they name is
dissipative, :class:`JointDissipation` refits the Lagrangian together with a
*penalized* :class:`~lagsindy.dissipation.DissipationLibrary` of the kinds the
probes named (its candidates on every coordinate, thresholded like the
Lagrangian's terms), returns that model instead, says so with a
:class:`JointDissipationWarning`, and records it in the model
(``est.joint_dissipation_``). The same data then give the pole's four terms, the
ratio ``theta_dot**2 / cos(theta)`` within 0.01 % and the damping within 0.1 %
(R^2 0.998). The joint fit takes the conservative fit's steps, the judgement of each
equation included: a 0.02 kg pole under damping 1 at 1 N kept ``x_dot**2`` alone
until its fit, like the conservative one, solved again with every term judged within
each coordinate's equation.

What stays as before: fits with a dissipation library of their own (pass
``dissipation=DissipationLibrary([])`` to keep a conservative fit, or fit inside
:func:`conservative_fits` to keep it with the probes' warning), passive fits
(cases II and III still warn and leave the model as fitted), fits whose probes find
an energy-adding force (a negative coefficient: an input delay or a sign error,
which a damping term would hide), and internal refits without probes
(:func:`~lagsindy.formulation.probes.without_probes`). Refits of a jointly fitted
model's configuration (diagnosis, bootstrap, delay search) fit the same
dissipation library: :func:`refit_dissipation`.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import os
import warnings

import numpy as np
from sklearn.base import clone

from ._stacklevel import outside_stacklevel
from ._torch import to_tensor
from .dissipation import DissipationLibrary
from .formulation.probes import PROBE_KINDS, UnmodelledForceWarning, probing
from .pipeline import (
    build_dissipation,
    copy_with,
    fit_data,
    make_setup,
    probes_of,
    setup_of,
)
from .settings import solver_settings

__all__ = [
    "conservative_fits",
    "fit",
    "JointDissipation",
    "JointDissipationWarning",
    "refit_config",
    "refit_dissipation",
    "refit_setup",
]

# Cases whose fits are redone jointly (passive fits only warn: their scale is set by
# one term, which a joint fit's damping can trade against).
JOINED_CASES = ("forces",)


_JOINING = contextvars.ContextVar("lagsindy_joint_dissipation", default=True)


@contextlib.contextmanager
def conservative_fits():
    """Fits inside the block are not redone jointly: they return the conservative
    model and warn (:class:`~lagsindy.formulation.probes.UnmodelledForceWarning`)
    as before. ``dissipation=DissipationLibrary([])`` keeps one fit conservative
    (and turns its probes off)."""
    token = _JOINING.set(False)
    try:
        yield
    finally:
        _JOINING.reset(token)


class JointDissipationWarning(UnmodelledForceWarning):
    """The fit found friction or damping dominating a conservative fit's residual
    and fitted it jointly with the Lagrangian (``est.joint_dissipation_``)."""


def named_kinds(named) -> list:
    """The force kinds of the probes' named terms (``viscous(x)`` -> ``viscous``),
    in the registry's probe order."""
    found = {name.split("(", 1)[0] for name in named}
    return [kind for kind in PROBE_KINDS if kind in found]


# Coulomb smoothing velocity of the joint fit's candidates: this share of each
# coordinate's top speed (99th percentile of |q_dot|), as lagsindy.diagnose's
# eps="auto" (DissipationLibrary's advice: about 1 % of the top speed).
EPS_FRACTION = 0.01


def speed_eps(Xt, coordinates) -> dict:
    """``{coordinate: eps}``: :data:`EPS_FRACTION` of each coordinate's 99th
    percentile speed in the data (``Xt``, rows ``[q, q_dot, q_ddot]``), 3 digits;
    the library's default where a coordinate does not move."""
    from .dissipation import DEFAULT_EPS

    d = len(coordinates)
    speed = Xt[:, d : 2 * d].abs().double().cpu().numpy()
    top = np.quantile(speed, 0.99, axis=0)
    return {
        c: float(f"{EPS_FRACTION * t:.3g}") if t > 0 else DEFAULT_EPS
        for c, t in zip(coordinates, top)
    }


def dominates(result, kinetic_sign: float = 1.0) -> bool:
    """Whether a probe result calls for a joint fit: the fit would warn
    (:meth:`~lagsindy.formulation.probes.ProbeResult.reported`, so the probes explain
    at least half of the residual) and every named force is dissipative (its
    coefficient has the sign of the model's kinetic energy)."""
    if result is None or not result.named or not result.reported(kinetic_sign):
        return False
    return all(kinetic_sign * c > 0 for c in result.named.values())


# Registries of the warnings shown again, per file: as warnings.warn's per-module
# registry, a "default" filter shows a warning from one place once, not at every fit.
_REGISTRIES: dict = {}


def _show(w):
    """Show a recorded warning again, from its original place."""
    registry = _REGISTRIES.setdefault(w.filename, {})
    # (a module name is needed: with module=None warn_explicit shows nothing)
    module = os.path.splitext(os.path.basename(w.filename or "<unknown>"))[0]
    warnings.warn_explicit(
        w.message, w.category, w.filename, w.lineno, module, registry
    )


class JointDissipation:
    """Redo a fit jointly with dissipation when its probes find damping dominating.

    Used by :meth:`LagrangianSINDy.fit <lagsindy.LagrangianSINDy.fit>`::

        joint = JointDissipation(setup, est.get_params(deep=False))
        with joint.watch():  # the conservative fit; its warnings are held
            ...
            check_fit(fitted, setup, stats, solution, Xt, tau)
        fitted = joint.result(fitted, stats, solution, formulation, Xt, tau_t, tau,
                              groups)

    Parameters
    ----------
    setup : FitSetup
        The conservative fit's setup.
    params : dict
        The estimator's parameters (``get_params(deep=False)``), for the joint
        fit's setup.
    """

    def __init__(self, setup, params):
        self.setup, self.params = setup, dict(params)
        self.active = (
            setup.case in JOINED_CASES
            and setup.dissipation.library is None
            and probing()
            and _JOINING.get()
        )
        self.caught = []

    @contextlib.contextmanager
    def watch(self):
        """Hold the warnings of the block (the conservative fit) while a joint fit
        may replace it; :meth:`result` shows them again when it does not."""
        if not self.active:
            yield self
            return
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield self
        self.caught = list(caught)

    def replay(self):
        """Show the held warnings (with their original place)."""
        for w in self.caught:
            _show(w)
        self.caught = []

    def result(
        self, fitted, stats, solution, formulation, Xt, tau_t, tau, groups, **kwargs
    ):
        """The joint fit when the conservative ``fitted``'s probes call for it (see
        :func:`dominates`), else ``fitted`` with its warnings shown.

        The joint fit is :func:`~lagsindy.pipeline.fit_data` with the dissipation
        candidates: the conservative fit's steps, the judgement of each equation
        (:func:`~lagsindy.pipeline.judge_each_equation`) included. ``kwargs`` go to
        it (``verbose``, ``tau_1d``).
        """
        if not self.active:
            return fitted
        probed, sign = probes_of(fitted, self.setup, stats, solution)
        if not dominates(probed, sign):
            self.replay()
            return fitted
        # Every probe kind, not only the named ones: on a camera cart-pole (cart in
        # pixels, viscous and Coulomb friction) the probes named coulomb(x) alone,
        # and a joint fit with it alone dropped the pole (R^2 0.65); with both kinds
        # and eps at 1 % of the top speed it kept the four terms (R^2 0.906).
        kinds = list(PROBE_KINDS)
        library = self.setup.library
        eps = speed_eps(Xt, list(library.coordinates_))
        dissipation = build_dissipation(DissipationLibrary(kinds, eps=eps), library)
        # the dissipation candidates are penalized and thresholded like any
        # (the estimator's dissipation_threshold)
        setup = make_setup(self.params, library, dissipation, self.setup.case)
        verbose = self.setup.solver.verbose
        setup.solver = dataclasses.replace(setup.solver, verbose=verbose)
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                # the conservative fit's steps, the judgement of each equation too
                joint, _, _ = fit_data(setup, formulation, Xt, tau, groups, **kwargs)
        except (ValueError, FloatingPointError) as exc:
            self.replay()
            warnings.warn(
                f"a joint fit with {dissipation.library!r} failed ({exc}); the model "
                "is the conservative fit",
                UserWarning,
                stacklevel=outside_stacklevel(),
            )
            return fitted
        kept = {
            t.name: float(c)
            for t, c in zip(joint.dissipation_terms, joint.dissipation_coef)
            if c != 0
        }
        joint.joint_dissipation = {
            "kinds": kinds,
            "eps": eps,
            "share": float(probed.share),
            "named": dict(probed.named),
            "residual": float(probed.residual),
            "kept": kept,
        }
        which = ", ".join(f"{k} = {v:.3g}" for k, v in kept.items()) or "none"
        named = ", ".join(f"{k} = {v:.3g}" for k, v in probed.named.items())
        warnings.warn(
            f"friction or damping explains {probed.share:.0%} of what a conservative "
            f"fit leaves ({named}), so the Lagrangian was fitted jointly with "
            f"DissipationLibrary({kinds}) (penalized; kept: {which}). "
            "est.joint_dissipation_ records it. To keep the conservative fit, pass "
            "dissipation=DissipationLibrary([]).",
            JointDissipationWarning,
            stacklevel=outside_stacklevel(),
        )
        for w in caught:
            _show(w)
        return joint


def refit_dissipation(est):
    """The dissipation library a refit of ``est``'s configuration should use:
    ``est.dissipation``, or, when ``est``'s fit was redone jointly (see
    :class:`JointDissipation`), the library it added (unbuilt: a clone). Refits
    run without probes and would otherwise fall back to the conservative fit."""
    if getattr(est, "dissipation", None) is not None:
        return est.dissipation
    fitted = getattr(est, "fitted_", None)
    if fitted is None or getattr(fitted, "joint_dissipation", None) is None:
        return None
    joint = fitted.joint_dissipation
    return DissipationLibrary(list(joint["kinds"]), eps=dict(joint["eps"]))


def refit_config(est):
    """What refits of ``est``'s configuration (which run without probes) should
    fit: ``est`` itself, or an unfitted copy configured as its fit ended, with

    - the dissipation library a joint fit added (:class:`JointDissipation`), and
    - the ``equation_threshold`` of a fit that solved again with every term judged
      within each coordinate's equation
      (:func:`~lagsindy.pipeline.judge_each_equation`; ``est.equation_threshold_``):
      otherwise each refit would start from the default rule and decide on its own
      whether to judge each equation, and a bootstrap's resamples would not be
      resamples of the fit.
    """
    changes = {}
    if getattr(est, "dissipation", None) is None:
        library = refit_dissipation(est)
        if library is not None:
            changes["dissipation"] = library
    judged = getattr(getattr(est, "fitted_", None), "equation_threshold", None)
    if not changes and judged is None:
        return est
    copy = copy_with(est)
    if judged is not None:
        solver = clone(solver_settings(copy.get_params(deep=False)))
        changes["solver"] = solver.set_params(equation_threshold=judged)
    return copy.set_params(**changes)


def refit_setup(est):
    """:func:`~lagsindy.pipeline.setup_of` ``est`` with the ``equation_threshold``
    its fit ended with (``est.equation_threshold_``, see :func:`refit_config`):
    what solves of its configuration from statistics (the bootstrap's fast path)
    use."""
    setup = setup_of(est)
    judged = getattr(est.fitted_, "equation_threshold", None)
    if judged is None:
        return setup
    settings = clone(setup.solver.settings).set_params(equation_threshold=judged)
    solver = dataclasses.replace(setup.solver, settings=settings)
    return dataclasses.replace(setup, solver=solver)


def fit(setup, params, formulation, Xt, tau, groups, *, tau_1d=False, verbose=0):
    """:func:`~lagsindy.pipeline.fit_data`, redone jointly with dissipation when the
    conservative fit's probes find that friction or damping dominates what it
    leaves (:class:`JointDissipation`). Returns the :class:`FittedLagrangian`."""
    joint = JointDissipation(setup, params)
    with joint.watch():
        fitted, stats, solution = fit_data(
            setup, formulation, Xt, tau, groups, tau_1d=tau_1d, verbose=verbose
        )
    tau_t = None if tau is None else to_tensor(tau, dtype=Xt.dtype, device=Xt.device)
    return joint.result(
        fitted, stats, solution, formulation, Xt, tau_t, tau, groups,
        verbose=verbose, tau_1d=tau_1d,
    )  # fmt: skip
