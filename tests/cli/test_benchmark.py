"""``benchmarks/cli.py`` runs and writes its tables (tiny sizes)."""

import pytest


@pytest.mark.slow  # about 20 s idle: one run of each command on a 600-row record
def test_cli_benchmark_tiny(tmp_path, monkeypatch):
    import benchmarks._common as common
    from benchmarks import cli

    monkeypatch.setenv("LAGSINDY_BENCH_TINY", "1")
    monkeypatch.setattr(common, "RESULTS", tmp_path)
    assert cli.main(["--quick"]) == 0
    text = (tmp_path / "cli_quick.md").read_text()
    assert "- command: `LAGSINDY_BENCH_TINY=1 python -m benchmarks.cli --quick`" in text
    for name in ("bad column", "missing file", "bad option (--lam -1)"):
        row = next(line for line in text.splitlines() if line.startswith(f"| {name} "))
        assert "| this | 2 |" in row, row
    fit = next(line for line in text.splitlines() if line.startswith("| this | "))
    assert fit.endswith("| 0 |") and fit.count(" s / ") == 6, fit
    assert "reading " in text and "building the candidate library poly3" in text
