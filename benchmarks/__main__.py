"""Run the benchmark scripts: ``python -m benchmarks [--quick] [NAME ...]``.

Every module ``benchmarks/<name>.py`` whose name does not start with ``_`` and that
defines ``main(argv)`` is a benchmark. With ``--quick`` each runs at reduced size and
writes ``results/<name>_quick.md`` (ignored by git), so committed full-size results
are never overwritten by a smoke check. Without it they run at full size.

    python -m benchmarks --quick                 # all of them, reduced (minutes)
    python -m benchmarks paper_tables sindy_pi   # these two, full size
    python -m benchmarks --list

A benchmark that needs something optional is skipped with a message instead of
ending the run: one that raises ImportError (a missing package, e.g. pysindy for
``sindy_pi``: ``pip install -e ".[bench]"``) or FileNotFoundError (missing data,
e.g. the MultiArm-Pendulum recordings for ``measured``), and, under ``--quick``, one
whose command line has no ``--quick`` option. The exit status is 1 only when a
benchmark failed.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import pkgutil
import resource
import sys
import time
import traceback
from pathlib import Path

from . import _common


def discover() -> dict:
    """``{name: module}`` of every benchmark module that defines ``main(argv)``."""
    here = Path(__file__).resolve().parent
    found = {}
    for info in sorted(pkgutil.iter_modules([str(here)]), key=lambda m: m.name):
        if info.name.startswith("_") or info.ispkg:
            continue
        module = importlib.import_module(f"{__package__}.{info.name}")
        if callable(getattr(module, "main", None)):
            found[info.name] = module
    return found


def _cpu() -> float:
    """CPU seconds of this process so far (all threads), user + system."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def accepts_quick(module) -> bool:
    """Whether the benchmark's command line knows ``--quick`` (read from its source)."""
    try:
        return '"--quick"' in inspect.getsource(module)
    except (OSError, TypeError):  # no source: try it
        return True


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks", description=__doc__.splitlines()[0]
    )
    parser.add_argument("names", nargs="*", help="benchmarks to run (default: all)")
    parser.add_argument(
        "--quick", action="store_true", help="reduced sizes, *_quick.md"
    )
    parser.add_argument(
        "--list", action="store_true", help="list the benchmarks and exit"
    )
    args = parser.parse_args(argv)
    found = discover()
    if args.list:
        for name, module in found.items():
            doc = (module.__doc__ or "").strip().splitlines()
            print(f"{name}: {doc[0] if doc else ''}")
        return 0
    unknown = [n for n in args.names if n not in found]
    if unknown:
        parser.error(f"unknown benchmark(s) {unknown}; available: {sorted(found)}")
    names = args.names or list(found)
    sub_argv = ["--quick"] if args.quick else []
    failed, skipped = [], []
    start_all, cpu_all = time.perf_counter(), _cpu()
    for name in names:
        _common.RUNNER_COMMAND = f"python -m benchmarks {' '.join(sub_argv + [name])}"
        print(f"=== {name} {' '.join(sub_argv)}", flush=True)
        if args.quick and not accepts_quick(found[name]):
            print(f"=== {name}: SKIPPED: its command line has no --quick option")
            skipped.append(name)
            continue
        start, cpu = time.perf_counter(), _cpu()
        try:
            found[name].main(list(sub_argv))
        except (ImportError, FileNotFoundError) as exc:
            # Optional packages or data: say what is missing and go on.
            print(f"=== {name}: SKIPPED: {type(exc).__name__}: {exc}", flush=True)
            skipped.append(name)
            continue
        except SystemExit as exc:  # argparse errors of the benchmark's own parser
            if exc.code not in (0, None):
                print(f"=== {name}: exited with status {exc.code}", flush=True)
                failed.append(name)
        except Exception:  # one broken benchmark must not hide the others' results
            traceback.print_exc()
            failed.append(name)
        finally:
            _common.RUNNER_COMMAND = None
        print(
            f"=== {name}: {time.perf_counter() - start:.1f} s "
            f"({_cpu() - cpu:.1f} CPU s)",
            flush=True,
        )
    print(
        f"all done in {time.perf_counter() - start_all:.1f} s "
        f"({_cpu() - cpu_all:.1f} CPU s)"
        + (f"; skipped: {skipped}" if skipped else "")
        + (f"; FAILED: {failed}" if failed else "")
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
