"""Undriven and light links (issue #41): what the default path keeps of a pole.

Three scenarios, each run as a user would (defaults: ``LagrangianSINDy(library).fit``
then ``lagsindy.diagnose``), each measured on held-out trajectories:

1. **Light pendulums on damped carts.** ``cart_pendulum(2.0, m, 0.3)`` with viscous
   cart damping ``b``, force on the cart only (``sincos`` input of amplitude 1 N and
   5 N), pole mass 1, 2, 5, 10 % of the cart's, ``b`` in 0.5, 1, 3, 5; 20 x 8 s at
   100 Hz, noise 1e-3 on positions (``protocol="sensor"``), seeds. With the chain
   library and with the paper's degree-3 library. Per fit and after ``diagnose``: the
   pole's terms kept, the error of the ratio ``theta_dot**2 / cos(theta)`` (true
   ``l / 2g``), the cart damping found, the other terms, the warnings, the held-out
   cart-force R^2, the time.
2. **Spherical pendulum**, viscous damping 0.4 on theta, driven on theta only (phi
   free, its column of tau zero), paper library: is ``viscous(theta)`` found within
   10 %?
3. **A real-rig-like cart-pole** (:func:`camera_cartpole`): light pole, 65 Hz camera
   stamps with jitter, dropped frames and time-stamp glitches, the cart in pixels,
   a bang-bang "voltage" acting through a gain after an actuator delay, viscous and
   Coulomb cart friction, motionless stretches. The default path with the chain
   library (:func:`camera_pipeline`: ``lagsindy.derivatives`` from the stamps, fit,
   diagnose): the four cart-pole terms, a positive-definite mass matrix, held-out
   cart-force R^2, 1 s rollouts, the delay found.

    python -m benchmarks.undriven            # results/undriven.md
    python -m benchmarks.undriven --quick    # smaller: results/undriven_quick.md
    python -m benchmarks.undriven --scenarios rig --seeds 2 --processes 2
"""

from __future__ import annotations

import argparse
import contextlib
import io
import math
import multiprocessing as mp
import os
import re
import time
import warnings

import numpy as np

from . import _common
from ._common import header, write
from ._evaluate import tiny
from ._undriven_report import light_report, rig_report, rig_text, spherical_report
from ._undriven_rig import (  # noqa: F401 - the simulator, public here
    GLITCH_KINDS,
    CameraRecords,
    camera_cartpole,
    camera_pipeline,
    r_squared,
    rig_model_in_pixels,
    rig_system,
    rig_truth_in_pixels,
    rollouts,
    warning_text,
)

CART_MASS, POLE_LENGTH, G = 2.0, 0.3, 9.81  # G as in _undriven_rig
FRACTIONS = (0.01, 0.02, 0.05, 0.10)
DAMPINGS = (0.5, 1.0, 3.0, 5.0)
AMPLITUDES = (1.0, 5.0)
POLE_TERMS = ("theta_dot**2", "theta_dot*x_dot*cos(theta)", "cos(theta)")
CART_POLE_TERMS = ("x_dot**2",) + POLE_TERMS
SPHERICAL_DAMPING = 0.4


# ----------------------------------------------------------------------------- helpers
def _call(fn, *args, **kwargs):
    """``(result or None, seconds, warnings, error or None, stdout)``."""
    buf = io.StringIO()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        start = time.perf_counter()
        try:
            with contextlib.redirect_stdout(buf):
                result, error = fn(*args, **kwargs), None
        except Exception as exc:  # noqa: BLE001 - a failure is a result here
            result, error = None, f"{type(exc).__name__}: {str(exc)[:160]}"
        seconds = time.perf_counter() - start
    return result, seconds, warning_text(caught), error, buf.getvalue()


def _terms(est) -> dict:
    """``{term: coefficient}`` of the kept Lagrangian terms."""
    return {str(n): float(c) for n, c in zip(est.term_names_, est.coef_) if c != 0}


def _dissipation(est) -> dict:
    """``{name: coefficient}`` of the kept non-conservative terms."""
    terms = getattr(est, "dissipation_terms_", None) or []
    coef = getattr(est, "dissipation_coef_", np.zeros(0))
    return {t.name: float(c) for t, c in zip(terms, coef) if c != 0}


def _pct(value, truth) -> float:
    return 100.0 * (value - truth) / truth


# ------------------------------------------------------------- 1. light pendulums
def light_system(fraction: float, damping: float):
    """A ``fraction`` x 2 kg point mass on a 0.3 m rod below a 2 kg cart with viscous
    damping ``damping`` (N s/m) on the cart; force on the cart only."""
    from lagsindy.systems import cart_pendulum

    system = cart_pendulum(CART_MASS, fraction * CART_MASS, POLE_LENGTH, G)
    return system.with_damping(viscous={"x": damping})


def _libraries(names):
    from lagsindy import CandidateLibrary

    out = {}
    for name in names:
        if name == "chain":
            out[name] = CandidateLibrary.chain(["x", "theta"], angles=["theta"])
        else:
            out[name] = CandidateLibrary.polynomial(
                ["x", "theta"], angles=["theta"], degree=3
            )
    return out


def _evaluate_cart(est, system, held, damping, stage) -> dict:
    """Pole terms, ratio, cart damping, other terms and held-out R^2 of one model."""
    coef = _terms(est)
    true = {
        str(n): float(c)
        for n, c in zip(est.term_names_, system.true_coefficients(est.library_))
        if c != 0
    }
    ratio_true = POLE_LENGTH / (2 * G)
    num, den = coef.get("theta_dot**2", 0.0), coef.get("cos(theta)", 0.0)
    ratio = num / den if den != 0 else float("nan")
    diss = _dissipation(est)
    b = diss.get("viscous(x)")
    other = [k for k in coef if k not in true]
    other += [k for k in diss if k != "viscous(x)"]
    try:
        r2 = r_squared(held.tau[:, 0], np.asarray(est.predict(held.X))[:, 0])
    except Exception:  # noqa: BLE001
        r2 = float("nan")
    return {
        "stage": stage,
        "pole_kept": sum(t in coef for t in POLE_TERMS),
        "cart_kept": "x_dot**2" in coef,
        "ratio": ratio,
        "ratio_error": _pct(ratio, ratio_true) if math.isfinite(ratio) else None,
        "b_found": b,
        "b_error": None if b is None else _pct(b, damping),
        "other": other,
        "coef_errors": {k: _pct(coef.get(k, 0.0), v) for k, v in true.items()},
        "r2": r2,
    }


def light_cell(task) -> list:
    """One light-pendulum cell (fraction, damping, amplitude, seed) for each library."""
    _one_thread()
    from lagsindy import LagrangianSINDy, diagnose
    from lagsindy.systems import make_dataset

    fraction, damping, amplitude, seed, n_traj, duration, libs = task
    system = light_system(fraction, damping)
    kw = dict(excitation="sincos", amplitude=amplitude, noise=1e-3, protocol="sensor")
    data = make_dataset(system, n_traj, duration, random_state=100 * seed + 1, **kw)
    held = make_dataset(
        system, max(3, n_traj // 4), duration, random_state=100 * seed + 2, **kw
    )
    rows = []
    for name, library in _libraries(libs).items():
        base = dict(
            fraction=fraction,
            damping=damping,
            amplitude=amplitude,
            seed=seed,
            library=name,
        )
        est = LagrangianSINDy(library)
        est, t_fit, w_fit, err, _ = _call(est.fit, data.X, data.tau, groups=data.groups)
        if est is None:
            rows.append({**base, "stage": "fit", "error": err, "time": t_fit})
            continue
        rows.append(
            {
                **base,
                **_evaluate_cart(est, system, held, damping, "fit"),
                "warnings": w_fit,
                "time": t_fit,
            }
        )
        rep, t_diag, w_diag, err, _ = _call(
            diagnose, est, data.X, data.tau, groups=data.groups
        )
        if rep is None:
            rows.append({**base, "stage": "diagnosed", "error": err, "time": t_diag})
            continue
        rows.append(
            {
                **base,
                **_evaluate_cart(rep.final, system, held, damping, "diagnosed"),
                "effects": rep.effects,
                "warnings": w_diag,
                "time": t_diag,
                "stop": rep.stop_reason[:100],
                "degenerate": len(rep.degenerate_folds),
            }
        )
    return rows


# ----------------------------------------------------------- 2. spherical pendulum
def spherical_theta_driven(damping: float = SPHERICAL_DAMPING):
    """The paper's spherical pendulum with viscous damping on theta, driven on theta
    only (input matrix ``[[1], [0]]``: phi is free)."""
    from lagsindy.systems import spherical_pendulum

    system = spherical_pendulum().with_damping(viscous={"theta": damping})
    system.input_matrix = np.array([[1.0], [0.0]])
    system.__dict__.pop("_equations", None)
    system.__dict__.pop("_compiled", None)
    system.name = f"spherical pendulum (viscous theta {damping}, driven on theta)"
    return system


def spherical_cell(task) -> list:
    """Fit + diagnose of the theta-driven damped spherical pendulum (paper library)."""
    _one_thread()
    from lagsindy import LagrangianSINDy, diagnose
    from lagsindy.systems import make_dataset

    seed, n_traj, duration = task
    system = spherical_theta_driven()
    kw = dict(excitation="sincos", amplitude=1.0, noise=1e-3, protocol="sensor")
    data = make_dataset(system, n_traj, duration, random_state=100 * seed + 3, **kw)
    held = make_dataset(
        system, max(3, n_traj // 4), duration, random_state=100 * seed + 4, **kw
    )
    assert np.all(data.tau[:, 1] == 0)  # phi undriven: a column of zeros
    rows = []
    base = dict(seed=seed)
    est = LagrangianSINDy(system.paper_library())
    est, t_fit, w_fit, err, _ = _call(est.fit, data.X, data.tau, groups=data.groups)
    if est is None:
        return [{**base, "stage": "fit", "error": err, "time": t_fit}]
    rep, t_diag, w_diag, err, _ = _call(
        diagnose, est, data.X, data.tau, groups=data.groups
    )
    for stage, model, extra in (
        ("fit", est, dict(warnings=w_fit, time=t_fit)),
        (
            "diagnosed",
            None if rep is None else rep.final,
            dict(
                warnings=w_diag,
                time=t_diag,
                error=err,
                effects=None if rep is None else rep.effects,
            ),
        ),
    ):
        if model is None:
            rows.append({**base, "stage": stage, **extra})
            continue
        coef = _terms(model)
        true = system.true_coefficients(model.library_)
        truth = {str(n): float(c) for n, c in zip(model.term_names_, true) if c != 0}
        diss = _dissipation(model)
        b = diss.get("viscous(theta)")
        rows.append(
            {
                **base,
                "stage": stage,
                **extra,
                "structure": set(coef) == set(truth),
                "missing": [k for k in truth if k not in coef],
                "extra": [k for k in coef if k not in truth],
                "b_found": b,
                "b_error": None if b is None else _pct(b, SPHERICAL_DAMPING),
                "dissipation": diss,
                "r2": r_squared(
                    held.tau[:, 0], np.asarray(model.predict(held.X))[:, 0]
                ),
            }
        )
    return rows


# ----------------------------------------------------- 3. a real-rig-like cart-pole
def _delay_note(stdout: str) -> str:
    found = re.findall(r"input delay (?:of )?(-?[\d.]+) ms", stdout)
    return found[0] if found else ""


def rig_cell(task) -> list:
    """The default path on simulated camera records, scored on held-out records."""
    _one_thread()
    from lagsindy import CandidateLibrary, LagrangianSINDy, diagnose, shift_input

    seed, n_records, duration, n_held, pole_mass, delay_true = task
    kw = dict(pole_mass=pole_mass, delay=delay_true)
    rec = camera_cartpole(n_records, duration, random_state=1000 + seed, **kw)
    held = camera_cartpole(n_held, duration, random_state=2000 + seed, **kw)
    X, tau, groups, t, notes = camera_pipeline(rec)
    Xh, tauh, gh, th, _ = camera_pipeline(held)
    truth = rig_truth_in_pixels(rec.truth)
    base = dict(
        seed=seed,
        pole_mass=pole_mass,
        delay=delay_true,
        rows=len(X),
        segments=len(np.unique(groups)),
        notes=notes,
    )
    # the ceiling: the true model on the same held-out derivatives, input shifted
    # by the true delay (and not shifted)
    reference = rig_model_in_pixels(rec.truth)
    tau_true = shift_input(tauh, th, delay_true, gh)
    f_true = reference.inverse_dynamics(Xh[:, :2], Xh[:, 2:4], Xh[:, 4:6])[:, 0]
    roll = rollouts(reference, Xh, tau_true, gh, th)
    rows = [
        {
            **base,
            "stage": "truth",
            "kept": list(CART_POLE_TERMS),
            "other": [],
            "mass_pd": 1.0,
            "r2": r_squared(tau_true[:, 0], f_true),
            "r2_unshifted": r_squared(tauh[:, 0], f_true),
            "delay_ms": 1000 * delay_true,
            "roll_theta": roll[0],
            "roll_x_px": roll[1],
            "roll_ok": roll[2],
            "hold_theta": roll[3],
            "time": 0.0,
        }
    ]
    library = CandidateLibrary.chain(["x", "theta"], angles=["theta"])
    est = LagrangianSINDy(library)
    est, t_fit, w_fit, err, _ = _call(est.fit, X, tau, groups=groups)
    if est is None:
        return rows + [{**base, "stage": "fit", "error": err, "time": t_fit}]
    rep, t_diag, w_diag, err, out = _call(
        diagnose, est, X, tau, groups=groups, verbose=1
    )
    for stage, model, extra in (
        ("fit", est, dict(warnings=w_fit, time=t_fit)),
        (
            "diagnosed",
            None if rep is None else rep.final,
            dict(
                warnings=w_diag,
                time=t_diag,
                error=err,
                effects=None if rep is None else rep.effects,
                delay_tried=_delay_note(out),
            ),
        ),
    ):
        if model is None:
            rows.append({**base, "stage": stage, **extra})
            continue
        delay = 0.0
        if stage == "diagnosed" and rep.steps and rep.effects[0] == "delay":
            delay = rep.steps[0].coefficient / 1000.0
        tau_h = shift_input(tauh, th, delay, gh) if delay else tauh
        coef = _terms(model)
        ratio = (
            coef.get("theta_dot**2", 0.0) / coef["cos(theta)"]
            if coef.get("cos(theta)")
            else float("nan")
        )
        mass = model.model_.mass_matrix(Xh[:, :2], Xh[:, 2:4])
        pd_share = float(np.mean(np.linalg.eigvalsh(mass)[:, 0] > 0))
        roll = rollouts(model, Xh, tau_h, gh, th)
        rows.append(
            {
                **base,
                "stage": stage,
                **extra,
                "kept": [k for k in CART_POLE_TERMS if k in coef],
                "other": [k for k in coef if k not in CART_POLE_TERMS],
                "coef_errors": {k: _pct(coef.get(k, 0.0), v) for k, v in truth.items()},
                "ratio_error": _pct(ratio, rec.truth["length"] / (2 * G))
                if math.isfinite(ratio)
                else None,
                "dissipation": _dissipation(model),
                "mass_pd": pd_share,
                "r2": r_squared(tau_h[:, 0], np.asarray(model.predict(Xh))[:, 0]),
                "delay_ms": 1000 * delay,
                "roll_theta": roll[0],
                "roll_x_px": roll[1],
                "roll_ok": roll[2],
                "hold_theta": roll[3],
            }
        )
    return rows


# ----------------------------------------------------------------------------- run
def _one_thread():
    import torch

    torch.set_num_threads(1)


def _run(fn, tasks, processes):
    if processes > 1 and len(tasks) > 1:
        with mp.get_context("spawn").Pool(processes) as pool:
            return [r for rows in pool.map(fn, tasks) for r in rows]
    return [r for task in tasks for r in fn(task)]


# ----------------------------------------------------------------------------- main
def sizes(quick: bool) -> dict:
    """Grid and sizes: full, ``--quick`` (smaller) or tiny (``LAGSINDY_BENCH_TINY``)."""
    if tiny():
        return dict(
            fractions=(0.05,),
            dampings=(3.0,),
            amplitudes=(5.0,),
            seeds=1,
            n_traj=4,
            duration=4.0,
            libs=("chain",),
            sph_traj=4,
            rig_records=2,
            rig_duration=6.0,
            rig_held=1,
            pole_masses=(0.05,),
            delays=(0.02,),
        )
    if quick:
        return dict(
            fractions=(0.01, 0.10),
            dampings=(3.0,),
            amplitudes=(1.0,),
            seeds=1,
            n_traj=10,
            duration=8.0,
            libs=("chain", "paper"),
            sph_traj=10,
            rig_records=6,
            rig_duration=10.0,
            rig_held=2,
            pole_masses=(0.05,),
            delays=(0.02,),
        )
    return dict(
        fractions=FRACTIONS,
        dampings=DAMPINGS,
        amplitudes=AMPLITUDES,
        seeds=3,
        n_traj=20,
        duration=8.0,
        libs=("chain", "paper"),
        sph_traj=20,
        rig_records=8,
        rig_duration=10.0,
        rig_held=3,
        pole_masses=(0.02, 0.05),
        delays=(0.015, 0.03),
    )


def code_commit() -> str:
    """Which lagsindy code ran: the checkout's HEAD, the last commit that changed
    ``lagsindy/`` and whether ``lagsindy/`` has uncommitted changes."""
    import subprocess
    from pathlib import Path

    root = str(Path(__file__).resolve().parent.parent)

    def git(*args):
        out = subprocess.run(
            ["git", "-C", root, *args], capture_output=True, text=True, timeout=30
        )
        return out.stdout.strip() if out.returncode == 0 else ""

    head = git("rev-parse", "--short", "HEAD")
    if not head:
        return "unknown (not a git checkout)"
    package = git("log", "-1", "--format=%h", "--", "lagsindy")
    dirty = git("status", "--porcelain", "--", "lagsindy")
    return f"checkout HEAD {head}; `lagsindy/` last changed in {package}" + (
        " (with uncommitted changes)" if dirty else ""
    )


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.undriven", description=__doc__.splitlines()[0]
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="fewer cells and seeds: results/undriven_quick.md",
    )
    parser.add_argument(
        "--scenarios",
        nargs="+",
        default=["light", "spherical", "rig"],
        choices=["light", "spherical", "rig"],
    )
    parser.add_argument("--seeds", type=int, default=None, help="seeds per cell")
    parser.add_argument(
        "--processes",
        type=int,
        default=1,
        help="worker processes (one torch thread each)",
    )
    args = parser.parse_args(argv)
    size = sizes(args.quick)
    seeds = range(args.seeds or size["seeds"])
    load_start = os.getloadavg()
    parts, timing = [], []

    def timed(label, fn, tasks):
        start, cpu = time.perf_counter(), time.process_time()
        rows = _run(fn, tasks, args.processes)
        wall = time.perf_counter() - start
        timing.append(
            f"{label}: {len(tasks)} cells, {wall:.0f} s wall"
            + ("" if args.processes > 1 else f", {time.process_time() - cpu:.0f} s CPU")
            + f", load average at its end {os.getloadavg()[0]:.1f}"
        )
        return rows

    if "light" in args.scenarios:
        tasks = [
            (f, b, a, s, size["n_traj"], size["duration"], size["libs"])
            for f in size["fractions"]
            for b in size["dampings"]
            for a in size["amplitudes"]
            for s in seeds
        ]
        rows = timed("light pendulums", light_cell, tasks)
        parts.append(
            "## 1. Light pendulums on damped carts\n\n"
            f"`cart_pendulum({CART_MASS:g}, m, {POLE_LENGTH:g})` with viscous cart "
            f'damping b, force on the cart only (`excitation="sincos"`, amplitude '
            f"in the table), {size['n_traj']} x {size['duration']:g} s at 100 Hz, "
            'noise 1e-3 on positions (`protocol="sensor"`), seeds '
            f"{list(seeds)}; held-out: {max(3, size['n_traj'] // 4)} more "
            "trajectories. `LagrangianSINDy(library).fit(X, tau, groups=groups)` then "
            "`diagnose(est, X, tau, groups=groups)`, defaults. True ratio "
            f"`theta_dot**2 / cos(theta)` = l / 2g = {POLE_LENGTH / (2 * G):.5f}.\n\n"
            + light_report(rows, size["libs"])
        )
    if "spherical" in args.scenarios:
        rows = timed(
            "spherical pendulum",
            spherical_cell,
            [(s, size["sph_traj"], size["duration"]) for s in seeds],
        )
        n_ok = sum(
            r.get("b_error") is not None and abs(r["b_error"]) <= 10
            for r in rows
            if r["stage"] == "diagnosed"
        )
        parts.append(
            "## 2. Spherical pendulum, damped theta, driven on theta only\n\n"
            f"`spherical_pendulum().with_damping(viscous={{'theta': "
            f"{SPHERICAL_DAMPING}}})` with input matrix `[[1], [0]]` (phi free; its "
            f"column of tau is zero), `sincos` amplitude 1, {size['sph_traj']} x "
            f"{size['duration']:g} s, noise 1e-3 on positions (`sensor`), the paper's "
            "library (`system.paper_library()`, separated, degree 2); fit + "
            f"`diagnose`, defaults. **`viscous(theta)` within 10 %: {n_ok} of "
            f"{len(list(seeds))} seeds.**\n\n" + spherical_report(rows)
        )
    if "rig" in args.scenarios:
        tasks = [
            (s, size["rig_records"], size["rig_duration"], size["rig_held"], m, d)
            for m in size["pole_masses"]
            for d in size["delays"]
            for s in seeds
        ]
        rows = timed("real-rig-like cart-pole", rig_cell, tasks)
        parts.append(
            "## 3. A real-rig-like cart-pole (camera, pixels, bang-bang voltage)\n\n"
            + rig_text(size)
            + "\n\n"
            + rig_report(rows)
        )
    load_end = os.getloadavg()
    text = header(
        "Undriven and light links (issue #41)", _common.command("undriven", argv)
    )
    text += f"Code: {code_commit()}.\n\n"
    text += (
        f"Load average (1, 5, 15 min) at the start: "
        f"{', '.join(f'{v:.1f}' for v in load_start)}; at the end: "
        f"{', '.join(f'{v:.1f}' for v in load_end)} ({os.cpu_count()} cores, "
        f"shared machine; {args.processes} worker process(es), one torch thread "
        "each). Times are wall-clock seconds under that load.\n\n"
        + "\n".join(f"- {t}" for t in timing)
        + "\n\n"
        + "\n\n".join(parts)
        + "\n"
    )
    write("undriven_quick.md" if args.quick else "undriven.md", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
