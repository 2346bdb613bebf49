"""Import cycles inside a Python package, found from the source (nothing is imported).

Every import statement counts, also one inside a function (a deferred import hides a
cycle, it does not remove it), relative or absolute. Importing ``pkg.sub.mod`` runs
``pkg/sub/__init__.py`` first, so that edge is added as well. Cycles are the strongly
connected components of the module graph with more than one module.

    python Testing/import_cycles.py FevarPlanner/FevarPlannerLib

prints each cycle and, for every edge inside it, the imported names and their lines;
exit code 1 when there is a cycle.
"""

from __future__ import annotations

import ast
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

__all__ = ["ImportEdge", "import_edges", "import_cycles"]


@dataclass(frozen=True)
class ImportEdge:
    """One imported name: ``importer`` needs ``imported`` for ``name`` at ``line``."""

    importer: str
    imported: str
    name: str
    line: int
    in_function: bool


def _module_names(root: Path) -> dict[str, Path]:
    names = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return names


def _owner(dotted: str, modules) -> str | None:
    """The module of the package that ``dotted`` names: itself or its nearest parent."""
    while dotted and dotted not in modules:
        dotted = dotted.rpartition(".")[0]
    return dotted or None


def _from_targets(module: str, is_package: bool, node: ast.ImportFrom, modules):
    """(target module, name) for each name of ``from X import a, b``."""
    if node.level == 0:
        base = node.module or ""
    else:
        parts = module.split(".") if is_package else module.split(".")[:-1]
        parts = parts[:len(parts) - (node.level - 1)]
        base = ".".join(parts + ([node.module] if node.module else []))
    for alias in node.names:
        submodule = f"{base}.{alias.name}"
        yield (submodule if submodule in modules else base), alias.name


def _statement_edges(module: str, path: Path, modules, package: str):
    tree = ast.parse(path.read_text(), filename=str(path))
    in_function = {id(inner) for outer in ast.walk(tree) if isinstance(outer, (ast.FunctionDef, ast.AsyncFunctionDef))
                   for inner in ast.walk(outer)}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            targets = _from_targets(module, path.name == "__init__.py", node, modules)
        elif isinstance(node, ast.Import):
            targets = [(alias.name, alias.name) for alias in node.names
                       if alias.name == package or alias.name.startswith(package + ".")]
        else:
            continue
        for target, name in targets:
            owner = _owner(target, modules)
            if owner and owner != module:
                yield ImportEdge(module, owner, name, node.lineno, id(node) in in_function)


def _parent_packages(importer: str, imported: str, package: str, modules):
    """The ``__init__`` modules that importing ``imported`` runs first (the top package aside)."""
    parent = imported.rpartition(".")[0]
    while parent and parent != package and parent in modules:
        if importer != parent and not importer.startswith(parent + "."):
            yield parent
        parent = parent.rpartition(".")[0]


def import_edges(package_dir) -> list[ImportEdge]:
    """Every import of one module of the package by another, from the source of ``package_dir``."""
    root = Path(package_dir).resolve()
    modules = _module_names(root)
    edges = []
    for module, path in modules.items():
        for edge in _statement_edges(module, path, modules, root.name):
            edges.append(edge)
            for parent in _parent_packages(module, edge.imported, root.name, modules):
                edges.append(ImportEdge(module, parent, f"(runs {parent}/__init__ for {edge.imported})",
                                        edge.line, edge.in_function))
    return edges


def _strongly_connected(graph: dict[str, set]) -> list[list[str]]:
    """Tarjan's algorithm, iterative; components in no particular order."""
    index, low, on_stack, stack, components = {}, {}, set(), [], []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                components.append(sorted(component))
    return components


def import_cycles(package_dir) -> list[tuple[list[str], list[ImportEdge]]]:
    """The import cycles of a package: (modules of one cycle, the edges between them), sorted.

    Parameters
    ----------
    package_dir : path
        The package folder (holding ``__init__.py``).

    Returns
    -------
    list of (list of str, list of ImportEdge)
        Empty when the import graph has no cycle.
    """
    edges = import_edges(package_dir)
    graph = defaultdict(set)
    for edge in edges:
        graph[edge.importer].add(edge.imported)
        graph.setdefault(edge.imported, set())
    cycles = []
    for component in _strongly_connected(graph):
        if len(component) > 1:
            members = set(component)
            cycles.append((component, [e for e in edges if e.importer in members and e.imported in members]))
    return sorted(cycles)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1:
        print(__doc__.strip().splitlines()[0], "\nusage: import_cycles.py PACKAGE_DIR", file=sys.stderr)
        return 2
    cycles = import_cycles(argv[0])
    if not cycles:
        print(f"{argv[0]}: no import cycle")
    for modules, edges in cycles:
        print("cycle: " + " <-> ".join(modules))
        for edge in edges:
            where = f"line {edge.line}" + (", inside a function" if edge.in_function else "")
            print(f"  {edge.importer} -> {edge.imported}: {edge.name} ({where})")
    return 1 if cycles else 0


if __name__ == "__main__":
    raise SystemExit(main())
