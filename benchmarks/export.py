"""Per-call cost of a model's forward dynamics: estimator vs exported code.

For the cart-pendulum and the triple pendulum (their true models, with viscous and
Coulomb friction on every coordinate, loaded from a model file as a fitted
estimator): the estimator's ``predict_acceleration`` (torch), the exported numpy
module (batched and one state per call), the exported C through ctypes (one call,
and one call of the C batch loop), the C measured inside C (a program that calls
the function in a loop; ``clock_gettime``), and CasADi (one call, and ``map``).
Every variant is first checked against the estimator (relative error reported).
Times are the minimum over repeats, on one thread.

    python -m benchmarks.export            # results/export.md
    python -m benchmarks.export --quick    # fewer states, results/export_quick.md
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from . import _common

SYSTEMS = ("cart_pendulum", "triple_pendulum")
VISCOUS, COULOMB = 0.15, 0.07


def _estimator(name: str, folder: Path):
    """The system's true model with friction, saved and loaded as an estimator."""
    from lagsindy import __version__, load_model
    from lagsindy.dissipation import make_term
    from lagsindy.io import expression_to_string
    from lagsindy.systems import SYSTEMS as ALL

    system = ALL[name]()
    coords = list(system.coordinates)
    terms = {t: c for t, c in system.terms().items() if t != "1"}
    dissipation = []
    for kind, value in (("viscous", VISCOUS), ("coulomb", COULOMB)):
        for c in coords:
            t = make_term(kind, c, coords)
            dissipation.append(
                {
                    "name": t.name,
                    "kind": t.kind,
                    "coordinates": list(t.coordinates),
                    "forces": [expression_to_string(f) for f in t.forces],
                    "rayleigh": None
                    if t.rayleigh is None
                    else expression_to_string(t.rayleigh),
                    "coefficient": value,
                }
            )
    doc = {
        "format": "lagsindy-model",
        "schema_version": 1,
        "lagsindy_version": __version__,
        "coordinates": coords,
        "terms": list(terms),
        "coefficients": list(terms.values()),
        "case": "forces",
        "fixed_term": None,
        "unpenalized": [],
        "hyperparameters": {},
        "n_features_in": 3 * len(coords),
        "feature_names_in": None,
        "tau_1d": False,
        "n_iter": 0,
        "residual": None,
        "dissipation": dissipation,
        "normalization": None,
    }
    path = folder / f"{name}.json"
    path.write_text(json.dumps(doc))
    return load_model(path)


def _best(fn, repeats: int, number: int) -> tuple[float, float]:
    """``(wall, cpu)`` seconds per call: each the minimum over ``repeats`` of
    ``number`` calls. The process's CPU time leaves out the time other jobs of a
    shared machine held the core."""
    wall = cpu = np.inf
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        for _ in range(number):
            fn()
        cpu = min(cpu, (time.process_time() - start_cpu) / number)
        wall = min(wall, (time.perf_counter() - start) / number)
    return wall, cpu


_TIMER = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "{name}.h"

static double now(clockid_t clock)
{{
    struct timespec t;
    clock_gettime(clock, &t);
    return t.tv_sec + 1e-9 * t.tv_nsec;
}}

int main(int argc, char **argv)
{{
    const int n = {n}, m = {m};
    long calls = argc > 1 ? atol(argv[1]) : 1000000;
    double x[64][2 * {n}], u[64][{m}], qdd[{n}], sink = 0.0, best = 1e30;
    double best_cpu = 1e30;
    srand(1);
    for (int s = 0; s < 64; ++s) {{
        for (int i = 0; i < 2 * n; ++i) x[s][i] = 4.0 * rand() / RAND_MAX - 2.0;
        for (int j = 0; j < m; ++j) u[s][j] = 2.0 * rand() / RAND_MAX - 1.0;
    }}
    for (int r = 0; r < 5; ++r) {{
        double start = now(CLOCK_MONOTONIC);
        double start_cpu = now(CLOCK_PROCESS_CPUTIME_ID);
        for (long k = 0; k < calls; ++k) {{
            {name}_forward_dynamics(x[k & 63], u[k & 63], qdd);
            sink += qdd[0];
        }}
        double per = (now(CLOCK_MONOTONIC) - start) / calls;
        double per_cpu = (now(CLOCK_PROCESS_CPUTIME_ID) - start_cpu) / calls;
        if (per < best) best = per;
        if (per_cpu < best_cpu) best_cpu = per_cpu;
    }}
    printf("%.6e %.6e %g\n", best, best_cpu, sink);
    return 0;
}}
"""


def _measure(name: str, folder: Path, sizes: dict) -> dict:
    import torch

    from lagsindy.export import (
        CModel,
        compile_c,
        export_model,
        find_compiler,
        load_python,
    )

    torch.set_num_threads(1)
    est = _estimator(name, folder)
    n = est.n_dof_
    rng = np.random.default_rng(0)
    big = sizes["batch"]
    x = rng.uniform(-2.0, 2.0, (big, 2 * n))
    u = rng.uniform(-1.0, 1.0, (big, n))
    X = np.concatenate([x, np.zeros((big, n))], axis=1)
    check = slice(0, 1000)
    reference = est.predict_acceleration(X[check], u[check])

    def error(values):
        values = np.asarray(values).reshape(-1, n)
        scale = np.abs(reference).max(axis=1)
        return float((np.abs(values - reference).max(axis=1) / scale).max())

    rows = []
    reps = sizes["repeats"]
    est_n = sizes["estimator_batch"]
    t = _best(lambda: est.predict_acceleration(X[:est_n], u[:est_n]), reps, 1)
    rows.append(
        (
            "estimator `predict_acceleration`, batch",
            (t[0] / est_n, t[1] / est_n),
            est_n,
            0.0,
        )
    )
    t = _best(
        lambda: est.predict_acceleration(X[:1], u[:1]), reps, sizes["single"] // 10
    )
    rows.append(("estimator, one state per call", t, 1, 0.0))

    py_path = export_model(est, folder / f"{name}_py.py")
    module = load_python(py_path.read_text(), name)
    err = error(module.forward_dynamics(x[check], u[check]))
    t = _best(lambda: module.forward_dynamics(x, u), reps, 1)
    rows.append(("exported numpy, batch", (t[0] / big, t[1] / big), big, err))
    one = [module.forward_dynamics(x[i], u[i]) for i in range(1000)]
    t = _best(lambda: module.forward_dynamics(x[7], u[7]), reps, sizes["single"])
    rows.append(("exported numpy, one state per call", t, 1, error(one)))

    c_note = "no C compiler"
    if find_compiler() is not None:
        c_file, _ = export_model(est, folder / f"{name}.c")
        model = CModel(compile_c(c_file), name)
        err = error(model.forward_dynamics(x[check], u[check]))
        f = model.functions["forward_dynamics"]
        xs, us, out = x[7].copy(), u[7].copy(), np.empty(n)
        px, pu, po = xs.ctypes.data, us.ctypes.data, out.ctypes.data
        t = _best(lambda: f(px, pu, po), reps, sizes["single"])
        rows.append(("C via ctypes, one call", t, 1, err))
        t = _best(lambda: model.forward_dynamics(x, u), reps, 1)
        rows.append(
            ("C via ctypes, the C batch loop", (t[0] / big, t[1] / big), big, err)
        )
        timer = folder / f"{name}_timer.c"
        timer.write_text(_TIMER.format(name=name, n=n, m=n))
        exe = folder / f"{name}_timer"
        cmd = [find_compiler(), "-O2", "-o", str(exe), str(timer), str(c_file), "-lm"]
        subprocess.run(cmd, check=True, capture_output=True, cwd=folder)
        done = subprocess.run(
            [str(exe), str(sizes["c_calls"])],
            check=True,
            capture_output=True,
            text=True,
        )
        rows.append(
            (
                "C inside C, one call (loop of calls)",
                tuple(float(v) for v in done.stdout.split()[:2]),
                1,
                err,
            )
        )
        c_note = ""

    ca_note = "CasADi not installed"
    if importlib.util.find_spec("casadi") is not None:
        from lagsindy.export import to_casadi

        f = to_casadi(est)
        mapped = f.forward_dynamics.map(1000)
        err = error(np.array(mapped(x[check].T, u[check].T)).T)
        xs, us = x[7].copy(), u[7].copy()
        t = _best(lambda: f.forward_dynamics(xs, us), reps, sizes["single"] // 10)
        rows.append(("CasADi `Function`, one call", t, 1, err))
        k = sizes["casadi_batch"]
        mapped = f.forward_dynamics.map(k)
        xt, ut = np.ascontiguousarray(x[:k].T), np.ascontiguousarray(u[:k].T)
        t = _best(lambda: mapped(xt, ut), reps, 1)
        rows.append(("CasADi `map`, batch", (t[0] / k, t[1] / k), k, err))
        ca_note = ""
    return {"rows": rows, "notes": [v for v in (c_note, ca_note) if v]}


def _time(seconds: float) -> str:
    if seconds < 1e-5:
        return f"{seconds * 1e9:.0f} ns"
    if seconds < 1e-2:
        return f"{seconds * 1e6:.1f} us"
    return f"{seconds * 1e3:.1f} ms"


def _table(name: str, result: dict) -> list:
    lines = [
        f"## {name.replace('_', ' ')} (with viscous and Coulomb friction)\n",
        "| variant | CPU per state | states/s (CPU) | wall per state | batch "
        "| max rel. error vs estimator |",
        "|---|---|---|---|---|---|",
    ]
    for label, (wall, cpu), batch, err in result["rows"]:
        ref = "(reference)" if label.startswith("estimator") else f"{err:.1e}"
        lines.append(
            f"| {label} | {_time(cpu)} | {1.0 / cpu:.3g} | {_time(wall)} | {batch} "
            f"| {ref} |"
        )
    lines += [f"\n{note}." for note in result["notes"]]
    return lines + [""]


def _targets(results: dict) -> list:
    """The issue's targets against the measurements (CPU time, then wall)."""
    lines = [
        "## Targets\n",
        "| target | system | CPU | wall | met (CPU / wall) |",
        "|---|---|---|---|---|",
    ]
    checks = (
        ("C single call under 2 us, inside C", "C inside C", 2e-6, True),
        (
            "C single call under 2 us, from Python (ctypes)",
            "C via ctypes, one",
            2e-6,
            True,
        ),
        ("numpy batched over 1e6 states/s", "exported numpy, batch", 1e-6, False),
    )
    for label, prefix, limit, is_time in checks:
        for name, result in results.items():
            row = next((r for r in result["rows"] if r[0].startswith(prefix)), None)
            if row is None:
                continue
            wall, cpu = row[1]
            shown = [_time(v) if is_time else f"{1.0 / v:.3g}/s" for v in (cpu, wall)]
            met = ["yes" if v < limit else "no" for v in (cpu, wall)]
            lines.append(
                f"| {label} | {name.replace('_', ' ')} | {shown[0]} | {shown[1]} "
                f"| {met[0]} / {met[1]} |"
            )
    return lines + [""]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer states and calls")
    parser.add_argument("--out", default=None, help="output file")
    args = parser.parse_args(argv)
    sizes = (
        {
            "batch": 20_000,
            "estimator_batch": 2_000,
            "single": 200,
            "repeats": 2,
            "c_calls": 20_000,
            "casadi_batch": 2_000,
        }
        if args.quick
        else {
            "batch": 1_000_000,
            "estimator_batch": 100_000,
            "single": 20_000,
            "repeats": 5,
            "c_calls": 2_000_000,
            "casadi_batch": 100_000,
        }
    )
    out = (
        Path(args.out)
        if args.out
        else _common.RESULTS / ("export_quick.md" if args.quick else "export.md")
    )
    import torch

    torch.set_num_threads(1)  # before the header, which states the threads
    load = os.getloadavg()[0]
    lines = [
        _common.header(
            "Forward dynamics per call: estimator vs exported code",
            _common.command("export", argv if argv is not None else sys.argv[1:]),
        ),
        f"Load average (1 min) at the start: {load:.2f} on {os.cpu_count()} cores "
        "(a shared machine: other jobs ran beside this one). One thread "
        "(torch.set_num_threads(1); numpy's elementwise code is single-threaded). "
        "Times are the minimum over repeats of the process's CPU time (what one "
        "core spends, without the time other jobs held it) and of the wall-clock "
        "time; 'one call' is the cost of one state. "
        "The C library is built with `cc -O2 -shared -fPIC`; 'C inside C' is a "
        "program calling the function in a loop over 64 states. Where the "
        "machine is loaded, wall-clock times exceed CPU times by the load's "
        "share of the cores.\n",
    ]
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in SYSTEMS:
            results[name] = _measure(name, Path(tmp), sizes)
            print("\n".join(_table(name, results[name])))
    lines += _targets(results)
    for name in SYSTEMS:
        lines += _table(name, results[name])
    lines.append(f"Load average (1 min) at the end: {os.getloadavg()[0]:.2f}.\n")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
