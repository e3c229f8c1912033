"""Probe forces: friction and damping that a fit without a dissipation library misses.

A conservative fit of damped data absorbs the damping into wrong Lagrangian
coefficients and leaves the rest in its residual, without any sign of it in the
coefficients themselves (a forced double pendulum with viscous damping at one joint
was fitted 35-41 % low, relative residual 0.46); a passive model without it does not
lose energy as the recording does. So a fit with no ``dissipation``, with measured
forces (case I) or passive (case III with a fixed scale, and case II), adds one
viscous and one Coulomb column per coordinate (the *probes*) to its Gram
statistics, fits the Lagrangian on the other columns only, and then refits the kept
terms by least squares with and without the probes (against tau; passive, against
the column of the term whose coefficient is 1: case III's fixed term, case II's
unit term). When the probes explain at least :data:`UNMODELLED_SHARE` of what
the model leaves, and enough of it (:meth:`ProbeResult.reported`), the fit warns
(:class:`UnmodelledForceWarning`) and names them.

The probes cost a few columns of the statistics and a few small eigenvalue
decompositions; the Lagrangian is fitted on the same columns as without them.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import warnings

import numpy as np
import torch

from ..force_kinds import kinds as registered_kinds
from .scaling import BalancedGram, dense_residuals, dense_solution
from .weak import window_stride

# Kinds of the probe forces (see lagsindy.dissipation.DissipationLibrary): the
# registry's kinds marked probe (viscous, coulomb), read at import.
PROBE_KINDS = tuple(kind.name for kind in registered_kinds() if kind.probe)

# Cases whose fits are probed: with forces (I) and passive (III, and II, whose fits
# on damped data warned of nothing: a double pendulum with viscous damping 0.3 at
# one joint, which case III reports, gave no warning in case II).
PROBED_CASES = ("forces", "fixed", "acceleration")

# Share of the kept terms' least-squares residual that the probes must explain for
# the fit to warn. Measured on simulations with the weak form (10 trajectories of
# 5 s; single, double and cart pendulums; noise up to 0.1): right models gave at most
# 0.40 (single pendulum, noise 0.03-0.1 on every column, residual 4e-4); viscous
# damping of 0.01-0.3 gave 0.47-1.0 except where noise dominated the residual.
UNMODELLED_SHARE = 0.5

# What the probes explain (a share of tau's sum of squares, or of the fixed term's
# column's in case III): below RESIDUAL_FLOOR it is rounding; from EXPLAINED_FLOOR
# (a force of 1 % of tau's RMS) it is reported whatever the coefficients' signs;
# in between only when every named force is dissipative (positive against a positive
# kinetic energy). Small damping matters: the measured single pendulum's explains
# 5.8e-5 (viscous 0.112; diagnose then cuts its rollout error three-fold), while
# noise 0.02 on q, q_dot and q_ddot drew fits of 1.4e-5 to 2.2e-5 from pairs of
# opposite signs (viscous -0.003 with Coulomb 0.005) or a negative Coulomb force.
RESIDUAL_FLOOR = 1e-7
EXPLAINED_FLOOR = 1e-4

# Independent equations the check needs per probe beyond the kept terms (3 weak-form
# windows once let 2 probes fit a 2-term model's residual exactly). m extra columns
# explain about m / (n - k) of pure noise: a half at this limit, where the share test
# alone would not separate noise from a force. The count is conservative: weak-form
# windows overlap and count stride / window each, though a bump's weight sits in
# about half its window (the tests' 4 trajectories of 300 samples: 44 windows of 81
# samples per coordinate, 2 coordinates, count 21.7; the kept terms 6 to 11).
ROWS_PER_PROBE = 2

# The probes named in the warning explain all but this share of what every probe
# explains.
NAMED_SHARE = 0.1


class UnmodelledForceWarning(UserWarning):
    """Friction or damping missing from the model explains much of the residual."""


_PROBING = contextvars.ContextVar("lagsindy_probe_forces", default=True)


@contextlib.contextmanager
def without_probes():
    """Fits inside the block add no probe forces.

    For the library's internal refits (delay search, resamples, held-out refits),
    whose warnings nobody sees: they skip the probes' columns, and refits of the
    same samples keep reusing each other's weak-form statistics.
    """
    token = _PROBING.set(False)
    try:
        yield
    finally:
        _PROBING.reset(token)


def probing() -> bool:
    """Whether a fit here adds probe forces (see :func:`without_probes`)."""
    return _PROBING.get()


@dataclasses.dataclass(frozen=True)
class ProbeResult:
    """What the probe forces explain of a fit's residual.

    Attributes
    ----------
    residual : float
        Relative residual of the kept terms refitted by least squares.
    probed : float
        The same with every probe force added.
    named : dict of str to float
        Only when :attr:`missing`: the probes that explain it, with their
        coefficients refitted with the kept terms. They are chosen one at a time,
        each the one that explains most with those before it, until they explain
        all but :data:`NAMED_SHARE` of what every probe explains.
    named_residual : float
        The relative residual with the kept terms and the named probes
        (``residual`` when none is named).
    passive : bool
        Passive fits: the residuals are relative to the column of the term whose
        coefficient is 1 (case III's fixed term, case II's unit term), and the
        coefficients in the fit's scale.
    """

    residual: float
    probed: float
    named: dict
    named_residual: float
    passive: bool = False

    @property
    def gain(self) -> float:
        """What every probe explains: ``residual - probed``."""
        return self.residual - self.probed

    @property
    def share(self) -> float:
        """The share of ``residual`` the probes explain."""
        return self.gain / self.residual if self.residual > 0 else 0.0

    @property
    def missing(self) -> bool:
        """The probes explain enough to be named (see :meth:`reported`)."""
        return self.gain >= RESIDUAL_FLOOR and self.share >= UNMODELLED_SHARE

    def reported(self, kinetic_sign: float = 1.0) -> bool:
        """Whether the fit warns: :attr:`missing`, and either the probes explain at
        least :data:`EXPLAINED_FLOOR` or every named force is dissipative (its
        coefficient has the sign ``kinetic_sign`` of the model's kinetic energy)."""
        if not self.missing:
            return False
        if self.gain >= EXPLAINED_FLOOR:
            return True
        signs = [kinetic_sign * c > 0 for c in self.named.values()]
        return bool(signs) and all(signs)


def split_probes(ladder, n_features: int, names, n_targets: int = 1) -> list:
    """The ladder's statistics without the probe columns, the full Gram kept aside.

    ``ladder`` holds functions returning :class:`GramStatistics` whose columns are
    the ``n_features`` candidates, then one per probe in ``names``, then
    ``n_targets`` targets (tau; none in case III).
    Each returned function gives statistics of the candidates and target only (what
    the fit sees), with ``probe_gram`` and ``probe_names`` set.
    """
    if not names:
        return ladder

    def split(build):
        full = build()
        width = full.gram.shape[-1]
        keep = list(range(n_features)) + list(range(width - n_targets, width))
        index = torch.as_tensor(keep, device=full.gram.device)
        gram = full.gram.index_select(-1, index).index_select(-2, index)
        return dataclasses.replace(
            full, gram=gram, probe_gram=full.gram, probe_names=tuple(names)
        )

    return [lambda build=build: split(build) for build in ladder]


def probe_term(case, coef, fixed):
    """The index of the term whose column is the probes' target in a passive fit:
    case III's ``fixed`` term, case II's unit term (the first of coefficient +-1,
    where its gauge puts the largest scaled term); ``None`` with forces."""
    if case == "fixed":
        return fixed
    if case != "acceleration" or not np.any(coef):
        return None
    unit = np.flatnonzero(np.abs(coef) == 1.0)
    return int(unit[0]) if unit.size else int(np.argmax(np.abs(coef)))


def enough_equations(independent, n_support: int, n_probes: int) -> bool:
    """Whether ``independent`` equations leave ``ROWS_PER_PROBE`` per probe beyond
    the ``n_support`` kept terms (else the probes are not fitted)."""
    return independent - n_support >= ROWS_PER_PROBE * n_probes


def named_enough(current: float, probed: float, gain: float) -> bool:
    """Whether the probes named so far (the residual ``current`` with them) explain
    all but ``NAMED_SHARE`` of what every probe explains (``gain``; the residual
    ``probed`` with every probe)."""
    return current - probed <= NAMED_SHARE * gain


def probe_forces(
    stats, coef, normalize: bool = True, fixed=None, row_scale=None
) -> ProbeResult | None:
    """What the probes of ``stats`` explain of the residual of ``coef``'s terms.

    With ``fixed`` (passive fits: the index of the term whose coefficient is 1, or
    -1 in case II; see :func:`probe_term`), that term's column is the target and
    the named coefficients are in ``coef``'s scale; otherwise tau, after the
    probes. ``row_scale``:
    the fit's row scales (the coordinates' equations weighted as the fit weighted
    them; without it they are balanced again, with the probes).

    The terms kept by the fit (``coef != 0``) are refitted by least squares on the
    Gram statistics with the probes (balanced as the fit balances), alone and with
    every probe; when the probes explain enough to warn, they are named one at a
    time (see :class:`ProbeResult`). ``None`` when ``stats`` has no probes, the fit
    kept no term, or the data hold fewer than :data:`ROWS_PER_PROBE` independent
    equations per probe beyond the kept terms.
    """
    if stats.probe_gram is None:
        return None
    names = list(stats.probe_names)
    n_features = len(coef)
    total = n_features + len(names)
    balanced = BalancedGram(
        stats.probe_gram,
        stats.n_rows,
        total,
        normalize=normalize,
        project_psd=stats.corrected,
        row_scale=row_scale,
    )
    usable = balanced.identifiable().cpu().numpy()
    support = np.flatnonzero(np.asarray(coef) != 0)
    target, sign = (total, 1.0) if fixed is None else (int(fixed), -1.0)
    support = support[support != target]
    probes = [k for k in range(n_features, total) if usable[k]]
    if not probes or not support.size:  # an empty model already warns
        return None
    independent = stats.n_rows * stats.gram.shape[0]
    if stats.formulation == "weak" and stats.window:
        independent *= window_stride(stats.window) / stats.window
    if not enough_equations(independent, support.size, len(probes)):
        return None  # too few equations to tell a force from noise
    every = np.concatenate([support, probes])
    fits = balanced.problems([(support, target, sign), (every, target, sign)])[0]
    base, probed = dense_residuals([datafit for datafit, _ in fits])
    passive = fixed is not None
    unnamed = ProbeResult(base, probed, {}, base, passive)
    if not unnamed.missing:
        return unnamed
    # forward selection: add the probe that explains most until the named ones
    # explain all but NAMED_SHARE of what every probe explains
    named, current = [], base
    while len(named) < len(probes) and not named_enough(current, probed, unnamed.gain):
        rest = [k for k in probes if k not in named]
        jobs = [(np.concatenate([support, named, [k]]), target, sign) for k in rest]
        found = dense_residuals([datafit for datafit, _ in balanced.problems(jobs)[0]])
        best = int(np.argmin(found))
        named, current = named + [rest[best]], found[best]
    ((datafit, to_coef),) = balanced.problems(
        [(np.append(support, named), target, sign)]
    )[0]
    w, named_residual = dense_solution(datafit)
    coefficients = to_coef(w).cpu().numpy()[len(support) :]
    if passive:  # fitted where coef[fixed] is +1: back to coef's own scale
        coefficients = coefficients * float(coef[fixed])
    return ProbeResult(
        residual=base,
        probed=probed,
        named={names[k - n_features]: float(c) for k, c in zip(named, coefficients)},
        named_residual=named_residual,
        passive=passive,
    )


def warn_unmodelled(
    result: ProbeResult | None, kinetic_sign: float = 1.0, stacklevel: int = 2
) -> bool:
    """Warn when ``result`` says a missing force explains much of the residual
    (:meth:`ProbeResult.reported`). Returns whether it warned.
    """
    if result is None or not result.reported(kinetic_sign):
        return False
    which = ", ".join(f"{name} = {c:.3g}" for name, c in result.named.items())
    if result.passive:
        measure = (
            "least-squares residual of the kept terms relative to the column of the "
            "term whose coefficient is 1"
        )
        scale = " in the fit's scale"
        harm = (
            "the model does not lose energy as the recording does, and its "
            "coefficients may be biased by it"
        )
        tests, advice = "missing terms", ""
    else:
        measure, scale = "relative least-squares residual of the kept terms", ""
        harm = "the Lagrangian's coefficients are likely biased by it"
        tests = "an input delay and missing terms"
        negative = any(kinetic_sign * c < 0 for c in result.named.values())
        advice = (
            " A negative coefficient is a force that adds energy: check tau's sign "
            "and whether tau is recorded late or early against q "
            "(lagsindy.estimate_delay)."
            if negative
            else ""
        )
    warnings.warn(
        f"friction or damping missing from the model explains {result.share:.0%} of "
        f"what the model leaves unexplained ({measure}: {result.residual:.3g}, and "
        f"{result.named_residual:.3g} with {which}{scale}): {harm}. Refit with "
        f"dissipation=DissipationLibrary({list(PROBE_KINDS)}), or run "
        f"lagsindy.diagnose, which also tests {tests}, to find and add the "
        f"effect.{advice}",
        UnmodelledForceWarning,
        stacklevel=stacklevel + 1,
    )
    return True
