"""The package layout reads as the pipeline: imports point down it, never in a circle, and the
public API stays where users import it from."""

from __future__ import annotations

import ast
from pathlib import Path

import colmap_citymodel

PACKAGE = Path(colmap_citymodel.__file__).parent
NAME = "colmap_citymodel"

#: The order of the stages. A module may import modules of its own rank or a lower one:
#: shared foundations first, then the pipeline read -> store -> georegister -> assign ->
#: adjust -> precision -> write, then what drives it (workflow, batch, CLI, simulation, demo).
RANKS = {
    "errors": 0, "options": 0, "files": 0, "_ext": 0,
    "citymodel": 1, "block": 2, "errormodel": 2, "align": 3, "assign": 4, "adjust": 5,
    "precision": 6, "output": 7, "workflow": 8, "mapper": 8, "batch": 9, "pipeline": 9,
    "simulate": 10, "demo": 11, "cli": 12,
    "__main__": 13,
    NAME: 14,  # the package's face: re-exports the public API
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_module(name: str) -> bool:
    path = PACKAGE.parent / Path(*name.split("."))
    return path.with_suffix(".py").exists() or (path / "__init__.py").exists()


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """ids of the import nodes under `if TYPE_CHECKING:` (names for annotations only)."""
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            skip.update(id(n) for n in ast.walk(node))
    return skip


def package_imports() -> dict[str, set[str]]:
    """module -> the package modules it imports anywhere in its code (function-level imports
    too, `if TYPE_CHECKING` ones not)."""
    graph: dict[str, set[str]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        module = module_name(path)
        is_package = path.name == "__init__.py"
        tree = ast.parse(path.read_text())
        skip = _type_checking_nodes(tree)
        targets = graph.setdefault(module, set())
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            if isinstance(node, ast.Import):
                targets.update(a.name for a in node.names if a.name.startswith(NAME))
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = module.split(".") if is_package else module.split(".")[:-1]
                    base = base[:len(base) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if not target.startswith(NAME):
                    continue
                for alias in node.names:  # `from pkg import module` imports the module
                    sub = f"{target}.{alias.name}"
                    targets.add(sub if _is_module(sub) else target)
        targets.discard(module)
    return graph


def rank(module: str) -> int:
    parts = module.split(".")
    return RANKS[parts[1]] if len(parts) > 1 else RANKS[NAME]


def test_every_module_has_a_rank():
    for module in package_imports():
        parts = module.split(".")
        assert len(parts) == 1 or parts[1] in RANKS, f"{module}: add its stage to RANKS"


def test_no_import_circle():
    graph = package_imports()
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(module: str) -> None:
        state[module] = 1
        path.append(module)
        for target in sorted(graph.get(module, ())):
            if target == NAME or (module.startswith(target + ".") and target in graph):
                continue  # a package's own face: importing it runs its __init__ only
            if state.get(target) == 1:
                circle = path[path.index(target):] + [target]
                raise AssertionError("import circle: " + " -> ".join(circle))
            if state.get(target) is None:
                visit(target)
        path.pop()
        state[module] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module)


def test_imports_point_down_the_pipeline():
    wrong = [f"{module} (rank {rank(module)}) imports {target} (rank {rank(target)})"
             for module, targets in package_imports().items() for target in targets
             if target != NAME and rank(target) > rank(module)]
    assert not wrong, "\n".join(wrong)


def test_one_definition_per_class():
    seen: dict[str, str] = {}
    twins = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.ClassDef):
                if node.name in seen:
                    twins.append(f"{node.name}: {seen[node.name]} and {module_name(path)}")
                seen[node.name] = module_name(path)
    assert not twins, twins


def test_public_api():
    import colmap_citymodel as api
    from colmap_citymodel.citymodel.read import read_city_model
    from colmap_citymodel.errors import CityModelError, InputError
    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.output.result import RefineResult
    from colmap_citymodel.workflow import refine

    assert api.refine is refine
    assert api.read_city_model is read_city_model
    assert api.RefineOptions is RefineOptions
    assert api.RefineResult is RefineResult
    assert api.CityModelError is CityModelError and issubclass(InputError, CityModelError)
    assert set(api.__all__) >= {"refine", "read_city_model", "RefineOptions", "RefineResult",
                                "CityModelError", "logger", "__version__"}
    # The default options carry the documented defaults (method.md; the assignment method is
    # the automatic choice between (c) and (a), options.AssignmentOptions.method).
    options = RefineOptions()
    assert options.adjustment.sigma_dtp == 0.2 and options.assignment.method == "auto"
