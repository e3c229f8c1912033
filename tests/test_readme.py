"""Every ```python block of README.md runs as written (issue 18).

A reader copies ONE block into a fresh interpreter in an empty folder, so each block
runs on its own (see ``_markdown_blocks.py``); a ```text block right after a block
shows lines its run must print. The README is the landing page (#44): install, the
two commands, one quick start; the longer examples are in ``docs/`` and run in
``test_docs.py``.
"""

import pytest
from _markdown_blocks import ROOT, blocks, line_matches, python_blocks, run_block

README = ROOT / "README.md"
BLOCKS = python_blocks(README)


def test_readme_has_a_quick_start():
    assert len(BLOCKS) >= 1
    assert any(expected for _, _, expected in BLOCKS)


def test_readme_keeps_the_test_command():
    """``.ci/run`` runs the fenced line after ``<!-- test-command -->``."""
    text = README.read_text(encoding="utf-8")
    assert "<!-- test-command -->" in text
    after = text.split("<!-- test-command -->", 1)[1]
    lang, _, code = blocks(after)[0]
    assert lang == "bash" and "python -m pytest" in code


def test_output_matching_can_fail():
    assert line_matches("L = 0.2427*theta_dot**2", "L = 0.2427*theta_dot**2")
    assert line_matches("error 0.0483", "error 0.04834")
    assert not line_matches("L = 0.2427*theta_dot**2", "L = 0.2527*theta_dot**2")
    assert not line_matches("L = 0.2427*theta_dot**2", "L = 0.2427*theta_dot**3")
    assert not line_matches("kept 4 terms", "kept 5 terms")


@pytest.mark.parametrize(
    "line, code, expected", BLOCKS, ids=[f"line{b[0]}" for b in BLOCKS]
)
def test_readme_block_runs_alone(line, code, expected, tmp_path):
    run_block(code, expected, tmp_path, f"README.md block at line {line}")
