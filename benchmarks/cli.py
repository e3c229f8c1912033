"""The command line's latency: how soon an error comes, how soon and how long a fit.

Every command runs in a fresh interpreter (``python -m lagsindy ...``, unbuffered)
started in an empty folder, timed from the start of the process to its first line of
output (stdout or stderr) and to its exit. The record is a forced double pendulum (two
angles), 6 trajectories x 10 s at 100 Hz = 6,000 rows of positions and inputs only
(the fit estimates the derivatives), noise 1e-3 rad on the positions: what
``lagsindy simulate --system double_pendulum --trajectories 6 --duration 10
--positions-only --noise 0.001 --protocol sensor`` writes. The fit is
``lagsindy fit record.csv --coordinates theta1,theta2 --angles all --library poly4``
(209 candidate terms, 128 after reduction) with its held-out score (a second fit).

The machine's load average is written with the results: on a shared machine the
times grow with it. ``--one-thread`` also times the fit with one thread for torch
and BLAS (``OMP_NUM_THREADS=1``): two threads on a busy machine spin against the other
processes. ``--baseline LABEL=PATH`` (repeatable) runs the same commands with another
checkout's lagsindy (for before/after figures).

    python -m benchmarks.cli --one-thread
    python -m benchmarks.cli --baseline before=/path/to/older/checkout
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from . import _common

ROOT = Path(__file__).resolve().parents[1]
RECORD = {"trajectories": 6, "duration": 10.0}  # 6,000 rows at 100 Hz
TINY_RECORD = {"trajectories": 2, "duration": 3.0}  # LAGSINDY_BENCH_TINY=1: tests
ERRORS = {
    "bad column": ["fit", "{csv}", "--coordinates", "theta1,nope", "--out", "m.json"],
    "missing file": ["fit", "none.csv", "--coordinates", "theta1", "--out", "m.json"],
    "bad option (--lam -1)": [
        *("fit", "{csv}", "--coordinates", "theta1,theta2", "--lam", "-1"),
        *("--out", "m.json"),
    ],
    "--version (no check: start-up only)": ["--version"],
}
# The seconds the fit's own lines state (the baseline has no library line).
LIBRARY_LINE = r"^library \S+: .*, ([\d.]+) s$"
FIT_LINE = r"fit took ([\d.]+) s"
HELD_OUT_LINE = r"refit on the rest, ([\d.]+) s"
FIT = [
    *("fit", "{csv}", "--coordinates", "theta1,theta2", "--angles", "all"),
    *("--library", "{library}", "--out", "m.json"),
]


def run(args, code_root, cwd, threads=None):
    """Seconds to the first line and to the exit, CPU seconds, exit status, output."""
    env = {
        **os.environ,
        "PYTHONPATH": str(code_root),
        "PYTHONUNBUFFERED": "1",
        "PYTHONDONTWRITEBYTECODE": "1",  # other checkouts stay as they are
        "MPLBACKEND": "Agg",
    }
    if threads is not None:
        for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env[name] = str(threads)
    start = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "lagsindy", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    first, lines = None, []
    for line in proc.stdout:
        if first is None:
            first = time.perf_counter() - start
        lines.append(line.rstrip("\n"))
    _, status, usage = os.wait4(proc.pid, 0)  # the child's own CPU time
    total = time.perf_counter() - start
    proc.returncode = code = os.waitstatus_to_exitcode(status)
    proc.stdout.close()
    cpu = usage.ru_utime + usage.ru_stime
    return {"first": first, "total": total, "cpu": cpu, "code": code, "output": lines}


def _record(folder, size):
    """Write the double-pendulum record; returns its path."""
    path = Path(folder) / "record.csv"
    from lagsindy.cli import main

    code = main(
        [
            *("simulate", "--system", "double_pendulum", "--positions-only"),
            *("--trajectories", str(size["trajectories"])),
            *("--duration", str(size["duration"]), "--noise", "0.001"),
            *("--protocol", "sensor", "--out", str(path), "--quiet"),
        ]
    )
    if code != 0:
        raise RuntimeError("could not write the record")
    return path


def _seconds(pattern, lines):
    """The number of seconds a line matching ``pattern`` states, or None."""
    for line in lines:
        m = re.search(pattern, line)
        if m:
            return float(m.group(1))
    return None


def _stats(values):
    values = [v for v in values if v is not None]
    if not values:
        return "-"
    return f"{min(values):.2f} s / {statistics.median(values):.2f} s"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one repeat of each")
    parser.add_argument(
        "--baseline",
        action="append",
        default=[],
        metavar="LABEL=PATH",
        help="another checkout to time (repeatable)",
    )
    parser.add_argument(
        "--one-thread", action="store_true", help="also time the fit with one thread"
    )
    parser.add_argument(
        "--repeats", type=int, default=None, help="repeats (default 5; fits 3)"
    )
    args = parser.parse_args(argv)
    tiny = os.environ.get("LAGSINDY_BENCH_TINY", "") not in ("", "0")
    size = TINY_RECORD if tiny else RECORD
    library = "poly3" if tiny else "poly4"
    repeats = args.repeats or (1 if (args.quick or tiny) else 5)
    fit_repeats = args.repeats or (1 if (args.quick or tiny) else 3)
    codes = [("this", ROOT)]
    for spec in args.baseline:
        label, _, path = spec.rpartition("=")
        codes.append((label or "baseline", Path(path).resolve()))
    load_before = os.getloadavg()
    rows, fits = [], []
    with tempfile.TemporaryDirectory() as folder:
        csv = _record(folder, size)
        n_rows = sum(1 for _ in open(csv)) - 1
        for label, root in codes:
            for name, template in ERRORS.items():
                cmd = [a.format(csv=csv) for a in template]
                runs = [run(cmd, root, folder) for _ in range(repeats)]
                rows.append((name, label, runs))
                print(label, name, _stats([r["total"] for r in runs]), flush=True)
            cmd = [a.format(csv=csv, library=library) for a in FIT]
            for threads in (None, 1) if args.one_thread else (None,):
                runs = [run(cmd, root, folder, threads) for _ in range(fit_repeats)]
                name = label if threads is None else f"{label}, 1 thread"
                fits.append((name, runs))
                print(name, "fit", _stats([r["total"] for r in runs]), flush=True)
    load_after = os.getloadavg()

    text = _common.header(
        "The command line: time to an error, and to a fit",
        _common.command("cli", argv),
    )
    text += (
        f"Record: forced double pendulum, {size['trajectories']} trajectories x "
        f"{size['duration']:g} s at 100 Hz = {n_rows} rows of positions and inputs "
        "(derivatives estimated by the fit), noise 1e-3 rad on the positions. Each "
        "command in a fresh interpreter (`python -m lagsindy ...`, unbuffered), "
        "timed from the process start (CPU: the process's user + system seconds, "
        "which a busy machine inflates less than the wall time); min / median over "
        f"{repeats} runs ({fit_repeats} for the fit). Load average (1 min) at the "
        f"start {load_before[0]:.2f}, at the end {load_after[0]:.2f}"
        + "".join(f"; '{label}' is `{root}`" for label, root in codes[1:])
        + ".\n\n## Errors\n\n"
        "| command | code | exit status | wall to the error (min / median) | CPU | "
        "message |\n|---|---|---|---|---|---|\n"
    )
    for name, label, runs in rows:
        message = runs[0]["output"][-1] if runs[0]["output"] else ""
        message = message.replace("|", "\\|")[:110]
        text += (
            f"| {name} | {label} | {runs[0]['code']} | "
            f"{_stats([r['total'] for r in runs])} | "
            f"{_stats([r['cpu'] for r in runs])} | `{message}` |\n"
        )
    text += (
        f"\n## `lagsindy fit --library {library}` on the record\n\n"
        f"`{' '.join(a.format(csv='record.csv', library=library) for a in FIT)}`\n\n"
        "| code | first line | library built | fit | held-out refit | total | "
        "CPU | exit status |\n|---|---|---|---|---|---|---|---|\n"
    )
    for label, runs in fits:
        outs = [r["output"] for r in runs]
        cells = [
            _stats([r["first"] for r in runs]),
            _stats([_seconds(LIBRARY_LINE, o) for o in outs]),
            _stats([_seconds(FIT_LINE, o) for o in outs]),
            _stats([_seconds(HELD_OUT_LINE, o) for o in outs]),
            _stats([r["total"] for r in runs]),
            _stats([r["cpu"] for r in runs]),
            str(runs[0]["code"]),
        ]
        text += f"| {label} | " + " | ".join(cells) + " |\n"
    for label, runs in fits:
        if label.endswith("1 thread"):
            continue
        text += f"\nOutput ({label}, first run):\n\n```text\n"
        text += "\n".join(runs[0]["output"]) + "\n```\n"
    name = "cli_quick.md" if args.quick else "cli.md"
    _common.write(name, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
