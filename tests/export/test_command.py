"""``lagsindy export`` through argparse (the lead registers add_export_command)."""

import argparse

import numpy as np
import pytest

from lagsindy.export import (
    CModel,
    compile_c,
    export_source,
    find_compiler,
    load_python,
)
from lagsindy.export.command import add_export_command, parse_matrix, run_export

from ._models import true_estimator


def _parser():
    parser = argparse.ArgumentParser(prog="lagsindy")
    sub = parser.add_subparsers(dest="command", required=True)
    add_export_command(sub)
    return parser


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    folder = tmp_path_factory.mktemp("saved")
    est, path = true_estimator("cart_pendulum", True, folder)
    return est, path


def test_python_export_from_a_model_file(saved, tmp_path, capsys):
    est, path = saved
    out = tmp_path / "cartpole.py"
    args = _parser().parse_args(["export", str(path), "--out", str(out)])
    assert args.func is run_export
    assert args.func(args) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    text = out.read_text()
    assert f"read from {path.name}" in text
    module = load_python(text)
    reference = load_python(export_source(est, "python"))
    x = np.array([[0.1, 2.0, -0.3, 0.4], [1.0, -1.0, 0.5, 0.0]])
    u = np.array([[0.5, -0.2], [0.0, 1.0]])
    np.testing.assert_array_equal(
        module.forward_dynamics(x, u), reference.forward_dynamics(x, u)
    )


@pytest.mark.skipif(find_compiler() is None, reason="no C compiler")
def test_c_export_with_an_input_matrix(saved, tmp_path):
    est, path = saved
    out = tmp_path / "cart"
    args = _parser().parse_args(
        [
            "export",
            str(path),
            "--format",
            "c",
            "--out",
            str(out),
            "--input-matrix",
            "1;0",
            "--quiet",
        ]
    )
    assert run_export(args) == 0
    assert (tmp_path / "cart.h").exists()
    model = CModel(compile_c(tmp_path / "cart.c"), "cart")
    assert model.n_inputs == 1
    python = load_python(export_source(est, "python"))
    x = np.array([0.1, 2.0, -0.3, 0.4])
    np.testing.assert_allclose(
        model.forward_dynamics(x, 0.7),
        python.forward_dynamics(x, [0.7, 0.0]),
        rtol=1e-14,
    )


def test_the_default_output_is_the_model_name_here(saved, tmp_path, monkeypatch):
    _, path = saved
    monkeypatch.chdir(tmp_path)
    args = _parser().parse_args(["export", str(path), "--format", "c", "--quiet"])
    assert run_export(args) == 0
    assert (tmp_path / f"{path.stem}.c").exists() and (
        tmp_path / f"{path.stem}.h"
    ).exists()


def test_bad_options_raise_value_errors(saved, tmp_path):
    _, path = saved
    parser = _parser()
    for text, message in (
        ("1;x", "must be numbers"),
        ("1,0;1", "rows of equal length"),
        ("1;0;0", r"input_matrix must have shape \(n_dof=2"),
    ):
        args = parser.parse_args(
            [
                "export",
                str(path),
                "--out",
                str(tmp_path / "m.py"),
                "--input-matrix",
                text,
            ]
        )
        with pytest.raises(ValueError, match=message):
            run_export(args)
    with pytest.raises(SystemExit):
        parser.parse_args(["export", str(path), "--format", "fortran"])
    missing = parser.parse_args(["export", str(tmp_path / "none.json")])
    with pytest.raises(FileNotFoundError):
        run_export(missing)
    np.testing.assert_array_equal(parse_matrix("1,0;0,2"), [[1.0, 0.0], [0.0, 2.0]])


def test_registering_the_command_imports_nothing_heavy():
    import subprocess
    import sys

    code = (
        "import sys; from lagsindy.export.command import add_export_command; "
        "print(sorted(m for m in ('numpy', 'sympy', 'torch', 'scipy') "
        "if m in sys.modules))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


def test_every_public_name_is_its_object_after_every_submodule_loaded():
    # a submodule named like a function would replace it on the package
    import importlib
    import pkgutil
    import types

    import lagsindy.export as export

    for info in pkgutil.iter_modules(export.__path__):
        importlib.import_module(f"lagsindy.export.{info.name}")
    for name in export.__all__:
        assert not isinstance(getattr(export, name), types.ModuleType), name
