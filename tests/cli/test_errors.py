"""Bad input: one line on stderr, exit status 2, before the slow work (#7, #44)."""

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lagsindy.cli import main

from ._helpers import ENV, run


def _bad_files(d):
    df = pd.read_csv(d / "data.csv")
    nan = df.copy()
    nan.loc[17, "theta"] = np.nan
    nan.to_csv(d / "nan.csv", index=False)
    text = df.astype({"x": object})
    text.loc[3, "x"] = "oops"
    text.to_csv(d / "text.csv", index=False)
    (d / "empty.csv").write_text("")
    lines = (d / "data.csv").read_text().splitlines()
    lines[5] = ",".join(lines[5].split(",")[:3])  # data row 4 cut after 3 fields
    (d / "short.csv").write_text("\n".join(lines) + "\n")
    (d / "header.csv").write_text("t,x\n")
    df[["x", "theta"]].to_csv(d / "no_t.csv", index=False)
    (d / "bad.json").write_text('{"format": "lagsindy-model"')
    doc = json.loads((d / "model.json").read_text())
    doc["terms"][0] = "__import__('os').system('touch pwned')"
    (d / "evil.json").write_text(json.dumps(doc))


BAD = [
    (
        ["fit", "{d}/none.csv", "--coordinates", "x", "--out", "{d}/o.json"],
        "file not found",
    ),
    (
        ["fit", "{d}/data.csv", "--coordinates", "x,phi", "--out", "{d}/o.json"],
        "no column 'phi'",
    ),
    (["fit", "{d}/nan.csv", "--coordinates", "x,theta", "--out", "{d}/o.json"], "NaN"),
    (
        ["fit", "{d}/short.csv", "--coordinates", "x,theta", "--out", "{d}/o.json"],
        r"on line 6 \(line 6 holds 3 of the header's \d+ fields: a row cut short\?\)",
    ),
    (
        ["fit", "{d}/text.csv", "--coordinates", "x,theta", "--out", "{d}/o.json"],
        "not numeric",
    ),
    (["fit", "{d}/empty.csv", "--coordinates", "x", "--out", "{d}/o.json"], "empty"),
    (["fit", "{d}/header.csv", "--coordinates", "x", "--out", "{d}/o.json"], "no rows"),
    (
        ["fit", "{d}/no_t.csv", "--coordinates", "x,theta", "--out", "{d}/o.json"],
        "'t' column",
    ),
    (
        [
            "fit",
            "{d}/data.csv",
            "--coordinates",
            "x,theta",
            "--input",
            "tau_x",
            "--out",
            "{d}/o.json",
        ],
        "one generalized-force column per coordinate",
    ),
    (
        [
            "fit",
            "{d}/data.csv",
            "--coordinates",
            "x,theta",
            "--input",
            "tau_x,nope",
            "--out",
            "{d}/o.json",
        ],
        "no column 'nope'",
    ),
    (
        [
            "fit",
            "{d}/data.csv",
            "--coordinates",
            "x,theta",
            "--library",
            "cubic",
            "--out",
            "{d}/o.json",
        ],
        "--library",
    ),
    (
        [
            "fit",
            "{d}/data.csv",
            "--coordinates",
            "x,theta",
            "--passive",
            "--fixed-term",
            "__import__('os')",
            "--out",
            "{d}/o.json",
        ],
        "not valid|unexpected",
    ),
    (
        [
            "fit",
            "{d}/data.csv",
            "--coordinates",
            "x,theta",
            "--lam",
            "-1",
            "--out",
            "{d}/o.json",
        ],
        "lam",
    ),
    (
        [
            "fit",
            "{d}/data.csv",
            "--coordinates",
            "x,theta",
            "--out",
            "{d}/nodir/o.json",
        ],
        "does not exist",
    ),
    (
        [
            "fit",
            "{d}/data.csv",
            "--coordinates",
            "x,theta",
            "--angles",
            "phi",
            "--out",
            "{d}/o.json",
        ],
        "--angles",
    ),
    (["fit", "{d}/data.csv", "--out", "{d}/o.json"], "--coordinates"),
    (
        [
            "fit",
            "{d}/data.csv",
            "--coordinates",
            "x,theta",
            "--lam",
            "abc",
            "--out",
            "{d}/o.json",
        ],
        "invalid float",
    ),
    (
        ["predict", "{d}/bad.json", "{d}/data.csv", "--out", "{d}/p.csv"],
        "not valid JSON",
    ),
    (["predict", "{d}/evil.json", "{d}/data.csv", "--out", "{d}/p.csv"], "not valid"),
    (["predict", "{d}/none.json", "{d}/data.csv", "--out", "{d}/p.csv"], "not found"),
    (["predict", "{d}/model.json", "{d}/nan.csv", "--out", "{d}/p.csv"], "NaN"),
    (
        ["simulate-model", "{d}/model.json", "--x0", "0,1", "--out", "{d}/s.csv"],
        "has 2 value",
    ),
    (
        ["simulate-model", "{d}/model.json", "--x0", "0,a,0,0", "--out", "{d}/s.csv"],
        "numbers",
    ),
    (
        ["simulate-model", "{d}/model.json", "--x0", "0,nan,0,0", "--out", "{d}/s.csv"],
        "NaN",
    ),
    (["simulate", "--system", "nosuch", "--out", "{d}/s.csv"], "unknown system"),
    (["simulate", "--out", "{d}/s.csv"], "--system"),
    (["simulate", "--system", "cart", "--noise", "-1", "--out", "{d}/s.csv"], "noise"),
    (["demo", "--system", "nosuch"], "unknown system"),
    (["nosuch"], "invalid choice"),
]


@pytest.mark.parametrize("args, message", BAD)
def test_bad_input_gives_one_line_and_status_2(capsys, workdir, args, message):
    if not (workdir / "evil.json").exists():
        _bad_files(workdir)
    args = [a.format(d=workdir) for a in args]
    code, _, err = run(capsys, *args)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("lagsindy")
    assert "error" in lines[0] and "Traceback" not in err
    assert re.search(message, lines[0]), lines[0]
    assert not (workdir / "pwned").exists() and not Path("pwned").exists()


@pytest.mark.skipif(
    shutil.which("lagsindy") is None, reason="console script not installed"
)
def test_console_script_bad_input_one_line(tmp_path):
    proc = subprocess.run(
        ["lagsindy", "fit", "missing.csv", "--coordinates", "x", "--out", "m.json"],
        cwd=tmp_path,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "lagsindy fit: error: file not found: missing.csv"
    ]


def test_warnings_are_printed_on_one_line(capsys, monkeypatch, workdir):
    import warnings

    import lagsindy.cli as cli

    def noisy(args):
        warnings.warn("first line\nsecond line", UserWarning)
        return 0

    monkeypatch.setattr(cli, "_fit", noisy)
    code, _, err = run(
        capsys,
        "fit",
        workdir / "data.csv",
        "--coordinates",
        "x",
        "--out",
        workdir / "unused.json",
    )
    assert code == 0
    assert err.splitlines() == ["lagsindy fit: warning: first line second line"]


def test_debug_shows_the_traceback(workdir):
    with pytest.raises(Exception, match="not found"):
        main(
            [
                "--debug",
                "fit",
                str(workdir / "none.csv"),
                "--coordinates",
                "x",
                "--out",
                str(workdir / "o.json"),
            ]
        )


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--lam", "-1"], "--lam must be a number >= 0"),
        (["--library", "foo"], "--library 'foo' is not known"),
        (["--input", "tau_x,nosuch"], "no column 'nosuch'"),
        (["--threshold", "1.5"], "--threshold must be in"),
        (["--coordinates", "theta,nosuch"], "no column 'nosuch'"),
    ],
)
def test_cheap_checks_come_before_derivatives(
    capsys, workdir, no_derivatives, extra, message
):
    args = ["fit", workdir / "q.csv", "--coordinates", "x,theta", "--angles", "theta"]
    code, _, err = run(capsys, *args, *extra, "--out", workdir / "never.json")
    assert code == 2, err
    assert message in err, err


def test_bad_values_are_reported_as_file_lines(capsys, workdir, tmp_path):
    df = pd.read_csv(workdir / "data.csv")
    df = df.astype({"theta": object})
    df.loc[500, "theta"] = "oops"  # data row 500 is file line 502 (header = line 1)
    csv = tmp_path / "bad.csv"
    df.to_csv(csv, index=False)
    lines = csv.read_text().splitlines()
    assert "oops" in lines[501] and "oops" not in lines[500]
    code, _, err = run(
        capsys, "fit", csv, "--coordinates", "x,theta", "--out", tmp_path / "m.json"
    )
    assert code == 2
    assert "line 502 holds 'oops'" in err, err


# ---------------------------------------- errors before the heavy imports (#44)
# Each command below is wrong in a way the options, the file names or the CSV's
# header show: it must end before pandas, torch, sympy, scikit-learn or scipy load
# (the child below lists them).
_FIT = ["fit", "{d}/data.csv", "--coordinates", "x,theta", "--out", "{d}/o.json"]
CHEAP = {
    "missing file": (
        ["fit", "{d}/none.csv", "--coordinates", "x", "--out", "{d}/o.json"],
        "file not found",
    ),
    "folder for data": (
        ["fit", "{d}", "--coordinates", "x", "--out", "{d}/o.json"],
        "is a folder",
    ),
    "empty file": (
        ["fit", "{d}/empty.csv", "--coordinates", "x", "--out", "{d}/o.json"],
        "is empty",
    ),
    "header only": (
        ["fit", "{d}/header.csv", "--coordinates", "x", "--out", "{d}/o.json"],
        "no rows",
    ),
    "bad column": (
        ["fit", "{d}/data.csv", "--coordinates", "x,phi", "--out", "{d}/o.json"],
        "no column 'phi'",
    ),
    "bad input column": ([*_FIT, "--input", "tau_x,nope"], "no column 'nope'"),
    "input count": ([*_FIT, "--input", "tau_x"], "one generalized-force column"),
    "no time": (
        ["fit", "{d}/no_t.csv", "--coordinates", "x,theta", "--out", "{d}/o.json"],
        "'t' column",
    ),
    "bad name": (
        ["fit", "{d}/data.csv", "--coordinates", "x-1", "--out", "{d}/o.json"],
        "coordinate name 'x-1' is not valid",
    ),
    "derivative name": (
        ["fit", "{d}/data.csv", "--coordinates", "x_dot", "--out", "{d}/o.json"],
        "reserved for its derivatives",
    ),
    "reserved name": (
        ["fit", "{d}/data.csv", "--coordinates", "x,sin", "--out", "{d}/o.json"],
        "is reserved .a function or constant name.",
    ),
    "repeated name": (
        ["fit", "{d}/data.csv", "--coordinates", "x,x", "--out", "{d}/o.json"],
        "appears twice",
    ),
    "angles": ([*_FIT, "--angles", "phi"], "--angles"),
    "lam": ([*_FIT, "--lam", "-1"], "--lam must be a number >= 0"),
    "lam nan": ([*_FIT, "--lam", "nan"], "--lam must be a number >= 0"),
    "threshold": ([*_FIT, "--threshold", "1"], "--threshold must be in"),
    "window": ([*_FIT, "--window", "3"], "--window must be at least 5"),
    "held-out": ([*_FIT, "--held-out", "1"], "--held-out must be in"),
    "refine": ([*_FIT, "--refine", "1"], "--refine needs a horizon"),
    "library": ([*_FIT, "--library", "cubic"], "--library 'cubic' is not known"),
    "library degree": ([*_FIT, "--library", "poly7"], "between 1 and 6"),
    "terms needed": ([*_FIT, "--library", "terms"], "--library terms needs"),
    "fixed term with forces": (
        [*_FIT, "--fixed-term", "theta_dot**2"],
        "--fixed-term is for passive data",
    ),
    "delay on passive data": ([*_FIT, "--passive", "--delay", "0.1"], "--delay"),
    "delay text": ([*_FIT, "--delay", "soon"], "--delay must be a number"),
    "out folder": (
        ["fit", "{d}/data.csv", "--coordinates", "x", "--out", "{d}/nodir/o.json"],
        "does not exist",
    ),
    "predict: no model": (
        ["predict", "{d}/none.json", "{d}/data.csv", "--out", "{d}/p.csv"],
        "model file not found",
    ),
    "predict: not JSON": (
        ["predict", "{d}/bad.json", "{d}/data.csv", "--out", "{d}/p.csv"],
        "not valid JSON",
    ),
    "predict: no time": (
        ["predict", "{d}/model.json", "{d}/no_t.csv", "--out", "{d}/p.csv"],
        "'t' column",
    ),
    "simulate-model: x0 count": (
        ["simulate-model", "{d}/model.json", "--x0", "0,1", "--out", "{d}/s.csv"],
        "has 2 value",
    ),
    "simulate-model: x0 text": (
        ["simulate-model", "{d}/model.json", "--x0", "0,a,0,0", "--out", "{d}/s.csv"],
        "numbers",
    ),
    "simulate: system": (
        ["simulate", "--system", "nosuch", "--out", "{d}/s.csv"],
        "unknown system",
    ),
    "simulate: noise": (
        ["simulate", "--system", "cart", "--noise", "-1", "--out", "{d}/s.csv"],
        "noise",
    ),
    "demo: system": (["demo", "--system", "nosuch"], "unknown system"),
    "demo: trajectories": (["demo", "--trajectories", "0"], "--trajectories"),
    "diagnose: passive model data": (
        ["diagnose", "{d}/data.csv", "--model", "{d}/model.json", "--passive"],
        "fitted with input forces",
    ),
    "diagnose: splits": (
        ["diagnose", "{d}/data.csv", "--model", "{d}/model.json", "--splits", "1"],
        "--splits",
    ),
    "diagnose: delay auto": (
        ["diagnose", "{d}/data.csv", "--model", "{d}/model.json", "--delay", "auto"],
        "--delay auto",
    ),
}
_CHILD = """
import contextlib, io, json, sys
from lagsindy.cli import main
HEAVY = ("torch", "sympy", "sklearn", "scipy", "pandas")
out = {}
for name, args in json.loads(sys.stdin.read()).items():
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(args)
    heavy = [m for m in HEAVY if m in sys.modules]
    out[name] = [code, err.getvalue(), heavy]
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def cheap_errors(workdir):
    """Every CHEAP command, run in order in one fresh interpreter: exit status,
    stderr and the heavy modules loaded by then."""
    if not (workdir / "evil.json").exists():
        _bad_files(workdir)
    cases = {k: [a.format(d=workdir) for a in v[0]] for k, v in CHEAP.items()}
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD],
        input=json.dumps(cases),
        env=ENV,
        cwd=workdir,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.splitlines()[-1])


@pytest.mark.parametrize("case", list(CHEAP))
def test_errors_come_before_heavy_imports(cheap_errors, case):
    code, err, heavy = cheap_errors[case]
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1, err
    assert re.search(CHEAP[case][1], err), err
    # the cases run in order in one interpreter: the first one that lists a module
    # is the one that loaded it
    assert heavy == [], f"{case!r} loaded {heavy} before its error: {err}"


def test_cheap_names_agree_with_the_library():
    """The checks' copies of the library's naming rules and system names; the
    light naming module's reserved names are the functions and constants a term
    string reads."""
    from lagsindy import _expr, _names
    from lagsindy.cli import _checks
    from lagsindy.systems import SYSTEMS, get_system

    assert set(_names.FUNCTION_NAMES) == set(_expr._SYMPY_FUNCTIONS)
    assert set(_names.CONSTANT_NAMES) == set(_expr._CONSTANTS)
    coords = ["x", "theta"]
    assert _checks.state_names(coords) == _expr.state_names(coords)
    assert _checks.state_names(coords, accelerations=False) == _expr.state_names(
        coords, accelerations=False
    )
    for name in [*SYSTEMS, "cart", "cart-pendulum", " Double Pendulum", "spring"]:
        try:
            expected = get_system(name).name, None
        except ValueError as exc:
            expected = None, str(exc)
        try:
            found = get_system(_checks.system_name(name)).name, None
        except _checks.CLIError as exc:
            found = None, str(exc)
        assert found == expected, name
