"""The import directions of docs/LAYOUT.md, checked on the source: who may import whom, and no circles.

Read from the files with `ast` (nothing is imported), so a violation is reported as the file, the line
and the rule, and the test costs a fraction of a second.
"""
from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("rvs_server", "toolbox", "drivers", "clients")
CAPABILITIES = ("system", "ptu", "imaging", "mapping", "navigation", "hopping", "routes", "hazard", "orientation",
                "tracking", "simulation")
# A capability reaches another only through these modules (its named interface).
INTERFACES = {
    ("navigation", "mapping"): {"rvs_server.mapping"},
    ("routes", "mapping"): {"rvs_server.mapping"},
    ("navigation", "orientation"): {"rvs_server.orientation"},
    ("routes", "orientation"): {"rvs_server.orientation"},
}


@dataclass(frozen=True)
class Import:
    source: str      # importing module
    target: str      # imported module (the longest name that is a module of ours)
    line: int
    top_level: bool  # run on import (not inside a function, not under TYPE_CHECKING)


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def our_modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in (REPO / package).rglob("*.py"):
            found[module_name(path)] = path
    return found


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> list[Import]:
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: list[Import] = []

    def resolve(base: str, names: list[str]) -> list[str]:
        # `from a.b import c` names module a.b.c when c is one, else a.b
        return sorted({f"{base}.{n}" if f"{base}.{n}" in modules else base for n in names}) or [base]

    def visit(node: ast.AST, top_level: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                visit(child, False)
            elif isinstance(child, ast.If) and _is_type_checking(child):
                visit(child, False)
            elif isinstance(child, ast.Import):
                for alias in child.names:
                    found.extend(Import(name, t, child.lineno, top_level) for t in resolve(alias.name, []))
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base_parts = package.split(".")[: len(package.split(".")) - (child.level - 1)]
                    base = ".".join(base_parts + ([child.module] if child.module else []))
                else:
                    base = child.module or ""
                targets = resolve(base, [a.name for a in child.names])
                found.extend(Import(name, t, child.lineno, top_level) for t in targets)
            else:
                visit(child, top_level)

    visit(tree, True)
    return [i for i in found if i.target.split(".")[0] in PACKAGES]


def all_imports() -> list[Import]:
    modules = our_modules()
    return [i for name, path in sorted(modules.items()) for i in imports_of(name, path, modules)]


def capability_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "rvs_server" and parts[1] in CAPABILITIES else None


def violation(i: Import) -> str | None:
    """The rule an import breaks, or None."""
    src, dst = i.source, i.target
    src_top, dst_top = src.split(".")[0], dst.split(".")[0]
    if src_top == "clients" and dst_top != "clients" and dst != "rvs_server.protocol":
        return "clients see only rvs_server.protocol"
    if src_top == "toolbox" and dst_top != "toolbox":
        return "the toolbox is algorithms only: it imports nothing of the server or the drivers"
    if src_top == "drivers" and dst_top in ("rvs_server", "clients"):
        return "drivers never import the server"
    if src_top == "rvs_server":
        mine, theirs = capability_of(src), capability_of(dst)
        if dst_top == "clients":
            return "the server never imports its clients"
        if mine is None and theirs is not None and src != "rvs_server.app":
            return "the core never imports a capability (only app.py lists them)"
        if mine is not None and dst_top == "drivers":
            return "a capability reaches the hardware and the simulator only through rvs_server.devices"
        if mine is not None and theirs is not None and mine != theirs and \
                dst not in INTERFACES.get((mine, theirs), set()):
            allowed = sorted(INTERFACES.get((mine, theirs), set())) or "nothing"
            return f"{mine} may import from {theirs} only {allowed}"
    return None


def test_every_import_points_the_way_the_layout_says():
    broken = [f"{i.source} line {i.line} imports {i.target}: {rule}"
              for i in all_imports() if (rule := violation(i))]
    assert not broken, "\n".join(broken)


def import_graph(imports: list[Import]) -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for i in imports:
        if i.target != i.source:
            graph.setdefault(i.source, set()).add(i.target)
    return graph


def describe_circle(circle: set[str], imports: list[Import]) -> str:
    edges = sorted(f"{i.source} line {i.line} -> {i.target}{'' if i.top_level else ' (deferred)'}"
                   for i in imports if i.source in circle and i.target in circle and i.source != i.target)
    return " -> ".join(sorted(circle)) + ":\n    " + "\n    ".join(edges)


def test_no_import_circles():
    """No circle between files, not even one that only runs later: every import counts, at the top,
    inside a function or under TYPE_CHECKING. A circle the type checker alone sees still ties the
    files together (neither can be read, tested or moved without the other); shared types belong in
    a module both import (rvs_server/host.py, rvs_server/recovery.py), and a seam in a Protocol
    (activities.ActivityHost, devices.rover.DrivingJob, hazard.guard.Watch, dispatch.DispatchHost)."""
    imports = all_imports()
    circles = strongly_connected(import_graph(imports))
    assert not circles, "import circles:\n" + "\n".join(describe_circle(c, imports) for c in circles)


def strongly_connected(graph: dict[str, set[str]]) -> list[set[str]]:
    """Tarjan's algorithm: the components with more than one module."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[set[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.add(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(component)

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return components


def test_the_checker_sees_a_broken_rule_and_a_circle():
    """The rules bite: each kind of wrong import is named, and a two-module circle is found."""
    assert violation(Import("clients.gnc", "rvs_server.dispatch", 1, True))
    assert violation(Import("toolbox.mapping.dem", "rvs_server.files", 1, True))
    assert violation(Import("drivers.sim.world", "rvs_server.protocol", 1, True))
    assert violation(Import("rvs_server.dispatch", "rvs_server.routes.commands", 1, True))
    assert violation(Import("rvs_server.navigation.navigate", "drivers.sim.motion", 1, True))
    assert violation(Import("rvs_server.routes.commands", "rvs_server.hopping.store", 1, True))
    assert violation(Import("rvs_server.navigation.navigate", "rvs_server.mapping.steps", 1, True))
    assert violation(Import("rvs_server.navigation.navigate", "rvs_server.mapping", 1, True)) is None
    assert violation(Import("drivers.sim.rover", "toolbox.geometry", 1, True)) is None
    assert strongly_connected({"a": {"b"}, "b": {"a"}, "c": {"a"}}) == [{"a", "b"}]


def test_a_circle_under_type_checking_or_in_a_function_counts(tmp_path):
    """The graph holds the imports the interpreter runs later or never: a circle made only of them is
    found, as test_no_import_circles needs."""
    package = tmp_path / "rvs_server"
    package.mkdir()
    (package / "a.py").write_text("from typing import TYPE_CHECKING\n"
                                  "if TYPE_CHECKING:\n    from rvs_server.b import B\n")
    (package / "b.py").write_text("def f():\n    from rvs_server import a\n    return a\n")
    modules = {"rvs_server.a": package / "a.py", "rvs_server.b": package / "b.py"}
    imports = [i for name, path in modules.items() for i in imports_of(name, path, modules)]
    assert {(i.source, i.target, i.top_level) for i in imports} == {
        ("rvs_server.a", "rvs_server.b", False), ("rvs_server.b", "rvs_server.a", False)}
    assert strongly_connected(import_graph(imports)) == [{"rvs_server.a", "rvs_server.b"}]
