"""Held-out scoring of supports, and refits, for :func:`~lagsindy.diagnose`.

:class:`_Statistics` holds per-fold Gram statistics (weak or strong form) of every
library term, candidate and the target; :class:`_Scorer` refits any support by least
squares on the other folds and measures the held-out residual; :func:`_fit_model`
reruns the estimator's sparse search with effects as known terms.
"""

from __future__ import annotations

import warnings
from numbers import Integral

import numpy as np
import torch
from sklearn.base import clone
from sklearn.model_selection import GroupKFold

from .. import pipeline
from .._torch import to_numpy
from ..cases.forces import hold_known
from ..dissipation import DEFAULT_EPS, DissipationLibrary
from ..evaluator import is_term_function, library_terms
from ..force_kinds import get as get_kind
from ..force_kinds import names as kind_names
from ..formulation.forms import StrongForm, WeakForm
from ..formulation.operator import EulerLagrangeOperator
from ..formulation.probes import without_probes
from ..formulation.weak import (
    WINDOW_FIRST,
    estimate_noise_covariance,
    estimate_sampling_interval,
    negligible_noise,
    trajectory_segments,
)
from ..joint import refit_config, refit_dissipation

# A refit whose mass matrix is singular or indefinite at more than this fraction of
# the checked samples cannot predict accelerations: the fold (or model) is degenerate.
_MASS_BAD_FRACTION = 0.01
# Samples per fold at which mass matrices are checked.
_MASS_ROWS = 150


def _columns(est, candidates):
    """The columns of :class:`_Statistics` for ``est``'s terms and the candidates.

    Returns the Euler-Lagrange operator over the library terms and conservative
    candidates, and forces and dissipative candidates; ``index`` (column of every
    term, force and gain candidate by name); which columns must be non-negative;
    and the number of Lagrangian columns.
    """
    cons = [c for c in candidates if c.kind == "conservative"]
    diss = [c for c in candidates if c.kind in kind_names()]
    gain = [c for c in candidates if c.kind == "gain"]
    lib_terms = library_terms(est.library_)
    if is_term_function(lib_terms):  # a robot's terms: no sympy terms to add to
        if cons:
            raise ValueError(
                "conservative candidates are sympy terms, and this library's terms are "
                "a torch term function (a robot's): leave 'conservative' out of the "
                "catalogue (lagsindy.robots.ROBOT_CATALOGUE; a spring is 'spring')"
            )
        n_lib = len(lib_terms.names)
    else:
        lib_terms = list(lib_terms) + [c.term for c in cons]
        n_lib = len(lib_terms)
    forces = list(est.dissipation_terms_) + [c.term for c in diss]
    coords = list(est.coordinates_)
    op = EulerLagrangeOperator(coords, lib_terms, forces=[f.forces for f in forces])
    n_force = len(forces)
    n_features = n_lib + n_force + len(gain)
    # (the library's names are cached; a conservative candidate's name is its str)
    names = list(est.library_.get_feature_names_out()) + [c.name for c in cons]
    index = {name: k for k, name in enumerate(names)}
    index.update({f.name: n_lib + k for k, f in enumerate(forces)})
    index.update({c.name: n_lib + n_force + k for k, c in enumerate(gain)})
    nonneg = np.zeros(n_features, dtype=bool)
    for k, f in enumerate(forces):
        nonneg[n_lib + k] = f.dissipative
    return op, index, nonneg, n_lib


def _kept_terms(model) -> set:
    """Names of the library terms the fitted ``model`` keeps (cached names)."""
    names = model.library_.get_feature_names_out()
    return {name for name, c in zip(names, model.coef_) if c}


def _support_in(index, model) -> set:
    """The columns (``index``: name -> column) of the terms and forces the fitted
    ``model`` keeps."""
    s = {index[name] for name in _kept_terms(model)}
    s |= {
        index[f.name]
        for f, c in zip(model.dissipation_terms_, model.dissipation_coef_)
        if c
    }
    return s


def _start_coefficients(est, index, n_features, n_lib, passive):
    """The starting model's coefficients over the columns, and the fixed column.

    Passive data: coefficients relative to the fixed term (its column, or the
    largest Lagrangian coefficient's with mass normalization or in case II).
    """
    start_coef = np.zeros(n_features)
    for name, c in zip(est.library_.get_feature_names_out(), est.coef_):
        start_coef[index[name]] = c
    for f, c in zip(est.dissipation_terms_, est.dissipation_coef_):
        start_coef[index[f.name]] = c
    fixed_col = None
    if passive:
        if est.fixed_term_ is not None:
            fixed_col = index[str(est.fixed_term_)]
        else:  # mass normalization or case II: the largest term sets the scale
            fixed_col = int(np.argmax(np.abs(start_coef[:n_lib])))
        start_coef = start_coef / start_coef[fixed_col]
    return start_coef, fixed_col


def _segments(Xt, d, groups, dt):
    """Time-ordered row blocks of every trajectory."""
    if groups is not None:
        return [s.cpu().numpy() for s in trajectory_segments(Xt, d, groups)]
    return [s.cpu().numpy() for s in trajectory_segments(Xt, d, None, dt=dt)]


def _make_folds(segments, n_splits):
    """Folds as lists of row blocks: whole trajectories, else time blocks."""
    if len(segments) >= n_splits:
        labels = np.concatenate([np.full(len(s), k) for k, s in enumerate(segments)])
        rows = np.concatenate(segments)
        folds = []
        for _, test in GroupKFold(n_splits).split(rows, groups=labels):
            ids = np.unique(labels[test])
            folds.append([segments[k] for k in ids])
        return folds, "trajectories"
    longest = max(len(s) for s in segments)
    if longest < 2 * n_splits:
        raise ValueError(
            f"need at least n_splits={n_splits} trajectories, or trajectories of at "
            f"least {2 * n_splits} samples to cut into time blocks; got "
            f"{len(segments)} trajector(ies) of at most {longest} samples"
        )
    folds = [[] for _ in range(n_splits)]
    for seg in segments:
        for k, block in enumerate(np.array_split(seg, n_splits)):
            if len(block):
                folds[k].append(block)
    return folds, "time blocks"


def _time_folds(est, Xt, groups, n_splits, window):
    """Sampling interval, trajectories, folds and test-function window of the data.

    Returns ``(dt, segments, folds, fold_kind, window)``; ``dt`` is None when it
    cannot be estimated, and ``window`` is odd and at most half the shortest block.
    """
    d = est.n_dof_
    own_form = pipeline.formulation_of(est.get_params(deep=False))
    dt = getattr(est, "dt_", None) or getattr(own_form, "dt", None)
    if dt is None:
        rough = _segments(Xt, d, groups, 0.0) if groups is not None else None
        rough = (
            [torch.as_tensor(s) for s in rough]
            if rough is not None
            else [torch.arange(Xt.shape[0])]
        )
        try:
            dt = estimate_sampling_interval(Xt, d, rough)
        except ValueError:
            dt = None
    segments = _segments(Xt, d, groups, dt if dt and dt > 0 else 0.0)
    folds, fold_kind = _make_folds(segments, n_splits)
    shortest_block = min(max(len(b) for b in blocks) for blocks in folds)
    chosen = getattr(est, "window_", None)  # the fit's (window="auto" chose it)
    own = getattr(own_form, "window", None)
    own = own if isinstance(own, Integral) else None
    win = int(window or chosen or own or WINDOW_FIRST)
    win = min(win, shortest_block // 2)
    if win % 2 == 0:
        win -= 1
    return dt, segments, folds, fold_kind, win


class _Statistics:
    """Per-fold Gram statistics of every library term, candidate and the target.

    Column layout: ``[library terms + conservative candidates | model forces +
    dissipative candidates | gain candidates | target]``. ``kind`` is ``"weak"``
    (integrated residual over windows) or ``"strong"`` (pointwise). The statistics
    of each block of the folds come from the formulation's
    ``trajectory_statistics`` (the weak form's noise covariance estimated once on
    every block); a fold's are the sum of its blocks'. ``raw`` holds them without,
    ``fit`` with the noise correction.
    """

    def __init__(self, op, Xt, tau_t, extra, folds, kind, *, window=None, dt=None):
        d = op.n_dof
        self.kind = kind
        blocks = [np.asarray(b) for fold in folds for b in fold]
        owner = np.asarray([k for k, fold in enumerate(folds) for _ in fold])
        labels = np.full(Xt.shape[0], -1)
        for j, b in enumerate(blocks):
            labels[b] = j
        if kind == "weak":
            usable = [torch.as_tensor(b) for b in blocks if len(b) >= window]
            if not usable:
                raise _NoWindows()
            cov = estimate_noise_covariance(Xt, usable, d)
            if negligible_noise(Xt, usable, cov):
                cov = None  # as the fit does (see weak.NEGLIGIBLE_NOISE)
            form = WeakForm(window=window, dt=dt, noise_cov=cov)
        else:
            form = StrongForm()
        inside = labels >= 0
        rows = np.flatnonzero(inside)
        stats = form.trajectory_statistics(
            op,
            Xt[rows],
            None if tau_t is None else tau_t[rows],
            labels[rows],
            extra=None if extra is None else extra[rows],
        )
        # the statistics' trajectories are the blocks, in order of first appearance
        seen, first = np.unique(labels[rows], return_index=True)
        fold_of = owner[seen[np.argsort(first)]]
        raw, fit = [], []
        for k in range(len(folds)):
            weights = (fold_of == k).astype(float)
            total = stats.total(weights, corrected=False)
            if kind == "weak" and total.n_rows == 0:
                raise _NoWindows()
            raw.append(to_numpy(total.gram))
            fit.append(to_numpy(stats.total(weights).gram))
        self.raw = np.stack(raw)  # (K, d, P, P)
        self.fit = np.stack(fit)


class _NoWindows(Exception):
    pass


class _Scorer:
    """Held-out score of any support over the columns of :class:`_Statistics`."""

    def __init__(
        self, stats, n_features, target, fixed_col, nonneg, weights, mass, known=None
    ):
        self.known = dict(known or {})  # column: value held (a robot's URDF model)
        if self.known:
            stats = _HeldStatistics(stats, self.known)
        self.stats = stats
        self.n_features = n_features
        self.target = target  # column index (case I) or None
        self.fixed_col = fixed_col  # passive: column with coefficient 1
        self.nonneg = nonneg  # bool per feature
        self.w = weights  # (d,)
        self.mass = mass  # per fold (rows, n_lib, d, d) mass matrices, or None
        full = np.einsum("i,kipq->pq", weights, stats.fit)
        diag = np.sqrt(np.clip(np.diag(full), 0, None))
        self.col = np.where(diag > 0, diag, 1.0)
        # The target (or the fixed term) keeps its units, so the SSE is in force
        # units squared, comparable with the reference scales, and coefficients
        # unscale by their own column alone.
        self.col[fixed_col if target is None else target] = 1.0
        self._cache = {}

    def _combine(self, g):
        return np.einsum("i,ipq->pq", self.w, g) / np.outer(self.col, self.col)

    def _solve(self, g, free):
        """LS coefficients (scaled) over ``free``; non-negative where required."""
        t = self.fixed_col if self.target is None else self.target
        sign = -1.0 if self.target is None else 1.0
        active = list(free)
        for _ in range(len(free) + 1):
            coef = _lstsq(g[np.ix_(active, active)], sign * g[active, t])
            neg = [(c, j) for c, j in zip(coef, active) if self.nonneg[j] and c < 0]
            if not neg:
                return active, coef
            active.remove(min(neg)[1])
        return active, coef

    def _sse(self, g_test, active, coef):
        """Weighted SSE per coordinate of the held-out residual."""
        t = self.fixed_col if self.target is None else self.target
        sign = -1.0 if self.target is None else 1.0
        out = []
        for gi in g_test:
            gs = gi / np.outer(self.col, self.col)
            yy = gs[t, t]
            b = sign * gs[active, t]
            out.append(
                max(yy - 2 * coef @ b + coef @ gs[np.ix_(active, active)] @ coef, 0)
            )
        return np.asarray(out)

    def _free(self, support):
        return [j for j in support if j != self.fixed_col and j not in self.known]

    def coefficients(self, support):
        """Full-data LS coefficients (unscaled) of ``support``, as {column: value}."""
        free = self._free(support)
        g = self._combine(self.stats.fit.sum(0))
        active, coef = self._solve(g, free)
        out = {j: c / self.col[j] for j, c in zip(active, coef)}
        if self.fixed_col is not None:
            out[self.fixed_col] = 1.0
        out.update({j: v for j, v in self.known.items() if j in support})
        return out

    def score(self, support):
        """Held-out relative RMS residual, per-fold values and degenerate folds."""
        key = tuple(sorted(support))
        if key in self._cache:
            return self._cache[key]
        free = self._free(key)
        K = self.stats.raw.shape[0]
        total = self._combine(self.stats.fit.sum(0))
        sse, ref, bad = np.zeros(K), np.zeros(K), []
        for k in range(K):
            train = total - self._combine(self.stats.fit[k])
            active, coef = self._solve(train, free)
            if self.mass is not None and not self._mass_ok(k, active, coef):
                bad.append(k)
            sse[k] = float(self.w @ self._sse(self.stats.raw[k], active, coef))
            ref[k] = float(self.w @ self.reference[k])
        # Degenerate folds are left out, unless every fold is degenerate (the
        # support itself cannot predict accelerations; valid() then rejects it).
        keep = np.ones(K, dtype=bool)
        if len(bad) < K:
            keep[bad] = False
        folds = np.where(keep, sse / np.maximum(ref, 1e-300), np.nan)
        den = ref[keep].sum()
        value = np.sqrt(sse[keep].sum() / den) if den > 0 else np.inf
        out = (float(value), folds, bad if len(bad) < K else [])
        self._cache[key] = out
        return out

    def _mass_ok(self, k, active, coef):
        n_lib = self.mass[k].shape[1]
        c = np.zeros(n_lib)
        for j, v in zip(active, coef):
            if j < n_lib:
                c[j] = v / self.col[j]
        if self.fixed_col is not None and self.fixed_col < n_lib:
            c[self.fixed_col] = 1.0
        for j, v in self.known.items():
            c[j] = v
        return _mass_definite(self.mass[k], c)


class _HeldStatistics:
    """A :class:`_Statistics`' ``raw`` and ``fit`` with known columns moved to the
    target (:func:`lagsindy.cases.forces.hold_known`), as every fit's solve does."""

    def __init__(self, stats, known):
        self.kind = stats.kind
        self.raw = hold_known(stats.raw, known)
        self.fit = hold_known(stats.fit, known)


def _mass_definite(mass, c):
    m = np.einsum("skij,k->sij", mass, c)
    eig = np.linalg.eigvalsh((m + np.swapaxes(m, 1, 2)) / 2)
    big = np.maximum(np.abs(eig).max(axis=1), 1e-300)
    definite = (eig > 1e-8 * big[:, None]).all(axis=1) | (
        eig < -1e-8 * big[:, None]
    ).all(axis=1)
    return (1.0 - definite.mean()) <= _MASS_BAD_FRACTION


def _mass_samples(op, Xt, folds):
    """Mass matrices of every column at samples of each fold, and of all the data.

    ``_MASS_ROWS`` samples per fold (for the folds' refits) and 400 of all the data
    (for the full-data fit), drawn with a fixed seed.
    """
    d = op.n_dof
    rng = np.random.default_rng(0)
    mass = []
    for blocks in folds:
        rows = np.concatenate(blocks)
        pick = np.sort(rng.choice(rows, size=min(len(rows), _MASS_ROWS), replace=False))
        with torch.no_grad():
            mass.append(to_numpy(op.mass_matrices(Xt[pick, :d], Xt[pick, d : 2 * d])))
    n = Xt.shape[0]
    all_rows = np.sort(rng.choice(n, size=min(n, 400), replace=False))
    mass_all = to_numpy(op.mass_matrices(Xt[all_rows, :d], Xt[all_rows, d : 2 * d]))
    return mass, mass_all


# Smallest scale of a coordinate's equation in diagnose's scorer, relative to the
# largest (measured: 1e-2 still let the spherical pendulum's phi equation collapse
# the refits, 1e-1 does not; light-pole grids identical at 1e-1).
_WEIGHT_FLOOR = 0.1


def _weighted_scorer(
    stats, start_coef, n_features, target, fixed_col, nonneg, mass, known=None
):
    """A :class:`_Scorer` whose equations are weighted by the starting model's forces.

    Each coordinate's weight is the inverse energy of the starting model's force
    contributions on it (the sum of the magnitudes of its terms), or of the measured
    force (``target``) when larger, that scale raised to at least
    ``_WEIGHT_FLOOR`` of the largest coordinate's; its per-fold ``reference`` scales
    are the same energies on each fold.

    The floor: a cyclic undriven coordinate (a spherical pendulum's phi) has terms
    whose Euler-Lagrange column is the rate of a conserved momentum, at noise level;
    weighted by that scale alone (1e7 times theta's), its equation, pure noise, was
    best met by coefficients near zero, every refit collapsed, and diagnose swapped
    gravity for an equivalent-on-the-data term plus an offset. A light link's
    equation (a pole of 1 % of the cart's mass) keeps its full weight above it.
    """
    full = stats.fit.sum(0)  # (d, P, P)
    d = full.shape[0]
    mag = np.sqrt(np.clip(np.einsum("ipp->ip", full)[:, :n_features], 0, None))
    model = mag @ np.abs(start_coef)  # (d,)
    meas = (
        np.zeros(d)
        if target is None
        else np.sqrt(np.clip(full[:, target, target], 0, None))
    )
    scale = np.maximum(model, meas)
    scale = np.maximum(scale, _WEIGHT_FLOOR * scale.max()) ** 2
    w = 1.0 / np.where(scale > 0, scale, 1.0)
    sc = _Scorer(stats, n_features, target, fixed_col, nonneg, w, mass, known)
    ref = []
    for g in stats.raw:
        magk = np.sqrt(np.clip(np.einsum("ipp->ip", g)[:, :n_features], 0, None))
        mk = magk @ np.abs(start_coef)
        tk = (
            np.zeros(d)
            if target is None
            else np.sqrt(np.clip(g[:, target, target], 0, None))
        )
        ref.append(np.maximum(mk, tk) ** 2)
    sc.reference = ref
    return sc


def _lstsq(g, b):
    if len(b) == 0:
        return np.zeros(0)
    evals, evecs = np.linalg.eigh((g + g.T) / 2)
    keep = evals > 1e-12 * max(evals[-1], 1e-300)
    inv = np.where(keep, 1.0 / np.where(keep, evals, 1.0), 0.0)
    return evecs @ (inv * (evecs.T @ b))


def _normalization(est):
    """The case III scale the fitted estimator chose, to keep it in refits."""
    return "mass" if getattr(est, "normalization_", None) == "mass" else est.fixed_term_


def _fit_model(est, X, tau, groups, *, effects=(), penalized=(), eps=None, fit=True):
    """Refit ``est``'s configuration: the Lagrangian's sparse search runs again.

    ``effects`` enter as known (unpenalized) terms, ``penalized`` as candidates.
    ``fit=False`` returns the configured (unfitted, quiet) estimator.
    """
    new = pipeline.copy_with(refit_config(est))  # the threshold rule its fit used
    unpenalized = list(est.unpenalized or [])
    library = clone(est.library_)
    cons = [c for c in list(effects) + list(penalized) if c.kind == "conservative"]
    if cons:
        library.set_params(terms=list(library.terms or []) + [c.term for c in cons])
        unpenalized += [str(c.term) for c in effects if c.kind == "conservative"]
    diss = [c for c in list(effects) + list(penalized) if c.kind in kind_names()]
    base = refit_dissipation(est)  # a jointly refitted model: its dissipation
    if base is not None and est.dissipation is None:
        new.set_params(dissipation=clone(base))
    if diss:
        dlib = (
            DissipationLibrary(kinds=(), coordinates=est.coordinates_)
            if base is None
            else clone(base)
        )
        old = dlib.eps
        merged = {
            c: (old.get(c, DEFAULT_EPS) if isinstance(old, dict) else float(old))
            for c in est.coordinates_
        }
        for c in diss:
            if "eps" in get_kind(c.kind).parameter_names:
                merged[c.coordinates[0]] = (eps or {}).get(
                    c.coordinates[0], DEFAULT_EPS
                )
        specs = list(dlib.terms or [])
        specs += [(c.kind, get_kind(c.kind).target(c.coordinates)) for c in diss]
        dlib.set_params(terms=specs, eps=merged)
        new.set_params(dissipation=dlib)
        unpenalized += [c.name for c in effects if c.kind in kind_names()]
    new.set_params(library=library, unpenalized=unpenalized or None)
    if est.case_ == "fixed":
        new.set_params(fixed_term=_normalization(est))
    # the formulation est's fit used, with the window it chose
    new.set_params(formulation=pipeline.fitted_formulation(est))
    new.set_params(verbose=0)  # refits are quiet; the result keeps est's verbose
    if not fit:
        return new
    with warnings.catch_warnings(), without_probes():
        warnings.simplefilter("ignore")
        new.fit(X, tau, groups=groups)
    return new.set_params(verbose=est.verbose)


def _adjusted_tau(tau, gains):
    if tau is None or not gains:
        return tau
    out = tau.copy()
    for i, gamma in gains.items():
        out[:, i] = out[:, i] * (1.0 + gamma)
    return out


def _residual(est, X, tau):
    """Euler-Lagrange (force) residual per sample: tau - Theta c (or -Theta c)."""
    pred = np.asarray(est.predict(X), dtype=float).reshape(len(X), -1)
    return (np.zeros_like(pred) if tau is None else tau) - pred


def _force_scale(est, Xt):
    """Per-coordinate RMS of the summed magnitudes of the model's force terms."""
    coef = est.fitted_.all_coef()
    support = np.flatnonzero(coef)
    if support.size == 0:
        return np.ones(est.n_dof_)
    cols = est.fitted_.feature_operator(support, Xt.device, Xt.dtype).columns(Xt)
    size = (cols.abs() * torch.as_tensor(np.abs(coef[support]), dtype=Xt.dtype)).sum(2)
    return np.sqrt(np.mean(to_numpy(size) ** 2, axis=0))
