"""The package layout: the import graph of src/bitcomm, read with `ast`, has no cycles, and each package
imports only the layers below it (what its `__init__` docstring says it may import).

Every import counts, at module level or inside a function, except those under `if TYPE_CHECKING:`
(they never run). `bitcomm` (the root `__init__`, whose public names load lazily) and the modules beside
it (config, errors, files, checkpoint, run_lock, plotting, stats) are the base layer; `bitcomm.cli` and
`bitcomm.__main__` (`python -m bitcomm`) sit with the commands.
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"

LAYERS = [
    {"base"},
    {"channel"},
    {"envs"},
    {"policies"},
    {"learn", "deploy"},
    {"studies"},
    {"commands"},
]
"""Lowest first. A package may import its own modules and the layers below its own, never a peer
(`learn` and `deploy` do not know each other)."""
LAYER = {package: rank for rank, packages in enumerate(LAYERS) for package in packages}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def package_of(module: str) -> str:
    """`bitcomm.learn.run` -> `learn`; the root and the modules beside it -> `base`; the command line's entry
    points, `bitcomm.cli` and `bitcomm.__main__`, -> `commands`."""
    parts = module.split(".")
    if module in ("bitcomm.cli", "bitcomm.__main__"):
        return "commands"
    if len(parts) == 1 or (SRC / "bitcomm" / f"{parts[1]}.py").is_file():
        return "base"
    return parts[1]


def _type_checking(node: ast.If) -> bool:
    return isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING"


def imports_of(path: Path) -> set[str]:
    """The `bitcomm` modules `path` imports when it runs (a `from X import name` of a submodule counts as it)."""
    here = module_name(path)
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.split(".")[0] == "bitcomm")
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "bitcomm":
            found.add(node.module)
            for a in node.names:  # `from bitcomm.envs import goal_exchange_v0` imports a module
                candidate = f"{node.module}.{a.name}"
                if resolve(candidate) is not None:
                    found.add(candidate)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text(), str(path)))
    found.discard(here)
    return found


def resolve(module: str) -> Path | None:
    base = SRC.joinpath(*module.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def import_graph() -> dict[str, set[str]]:
    """Module -> the modules it imports; importing `a.b.c` runs `a/__init__` and `a/b/__init__` too,
    except the importer's own enclosing packages (already running when it runs)."""
    graph: dict[str, set[str]] = {}
    for path in sorted((SRC / "bitcomm").rglob("*.py")):
        here = module_name(path).split(".")
        enclosing = {".".join(here[:k]) for k in range(1, len(here) + 1)}
        edges = set()
        for target in imports_of(path):
            parts = target.split(".")
            edges.update(p for p in (".".join(parts[:k]) for k in range(2, len(parts) + 1)) if resolve(p))
        graph[module_name(path)] = edges - enclosing
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of `graph` as a list of nodes (first == last), or None."""
    colour: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def dfs(node: str) -> list[str] | None:
        colour[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if colour.get(nxt) == 1:
                return [*stack[stack.index(nxt) :], nxt]
            if nxt not in colour and (found := dfs(nxt)) is not None:
                return found
        stack.pop()
        colour[node] = 2
        return None

    for node in sorted(graph):
        if node not in colour and (found := dfs(node)) is not None:
            return found
    return None


def test_every_package_has_a_layer_and_a_docstring() -> None:
    packages = {p.parent.name for p in (SRC / "bitcomm").glob("*/__init__.py")}
    assert packages <= set(LAYER), f"packages without a layer: {packages - set(LAYER)}"
    for package in packages:
        doc = ast.get_docstring(ast.parse((SRC / "bitcomm" / package / "__init__.py").read_text()))
        assert doc, f"bitcomm.{package} has no docstring"
        assert "import" in doc, f"bitcomm.{package}'s docstring does not say what it may import"


def test_packages_import_only_lower_layers() -> None:
    bad = []
    for module, targets in import_graph().items():
        src = package_of(module)
        for target in targets:
            dst = package_of(target)
            if dst != src and LAYER[dst] >= LAYER[src]:
                bad.append(f"{module} ({src}) imports {target} ({dst})")
    assert not bad, "\n".join(bad)


def test_no_import_cycles() -> None:
    graph = import_graph()
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph) or [])
    packages: dict[str, set[str]] = {}
    for module, targets in graph.items():
        packages.setdefault(package_of(module), set()).update(package_of(t) for t in targets)
    for src, dsts in packages.items():
        dsts.discard(src)
    assert find_cycle(packages) is None, " -> ".join(find_cycle(packages) or [])


def test_the_graph_sees_function_level_imports() -> None:
    """The reader is what the two tests above rely on: a cycle through a function-level import is caught."""
    assert "bitcomm.learn.a3c" in import_graph()["bitcomm.learn.run"]  # imported inside `train`
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None
