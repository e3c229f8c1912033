"""GPU fit time against the hardware floor (issue 16): case I, 169 terms, 1M, 4M rows.

For each size, in one process on ``--device`` (default ``cuda``):

- the median wall time of ``--repeats`` case I fits (cart-pendulum, random rows with
  exact accelerations, :func:`benchmarks.speed.random_rows`; cart polynomial library of
  degree 5: 169 terms; ``formulation="strong"``: random rows are no trajectories),
  after a warm-up fit on a slice, the device synchronized;
- the Gram floor: one float64 ``A.T @ A`` of the regression tensor's size (``rows *
  n_dof`` by ``terms + 1``) on the same device, the least work a Gram-based fit does;
- the peak device memory of the fits (``torch.cuda.max_memory_allocated``);
- one more fit under ``torch.profiler``: the summed device time of the kernels, and the
  number of kernel launches (``cudaLaunchKernel`` calls on CUDA; on CPU, the number
  of aten operator calls, the counterpart of launches).

Targets (issue 16, H100 or similar): 1M rows <= 0.3 s, 4M rows <= 1 s.

Without a GPU the script writes that none was found (and measures nothing) unless
``--device cpu`` is given, which runs the same measurement on the CPU (the test runs
it at a tiny size).

    python -m benchmarks.gpu                           # results/gpu.md
    python -m benchmarks.gpu --rows 1000000 --repeats 3
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
import warnings

from . import _common
from ._common import header, write

ROWS = (1_000_000, 4_000_000)
DEGREE = 5  # 169 terms after reduction


def _sync(device):
    import torch

    if device == "cuda":
        torch.cuda.synchronize()


def profile_fit(fit, device):
    """``(kernel seconds, launches)`` of one call of ``fit`` under torch.profiler."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU]
    if device == "cuda":
        activities.append(ProfilerActivity.CUDA)
    with profile(activities=activities) as prof:
        fit()
        _sync(device)
    kernel_us, launches = 0.0, 0
    for event in prof.events():
        name = event.name
        if device == "cuda":
            if event.device_type == torch.autograd.DeviceType.CUDA:
                kernel_us += getattr(event, "device_time", None) or getattr(
                    event, "cuda_time", 0.0
                )
            if name in ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC"):
                launches += 1
        elif name.startswith("aten::"):
            launches += 1
            if event.cpu_parent is None:  # top-level operators: no double counting
                kernel_us += event.cpu_time_total
    return kernel_us * 1e-6, launches


def measure(n_rows, device, repeats, degree=DEGREE):
    """One size: fit times, floor, peak memory, profiled kernel time and launches."""
    import torch

    from lagsindy import CandidateLibrary, LagrangianSINDy
    from lagsindy.systems import cart_pendulum

    from .speed import random_rows

    warnings.simplefilter("ignore")  # the figures, not the fits' warnings
    system = cart_pendulum()
    library = CandidateLibrary.polynomial(
        ["x", "theta"], angles=["theta"], degree=degree
    )
    library.build()
    X, tau = random_rows(system, n_rows)
    LagrangianSINDy(library, device=device, formulation="strong").fit(
        X[:2000], tau[:2000]
    )  # warm-up
    a = torch.randn(
        n_rows * system.n_dof, len(library) + 1, dtype=torch.float64, device=device
    )
    floors, fits = [], []
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    est = None
    for _ in range(repeats):
        _sync(device)
        start = time.perf_counter()
        a.T @ a
        _sync(device)
        floors.append(time.perf_counter() - start)
        est = LagrangianSINDy(library, device=device, formulation="strong")
        start = time.perf_counter()
        est.fit(X, tau)
        _sync(device)
        fits.append(time.perf_counter() - start)
    peak = torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else None
    del a
    kernel_s, launches = profile_fit(
        lambda: LagrangianSINDy(library, device=device, formulation="strong").fit(
            X, tau
        ),
        device,
    )
    return dict(
        rows=n_rows,
        terms=len(library),
        device=device,
        fit=statistics.median(fits),
        fits=fits,
        floor=statistics.median(floors),
        peak_mib=peak,
        kernel_s=kernel_s,
        launches=launches,
        support=sorted(est.term_names_[est.support_].tolist()),
    )


def report(results, device) -> str:
    lines = [
        "| rows x terms | device | median fit | Gram floor | fit / floor | kernel time "
        "(profiled fit) | launches | peak device memory |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        peak = f"{r['peak_mib']:.0f} MiB" if r["peak_mib"] is not None else "-"
        lines.append(
            f"| {r['rows']} x {r['terms']} | {r['device']} | {r['fit']:.3g} s | "
            f"{r['floor']:.3g} s | {r['fit'] / r['floor']:.1f} | "
            f"{r['kernel_s']:.3g} s | {r['launches']} | {peak} |"
        )
    lines.append("")
    lines.append(
        "All fit times: "
        + "; ".join(
            f"{r['rows']} rows: " + ", ".join(f"{t:.3g}" for t in r["fits"]) + " s"
            for r in results
        )
        + f". Learned support ({results[-1]['rows']} rows): "
        + ", ".join(f"`{s}`" for s in results[-1]["support"])
        + "."
    )
    if device == "cuda":
        lines.append(
            "\nTargets (issue 16): 1M rows <= 0.3 s, 4M rows <= 1 s on an H100 or "
            "similar."
        )
    else:
        lines.append(
            "\n'launches' on CPU counts aten operator calls, 'kernel time' the CPU "
            "time of the top-level operators."
        )
    return "\n".join(lines) + "\n"


def main(argv=None):
    import torch

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", choices=("cuda", "cpu"))
    parser.add_argument("--rows", default=",".join(str(r) for r in ROWS))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--degree", type=int, default=DEGREE)
    parser.add_argument("--quick", action="store_true", help="1M rows only, 1 repeat")
    args = parser.parse_args(argv)
    rows = [int(r) for r in args.rows.split(",") if r]
    tiny = os.environ.get("LAGSINDY_BENCH_TINY", "") not in ("", "0")
    if args.quick:
        rows, args.repeats = rows[:1], 1
    if tiny:
        rows, args.repeats, args.degree = [3000], 1, 3
    suffix = "_quick" if (args.quick or tiny) else ""
    text = header("GPU fit time at the hardware floor", _common.command("gpu", argv))
    text += "\n" + __doc__.split("\n\n", 1)[1].rsplit("\n\n    python", 1)[0] + "\n\n"
    if args.device == "cuda" and not torch.cuda.is_available():
        text += (
            "No GPU on this machine (`torch.cuda.is_available()` is False): nothing "
            "measured.\n"
        )
    else:
        results = [measure(n, args.device, args.repeats, args.degree) for n in rows]
        if args.device == "cuda":
            text += f"GPU: {torch.cuda.get_device_name(0)}.\n\n"
        text += report(results, args.device)
    write(f"gpu{suffix}.md", text)
    return 0


if __name__ == "__main__":
    main()
