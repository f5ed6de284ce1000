"""The layers of the code base, read from the source (no import is executed).

- ``core/`` is a library: it imports nothing from ``app/`` and none of the
  web or database libraries (STYLE.md).
- ``app/`` has no import cycle, counting imports inside functions and under
  ``TYPE_CHECKING`` too: dependencies point one way.
- ``app/``'s entry points (``app.api``, ``app.web``, ``app.cli``, ``app.main``)
  sit on top: nothing below them imports them.

Each failure names the file, line and module of the offending import.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Libraries of the web and database layers that core/ must never import.
WEB_AND_DB_LIBRARIES = (
    "alembic",
    "fastapi",
    "fhir",
    "jinja2",
    "psycopg",
    "pydantic",
    "pydantic_settings",
    "python_multipart",
    "sqlalchemy",
    "starlette",
    "uvicorn",
    "weasyprint",
)
# app's entry points: only they (and each other) may import them.
ENTRY_POINTS = ("app.api", "app.web", "app.cli", "app.main")


@dataclass(frozen=True)
class Import:
    source: str  # importing module, e.g. "app.audit"
    target: str  # imported module, e.g. "app.auth"
    where: str  # "app/audit.py:25"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules(package: str) -> dict[str, Path]:
    return {_module_name(p): p for p in sorted((ROOT / package).rglob("*.py"))}


def _imports(name: str, path: Path, known: set[str]) -> list[Import]:
    """Every import statement of the module, resolved to the modules it names."""
    is_package = path.name == "__init__.py"
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        where = f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 0)}"
        if isinstance(node, ast.Import):
            out.extend(Import(name, alias.name, where) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".")
                anchor = anchor if is_package else anchor[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                out.append(Import(name, sub if sub in known else base, where))
    return out


def _graph(package: str) -> tuple[dict[str, Path], list[Import]]:
    modules = _modules(package)
    known = set(modules)
    edges = [imp for name, path in modules.items() for imp in _imports(name, path, known)]
    return modules, edges


def test_core_imports_neither_app_nor_web_or_database_libraries() -> None:
    _, edges = _graph("core")
    bad = [
        f"{imp.where} imports {imp.target}"
        for imp in edges
        if imp.target.split(".")[0] in ("app", *WEB_AND_DB_LIBRARIES)
    ]
    assert not bad, "core/ must stay a library:\n" + "\n".join(bad)


def _cycle_through(start: str, graph: dict[str, list[Import]]) -> list[Import] | None:
    """The shortest chain of imports from ``start`` back to itself, if any."""
    frontier: list[list[Import]] = [[imp] for imp in graph.get(start, [])]
    seen = {start}
    while frontier:
        chain = frontier.pop(0)
        last = chain[-1].target
        if last == start:
            return chain
        if last in seen:
            continue
        seen.add(last)
        frontier.extend([*chain, imp] for imp in graph.get(last, []))
    return None


def test_app_has_no_import_cycle() -> None:
    modules, edges = _graph("app")
    graph: dict[str, list[Import]] = {}
    for imp in edges:
        if imp.target in modules and imp.target != imp.source:
            graph.setdefault(imp.source, []).append(imp)
    cycles = []
    reported: set[frozenset[str]] = set()
    for name in sorted(modules):
        chain = _cycle_through(name, graph)
        if chain is None:
            continue
        members = frozenset(imp.source for imp in chain)
        if members in reported:
            continue
        reported.add(members)
        cycles.append(" -> ".join(f"{imp.source} ({imp.where})" for imp in chain) + f" -> {name}")
    assert not cycles, "import cycles in app/:\n" + "\n".join(cycles)


def _is_entry_point(module: str) -> bool:
    return any(module == e or module.startswith(e + ".") for e in ENTRY_POINTS)


def test_nothing_in_app_imports_its_entry_points_from_below() -> None:
    _, edges = _graph("app")
    bad = [
        f"{imp.where} ({imp.source}) imports {imp.target}"
        for imp in edges
        if _is_entry_point(imp.target) and not _is_entry_point(imp.source)
    ]
    assert not bad, "app's lower modules must not import the API, pages or CLI:\n" + "\n".join(bad)
