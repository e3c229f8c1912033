"""Symbols, safe parsing of expression strings, and sympy -> torch compilation.

Everything that turns text or sympy trees into something numeric lives here, so that
no other module needs ``eval``, ``sympify`` or ``lambdify`` on user-supplied text.

Naming convention: a coordinate ``theta`` has the velocity symbol ``theta_dot`` and the
acceleration symbol ``theta_ddot``. All symbols are real.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Callable, Iterable, Sequence

import sympy as sp
import torch

from ._names import (
    ACCELERATION_SUFFIX,
    VELOCITY_SUFFIX,
    name_problem,
    repeated_name,
)

# Functions a term string may call, mapped to sympy and to torch.
_SYMPY_FUNCTIONS: dict[str, Callable] = {
    "sin": sp.sin,
    "cos": sp.cos,
    "tan": sp.tan,
    "sinh": sp.sinh,
    "cosh": sp.cosh,
    "tanh": sp.tanh,
    "exp": sp.exp,
    "log": sp.log,
    "sqrt": sp.sqrt,
    "Abs": sp.Abs,
    "abs": sp.Abs,
    "sign": sp.sign,
}
_CONSTANTS = {"pi": sp.pi, "E": sp.E}
MAX_EXPRESSION_LENGTH = 10_000
MAX_EXPONENT = 64
# Largest magnitude (in bits, |log2|) of a power of two numbers: sympy evaluates
# numeric powers exactly, so "((10**64)**64)**64" would otherwise take minutes.
MAX_NUMERIC_POWER_BITS = 4096
# Longest numeric literal and largest decimal exponent of one ("1e99999999999" made
# sympy exhaust memory).
MAX_NUMBER_LENGTH = 400
MAX_DECIMAL_EXPONENT = 1000


class ExpressionError(ValueError):
    """A term string that is not a valid expression over the declared coordinates."""


# ----------------------------------------------------------------------------- symbols
def check_coordinate_names(names: Iterable[str]) -> list[str]:
    """Validate coordinate names and return them as a list.

    Raises ``ValueError`` naming the offending entry when a name is not an identifier,
    is reserved (a function or constant name), ends in a derivative suffix, or repeats.
    """
    names = list(names)
    if not names:
        raise ValueError("at least one coordinate name is needed, got an empty list")
    for problem in (*map(name_problem, names), repeated_name(names)):
        if problem is not None:
            raise ValueError(problem)
    return names


def velocity_name(name: str) -> str:
    return name + VELOCITY_SUFFIX


def acceleration_name(name: str) -> str:
    return name + ACCELERATION_SUFFIX


def symbols_for(names: Sequence[str]) -> tuple[list, list, list]:
    """Return the position, velocity and acceleration symbols of named coordinates."""
    q = [sp.Symbol(n, real=True) for n in names]
    qd = [sp.Symbol(velocity_name(n), real=True) for n in names]
    qdd = [sp.Symbol(acceleration_name(n), real=True) for n in names]
    return q, qd, qdd


def state_names(names: Sequence[str], *, accelerations: bool = True) -> list[str]:
    """Column names of the X layout: ``[q..., q_dot..., q_ddot...]``."""
    out = list(names) + [velocity_name(n) for n in names]
    if accelerations:
        out += [acceleration_name(n) for n in names]
    return out


def canonical(expr, names: Sequence[str], *, accelerations: bool = False) -> sp.Expr:
    """Return ``expr`` (a sympy expression or a string) over this module's symbols.

    Strings go through :func:`parse_expression`. Sympy input has its free symbols
    matched by name, so ``sympy.Symbol('theta')`` and the real ``theta`` used here are
    the same coordinate. Any other free symbol raises ``ValueError``.
    """
    allowed = state_names(names, accelerations=accelerations)
    if isinstance(expr, str):
        return parse_expression(expr, allowed)
    if isinstance(expr, (int, float)):
        return sp.Float(expr) if isinstance(expr, float) else sp.Integer(expr)
    if not isinstance(expr, sp.Basic):
        raise TypeError(
            f"expected a sympy expression or a string, got {type(expr).__name__}"
        )
    mapping = {}
    table = {s.name: s for s in sp.symbols(allowed, real=True)}
    for s in expr.free_symbols:
        if s.name not in table:
            raise ValueError(
                f"expression {expr} uses the symbol {s.name!r}, which is not one of "
                f"the coordinates or their velocities {allowed}"
            )
        mapping[s] = table[s.name]
    return sp.sympify(expr).xreplace(mapping)


# ----------------------------------------------------------------------------- parser
_TOKEN_RE = re.compile(
    r"\s*(?:(?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)"
    r"|(?P<name>[A-Za-z_][A-Za-z0-9_]*)"
    r"|(?P<op>\*\*|[-+*/^(),]))"
)


def _tokenize(text: str) -> list[tuple[str, str]]:
    tokens = []
    pos = 0
    text = text.rstrip()
    while pos < len(text):
        m = _TOKEN_RE.match(text, pos)
        if not m or m.end() == pos:
            raise ExpressionError(
                f"unexpected character {text[pos:].lstrip()[:1]!r} at position {pos} "
                f"in {text!r}"
            )
        kind = m.lastgroup
        tokens.append((kind, m.group(kind)))
        pos = m.end()
    return tokens


class _Parser:
    """Recursive-descent parser for arithmetic over an allow-list of names.

    Grammar (Python precedence; ``^`` is accepted as ``**``)::

        expr   := term (("+" | "-") term)*
        term   := unary (("*" | "/") unary)*
        unary  := ("+" | "-") unary | power
        power  := atom (("**" | "^") unary)?
        atom   := NUMBER | NAME | FUNC "(" expr ")" | "(" expr ")"
    """

    def __init__(self, text: str, symbols: dict[str, sp.Symbol]):
        self.text = text
        self.tokens = _tokenize(text)
        self.pos = 0
        self.symbols = symbols

    def _peek(self):
        return self.tokens[self.pos] if self.pos < len(self.tokens) else (None, None)

    def _next(self):
        tok = self._peek()
        self.pos += 1
        return tok

    def _expect(self, value):
        kind, tok = self._next()
        if tok != value:
            found = "end of text" if tok is None else repr(tok)
            raise ExpressionError(
                f"expected {value!r} but found {found} in {self.text!r}"
            )

    def parse(self) -> sp.Expr:
        if not self.tokens:
            raise ExpressionError("empty expression")
        out = self._expr()
        if self.pos != len(self.tokens):
            raise ExpressionError(
                f"unexpected {self.tokens[self.pos][1]!r} in {self.text!r}"
            )
        return out

    def _expr(self):
        out = self._term()
        while self._peek()[1] in ("+", "-"):
            op = self._next()[1]
            rhs = self._term()
            out = out + rhs if op == "+" else out - rhs
        return out

    def _term(self):
        out = self._unary()
        while self._peek()[1] in ("*", "/"):
            op = self._next()[1]
            rhs = self._unary()
            out = out * rhs if op == "*" else out / rhs
        return out

    def _unary(self):
        if self._peek()[1] in ("+", "-"):
            op = self._next()[1]
            val = self._unary()
            return -val if op == "-" else val
        return self._power()

    def _power(self):
        base = self._atom()
        if self._peek()[1] in ("**", "^"):
            self._next()
            exponent = self._unary()
            if exponent.is_number and _magnitude(exponent) > MAX_EXPONENT:
                raise ExpressionError(
                    f"exponent {exponent} exceeds the limit of {MAX_EXPONENT} in "
                    f"{self.text!r}"
                )
            if (
                base.is_number
                and exponent.is_number
                and _power_too_large(base, exponent)
            ):
                raise ExpressionError(
                    f"a numeric power in {self.text!r} exceeds "
                    f"2**{MAX_NUMERIC_POWER_BITS}"
                )
            return base**exponent
        return base

    def _atom(self):
        kind, tok = self._next()
        if kind == "num":
            mantissa, _, power = tok.lower().partition("e")
            if len(tok) > MAX_NUMBER_LENGTH or (
                power and abs(int(power)) > MAX_DECIMAL_EXPONENT
            ):
                raise ExpressionError(
                    f"number {tok[:40]!r} is too large in {self.text!r}"
                )
            if re.fullmatch(r"\d+", tok):
                return sp.Integer(int(tok))
            return sp.Float(tok)
        if kind == "name":
            if tok in _SYMPY_FUNCTIONS:
                self._expect("(")
                arg = self._expr()
                self._expect(")")
                return _SYMPY_FUNCTIONS[tok](arg)
            if tok in _CONSTANTS:
                return _CONSTANTS[tok]
            if tok in self.symbols:
                return self.symbols[tok]
            raise ExpressionError(
                f"unknown name {tok!r} in {self.text!r}; allowed are the coordinates "
                f"and velocities {sorted(self.symbols)} and the functions "
                f"{sorted(_SYMPY_FUNCTIONS)}"
            )
        if tok == "(":
            out = self._expr()
            self._expect(")")
            return out
        found = "end of text" if tok is None else repr(tok)
        raise ExpressionError(f"unexpected {found} in {self.text!r}")


def _magnitude(number) -> float:
    """``abs`` of a sympy number; inf when it has none (zoo, nan)."""
    try:
        return abs(complex(number))
    except (TypeError, ValueError, OverflowError):
        return math.inf


def _power_too_large(base, exponent) -> bool:
    b, e = _magnitude(base), _magnitude(exponent)
    if not (math.isfinite(b) and math.isfinite(e)):
        return True
    return b != 0 and e * abs(math.log2(b)) > MAX_NUMERIC_POWER_BITS


def parse_expression(text: str, allowed_names: Sequence[str]) -> sp.Expr:
    """Parse ``text`` into a sympy expression without evaluating any Python.

    Only numbers, the names in ``allowed_names`` (bound to real symbols), the
    constants ``pi`` and ``E``, the functions sin, cos, tan, sinh, cosh, tanh, exp,
    log, sqrt, Abs/abs and sign, the operators ``+ - * / ** ^`` and parentheses are
    accepted. Anything else raises :class:`ExpressionError` (a ``ValueError``).

    Parameters
    ----------
    text : str
        The expression, e.g. ``"theta_dot**2*cos(theta)"``.
    allowed_names : sequence of str
        Symbol names the expression may use.

    Returns
    -------
    sympy.Expr
    """
    if not isinstance(text, str):
        raise ExpressionError(f"expected a string, got {type(text).__name__}")
    if len(text) > MAX_EXPRESSION_LENGTH:
        raise ExpressionError(
            f"expression of {len(text)} characters exceeds the limit of "
            f"{MAX_EXPRESSION_LENGTH}"
        )
    symbols = {n: sp.Symbol(n, real=True) for n in allowed_names}
    try:
        expr = sp.sympify(_Parser(text, symbols).parse())
    except RecursionError:
        raise ExpressionError(
            f"expression nested too deeply: {text[:60]!r}..."
        ) from None
    if expr.has(sp.zoo, sp.nan, sp.oo, -sp.oo):
        raise ExpressionError(f"expression {text!r} is not finite (division by zero?)")
    return expr


# ----------------------------------------------------------------------------- torch
_TORCH_FUNCTIONS = {
    sp.sin: torch.sin,
    sp.cos: torch.cos,
    sp.tan: torch.tan,
    sp.sinh: torch.sinh,
    sp.cosh: torch.cosh,
    sp.tanh: torch.tanh,
    sp.exp: torch.exp,
    sp.log: torch.log,
    sp.Abs: torch.abs,
    sp.sign: torch.sign,
}


def _evaluate(expr, env: dict, like: torch.Tensor):
    """Evaluate a sympy tree with torch operations; ``env`` maps symbols to tensors."""
    hit = env.get(expr)
    if hit is not None:
        return hit
    if expr.is_Number or expr.is_NumberSymbol:
        return float(expr)
    if expr.is_Add:
        args = [_evaluate(a, env, like) for a in expr.args]
        out = args[0]
        for a in args[1:]:
            out = out + a
        return out
    if expr.is_Mul:
        args = [_evaluate(a, env, like) for a in expr.args]
        out = args[0]
        for a in args[1:]:
            out = out * a
        return out
    if expr.is_Pow:
        base = _evaluate(expr.base, env, like)
        exponent = expr.exp
        if exponent.is_Integer:
            e = int(exponent)
            if e == -1:
                return 1.0 / base
            return base**e
        if exponent == sp.Rational(1, 2):
            return torch.sqrt(base) if torch.is_tensor(base) else base**0.5
        return base ** _evaluate(exponent, env, like)
    func = _TORCH_FUNCTIONS.get(expr.func)
    if func is None or len(expr.args) != 1:
        raise ValueError(f"cannot compile {expr} to torch: unsupported function")
    arg = _evaluate(expr.args[0], env, like)
    if not torch.is_tensor(arg):
        arg = torch.as_tensor(arg, dtype=like.dtype, device=like.device)
    return func(arg)


@functools.lru_cache(maxsize=256)
def _cse(exprs: tuple):
    """``sympy.cse`` of ``exprs``, once per set of expressions.

    The same force and term expressions are compiled again by every operator that
    holds them (``diagnose`` builds several: fold statistics, refits, the delay
    search), and the elimination costs milliseconds per expression set. Sympy
    expressions are immutable and hash by value, so the result can be shared.
    """
    return sp.cse(list(exprs), optimizations=None)


def compile_torch(exprs: Sequence[sp.Expr], inputs: Sequence[Sequence[sp.Symbol]]):
    """Compile sympy expressions into one torch function of per-sample vectors.

    Parameters
    ----------
    exprs : sequence of sympy.Expr
        Expressions to evaluate.
    inputs : sequence of sequences of sympy.Symbol
        One group of symbols per positional argument of the returned function, e.g.
        ``(q_symbols, qd_symbols)``.

    Returns
    -------
    callable
        ``f(*vectors) -> Tensor of shape (len(exprs),)`` for vectors of shape
        ``(len(group),)``; it composes with ``torch.func`` transforms (vmap, jacfwd,
        jvp). Common subexpressions are evaluated once.
    """
    replacements, reduced = _cse(tuple(sp.sympify(e) for e in exprs))
    groups = [list(g) for g in inputs]

    def function(*vectors: torch.Tensor) -> torch.Tensor:
        like = vectors[0]
        env = {}
        for symbols, vec in zip(groups, vectors):
            for i, s in enumerate(symbols):
                env[s] = vec[i]
        for sym, sub in replacements:
            env[sym] = _evaluate(sub, env, like)
        values = []
        for e in reduced:
            v = _evaluate(e, env, like)
            if not torch.is_tensor(v):
                v = torch.full_like(like[0], float(v))
            values.append(v)
        if not values:
            return like.new_zeros((0,))
        return torch.stack(values)

    return function
