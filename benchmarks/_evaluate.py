"""Shared evaluation helpers: structure comparison, coefficient error, timed fits."""

from __future__ import annotations

import os
import time
import warnings

import numpy as np

NOISE_LEVELS = (0.0, 1e-3, 2e-2, 6e-2, 1e-1)


def tiny() -> bool:
    """True when ``LAGSINDY_BENCH_TINY`` is set: the smallest sizes, for the tests."""
    return os.environ.get("LAGSINDY_BENCH_TINY", "") not in ("", "0")


def fmt_sigma(sigma: float) -> str:
    return "0" if sigma == 0 else f"{sigma:g}"


def compare_structure(system, est, *, up_to_scale: bool) -> dict:
    """Compare a fitted estimator's support and coefficients with the true Lagrangian.

    The true Lagrangian is expressed in the estimator's fitted library
    (``system.true_coefficients(est.library_)``), so equivalent forms map to the same
    coefficients. With ``up_to_scale`` (passive data, where ``k L`` is as valid as
    ``L``) the learned coefficients are first divided by the least-squares scale
    ``s = <c, c_true> / <c_true, c_true>``.

    Returns
    -------
    dict with ``correct`` (bool: exactly the true set of terms), ``extra`` and
    ``missing`` (lists of term names), ``coef_error`` (relative 2-norm error of the
    coefficients, after rescaling when ``up_to_scale``) and ``scale``.
    """
    true = system.true_coefficients(est.library_)
    coef = np.asarray(est.coef_, dtype=float)
    names = list(est.term_names_)
    true_s = true != 0
    est_s = coef != 0
    extra = [names[k] for k in np.flatnonzero(est_s & ~true_s)]
    missing = [names[k] for k in np.flatnonzero(true_s & ~est_s)]
    scale = 1.0
    if up_to_scale:
        denom = float(true @ true)
        scale = float(coef @ true) / denom if denom > 0 else 0.0
    if scale == 0.0 or not np.isfinite(scale):
        err = np.inf
    else:
        err = float(np.linalg.norm(coef / scale - true) / np.linalg.norm(true))
    return {
        "correct": not extra and not missing,
        "extra": extra,
        "missing": missing,
        "coef_error": err,
        "scale": scale,
    }


def _fit_worker(est, X, tau, groups, queue):
    queue.put(timed_fit(est, X, tau, groups=groups))


def timed_fit(est, X, tau=None, *, groups=None, time_limit=None):
    """Fit ``est``; return ``(est or None, seconds, warning names, error or None)``.

    With ``time_limit`` (seconds) the fit runs in a fresh (spawned) process that is
    stopped after that long; the error text then says so. The time reported is the
    child's own fit time.
    """
    if time_limit is not None:
        import multiprocessing as mp
        import queue as _queue

        ctx = mp.get_context("spawn")
        q = ctx.Queue()
        proc = ctx.Process(target=_fit_worker, args=(est, X, tau, groups, q))
        proc.start()
        try:
            # Generous margin for the child's start (imports) beyond the fit itself.
            out = q.get(timeout=time_limit + 60)
        except _queue.Empty:
            out = (
                None,
                float(time_limit),
                [],
                f"stopped: no result after {time_limit + 60:g} s "
                f"(limit {time_limit:g} s "
                "plus 60 s for the process start)",
            )
        proc.join(timeout=5)
        if proc.is_alive():
            proc.terminate()
            proc.join()
        return out
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        start = time.perf_counter()
        try:
            kw = {} if groups is None else {"groups": groups}
            if tau is None:
                est.fit(X, **kw)
            else:
                est.fit(X, tau, **kw)
            error = None
        except (ValueError, FloatingPointError, RuntimeError) as exc:
            error = f"{type(exc).__name__}: {exc}"
        seconds = time.perf_counter() - start
    names = sorted(
        {
            w.category.__name__
            for w in caught
            if not issubclass(w.category, (DeprecationWarning, FutureWarning))
        }
    )
    return (None if error else est), seconds, names, error


def short(expr_text: str, limit: int = 400) -> str:
    """Markdown-safe expression text (pipes escaped), cut at ``limit`` characters."""
    text = expr_text.replace("|", "\\|")
    return text if len(text) <= limit else text[:limit] + " ..."
