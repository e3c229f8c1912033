"""Every ```python block of README.md runs as written (issue 18).

A reader copies ONE block into a fresh interpreter in an empty folder, so each block
runs on its own: a fresh ``python`` subprocess, an empty temporary working folder, and
PYTHONPATH pointing at this checkout. A block followed directly by a ```text block
shows its output: every line of that block must appear in what the run printed (same
words, numbers equal to the digits shown, within a small tolerance), so the README's
numbers are the ones its code prints.
"""

import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
_FENCE = re.compile(r"^```([\w-]*)\s*$")
_NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def _blocks(text):
    """(language, first line number, code) of every fenced block, in order."""
    blocks, lang, start, body = [], None, 0, []
    for i, line in enumerate(text.splitlines(), 1):
        m = _FENCE.match(line.strip())
        if lang is None:
            if m:
                lang, start, body = m.group(1), i, []
        elif line.strip() == "```":
            blocks.append((lang, start, "\n".join(body) + "\n"))
            lang = None
        else:
            body.append(line)
    assert lang is None, f"README.md: the block opened at line {start} is not closed"
    return blocks


def _python_blocks():
    """(line, code, expected output or None) for each ```python block."""
    text = README.read_text(encoding="utf-8")
    blocks = _blocks(text)
    lines = text.splitlines()
    out = []
    for k, (lang, start, code) in enumerate(blocks):
        if lang != "python":
            continue
        expected = None
        if k + 1 < len(blocks) and blocks[k + 1][0] == "text":
            end = start + code.count("\n") + 1  # the closing fence of this block
            between = lines[end : blocks[k + 1][1] - 1]
            if not any(s.strip() for s in between):
                expected = blocks[k + 1][2]
        out.append((start, code, expected))
    return out


BLOCKS = _python_blocks()


def _skeleton(line):
    """A line's words (numbers replaced by '#') and its numbers."""
    numbers = _NUMBER.findall(line)
    words = _NUMBER.sub("#", line).split()
    return words, numbers


def _close(shown, printed):
    """``printed`` rounds to ``shown`` (or nearly: 1 in the last digit, 0.5 % rel)."""
    a, b = float(shown), float(printed)
    if "e" in shown.lower() or "." not in shown:
        ulp = 0.0
    else:
        ulp = 10.0 ** -len(shown.split(".")[1].split("e")[0])
    return math.isclose(a, b, rel_tol=5e-3, abs_tol=ulp * 1.01)


def _line_matches(shown, printed):
    w1, n1 = _skeleton(shown)
    w2, n2 = _skeleton(printed)
    return w1 == w2 and all(_close(a, b) for a, b in zip(n1, n2))


def test_readme_has_python_blocks():
    # The README shows quick start, own data, lam search, diagnosis, save/load, plots.
    assert len(BLOCKS) >= 6


def test_output_matching_can_fail():
    assert _line_matches("L = 0.2427*theta_dot**2", "L = 0.2427*theta_dot**2")
    assert _line_matches("error 0.0483", "error 0.04834")
    assert not _line_matches("L = 0.2427*theta_dot**2", "L = 0.2527*theta_dot**2")
    assert not _line_matches("L = 0.2427*theta_dot**2", "L = 0.2427*theta_dot**3")
    assert not _line_matches("kept 4 terms", "kept 5 terms")


@pytest.mark.parametrize(
    "line, code, expected", BLOCKS, ids=[f"line{b[0]}" for b in BLOCKS]
)
def test_readme_block_runs_alone(line, code, expected, tmp_path):
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "MPLBACKEND": "Agg",
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1"),
    }
    script = tmp_path / "block.py"
    script.write_text(code, encoding="utf-8")
    work = tmp_path / "empty"
    work.mkdir()
    start = time.monotonic()
    proc = subprocess.run(
        [sys.executable, str(script)],
        cwd=work,
        env=env,
        text=True,
        capture_output=True,
        timeout=300,
    )
    elapsed = time.monotonic() - start
    assert proc.returncode == 0, (
        f"README.md block at line {line} failed:\n{proc.stderr[-3000:]}"
    )
    if expected is not None:
        printed = proc.stdout.splitlines()
        for shown in expected.splitlines():
            if not shown.strip():
                continue
            assert any(_line_matches(shown, p) for p in printed), (
                f"README.md block at line {line} shows\n  {shown}\nbut printed\n"
                + proc.stdout[-3000:]
            )
    print(f"README block at line {line}: {elapsed:.1f} s")
