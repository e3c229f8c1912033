"""The documentation (#44): its code runs, it builds without a warning, every public
name has a page, and (slow) the example gallery runs.

The build needs the ``docs`` extra (``pip install -e ".[docs]"``); without Sphinx and
its extensions those tests are skipped. They build a copy of ``docs/`` in a temporary
folder (``LAGSINDY_DOCS_ROOT`` points ``conf.py`` at this checkout), so the source
tree gets no generated files.
"""

import importlib
import os
import pkgutil
import shutil
import subprocess
import sys

import pytest
from _markdown_blocks import ROOT, blocks, python_blocks, run_block

import lagsindy

DOCS = ROOT / "docs"
GENERATED = ("_build", "api/generated", "auto_examples", "benchmarks/results")
# Public submodules that the API pages do not list, and why. Every other public
# submodule has a module page; those with an __all__, a page for each of its names.
NOT_IN_THE_API = {
    "cli": "the command line, documented in cli.md",
    "estimator": "LagrangianSINDy, documented in lagsindy's namespace",
    "library": "CandidateLibrary, documented in lagsindy's namespace",
    "refine": "refine and Refinement, documented in lagsindy's namespace",
    "model": "the fitted Lagrangian behind the estimator's methods",
    "euler_lagrange": "defines no public name",
    "angle_units": "helpers of the fit's warnings about angle units",
}


def _pages():
    for path in sorted(DOCS.rglob("*.md")):
        rel = path.relative_to(DOCS).as_posix()
        if not any(rel.startswith(g + "/") for g in GENERATED):
            yield path


BLOCKS = [
    (path.relative_to(ROOT).as_posix(), *block)
    for path in _pages()
    for block in python_blocks(path)
]


# Fence languages the pages may use: ```python blocks run here; the others are shown
# only (```pycon: an illustration that needs a cluster or the user's files). Any
# other spelling of Python (```py, ```{code-block} python, ```{code-cell}) would be
# neither run nor noticed.
SHOWN_ONLY = {"text", "bash", "pycon", "{eval-rst}", "{toctree}", "{include}", ""}


def test_the_guide_has_runnable_examples():
    assert len(BLOCKS) >= 30  # measured 39 on 17 pages (#44's topic pages included)
    pages = {page for page, *_ in BLOCKS}
    for name in ("clocks", "undriven", "robots", "scale", "using_the_model"):
        assert f"docs/{name}.md" in pages
    for name in ("force_kinds", "evaluator", "solvers", "user_guide/fitting"):
        assert f"docs/{name}.md" in pages


def unrun_blocks(text):
    """(line, language) of the fenced blocks that are neither run nor shown-only."""
    return [
        (line, lang)
        for lang, line, _ in blocks(text)
        if lang != "python" and lang not in SHOWN_ONLY
    ]


def test_unrun_blocks_can_fail():
    text = "```python\nx = 1\n```\n```text\n1\n```\n```py\nx = 2\n```\n"
    assert unrun_blocks(text) == [(7, "py")]


def test_every_code_block_is_run_or_shown_only():
    for path in _pages():
        found = unrun_blocks(path.read_text(encoding="utf-8"))
        assert found == [], (
            f"{path.relative_to(ROOT)}: blocks (line, language) {found} are not run "
            "by this test: write runnable code as ```python"
        )


@pytest.mark.parametrize("fresh", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_a_block_runs_alone_and_can_fail(fresh, tmp_path):
    """The block runner (the block server's forked children, or a fresh
    interpreter each): a block sees nothing of another, in its own empty folder."""

    def run(code, expected=None):
        folder = tmp_path / f"b{len(list(tmp_path.iterdir()))}"
        folder.mkdir()
        run_block(code, expected, folder, "test block", fresh=fresh)

    run("import os\nx = 1\nopen('left.txt', 'w').write('x')\nprint(os.listdir())")
    with pytest.raises(AssertionError, match="NameError"):
        run("print(x)")  # the previous block's name is not there
    with pytest.raises(AssertionError, match="left.txt"):
        run(
            "import os\nassert not os.listdir(), os.listdir()\nopen('left.txt', 'w')\n"
            "import sys\nsys.exit(os.listdir())"
        )
    with pytest.raises(AssertionError, match="failed"):
        run("import sys\nsys.exit(3)")
    run("import sys\nsys.exit(0)")
    with pytest.raises(AssertionError, match="but printed"):
        run("print('L = 0.31*x')", "L = 0.24*x")
    run("if __name__ == '__main__':\n    print('L = 0.25*x')", "L = 0.25*x")
    with pytest.raises(AssertionError, match="not yet imported"):
        run("import sys\nassert 'lagsindy' in sys.modules, 'not yet imported'")


@pytest.mark.parametrize(
    "page, line, code, expected", BLOCKS, ids=[f"{b[0]}:{b[1]}" for b in BLOCKS]
)
@pytest.mark.parametrize("fresh", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_docs_block_runs_alone(page, line, code, expected, fresh, tmp_path):
    # optional dependencies: CasADi (the "casadi" extra) and a C compiler
    if "import casadi" in code:
        pytest.importorskip("casadi", reason="CasADi is not installed")
    if "compile_c" in code:
        from lagsindy.export import find_compiler

        if find_compiler() is None:
            pytest.skip("no C compiler")
    run_block(code, expected, tmp_path, f"{page} block at line {line}", fresh=fresh)


def _need_sphinx():
    for name in (
        "sphinx",
        "numpydoc",
        "sphinx_gallery",
        "pydata_sphinx_theme",
        "myst_parser",
    ):
        pytest.importorskip(name, reason=f'{name} is not installed (".[docs]" extra)')


def _build(tmp_path, *options, timeout=1800):
    """Build a copy of docs/ with warnings as errors; returns the HTML folder."""
    source = tmp_path / "docs"
    shutil.copytree(
        DOCS,
        source,
        ignore=lambda folder, names: [
            n
            for n in names
            if (os.path.relpath(os.path.join(folder, n), DOCS).replace(os.sep, "/"))
            in GENERATED
        ],
    )
    html = tmp_path / "html"
    env = {
        **os.environ,
        "LAGSINDY_DOCS_ROOT": str(ROOT),
        "PYTHONPATH": str(ROOT),
        "MPLBACKEND": "Agg",
        "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1"),
    }
    proc = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-b", "html"]
        + list(options)
        + [str(source), str(html)],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    warnings = [
        line
        for line in (proc.stdout + proc.stderr).splitlines()
        if "WARNING" in line or "ERROR" in line
    ]
    assert proc.returncode == 0, "\n".join(warnings[:40]) or proc.stderr[-3000:]
    return html


def _public_modules():
    """``{name: module}`` of the package's public submodules (not NOT_IN_THE_API)."""
    out = {}
    for info in pkgutil.iter_modules(lagsindy.__path__):
        if info.name.startswith("_") or info.name in NOT_IN_THE_API:
            continue
        out[info.name] = importlib.import_module(f"lagsindy.{info.name}")
    return out


def missing_pages(generated):
    """Public names without an API page, given the generated pages' names."""
    pages = {p.removesuffix(".html") for p in generated}
    missing = [
        f"lagsindy.{name}"
        for name in lagsindy.__all__
        if name != "__version__" and f"lagsindy.{name}" not in pages
    ]
    for mod_name, module in _public_modules().items():
        full = f"lagsindy.{mod_name}"
        if full not in pages:
            missing.append(f"{full} (module page)")
            continue
        for name in getattr(module, "__all__", []):
            if f"{full}.{name}" in pages:
                continue
            shared = name in lagsindy.__all__ and getattr(lagsindy, name) is getattr(
                module, name
            )
            if not (shared and f"lagsindy.{name}" in pages):
                missing.append(f"{full}.{name}")
    return missing


def test_missing_pages_can_fail():
    assert missing_pages([]) and "lagsindy.LagrangianSINDy" in missing_pages([])
    everything = {f"lagsindy.{n}.html" for n in lagsindy.__all__}
    for mod_name, module in _public_modules().items():
        everything.add(f"lagsindy.{mod_name}.html")
        everything |= {
            f"lagsindy.{mod_name}.{n}.html" for n in getattr(module, "__all__", [])
        }
    assert missing_pages(everything) == []
    assert missing_pages(everything - {"lagsindy.systems.make_dataset.html"}) == [
        "lagsindy.systems.make_dataset"
    ]
    # a module without __all__ needs its page too
    assert missing_pages(everything - {"lagsindy.force_kinds.html"}) == [
        "lagsindy.force_kinds (module page)"
    ]


def test_modules_left_out_of_the_api_exist():
    names = {info.name for info in pkgutil.iter_modules(lagsindy.__path__)}
    assert set(NOT_IN_THE_API) <= names


def test_docs_build_without_warnings_and_every_public_name_has_a_page(tmp_path):
    _need_sphinx()
    html = _build(tmp_path, "-D", "plot_gallery=0")
    assert (html / "index.html").exists()
    generated = [p.name for p in (html / "api" / "generated").glob("*.html")]
    assert missing_pages(generated) == [], (
        "add these names to docs/api/index.md (or to a public module's __all__, "
        "whose page lists it)"
    )
    # every benchmark results file has its page, every example its gallery page
    for path in (ROOT / "benchmarks" / "results").glob("*.md"):
        if not path.stem.endswith("_quick"):
            assert (html / "benchmarks" / "results" / f"{path.stem}.html").exists()
    for path in (ROOT / "examples").glob("*.py"):
        assert (html / "auto_examples" / f"{path.stem}.html").exists()


@pytest.mark.slow  # runs every example inside the build
def test_docs_gallery_runs(tmp_path):
    _need_sphinx()
    html = _build(tmp_path, timeout=3600)
    for path in (ROOT / "examples").glob("*.py"):
        page = html / "auto_examples" / f"{path.stem}.html"
        if page.exists():  # (an example whose optional package is missing is left out)
            assert "sphx-glr-script-out" in page.read_text(), (
                f"{path.name} printed nothing"
            )
    # the real recordings: the fit's ratio and the diagnosis's validation score
    measured = (html / "auto_examples" / "measured_pendulum.html").read_text()
    assert "ratio cos(phi)/phi_dot**2" in measured
    assert "validation R^2 after the diagnosis" in measured
