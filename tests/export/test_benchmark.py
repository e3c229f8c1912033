"""benchmarks/export.py runs end to end at its quick size (the figures are in
benchmarks/results/export.md)."""

import importlib.util

from benchmarks import export as bench
from lagsindy.export import find_compiler


def test_quick_benchmark_writes_every_variant(tmp_path):
    out = tmp_path / "export_quick.md"
    assert bench.main(["--quick", "--out", str(out)]) == 0
    text = out.read_text()
    assert "- command: `python -m benchmarks.export --quick" in text
    assert "Load average (1 min) at the start" in text
    for system in ("cart pendulum", "triple pendulum"):
        assert f"## {system}" in text
    rows = [line for line in text.splitlines() if line.startswith("| exported numpy")]
    assert len(rows) == 4
    c_rows = 3 if find_compiler() is not None else 0
    casadi_rows = 2 if importlib.util.find_spec("casadi") is not None else 0
    variants = ("| C via", "| C inside", "| CasADi")
    found = sum(line.startswith(variants) for line in text.splitlines())
    assert found == 2 * (c_rows + casadi_rows)
    assert "## Targets" in text
    # every variant agrees with the estimator (the last column)
    for line in text.splitlines():
        if line.startswith(("| exported", *variants)):
            assert float(line.rstrip(" |").split("|")[-1]) < 1e-12
