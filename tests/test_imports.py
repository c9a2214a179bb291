"""The package's imports: no cycles, the layering of docs/DESIGN (vision <- drivers <- control), and every
module importable on its own.

The import graph is read statically (ast), from module-level imports only: an import inside a function
runs when the function is called, after every module has finished loading, so it cannot take part in a
cycle at import time (and lazy imports that hide a cycle are what this test is here to make unnecessary).
Importing ``a.b.c`` also initialises the package ``a.b``; that containment is not counted as an edge,
but an explicit ``from a.b import X`` in ``a.b.c`` is (it needs ``a/b/__init__.py`` to have run).
"""
from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
LAYERS = ("control", "drivers", "vision")
# layer -> layers it must never import (docs: "Imports point one way")
FORBIDDEN = {"vision": ("control", "drivers"), "drivers": ("control",)}


def package_modules() -> dict[str, Path]:
    """vbnav module name -> source file, for every module of the three layers."""
    mods = {}
    for layer in LAYERS:
        for path in sorted((REPO / layer).rglob("*.py")):
            parts = list(path.relative_to(REPO).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods["vbnav." + ".".join(parts)] = path
    return mods


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or \
        (isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _import_nodes(tree: ast.Module, module_level: bool):
    """Import statements; with module_level, only those that run when the module is imported."""
    stack = list(tree.body)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
            continue
        if module_level:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                continue
            if isinstance(node, ast.If) and _is_type_checking(node):
                stack.extend(node.orelse)
                continue
        stack.extend(ast.iter_child_nodes(node))


def imports_of(name: str, path: Path, modules: dict[str, Path], module_level: bool = True) -> set[str]:
    """The vbnav modules that ``name`` imports (a ``from pkg import x`` names ``pkg.x`` when that is a module)."""
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in _import_nodes(tree, module_level):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        else:
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        out.update(t for t in targets if t in modules and t != name)
    return out


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as [a, b, ..., a], or None (iterative depth-first search)."""
    state = dict.fromkeys(graph, 0)          # 0 unseen, 1 on the current path, 2 done
    for root in sorted(graph):
        if state[root]:
            continue
        path, iters = [root], [iter(sorted(graph[root]))]
        state[root] = 1
        while path:
            nxt = next(iters[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                iters.pop()
            elif state[nxt] == 1:
                return path[path.index(nxt):] + [nxt]
            elif state[nxt] == 0:
                state[nxt] = 1
                path.append(nxt)
                iters.append(iter(sorted(graph[nxt])))
    return None


def test_module_level_imports_have_no_cycle():
    modules = package_modules()
    graph = {m: imports_of(m, p, modules) for m, p in modules.items()}
    assert sum(map(len, graph.values())) > 100          # the reader found the package's imports
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_find_cycle_names_the_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_layers_import_one_way():
    """vision imports neither control nor drivers; drivers never imports control (lazy imports included)."""
    modules = package_modules()
    bad = []
    for name, path in modules.items():
        layer = name.split(".")[1]
        for target in imports_of(name, path, modules, module_level=False):
            if target.split(".")[1] in FORBIDDEN.get(layer, ()):
                bad.append(f"{name} imports {target}")
    assert not bad, "\n".join(bad)


def test_every_module_imports_in_a_fresh_interpreter():
    """Each module on its own, so an import that only works after some other module loaded shows up. Each
    module is imported in a process where no other vbnav module was (tests/cli_forks.py --imports: forked
    from an interpreter that loaded only the heavy third-party libraries)."""
    modules = sorted(package_modules())
    r = subprocess.run([sys.executable, str(REPO / "tests" / "cli_forks.py"), "--imports"], input=json.dumps(modules),
                       capture_output=True, text=True, timeout=600, cwd=REPO)
    assert r.returncode == 0, r.stderr
    results = json.loads(r.stdout)
    assert len(results) == len(modules)
    failed = [f"{m}: {(res['stderr'].strip().splitlines() or ['?'])[-1]}" for m, res in zip(modules, results)
              if res["returncode"] != 0]
    assert not failed, "modules that fail to import alone:\n" + "\n".join(failed)
