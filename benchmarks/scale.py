"""Fits from partitioned data: a forced double pendulum log written as Parquet, fitted
by Dask partition by partition, against the in-memory fit of the same rows.

Writes ``results/scale.md``. Each measurement runs in a fresh process; peak memory
is the largest sum of the resident sizes of that process and its children (the
Dask workers), sampled every 20 ms with psutil (a dependency of
``dask.distributed``). The load average is read before and after each.

Sizes (``--trajectories`` x ``--samples`` per trajectory, sampled at 100 Hz):

* this machine (default): 1,000 x 1,000 (1e6 rows) fitted in memory and by 1 and
  2 Dask workers, then 2,000 x 1,000 (2e6 rows) by 1 and 2 workers;
* the issue's size (``--full``): 10,000 x 10,000 (1e8 rows), the in-memory
  comparison on the first 1,000 trajectories (1e7 rows).

The data are simulated by :func:`simulate_batch`: one fixed-step DOP853 integrator
(scipy's tableau, one step per sample) over a whole batch of trajectories at once in
numpy, with the double pendulum's equations of motion in closed form: 0.24 CPU-s
per 1e5 rows in batches of 1,000 trajectories, against 3.8 for
:func:`lagsindy.systems.make_dataset` (an adaptive solver; 16x), and closer to a
tight reference solution (see ``tests/test_partitioned_scale.py``). File ``k``
holds the trajectories ``make_dataset(..., random_state=1000 + k)`` starts from.

``python -m benchmarks.scale [--full] [--dir DIR] [--runs NAMES]`` (needs
``lagsindy[dask]``); ``--runs`` measures some rows only (results are kept in
``DIR/.../results.json``, the report shows every row measured so far).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

from . import _common

RATE = 100.0
PER_FILE = 100  # trajectories per Parquet file (one row group each)
BATCH_FILES = 10  # files simulated together (one batch of 1,000 trajectories)
FORMULATION = "strong"
# double_pendulum()'s parameters (its defaults), for the closed-form dynamics
M1 = M2 = L1 = L2 = 1.0
GRAVITY = 9.81


def _system():
    from lagsindy.systems import double_pendulum

    return double_pendulum()


# ------------------------------------------------------------------ the data
def accelerations(q1, q2, w1, w2, tau1, tau2):
    """The double pendulum's angular accelerations (elementwise, closed form).

    ``M(q) qdd = tau - c(q, qd) - g(q)`` with ``M = [[(m1+m2) l1^2, m2 l1 l2 cos
    d], [m2 l1 l2 cos d, m2 l2^2]]``, ``d = q1 - q2``: the Euler-Lagrange equations
    of :func:`lagsindy.systems.double_pendulum`'s Lagrangian, solved by Cramer's
    rule.
    """
    d = q1 - q2
    c, s = np.cos(d), np.sin(d)
    a, e, ml = (M1 + M2) * L1 * L1, M2 * L2 * L2, M2 * L1 * L2
    b = ml * c
    r1 = tau1 - ml * s * w2 * w2 - (M1 + M2) * GRAVITY * L1 * np.sin(q1)
    r2 = tau2 + ml * s * w1 * w1 - M2 * GRAVITY * L2 * np.sin(q2)
    det = a * e - b * b
    return (e * r1 - b * r2) / det, (a * r2 - b * r1) / det


def paper_forces(t, omega, input_matrix):
    """``B u(t)`` of the paper's input ``u = [cos wt - sin wt, sin wt]``."""
    c, s = np.cos(omega * t), np.sin(omega * t)
    u1, u2 = c - s, s
    B = input_matrix
    return B[0, 0] * u1 + B[0, 1] * u2, B[1, 0] * u1 + B[1, 1] * u2


def simulate_batch(x0, omega, t, input_matrix, substeps=1):
    """States of a batch of forced double pendulums at the times ``t``.

    Parameters
    ----------
    x0 : ndarray of shape (n_trajectories, 4)
        ``[q1, q2, q1_dot, q2_dot]`` at ``t[0]``.
    omega : ndarray of shape (n_trajectories,)
        The input's frequency per trajectory.
    t : ndarray of shape (n_times,)
        Output times (steps of ``(t[i+1] - t[i]) / substeps``).
    input_matrix : ndarray of shape (2, 2)
    substeps : int, default=1
        DOP853 steps per output interval.

    Returns
    -------
    ndarray of shape (n_times, 4, n_trajectories)
    """
    from scipy.integrate import DOP853

    A, weights, nodes = DOP853.A[:12, :12], DOP853.B, DOP853.C
    y = np.array(np.asarray(x0, dtype=float).T)  # (4, n)
    n = y.shape[1]
    out = np.empty((t.size, 4, n))
    out[0] = y
    K = np.empty((12, 4, n))
    flat = K.reshape(12, -1)

    def rhs(tt, state, k):
        tau1, tau2 = paper_forces(tt, omega, input_matrix)
        k[0], k[1] = state[2], state[3]
        k[2], k[3] = accelerations(*state, tau1, tau2)

    for i in range(t.size - 1):
        h = (t[i + 1] - t[i]) / substeps
        for j in range(substeps):
            t0 = t[i] + j * h
            rhs(t0, y, K[0])
            for s in range(1, 12):
                rhs(
                    t0 + nodes[s] * h, y + h * (A[s, :s] @ flat[:s]).reshape(4, n), K[s]
                )
            y = y + h * (weights @ flat).reshape(4, n)
        out[i + 1] = y
    return out


def file_draws(system, k):
    """Initial states and input frequencies of file ``k``'s ``PER_FILE``
    trajectories (the draws of ``make_dataset(random_state=1000 + k)``)."""
    from sklearn.utils import check_random_state

    rng = check_random_state(1000 + k)
    x0 = system.sample_initial_states(PER_FILE, rng)
    return x0, rng.uniform(math.pi / 2, math.pi, PER_FILE)


def write_data(folder: Path, n_traj: int, n_samples: int, backwards=False) -> int:
    """The log as Parquet files of ``PER_FILE`` whole trajectories each.

    File ``k`` always holds the same trajectories (files already there are kept,
    so a larger run extends a smaller one). ``BATCH_FILES`` files are simulated
    together and written one by one: memory is bounded by one batch (about 450 MB
    at 10,000 samples per trajectory). ``backwards``: the last batch first (a
    second process can write the other end of the same data). Returns the number
    of rows written.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    folder.mkdir(parents=True, exist_ok=True)
    system = _system()
    B = np.asarray(system.input_matrix, dtype=float)
    t = np.arange(n_samples) / RATE
    n_files = -(-n_traj // PER_FILE)
    written = 0
    names = [f"theta{i}" for i in (1, 2)]
    starts = list(range(0, n_files, BATCH_FILES))
    for first in reversed(starts) if backwards else starts:
        batch = [k for k in range(first, min(first + BATCH_FILES, n_files))]
        todo = [k for k in batch if not (folder / f"part-{k:05d}.parquet").exists()]
        if not todo:
            continue
        draws = [file_draws(system, k) for k in todo]
        x0 = np.concatenate([d[0] for d in draws])
        omega = np.concatenate([d[1] for d in draws])
        states = simulate_batch(x0, omega, t, B)  # (n_samples, 4, n_batch)
        for j, k in enumerate(todo):
            cols = slice(j * PER_FILE, (j + 1) * PER_FILE)
            st = states[:, :, cols].transpose(2, 0, 1).reshape(-1, 4)
            om = np.repeat(omega[cols], n_samples)
            tt = np.tile(t, PER_FILE)
            tau1, tau2 = paper_forces(tt, om, B)
            a1, a2 = accelerations(st[:, 0], st[:, 1], st[:, 2], st[:, 3], tau1, tau2)
            table = pa.table(
                {
                    "trajectory": np.repeat(
                        np.arange(k * PER_FILE, (k + 1) * PER_FILE, dtype=np.int64),
                        n_samples,
                    ),
                    names[0]: st[:, 0],
                    names[1]: st[:, 1],
                    f"{names[0]}_dot": st[:, 2],
                    f"{names[1]}_dot": st[:, 3],
                    f"{names[0]}_ddot": a1,
                    f"{names[1]}_ddot": a2,
                    f"tau_{names[0]}": tau1,
                    f"tau_{names[1]}": tau2,
                }
            )
            path = folder / f"part-{k:05d}.parquet"
            pq.write_table(table, path.with_suffix(".tmp"), row_group_size=len(tt))
            path.with_suffix(".tmp").rename(path)
            del table, st
        del states
        written += len(todo) * PER_FILE * n_samples
        print(f"  wrote {(todo[-1] + 1) * PER_FILE}/{n_traj} trajectories", flush=True)
    return written


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
    load_before = os.getloadavg()[0]
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
            done = _count_partitions(cluster)
            ready = time.perf_counter() - start
            start = time.perf_counter()
            if spec.get("progress"):  # partial figures, should the run be stopped
                _report_progress(spec["progress"], start, done, peak)
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
        # the machine's load average (1 min) before and after: other sessions
        "load_before": load_before,
        "load_after": os.getloadavg()[0],
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


def _count_partitions(cluster):
    """The partitions done (tasks ``_apply-*`` reaching memory), counted by a
    plugin of a ``LocalCluster``'s in-process scheduler."""
    from distributed.diagnostics.plugin import SchedulerPlugin

    class Partitions(SchedulerPlugin):
        name = "lagsindy-partitions"
        done = 0

        def transition(self, key, start, finish, *args, **kwargs):
            name = key[0] if isinstance(key, tuple) else key
            if finish == "memory" and str(name).startswith("_apply"):
                self.done += 1

    counter = Partitions()
    cluster.scheduler.add_plugin(counter)
    return counter


def _report_progress(path, start, done, peak, every=10.0):
    """Every ``every`` s: seconds since ``start``, partitions done, peak memory."""

    def run():
        while True:
            Path(path).write_text(
                json.dumps(
                    {
                        "seconds": time.perf_counter() - start,
                        "partitions_done": done.done,
                        "peak_mib": peak.peak / 2**20,
                        "load": os.getloadavg()[0],
                    }
                )
            )
            time.sleep(every)

    threading.Thread(target=run, daemon=True).start()


def _one_thread():
    import torch

    torch.set_num_threads(1)


def _run(spec):
    return _common.run_in("scale", "--_measure", spec, timeout=3600)


def plan(full: bool):
    """``(n_samples, n_trajectories, runs)``: the runs by name, in order."""
    if full:
        n_samples, small, large = 10_000, 10, 100  # files: 1e7 and 1e8 rows
    else:
        n_samples, small, large = 1_000, 10, 20  # 1e6 and 2e6 rows
    runs = {
        "memory-small": {"mode": "memory", "files": small},
        "dask1-small": {"mode": "dask", "workers": 1, "files": small},
        "dask2-small": {"mode": "dask", "workers": 2, "files": small},
        "dask1-large": {"mode": "dask", "workers": 1, "files": large},
        "dask2-large": {"mode": "dask", "workers": 2, "files": large},
    }
    return n_samples, large * PER_FILE, runs


def _uptime() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f}, {five:.2f}, {fifteen:.2f}"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="the issue's 1e8 rows")
    parser.add_argument(
        "--quick", action="store_true", help="the default size (as without --full)"
    )
    parser.add_argument("--dir", default=None, help="where the Parquet data go")
    parser.add_argument(
        "--runs",
        default=None,
        help="comma-separated rows to measure (memory-small, dask1-small, "
        "dask2-small, dask1-large, dask2-large; default: all), 'none': data only",
    )
    parser.add_argument("--_measure", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args._measure:
        print(json.dumps(measure(json.loads(args._measure))))
        return
    n_samples, n_traj, runs = plan(args.full)
    folder = Path(args.dir or os.environ.get("TMPDIR", "/tmp")) / (
        f"lagsindy_scale_dop853_{n_samples}"
    )
    names = (
        list(runs)
        if args.runs is None
        else [r for r in args.runs.split(",") if r and r != "none"]
    )
    if names:  # the files these runs read (another process may write the rest)
        n_traj = max(runs[name]["files"] for name in names) * PER_FILE
    print(f"data: {_uptime()}", flush=True)
    t0 = time.perf_counter()
    written = write_data(folder, n_traj, n_samples)
    made = time.perf_counter() - t0
    print(f"data: {made:.0f} s, {_uptime()}", flush=True)
    store = folder / "results.json"
    results = json.loads(store.read_text()) if store.exists() else {}
    if written == n_traj * n_samples:  # all written now: how long it took
        results["_data"] = {"seconds": made, "rows": written}
    for name in names:
        spec = {**runs[name], "folder": str(folder)}
        if spec["mode"] == "dask":
            spec["progress"] = str(folder / f"progress-{name}.json")
        print(f"measuring {name} {spec} ({_uptime()})", flush=True)
        res = _run(spec)
        progress = Path(spec.get("progress", folder / "none"))
        if "error" in res and progress.exists():  # stopped: what it had done
            res["progress"] = json.loads(progress.read_text())
            res["rows_per_file"] = PER_FILE * n_samples
        print({k: v for k, v in res.items() if k != "coef"}, flush=True)
        results = {**(json.loads(store.read_text()) if store.exists() else {})}
        results[name] = res
        store.write_text(json.dumps(results))
    _common.write("scale.md", report(results, runs, args, n_samples))


def report(results, runs, args, n_samples) -> str:
    text = _common.header(
        "Fits from partitioned data (Dask, Parquet): forced double pendulum",
        _common.command("scale", sys.argv[1:] if args is None else None),
    )
    data = results.get("_data")
    made = (
        f"simulated and written in {data['seconds']:.0f} s for {data['rows']:,} rows"
        if data
        else "read back from an earlier run"
    )
    text += (
        f"Data: forced double pendulum (`paper` input), noise-free, {RATE:g} Hz, "
        f"{n_samples} samples per trajectory, Parquet files of {PER_FILE} whole "
        f"trajectories ({made}; a batched fixed-step DOP853, one step per "
        "sample). "
        f"Library: the paper's ({_estimator().library.build().terms_.__len__()} "
        f"candidates), `formulation={FORMULATION!r}`, case I. Each row is a fresh "
        "process; time from reading the Parquet files to the fitted model "
        "(the Dask rows: after the cluster started, whose start time is listed "
        "apart); peak memory: the largest sum of the resident sizes of the process "
        "and its workers; load: the machine's 1-minute load average before / after "
        "the row (2 cores; other sessions ran meanwhile, so absolute times are "
        "loaded).\n\n"
    )
    text += (
        "| fit | rows | time | rows / s | of in-memory | peak memory | "
        "max coef. difference (rel.) | cluster start | load before / after |\n"
        "|---|---|---|---|---|---|---|---|---|\n"
    )
    base = results.get("memory-small")
    last = None
    for key in runs:
        r = results.get(key)
        if r is None:
            continue
        if "error" in r and "progress" in r:  # stopped: the partitions it did
            p = r["progress"]
            done = p["partitions_done"] * r["rows_per_file"]
            rate = done / p["seconds"]
            rel = "-"
            if base is not None and "error" not in base:
                rel = f"{rate / (base['rows'] / base['seconds']):.0%}"
            text += (
                f"| Dask, {r['workers']} worker(s), stopped | {done:,} of "
                f"{r['files'] * r['rows_per_file']:,} | {p['seconds']:.1f} s | "
                f"{rate:,.0f} | {rel} | {p['peak_mib']:.0f} MiB | - | - | "
                f"- / {p['load']:.1f} |\n"
            )
            continue
        if "error" in r:
            text += f"| {key} | - | error: {r['error']} | | | | | | |\n"
            continue
        last = r
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
        start = f"{r['cluster_seconds']:.0f} s" if "cluster_seconds" in r else "-"
        load = f"{r.get('load_before', float('nan')):.1f} / "
        load += f"{r.get('load_after', r.get('load', float('nan'))):.1f}"
        text += (
            f"| {name} | {r['rows']:,} | {r['seconds']:.1f} s | {rate:,.0f} | {rel} | "
            f"{r['peak_mib']:.0f} MiB | {diff} | {start} | {load} |\n"
        )
    if last is not None:
        text += f"\nLearned on the largest data: `{last['equation']}`\n"
    return text


if __name__ == "__main__":
    main(sys.argv[1:])
