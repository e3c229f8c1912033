"""Shared helpers of the benchmark scripts: machine description and result headers."""

from __future__ import annotations

import datetime as _dt
import os
import platform
import shlex
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
