r"""The weak form's integrals: Gram statistics of the windows of each trajectory.

Multiplying the Euler-Lagrange equations by a test function :math:`\psi_w` supported
on a window of samples and integrating by parts gives, for each window and
coordinate,

.. math::

    \sum_k c_k \int \big(-\dot\psi_w \partial_{\dot q}\phi_k
    - \psi_w \partial_q \phi_k\big) dt - \sum_j d_j \int \psi_w Q_j dt
    = \int \psi_w \tau\, dt,

which needs no accelerations. The per-sample integrands (the terms' gradients, the
forces) come from a :class:`~lagsindy.evaluator.TermEvaluator`; their sums over the
windows from :mod:`.testfunctions`. :func:`weak_grams` evaluates the integrands
once for several windows, subtracts the first-order noise part (an
errors-in-variables correction, from the terms' Hessians and the forces'
Jacobians) and, inside :func:`reuse_weak_columns`, reuses the features' window
columns between refits of the same samples.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import hashlib

import numpy as np
import torch

from .testfunctions import (
    _band,
    _correlate,
    _noise_block,
    _window_weights,
    bump_function,
)

# Samples used to evaluate the weak form's noise correction (a sum over samples).
NOISE_ROWS = 10_000
# Elements (float64) of the weak form's integrands and gradient kernel output per
# chunk of trajectories (see _integrand_chunks).
WEAK_CHUNK = 1 << 19

# Per-window weak-form columns of the features kept for reuse (see reuse_weak_columns);
# None outside a reuse block.
_WEAK_REUSE = contextvars.ContextVar("lagsindy_weak_reuse", default=None)


@contextlib.contextmanager
def reuse_weak_columns():
    """Within the block, weak-form statistics of the same samples reuse the features.

    Refits of the same samples differ in their input (an input delay search) or in
    some features (diagnose adds effects), while each feature's window sums stay the
    same. Inside this block :func:`weak_grams` keeps the features' Gram block, noise
    part and window columns (keyed by the samples, windows, sampling interval and
    noise covariance); a later call whose features are all among a kept call's
    gathers their block and only integrates its input, equal to a fresh call up to
    rounding. The kept columns go when the block ends.
    """
    token = _WEAK_REUSE.set({})
    try:
        yield
    finally:
        _WEAK_REUSE.reset(token)


def weak_gram(
    ev,
    X: torch.Tensor,
    y: torch.Tensor | None,
    segments,
    *,
    window: int,
    stride: int,
    dt: float,
    noise_cov: torch.Tensor | None = None,
    noise_rows: int = NOISE_ROWS,
    extra: torch.Tensor | None = None,
    return_noise: bool = False,
):
    r"""Per-dof Gram statistics of the weak (integral) Euler-Lagrange equations.

    Multiplying the Euler-Lagrange equations by a test function :math:`\psi_w`
    supported on a window of ``window`` samples and integrating by parts gives,
    for each window and coordinate,

    .. math::

        \sum_k c_k \int \big(-\dot\psi_w \partial_{\dot q}\phi_k
        - \psi_w \partial_q \phi_k\big) dt - \sum_j d_j \int \psi_w Q_j dt
        = \int \psi_w \tau\, dt,

    which needs no accelerations and averages measurement noise over the window.
    With ``noise_cov`` (the covariance :math:`\Lambda` of white noise on
    :math:`[q, \dot q]`), the noise-induced part of the Gram matrix,
    :math:`\sum_w \sum_s J_{ws}^\top \Lambda J_{ws}` to first order in the noise
    (:math:`J_{ws}` the sensitivity of window :math:`w`'s columns to sample
    :math:`s`), is subtracted: an errors-in-variables correction of the
    attenuation that noisy regressors cause. The correction is a sum over samples;
    it is evaluated on at most ``noise_rows`` samples drawn with a fixed seed and
    scaled up (an unbiased estimate).

    Parameters
    ----------
    ev : TermEvaluator
        The terms and forces (:class:`~lagsindy.evaluator.TermEvaluator`).
    X : Tensor of shape (n_samples, >= 2 * n_dof)
        Rows ``[q, qd, ...]``; accelerations are not used.
    y : Tensor of shape (n_samples, n_dof) or None
        Generalized forces (assumed noise-free or independent of the noise on X).
    segments : list of LongTensor
        Rows of each trajectory, in time order, uniformly sampled; each at least
        ``window`` long.
    window, stride : int
        Samples per test function, and between window starts.
    dt : float
        Sampling interval.
    noise_cov : Tensor of shape (2 * n_dof, 2 * n_dof), optional
    noise_rows : int, default=10000
    extra : Tensor of shape (n_samples, n_dof, n_extra), optional
        Further left-hand-side integrands given per sample, integrated against
        the test functions like forces (no noise correction for them).
    return_noise : bool, default=False
        Return the uncorrected Gram and the noise part separately (their
        difference is the corrected Gram).

    Returns
    -------
    gram : Tensor of shape (n_dof, P, P)
        With ``P = n_columns (+ n_extra) (+ 1 for y)``; corrected for noise when
        ``noise_cov`` is given.
    noise : Tensor of shape (n_dof, P, P)
        Only with ``return_noise=True`` (then ``gram`` is uncorrected).
    n_windows : int
    """
    out = weak_grams(
        ev,
        X,
        y,
        {int(window): segments},
        strides={int(window): stride},
        dt=dt,
        noise_cov=noise_cov,
        noise_rows=noise_rows,
        extra=extra,
        return_noise=return_noise,
    )
    return out[int(window)]


def weak_grams(
    ev,
    X: torch.Tensor,
    y: torch.Tensor | None,
    segments_by_window: dict,
    *,
    strides: dict,
    dt: float,
    noise_cov: torch.Tensor | None = None,
    noise_rows: int = NOISE_ROWS,
    extra: torch.Tensor | None = None,
    return_noise: bool = False,
    lazy: bool = False,
    per_segment: bool = False,
) -> dict:
    """:func:`weak_gram` for several windows from one evaluation of the integrands.

    The per-sample integrands and (with ``noise_cov``) their sensitivities to the
    noise do not depend on the window, only their sums over windows do; so trying
    several windows costs little more than one.

    Parameters
    ----------
    ev, X, y, dt, noise_cov, noise_rows, extra, return_noise
        As for :func:`weak_gram`.
    segments_by_window : dict of int to list of LongTensor
        For each window (samples), the trajectories it is applied to (each at
        least that long); every window's segments must be among the first
        window's (the integrands are evaluated on those).
    strides : dict of int to int
        Samples between window starts, per window.
    lazy : bool, default=False
        Return, per window, a function of no arguments that sums the statistics
        when called (the shared integrands are evaluated now), so that windows
        never asked for cost nothing more. It also takes ``dt=`` (another
        sampling interval: the integrands do not depend on it, only the test
        functions do).
    per_segment : bool, default=False
        Keep each segment's statistics apart: ``gram`` (and ``noise``) get a
        leading axis over the window's segments and ``n_windows`` is an array
        (what a bootstrap over trajectories resamples). The noise part is then
        summed over every sample (``noise_rows`` is not used).

    Returns
    -------
    dict of int to tuple (or to a function returning it, with ``lazy=True``)
        Per window, ``(gram, n_windows)``, or ``(gram, noise, n_windows)`` with
        ``return_noise=True`` (see :func:`weak_gram`).
    """
    d = ev.n_dof
    windows = list(segments_by_window)
    base = list(segments_by_window[windows[0]])
    order = torch.cat(base)
    q, qd = X[order, :d], X[order, d : 2 * d]
    store = _WEAK_REUSE.get()
    key, dt_kept = None, float(dt)
    if store is not None:
        rows = order.shape[0] if per_segment else noise_rows
        key = _reuse_key(
            ev, X, order, segments_by_window, strides, dt, noise_cov, rows, per_segment
        )
        found = _kept_block(ev, store.get(key, ()), windows)
        if found is not None:

            def fresh():  # at another sampling interval the kept columns do not apply
                token = _WEAK_REUSE.set(None)
                try:
                    return weak_grams(
                        ev, X, y, segments_by_window, strides=strides, dt=dt,
                        noise_cov=noise_cov, noise_rows=noise_rows, extra=extra,
                        return_noise=return_noise, lazy=True, per_segment=per_segment,
                    )  # fmt: skip
                finally:
                    _WEAK_REUSE.reset(token)

            inputs = _input_integrands(X, y, extra, order)
            return _reused_grams(
                ev, *found, inputs, order, windows, dt, return_noise, lazy, fresh
            )
    lengths = [int(s.shape[0]) for s in base]
    chunks, owner = _integrand_chunks(ev, q, qd, order, y, extra, lengths)
    width = chunks[0][1].shape[2]
    # Where each base segment's rows sit (by its first row): its position among
    # all the rows, its length and the chunk of integrands that holds it.
    starts = np.cumsum([0] + lengths[:-1])
    offsets = {
        int(seg[0]): (int(start), length, c)
        for seg, start, length, c in zip(base, starts, lengths, owner)
    }
    sens = None
    if noise_cov is not None:
        rows = order.shape[0] if per_segment else noise_rows
        sens = _noise_sensitivities(ev, q, qd, rows)

    def build(window, dt=dt):
        stride = int(strides[window])
        psi, dpsi = (k.to(X) for k in bump_function(window, dt))
        grams, counts, slices, feats = [], [], [], []
        keep = key is not None and float(dt) == dt_kept  # the key's sampling interval
        weights = [X.new_zeros(order.shape[0]) for _ in range(3)]
        bands = {}  # per segment length: the windows' banded matrices
        for seg in segments_by_window[window]:
            first, n, c = offsets[int(seg[0])]
            sl = slice(first, first + n)
            slices.append(sl)
            if n not in bands:
                bands[n] = (_band(dpsi, n, stride), _band(psi, n, stride))
            band_a, band_b = bands[n]
            begin, a_int, b_int = chunks[c]
            here = slice(first - begin, first - begin + n)
            cols = -dt * (
                _correlate(a_int[here], dpsi, stride, band_a)
                + _correlate(b_int[here], psi, stride, band_b)
            )
            counts.append(cols.shape[0])
            by_dof = cols.transpose(0, 1)  # (dof, windows, columns)
            grams.append(torch.bmm(by_dof.transpose(1, 2), by_dof))
            if keep:
                feats.append((sl, cols[:, :, : ev.n_columns]))
            if sens is not None:
                for acc, w in zip(
                    weights, _window_weights(n, -dt * dpsi, -dt * psi, stride)
                ):
                    acc[sl] = w
        if per_segment:
            gram = torch.stack(grams) if grams else X.new_zeros((0, d, width, width))
            n_windows = np.asarray(counts, dtype=np.int64)
        else:
            gram = X.new_zeros((d, width, width))
            for g in grams:
                gram += g
            n_windows = sum(counts)
        noise = torch.zeros_like(gram)
        if sens is not None:
            noise = _noise_block(
                d, sens, weights, noise_cov, width, slices if per_segment else None
            )
        if keep:  # the features' part, for fits with other forces
            ids = _feature_ids(ev)
            entries = store.setdefault(key, [])
            kept = next((e[1] for e in entries if e[0] == ids), None)
            if kept is None:
                kept = {}
                entries.append((ids, kept))
            pf = ev.n_columns
            # copies: the caller owns the returned matrices (and may change them)
            kept[window] = (
                gram[..., :pf, :pf].clone(),
                noise[..., :pf, :pf].clone(),
                n_windows,
                stride,
                feats,
            )
        return (gram, noise, n_windows) if return_noise else (gram - noise, n_windows)

    if lazy:
        return {w: functools.partial(build, w) for w in windows}
    return {w: build(w) for w in windows}


def _integrand_chunks(ev, q, qd, order, y, extra, lengths):
    """:func:`_weak_integrands` by consecutive groups of whole segments.

    On the CPU a group holds about :data:`WEAK_CHUNK` elements of integrands and
    kernel output (at least one segment): the buffers stay in cache and are
    reused by the allocator, not mapped afresh (on 50,000 rows x 39 terms one
    block took 2x longer). On a GPU all rows form one group. The integrands
    are those of one call on all rows.

    Returns
    -------
    chunks : list of (start, a, b)
        The integrands (see :func:`_weak_integrands`) of the rows
        ``order[start:start + len(a)]``.
    owner : list of int
        The chunk of each segment.
    """
    per_row = ev.n_dof * 2 * (_width(ev, y, extra) + ev.n_terms)
    # On a GPU one launch of each kernel over all rows costs less than many.
    on_cpu = q.device.type == "cpu"
    target = max(1, WEAK_CHUNK // per_row) if on_cpu else max(1, q.shape[0])
    bounds, owner, start, size = [], [], 0, 0
    for length in lengths:
        owner.append(len(bounds))
        size += length
        if size >= target:
            bounds.append((start, start + size))
            start, size = start + size, 0
    if size or not bounds:
        bounds.append((start, start + size))
    chunks = [
        (a, *_weak_integrands(ev, q[a:b], qd[a:b], order[a:b], y, extra))
        for a, b in bounds
    ]
    return chunks, owner


def _width(ev, y, extra) -> int:
    """Columns of the statistics and integrands: features, ``extra``, ``y``."""
    n_extra = 0 if extra is None else extra.shape[2]
    return ev.n_columns + n_extra + (0 if y is None else 1)


def _weak_integrands(ev, q, qd, order, y, extra):
    """Integrands per sample, each of shape (n, n_dof, width): the a-weighted part
    (with dpsi: dphi/dqd, zeros beside it) and the b-weighted part (with psi:
    dphi/dq, the forces, ``-extra``, ``-y``).

    Written into two buffers: when every term is batched, straight from the
    gradient kernel's (term, [q, qd], sample) output, one transposing copy per
    coordinate and buffer.
    """
    d, n = ev.n_dof, q.shape[0]
    p = ev.n_terms
    f = ev.n_forces
    n_extra = 0 if extra is None else extra.shape[2]
    width = _width(ev, y, extra)
    a_int = q.new_zeros((n, d, width))
    b_int = q.new_empty((n, d, width))
    if ev.fully_batched:
        g = ev.gradients_t(q, qd)  # (p, 2d, n): the kernel's own output
        # one 2-d transpose per coordinate: a third faster than one
        # 3-d permuted copy of each half
        for i in range(d):
            a_int[:, i, :p] = g[:, d + i].T  # dphi/dqd_i: (n, p)
            b_int[:, i, :p] = g[:, i].T  # dphi/dq_i
    elif p:
        g = ev.gradients(q, qd)
        a_int[:, :, :p] = g[:, :, d:].transpose(1, 2)
        b_int[:, :, :p] = g[:, :, :d].transpose(1, 2)
    if f:
        b_int[:, :, p : p + f] = ev.force_values(q, qd)  # (n, d, f)
    if extra is not None:
        # the column below is then +int psi e
        b_int[:, :, p + f : p + f + n_extra] = -extra[order]
    if y is not None:
        b_int[:, :, -1] = -y[order]  # so that the column below is +int psi tau
    return a_int, b_int


def _reuse_key(
    ev, X, order, segments_by_window, strides, dt, noise_cov, rows, per_segment
):
    """What the feature part of :func:`weak_grams` depends on besides the
    features themselves (labelled by :func:`_feature_ids`), ``y`` and ``extra``:
    the samples, the windows, the sampling interval, the noise correction and
    whether the segments are kept apart."""
    d = ev.n_dof
    digest = hashlib.blake2b(
        X[order, : 2 * d].detach().cpu().contiguous().numpy().tobytes(),
        digest_size=16,
    ).hexdigest()
    layout = tuple(
        (int(w), int(strides[w]), tuple((int(s[0]), len(s)) for s in segs))
        for w, segs in segments_by_window.items()
    )
    cov = None if noise_cov is None else noise_cov.detach().cpu().numpy().tobytes()
    return (
        tuple(ev.coordinates),
        str(X.dtype),
        str(X.device),
        digest,
        layout,
        float(dt),
        cov,
        int(rows),
        bool(per_segment),
    )


def _feature_ids(ev) -> tuple:
    """What identifies each feature (column) across evaluators: its term or force."""
    return tuple(("term", t) for t in ev.term_ids) + tuple(
        ("force", tuple(f)) for f in ev.forces
    )


def _kept_block(ev, entries, windows):
    """``(kept, index)``: a reuse entry holding every feature of ``ev``
    (at ``index`` in its columns) for every window asked for, or None."""
    ids = _feature_ids(ev)
    for have, kept in entries:
        if all(w in kept for w in windows):
            position = {f: k for k, f in enumerate(have)}
            if all(f in position for f in ids):
                return kept, [position[f] for f in ids]
    return None


def _input_integrands(X, y, extra, order):
    """The b-integrands of the columns that are not features (``-extra``, ``-y``:
    see :func:`_weak_integrands`), of shape (n, n_dof, e); ``None`` without any."""
    parts = []
    if extra is not None:
        parts.append(-extra[order])
    if y is not None:
        parts.append(-y[order].unsqueeze(2))
    if not parts:
        return None
    return parts[0] if len(parts) == 1 else torch.cat(parts, dim=2)


def _reused_grams(
    ev, kept, index, inputs, order, windows, dt, return_noise, lazy, fresh
):
    """:func:`weak_grams` from a reuse block's kept feature columns and new inputs.

    The feature block of each Gram matrix (and of its noise part; per segment when
    the kept ones are) is gathered from the kept one at ``index``; the rows and
    columns of the inputs (``extra`` and ``y``, :func:`_input_integrands`) are sums
    of the kept feature columns times the inputs' window integrals. At another
    sampling interval than the kept one (``lazy`` builds take ``dt=``) the
    statistics are computed afresh (``fresh``).
    """
    device = order.device
    index = torch.as_tensor(index, dtype=torch.long, device=device)
    pf = len(index)
    n_in = 0 if inputs is None else inputs.shape[2]
    width = pf + n_in
    again = []  # the fresh statistics, computed once when asked for
    dt_kept = float(dt)

    def build(window, dt=dt):
        if float(dt) != dt_kept:
            if not again:
                again.append(fresh())
            return again[0][window](dt=dt)
        kept_gram, kept_noise, n_windows, stride, feats = kept[window]
        lead = kept_gram.shape[:-3]  # (segments,) when kept apart, else ()
        gram = kept_gram.new_zeros((*lead, ev.n_dof, width, width))
        noise = torch.zeros_like(gram)
        gram[..., :pf, :pf] = kept_gram[..., index][..., index, :]
        noise[..., :pf, :pf] = kept_noise[..., index][..., index, :]
        if inputs is not None:
            psi, _ = (k.to(inputs) for k in bump_function(window, dt))
            cross = gram.new_zeros((len(feats), ev.n_dof, pf, n_in))
            square = gram.new_zeros((len(feats), ev.n_dof, n_in, n_in))
            for k, (sl, cols) in enumerate(feats):
                icols = -dt * _correlate(inputs[sl], psi, stride)  # (w, dof, e)
                cross[k] = torch.einsum("wip,wie->ipe", cols[:, :, index], icols)
                square[k] = torch.einsum("wie,wif->ief", icols, icols)
            if not lead:  # summed over the segments
                cross, square = cross.sum(0), square.sum(0)
            gram[..., :pf, pf:] = cross
            gram[..., pf:, :pf] = cross.transpose(-1, -2)
            gram[..., pf:, pf:] = square
        return (gram, noise, n_windows) if return_noise else (gram - noise, n_windows)

    if lazy:
        return {w: functools.partial(build, w) for w in windows}
    return {w: build(w) for w in windows}


def _noise_sensitivities(ev, q, qd, noise_rows):
    """Rows used by the noise correction and the integrands' sensitivities there.

    Returns ``(rows, factor, h1, h2)``: ``rows`` the sample indices (``None``: all),
    ``factor`` the scale-up of the subsample, and ``h1[k, i, x, s]``,
    ``h2[k, i, x, s]`` the derivatives of the a- and b-integrands of feature ``k``
    and coordinate ``i`` with respect to ``x = [q, qd]`` at sample ``s`` (samples
    last: the kernels' own layout, in which :func:`.testfunctions._noise_block` needs no
    transposing copies).
    """
    d = ev.n_dof
    n = q.shape[0]
    rows, factor = None, 1.0
    if n > noise_rows:
        pick = np.sort(np.random.default_rng(0).choice(n, noise_rows, replace=False))
        rows = torch.as_tensor(pick, device=q.device)
        q, qd = q[rows], qd[rows]
        factor = n / noise_rows
    h1_parts, h2_parts = [], []
    if ev.n_terms:
        hess = ev.hessians_t(q, qd)  # (p, 2d, 2d, n)
        h1_parts.append(hess[:, d:])
        h2_parts.append(hess[:, :d])
    if ev.n_forces:
        jac = ev.force_jacobians_t(q, qd)  # (f, d, 2d, n)
        h1_parts.append(torch.zeros_like(jac))
        h2_parts.append(jac)
    if len(h1_parts) == 1:  # views of the hessians: no copy needed
        return rows, factor, h1_parts[0], h2_parts[0]
    return rows, factor, torch.cat(h1_parts), torch.cat(h2_parts)
