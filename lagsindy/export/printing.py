"""sympy code printers for the exports: exact numbers, small powers as products.

sympy's Python and NumPy printers write floats with 15 significant digits, which
changes a learned coefficient in its last bits; these printers write Python's exact
``repr`` of each double, so an exported file computes with the model's own numbers.
Small integer powers are written as products (``x*x*x``): ``pow`` is a library call
in C and a slow path in numpy.
"""

from __future__ import annotations

import sympy as sp
from sympy.printing.c import C99CodePrinter
from sympy.printing.numpy import NumPyPrinter
from sympy.printing.precedence import PRECEDENCE
from sympy.printing.pycode import PythonCodePrinter

# Integer exponents up to this size are written as repeated products.
MAX_PRODUCT_POWER = 4


class _ExactMixin:
    def _print_Float(self, expr):
        value = float(expr)
        text = repr(value)
        return f"({text})" if value < 0 else text

    def _small_power(self, expr):
        base, exp = expr.as_base_exp()
        if not (exp.is_Integer and 1 <= abs(int(exp)) <= MAX_PRODUCT_POWER):
            return None
        b = self.parenthesize(base, PRECEDENCE["Mul"], strict=True)
        product = "*".join([b] * abs(int(exp)))
        if int(exp) > 0:
            return product if int(exp) == 1 else f"({product})"
        return f"({self._one}/({product}))"

    def _print_Pow(self, expr, *args, **kwargs):
        text = self._small_power(expr)
        if text is not None:
            return text
        return super()._print_Pow(expr, *args, **kwargs)


class NumpyExactPrinter(_ExactMixin, NumPyPrinter):
    """numpy code (``numpy.cos``...) with exact floats."""

    _one = "1.0"


class MathExactPrinter(_ExactMixin, PythonCodePrinter):
    """Python ``math`` code (for one state at a time) with exact floats."""

    _one = "1.0"


class CExactPrinter(_ExactMixin, C99CodePrinter):
    """C99 code (double precision) with exact floats."""

    _one = "1.0"


def numbered(prefix: str, n: int) -> list:
    """Symbols ``prefix0 .. prefix{n-1}`` (real)."""
    return [sp.Symbol(f"{prefix}{i}", real=True) for i in range(n)]


def common_subexpressions(exprs, prefix: str = "c"):
    """``(replacements, reduced)`` of :func:`sympy.cse` with symbols ``c0, c1, ...``."""
    replacements, reduced = sp.cse(
        [sp.sympify(e) for e in exprs], symbols=sp.numbered_symbols(prefix, real=True)
    )
    return replacements, reduced


def check_printable(exprs, printer) -> None:
    """Raise a clear error when ``printer`` cannot write one of ``exprs``."""
    for e in exprs:
        text = printer.doprint(e)
        if "Not supported" in text or "# Not supported" in text:
            raise ValueError(
                f"the expression {e} uses a function that cannot be exported to "
                f"{type(printer).__name__.replace('ExactPrinter', '')} code"
            )


__all__ = [
    "CExactPrinter",
    "MAX_PRODUCT_POWER",
    "MathExactPrinter",
    "NumpyExactPrinter",
    "check_printable",
    "common_subexpressions",
    "numbered",
]
