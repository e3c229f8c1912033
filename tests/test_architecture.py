"""The package layout the architecture issue asks for, checked on the source."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "lagsindy"
MODULES = sorted(PACKAGE.rglob("*.py"))


def _imports_estimator(tree, module: Path) -> bool:
    depth = len(module.relative_to(PACKAGE).parts) - 1
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            target = node.module or ""
            if node.level:  # relative: resolve against the module's package
                if node.level - 1 > depth:
                    continue
                base = list(module.relative_to(PACKAGE).parts[: depth - node.level + 1])
                target = ".".join(["lagsindy", *base, target]).rstrip(".")
            if target == "lagsindy.estimator" or (
                target == "lagsindy" and any(a.name == "estimator" for a in node.names)
            ):
                return True
        if isinstance(node, ast.Import):
            if any(a.name == "lagsindy.estimator" for a in node.names):
                return True
    return False


@pytest.mark.parametrize("module", MODULES, ids=lambda m: str(m.relative_to(PACKAGE)))
def test_only_the_facade_and_the_cli_import_the_estimator(module):
    rel = module.relative_to(PACKAGE)
    allowed = (
        rel.parts[0] == "cli"
        or rel == Path("__init__.py")
        or rel.name == "estimator.py"
    )
    if not allowed:
        assert not _imports_estimator(ast.parse(module.read_text()), module)


def test_the_import_check_sees_an_import():
    # the check above must be able to fail
    fake = PACKAGE / "io" / "model_file.py"
    assert _imports_estimator(
        ast.parse("from ..estimator import LagrangianSINDy"), fake
    )
    assert _imports_estimator(ast.parse("import lagsindy.estimator"), fake)
    assert not _imports_estimator(ast.parse("from ..model import MassCheck"), fake)


@pytest.mark.parametrize("module", MODULES, ids=lambda m: str(m.relative_to(PACKAGE)))
def test_no_module_over_900_lines(module):
    assert len(module.read_text().splitlines()) <= 900


def test_the_estimator_class_is_a_facade():
    tree = ast.parse((PACKAGE / "estimator.py").read_text())
    (cls,) = [
        n
        for n in tree.body
        if isinstance(n, ast.ClassDef) and n.name == "LagrangianSINDy"
    ]
    assert cls.end_lineno - cls.lineno + 1 <= 450
