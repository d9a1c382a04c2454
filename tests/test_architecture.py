"""The package's layout: no import circle between its modules, nor between its packages (function-local
imports included), no test oracle left in src, and no underscore name imported from another package
(docs/architecture.md)."""

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "groomtool"


def _modules() -> dict:
    mods = {}
    for path in SRC.rglob("*.py"):
        parts = path.relative_to(SRC.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        mods[name] = path
    return mods


def _imports(mods: dict) -> dict:
    """module -> the groomtool modules it imports anywhere in its source."""
    edges = {}
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[:len(package.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                for alias in node.names:
                    if f"{target}.{alias.name}" in mods:
                        found.add(f"{target}.{alias.name}")
                    elif target in mods:
                        found.add(target)
            elif isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names if alias.name in mods)
        edges[name] = found - {name}
    return edges


def _cycles(edges: dict) -> list:
    """Strongly connected components of more than one node (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in list(edges):
        if v not in index:
            visit(v)
    return out


def test_no_import_circle_between_modules():
    assert _cycles(_imports(_modules())) == []


def test_no_import_circle_between_packages():
    def package(name):  # groomtool.io.usd -> groomtool.io; top-level modules are their own
        return ".".join(name.split(".")[:2])

    edges = {}
    for a, targets in _imports(_modules()).items():
        for b in targets:
            if package(a) != package(b):
                edges.setdefault(package(a), set()).add(package(b))
    assert _cycles(edges) == []


def test_no_test_oracle_in_src():
    """Reference implementations that only tests use live in tests/reference/."""
    names = []
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and (
                    node.name.endswith(("_reference", "_numpy")) or node.name.startswith("_reference")):
                names.append(f"{path.relative_to(SRC)}:{node.name}")
    assert names == []


def test_no_private_import_across_packages():
    """A module imports another package's underscore names only through its public API."""
    def package(name):
        return ".".join(name.split(".")[:2])

    mods = _modules()
    found = []
    for name, path in mods.items():
        pkg = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.ImportFrom):
                continue
            if node.level:
                base = pkg.split(".")[:len(pkg.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("groomtool"):
                continue
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__") and package(target) != package(name):
                    found.append(f"{name}: from {target} import {alias.name}")
    assert found == []
