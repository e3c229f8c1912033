"""Every ```python block of README.md runs as written (issue 18).

A reader copies ONE block into a fresh interpreter in an empty folder, so each block
runs on its own (see ``_markdown_blocks.py``); a ```text block right after a block
shows lines its run must print. The README is the landing page (#44): install, the
two commands, one quick start; the longer examples are in ``docs/`` and run in
``test_docs.py``.
"""

import re

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


def broken_links(text, base=ROOT):
    """Relative Markdown links of ``text`` whose file (or folder) does not exist."""
    out = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # https:, mailto:, an anchor on the same page
        if not (base / target.split("#", 1)[0]).exists():
            out.append(target)
    return out


def test_readme_links_resolve():
    text = README.read_text(encoding="utf-8")
    assert len(re.findall(r"\]\(docs/", text)) >= 10  # measured 18
    assert broken_links(text) == []


def test_broken_links_can_fail():
    text = "[a](docs/index.md) [b](docs/nowhere.md#x) [c](https://x.org) [d](#top)"
    assert broken_links(text) == ["docs/nowhere.md#x"]


def test_readme_is_a_landing_page():
    """Install, the two commands, one quick start, links (#44): not a manual."""
    text = README.read_text(encoding="utf-8")
    for heading in (
        "## Install",
        "## Two commands",
        "## Quick start",
        "## Documentation",
    ):
        assert heading in text
    assert len(text.splitlines()) <= 160  # 130 lines when written (490 before #44)
    assert len(BLOCKS) <= 2


def test_output_matching_can_fail():
    assert line_matches("L = 0.2427*theta_dot**2", "L = 0.2427*theta_dot**2")
    assert line_matches("error 0.0483", "error 0.04834")
    assert not line_matches("L = 0.2427*theta_dot**2", "L = 0.2527*theta_dot**2")
    assert not line_matches("L = 0.2427*theta_dot**2", "L = 0.2427*theta_dot**3")
    assert not line_matches("kept 4 terms", "kept 5 terms")


@pytest.mark.parametrize(
    "line, code, expected", BLOCKS, ids=[f"line{b[0]}" for b in BLOCKS]
)
@pytest.mark.parametrize("fresh", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_readme_block_runs_alone(line, code, expected, fresh, tmp_path):
    run_block(code, expected, tmp_path, f"README.md block at line {line}", fresh=fresh)
