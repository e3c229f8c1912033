"""The exported C: builds cleanly, links into a program, reports a singular matrix."""

import subprocess

import numpy as np
import pytest

from lagsindy import MechanicalModel
from lagsindy.export import (
    BUILD_LINE,
    CModel,
    compile_c,
    export_model,
    export_source,
    find_compiler,
    load_python,
)
from lagsindy.systems import triple_pendulum

pytestmark = pytest.mark.skipif(find_compiler() is None, reason="no C compiler")

STRICT = ("-O2", "-std=c99", "-Wall", "-Wextra", "-pedantic", "-Werror")


@pytest.fixture(scope="module")
def triple(tmp_path_factory):
    folder = tmp_path_factory.mktemp("triple")
    system = triple_pendulum().with_damping({"theta1": 0.2}, {"theta3": 0.05})
    c_file, h_file = export_model(system, folder / "triple.c")
    library = compile_c(c_file, flags=STRICT)
    python = load_python(export_source(system, "python"))
    return system, c_file, h_file, CModel(library, "triple"), python


def test_header_states_the_build_line_and_the_functions(triple):
    _, c_file, h_file, _, _ = triple
    header = h_file.read_text()
    assert BUILD_LINE.format(name="triple") in header
    assert "cc -O2 -shared -fPIC -o libtriple.so triple.c -lm" in c_file.read_text()
    for signature in (
        "int triple_forward_dynamics(const double *x, const double *u, double *qdd);",
        "double triple_energy(const double *q, const double *qd);",
        "#define TRIPLE_N_DOF 3",
    ):
        assert signature in header


def test_c_equals_the_python_export_with_and_without_inputs(triple):
    _, _, _, c_model, python = triple
    rng = np.random.default_rng(0)
    x = rng.uniform(-2, 2, (200, 6))
    u = rng.uniform(-1, 1, (200, 3))
    for inputs in (u, None):
        np.testing.assert_allclose(
            c_model.forward_dynamics(x, inputs),
            python.forward_dynamics(x, inputs),
            rtol=1e-13,
            atol=1e-13,
        )
    np.testing.assert_allclose(
        c_model.mass_matrix(x[:, :3], x[:, 3:]), python.mass_matrix(x[:, :3], x[:, 3:])
    )


def test_a_c_program_links_the_export(triple, tmp_path):
    _, c_file, _, _, python = triple
    main = tmp_path / "main.c"
    main.write_text(
        f'#include <stdio.h>\n#include "{c_file.with_suffix(".h")}"\n'
        "int main(void) {\n"
        "    double x[6] = {0.1, -0.2, 0.3, 0.5, -0.4, 0.2}, u[3] = {1, 0, -1};\n"
        "    double xdot[6];\n"
        "    int status = triple_state_derivative(x, u, xdot);\n"
        '    printf("%d %.17g %.17g %.17g\\n", status, xdot[3], xdot[4], xdot[5]);\n'
        "    return 0;\n}\n"
    )
    exe = tmp_path / "main"
    build = [find_compiler(), *STRICT, "-o", str(exe), str(main), str(c_file), "-lm"]
    subprocess.run(build, check=True, capture_output=True)
    status, *values = subprocess.run(
        [str(exe)], check=True, capture_output=True, text=True
    ).stdout.split()
    assert status == "0"
    expected = python.forward_dynamics(
        [0.1, -0.2, 0.3, 0.5, -0.4, 0.2], [1.0, 0.0, -1.0]
    )
    np.testing.assert_allclose([float(v) for v in values], expected, rtol=1e-13)


def test_a_singular_mass_matrix_returns_minus_one(tmp_path):
    model = MechanicalModel("0.5*x**2*x_dot**2 + 0.5*y_dot**2 - y**2", ["x", "y"])
    c_file, _ = export_model(model, tmp_path / "singular.c")
    c_model = CModel(compile_c(c_file, flags=STRICT), "singular")
    f = c_model.functions["forward_dynamics"]
    x = np.array([0.0, 1.0, 0.2, 0.3])
    out = np.zeros(2)
    assert f(x.ctypes.data, None, out.ctypes.data) == -1
    assert np.isnan(out).all()
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        c_model.forward_dynamics(x)
    np.testing.assert_allclose(
        c_model.forward_dynamics([2.0, 1.0, 0.0, 0.3]), [0.0, -2.0], atol=1e-15
    )


def test_a_zero_first_pivot_is_pivoted(tmp_path):
    model = MechanicalModel("x_dot*y_dot - 0.5*x**2 - 2*y**2", ["x", "y"])
    c_file, _ = export_model(model, tmp_path / "swap.c")
    c_model = CModel(compile_c(c_file, flags=STRICT), "swap")
    x, u = np.array([0.3, -0.5, 1.0, 2.0]), np.array([0.7, -0.2])
    # qdd_x = u_y - 4 y, qdd_y = u_x - x
    np.testing.assert_allclose(
        c_model.forward_dynamics(x, u), [-0.2 + 2.0, 0.7 - 0.3], rtol=1e-15
    )


def test_a_failed_build_says_why(tmp_path):
    bad = tmp_path / "bad.c"
    bad.write_text("int f(void) { return }\n")
    with pytest.raises(RuntimeError, match="building .*bad.c failed"):
        compile_c(bad)


def test_a_library_in_the_current_folder_loads(tmp_path, monkeypatch):
    # ctypes searches the system's library path for a bare file name
    monkeypatch.chdir(tmp_path)
    source, _ = export_model(MechanicalModel("0.5*x_dot**2 - x**2", ["x"]), "spring.c")
    model = CModel(compile_c(source), "spring")
    np.testing.assert_allclose(model.forward_dynamics([0.5, 0.0], [1.0]), [0.0])
