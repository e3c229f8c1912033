"""Help texts, defaults, wording and the import cost of ``--help``."""

import subprocess
import sys

import pytest

from ._helpers import ENV, run


@pytest.mark.parametrize(
    "command", [[], ["demo"], ["simulate"], ["simulate-model"], ["fit"], ["predict"]]
)
def test_help_everywhere(capsys, command):
    code, out, _ = run(capsys, *command, "--help")
    assert code == 0 and out.startswith("usage: lagsindy")


def _options(parser):
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from ((name, a) for a in sub._actions)


def test_every_option_has_help_and_shows_its_default():
    import argparse

    from lagsindy.cli import build_parser

    parser = build_parser()
    checked = 0
    for command, action in _options(parser):
        if isinstance(action, argparse._HelpAction):
            continue
        assert action.help, f"{command} {action.dest} has no help text"
        flag = isinstance(
            action, (argparse._StoreTrueAction, argparse._StoreConstAction)
        )
        # --system / --model of simulate: one of them is required (a group)
        grouped = command == "simulate" and action.dest in ("system", "model")
        if action.option_strings and not (flag or action.required or grouped):
            formatter = parser._get_formatter()
            text = formatter._get_help_string(action) % {"default": action.default}
            where = f"{command} {action.option_strings}"
            # options whose default is None say what not giving them does
            assert "default" in text or "required" in text, f"{where} hides its default"
            checked += 1
    assert checked > 60  # measured 64 options (50 with a default other than None)


def test_simulate_help_shows_its_defaults(capsys):
    code, out, _ = run(capsys, "simulate", "--help")
    assert code == 0
    flat = " ".join(out.split())
    for text in (
        "--trajectories TRAJECTORIES number of trajectories",
        "(default: 100)",
        "(default: 5.0)",
        "(default: 100.0)",
        "random seed of the initial states, inputs and noise (default: 0)",
    ):
        assert text in flat, flat


def test_help_imports_no_heavy_module():
    # The parser and --help need neither torch, sympy, scikit-learn nor pandas.
    code = (
        "import sys, lagsindy.cli as c\n"
        "c.build_parser()\n"
        "try:\n"
        "    c.main(['--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "heavy = [m for m in ('torch', 'sympy', 'sklearn', 'pandas', 'scipy')"
        " if m in sys.modules]\n"
        "print('HEAVY', heavy)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "HEAVY []" in proc.stdout, proc.stdout[-500:]


def test_import_lagsindy_is_lazy_but_complete():
    code = (
        "import sys, lagsindy\n"
        "assert 'torch' not in sys.modules\n"
        "from lagsindy import *\n"
        "import lagsindy.estimator as e\n"
        "assert lagsindy.LagrangianSINDy is e.LagrangianSINDy\n"
        "assert set(lagsindy.__all__) <= set(dir(lagsindy))\n"
        "print('OK')\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code],
        env=ENV,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0 and "OK" in proc.stdout, proc.stderr


def test_cli_wording_replaces_every_python_hint():
    from lagsindy.cli import _CLI_WORDING, _cli_wording

    for python, cli in _CLI_WORDING:
        assert _cli_wording(f"a {python} b") == f"a {cli} b"
    assert _cli_wording("try window=81 here") == "try window=81 here"


def test_refine_stays_the_function_when_its_module_is_imported():
    """``lagsindy.refine`` is a function and a submodule; importing the submodule
    (as the command line and the API pages do) bound the package's name to the
    module, so ``from lagsindy import refine`` gave a module."""
    code = (
        "import lagsindy.refine\n"
        "import lagsindy\n"
        "from lagsindy import refine\n"
        "from lagsindy.refine import Refinement\n"
        "assert callable(refine) and refine is lagsindy.refine, refine\n"
        "assert refine.__module__ == 'lagsindy.refine'\n"
        "print('OK')\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], env=ENV, capture_output=True, text=True,
        timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0 and "OK" in proc.stdout, proc.stderr
