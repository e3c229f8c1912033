"""Fenced code blocks of Markdown files, and running a ```python block on its own.

Used by ``test_readme.py`` (README.md) and ``test_docs.py`` (``docs/**/*.md``). A
reader copies ONE block into a fresh interpreter in an empty folder, so each block
runs on its own: a fresh ``python`` subprocess, an empty temporary working folder, and
PYTHONPATH pointing at this checkout. A block followed directly by a ```text block
shows its output: every line of that block must appear in what the run printed (same
words, numbers equal to the digits shown, within a small tolerance), so the pages'
numbers are the ones their code prints.

A fresh interpreter spends most of a block's time importing torch, scikit-learn,
scipy and sympy (about 6 s of 7 on the 2-core machine), so by default a block runs
in a child forked from a *block server*: a fresh interpreter, started once per test
process, that has imported those third-party libraries and nothing else (never
lagsindy, never another block). Each child gets its own empty folder, a fresh
``__main__`` namespace and ``sys.argv``, as ``python block.py`` would. Where
``fork`` is unsafe or missing (not Linux), with ``LAGSINDY_FRESH_BLOCKS=1``, and in
the ``-m slow`` twins of the block tests (``fresh=True``), each block runs in its own
``python`` subprocess instead.
"""

import atexit
import json
import math
import os
import re
import selectors
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_FENCE = re.compile(r"^(`{3,})(\S*)\s*$")  # ```python, ```{eval-rst}, ```
_NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def blocks(text, name="the file"):
    """(language, first line number, code) of every fenced block, in order."""
    out, lang, fence, start, body = [], None, None, 0, []
    for i, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        if lang is None:
            m = _FENCE.match(stripped)
            if m:
                fence, lang, start, body = m.group(1), m.group(2), i, []
        elif stripped == fence:
            out.append((lang, start, "\n".join(body) + "\n"))
            lang = None
        else:
            body.append(line)
    assert lang is None, f"{name}: the block opened at line {start} is not closed"
    return out


def python_blocks(path):
    """(line, code, expected output or None) for each ```python block of ``path``."""
    text = Path(path).read_text(encoding="utf-8")
    found = blocks(text, str(path))
    lines = text.splitlines()
    out = []
    for k, (lang, start, code) in enumerate(found):
        if lang != "python":
            continue
        expected = None
        if k + 1 < len(found) and found[k + 1][0] == "text":
            end = start + code.count("\n") + 1  # the closing fence of this block
            between = lines[end : found[k + 1][1] - 1]
            if not any(s.strip() for s in between):
                expected = found[k + 1][2]
        out.append((start, code, expected))
    return out


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


def line_matches(shown, printed):
    """Same words, and each number of ``printed`` rounds to the one ``shown``."""
    w1, n1 = _skeleton(shown)
    w2, n2 = _skeleton(printed)
    return w1 == w2 and all(_close(a, b) for a, b in zip(n1, n2))


_SERVER_CODE = r"""
import json, os, runpy, sys, traceback
import numpy, pandas, scipy.integrate, scipy.linalg, sklearn.base, sympy, torch
for line in sys.stdin:
    script, work, out, err = json.loads(line)
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
            os.dup2(os.open(out, flags), 1)
            os.dup2(os.open(err, flags), 2)
            os.chdir(work)
            sys.argv = [script]
            sys.path[0] = os.path.dirname(script)
            try:
                runpy.run_path(script, run_name="__main__")
                code = 0
            except SystemExit as exc:
                if exc.code is None or isinstance(exc.code, int):
                    code = exc.code or 0
                else:
                    print(exc.code, file=sys.stderr)
            except BaseException:
                traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    status = os.waitpid(pid, 0)[1]
    print(json.dumps(os.waitstatus_to_exitcode(status)), flush=True)
"""
_SERVER = None


def _env():
    return {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "MPLBACKEND": "Agg",
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1"),
    }


def _use_server():
    return sys.platform.startswith("linux") and not os.environ.get(
        "LAGSINDY_FRESH_BLOCKS"
    )


def _server():
    global _SERVER
    if _SERVER is None or _SERVER.poll() is not None:
        _SERVER = subprocess.Popen(
            [sys.executable, "-c", _SERVER_CODE],
            env=_env(),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        atexit.register(_SERVER.kill)
    return _SERVER


def _run_forked(script, work, timeout):
    """(exit status, stdout, stderr) of ``script`` run by the block server."""
    out, err = work.parent / "stdout.txt", work.parent / "stderr.txt"
    server = _server()
    server.stdin.write(json.dumps([str(script), str(work), str(out), str(err)]))
    server.stdin.write("\n")
    server.stdin.flush()
    with selectors.DefaultSelector() as sel:
        sel.register(server.stdout, selectors.EVENT_READ)
        if not sel.select(timeout):
            server.kill()
            raise TimeoutError(f"the block ran longer than {timeout} s")
    status = json.loads(server.stdout.readline())
    return status, out.read_text(), err.read_text()


def run_block(code, expected, tmp_path, where, *, fresh=False):
    """Run ``code`` alone in an empty folder; check the lines ``expected`` shows.
    ``fresh``: in its own ``python`` subprocess (else by the block server where
    that is used; see the module docstring)."""
    script = tmp_path / "block.py"
    script.write_text(code, encoding="utf-8")
    work = tmp_path / "empty"
    work.mkdir()
    start = time.monotonic()
    if fresh or not _use_server():
        proc = subprocess.run(
            [sys.executable, str(script)],
            cwd=work,
            env=_env(),
            text=True,
            capture_output=True,
            timeout=300,
        )
        status, stdout, stderr = proc.returncode, proc.stdout, proc.stderr
    else:
        status, stdout, stderr = _run_forked(script, work, 300)
    elapsed = time.monotonic() - start
    assert status == 0, f"{where} failed:\n{stderr[-3000:]}"
    if expected is not None:
        printed = stdout.splitlines()
        for shown in expected.splitlines():
            if not shown.strip():
                continue
            assert any(line_matches(shown, p) for p in printed), (
                f"{where} shows\n  {shown}\nbut printed\n" + stdout[-3000:]
            )
    print(f"{where}: {elapsed:.1f} s")
