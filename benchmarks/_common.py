"""Shared helpers of the benchmark scripts: machine description and result headers."""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def machine() -> str:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none"
    return (
        f"{cpu}; {os.cpu_count()} CPU cores visible, "
        f"torch threads {torch.get_num_threads()}; "
        f"GPU: {gpu}; Python {platform.python_version()}, torch {torch.__version__}"
    )


# Set by ``python -m benchmarks`` so results say which command made them.
RUNNER_COMMAND: str | None = None


def command(module: str | None = None, argv=None) -> str:
    """The command line that reproduces a result file.

    ``module`` is the script's name (``"paper_tables"``) and ``argv`` the arguments
    its ``main`` received (``None``: the process's own ``sys.argv``).
    """
    env = (
        "LAGSINDY_BENCH_TINY=1 "
        if os.environ.get("LAGSINDY_BENCH_TINY", "") not in ("", "0")
        else ""
    )
    if RUNNER_COMMAND is not None:
        return env + RUNNER_COMMAND
    if module is None:
        module = Path(sys.argv[0]).stem
    args = sys.argv[1:] if argv is None else list(argv)
    return (
        env
        + f"python -m benchmarks.{module}"
        + (" " + " ".join(shlex.quote(a) for a in args) if args else "")
    )


def header(title: str, cmd: str | None = None) -> str:
    import lagsindy

    return (
        f"# {title}\n\n"
        f"- command: `{cmd or command()}`\n"
        f"- date: {_dt.date.today().isoformat()}\n"
        f"- machine: {machine()}\n"
        f"- lagsindy {lagsindy.__version__}\n\n"
    )


def write(name: str, text: str) -> Path:
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / name
    path.write_text(text)
    print(f"wrote {path}")
    return path


def run_in(module, flag, spec, code_root=None, timeout=1800, env=None):
    """Run ``python -m benchmarks.<module> <flag> <spec as JSON>`` in a fresh
    interpreter and return the JSON object its last line prints.

    ``code_root``: import lagsindy from that checkout instead of this one (for
    before/after comparisons); the benchmark's own code is always this checkout's.
    A timeout or a failure gives ``{**spec, "error": ...}``.
    """
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    code = os.path.abspath(code_root or root)
    # lagsindy is imported first (from code_root when given), then this checkout's
    # benchmarks package runs the measurement.
    boot = (
        f"import runpy, sys; sys.path.insert(0, {code!r}); import lagsindy; "
        f"sys.path[0] = {root!r}; sys.argv[0] = {module!r}; "
        f"runpy.run_module('benchmarks.{module}', run_name='__main__')"
    )
    cmd = [sys.executable, "-c", boot, flag, json.dumps(spec)]
    try:
        out = subprocess.run(
            cmd,
            capture_output=True,
            text=True,
            timeout=timeout,
            cwd=root,
            env=None if env is None else {**os.environ, **env},
        )
    except subprocess.TimeoutExpired:
        return {**spec, "error": f"no result within {timeout} s"}
    if out.returncode != 0:
        tail = out.stderr.strip().splitlines()
        return {**spec, "error": tail[-1] if tail else f"exit {out.returncode}"}
    return json.loads(out.stdout.strip().splitlines()[-1])
