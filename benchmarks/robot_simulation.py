"""Simulating fitted robot models: the rigid-body algorithms against the generic path.

Run::

    python -m benchmarks.robot_simulation            # 2 s of both arms
    python -m benchmarks.robot_simulation --quick    # 0.5 s, shorter generic runs

Writes ``results/robot_simulation.md`` (``_quick`` with ``--quick``).

For the shipped two-link arm and seven-joint arm (``example_urdf``), a strong-form
fit of a multi-sine record (torques from lagsindy's own regressor with rotor
inertias, viscous and Coulomb friction and an offset per joint) is simulated along
the record's torques, from its first state, in one process by both paths:

* **fast**: the fitted model's mass matrix and bias by the composite rigid body and
  Newton-Euler algorithms in NumPy (``RobotTerms.numpy_dynamics``), what
  ``est.simulate`` runs now;
* **generic**: what it ran before (and runs for every other model given by a torch
  term function): reverse-mode autograd of the Lagrangian in torch
  (``TermEvaluator.numpy_model``), switched on by hiding ``numpy_dynamics``.

The input is the record's torque at ``--input-rate`` (100 Hz by default; the
integrator steps to every sample, so the number of right-hand-side calls grows with
it). Measured: right-hand-side evaluations per second on one state (mass matrix,
bias and forces, then the solve; the two paths alternated, median of repeats), the
wall time of the simulation with each path, the number of right-hand-side calls, and
the largest relative difference of the trajectories. The generic path costs about 0.1 s
per call on the seven-joint arm, so there it simulates only the first
``--generic-horizon`` seconds; the ratio is taken on that same horizon.
"""

from __future__ import annotations

import argparse
import os
import time
import warnings

import numpy as np

from lagsindy import CandidateLibrary, DissipationLibrary, LagrangianSINDy
from lagsindy.robots import BaseTerms, example_urdf, multisine

from ._common import command, header, write
from ._evaluate import tiny

ARM7_JOINTS = [f"joint{i}" for i in range(1, 8)]


def fitted(name, duration=6.0, rate=500.0, seed=0):
    """A strong-form fit of the arm on a noise-free multi-sine record; returns
    ``(est, t, X, tau)``."""
    joints = ARM7_JOINTS if name == "arm7" else None
    lib = CandidateLibrary.from_urdf(example_urdf(name), joints)
    n = lib.tree_.n_dof
    t = np.arange(0.0, duration, 1.0 / rate)
    q, qd, qdd = multisine(t, n, random_state=seed)
    truth = lib.nominal_.copy()
    truth[-n:] = np.linspace(0.02, 0.002, n)  # rotor inertias
    tau = lib.euler_lagrange_columns(q, qd, qdd) @ truth + 0.3 * qd
    tau += 0.2 * np.tanh(qd / 0.01) + 0.05  # Coulomb friction and an offset
    est = LagrangianSINDy(
        lib,
        dissipation=DissipationLibrary(["viscous", "coulomb", "bias"]),
        formulation="strong",
    )
    X = np.hstack([q, qd, qdd])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        est.fit(X, tau)
    return est, t, X, tau


class _Path:
    """Switch an estimator's model between the fast and the generic path."""

    def __init__(self, est):
        self.est = est
        self.saved = BaseTerms.__dict__["numpy_dynamics"]

    def use(self, fast: bool):
        BaseTerms.numpy_dynamics = self.saved if fast else None
        self.est.model_.__dict__.pop("_compiled", None)  # rebuilt on the next call
        return self.est.model_._numeric()

    def restore(self):
        self.use(True)


def _rhs_rate(numeric, state, n_dof, seconds):
    """Right-hand-side evaluations per second on one state (M, h, forces, solve)."""
    q, qd = state[None, :n_dof], state[None, n_dof:]
    tau = np.zeros((1, n_dof))
    calls, start = 0, time.perf_counter()
    while True:
        mass, rest = numeric.mass_and_rest(q, qd)
        np.linalg.solve(mass, (tau - rest)[..., None])
        calls += 1
        elapsed = time.perf_counter() - start
        if elapsed > seconds and calls >= 3:
            return calls / elapsed


def _simulate(est, x0, t, tau):
    """Wall time, right-hand-side calls and states of ``est.simulate``."""
    numeric = est.model_._numeric()
    inner, count = numeric.mass_and_rest, [0]

    def counted(q, qd):
        count[0] += 1
        return inner(q, qd)

    numeric.mass_and_rest = counted
    start = time.perf_counter()
    states = est.simulate(x0, t, tau)
    return time.perf_counter() - start, count[0], states


def measure(name, horizon, generic_horizon, rate_seconds, repeats, input_rate):
    """One arm's numbers, as a dict."""
    est, t, X, tau = fitted(name)
    step = max(1, round(1.0 / (input_rate * (t[1] - t[0]))))
    t, X, tau = t[::step], X[::step], tau[::step]  # the input as simulated
    n = est.model_.n_dof
    x0 = X[0, : 2 * n]
    switch = _Path(est)
    try:
        fast_rates, slow_rates = [], []
        for _ in range(repeats):  # alternated: the machine is shared and noisy
            fast_rates.append(_rhs_rate(switch.use(True), x0, n, rate_seconds))
            slow_rates.append(_rhs_rate(switch.use(False), x0, n, rate_seconds))
        keep = t <= horizon + 1e-12
        switch.use(True)
        fast_wall, fast_calls, fast_states = _simulate(est, x0, t[keep], tau[keep])
        short = t <= generic_horizon + 1e-12
        switch.use(True)
        fast_short, _, fast_head = _simulate(est, x0, t[short], tau[short])
        switch.use(False)
        slow_short, slow_calls, slow_head = _simulate(est, x0, t[short], tau[short])
        full = generic_horizon >= horizon
    finally:
        switch.restore()
    diff = np.abs(fast_head - slow_head).max() / np.abs(slow_head).max()
    return dict(
        name=name,
        n_dof=n,
        fast_rate=float(np.median(fast_rates)),
        slow_rate=float(np.median(slow_rates)),
        horizon=horizon,
        fast_wall=fast_wall,
        fast_calls=fast_calls,
        generic_horizon=min(generic_horizon, horizon),
        fast_short=fast_short,
        slow_short=slow_short,
        slow_calls=slow_calls,
        full=full,
        diff=float(diff),
        finite=bool(np.isfinite(fast_states).all()),
    )


def table(rows) -> str:
    lines = [
        "| arm | RHS/s fast | RHS/s generic | ratio | simulate fast | RHS calls "
        "| same horizon: fast | generic | ratio | trajectories differ |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['name']} ({r['n_dof']} joints) | {r['fast_rate']:.0f} "
            f"| {r['slow_rate']:.1f} | {r['fast_rate'] / r['slow_rate']:.0f} "
            f"| {r['fast_wall']:.3g} s ({r['horizon']:g} s simulated) "
            f"| {r['fast_calls']} "
            f"| {r['fast_short']:.3g} s ({r['generic_horizon']:g} s) "
            f"| {r['slow_short']:.3g} s ({r['slow_calls']} calls) "
            f"| {r['slow_short'] / r['fast_short']:.0f} | {r['diff']:.1e} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--horizon", type=float, default=2.0, help="seconds simulated")
    parser.add_argument(
        "--generic-horizon",
        type=float,
        default=None,
        help="seconds the generic path simulates (default: all of the two-link "
        "arm's, 0.1 s of the seven-joint arm's)",
    )
    parser.add_argument(
        "--input-rate",
        type=float,
        default=100.0,
        help="samples per second of the torque input simulated along (the "
        "integrator steps to every sample)",
    )
    parser.add_argument("--quick", action="store_true", help="0.5 s, fewer repeats")
    args = parser.parse_args(argv)
    quick = args.quick or tiny()
    horizon = 0.5 if quick else args.horizon
    if tiny():
        horizon = 0.05
    repeats, rate_seconds = (3, 0.3) if quick else (7, 1.0)
    rows, load = [], [os.getloadavg()[0]]
    for name in ("planar2", "arm7"):
        generic = args.generic_horizon
        if generic is None:
            generic = horizon if name == "planar2" else min(horizon, 0.1)
        if tiny():
            generic = min(generic, 0.01)
        rows.append(
            measure(name, horizon, generic, rate_seconds, repeats, args.input_rate)
        )
        load.append(os.getloadavg()[0])
        print(table(rows[-1:]), flush=True)
    title = __doc__.splitlines()[0]
    text = header(title, command("robot_simulation", argv)) + table(rows)
    text += (
        "\nRHS/s: right-hand-side evaluations per second on one state (median of "
        f"{repeats} alternated runs of {rate_seconds:g} s); simulate: "
        f"`est.simulate(x0, t, tau)` along the record's torques sampled at "
        f"{args.input_rate:g} Hz (DOP853, rtol 1e-9, a step to every sample), "
        "wall time and right-hand-side calls; same horizon: both paths over the "
        "generic path's horizon; trajectories differ: largest relative difference "
        "of the states over that horizon. Load average (1 min) at the start and "
        f"after each arm: {', '.join(f'{x:.1f}' for x in load)}: wall times are single "
        "runs under the machine's varying load, the right-hand-side rates medians "
        "of alternated runs (the steadier ratio).\n"
    )
    name = "robot_simulation" + ("_quick" if quick else "")
    write(f"{name}.md", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
