"""The package's layout contract, checked on the source (see ARCHITECTURE.md).

Units are the package's top-level modules and sub-packages (``io.model_file`` is a
unit of its own: the model document, below the estimator that reads it). A unit may
import units of its own layer or below, never above; nothing imports the package
itself; no unit imports or reaches another unit's private (``_name``) names.
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "lagsindy"
MODULES = sorted(PACKAGE.rglob("*.py"))

# Lowest first. A unit is the longest dotted prefix of a module listed here.
LAYERS = [
    ("base", ["_expr", "_lazy", "_names", "_stacklevel", "_torch", "_params", "_validation", "_version"]),
    ("differentiation", ["differentiation"]),
    (
        "terms and forces",
        [
            "_batched",
            "_torchfunc",
            "evaluator",
            "library",
            "reduction",
            "dissipation",
            "force_kinds",
            "robots",
        ],
    ),
    ("mechanics", ["dynamics"]),
    ("solvers", ["solvers"]),
    ("formulation", ["formulation", "euler_lagrange"]),
    ("cases", ["cases"]),
    ("fitted state", ["angle_units", "model", "io.model_file", "settings"]),
    ("what a model is used for", ["export"]),
    ("pipeline", ["pipeline", "partitioned", "joint"]),
    ("estimator", ["estimator"]),
    (
        "consumers",
        ["diagnostics", "uncertainty", "delay", "refine", "plotting"],
    ),
    ("files and data", ["io", "systems"]),
    ("command line and facade", ["cli", "export.command", "__init__", "__main__"]),
]
LAYER_OF = {unit: k for k, (_, units) in enumerate(LAYERS) for unit in units}
# Modules whose private names are the package's shared base (imported as modules).
BASE_MODULES = set(LAYERS[0][1]) | {"_batched"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE).with_suffix("").parts)
    if parts[-1] == "__init__" and len(parts) > 1:
        parts = parts[:-1]
    return ".".join(parts)


def unit_of(dotted: str) -> str | None:
    """The unit of a module path relative to the package (``""``: the package)."""
    if dotted in ("", "__init__"):
        return "__init__"
    parts = dotted.split(".")
    for k in range(len(parts), 0, -1):
        if ".".join(parts[:k]) in LAYER_OF:
            return ".".join(parts[:k])
    return None


def imports(tree, module: str):
    """``(target module relative to the package, imported name or None, line)`` of
    every import of the package in a module's source, function-level ones too."""
    package = module.split(".")[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                target = ".".join([*base, node.module] if node.module else base)
            elif (node.module or "").split(".")[0] == "lagsindy":
                target = node.module[len("lagsindy") :].lstrip(".")
            else:
                continue
            for alias in node.names:
                out.append((target, alias.name, node.lineno))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "lagsindy":
                    out.append((alias.name[len("lagsindy") :].lstrip("."), None, 0))
    return out


def _sources():
    for path in MODULES:
        name = _module_name(path)
        if path.name == "__init__.py":
            name = name + ".__init__" if name != "__init__" else "__init__"
        yield path, name, ast.parse(path.read_text())


def layer_violations(tree, module: str) -> list:
    """Imports of ``module`` that go to a higher layer, or to the package itself."""
    unit = unit_of(module.removesuffix(".__init__"))
    bad = []
    for target, name, line in imports(tree, module):
        if target == "" and name not in LAYER_OF:
            if unit not in ("__init__", "__main__"):
                bad.append(f"line {line}: imports the package itself ({name})")
            continue
        other = unit_of(name if target == "" else target)
        if other is None or unit is None or other == unit:
            continue
        if LAYER_OF[other] > LAYER_OF[unit]:
            bad.append(f"line {line}: {unit} imports {other} (a higher layer)")
    return bad


def private_imports(tree, module: str) -> list:
    """Private names a module imports from another unit."""
    unit = unit_of(module.removesuffix(".__init__"))
    bad = []
    for target, name, line in imports(tree, module):
        other = unit_of(target) if target else None
        if other is None or other == unit or name is None:
            continue
        if name.startswith("_") and not name.startswith("__"):
            if target in BASE_MODULES and name in BASE_MODULES:
                continue
            bad.append(f"line {line}: {name} from {target}")
    return bad


def _defined_private(tree) -> set:
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.ClassDef | ast.AsyncFunctionDef):
            if node.name.startswith("_") and not node.name.startswith("__"):
                names.add(node.name)
    return names


def private_reach_through(sources) -> list:
    """``x._name`` where ``_name`` is a function defined only in other units."""
    defined = {}
    for _, module, tree in sources:
        unit = unit_of(module.removesuffix(".__init__"))
        for name in _defined_private(tree):
            defined.setdefault(name, set()).add(unit)
    bad = []
    for path, module, tree in sources:
        unit = unit_of(module.removesuffix(".__init__"))
        for node in ast.walk(tree):
            if not isinstance(node, ast.Attribute) or node.attr not in defined:
                continue
            if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
                continue
            if unit not in defined[node.attr]:
                bad.append(f"{path.name}:{node.lineno}: .{node.attr}")
    return bad


SOURCES = list(_sources())


@pytest.mark.parametrize(
    "path,module,tree",
    SOURCES,
    ids=[str(p.relative_to(PACKAGE)) for p, _, _ in SOURCES],
)
def test_layers(path, module, tree):
    assert unit_of(module.removesuffix(".__init__")) is not None, (
        f"{module} belongs to no layer: add it to LAYERS (and ARCHITECTURE.md)"
    )
    assert not layer_violations(tree, module)
    assert not private_imports(tree, module)


def test_no_private_reach_through():
    assert not private_reach_through(SOURCES)


def test_the_checks_can_fail():
    def tree(code):
        return ast.parse(code)

    # a lower layer importing a higher one, relative and absolute
    assert layer_violations(tree("from ..estimator import X"), "io.model_file")
    assert layer_violations(tree("from .estimator import X"), "model")
    assert layer_violations(tree("import lagsindy.pipeline"), "cases.fixed")
    assert layer_violations(tree("from lagsindy import LagrangianSINDy"), "delay")
    assert layer_violations(tree("from . import LagrangianSINDy"), "delay")
    # allowed: downward and within a unit
    assert not layer_violations(tree("from .model import X"), "estimator")
    assert not layer_violations(tree("from .scoring import X"), "diagnostics.loop")
    assert not layer_violations(tree("from . import pipeline"), "delay")
    # private names across units
    assert private_imports(tree("from ..formulation.weak import _jumps"), "refine")
    assert not private_imports(tree("from .scoring import _Scorer"), "diagnostics.loop")
    srcs = [
        (Path("a.py"), "estimator", tree("class E:\n    def _prep(self): pass")),
        (Path("b.py"), "delay", tree("def f(est):\n    return est._prep()")),
    ]
    assert private_reach_through(srcs)


@pytest.mark.parametrize("path", MODULES, ids=lambda m: str(m.relative_to(PACKAGE)))
def test_no_module_over_700_lines(path):
    assert len(path.read_text().splitlines()) <= 700


def test_the_estimator_is_a_facade():
    assert len((PACKAGE / "estimator.py").read_text().splitlines()) <= 500
