"""Run the benchmark scripts: ``python -m benchmarks [--quick] [NAME ...]``.

Every module ``benchmarks/<name>.py`` whose name does not start with ``_`` and that
defines ``main(argv)`` is a benchmark. With ``--quick`` each runs at reduced size and
writes ``results/<name>_quick.md`` (ignored by git), so committed full-size results
are never overwritten by a smoke check. Without it they run at full size.

    python -m benchmarks --quick                 # all of them, reduced (minutes)
    python -m benchmarks paper_tables sindy_pi   # these two, full size
    python -m benchmarks --list
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
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
    failed = []
    start_all = time.perf_counter()
    for name in names:
        _common.RUNNER_COMMAND = f"python -m benchmarks {' '.join(sub_argv + [name])}"
        print(f"=== {name} {' '.join(sub_argv)}", flush=True)
        start = time.perf_counter()
        try:
            found[name].main(list(sub_argv))
        except Exception:  # one broken benchmark must not hide the others' results
            traceback.print_exc()
            failed.append(name)
        finally:
            _common.RUNNER_COMMAND = None
        print(f"=== {name}: {time.perf_counter() - start:.1f} s", flush=True)
    print(
        f"all done in {time.perf_counter() - start_all:.1f} s"
        + (f"; FAILED: {failed}" if failed else "")
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
