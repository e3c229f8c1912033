"""Fit time of LagrangianSINDy (case I, Gram-matrix FISTA).

Default: the cart-pendulum, 100 trajectories x 500 samples, the paper's 55-term
library, active (forced) data; the median of 5 fits after one warm-up fit (the first
fit in a process also pays torch's lazy imports, reported separately).

Then how the cost grows: fit time and peak memory against the number of samples
(1e3 .. 1e6 rows, the paper's cart library) and against the library size (cart
polynomial libraries of degree 2 .. 5: 14 .. 169 terms), each measurement in its own
process so that its peak resident memory (``resource.getrusage`` ``ru_maxrss``) is its
own; a plot in ``results/speed.png``. On a machine with CUDA the same fits also run
with ``device="cuda"`` and the speed-up is reported.

    python -m benchmarks.speed            # writes benchmarks/results/speed.md
    python -m benchmarks.speed --quick    # smaller, for a smoke check
    python -m benchmarks.speed --ratios   # only the passive-search / diagnosis
                                          # section (replaced in speed.md)
    python -m benchmarks.speed --fit-only     # only its (a) fits and (b) memory
    python -m benchmarks.speed --floor-fits   # only the fit / Gram floor rows
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time

import numpy as np

from lagsindy import CandidateLibrary, LagrangianSINDy
from lagsindy.systems import cart_pendulum, make_dataset

from . import _common
from ._common import command, header, write
from ._evaluate import tiny


def time_fits(X, tau, library, repeats):
    times = []
    est = None
    for _ in range(repeats):
        est = LagrangianSINDy(library)
        start = time.perf_counter()
        est.fit(X, tau)
        times.append(time.perf_counter() - start)
    return times, est


def random_rows(system, n_rows, seed=0):
    """Case I rows at random states: ``[q, qdot, qddot]`` and ``tau``.

    Case I treats rows as independent samples, so for the scaling study the rows are
    drawn at random (x ~ U(-1, 1), theta ~ U(-pi, pi), velocities ~ U(-2, 2), force
    on the cart ~ U(-1, 1)) with exact accelerations from the equations of motion,
    rather than integrated as trajectories (the fit cost does not depend on how the
    rows were made; the simulation of 2,000 trajectories would).
    """
    rng = np.random.default_rng(seed)
    n = system.n_dof
    q = np.column_stack(
        [rng.uniform(-1, 1, n_rows), rng.uniform(-math.pi, math.pi, n_rows)]
    )
    qd = rng.uniform(-2, 2, (n_rows, n))
    u = rng.uniform(-1, 1, (n_rows, system.n_inputs))
    tau = u @ system.input_matrix.T
    X = system.trajectory_to_X(np.concatenate([q, qd], axis=1), tau)
    return X, tau


def _rss_kib():
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024


def measure(spec):
    """One measurement (run in a fresh process): median fit time and memory."""
    import resource

    import torch

    system = cart_pendulum()
    library = CandidateLibrary.polynomial(
        ["x", "theta"], angles=["theta"], degree=spec["degree"]
    )
    library.build()
    X, tau = random_rows(system, spec["n_rows"])
    device = spec["device"]
    # Warm-up on a small slice: torch's lazy imports and kernel set-up are not the fit.
    LagrangianSINDy(library, device=device).fit(X[:2000], tau[:2000])
    if device == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    rss_before = _rss_kib()
    peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    times, cpu, est = [], [], None
    for _ in range(spec["repeats"]):
        est = LagrangianSINDy(library, device=device)
        start, start_cpu = time.perf_counter(), time.process_time()
        est.fit(X, tau)
        if device == "cuda":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    # KiB on Linux. The kernel updates ru_maxrss lazily, so it can trail the current
    # size read from /proc by a few pages: the peak is at least either reading.
    peak = max(
        resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, rss_before, _rss_kib()
    )
    return {
        **spec,
        "n_terms": len(library),
        "time": statistics.median(times),
        "times": times,
        "cpu": statistics.median(cpu),
        "cpus": cpu,
        "threads": torch.get_num_threads(),
        "rss_before_mib": rss_before / 1024,
        "peak_rss_mib": peak / 1024,
        "peak_before_mib": peak_before / 1024,
        "cuda_peak_mib": (
            torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else None
        ),
        "n_iter": est.n_iter_,
        "correct": sorted(est.term_names_[est.support_].tolist())
        == sorted(
            ["theta_dot**2", "theta_dot*x_dot*cos(theta)", "x_dot**2", "cos(theta)"]
        ),
    }


def run_measurement(spec, timeout=1800):
    """Run :func:`measure` in a fresh interpreter; its result (or an error)."""
    cmd = [sys.executable, "-m", "benchmarks.speed", "--_measure", json.dumps(spec)]
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        out = subprocess.run(
            cmd, capture_output=True, text=True, timeout=timeout, cwd=root
        )
    except subprocess.TimeoutExpired:
        return {**spec, "error": f"no result within {timeout} s"}
    if out.returncode != 0:
        return {
            **spec,
            "error": out.stderr.strip().splitlines()[-1]
            if out.stderr
            else f"exit {out.returncode}",
        }
    return json.loads(out.stdout.strip().splitlines()[-1])


def scaling(quick):
    """Fit time and memory against samples and library size (CPU, and CUDA)."""
    import torch

    if tiny():
        sizes, degrees, repeats = [1000], [2], 1
    elif quick:
        sizes, degrees, repeats = [1000, 10_000], [2, 3], 1
    else:
        sizes, degrees, repeats = [1000, 10_000, 100_000, 1_000_000], [2, 3, 4, 5], 3
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    rows_sweep, lib_sweep = [], []
    for device in devices:
        for n in sizes:
            res = run_measurement(
                {"n_rows": n, "degree": 3, "device": device, "repeats": repeats}
            )
            rows_sweep.append(res)
            print("samples", res, flush=True)
        lib_rows = sizes[1] if len(sizes) > 1 else sizes[0]
        for d in degrees:
            res = run_measurement(
                {"n_rows": lib_rows, "degree": d, "device": device, "repeats": repeats}
            )
            lib_sweep.append(res)
            print("library", res, flush=True)
    return rows_sweep, lib_sweep, devices


def _row(res, key):
    if "error" in res:
        return (
            f"| {res[key]} | {res['device']} | - | - | - | - | - | "
            f"error: {res['error']} |\n"
        )
    return (
        f"| {res[key] if key == 'n_rows' else res['n_terms']} | {res['device']} | "
        f"{res['time']:.3g} s | {res['threads']} | {res['rss_before_mib']:.0f} MiB "
        f"(peak so far {res['peak_before_mib']:.0f} MiB) | "
        f"{res['peak_rss_mib']:.0f} MiB"
        + (f" (GPU {res['cuda_peak_mib']:.0f} MiB)" if res.get("cuda_peak_mib") else "")
        + f" | {res['n_iter']} | {'yes' if res['correct'] else 'no'} |\n"
    )


def scaling_text(rows_sweep, lib_sweep, devices, plot_name):
    import torch

    head = (
        "| {} | device | median fit time | torch threads | RSS before the fits | "
        "peak RSS | FISTA iterations | true structure |\n"
        "|---|---|---|---|---|---|---|---|\n"
    )
    text = "\n## How the cost grows (case I, cart-pendulum)\n\n"
    text += (
        "Each row is a fresh process (`python -m benchmarks.speed --_measure ...`): "
        "the "
        "data are made, the library built and one small warm-up fit run, then the "
        "median of the timed fits is reported. Rows are random states with exact "
        "accelerations (see `random_rows`). Memory is the process's peak resident set "
        "size from `resource.getrusage(RUSAGE_SELF).ru_maxrss` (psutil is not used; "
        "tracemalloc does not see torch's allocations); it includes Python, torch and "
        "the data, so compare it with the resident size measured just before the "
        "fits (and with the process's peak up to then: imports, data and the "
        "warm-up fit; when the final peak equals it, the timed fits did not raise "
        "it).\n\n"
    )
    text += "### Against the number of samples (library of degree 3: 39 terms)\n\n"
    text += head.format("rows")
    text += "".join(_row(r, "n_rows") for r in rows_sweep)
    lib_rows = lib_sweep[0]["n_rows"] if lib_sweep else 0
    text += (
        f"\n### Against the library size ({lib_rows} rows; cart polynomial "
        "libraries of increasing degree)\n\n"
    )
    text += head.format("terms")
    text += "".join(_row(r, "degree") for r in lib_sweep)
    if "cuda" in devices:
        text += (
            "\n### GPU speed-up (CPU time / CUDA time)\n\n"
            "| sweep | size | speed-up |\n|---|---|---|\n"
        )
        for name, sweep, key in (
            ("rows", rows_sweep, "n_rows"),
            ("terms", lib_sweep, "degree"),
        ):
            cpu = {
                r[key]: r for r in sweep if r["device"] == "cpu" and "error" not in r
            }
            for r in sweep:
                if r["device"] == "cuda" and "error" not in r and r[key] in cpu:
                    text += (
                        f"| {name} | "
                        f"{r['n_rows'] if key == 'n_rows' else r['n_terms']} | "
                        f"{cpu[r[key]]['time'] / r['time']:.2f}x |\n"
                    )
        text += f"\nGPU: {torch.cuda.get_device_name(0)}.\n"
    else:
        text += (
            "\nGPU: no GPU (`torch.cuda.is_available()` is False), "
            "so no CUDA timings.\n"
        )
    text += f"\n![fit time]({plot_name})\n"
    return text


def plot(rows_sweep, lib_sweep, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, sweep, key, label in (
        (axes[0], rows_sweep, "n_rows", "rows (samples)"),
        (axes[1], lib_sweep, "n_terms", "library terms"),
    ):
        for device in sorted({r["device"] for r in sweep}):
            pts = [
                (r[key], r["time"])
                for r in sweep
                if r["device"] == device and "error" not in r
            ]
            if pts:
                xs, ys = zip(*pts)
                ax.loglog(xs, ys, "o-", label=device)
        ax.set_xlabel(label)
        ax.set_ylabel("median fit time (s)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    axes[0].set_title("case I, cart-pendulum, 39 terms")
    axes[1].set_title("case I, cart-pendulum")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ----------------------------------------------------------------- hardware floor
FLOOR_CASES = [(200_000, 5), (50_000, 3)]  # (rows, cart library degree): 169, 39 terms
SIMULATION_SECONDS = 25.0


def measure_floor(spec):
    """Fit time against the Gram floor, in one process (run by :func:`floor_table`).

    The floor is one float64 ``A.T @ A`` of the regression tensor's size (``n_rows *
    n_dof`` rows, ``n_terms + 1`` columns), the least work a Gram-based fit can do.
    """
    import torch

    system = cart_pendulum()
    library = CandidateLibrary.polynomial(
        ["x", "theta"], angles=["theta"], degree=spec["degree"]
    )
    library.build()
    X, tau = random_rows(system, spec["n_rows"])
    LagrangianSINDy(library).fit(X[:2000], tau[:2000])  # warm-up
    a = torch.randn(X.shape[0] * system.n_dof, len(library) + 1, dtype=torch.float64)
    floors, fits, floor_cpu, fit_cpu = [], [], [], []
    load = [_load()]
    for _ in range(spec["repeats"]):
        start, start_cpu = time.perf_counter(), time.process_time()
        a.T @ a
        floors.append(time.perf_counter() - start)
        floor_cpu.append(time.process_time() - start_cpu)
        start, start_cpu = time.perf_counter(), time.process_time()
        LagrangianSINDy(library).fit(X, tau)
        fits.append(time.perf_counter() - start)
        fit_cpu.append(time.process_time() - start_cpu)
    load.append(_load())
    import lagsindy

    return {
        **spec,
        "lagsindy": os.path.dirname(lagsindy.__file__),
        "n_terms": len(library),
        "floor": statistics.median(floors),
        "fit": statistics.median(fits),
        "floors": floors,
        "fits": fits,
        "floor_cpu": floor_cpu,
        "fit_cpu": fit_cpu,
        "load": load,
        "threads": torch.get_num_threads(),
    }


FLOOR_FITS_MARKER = "\n### Fit against the Gram floor, remeasured"


def floor_fits_section(baseline=None, repeats=3, quick=False, processes=2, argv=None):
    """Markdown: only the fit / Gram floor rows of the floor section (``--floor-fits``).

    Each row is one fresh process timing the floor and the fit alternately
    (:func:`measure_floor`); best and median of ``repeats``, wall and CPU time,
    and the load average when the process started and ended.
    """
    cases = [(20_000, 3)] if quick or tiny() else FLOOR_CASES
    processes = 1 if quick or tiny() else processes
    load_start = _load()
    lines = [
        FLOOR_FITS_MARKER.strip("\n") + " (issue 16)",
        "",
        f"Command `{command('speed', argv)}`, {_common.machine()}. Each row is one "
        f"fresh process that times the floor (one float64 `A.T @ A` of the "
        "regression tensor's size) and the default case I fit on the same rows, "
        f"alternately, {repeats} times; ratios of the best times (of the medians "
        "in brackets). Load average (1 min) when each process started / ended.",
        "",
        "| rows x terms | code | process | floor wall | fit wall | fit / floor "
        "(medians) | floor CPU | fit CPU | fit / floor CPU | load |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for n_rows, degree in cases:
        spec = {"n_rows": n_rows, "degree": degree, "repeats": repeats}
        for k in range(processes):
            for label, root in _codes(baseline):
                r = _run_in(spec, "floor", root)
                print("floor fits", label, r, flush=True)
                if "error" in r:
                    lines.append(
                        f"| {n_rows} x deg {degree} | {label} | #{k + 1} | "
                        f"error: {r['error']} | - | - | - | - | - | - |"
                    )
                    continue
                fl, fi = min(r["floors"]), min(r["fits"])
                fl_c, fi_c = min(r["floor_cpu"]), min(r["fit_cpu"])
                lines.append(
                    f"| {n_rows} x {r['n_terms']} | {label} | #{k + 1} | "
                    f"{fl:.3g} s | {fi:.3g} s | **{fi / fl:.1f}** "
                    f"({r['fit'] / r['floor']:.1f}) | {fl_c:.3g} s | {fi_c:.3g} s | "
                    f"{fi_c / fl_c:.1f} | {r['load'][0]:.1f} / {r['load'][1]:.1f} |"
                )
    lines += [
        "",
        "Targets: 200k x 169 fit <= 5x the floor (same process); 50k x 39 fit "
        f"<= 0.1 s. Load average (1 min) {load_start:.1f} at the start, "
        f"{_load():.1f} at the end, on {os.cpu_count()} cores.",
        "",
    ]
    return "\n".join(lines)


def _replace_subsection(old_text, section, marker, parent):
    """``old_text`` with the ``### `` subsection at ``marker`` replaced by ``section``.

    The subsection runs to the next ``### `` or ``## `` heading. Without it,
    ``section`` goes before the first ``### `` heading of the ``## `` section at
    ``parent`` (or at that section's end; or at the end of the text).
    """
    if marker in old_text:
        head, rest = old_text.split(marker, 1)
        stops = [i for i in (rest.find("\n### "), rest.find("\n## ")) if i >= 0]
        tail = rest[min(stops) :] if stops else ""
        return head.rstrip("\n") + "\n\n" + section.strip("\n") + "\n" + tail
    if parent not in old_text:
        return old_text.rstrip("\n") + "\n\n" + section
    head, rest = old_text.split(parent, 1)
    stops = [i for i in (rest.find("\n### "), rest.find("\n## ")) if i >= 0]
    at = min(stops) if stops else len(rest)
    return (
        head
        + parent
        + rest[:at].rstrip("\n")
        + "\n\n"
        + section.strip("\n")
        + "\n"
        + rest[at:]
    )


def measure_simulation(spec):
    """Seconds to simulate the cart-pendulum under a sampled 1 kHz random input."""
    system = cart_pendulum()
    t = np.arange(0.0, spec["seconds"], 1e-3)
    u = np.random.default_rng(0).normal(size=(t.size, system.n_inputs))
    start = time.perf_counter()
    system.simulate([0.1, 0.2, 0.0, 0.0], t, u)
    return {**spec, "time": time.perf_counter() - start}


def _run_in(spec, kind, code_root=None, timeout=1800):
    """Run one ``--_<kind>`` measurement in a fresh interpreter.

    ``code_root``: import lagsindy from that checkout instead (for before/after).
    """
    return _common.run_in("speed", f"--_{kind}", spec, code_root, timeout)


def _codes(baseline):
    """``(label, code root)`` of the code measured: this checkout, then ``baseline``."""
    return [("after", None)] + ([("before", baseline)] if baseline else [])


def _commit(path):
    try:
        out = subprocess.run(
            ["git", "-C", path, "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
        )
        return out.stdout.strip() or "unknown"
    except OSError:
        return "unknown"


def _load():
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


def floor_section(baseline=None, repeats=3, quick=False):
    """Markdown: fit / Gram floor, simulation time and 1M-row memory (new and before)."""
    cases = [(20_000, 3)] if quick or tiny() else FLOOR_CASES
    sim_new = 0.5 if quick or tiny() else SIMULATION_SECONDS
    load_before = _load()
    lines = [
        "\n## At the hardware floor (issue 16)\n",
        "Each row is one fresh process that times the Gram floor (one float64 "
        "`A.T @ A` of the regression tensor's size: rows x dof by terms + 1) and the "
        "case I fit on the same rows, alternately, median of "
        f"{repeats}; the ratio is what counts on a shared machine. "
        + (
            f"'before' runs the same measurement with lagsindy imported from "
            f"`{baseline}` (commit {_commit(baseline)}), in the same run."
            if baseline
            else ""
        )
        + "\n",
        "| rows x terms | code | Gram floor | fit | fit / floor | torch threads |",
        "|---|---|---|---|---|---|",
    ]
    for n_rows, degree in cases:
        spec = {"n_rows": n_rows, "degree": degree, "repeats": repeats}
        for label, root in _codes(baseline):
            r = _run_in(spec, "floor", root)
            print("floor", label, r, flush=True)
            if "error" in r:
                lines.append(
                    f"| {n_rows} x deg {degree} | {label} | - | - | - | error: {r['error']} |"
                )
                continue
            lines.append(
                f"| {n_rows} x {r['n_terms']} | {label} | {r['floor']:.3g} s | "
                f"{r['fit']:.3g} s | **{r['fit'] / r['floor']:.1f}** | {r['threads']} |"
            )
    lines += [
        "",
        "Targets: 200k x 169 fit <= 5x the floor; 50k x 39 fit <= 0.1 s (absolute "
        "times depend on the load below).",
        "",
        "### Simulation with a sampled 1 kHz input (cart-pendulum, random input)",
        "",
        "| simulated | code | wall time |",
        "|---|---|---|",
    ]
    sims = [("after", None, sim_new), ("after", None, 0.5)]
    if baseline:
        sims.append(("before", baseline, 0.5))  # the old code needs ~20 s per 1 s
    for label, root, seconds in sims:
        r = _run_in({"seconds": seconds}, "simulate", root)
        print("simulate", label, r, flush=True)
        value = r.get("error") or f"{r['time']:.3g} s"
        lines.append(f"| {seconds:g} s | {label} | {value} |")
    lines += ["", f"Target: {SIMULATION_SECONDS:g} s simulated in <= 5 s.", ""]
    if not (quick or tiny()):
        lines += [
            "### Memory: 1M rows x 169 terms on CPU",
            "",
            "| rows x terms | median fit time | RSS before the fits | peak RSS |",
            "|---|---|---|---|",
        ]
        if _load() > 2 * (os.cpu_count() or 1):
            lines.append("| - | skipped: machine too loaded | - | - |")
        else:
            r = run_measurement(
                {"n_rows": 1_000_000, "degree": 5, "device": "cpu", "repeats": 1}
            )
            print("memory", r, flush=True)
            if "error" in r:
                lines.append(f"| 1000000 x 169 | error: {r['error']} | - | - |")
            else:
                lines.append(
                    f"| 1000000 x {r['n_terms']} | {r['time']:.3g} s | "
                    f"{r['rss_before_mib']:.0f} MiB | **{r['peak_rss_mib']:.0f} MiB** |"
                )
        lines += ["", "Target: under 2 GB (2048 MiB) peak.", ""]
    lines += [
        f"Load average (1 min) at the start: {load_before:.1f}, at the end: "
        f"{_load():.1f}, on {os.cpu_count()} cores (other jobs shared the machine).",
        "",
        "GPU: none on this machine, so no GPU figures (the targets of 1M rows x 169 "
        "terms <= 0.3 s and 4M rows <= 1 s on an H100 are not measured here; the "
        "batched kernels follow the input's device, and `tests/test_batched.py` has a "
        "`gpu` test of a CUDA fit).",
        "",
    ]
    return "\n".join(lines)


# ------------------------------------------------- passive search and diagnosis
RATIOS_MARKER = "\n## Passive search and diagnosis against one fit"
# Functions whose cumulative CPU time the profile of one passive search reports:
# (label, file suffix or suffixes, function names).
SEARCH_STEPS = [
    ("whole fit", "lagsindy/estimator.py", ("fit",)),
    ("Gram statistics (weak form)", "formulation/__init__.py", ("gram_statistics",)),
    (
        "- of which the noise correction",
        ("formulation/weak_integrals.py", "formulation/testfunctions.py"),
        ("_noise_sensitivities", "_noise_block"),
    ),
    ("case III search (`fit_fixed`)", "cases/fixed.py", ("fit_fixed",)),
    (
        "- sparse solves: ranking + shortlist",
        "cases/sparse.py",
        ("solve", "solve_many"),
    ),
    (
        "- - of which staged FISTA runs (one by one, batched)",
        "solvers/staged.py",
        ("staged_fista", "staged_fista_batch"),
    ),
    ("- - of which dense bounds (eigh)", "formulation/scaling.py", ("dense_residual",)),
    ("- mass normalization", "cases/fixed.py", ("solve_mass",)),
    (
        "- acceleration scoring of the shortlist",
        "cases/fixed.py",
        ("acceleration_r2", "acceleration_r2s"),
    ),
    ("mass-matrix check of the result", "lagsindy/model.py", ("checked_mass",)),
]

# The same for one ``diagnose`` of the case I model.
DIAGNOSE_STEPS = [
    ("whole diagnose", "diagnostics/search.py", ("diagnose",)),
    (
        "weak Gram statistics, every call",
        "formulation/weak_integrals.py",
        ("weak_grams",),
    ),
    (
        "- of which the noise correction",
        ("formulation/weak_integrals.py", "formulation/testfunctions.py"),
        ("_noise_sensitivities", "_noise_block"),
    ),
    (
        "fold statistics (`diagnostics.scoring` constructors)",
        "diagnostics/scoring.py",
        ("__init__",),
    ),
    ("refits from rows (`LagrangianSINDy.fit`)", "lagsindy/estimator.py", ("fit",)),
    # every estimate goes through ``_estimate_delay`` (diagnose calls it directly)
    (
        "input delay search (`estimate_delay`)",
        "lagsindy/delay.py",
        ("_estimate_delay",),
    ),
    (
        "- of which its least squares (`_fold_scores`, one per fold)",
        "lagsindy/delay.py",
        ("_fold_scores",),
    ),
    ("candidate catalogue (`_catalogue`)", "diagnostics/catalogue.py", ("_catalogue",)),
]


def _timed(fn):
    start, start_cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - start, time.process_time() - start_cpu


def _profile_steps(fn, steps=None):
    """CPU seconds and calls of ``steps`` (default :data:`SEARCH_STEPS`) in one
    profiled call of ``fn``."""
    import cProfile
    import pstats

    prof = cProfile.Profile(time.process_time)
    prof.enable()
    fn()
    prof.disable()
    stats = pstats.Stats(prof).stats
    found = []
    for label, suffix, names in SEARCH_STEPS if steps is None else steps:
        calls, seconds = 0, 0.0
        for (path, _, name), (_, ncalls, _, cumtime, _) in stats.items():
            if name in names and path.replace("\\", "/").endswith(suffix):
                calls += ncalls
                seconds += cumtime
        found.append((label, calls, seconds))
    return found


def measure_ratios(spec):
    """Case I fit, case III (fixed term, search) and ``diagnose``, in one process.

    The cart-pendulum with the paper's library: ``n_trajectories`` forced (sincos)
    and as many passive trajectories (``make_dataset``, seed 0), fitted with the
    estimator's defaults (``formulation="auto"``: the weak form) and ``groups``.
    Every run (the four fits, then ``diagnose`` of the case I model and of the
    search's model just fitted) alternates, ``repeats`` times; the best (smallest)
    wall and CPU (``time.process_time``) time of each, since on a shared machine
    the load only ever adds time. Then a profile of the passive search (the less
    disturbed of two profiled runs).
    """
    import warnings

    import torch

    from lagsindy import diagnose

    warnings.simplefilter("ignore")
    system = cart_pendulum()
    library = system.paper_library()
    n = spec["n_trajectories"]
    forced = make_dataset(system, n_trajectories=n, excitation="sincos", random_state=0)
    passive = make_dataset(system, n_trajectories=n, excitation=None, random_state=0)
    LagrangianSINDy(library).fit(forced.X[:1000], forced.tau[:1000])  # warm-up
    fits = {
        "case I": lambda: LagrangianSINDy(library).fit(
            forced.X, forced.tau, groups=forced.groups
        ),
        "case I, strong form": lambda: LagrangianSINDy(
            library, formulation="strong"
        ).fit(forced.X, forced.tau),
        "case III, fixed term": lambda: LagrangianSINDy(
            library, fixed_term=system.fixed_term
        ).fit(passive.X, groups=passive.groups),
        "case III, search": lambda: LagrangianSINDy(library).fit(
            passive.X, groups=passive.groups
        ),
    }
    models = {}
    runs = dict(fits)
    if spec.get("diagnose", True):
        runs["diagnose, case I model"] = lambda: diagnose(
            models["case I"], forced.X, forced.tau, groups=forced.groups
        )
        runs["diagnose, searched passive model"] = lambda: diagnose(
            models["case III, search"], passive.X, groups=passive.groups
        )
    wall = {k: [] for k in runs}
    cpu = {k: [] for k in runs}
    load = [_load()]
    for _ in range(spec["repeats"]):
        for name, run in runs.items():
            result, w, c = _timed(run)
            if name in fits:
                models[name] = result
            wall[name].append(w)
            cpu[name].append(c)
    profiles = [_profile_steps(fits["case III, search"]) for _ in range(2)]
    diagnose_profile = None
    if spec.get("diagnose", True):
        diagnose_profile = _profile_steps(
            runs["diagnose, case I model"], DIAGNOSE_STEPS
        )
    load.append(_load())
    out = {
        **spec,
        "rows": int(forced.X.shape[0]),
        "n_terms": len(library),
        "threads": torch.get_num_threads(),
        "wall": {k: min(v) for k, v in wall.items()},
        "cpu": {k: min(v) for k, v in cpu.items()},
        "wall_all": wall,
        "cpu_all": cpu,
        "learned": {k: m.equation(4) for k, m in models.items()},
        "search_choice": f"{models['case III, search'].normalization_}, "
        f"{models['case III, search'].fixed_term_}",
        "profile": min(profiles, key=lambda steps: steps[0][2]),
        "diagnose_profile": diagnose_profile,
        "load": load,
    }
    import lagsindy

    out["lagsindy"] = os.path.dirname(lagsindy.__file__)
    return out


def _ratio_rows(res, label):
    base_wall, base_cpu = res["wall"]["case I"], res["cpu"]["case I"]
    rows = []
    for name in res["wall"]:
        rows.append(
            f"| {name} | {label} | {res['wall'][name]:.2f} s | "
            f"{res['cpu'][name]:.2f} s | {res['wall'][name] / base_wall:.2f} | "
            f"**{res['cpu'][name] / base_cpu:.2f}** |"
        )
    return rows


def _least_disturbed(results):
    """The process whose case I fit was fastest (CPU), among those without errors."""
    ok = [r for r in results if "error" not in r]
    return min(ok, key=lambda r: r["cpu"]["case I"]) if ok else results[0]


FIT_MARKER = "\n### (a) Case I fit, cart-pendulum"
FIT_END_MARKER = "\n### (c) Passive search"


def fit_lines(repeats=3, small=False, processes=2):
    """Markdown lines of (a): the default data and the 50k x 39 random rows."""
    lines = [
        "### (a) Case I fit, cart-pendulum, 50k rows x 39 terms",
        "",
        "| data | formulation | process | best wall (median) | best CPU | "
        "torch threads |",
        "|---|---|---|---|---|---|",
    ]
    n_default = 3 if small else 100
    for k in range(processes):
        r = _run_in(
            {"n_trajectories": n_default, "repeats": 1 if small else repeats},
            "default",
        )
        print("default", r, flush=True)
        for form in ("auto", "strong"):
            if "error" in r:
                lines.append(f"| - | {form} | #{k + 1} | error: {r['error']} | - | - |")
                break
            lines.append(
                f"| {n_default} trajectories x 500 samples ({r['rows']} rows), "
                f"paper library ({r['n_terms']} terms) | {form} "
                f"({r['formulation'][form]}) | #{k + 1} | "
                f"{r['wall'][form]:.3g} s ({r['wall_median'][form]:.3g} s) | "
                f"{r['cpu'][form]:.3g} s | {r['threads']} |"
            )
    rows = 2000 if small else 50_000
    for k in range(processes):
        r = run_measurement(
            {
                "n_rows": rows,
                "degree": 3,
                "device": "cpu",
                "repeats": 1 if small else repeats,
            }
        )
        print("random rows", r, flush=True)
        lines.append(
            f"| {rows} random rows (`random_rows`), cart library degree 3 | strong "
            f"(fallback: rows not time-ordered) | #{k + 1} | "
            + (
                f"error: {r['error']} | - | - |"
                if "error" in r
                else f"{min(r['times']):.3g} s ({r['time']:.3g} s) | "
                f"{min(r['cpus']):.3g} s | {r['threads']} |"
            )
        )
    return lines + ["", "Target: <= 0.1 s on 2 cores.", ""]


def memory_lines(small=False):
    """Markdown lines of (b): peak memory of one 1M x 169 fit."""
    lines = [
        "### (b) Memory: 1M rows x 169 terms, case I on CPU",
        "",
        "| rows x terms | fit wall | fit CPU | RSS before the fit | peak RSS |",
        "|---|---|---|---|---|",
    ]
    big = 20_000 if small else 1_000_000
    r = run_measurement({"n_rows": big, "degree": 5, "device": "cpu", "repeats": 1})
    print("memory", r, flush=True)
    if "error" in r:
        lines.append(f"| {big} x deg 5 | error: {r['error']} | - | - | - |")
    else:
        lines.append(
            f"| {big} x {r['n_terms']} | {r['time']:.3g} s | {r['cpu']:.3g} s | "
            f"{r['rss_before_mib']:.0f} MiB | **{r['peak_rss_mib']:.0f} MiB** |"
        )
    return lines + ["", "Target: under 2 GB (2048 MiB) peak.", ""]


def fit_section(repeats=3, quick=False, processes=2, argv=None):
    """Markdown: only (a) and (b) of the ratios section, with their own stamp.

    Written by ``--fit-only`` between the (a) heading and the (c) heading of
    ``speed.md``, so that (c), which other work regenerates, is left as it is.
    """
    small = quick or tiny()
    processes = 1 if small else processes
    load_start = _load()
    lines = fit_lines(repeats, small, processes) + memory_lines(small)
    lines += [
        f"(a) and (b) measured by `{command('speed', argv)}` on "
        f"{_common.machine()}; {processes} process(es) per row kind, "
        f"best of {1 if small else repeats} fits each; load average (1 min) "
        f"{load_start:.1f} at the start, {_load():.1f} at the end, on "
        f"{os.cpu_count()} cores.",
        "",
    ]
    return "\n".join(lines)


def _replace_between(old_text, section, start, end):
    """``old_text`` with the text from ``start`` up to ``end`` replaced by ``section``
    (``section`` appended when either marker is missing)."""
    if start not in old_text or end not in old_text.split(start, 1)[1]:
        return old_text.rstrip("\n") + "\n\n" + section
    head, rest = old_text.split(start, 1)
    tail = rest[rest.index(end) :]
    return head.rstrip("\n") + "\n\n" + section.strip("\n") + "\n" + tail


def ratios_section(baseline=None, repeats=3, quick=False, processes=2):
    """Markdown: issue 16's (a) 50k x 39 fit, (b) 1M x 169 memory, (c) ratios.

    (a) and (c) run in ``processes`` fresh processes each (alternating 'after' and
    'before' for (c)): on a loaded 2-core machine a process with two torch threads
    is now and then several times slower throughout (CPU time = wall time: its two
    threads share one core and wait for each other), so every process is reported
    and the targets are judged on the least disturbed one.
    """
    small = quick or tiny()
    processes = 1 if small else processes
    load_start = _load()
    lines = [
        RATIOS_MARKER.strip("\n") + " (issue 16)",
        "",
        f"Load average (1 min) at the start: {load_start:.1f} on {os.cpu_count()} "
        "cores. The machine is shared, so wall times vary with the load; CPU times "
        "(`time.process_time`, all of the process's threads: a torch thread that "
        "spins while waiting counts too) vary less, and the ratios are taken within "
        "one process. Each measurement runs in "
        f"{processes} fresh process(es) (#1, #2...), one after the other: a process "
        "whose two torch threads end up on one busy core is several times slower "
        "throughout (its CPU time then equals its wall time), so all are shown.",
        "",
    ]
    lines += fit_lines(repeats, small, processes) + memory_lines(small)
    n_traj = 3 if small else 20
    spec = {"n_trajectories": n_traj, "repeats": 1 if small else repeats}
    after, before = [], []
    for _ in range(processes):
        after.append(_run_in(spec, "ratios"))
        print("ratios after", after[-1], flush=True)
        if baseline:
            before.append(_run_in(spec, "ratios", code_root=baseline))
            print("ratios before", before[-1], flush=True)
    lines += [
        "### (c) Passive search and diagnosis against one case I fit",
        "",
        f"Cart-pendulum, paper library, `make_dataset(system, n_trajectories={n_traj}, "
        'excitation=..., random_state=0)`: forced (`"sincos"`) for case I, passive '
        "(`None`) for case III, the same size; estimator defaults "
        '(`formulation="auto"`: weak) with `groups`; `diagnose(est, X, tau, '
        f"groups=...)` with its defaults. Best of {spec['repeats']} alternating runs "
        "(each run: the four fits, then the two diagnoses). Ratios are to the case I "
        "fit in the same process."
        + (
            f" 'before' imports lagsindy from `{baseline}` (commit "
            f"{_commit(baseline)}), same data and runs."
            if baseline
            else ""
        ),
        "",
        "| run | code | process | wall | CPU | wall / case I | CPU / case I |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, results in (("after", after), ("before", before)):
        for k, res in enumerate(results):
            if "error" in res:
                lines.append(
                    f"| - | {label} | #{k + 1} | error: {res['error']} | - | - | - |"
                )
                continue
            lines += _ratio_rows(res, f"{label} | #{k + 1}")
    best = _least_disturbed(after)
    if "error" not in best:
        cpu = best["cpu"]
        search = cpu["case III, search"] / cpu["case I"]
        lines += [
            "",
            f"Search chose: {best['search_choice']}; learned `"
            f"{best['learned']['case III, search']}`.",
            "",
            "Targets, in the least disturbed 'after' process (#"
            f"{after.index(best) + 1}): passive search <= 2x a case I fit: "
            f"{'met' if search <= 2 else 'NOT met'} ({search:.2f}x CPU)",
        ]
        if "diagnose, case I model" in cpu:
            diag = cpu["diagnose, case I model"] / cpu["case I"]
            lines[-1] += (
                f"; diagnose <= 3x a fit: {'met' if diag <= 3 else 'NOT met'} "
                f"({diag:.1f}x CPU for the case I model)."
            )
        lines += [
            "",
            "Where one passive search goes (cProfile with `time.process_time`, the "
            "less disturbed of two profiled fits in the least disturbed process of "
            "each code; cumulative per function, so nested rows are parts of the row "
            "above; the profiler's own overhead inflates the many small calls):",
            "",
            "| step | code | calls | CPU | share |",
            "|---|---|---|---|---|",
        ]
        for label, results in (("after", after), ("before", before)):
            if not results:
                continue
            res = _least_disturbed(results)
            if "error" in res:
                continue
            total = res["profile"][0][2]
            for step, calls, seconds in res["profile"]:
                lines.append(
                    f"| {step} | {label} | {calls} | {seconds:.2f} s | "
                    f"{100 * seconds / max(total, 1e-12):.0f} % |"
                )
        if best.get("diagnose_profile"):
            total = best["diagnose_profile"][0][2]
            lines += [
                "",
                "Where one `diagnose` of the case I model goes (cProfile, one run; "
                "`_Statistics` builds the held-out folds' weak Gram statistics; rows "
                "overlap, e.g. the delay search refits the model):",
                "",
                "| step | calls | CPU | share |",
                "|---|---|---|---|",
            ]
            for step, calls, seconds in best["diagnose_profile"]:
                lines.append(
                    f"| {step} | {calls} | {seconds:.2f} s | "
                    f"{100 * seconds / max(total, 1e-12):.0f} % |"
                )
    loads = [x for r in after + before if "load" in r for x in r["load"]]
    lines += [
        "",
        "Load average (1 min) during (c): "
        + (f"{min(loads):.1f} .. {max(loads):.1f}" if loads else "-")
        + f"; at the end {_load():.1f}.",
        "",
    ]
    return "\n".join(lines)


def measure_default(spec):
    """Case I on the default data (100 x 500 sincos trajectories): auto and strong."""
    import warnings

    import torch

    warnings.simplefilter("ignore")
    system = cart_pendulum()
    library = system.paper_library()
    data = make_dataset(
        system,
        n_trajectories=spec["n_trajectories"],
        excitation="sincos",
        random_state=0,
    )
    LagrangianSINDy(library).fit(data.X[:1000], data.tau[:1000])  # warm-up
    wall = {"auto": [], "strong": []}
    cpu = {"auto": [], "strong": []}
    used = {}
    for _ in range(spec["repeats"]):
        for form in wall:
            est, w, c = _timed(
                lambda form=form: LagrangianSINDy(library, formulation=form).fit(
                    data.X, data.tau
                )
            )
            wall[form].append(w)
            cpu[form].append(c)
            used[form] = est.formulation_
    return {
        **spec,
        "rows": int(data.X.shape[0]),
        "n_terms": len(library),
        "threads": torch.get_num_threads(),
        "wall": {k: min(v) for k, v in wall.items()},
        "cpu": {k: min(v) for k, v in cpu.items()},
        "wall_median": {k: statistics.median(v) for k, v in wall.items()},
        "formulation": used,
    }


def _replace_section(old_text, section, marker="\n## At the hardware floor"):
    """``old_text`` with the section that starts at ``marker`` replaced by ``section``.

    The section runs up to the next level-2 heading (or the end); when ``old_text``
    has none, ``section`` is appended.
    """
    if marker not in old_text:
        return old_text.rstrip("\n") + "\n" + section
    head, rest = old_text.split(marker, 1)
    after = rest.find("\n## ")
    tail = "" if after < 0 else rest[after:]
    return head.rstrip("\n") + "\n" + section.rstrip("\n") + "\n" + tail


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--no-scaling",
        action="store_true",
        help="only the default cart-pendulum timing",
    )
    parser.add_argument(
        "--floor-only",
        action="store_true",
        help="only the hardware-floor section (replaced in speed.md)",
    )
    parser.add_argument(
        "--baseline",
        default=None,
        help="another checkout (path) to time as 'before' in the floor section",
    )
    parser.add_argument(
        "--ratios",
        action="store_true",
        help="only the passive-search / diagnosis section (replaced in speed.md)",
    )
    parser.add_argument(
        "--fit-only",
        action="store_true",
        help="only (a) and (b) of the passive-search section: the 50k-row fits and "
        "the 1M-row memory (replaced in speed.md; (c) is left as it is)",
    )
    parser.add_argument(
        "--floor-fits",
        action="store_true",
        help="only the fit / Gram floor rows (a subsection of the floor section, "
        "replaced in speed.md; the simulation and memory parts are left as they are)",
    )
    parser.add_argument("--_measure", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--_ratios", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--_default", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--_floor", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--_simulate", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args._measure is not None:
        print(json.dumps(measure(json.loads(args._measure))))
        return
    if args._floor is not None:
        print(json.dumps(measure_floor(json.loads(args._floor))))
        return
    if args._simulate is not None:
        print(json.dumps(measure_simulation(json.loads(args._simulate))))
        return
    if args._ratios is not None:
        print(json.dumps(measure_ratios(json.loads(args._ratios))))
        return
    if args._default is not None:
        print(json.dumps(measure_default(json.loads(args._default))))
        return
    quick = args.quick or tiny()
    name = "speed_quick.md" if quick else "speed.md"
    if args.fit_only or args.floor_fits:
        repeats = 1 if quick else min(args.repeats, 5)
        path = _common.RESULTS / name
        old = (
            path.read_text()
            if path.exists()
            else header("Fit time: cart-pendulum, case I", command("speed", argv))
        )
        if args.fit_only:
            section = fit_section(repeats=repeats, quick=quick, argv=argv)
            text = _replace_between(old, section, FIT_MARKER, FIT_END_MARKER)
        else:
            section = floor_fits_section(
                args.baseline, repeats=repeats, quick=quick, argv=argv
            )
            text = _replace_subsection(
                old, section, FLOOR_FITS_MARKER, "\n## At the hardware floor"
            )
        write(name, text)
        print(section)
        return
    if args.ratios or args.floor_only:
        # The ratios' runs are short (a few tenths of a second): up to 9 repeats,
        # since on a shared machine one disturbed run moves a best-of-3 ratio by 0.3.
        cap = 9 if args.ratios else 3
        repeats = 1 if quick else min(args.repeats, cap)
        if args.ratios:
            section = ratios_section(args.baseline, repeats=repeats, quick=quick)
            title, marker = "Passive search", RATIOS_MARKER
        else:
            section = floor_section(args.baseline, repeats=repeats, quick=quick)
            title, marker = "Hardware floor", "\n## At the hardware floor"
        path = _common.RESULTS / name
        old = (
            path.read_text()
            if path.exists()
            else header("Fit time: cart-pendulum, case I", command("speed", argv))
        )
        stamp = "\n".join(header(title, command("speed", argv)).splitlines()[2:])
        write(name, _replace_section(old, "\n" + section + "\n" + stamp, marker))
        print(section)
        return
    quick = args.quick or tiny()
    n_traj = 3 if tiny() else 10 if quick else 100
    repeats = 2 if quick else args.repeats
    system = cart_pendulum()
    data = make_dataset(
        system, n_trajectories=n_traj, excitation="sincos", random_state=0
    )
    library = system.paper_library()
    start = time.perf_counter()
    LagrangianSINDy(library).fit(data.X, data.tau)
    first = time.perf_counter() - start
    times, est = time_fits(data.X, data.tau, library, repeats)
    median = statistics.median(times)
    text = header("Fit time: cart-pendulum, case I", command("speed", argv))
    text += (
        f"Data: {n_traj} trajectories x 500 samples ({data.X.shape[0]} rows), "
        "noise-free, "
        f"tau = a sin(wt) + b cos(wt) on the cart. Library: {len(library.candidates_)} "
        f"candidates ({len(library)} after removing trivial and dependent terms).\n\n"
        f"| quantity | value |\n|---|---|\n"
        f"| median fit time over {repeats} fits | **{median:.3f} s** |\n"
        f"| all fit times | {', '.join(f'{t:.3f}' for t in times)} s |\n"
        f"| first fit in the process (torch lazy imports included) | {first:.3f} s |\n"
        f"| FISTA iterations (all stages) | {est.n_iter_} |\n"
        f"| stages | {len(est.stages_)} |\n"
        f"| learned | `{est.equation(4)}` |\n\n"
        f"Target (core issue): under 1 s per fit: "
        f"{'met' if median < 1.0 else 'NOT met'}.\n"
    )
    if not args.no_scaling:
        rows_sweep, lib_sweep, devices = scaling(quick)
        plot_name = "speed_quick.png" if quick else "speed.png"
        _common.RESULTS.mkdir(parents=True, exist_ok=True)
        plot(rows_sweep, lib_sweep, _common.RESULTS / plot_name)
        text += scaling_text(rows_sweep, lib_sweep, devices, plot_name)
        text += floor_section(args.baseline, repeats=2 if quick else 3, quick=quick)
    write("speed_quick.md" if quick else "speed.md", text)
    print(text)


if __name__ == "__main__":
    main()
