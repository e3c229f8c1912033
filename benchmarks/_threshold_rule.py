"""Run a benchmark with another hard-threshold rule, to compare before and after.

    python -m benchmarks._threshold_rule None robustness --quick --workers 1
    python -m benchmarks._threshold_rule 0.25 robustness --quick --workers 1

The first argument is the default ``StagedFISTA(equation_threshold=...)`` for every
fit the benchmark makes (``None``: the paper's global rule alone; the library's
default is 0.25); the second the benchmark module, then its own arguments. Results
go to ``benchmarks/results/threshold_<value>/`` so that the committed results stay
those of the defaults. ``benchmarks/results/threshold.md`` summarizes the runs.
"""

from __future__ import annotations

import importlib
import sys
import time


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    value, which, rest = argv[0], argv[1], argv[2:]
    from lagsindy.solvers import settings

    defaults = list(settings.StagedFISTA.__init__.__defaults__)
    defaults[-1] = None if value == "None" else float(value)
    settings.StagedFISTA.__init__.__defaults__ = tuple(defaults)
    from . import _common

    _common.RESULTS = _common.RESULTS / f"threshold_{value}"
    _common.RESULTS.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    importlib.import_module(f"benchmarks.{which}").main(rest)
    print(f"{which} with equation_threshold={value}: {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
