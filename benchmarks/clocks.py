"""Real clocks: uneven time stamps, dropped frames, gaps, logger clocks and edges.

What the same records give on ugly clocks against an even clock (issue #40):

1. **Camera clocks** (simulated): a passive and a forced double pendulum with
   unequal links (``m1 = 1, m2 = 0.6, l1 = 1, l2 = 0.7``), 100 Hz nominal, each
   sample taken at ``k / 100 + U(-j, j) / 100`` s (truthful stamps, jitter ``j`` of
   0, 10, 20 or 30 %), 0, 5 or 15 % of the frames dropped at random, two gaps of
   0.12 to 0.2 s per 8 s record, noise 1e-3 rad on the angles. Each record is
   fitted by

   * ``default``: the documented path, ``derivatives(q, t, groups=...,
     return_clock=True)`` (clock cleaning on) then ``LagrangianSINDy(...).fit(X,
     tau, t=clock)``: the fit puts the weak form's rows on an even clock per
     gap-free segment (:func:`lagsindy.differentiation.to_even_clock`);
   * ``resample``: :func:`lagsindy.differentiation.resample` onto an even 100 Hz
     grid inside each segment (P-spline; forces interpolated), then the same fit;
   * ``former default (no t)`` (the acceptance case only): no time stamps;
   * ``time-stamp weak form``: the hook ``fit_uneven`` (:func:`measure`; ``--stamp``).

   and compared with the fit of the same trajectories (initial states, inputs,
   noise level) sampled on an even clock with no drops and no gaps: the same terms?
   the largest relative difference of the coefficients (passive: of the ratios to
   ``theta1_dot**2``), and whether the terms are exactly the true ones.

2. **Logger clock**: the forced double pendulum on an exact 1 kHz cycle, 2 % of
   the cycles skipped, 5 % of the rows repeating the previous row (state and
   forces) as a logger re-reading a stale sample, stamped by a clock with +-0.3 ms
   of uniform jitter (and a Gaussian 0.3 ms variant with and without the recorded
   velocities); noise 1e-5 rad (an encoder) and 1e-3 rad. Accelerations against
   those of the same positions on the true clock (stale rows removed), rows at
   least 3 samples from a segment end, with the stamps as given (``clean=False``)
   and cleaned (default); then the fit (resample route) against the fit on the true
   clock.

3. **The shipped MultiArm triple pendulum** (1 kHz encoder record thinned to 100 Hz)
   thinned irregularly instead: one sample every 10 ms +- 2 ms (20 % jitter, the
   samples' true times kept) and 10 % of those dropped; chain library, weak form:
   terms and ratios against the regular 100 Hz thinning.

4. **Edges**: RMS error of the P-spline's q_ddot at the first/last samples of every
   segment relative to the interior (camera records), and what flagging
   ``edge_samples=3`` removes.

    python -m benchmarks.clocks            # results/clocks.md
    python -m benchmarks.clocks --quick    # fewer, shorter records: clocks_quick.md
    python -m benchmarks.clocks --stamp    # time-stamp weak form: clocks_stamp.md
    python -m benchmarks.clocks --edges    # edge rows in fits: clocks_edges.md
"""

from __future__ import annotations

import argparse
import inspect
import os
import time
import warnings

import numpy as np

from . import _common
from ._common import header, write

LINKS = dict(m1=1.0, m2=0.6, l1=1.0, l2=0.7)
JITTERS = (0.0, 0.1, 0.2, 0.3)
DROPS = (0.0, 0.05, 0.15)
NOISE = 1e-3
RATE = 100.0


def _tiny() -> bool:
    return os.environ.get("LAGSINDY_BENCH_TINY", "") not in ("", "0")


def system():
    from lagsindy.systems import double_pendulum

    return double_pendulum(**LINKS)


# ----------------------------------------------------------------------------- data
def camera_clock(n, rng, jitter, drop, n_gaps, duration):
    """True sample times of one record: nominal 100 Hz, jitter, drops and gaps."""
    base = np.arange(n) / RATE
    times = base + (rng.uniform(-jitter, jitter, n) / RATE if jitter else 0.0)
    times[0] = 0.0
    keep = rng.random(n) >= drop
    keep[0] = keep[-1] = True
    for _ in range(n_gaps):
        length = rng.uniform(0.12, 0.2)
        start = rng.uniform(0.15, 0.8) * duration
        keep &= ~((base > start) & (base < start + length))
    return np.sort(times[keep])


def records(sys_, n_traj, duration, forced, seed, clock):
    """Simulated trajectories sampled at the times ``clock(k, rng)`` returns.

    Returns dict with q (noisy angles), t, groups, tau (or None), X (exact [q, qd,
    qdd])."""
    rng = np.random.default_rng(seed)
    x0 = sys_.sample_initial_states(n_traj, np.random.RandomState(seed))
    omega = np.random.RandomState(seed + 1).uniform(np.pi / 2, np.pi, n_traj)
    parts = {k: [] for k in ("q", "t", "groups", "tau", "X")}
    for k in range(n_traj):
        tt = clock(k, rng)
        u_fn, tau = None, None
        if forced:
            w = np.array([omega[k]])

            def u_fn(s, _x, w=w):
                return sys_.paper_input(s, w)[0]

            u = np.stack([u_fn(s, None) for s in tt])
            tau = u @ sys_.input_matrix.T
        states = sys_.simulate(x0[k], tt, u_fn)
        X = sys_.trajectory_to_X(states, tau)
        noise_rng = np.random.default_rng([seed, k])
        parts["q"].append(X[:, :2] + NOISE * noise_rng.standard_normal((tt.size, 2)))
        parts["t"].append(tt)
        parts["groups"].append(np.full(tt.size, k))
        parts["tau"].append(tau)
        parts["X"].append(X)
    return {
        key: None if val[0] is None else np.concatenate(val)
        for key, val in parts.items()
    }


# ----------------------------------------------------------------------------- fits
def _quiet(fn):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = fn()
    return out, caught


def route_default(rec, library, clock=None):
    """The documented path: derivatives with the clock, then the fit given it."""
    from lagsindy import LagrangianSINDy
    from lagsindy.differentiation import derivatives

    def run():
        X, clk = derivatives(
            rec["q"], rec["t"], groups=rec["groups"], angles="all",
            return_clock=True, clean=True if clock is None else clock,
        )  # fmt: skip
        return LagrangianSINDy(library).fit(X, rec["tau"], t=clk)

    return _quiet(run)


def route_no_t(rec, library):
    """The former default: the segments as groups, rows taken as evenly spaced."""
    from lagsindy import LagrangianSINDy
    from lagsindy.differentiation import derivatives

    def run():
        X, seg = derivatives(
            rec["q"], rec["t"], groups=rec["groups"], angles="all", return_groups=True
        )
        return LagrangianSINDy(library).fit(X, rec["tau"], groups=seg)

    return _quiet(run)


def route_resample(rec, library, dt=1 / RATE, clock=None):
    from lagsindy import LagrangianSINDy
    from lagsindy.differentiation import resample

    def run():
        r = resample(
            rec["q"],
            rec["t"],
            dt,
            groups=rec["groups"],
            tau=rec["tau"],
            angles="all",
            clean=True if clock is None else clock,
        )
        return LagrangianSINDy(library).fit(r.X, r.tau, groups=r.groups)

    return _quiet(run)


def route_uneven(rec, library, fit_uneven):
    """The hook: ``fit_uneven(X, tau, t, groups, library=...)`` on the cleaned rows."""
    from lagsindy.differentiation import derivatives

    def run():
        X, clock = derivatives(
            rec["q"], rec["t"], groups=rec["groups"], angles="all", return_clock=True
        )
        rows = clock.rows
        tau = None if rec["tau"] is None else rec["tau"][rows]
        kwargs = {}
        if "library" in inspect.signature(fit_uneven).parameters:
            kwargs["library"] = library
        return fit_uneven(X[rows], tau, clock.t[rows], clock.groups[rows], **kwargs)

    return _quiet(run)


def coefficients(est, passive, pivot="theta1_dot**2"):
    table = est.coef_table().set_index("term")["coefficient"]
    table = table[table != 0]
    if passive and pivot in table.index:
        table = table / table[pivot]
    return table


def compare(got, ref):
    """(same terms, largest relative difference over the reference's terms)."""
    same = set(got.index) == set(ref.index)
    diff = max(
        abs(got.get(k, 0.0) / v - 1) if v else abs(got.get(k, 0.0))
        for k, v in ref.items()
    )
    return same, float(diff)


def true_terms(sys_, library):
    coef = sys_.true_coefficients(library)
    return {str(t) for t, c in zip(library.terms_, coef) if c != 0}


# ----------------------------------------------------------------------------- studies
def camera_study(sizes, fit_uneven=None, jitters=JITTERS, drops=DROPS):
    sys_ = system()
    library = sys_.paper_library()
    rows = []
    n_traj, duration = sizes
    n = int(round(duration * RATE))
    for forced in (False, True):
        label = "forced" if forced else "passive"

        def even(k, rng):
            return np.arange(n) / RATE

        ref_rec = records(sys_, n_traj, duration, forced, 0, even)
        (ref, _), wall = _timed(lambda: route_default(ref_rec, library))
        ref_c = coefficients(ref, not forced)
        truth = true_terms(sys_, ref.library_)
        rows.append(
            dict(
                system=label, jitter=0.0, drop=0.0, gaps=0, route="even clock",
                rows=len(ref_rec["t"]), same="reference",
                exact=set(ref_c.index) == truth, diff=0.0, wall=wall, warnings="",
            )
        )  # fmt: skip
        for jitter in jitters:
            for drop in drops:

                def clock(k, rng, jitter=jitter, drop=drop):
                    return camera_clock(n, rng, jitter, drop, 2, duration)

                rec = records(sys_, n_traj, duration, forced, 0, clock)
                routes = [
                    ("default", lambda: route_default(rec, library)),
                    ("resample", lambda: route_resample(rec, library)),
                ]
                if (jitter, drop) == (0.2, 0.05):  # the acceptance case
                    routes.append(
                        ("former default (no t)", lambda: route_no_t(rec, library))
                    )
                if fit_uneven is not None:
                    routes.append(
                        (
                            "time-stamp weak form",
                            lambda: route_uneven(rec, library, fit_uneven),
                        )
                    )
                for name, run in routes:
                    try:
                        (est, caught), wall = _timed(run)
                    except Exception as exc:  # noqa: BLE001 - reported in the table
                        rows.append(
                            dict(system=label, jitter=jitter, drop=drop, gaps=2,
                                 route=name, rows=len(rec["t"]), same="error",
                                 exact=False, diff=np.nan, wall=np.nan,
                                 warnings=f"{type(exc).__name__}: {exc}"[:120])
                        )  # fmt: skip
                        continue
                    got = coefficients(est, not forced)
                    same, diff = compare(got, ref_c)
                    kinds = sorted({_kind(str(w.message)) for w in caught})
                    rows.append(
                        dict(system=label, jitter=jitter, drop=drop, gaps=2,
                             route=name, rows=len(rec["t"]), same=same,
                             exact=set(got.index) == truth, diff=diff, wall=wall,
                             warnings=", ".join(k for k in kinds if k))
                    )  # fmt: skip
                    print(rows[-1], flush=True)
    return rows


def _kind(text):
    for key, name in (
        ("gap(s) in the time stamps", "gaps"),
        ("dropped frames", "dropped frames"),
        ("repeat the previous row", "stale rows"),
        ("disagree with the motion", "clock rebuilt"),
        ("median steps after the previous", "near-duplicates"),
        ("too few to differentiate", "short segments"),
        ("mass matrix", "mass matrix"),
        ("strong", "strong form"),
    ):
        if key in text:
            return name
    return "other"


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def logger_records(n_traj, duration, seed, noise, gaussian):
    """Forced double pendulum on a 1 kHz cycle, logged with stale rows and jitter."""
    sys_ = system()
    period = 1e-3
    rng = np.random.default_rng(seed)
    x0 = sys_.sample_initial_states(n_traj, np.random.RandomState(seed))
    omega = np.random.RandomState(seed + 1).uniform(np.pi / 2, np.pi, n_traj)
    out = {k: [] for k in ("q", "t", "true_t", "groups", "tau", "v", "stale", "X")}
    for k in range(n_traj):
        cycles = np.arange(int(round(duration / period)))
        logged = rng.random(cycles.size) >= 0.02
        logged[0] = True
        tt = cycles[logged] * period
        w = np.array([omega[k]])

        def u_fn(s, _x, w=w):
            return sys_.paper_input(s, w)[0]

        tau = np.stack([u_fn(s, None) for s in tt]) @ sys_.input_matrix.T
        X = sys_.trajectory_to_X(sys_.simulate(x0[k], tt, u_fn), tau)
        q = X[:, :2] + noise * rng.standard_normal((tt.size, 2))
        stale = rng.random(tt.size) < 0.05
        stale[0] = False
        source = np.arange(tt.size)
        for j in np.flatnonzero(stale):
            source[j] = source[j - 1]
        jitter = (
            rng.normal(0, 3e-4, tt.size)
            if gaussian
            else rng.uniform(-3e-4, 3e-4, tt.size)
        )
        out["q"].append(q[source])
        out["t"].append(10.0 * k + tt + jitter)
        out["true_t"].append(10.0 * k + tt)
        out["groups"].append(np.full(tt.size, k))
        out["tau"].append(tau[source])
        out["v"].append(X[source, 2:4])
        out["stale"].append(stale)
        out["X"].append(X)
    return {key: np.concatenate(val) for key, val in out.items()}


def logger_study(sizes):
    from lagsindy.differentiation import clean_clock, derivatives

    n_traj, duration = sizes
    lines = []
    cases = [
        ("uniform +-0.3 ms", 1e-5, False, False),
        ("uniform +-0.3 ms", 1e-3, False, False),
        ("Gaussian 0.3 ms", 1e-5, True, False),
        ("Gaussian 0.3 ms", 1e-5, True, True),
        ("Gaussian 0.3 ms", 1e-3, True, False),
        ("Gaussian 0.3 ms", 1e-3, True, True),
    ]
    fits = {}
    for jitter, noise, gaussian, use_v in cases:
        rec = logger_records(n_traj, duration, 3, noise, gaussian)
        fresh = ~rec["stale"]
        truth = derivatives(
            rec["q"][fresh], rec["true_t"][fresh], groups=rec["groups"][fresh],
            angles="all", clean=False,
        )  # fmt: skip
        try:
            (as_given, _), _ = _timed(lambda: _quiet(lambda: derivatives(
                rec["q"], rec["t"], groups=rec["groups"], angles="all", clean=False
            )))  # fmt: skip
            given = as_given
        except ValueError:
            given = None  # stamps going back: refused as given
        t0 = time.perf_counter()
        try:
            clock, caught = _quiet(lambda: clean_clock(
                rec["t"], rec["q"], rec["groups"], angles="all",
                velocities=rec["v"] if use_v else None,
            ))  # fmt: skip
        except ValueError as exc:  # no cycle found and stamps going back
            lines.append(
                f"| {jitter} | {noise:g} | {'yes' if use_v else 'no'} | "
                f"{int(rec['stale'].sum())} / - | refused (stamps go back) | "
                f"refused: {str(exc)[:60]}... | - | - | - |"
            )
            print(lines[-1], flush=True)
            continue
        cleaned = derivatives(
            rec["q"], rec["t"], groups=rec["groups"], angles="all", clean=clock
        )
        wall = time.perf_counter() - t0
        rows = np.flatnonzero(fresh)
        inner = _inner(rec["groups"][fresh], 3) & clock.keep[rows] & ~clock.edge[rows]

        def rel(est):
            a, b = est[rows][inner][:, 4:], truth[inner][:, 4:]
            return float(np.sqrt(np.mean((a - b) ** 2) / np.mean(b**2)))

        exact = rec["X"][fresh][inner][:, 4:]
        err_truth = float(
            np.sqrt(np.mean((truth[inner][:, 4:] - exact) ** 2) / np.mean(exact**2))
        )
        lines.append(
            f"| {jitter} | {noise:g} | {'yes' if use_v else 'no'} | "
            f"{int(rec['stale'].sum())} / {int((~clock.keep).sum())} | "
            f"{'refused (stamps go back)' if given is None else f'{rel(given):.3g}'} | "
            f"{rel(cleaned):.3g} | {err_truth:.3g} | "
            f"{'rebuilt' if clock.period else 'stamps kept'} | {wall:.1f} s |"
        )
        print(lines[-1], flush=True)
        if not gaussian:
            fits[noise] = (rec, clock)
    # fits: the clean record on the true clock vs the logged one (resample route)
    fit_lines = []
    sys_ = system()
    library = sys_.paper_library()
    for noise, (rec, clock) in fits.items():
        fresh = ~rec["stale"]
        clean = {
            "q": rec["q"][fresh], "t": rec["true_t"][fresh],
            "groups": rec["groups"][fresh], "tau": rec["tau"][fresh],
        }  # fmt: skip
        for route in ("default", "resample"):
            if route == "default":
                (ref, _), _ = _timed(lambda: route_default(clean, library))
                (got, _), wall = _timed(
                    lambda: route_default(rec, library, clock=clock)
                )
            else:
                (ref, _), _ = _timed(lambda: route_resample(clean, library, dt=1e-3))
                (got, _), wall = _timed(
                    lambda: route_resample(rec, library, dt=1e-3, clock=clock)
                )
            same, diff = compare(coefficients(got, False), coefficients(ref, False))
            truth_terms = true_terms(sys_, ref.library_)
            fit_lines.append(
                f"| {noise:g} | {route} | {same} | {diff:.2%} | "
                f"{set(coefficients(got, False).index) == truth_terms} | "
                f"{wall:.0f} s |"
            )
            print(fit_lines[-1], flush=True)
    return lines, fit_lines


def _inner(groups, edge):
    inner = np.zeros(groups.size, dtype=bool)
    starts = np.r_[0, np.flatnonzero(np.diff(groups)) + 1]
    stops = np.r_[starts[1:], groups.size]
    for a, b in zip(starts, stops):
        inner[a + edge : b - edge] = True
    return inner


def triple_study(quick):
    from lagsindy import CandidateLibrary, LagrangianSINDy
    from lagsindy.differentiation import derivatives, resample
    from lagsindy.formulation import AutoForm
    from lagsindy.io import load_multiarm_pendulum

    frame = load_multiarm_pendulum(which="triple", split="id")
    if quick:
        frame = frame[frame["trajectory"] < 6]
    names = ["phi1", "phi2", "phi3"]
    q_all = frame[["theta1", "theta2", "theta3"]].to_numpy() - np.pi
    t_all = frame["t"].to_numpy()
    stretch_all = np.r_[0, np.cumsum(np.diff(t_all) > 0.0015)]
    library = CandidateLibrary.chain(names)
    pivot = "phi1_dot**2"
    rng = np.random.default_rng(4)
    regular = np.arange(0, t_all.size, 10)
    jittered = np.clip(regular + rng.integers(-2, 3, regular.size), 0, t_all.size - 1)
    jittered = np.unique(jittered[rng.random(jittered.size) >= 0.10])
    out = []
    fits = {}
    for name, idx in (("regular 100 Hz", regular), ("irregular", jittered)):
        q, t, g = q_all[idx], t_all[idx], stretch_all[idx]
        for route in ("default", "resample", "former default (no t)"):
            if name.startswith("regular") and route != "default":
                continue

            def run(q=q, t=t, g=g, route=route):
                if route == "default":
                    X, clock = derivatives(
                        q, t, groups=g, angles="all", return_clock=True
                    )
                    return LagrangianSINDy(library, dt=0.01).fit(X, t=clock)
                if route.startswith("former"):
                    X, seg = derivatives(
                        q, t, groups=g, angles="all", return_groups=True
                    )
                    return LagrangianSINDy(library, formulation=AutoForm(dt=0.01)).fit(
                        X, groups=seg
                    )
                r = resample(q, t, 0.01, groups=g, angles="all")
                return LagrangianSINDy(library, formulation=AutoForm(dt=0.01)).fit(
                    r.X, groups=r.groups
                )

            (est, caught), wall = _timed(lambda run=run: _quiet(run))
            fits[(name, route)] = coefficients(est, True, pivot)
            kinds = sorted({_kind(str(w.message)) for w in caught} - {"other"})
            out.append((name, route, len(idx), fits[(name, route)], wall, kinds))
    ref = fits[("regular 100 Hz", "default")]
    lines = []
    for name, route, n_rows, c, wall, kinds in out:
        same, diff = compare(c, ref)
        lines.append(
            f"| {name} | {route} | {n_rows} | {len(c)} | {same} | {diff:.2%} | "
            f"{wall:.1f} s | {', '.join(kinds)} |"
        )
    return lines


def edge_study(sizes):
    from lagsindy.differentiation import derivatives

    sys_ = system()
    n_traj, duration = sizes
    n = int(round(duration * RATE))
    lines = []
    for jitter, drop in ((0.0, 0.0), (0.2, 0.05)):

        def clock(k, rng, jitter=jitter, drop=drop):
            return camera_clock(n, rng, jitter, drop, 2, duration)

        rec = records(sys_, n_traj, duration, False, 1, clock)
        (X, clk), _ = _quiet(lambda: derivatives(
            rec["q"], rec["t"], groups=rec["groups"], angles="all", return_clock=True
        ))  # fmt: skip
        err = X[:, 4:] - rec["X"][:, 4:]
        dist = np.full(err.shape[0], 10**6)
        for s in np.unique(clk.groups[clk.keep]):
            idx = np.flatnonzero(clk.keep & (clk.groups == s))
            m = idx.size
            dist[idx] = np.minimum(np.arange(m), np.arange(m)[::-1])
        interior = dist >= 10
        rin = np.sqrt(np.mean(err[interior] ** 2))
        by = [np.sqrt(np.mean(err[dist == k] ** 2)) for k in range(5)]
        valid = clk.keep
        total = np.sum(err[valid] ** 2)
        share = np.sum(err[valid & clk.edge] ** 2) / total
        after = np.sqrt(np.mean(err[valid & ~clk.edge] ** 2))
        before = np.sqrt(np.mean(err[valid] ** 2))
        lines.append(
            f"| {jitter:.0%} jitter, {drop:.0%} dropped, 2 gaps | {rin:.3g} | "
            + " | ".join(f"{b:.3g} ({b / rin:.1f}x)" for b in by)
            + f" | {np.mean(clk.edge[valid]):.1%} | {share:.0%} | {before:.3g} -> "
            f"{after:.3g} |"
        )
    return lines


# ----------------------------------------------------------------------------- report
def measure(fit_uneven=None, quick=False):
    """Run every study; returns the Markdown body.

    Parameters
    ----------
    fit_uneven : callable, optional
        ``fit_uneven(X, tau, t, groups[, library=...]) -> fitted LagrangianSINDy``:
        a fit on the actual time stamps. It gets the cleaned rows
        (``derivatives(..., return_clock=True)``: ``X[clock.rows]``, the forces of
        those rows or None, ``clock.t`` and ``clock.groups`` of those rows) and, if
        it takes a ``library`` keyword, the benchmark's candidate library. ``None``:
        the camera tables have no such rows.
    quick : bool
    """
    tiny = _tiny()
    camera_sizes = (2, 3.0) if tiny else (4, 6.0) if quick else (10, 8.0)
    logger_sizes = (1, 2.0) if tiny else (2, 3.0) if quick else (4, 5.0)
    jitters = (0.0, 0.2) if (tiny or quick) else JITTERS
    drops = (0.05,) if tiny else (0.0, 0.05) if quick else DROPS
    body = []
    t0 = time.perf_counter()
    rows = camera_study(camera_sizes, fit_uneven, jitters, drops)
    body.append(_camera_table(rows, camera_sizes))
    if not tiny:
        lines, fit_lines = logger_study(logger_sizes)
        body.append(_logger_table(lines, fit_lines, logger_sizes))
        body.append(_triple_table(triple_study(quick)))
    body.append(_edge_table(edge_study(camera_sizes)))
    body.append(f"Total time: {time.perf_counter() - t0:.0f} s.\n")
    return "\n".join(body)


def _camera_table(rows, sizes):
    n_traj, duration = sizes
    out = [
        "## 1. Camera clocks (simulated double pendulum, unequal links)\n",
        f"{n_traj} trajectories x {duration:g} s, 100 Hz nominal, noise {NOISE:g} "
        "rad, two gaps of 0.12-0.2 s per record (none on the even clock). `same`: "
        "the same terms as the even-clock fit of the same trajectories; `diff`: the "
        "largest relative difference of its coefficients (passive: ratios to "
        "theta1_dot**2); `true`: exactly the true terms. Warnings: what the run "
        "said (one line per kind).\n",
        "| system | jitter | dropped | route | rows | same | diff | true | time | "
        "warnings |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        out.append(
            f"| {r['system']} | {r['jitter']:.0%} | {r['drop']:.0%} | {r['route']} | "
            f"{r['rows']} | {r['same']} | {r['diff']:.2%} | {r['exact']} | "
            f"{r['wall']:.0f} s | {r['warnings']} |"
        )
    return "\n".join(out) + "\n"


def _logger_table(lines, fit_lines, sizes):
    n_traj, duration = sizes
    return "\n".join(
        [
            "## 2. Logger clock (forced double pendulum, exact 1 kHz cycle)\n",
            f"{n_traj} trajectories x {duration:g} s; 2 % of the cycles skipped, 5 % "
            "of the rows repeat the previous row; accelerations: relative RMS "
            "difference from the P-spline on the true clock (same positions, stale "
            "rows removed), rows at least 3 samples from a segment end.\n",
            "| stamp jitter | noise (rad) | velocities given | stale rows (true / "
            "dropped) | q_ddot, stamps as given | q_ddot, cleaned | true clock vs "
            "exact | clock | cleaning time |",
            "|---|---|---|---|---|---|---|---|---|",
            *lines,
            "",
            "Fit of the logged record (uniform jitter; the cleaned clock) against "
            "the fit of the clean record on the true clock (same route). `default`: "
            "`derivatives(..., return_clock=True)` then `fit(X, tau, t=clock)`; "
            "`resample`: `resample(..., dt=1e-3)` then the fit:\n",
            "| noise (rad) | route | same terms | largest coefficient difference | "
            "true terms | time |",
            "|---|---|---|---|---|---|",
            *fit_lines,
            "",
        ]
    )


def _triple_table(lines):
    return "\n".join(
        [
            "## 3. Shipped MultiArm triple pendulum, thinned irregularly\n",
            "Identification record, phi = theta - pi, chain library, weak form "
            "(dt = 0.01). Regular: every 10th sample of 1 kHz; irregular: every "
            "10th +- 2 samples (20 % jitter, true times) with 10 % of those "
            "dropped. Compared with the regular fit (ratios to phi1_dot**2).\n",
            "| thinning | route | rows | terms | same terms | largest ratio "
            "difference | time | warnings |",
            "|---|---|---|---|---|---|---|---|",
            *lines,
            "",
        ]
    )


def _edge_table(lines):
    return "\n".join(
        [
            "## 4. Edges: q_ddot error at segment ends (P-spline, passive records)\n",
            "RMS error of q_ddot against the exact accelerations at the k-th sample "
            "from a segment end (k = 0 is the first or last sample), and relative "
            "to the interior (10 or more samples from an end); then the rows "
            "flagged by `edge` (3 per end), their share of the squared error, and "
            "the RMS error before -> after leaving them out.\n",
            "| clock | interior | k = 0 | 1 | 2 | 3 | 4 | rows flagged | share of "
            "squared error | RMS before -> after |",
            "|---|---|---|---|---|---|---|---|---|---|",
            *lines,
            "",
        ]
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--stamp", action="store_true", help="see the docstring")
    parser.add_argument("--edges", action="store_true", help="see the docstring")
    args = parser.parse_args(argv)
    cmd = _common.command("clocks", argv)
    if args.edges:
        from ._clock_edges import edge_fit_study, edge_table

        sizes = (2, 4.0) if _tiny() else (6, 6.0)
        body = edge_table(
            edge_fit_study(sizes, (10,) if _tiny() else (2, 6, 10)), sizes
        )
        write("clocks_edges.md", header("Edge rows (issue #40)", cmd) + body)
        return 0
    if args.stamp:
        from ._stampweak import stamp_report

        return stamp_report(cmd)
    body = measure(quick=args.quick)
    name = "clocks_quick.md" if (args.quick or _tiny()) else "clocks.md"
    write(name, header("Real clocks (issue #40)", cmd) + body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
