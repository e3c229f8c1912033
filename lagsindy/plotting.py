"""Figures: measured vs model trajectories, the sparsification path, residuals.

matplotlib is an optional dependency (``pip install "lagsindy[plot]"``); it is imported
when a function here is called. The functions build :class:`matplotlib.figure.Figure`
objects directly (not through ``pyplot``), so they touch no global figure state and
work with any backend; each returns the figure and, given ``path``, saves it (PNG by
the file's extension).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

_INSTALL_HINT = (
    "lagsindy.plotting needs matplotlib, which is not installed; install the plot "
    'extra: pip install "lagsindy[plot]" (or pip install matplotlib)'
)


def _figure(**kwargs):
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(_INSTALL_HINT) from exc
    return Figure(**kwargs)


def _finish(fig, path):
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=110)
    return fig


def _units(units, n):
    """Per-coordinate units (``None`` entries when unknown)."""
    if units is None:
        return [None] * n
    units = list(units)
    if len(units) != n:
        raise ValueError(f"got {len(units)} units for states with {n} coordinates")
    return [u or None for u in units]


def _label(name, unit):
    return name if unit is None else f"{name} ({unit})"


def _names(coordinates, n):
    if coordinates is None:
        return [f"q{i}" for i in range(n)]
    coordinates = list(coordinates)
    if len(coordinates) != n:
        raise ValueError(
            f"got {len(coordinates)} coordinate names for states with {n} coordinates"
        )
    return coordinates


def plot_trajectories(
    t,
    true_states,
    learned_states,
    coordinates: Sequence[str] | None = None,
    *,
    labels: tuple[str, str] = ("measured", "model"),
    velocities: bool = False,
    units: Sequence[str] | None = None,
    title: str | None = None,
    path=None,
):
    """Positions (and optionally velocities) of two trajectories over time.

    Parameters
    ----------
    t : array-like of shape (n_times,)
    true_states, learned_states : array-like of shape (n_times, 2 * n_dof)
        States ``[q..., q_dot...]``: the measured ones (or a simulation of the
        true system) and the model's, e.g. from ``est.simulate``.
        ``learned_states`` may be ``None`` (a model that could not be integrated)
        or shorter than ``t``.
    coordinates : sequence of str, default=None
        Coordinate names for the axis labels (``q0, q1, ...`` when ``None``).
    labels : tuple of str, default=("measured", "model")
        Legend labels of the two trajectories (e.g. ``("true system", "model")``
        for a simulated system).
    velocities : bool, default=False
        Add a column of velocity plots.
    units : sequence of str, default=None
        Unit of each coordinate (e.g. ``["m", "rad"]``) for the axis labels;
        velocities get ``unit/s``. Time is in seconds.
    title : str, default=None
    path : str or path-like, default=None
        Save the figure there (PNG for ``*.png``).

    Returns
    -------
    matplotlib.figure.Figure
    """
    t = np.asarray(t, dtype=float).ravel()
    a = np.asarray(true_states, dtype=float)
    if a.ndim != 2 or a.shape[1] % 2 or a.shape[0] != t.size:
        raise ValueError(
            f"true_states must have shape (len(t)={t.size}, 2 * n_dof), got {a.shape}"
        )
    n = a.shape[1] // 2
    b = None if learned_states is None else np.asarray(learned_states, dtype=float)
    if b is not None and (
        b.ndim != 2 or b.shape[1] != a.shape[1] or b.shape[0] > t.size
    ):
        raise ValueError(
            f"learned_states must have shape (<= {t.size}, {a.shape[1]}), got {b.shape}"
        )
    names = _names(coordinates, n)
    unit = _units(units, n)
    cols = 2 if velocities else 1
    fig = _figure(figsize=(6.5 * cols, 2.2 * n + 0.8))
    axes = np.asarray(fig.subplots(n, cols, sharex=True, squeeze=False))
    for i in range(n):
        for j in range(cols):
            ax = axes[i, j]
            k = i + j * n
            ax.plot(t, a[:, k], color="k", lw=1.6, label=labels[0])
            if b is not None:
                ax.plot(
                    t[: b.shape[0]],
                    b[:, k],
                    color="C1",
                    lw=1.3,
                    ls="--",
                    label=labels[1],
                )
            u = None if unit[i] is None else unit[i] + ("/s" if j else "")
            ax.set_ylabel(_label(names[i] + ("_dot" if j else ""), u))
            ax.grid(alpha=0.3)
    for j in range(cols):
        axes[-1, j].set_xlabel("t (s)")
    axes[0, 0].legend(loc="best", fontsize="small")
    if b is None:
        axes[0, 0].set_title(
            f"{labels[1]} model could not be integrated", fontsize="small"
        )
    if title:
        fig.suptitle(title)
    return _finish(fig, path)


def plot_coefficient_path(
    est,
    *,
    terms: Sequence[str] | None = None,
    max_terms: int = 12,
    path=None,
):
    """Coefficient of each term at each stage of the staged FISTA fit.

    Shows how thresholding sparsifies the model: one line per term that was nonzero
    at some stage, against the stage (labelled with its ``lam``), with the final
    (debiased) coefficients as the last point.

    Parameters
    ----------
    est : LagrangianSINDy
        A fitted estimator (uses ``stages_``, ``coef_`` and ``term_names_``), or a
        list of :class:`lagsindy.solvers.Stage` (then ``terms`` names the terms).
    terms : sequence of str, default=None
        Term names; by default ``est.term_names_``.
    max_terms : int, default=12
        Show at most this many terms (the largest at the final stage, then by peak).
    path : str or path-like, default=None

    Returns
    -------
    matplotlib.figure.Figure
    """
    if isinstance(est, list | tuple):
        stages, final = list(est), None
    else:
        stages, final = (
            list(getattr(est, "stages_", [])),
            np.asarray(est.coef_, dtype=float),
        )
        if terms is None:
            terms = [str(t) for t in est.term_names_]
    if not stages:
        raise ValueError(
            "no stages to plot: the estimator has no sparsification path (a model "
            "loaded from a file does not keep one; refit it)"
        )
    path_coef = np.stack([np.asarray(s.coef, dtype=float) for s in stages])
    if final is not None:
        path_coef = np.vstack([path_coef, final])
    n_terms = path_coef.shape[1]
    if terms is None:
        terms = [f"term {k}" for k in range(n_terms)]
    if len(terms) != n_terms:
        raise ValueError(f"got {len(terms)} term names for {n_terms} coefficients")
    ever = np.flatnonzero(np.any(path_coef != 0, axis=0))
    peak = np.abs(path_coef[:, ever]).max(axis=0)
    last = np.abs(path_coef[-1, ever])
    order = ever[np.lexsort((-peak, -last))][:max_terms]
    x = np.arange(path_coef.shape[0])
    ticks = [f"{k + 1}\nlam={s.lam:.1e}" for k, s in enumerate(stages)]
    if final is not None:
        ticks.append("final")
    fig = _figure(figsize=(7.5, 4.5))
    ax = fig.subplots()
    for k in order:
        ax.plot(x, path_coef[:, k], marker="o", ms=3.5, label=str(terms[k]))
    hidden = len(ever) - len(order)
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xticks(x)
    ax.set_xticklabels(ticks, fontsize="small")
    ax.set_xlabel("stage")
    ax.set_ylabel("coefficient")
    ax.set_yscale("symlog", linthresh=max(1e-3, 1e-3 * float(np.abs(path_coef).max())))
    ax.set_title(
        "sparsification path"
        + (f" ({hidden} smaller terms not shown)" if hidden > 0 else "")
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize="x-small", loc="center left", bbox_to_anchor=(1.01, 0.5))
    return _finish(fig, path)


def plot_residuals(
    est,
    X,
    tau=None,
    *,
    kind: str = "auto",
    t=None,
    dt=None,
    units: Sequence[str] | None = None,
    force_units: Sequence[str] | None = None,
    bins: int = 50,
    path=None,
):
    """Residuals of a fitted model per coordinate: over time and as a histogram.

    ``kind="forces"``: ``tau - est.predict(X)`` (needs ``tau``);
    ``kind="acceleration"``: the measured accelerations in ``X`` minus
    ``est.predict_acceleration(X, tau)`` (passive data: ``tau=None``). ``"auto"``
    picks forces for a model fit with forces (case I) when ``tau`` is given, else
    accelerations. Structure over time (drift, periodic bumps) hints at a missing
    effect such as friction; a narrow symmetric histogram at noise. Each panel's
    title gives the residual's RMS and its share of the measured signal's RMS (for
    forces: ``RMS(tau - predicted) / RMS(tau)``, "% of the measured force", the share
    :func:`lagsindy.diagnose` reports).

    Parameters
    ----------
    est : LagrangianSINDy
        A fitted estimator.
    X : array-like or DataFrame of shape (n_samples, 3 * n_dof)
    tau : array-like of shape (n_samples, n_dof), default=None
        Generalized forces; ``None`` for passive data.
    kind : {"auto", "forces", "acceleration"}, default="auto"
    t : array-like of shape (n_samples,), default=None
        Time of each sample in seconds (e.g. ``Dataset.t``).
    dt : float, default=None
        Sampling interval in seconds, when ``t`` is not given: the abscissa is then
        ``dt * sample``. With neither, the fit's ``dt_`` when set, else the sample index.
    units : sequence of str, default=None
        Unit of each coordinate (``"m"``, ``"rad"``, ``"px"``, ...): an
        acceleration residual's axis gets unit/s^2.
    force_units : sequence of str, default=None
        Unit of each column of ``tau`` (``"N"``, ``"N*m"``, ``"V"``, ...): a force
        residual's axis gets it. Without it the axis says "units of tau" (the
        input of a coordinate in radians may be a torque or a voltage: no unit is
        guessed).
    bins : int, default=50
    path : str or path-like, default=None

    Returns
    -------
    matplotlib.figure.Figure
    """
    if kind not in ("auto", "forces", "acceleration"):
        raise ValueError(
            f"kind must be 'auto', 'forces' or 'acceleration', got {kind!r}"
        )
    coords = list(est.coordinates_)
    n = len(coords)
    if kind == "auto":
        kind = "forces" if tau is not None and est.case_ == "forces" else "acceleration"
    if kind == "forces":
        if tau is None:
            raise ValueError(
                "kind='forces' needs tau (the measured generalized forces)"
            )
        pred = np.asarray(est.predict(X), dtype=float).reshape(-1, n)
        measured = np.asarray(tau, dtype=float).reshape(-1, n)
        what, measured_what = "force residual", "measured force"
    else:
        pred = np.asarray(est.predict_acceleration(X, tau), dtype=float).reshape(-1, n)
        measured = _accelerations(X, coords)
        what, measured_what = "acceleration residual", "measured acceleration"
    resid = measured - pred
    unit = _units(units, n)
    if kind == "forces":
        runit = [u or "units of tau" for u in _units(force_units, n)]
    else:
        runit = [None if u is None else f"{u}/s^2" for u in unit]
    if t is None and dt is None:
        dt = getattr(est, "dt_", None)  # the fit's sampling interval
    if t is not None:
        x, xlabel = np.asarray(t, dtype=float).ravel(), "t (s)"
    elif dt is not None:
        if not float(dt) > 0:
            raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
        x, xlabel = np.arange(resid.shape[0]) * float(dt), "t (s), samples end to end"
    else:
        x, xlabel = np.arange(resid.shape[0]), "sample (pass t= or dt= for time)"
    if x.size != resid.shape[0]:
        raise ValueError(f"t has {x.size} entries for {resid.shape[0]} samples")
    fig = _figure(figsize=(10, 2.4 * n + 0.6))
    axes = np.asarray(
        fig.subplots(n, 2, squeeze=False, gridspec_kw={"width_ratios": [3, 1]})
    )
    for i, name in enumerate(coords):
        r = resid[:, i]
        ax = axes[i, 0]
        ax.plot(x, r, ".", ms=1.5, color="C0")
        ax.axhline(0.0, color="k", lw=0.8)
        ax.set_ylabel(_label(f"{name}\n{what}", runit[i]))
        ax.grid(alpha=0.3)
        rms = float(np.sqrt(np.mean(r**2)))
        scale = float(np.sqrt(np.mean(measured[:, i] ** 2)))
        rel = f", {rms / scale:.2%} of the {measured_what}" if scale > 0 else ""
        ax.set_title(f"{name}: RMS {rms:.3g}{rel}", fontsize="small")
        axes[i, 1].hist(r, bins=bins, color="C0", alpha=0.8)
        axes[i, 1].set_xlabel(_label("residual", runit[i]))
    axes[-1, 0].set_xlabel(xlabel)
    return _finish(fig, path)


def _accelerations(X, coords):
    from ._expr import acceleration_name
    from ._validation import is_frame

    n = len(coords)
    if is_frame(X):
        return X[[acceleration_name(c) for c in coords]].to_numpy(dtype=float)
    X = np.asarray(X, dtype=float)
    return X[:, 2 * n : 3 * n]


__all__ = ["plot_coefficient_path", "plot_residuals", "plot_trajectories"]
