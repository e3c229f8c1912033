r"""Test functions of the weak form and sums over their windows.

The weak form (:mod:`~lagsindy.formulation.weak_integrals`) integrates per-sample
integrands against a bump test function on every window of a trajectory. This module
holds the bump (:func:`bump_function`), the windows' sliding sums as products with a
banded matrix (:func:`_correlate`, :func:`_band`, and :class:`_BlockBand` for long
segments), and the first-order noise part of the windows' Gram matrix
(:func:`_window_weights`, :func:`_noise_block`).
"""

from __future__ import annotations

import torch


def bump_function(window: int, dt: float, power: int = 4):
    r"""Bump test function on ``window`` samples and its time derivative.

    :math:`\psi(s) = (1 - s^2)^{m}` for :math:`s \in [-1, 1]` across the window, with
    ``m = power``; :math:`\psi` and its first ``m - 1`` derivatives vanish at both
    ends, so integration by parts has no boundary terms and the rectangle rule is
    accurate.

    Returns
    -------
    psi, dpsi : Tensor of shape (window,)
        Values and time derivatives (per second) at the samples.
    """
    s = torch.linspace(-1.0, 1.0, window, dtype=torch.float64)
    half = (window - 1) / 2 * dt
    psi = (1 - s**2) ** power
    dpsi = -2 * power * s * (1 - s**2) ** (power - 1) / half
    return psi, dpsi


# A segment whose banded matrix of windows (see _band) would hold more entries than
# this is correlated in blocks of BAND_BLOCK windows that share one small band: the
# whole matrix grows with the square of the segment's length (a 100,000-sample
# record at window 81: 5,000 x 100,000 entries, 4 GB, per matrix).
BAND_ENTRIES = 1 << 22
BAND_BLOCK = 64


def _correlate(
    signal: torch.Tensor, kernel: torch.Tensor, stride: int, band=None
) -> torch.Tensor:
    """Sliding sums ``sum_j kernel[j] signal[start + j]`` along dim 0, every ``stride``.

    One matrix product with the banded matrix of the windows (``band``, from
    :func:`_band`, when the caller has it already): on CPU in float64 this is many
    times faster than ``conv1d`` with one input channel, which has no fast kernel.
    A long segment's band is one block of windows, slid along the rows
    (:class:`_BlockBand`).
    """
    n = signal.shape[0]
    if band is None:
        band = _band(kernel.to(signal), n, stride)
    flat = signal.reshape(n, -1)
    out = band @ flat if isinstance(band, torch.Tensor) else band.apply(flat)
    return out.reshape(-1, *signal.shape[1:])


def _band(kernel: torch.Tensor, n: int, stride: int):
    """``B`` of shape (n_windows, n) with ``B[w, w * stride + j] = kernel[j]``.

    When ``B`` would hold more than :data:`BAND_ENTRIES` entries, a
    :class:`_BlockBand` instead: the same products, in blocks of windows.
    """
    k = kernel.shape[0]
    n_win = max(0, (n - k) // stride + 1)
    if n_win * n <= BAND_ENTRIES or n_win <= BAND_BLOCK:
        return _band_matrix(kernel, n_win, n, stride)
    rows = (BAND_BLOCK - 1) * stride + k
    return _BlockBand(_band_matrix(kernel, BAND_BLOCK, rows, stride), n_win, stride)


def _band_matrix(kernel, n_win, n, stride):
    k = kernel.shape[0]
    band = kernel.new_zeros((n_win, n))
    starts = torch.arange(n_win, device=kernel.device).unsqueeze(1) * stride
    band.scatter_(
        1, starts + torch.arange(k, device=kernel.device), kernel.expand(n_win, k)
    )
    return band


class _BlockBand:
    """The banded matrix of a long segment's windows, as one block slid along it.

    The windows are shifts of one kernel, so every block of :data:`BAND_BLOCK`
    consecutive windows has the same band (``block``, of shape (BAND_BLOCK, rows)),
    applied to the rows under the block: memory and work grow with the segment's
    length, not its square.
    """

    def __init__(self, block, n_win, stride):
        self.block, self.n_win, self.stride = block, n_win, stride

    def apply(self, flat):
        """The windows' sums of ``flat`` (rows, columns): (n_windows, columns)."""
        per, rows = self.block.shape
        hop = per * self.stride
        n_full = self.n_win // per
        parts = []
        if n_full:
            # (blocks, rows, columns): overlapping views of ``flat``, no copy
            views = flat[: (n_full - 1) * hop + rows].unfold(0, rows, hop)
            full = torch.matmul(self.block, views.transpose(1, 2))
            parts.append(full.reshape(-1, flat.shape[1]))
        rest = self.n_win - n_full * per
        if rest:
            width = rows - (per - 1) * self.stride  # the kernel's length
            span = (rest - 1) * self.stride + width
            start = n_full * hop
            parts.append(self.block[:rest, :span] @ flat[start : start + span])
        return torch.cat(parts) if len(parts) > 1 else parts[0]


def _window_weights(n: int, kernel_a, kernel_b, stride: int):
    """Per-sample sums over windows of a^2, a b and b^2 (for the noise correction)."""
    k = kernel_a.shape[0]
    n_win = (n - k) // stride + 1
    starts = kernel_a.new_zeros((1, 1, n_win))
    starts[..., :] = 1.0
    out = []
    for kern in (kernel_a * kernel_a, kernel_a * kernel_b, kernel_b * kernel_b):
        # scatter each window's kernel onto its samples: a transposed correlation
        full = torch.nn.functional.conv_transpose1d(
            starts, kern.view(1, 1, -1), stride=stride
        )
        res = kernel_a.new_zeros(n)
        res[: full.shape[-1]] = full.flatten()[:n]
        out.append(res)
    return tuple(out)


def _noise_block(d, sens, weights, noise_cov, width, slices=None):
    """First-order noise contribution to the weak Gram (see
    :func:`~lagsindy.formulation.weak_integrals.weak_grams`), from the
    sensitivities of :func:`~lagsindy.formulation.weak_integrals._noise_sensitivities`
    and the per-sample window weights, for ``d`` coordinates.

    With ``slices`` (row ranges, every row sampled): one contribution per range,
    stacked on a leading axis.
    """
    rows, factor, h1, h2 = sens
    a2, ab, b2 = weights
    if rows is not None:
        a2, ab, b2 = a2[rows], ab[rows], b2[rows]
    p0 = h1.shape[0]
    # sum_s [h1 h2]^T (W_s kron Lambda) [h1 h2], W_s = [[a2, ab], [ab, b2]] (a
    # Gram matrix of the test functions, so positive semi-definite). Its LDL^T
    # factors, W_s = u u^T + v v^T with u = (sqrt(a2), ab / sqrt(a2)) and
    # v = (0, sqrt(b2 - ab^2 / a2)), turn the four products into one:
    # sum_s z1 Lambda z1^T + z2 Lambda z2^T, z1 = sqrt(a2) h1 + ab / sqrt(a2) h2,
    # z2 = sqrt(b2 - ab^2 / a2) h2 (a2 = 0 implies ab = 0: Cauchy-Schwarz).
    # Samples last throughout: the per-sample weights scale the last axis, Lambda
    # mixes the 2d derivatives, and the sum over samples and derivatives is one
    # matrix product (P0, 2 * 2d * n) x (2 * 2d * n, P0) per coordinate.
    pos = a2 > 0
    root = torch.sqrt(torch.where(pos, a2, torch.ones_like(a2)))
    u1 = torch.sqrt(a2)
    u2 = torch.where(pos, ab / root, torch.zeros_like(a2))
    v2 = torch.sqrt(torch.clamp(b2 - u2 * u2, min=0.0))
    n = h1.shape[-1]
    parts = [slice(0, n)] if slices is None else slices
    out = h1.new_zeros((len(parts), d, width, width))
    z = h1.new_empty((p0, 2) + h1.shape[2:])  # (P0, 2, 2d, n)
    for i in range(d):
        m1, m2 = h1[:, i], h2[:, i]  # (P0, 2d, n)
        # in place: on these strided views, out-of-place products and their sum
        # cost several times more (temporaries in a transposed order)
        torch.mul(m1, u1, out=z[:, 0])
        z[:, 0].addcmul_(m2, u2)
        torch.mul(m2, v2, out=z[:, 1])
        lz = torch.matmul(noise_cov.T, z)  # Lambda over the 2d derivatives
        for j, sl in enumerate(parts):  # (all rows: views, no copies)
            block = lz[..., sl].reshape(p0, -1) @ z[..., sl].reshape(p0, -1).T
            out[j, i, :p0, :p0] = factor * block
    return out[0] if slices is None else out
