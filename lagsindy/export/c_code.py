"""Standalone C (a ``.c`` and a ``.h``, double precision) of a model's equations.

The functions carry the file's name as a prefix (``<name>_forward_dynamics``...),
so several exported models link into one program. States are
``x = [q..., q_dot...]``; arrays are row-major. The mass matrix is solved by an LU
factorization with partial pivoting written out in the file (no LAPACK); a
singular one makes the function return -1 and write NaN.
"""

from __future__ import annotations

import re

from .equations import ModelEquations
from .printing import CExactPrinter, check_printable, common_subexpressions
from .python_code import symbolic

BUILD_LINE = "cc -O2 -shared -fPIC -o lib{name}.so {name}.c -lm"


def c_identifier(name: str) -> str:
    """``name`` made a valid C identifier (letters, digits, ``_``; no leading digit)."""
    ident = re.sub(r"[^A-Za-z0-9_]", "_", str(name)) or "model"
    if ident[0].isdigit():
        ident = "m_" + ident
    return ident


def _comment(lines) -> list:
    out = ["/*"]
    for line in lines:
        out.append((" * " + line.replace("*/", "* /")).rstrip())
    out.append(" */")
    return out


def _state_lines(n, exprs) -> list:
    """``const double q0 = q[0];``... for the state symbols ``exprs`` use."""
    used = {str(s) for e in exprs for s in e.free_symbols}
    lines = [f"    const double q{i} = q[{i}];" for i in range(n) if f"q{i}" in used]
    lines += [f"    const double v{i} = qd[{i}];" for i in range(n) if f"v{i}" in used]
    return lines


def _terms_function(prefix, n, mass, rest, printer) -> list:
    exprs = mass + rest
    check_printable(exprs, printer)
    replacements, reduced = common_subexpressions(exprs)
    lines = [
        f"static void {prefix}_terms(const double *q, const double *qd, double *m, "
        "double *r)",
        "{",
    ]
    lines += _state_lines(n, exprs)
    lines += [
        f"    const double {sym} = {printer.doprint(value)};"
        for sym, value in replacements
    ]
    lines += [
        f"    m[{k}] = {printer.doprint(e)};" for k, e in enumerate(reduced[: n * n])
    ]
    lines += [
        f"    r[{k}] = {printer.doprint(e)};" for k, e in enumerate(reduced[n * n :])
    ]
    lines += ["    (void)q;", "    (void)qd;", "}"]
    return lines


def _energy_function(prefix, n, energy, printer) -> list:
    check_printable([energy], printer)
    replacements, reduced = common_subexpressions([energy])
    lines = [f"double {prefix}_energy(const double *q, const double *qd)", "{"]
    lines += ["    (void)q;", "    (void)qd;"] + _state_lines(n, [energy])
    lines += [
        f"    const double {sym} = {printer.doprint(value)};"
        for sym, value in replacements
    ]
    lines += [f"    return {printer.doprint(reduced[0])};", "}"]
    return lines


def _generalized_lines(eq: ModelEquations) -> list:
    """``r[i] = (B u)_i - r[i]`` with the input matrix's entries written out."""
    lines = []
    for i, row in enumerate(eq.input_matrix):
        parts = [
            f"u[{j}]" if float(b) == 1.0 else f"({float(b)!r})*u[{j}]"
            for j, b in enumerate(row)
            if float(b) != 0.0
        ]
        lines.append(
            f"        r[{i}] = {' + '.join(parts) if parts else '0.0'} - r[{i}];"
        )
    return lines


_SOLVE = """
/* Solve a x = b in place (a: N x N row-major, overwritten by its LU factors; b: the
 * right-hand side, overwritten by x) by Gaussian elimination with partial pivoting.
 * Returns 0, or -1 when a pivot is zero (a singular matrix; b is then all NaN). */
static int {p}_solve(double *a, double *b)
{{
    for (int k = 0; k < N; ++k) {{
        int piv = k;
        double big = fabs(a[k * N + k]);
        for (int i = k + 1; i < N; ++i) {{
            double v = fabs(a[i * N + k]);
            if (v > big) {{
                big = v;
                piv = i;
            }}
        }}
        if (!(big > 0.0)) {{
            for (int i = 0; i < N; ++i) b[i] = NAN;
            return -1;
        }}
        if (piv != k) {{
            for (int j = 0; j < N; ++j) {{
                double t = a[k * N + j];
                a[k * N + j] = a[piv * N + j];
                a[piv * N + j] = t;
            }}
            double t = b[k];
            b[k] = b[piv];
            b[piv] = t;
        }}
        for (int i = k + 1; i < N; ++i) {{
            double f = a[i * N + k] / a[k * N + k];
            for (int j = k + 1; j < N; ++j) a[i * N + j] -= f * a[k * N + j];
            b[i] -= f * b[k];
        }}
    }}
    for (int i = N - 1; i >= 0; --i) {{
        double s = b[i];
        for (int j = i + 1; j < N; ++j) s -= a[i * N + j] * b[j];
        b[i] = s / a[i * N + i];
    }}
    return 0;
}}

int {p}_forward_dynamics(const double *x, const double *u, double *qdd)
{{
    double m[N * N], r[N];
    {p}_terms(x, x + N, m, r);
    if (u) {{
{generalized}
    }} else {{
        for (int i = 0; i < N; ++i) r[i] = -r[i];
    }}
    int status = {p}_solve(m, r);
    for (int i = 0; i < N; ++i) qdd[i] = r[i];
    return status;
}}

int {p}_forward_dynamics_batch(size_t count, const double *x, const double *u,
                               double *qdd)
{{
    int status = 0;
    for (size_t s = 0; s < count; ++s) {{
        if ({p}_forward_dynamics(x + s * 2 * N, u ? u + s * NU : 0, qdd + s * N))
            status = -1;
    }}
    return status;
}}

int {p}_state_derivative(const double *x, const double *u, double *xdot)
{{
    for (int i = 0; i < N; ++i) xdot[i] = x[N + i];
    return {p}_forward_dynamics(x, u, xdot + N);
}}

void {p}_inverse_dynamics(const double *q, const double *qd, const double *qdd,
                          double *tau)
{{
    double m[N * N], r[N];
    {p}_terms(q, qd, m, r);
    for (int i = 0; i < N; ++i) {{
        double s = r[i];
        for (int j = 0; j < N; ++j) s += m[i * N + j] * qdd[j];
        tau[i] = s;
    }}
}}

void {p}_mass_matrix(const double *q, const double *qd, double *mass)
{{
    double r[N];
    {p}_terms(q, qd, mass, r);
}}

int {p}_n_dof(void) {{ return N; }}

int {p}_n_inputs(void) {{ return NU; }}
"""


def _header(eq: ModelEquations, name: str) -> str:
    p = c_identifier(name)
    guard = f"LAGSINDY_{p.upper()}_H"
    n, m = eq.n_dof, eq.n_inputs
    lines = _comment(
        [f"{name}.h: equations of motion exported by lagsindy (C99, double).", ""]
        + eq.provenance_lines()
        + [
            "",
            f"Build: {BUILD_LINE.format(name=name)}",
            "",
            f"States x = [q..., q_dot...] ({2 * n} doubles); u: {m} input(s), the",
            "generalized forces are B u; NULL means no input. Matrices row-major.",
        ]
    )
    lines += [
        f"#ifndef {guard}",
        f"#define {guard}",
        "",
        "#include <stddef.h>",
        "",
        f"#define {p.upper()}_N_DOF {n}",
        f"#define {p.upper()}_N_INPUTS {m}",
        "",
        "#ifdef __cplusplus",
        'extern "C" {',
        "#endif",
        "",
        "/* Accelerations qdd (N_DOF) at state x under inputs u. Returns 0, or -1",
        " * where the mass matrix is singular (qdd is then NaN). */",
        f"int {p}_forward_dynamics(const double *x, const double *u, double *qdd);",
        "",
        "/* The same for count states (x: count x 2 N_DOF, u: count x N_INPUTS or",
        " * NULL, qdd: count x N_DOF). Returns -1 if any mass matrix was singular. */",
        f"int {p}_forward_dynamics_batch(size_t count, const double *x, "
        "const double *u, double *qdd);",
        "",
        "/* xdot = [q_dot, q_ddot] (2 N_DOF), the right-hand side for integrators. */",
        f"int {p}_state_derivative(const double *x, const double *u, double *xdot);",
        "",
        "/* Generalized forces tau = M qdd + r (N_DOF) that produce qdd. */",
        f"void {p}_inverse_dynamics(const double *q, const double *qd, "
        "const double *qdd, double *tau);",
        "",
        "/* Mass matrix d2L/dq_dot2 (N_DOF x N_DOF, row-major). */",
        f"void {p}_mass_matrix(const double *q, const double *qd, double *mass);",
        "",
        "/* Energy function sum q_dot dL/dq_dot - L. */",
        f"double {p}_energy(const double *q, const double *qd);",
        "",
        "/* The sizes, for callers that load the library at run time. */",
        f"int {p}_n_dof(void);",
        f"int {p}_n_inputs(void);",
        "",
        "#ifdef __cplusplus",
        "}",
        "#endif",
        "",
        f"#endif /* {guard} */",
    ]
    return "\n".join(lines) + "\n"


def c_sources(eq: ModelEquations, name: str = "model") -> tuple[str, str]:
    """``(source, header)``: the text of ``<name>.c`` and ``<name>.h``.

    ``name`` becomes the functions' prefix (made a C identifier) and the header
    the ``.c`` includes.
    """
    p = c_identifier(name)
    n = eq.n_dof
    _, _, mass, rest, energy = symbolic(eq)
    printer = CExactPrinter()
    lines = _comment(
        [f"{name}.c: equations of motion exported by lagsindy (C99, double).", ""]
        + eq.provenance_lines()
        + ["", f"Build: {BUILD_LINE.format(name=name)}"]
    )
    lines += [
        "#include <math.h>",
        "#include <stddef.h>",
        "",
        f'#include "{name}.h"',
        "",
        f"#define N {n}",
        f"#define NU {eq.n_inputs}",
        "",
    ]
    lines += _terms_function(p, n, mass, rest, printer)
    lines += [""]
    lines += _energy_function(p, n, energy, printer)
    source = (
        "\n".join(lines)
        + "\n"
        + _SOLVE.format(p=p, generalized="\n".join(_generalized_lines(eq)))
    )
    return source, _header(eq, name)


__all__ = ["BUILD_LINE", "c_identifier", "c_sources"]
