"""Fits from partitioned data: a forced double pendulum log written as Parquet, fitted
by Dask partition by partition, against the in-memory fit of the same rows.

Writes ``results/scale.md``. Each measurement runs in a fresh process; peak memory
is the largest sum of the resident sizes of that process and its children (the
Dask workers), sampled every 20 ms with psutil (a dependency of
``dask.distributed``).

Sizes (``--trajectories`` x ``--samples`` per trajectory, sampled at 100 Hz):

* this machine (default): 1,000 x 1,000 (1e6 rows) fitted in memory and by 1 and
  2 Dask workers, then 2,000 x 1,000 (2e6 rows) by 2 workers only;
* the issue's size (``--full``): 10,000 x 10,000 (1e8 rows), the in-memory
  comparison on the first 1,000 trajectories (1e7 rows). Simulating the data takes
  about 50 s per 1e6 rows on the 2-core machine (about 1.5 h for 1e8).

``python -m benchmarks.scale [--full] [--dir DIR]`` (needs ``lagsindy[dask]``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

from . import _common

RATE = 100.0
PER_FILE = 100  # trajectories per Parquet file (one row group each)
FORMULATION = "strong"


def _system():
    from lagsindy.systems import double_pendulum

    return double_pendulum()


def write_data(folder: Path, n_traj: int, n_samples: int) -> Path:
    """The log as Parquet files of ``PER_FILE`` whole trajectories each (file
    ``k`` always holds the same simulated trajectories: files already there are
    kept, so a larger run extends a smaller one)."""
    from lagsindy.systems import make_dataset

    folder.mkdir(parents=True, exist_ok=True)
    system = _system()
    for k, first in enumerate(range(0, n_traj, PER_FILE)):
        path = folder / f"part-{k:05d}.parquet"
        if path.exists():
            continue
        data = make_dataset(
            system,
            n_trajectories=PER_FILE,
            duration=n_samples / RATE,
            rate=RATE,
            excitation="paper",
            random_state=1000 + k,
        )
        frame = data.to_frame()
        frame["trajectory"] = frame["trajectory"].astype(np.int64) + first
        frame = frame.drop(columns=["t"])
        frame.to_parquet(path.with_suffix(".tmp"), index=False)
        path.with_suffix(".tmp").rename(path)
        print(f"  wrote {first + PER_FILE}/{n_traj} trajectories", flush=True)
    return folder


class PeakRSS:
    """Largest summed resident size of this process and its children."""

    def __init__(self, every=0.02):
        import psutil

        self.proc, self.every, self.peak = psutil.Process(), every, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self._stop.is_set():
            total = 0
            try:
                for p in [self.proc, *self.proc.children(recursive=True)]:
                    try:
                        total += p.memory_info().rss
                    except Exception:  # noqa: BLE001 - a child that just ended
                        pass
            except Exception:  # noqa: BLE001
                pass
            self.peak = max(self.peak, total)
            time.sleep(self.every)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def _estimator():
    from lagsindy import LagrangianSINDy

    return LagrangianSINDy(_system().paper_library(), formulation=FORMULATION)


def measure(spec: dict) -> dict:
    """One fit in this process: ``spec["mode"]`` "memory" or "dask" with
    ``workers``, on the first ``files`` Parquet files of ``folder``."""
    import warnings

    warnings.simplefilter("ignore")
    files = sorted(Path(spec["folder"]).glob("part-*.parquet"))[: spec["files"]]
    est = _estimator()
    with PeakRSS() as peak:
        start = time.perf_counter()
        if spec["mode"] == "memory":
            import pandas as pd

            frame = pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)
            read = time.perf_counter() - start
            n_rows = len(frame)
            cols = [c for c in frame.columns if c not in ("trajectory",)]
            tau = frame[[c for c in cols if c.startswith("tau_")]].to_numpy()
            X = frame[[c for c in cols if not c.startswith("tau_")]]
            groups = frame["trajectory"].to_numpy()
            del frame
            est.fit(X, tau, groups=groups)
        else:
            import dask.dataframe as dd
            from dask.distributed import Client, LocalCluster

            cluster = LocalCluster(
                n_workers=spec["workers"],
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
                memory_limit=0,
            )
            client = Client(cluster)
            client.run(_one_thread)
            ready = time.perf_counter() - start
            start = time.perf_counter()
            import pyarrow.parquet as pq

            ddf = dd.read_parquet([str(f) for f in files])
            n_rows = sum(pq.ParquetFile(f).metadata.num_rows for f in files)
            read = time.perf_counter() - start
            est.fit(ddf)
            client.close()
            cluster.close()
        elapsed = time.perf_counter() - start
    out = {
        **spec,
        "load": os.getloadavg()[0],  # other processes on the machine (1 min)
        "rows": n_rows,
        "seconds": elapsed,
        "read_seconds": read,
        "peak_mib": peak.peak / 2**20,
        "coef": est.fitted_.all_coef().tolist(),
        "equation": est.equation(4),
    }
    if spec["mode"] == "dask":
        out["cluster_seconds"] = ready
    return out


def _one_thread():
    import torch

    torch.set_num_threads(1)


def _run(spec):
    return _common.run_in("scale", "--_measure", spec, timeout=3600)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="the issue's 1e8 rows")
    parser.add_argument(
        "--quick", action="store_true", help="the default size (as without --full)"
    )
    parser.add_argument("--dir", default=None, help="where the Parquet data go")
    parser.add_argument("--_measure", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args._measure:
        print(json.dumps(measure(json.loads(args._measure))))
        return
    if args.full:
        n_samples, compare, large = 10_000, 1_000, 10_000
    else:
        n_samples, compare, large = 1_000, 1_000, 2_000
    folder = Path(args.dir or os.environ.get("TMPDIR", "/tmp")) / (
        f"lagsindy_scale_{n_samples}"
    )
    t0 = time.perf_counter()
    write_data(folder, large, n_samples)
    made = time.perf_counter() - t0
    small = compare // PER_FILE
    runs = [
        {"mode": "memory", "files": small},
        {"mode": "dask", "workers": 1, "files": small},
        {"mode": "dask", "workers": 2, "files": small},
        {"mode": "dask", "workers": 2, "files": large // PER_FILE},
    ]
    results = []
    for spec in runs:
        spec = {**spec, "folder": str(folder)}
        print(f"measuring {spec}", flush=True)
        res = _run(spec)
        print({k: v for k, v in res.items() if k != "coef"}, flush=True)
        results.append(res)
    _common.write("scale.md", report(results, made, args, n_samples))


def report(results, made, args, n_samples) -> str:
    text = _common.header(
        "Fits from partitioned data (Dask, Parquet): forced double pendulum",
        _common.command("scale", sys.argv[1:] if args is None else None),
    )
    text += (
        f"Data: forced double pendulum (`paper` input), noise-free, {RATE:g} Hz, "
        f"{n_samples} samples per trajectory, Parquet files of {PER_FILE} whole "
        f"trajectories (made in {made:.0f} s, or read back when already there). "
        f"Library: the paper's ({_estimator().library.build().terms_.__len__()} "
        f"candidates), `formulation={FORMULATION!r}`, case I. Each row is a fresh "
        "process; time from reading the Parquet files to the fitted model "
        "(the Dask rows: after the cluster started); peak memory: the largest sum "
        "of the resident sizes of the process and its workers.\n\n"
    )
    text += (
        "| fit | rows | time | rows / s | of in-memory | peak memory | "
        "max coef. difference (rel.) | load average |\n"
        "|---|---|---|---|---|---|---|---|\n"
    )
    base = next((r for r in results if r.get("mode") == "memory"), None)
    for r in results:
        if "error" in r:
            text += f"| {r['mode']} | - | error: {r['error']} | | | | | |\n"
            continue
        name = (
            "in memory" if r["mode"] == "memory" else f"Dask, {r['workers']} worker(s)"
        )
        rate = r["rows"] / r["seconds"]
        rel, diff = "-", "-"
        if base is not None and "error" not in base:
            rel = f"{rate / (base['rows'] / base['seconds']):.0%}"
            if r["rows"] == base["rows"]:
                a, b = np.asarray(base["coef"]), np.asarray(r["coef"])
                diff = f"{np.abs(a - b).max() / np.abs(a).max():.1e}"
        text += (
            f"| {name} | {r['rows']:,} | {r['seconds']:.1f} s | {rate:,.0f} | {rel} | "
            f"{r['peak_mib']:.0f} MiB | {diff} | {r.get('load', float('nan')):.1f} |\n"
        )
    last = results[-1]
    if "equation" in last:
        text += f"\nLearned on the largest data: `{last['equation']}`\n"
    return text


if __name__ == "__main__":
    main(sys.argv[1:])
