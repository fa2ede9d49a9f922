"""The import rule of the code base (`README.md`, Layout), checked on the source with `ast`.

Imports run one way: `services` -> `workers` -> `db` -> `workers.pipeline`. The pipeline imports
none of the service frameworks, no module imports itself in a circle (imports under
`TYPE_CHECKING` and inside functions count: a circle hidden there is still a circle), and no
product module reaches another through `importlib`.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("services", "workers", "db")
#: layer of each top-level part, lowest first; a module may import only its own layer or lower
LAYERS = ("workers.pipeline", "db", "workers", "services")
#: third-party packages the pipeline must never import
SERVICE_FRAMEWORKS = ("sqlalchemy", "geoalchemy2", "alembic", "psycopg", "fastapi", "starlette", "uvicorn",
                      "celery", "kombu", "redis")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def product_modules() -> dict[str, Path]:
    """Every Python module of the product (not tests, not bench), name -> file."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            if "migrations" in path.parts and "versions" in path.parts:
                continue  # Alembic revision scripts are loaded by Alembic, not imported
            out[_module_name(path)] = path
    return out


def imports_of(path: Path, name: str, modules: dict[str, Path]) -> list[tuple[str, int]]:
    """(imported module, line) for every import anywhere in the file, resolved to the most
    specific product module (`from a.b import c` is `a.b.c` when that is a module)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: list[tuple[str, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")
                up = up[: len(up) - (node.level - 1)]
                base = ".".join([*up, base] if base else up)
            for a in node.names:
                full = f"{base}.{a.name}"
                found.append((full if full in modules else base, node.lineno))
    return found


def layer(module: str) -> int | None:
    """Index into `LAYERS` of a product module (None: third party or standard library)."""
    best = None
    for k, prefix in enumerate(LAYERS):
        inside = module == prefix or module.startswith(prefix + ".")
        if inside and (best is None or len(prefix) > len(LAYERS[best])):
            best = k
    return best


def test_the_rule_sees_every_layer() -> None:
    """The walk finds modules in every layer (a rule that checks nothing cannot fail)."""
    modules = product_modules()
    assert {layer(m) for m in modules} == set(range(len(LAYERS)))
    assert len(modules) > 60


def test_imports_run_downward_only() -> None:
    modules = product_modules()
    wrong = []
    for name, path in modules.items():
        own = layer(name)
        for target, line in imports_of(path, name, modules):
            other = layer(target)
            if other is not None and own is not None and other > own:
                wrong.append(f"{path.relative_to(REPO)}:{line}: {name} ({LAYERS[own]}) imports "
                             f"{target} ({LAYERS[other]})")
    assert not wrong, "imports that run upward:\n" + "\n".join(wrong)


def test_the_pipeline_imports_no_service_framework() -> None:
    modules = product_modules()
    wrong = []
    for name, path in modules.items():
        if layer(name) != 0:
            continue
        for target, line in imports_of(path, name, modules):
            if target.split(".")[0] in SERVICE_FRAMEWORKS:
                wrong.append(f"{path.relative_to(REPO)}:{line}: {target}")
    assert not wrong, "the pipeline imports a service framework:\n" + "\n".join(wrong)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module, or with a self loop (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
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
            if len(comp) > 1 or v in graph.get(v, ()):
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> product modules it imports (a package's own submodules excluded: importing a
    submodule runs its package first, which is not a circle of the code)."""
    modules = product_modules()
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets = {t for t, _ in imports_of(path, name, modules) if t in modules and t != name}
        graph[name] = {t for t in targets if not name.startswith(t + ".")}
    return graph


def test_no_import_circle() -> None:
    cycles = _cycles(import_graph())
    assert not cycles, "import circles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_finder_finds_a_circle() -> None:
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


@pytest.mark.parametrize("call", ["importlib.import_module", "importlib.util.find_spec", "__import__("])
def test_no_module_is_reached_through_importlib(call: str) -> None:
    wrong = [
        str(path.relative_to(REPO))
        for name, path in product_modules().items()
        if call in path.read_text(encoding="utf-8") and not name.startswith("db.migrations")
    ]
    assert not wrong, f"{call} in: {', '.join(wrong)}"
