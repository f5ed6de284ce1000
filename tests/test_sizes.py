"""The house limits of app/ (issue 12, STYLE.md): modules and functions a reader can hold.

- A module of ``app/`` has at most :data:`MODULE_LINES` lines, unless it is one
  cohesive thing and its docstring says why, with the words "One module on
  purpose" (as ``app/models.py`` does).
- A function or method of ``app/`` has at most :data:`FUNCTION_LINES` lines
  (from its ``def`` or first decorator to its last line, docstring included).

Read from the source (nothing is imported); each failure names the file and
line, so the next split starts where the code grew.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODULE_LINES = 500
FUNCTION_LINES = 80
ON_PURPOSE = "One module on purpose"


def _modules() -> list[Path]:
    return sorted((ROOT / "app").rglob("*.py"))


def test_app_modules_stay_under_the_limit_or_say_why() -> None:
    long = []
    for path in _modules():
        text = path.read_text(encoding="utf-8")
        n = len(text.splitlines())
        doc = ast.get_docstring(ast.parse(text)) or ""
        if n > MODULE_LINES and ON_PURPOSE not in doc:
            long.append(f"{path.relative_to(ROOT)}: {n} lines")
    assert not long, (
        f"app/ modules over {MODULE_LINES} lines whose docstring does not say why"
        f" ({ON_PURPOSE!r}); split them along a seam:\n" + "\n".join(long)
    )


def test_app_functions_stay_under_the_limit() -> None:
    long = []
    for path in _modules():
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
                n = (node.end_lineno or node.lineno) - first + 1
                if n > FUNCTION_LINES:
                    long.append(f"{path.relative_to(ROOT)}:{first} {node.name}: {n} lines")
    assert not long, f"app/ functions over {FUNCTION_LINES} lines:\n" + "\n".join(long)


def test_the_limits_are_checked_on_something() -> None:
    # The walk above must see the real tree (a wrong ROOT would pass vacuously).
    assert len(_modules()) > 50
    assert (ROOT / "app" / "models.py").is_file()
