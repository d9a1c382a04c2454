"""The package's layout: no import circle between its modules, nor between its packages (function-local
imports included), no test oracle left in src, no public function that only the tests use, and no underscore
name imported from another package (docs/architecture.md)."""

import ast
import re
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


# Public names that the package itself does not call but users do: each documented (the page in the comment).
USED_OUTSIDE_THE_PACKAGE = {
    "groom.py:Groom.scaled",              # a groom in other units; docs/architecture.md "Public API"
    "rods/superhelix.py:elastic_energy",  # the rod model's energy; docs/architecture.md "Public API"
    "rods/clothoid.py:elastic_energy",    # the same for Super Space Clothoids; docs/clothoid.md's API list
    "rods/cosserat.py:pyelastica_rod",    # the PyElastica loader of the rest data; docs/rest_data.md
    "rods/der.py:der_energy",             # the DER energy of the rest data; docs/rest_data.md
    "simulate.py:Simulator.energies",     # a state's energies; docs/simulation.md section 4, architecture.md
    "rods/dynamics.py:clothoid_kinetic_energy",  # T from the point velocities; docs/clothoid.md, architecture.md
}


def _names_used(paths) -> set:
    """Every name a module refers to: names, attributes, imported names, and strings that are identifiers
    (getattr, __all__); a definition itself does not count."""
    used = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Name):
                used.add(node.id)
            elif isinstance(node, ast.Attribute):
                used.add(node.attr)
            elif isinstance(node, ast.alias):
                used.add(node.name.rsplit(".", 1)[-1])
            elif isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.isidentifier():
                used.add(node.value)
    return used


def test_no_public_function_used_only_by_tests():
    """A public function, class or method of the package that only tests/ refer to is a test oracle or helper:
    it belongs in tests/reference/ (or, if users call it, in USED_OUTSIDE_THE_PACKAGE with its page).  By name:
    a name used anywhere in src/ or bench/ counts as used (methods of the same name included)."""
    root = SRC.parents[1]
    outside = _names_used(SRC.rglob("*.py")) | _names_used((root / "bench").rglob("*.py"))
    outside |= set(re.findall(r"\w+", (root / "pyproject.toml").read_text(encoding="utf-8")))  # entry points
    by_tests = _names_used((root / "tests").rglob("*.py"))
    found = []
    for path in SRC.rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in tree.body:
            members = [(node.name, node)] if isinstance(node, (ast.FunctionDef, ast.ClassDef)) else []
            if isinstance(node, ast.ClassDef):
                members += [(f"{node.name}.{sub.name}", sub) for sub in node.body if isinstance(sub, ast.FunctionDef)]
            for qualname, member in members:
                name = member.name
                if name.startswith("_") or name in outside or name not in by_tests:
                    continue
                found.append(f"{path.relative_to(SRC).as_posix()}:{qualname}")
    assert sorted(set(found) - USED_OUTSIDE_THE_PACKAGE) == []
    assert sorted(USED_OUTSIDE_THE_PACKAGE - set(found)) == []  # stale entries: used in the package by now
