"""Seeded, small data sets of issue #41 (undriven and light links), for tests.

The simulators live in :mod:`benchmarks.undriven` (the benchmark runs them at full
size); these wrappers give the same data at sizes a test can afford, each fully
determined by its arguments:

- :func:`light_pendulum_data`: a light pendulum under a damped cart, force on the
  cart only (tau's theta column is zero);
- :func:`spherical_data`: the spherical pendulum damped and driven on theta only
  (phi free: tau's phi column is zero);
- :func:`camera_rig_data`: the real-rig-like cart-pole (camera stamps, pixels,
  bang-bang voltage, actuator delay, cart friction), through the default path's data
  preparation, with held-out records and the true model in the same units.

Scoring helpers: :func:`cart_r2` (held-out R^2 of the driven coordinate's force),
:func:`rollouts` (1 s rollouts), :func:`pole_ratio`, :func:`found_damping`.
Measured values at these sizes are in ``tests/test_undriven_bench.py``.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from benchmarks import undriven as _bench

POLE_TERMS = _bench.POLE_TERMS
CART_POLE_TERMS = _bench.CART_POLE_TERMS
TRUE_POLE_RATIO = _bench.POLE_LENGTH / (2 * _bench.G)  # theta_dot**2 / cos(theta)
SPHERICAL_DAMPING = _bench.SPHERICAL_DAMPING
r_squared = _bench.r_squared  # r_squared(true, pred): R^2, NaN for a constant true


def chain_library():
    """``CandidateLibrary.chain(["x", "theta"], angles=["theta"])``."""
    from lagsindy import CandidateLibrary

    return CandidateLibrary.chain(["x", "theta"], angles=["theta"])


def light_pendulum_data(
    fraction=0.05,
    damping=3.0,
    amplitude=5.0,
    *,
    n_trajectories=6,
    duration=4.0,
    n_heldout=3,
    seed=0,
):
    """``(system, data, heldout)``: ``fraction`` x 2 kg pole (0.3 m) on a 2 kg cart
    with viscous damping ``damping``, ``sincos`` force of ``amplitude`` N on the cart,
    noise 1e-3 on positions (``protocol="sensor"``), 100 Hz.

    ``data`` and ``heldout`` are :class:`lagsindy.systems.Dataset` s from different
    seeds; ``data.tau[:, 1]`` is zero (the pole is undriven).
    """
    from lagsindy.systems import make_dataset

    system = _bench.light_system(fraction, damping)
    kw = dict(excitation="sincos", amplitude=amplitude, noise=1e-3, protocol="sensor")
    data = make_dataset(
        system, n_trajectories, duration, random_state=100 * seed + 1, **kw
    )
    heldout = make_dataset(
        system, n_heldout, duration, random_state=100 * seed + 2, **kw
    )
    return system, data, heldout


def spherical_data(*, n_trajectories=6, duration=4.0, n_heldout=3, seed=0):
    """``(system, data, heldout)``: the spherical pendulum with viscous damping 0.4 on
    theta, driven on theta only (``sincos`` amplitude 1; ``tau[:, 1]`` is zero),
    noise 1e-3 on positions (``sensor``). Fit with ``system.paper_library()``."""
    from lagsindy.systems import make_dataset

    system = _bench.spherical_theta_driven()
    kw = dict(excitation="sincos", amplitude=1.0, noise=1e-3, protocol="sensor")
    data = make_dataset(
        system, n_trajectories, duration, random_state=100 * seed + 3, **kw
    )
    heldout = make_dataset(
        system, n_heldout, duration, random_state=100 * seed + 4, **kw
    )
    return system, data, heldout


def camera_rig_data(n_records=3, duration=8.0, *, n_heldout=2, seed=0, **kwargs):
    """The real-rig-like cart-pole, ready for ``fit`` (x in pixels, tau in volts).

    ``kwargs`` go to :func:`benchmarks.undriven.camera_cartpole` (``pole_mass``,
    ``delay``, ``n_glitches``, ...). Returns a namespace with ``X``, ``tau``,
    ``groups``, ``t`` (the training records after :func:`camera_pipeline`: tau is
    ``[u, 0]``), ``held`` (the same for ``n_heldout`` records of another seed),
    ``records`` and ``held_records`` (the raw :class:`CameraRecords`), ``truth``
    (the simulator's parameters), ``coefficients`` (the four true Lagrangian
    coefficients in these units) and ``reference`` (the true model in these units,
    a :class:`lagsindy.MechanicalModel` with inputs ``[u, 0]``).
    """
    records = _bench.camera_cartpole(
        n_records, duration, random_state=1000 + seed, **kwargs
    )
    held_records = _bench.camera_cartpole(
        n_heldout, duration, random_state=2000 + seed, **kwargs
    )
    X, tau, groups, t, notes = _bench.camera_pipeline(records)
    Xh, tauh, gh, th, _ = _bench.camera_pipeline(held_records)
    return SimpleNamespace(
        X=X,
        tau=tau,
        groups=groups,
        t=t,
        notes=notes,
        held=SimpleNamespace(X=Xh, tau=tauh, groups=gh, t=th),
        records=records,
        held_records=held_records,
        truth=records.truth,
        coefficients=_bench.rig_truth_in_pixels(records.truth),
        reference=_bench.rig_model_in_pixels(records.truth),
    )


def cart_r2(est, X, tau, *, column=0) -> float:
    """R^2 of ``est.predict(X)`` against ``tau`` on one (driven) coordinate."""
    return _bench.r_squared(tau[:, column], np.asarray(est.predict(X))[:, column])


def rollouts(model, X, tau, groups, t, horizon=1.0) -> dict:
    """``horizon`` s rollouts from the estimated states with the given inputs.

    ``model`` is a fitted estimator or a :class:`~lagsindy.MechanicalModel`. Returns
    the median RMS errors ``theta`` (rad) and ``x`` (X's units), the share
    ``simulated`` of windows that integrate, and ``hold`` (the pole error of
    holding the initial state).
    """
    theta, x, ok, hold = _bench.rollouts(model, X, tau, groups, t, horizon)
    return {"theta": theta, "x": x, "simulated": ok, "hold": hold}


def pole_ratio(est) -> float:
    """Learned ``theta_dot**2 / cos(theta)`` (NaN when ``cos(theta)`` is pruned)."""
    coef = dict(zip(map(str, est.term_names_), est.coef_))
    den = coef.get("cos(theta)", 0.0)
    return coef.get("theta_dot**2", 0.0) / den if den else float("nan")


def found_damping(est, name="viscous(x)"):
    """Coefficient of a kept non-conservative term, or ``None``."""
    return _bench._dissipation(est).get(name)
