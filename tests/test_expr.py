import numpy as np
import pytest
import sympy as sp
import torch

from lagsindy._expr import (
    ExpressionError,
    canonical,
    check_coordinate_names,
    compile_torch,
    parse_expression,
    symbols_for,
)

NAMES = ["x", "theta", "x_dot", "theta_dot"]


@pytest.mark.parametrize(
    "text, expected",
    [
        ("theta_dot**2*cos(theta)", "theta_dot**2*cos(theta)"),
        ("x_dot^2/2", "x_dot**2/2"),
        ("-x**2", "-x**2"),
        ("2*-x", "-2*x"),
        ("1.5e-3*Abs(x_dot)**3", "0.0015*Abs(x_dot)**3"),
        ("tanh(x_dot/0.01) + sign(x)", "sign(x) + tanh(100.0*x_dot)"),
        ("(x - theta)**2", "(-theta + x)**2"),
        ("pi*sin(theta)", "pi*sin(theta)"),
    ],
)
def test_parse_valid(text, expected):
    expr = parse_expression(text, NAMES)
    ref = sp.sympify(expected, locals={n: sp.Symbol(n, real=True) for n in NAMES})
    syms = sorted(ref.free_symbols | expr.free_symbols, key=str)
    rng = np.random.default_rng(0)
    for _ in range(3):
        point = dict(zip(syms, rng.uniform(-2, 2, len(syms))))
        assert float(expr.subs(point)) == pytest.approx(
            float(ref.subs(point)), rel=1e-14
        )


@pytest.mark.parametrize(
    "text",
    [
        "__import__('os').system('echo pwned')",
        "x.__class__",
        "lambda: 1",
        "open('f')",
        "y + 1",
        "x[0]",
        "x;x",
        "sin x",
        "x +",
        "(x",
        "exp(x)**1000",
        "",
        "x, x",
        "eval('1')",
        "x @ x",
    ],
)
def test_parse_rejects_everything_else(text):
    with pytest.raises(ExpressionError):
        parse_expression(text, NAMES)


def test_parse_does_not_evaluate_python(monkeypatch):
    called = []
    monkeypatch.setattr("builtins.eval", lambda *a, **k: called.append(a))
    with pytest.raises(ExpressionError):
        parse_expression("__import__('os')", NAMES)
    parse_expression("x**2 + sin(theta)", NAMES)
    assert called == []


def test_canonical_matches_symbols_by_name():
    plain = sp.Symbol("theta") ** 2
    out = canonical(plain, ["theta"])
    assert out == sp.Symbol("theta", real=True) ** 2
    with pytest.raises(ValueError, match="'y'"):
        canonical(sp.Symbol("y"), ["theta"])


@pytest.mark.parametrize("bad", [["x", "x"], ["1x"], ["sin"], ["x_dot"], [], ["a b"]])
def test_bad_coordinate_names(bad):
    with pytest.raises(ValueError):
        check_coordinate_names(bad)


def test_compile_torch_matches_sympy():
    q, qd, _ = symbols_for(["x", "theta"])
    exprs = [
        qd[1] ** 2 * sp.cos(q[1]),
        q[0] * qd[0] * sp.sin(q[1]) ** 2,
        sp.Abs(qd[0]) ** 3 / 3,
        sp.tanh(qd[0] / sp.Float(0.01)),
        sp.Integer(3),
        sp.sqrt(1 + q[0] ** 2),
        1 / (2 + sp.cos(q[1])),
    ]
    f = compile_torch(exprs, (q, qd))
    rng = np.random.default_rng(0)
    for _ in range(5):
        qv, qdv = rng.normal(size=2), rng.normal(size=2)
        got = f(torch.tensor(qv), torch.tensor(qdv)).numpy()
        subs = {**dict(zip(q, qv)), **dict(zip(qd, qdv))}
        want = np.array([float(e.subs(subs)) for e in exprs])
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_compiled_expressions_share_one_elimination():
    """``compile_torch`` runs sympy's CSE once per expression set (cached by value);
    the functions it returns still evaluate their own inputs."""
    from lagsindy._expr import _cse, compile_torch, symbols_for

    q, qd, _ = symbols_for(["x"])
    exprs = [sp.tanh(qd[0] / sp.Float(0.01)) * sp.cos(q[0]), sp.cos(q[0]) ** 2]
    _cse.cache_clear()
    f = compile_torch(exprs, (q, qd))
    g = compile_torch([e.func(*e.args) for e in exprs], (q, qd))  # rebuilt, equal
    info = _cse.cache_info()
    assert (info.misses, info.hits) == (1, 1)
    a = torch.tensor([0.3], dtype=torch.float64)
    b = torch.tensor([0.02], dtype=torch.float64)
    want = [np.tanh(2.0) * np.cos(0.3), np.cos(0.3) ** 2]
    # torch's tanh and cos against numpy's (other math libraries): a few ulp
    np.testing.assert_allclose(f(a, b).numpy(), want, rtol=4e-15)
    np.testing.assert_allclose(g(a, b).numpy(), want, rtol=4e-15)
