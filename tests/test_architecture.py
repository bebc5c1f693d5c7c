"""The library's shape (docs/architecture.md): no import cycles, small modules and functions,
algorithms apart from the artifact layer, private helpers kept in their module."""
import ast
from pathlib import Path

import pytest

STEX = Path(__file__).resolve().parents[1] / "stex"
MAX_MODULE_LINES = 900
MAX_FUNCTION_LINES = 120
# Modules that read or write stores and files; every other module is pure (arrays in, arrays out).
ARTIFACT_LAYER = ("stex.io", "stex.stages", "stex.cli", "stex.reporting", "stex.preview",
                  "stex.logs", "stex.config", "stex.viewer", "stex.runlock")
STORE_MODULES = ("zarr", "stex.io", "stex.stages")


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(STEX.rglob("*.py")):
        parts = path.relative_to(STEX.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path):
    """(imported module, imported names, node, inside a function) for every import of a module."""
    tree = ast.parse(path.read_text())
    parents = {}
    for node in ast.walk(tree):
        for child in ast.iter_child_nodes(node):
            parents[child] = node
    for node in ast.walk(tree):
        if not isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        p, inside = parents.get(node), False
        while p is not None:
            if isinstance(p, (ast.FunctionDef, ast.AsyncFunctionDef)):
                inside = True
            p = parents.get(p)
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, [], node, inside
        else:
            mod = node.module or ""
            if node.level:
                base = name.split(".")
                base = base[: len(base) - node.level + (1 if path.name == "__init__.py" else 0)]
                mod = ".".join(base + ([mod] if mod else []))
            yield mod, [a.name for a in node.names], node, inside


def _graph() -> dict[str, set[str]]:
    graph = {m: set() for m in MODULES}
    for name, path in MODULES.items():
        for mod, names, _, _ in _imports(name, path):
            for target in [mod] + [f"{mod}.{n}" for n in names]:
                if target in MODULES and target != name:
                    graph[name].add(target)
    return graph


def _cycles(graph) -> list[list[str]]:
    index, low, stack, on, found, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
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
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _in(name: str, prefixes) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def test_no_import_cycle():
    assert _cycles(_graph()) == []


def test_no_stex_import_inside_a_function():
    found = [f"{name}:{node.lineno} {mod}" for name, path in MODULES.items()
             for mod, _, node, inside in _imports(name, path) if inside and _in(mod, ("stex",))]
    assert found == []


def test_imports_inside_functions_say_why():
    """A third-party import inside a function is there because the dependency is heavy or
    optional; the line (or the one above it) says so."""
    missing = []
    for name, path in MODULES.items():
        lines = path.read_text().splitlines()
        for mod, _, node, inside in _imports(name, path):
            if inside and "#" not in lines[node.lineno - 1] and not lines[node.lineno - 2].strip().startswith("#"):
                missing.append(f"{name}:{node.lineno} {mod}")
    assert missing == []


def test_no_private_name_imported_from_another_module():
    found = [f"{name}:{node.lineno} {mod}.{n}" for name, path in MODULES.items()
             for mod, names, node, _ in _imports(name, path) if _in(mod, ("stex",))
             for n in names if n.startswith("_") and n != "__version__"]
    assert found == []


def test_pure_modules_import_no_store_code():
    """Algorithms never open stores: the modules outside the artifact layer import neither zarr
    nor stex.io nor stex.stages, directly or through another stex module."""
    graph = _graph()
    direct = {name: {mod for mod, _, _, _ in _imports(name, path)} for name, path in MODULES.items()}
    bad = []
    for name in MODULES:
        if _in(name, ARTIFACT_LAYER):
            continue
        seen, todo = set(), [name]
        while todo:
            m = todo.pop()
            if m in seen:
                continue
            seen.add(m)
            if any(_in(d, STORE_MODULES) for d in direct[m]):
                bad.append(f"{name} (via {m})")
                break
            todo.extend(graph[m])
    assert bad == []


@pytest.mark.parametrize("name", sorted(MODULES))
def test_module_size(name):
    assert len(MODULES[name].read_text().splitlines()) <= MAX_MODULE_LINES


def test_function_size():
    """Numba kernels are exempt: splitting them costs speed."""
    long = []
    for name, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                decorators = " ".join(ast.unparse(d) for d in node.decorator_list)
                if node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES and "jit" not in decorators:
                    long.append(f"{name}.{node.name} ({node.end_lineno - node.lineno + 1} lines)")
    assert long == []
