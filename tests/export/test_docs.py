"""Every ```python block of docs/using_the_model.md runs as written.

Each block runs on its own in a fresh interpreter and an empty folder (all blocks at
once, as subprocesses). A block that imports casadi is skipped where CasADi is not
installed (it is an optional dependency); one that compiles C, where no compiler is.
"""

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from lagsindy.export import find_compiler

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "using_the_model.md"


def _python_blocks():
    blocks = re.findall(r"^```python\n(.*?)^```$", DOC.read_text(), re.M | re.S)
    assert len(blocks) >= 5
    return blocks


BLOCKS = _python_blocks()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    procs = []
    for k, code in enumerate(BLOCKS):
        needs_casadi = "import casadi" in code
        if needs_casadi and importlib.util.find_spec("casadi") is None:
            procs.append(None)
            continue
        procs.append(
            subprocess.Popen(
                [sys.executable, "-c", code],
                cwd=tmp_path_factory.mktemp(f"block{k}"),
                env=env,
                text=True,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
            )
        )
    return [
        None if p is None else (*p.communicate(timeout=600), p.returncode)
        for p in procs
    ]


@pytest.mark.parametrize("k", range(len(BLOCKS)))
def test_block_runs(runs, k):
    if runs[k] is None:
        pytest.skip("CasADi is not installed")
    if "compile_c" in BLOCKS[k] and find_compiler() is None:
        pytest.skip("no C compiler")
    out, err, code = runs[k]
    assert code == 0, f"block {k}:\n{BLOCKS[k]}\n{err[-3000:]}"
    assert out.strip()
