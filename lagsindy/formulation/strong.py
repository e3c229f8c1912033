r"""The strong (pointwise) form: Gram statistics of the Euler-Lagrange columns.

At every sample the Euler-Lagrange equations of :math:`L = \sum_k c_k \phi_k` with
forces :math:`\sum_j d_j Q_j` read :math:`\Theta c = \tau` (columns from a
:class:`~lagsindy.evaluator.TermEvaluator`). :func:`strong_gram` accumulates, per
coordinate, the Gram matrix of :math:`[\Theta \mid \text{extra} \mid \tau]` over the
samples in chunks, so :math:`\Theta` is never held in memory whole.
"""

from __future__ import annotations

import torch

# Elements (float64: 8 bytes each) of the buffers of one chunk of the strong-form Gram
# (strong_gram): the columns are written and multiplied while they are still in the
# processor's cache, rather than streamed through memory.
GRAM_CACHE = 1 << 20
GRAM_MIN_CHUNK = 256


def _chunks(n: int, size: int):
    size = max(1, int(size))
    return (slice(start, min(n, start + size)) for start in range(0, n, size))


def gram_chunk(ev, width: int) -> int:
    """Samples per chunk of :func:`strong_gram`: its buffers fit about ``GRAM_CACHE``.

    Parameters
    ----------
    ev : TermEvaluator
    width : int
        Columns of the statistics.

    Returns
    -------
    int
    """
    per_sample = ev.n_dof * width + ev.column_work()
    step = GRAM_CACHE // max(per_sample, 1)
    return max(GRAM_MIN_CHUNK, min(int(ev.chunk_size), step))


def strong_gram(
    ev,
    X: torch.Tensor,
    y: torch.Tensor | None = None,
    extra: torch.Tensor | None = None,
) -> torch.Tensor:
    """Per-dof Gram statistics of ``A = [Theta | extra | y]``, accumulated in chunks.

    Parameters
    ----------
    ev : TermEvaluator
        The terms and forces (:class:`~lagsindy.evaluator.TermEvaluator`).
    X : Tensor of shape (n_samples, 3 * n_dof)
        Rows ``[q, qd, qdd]``.
    y : Tensor of shape (n_samples, n_dof), optional
        Target generalized forces, appended as the last column of ``A``.
    extra : Tensor of shape (n_samples, n_dof, n_extra), optional
        Further left-hand-side columns given per sample (e.g. a measured input,
        to test an input gain error).

    Returns
    -------
    Tensor of shape (n_dof, n_columns (+ n_extra) (+1), same)
        ``G[i] = A[:, i, :].T @ A[:, i, :]``.
    """
    d = ev.n_dof
    n_extra = 0 if extra is None else extra.shape[2]
    width = ev.n_columns + n_extra + (0 if y is None else 1)
    out = X.new_zeros((d, width, width))
    p, buf, work = ev.n_columns, None, {}
    for sl in _chunks(X.shape[0], gram_chunk(ev, width)):
        # layout (n_dof, columns, samples): one matrix product per dof, on a
        # buffer reused from chunk to chunk (cache-sized: its columns are
        # written, then read by the product while they are still in cache)
        m = sl.stop - sl.start
        if buf is None or buf.shape[2] != m:
            buf = X.new_empty((d, width, m))
        Xs = X[sl]
        ev.columns_into(
            Xs[:, :d], Xs[:, d : 2 * d], Xs[:, 2 * d : 3 * d], buf[:, :p], work
        )
        if extra is not None:
            buf[:, p : p + n_extra] = extra[sl].permute(1, 2, 0)
        if y is not None:
            buf[:, -1] = y[sl].T
        out.baddbmm_(buf, buf.transpose(1, 2))
    return out
